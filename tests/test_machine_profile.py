"""Machine profiles: grbl $$ dumps and LinuxCNC INIs -> profile, the shipped
grbl 1.1 defaults, the spec's machine section, and bad files (exit 2)."""

from pathlib import Path

import pytest

from fabkit.cli import main
from fabkit.errors import SpecError
from fabkit.machine.profile import grbl_defaults, import_settings, load_machine, parse_grbl, parse_linuxcnc_ini

DUMP = """$0=10
$11=0.020
$12=0.002
$30=24000
$31=1000
$100=800.000
$101=800.000
$102=400.000
$110=5000.000
$111=4000.000
$112=1000.000
$120=500.000
$121=400.000
$122=100.000
$130=300.000
$131=180.000
$132=80.000
ok
"""

INI = """[EMC]
MACHINE = test mill
[TRAJ]
LINEAR_UNITS = inch   # comment
MAX_LINEAR_VELOCITY = 2.0
MAX_LINEAR_ACCELERATION = 10
[EMCIO]
TOOL_TABLE = tool.tbl
[SPINDLE_0]
MAX_FORWARD_VELOCITY = 10000
MIN_FORWARD_VELOCITY = 500
[AXIS_X]
MIN_LIMIT = -1.0
MAX_LIMIT = 9.0
MAX_VELOCITY = 1.5
MAX_ACCELERATION = 20.0
[AXIS_Y]
MIN_LIMIT = 0
MAX_LIMIT = 6
MAX_VELOCITY = 1.5
MAX_ACCELERATION = 20.0
[AXIS_Z]
MIN_LIMIT = -4
MAX_LIMIT = 0.0
MAX_VELOCITY = 0.5
MAX_ACCELERATION = 10.0
"""


def test_grbl_dump():
    m = parse_grbl(DUMP, "dump.txt")
    assert m.controller == "grbl" and not m.tool_changer
    assert m.max_rate == (5000.0, 4000.0, 1000.0)
    assert m.acceleration == (500.0, 400.0, 100.0)       # grbl's $12x are mm/s^2 already
    assert m.travel == (300.0, 180.0, 80.0)
    assert m.steps_per_mm == (800.0, 800.0, 400.0)
    assert m.junction_deviation == 0.02 and m.arc_tolerance == 0.002
    assert m.spindle == (1000.0, 24000.0)


def test_linuxcnc_ini_units_converted():
    m = parse_linuxcnc_ini(INI, "mill.ini")
    assert m.controller == "linuxcnc" and m.tool_changer
    assert m.max_rate == pytest.approx((1.5 * 25.4 * 60, 1.5 * 25.4 * 60, 0.5 * 25.4 * 60))
    assert m.acceleration == pytest.approx((20 * 25.4, 20 * 25.4, 10 * 25.4))
    assert m.travel == pytest.approx((10 * 25.4, 6 * 25.4, 4 * 25.4))
    assert m.max_velocity == pytest.approx(2.0 * 25.4 * 60) and m.max_acceleration == pytest.approx(254.0)
    assert m.spindle == (500.0, 10000.0)


def test_shipped_defaults_are_grbl_1_1h():
    # grbl 1.1h grbl/defaults.h, DEFAULTS_GENERIC
    m = grbl_defaults()
    assert m.max_rate == (500.0,) * 3 and m.acceleration == (10.0,) * 3 and m.travel == (200.0,) * 3
    assert m.steps_per_mm == (250.0,) * 3 and m.junction_deviation == 0.01 and m.arc_tolerance == 0.002
    assert m.spindle == (0.0, 1000.0) and m.controller == "grbl"


def test_import_roundtrip(tmp_path, capsys):
    src = tmp_path / "dump.txt"
    src.write_text(DUMP)
    out = tmp_path / "m.yaml"
    assert main(["machine", "import", str(src), "-o", str(out)]) == 0
    assert load_machine(out).to_dict() == parse_grbl(DUMP, str(src)).to_dict()


def test_spec_machine_section(tmp_path):
    from fabkit.spec import load_spec

    p = tmp_path / "s.yaml"
    p.write_text("machine:\n  controller: linuxcnc\n  max_rate: [3000, 3000, 1000]\n  tool_changer: true\n")
    s = load_spec(p)
    assert s.machine.max_rate == (3000.0, 3000.0, 1000.0) and s.machine.tool_changer is True
    assert load_machine(p).controller == "linuxcnc"     # a spec with a machine section is a profile file


@pytest.mark.parametrize("text, words", [
    ("hello\n", "not a grbl $$ dump"),
    ("$110=500\n$111=500\n", "missing $11"),
    (DUMP.replace("$121=400.000", "$121=-4"), "$121: must be > 0"),
    (INI.replace("MAX_VELOCITY = 0.5\n", ""), "[AXIS_Z]MAX_VELOCITY: missing key"),
    (INI.replace("LINEAR_UNITS = inch", "LINEAR_UNITS = furlong"), "LINEAR_UNITS: unknown unit"),
])
def test_bad_settings_exit_2(tmp_path, capsys, text, words):
    src = tmp_path / "bad.txt"
    src.write_text(text)
    out = tmp_path / "out.yaml"
    assert main(["machine", "import", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and str(src) in err and "\n" not in err and "Traceback" not in err
    assert not out.exists()


def test_bad_profile_file(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("controller: grbl\nmax_rate: [500, 500]\n")
    with pytest.raises(SpecError, match="max_rate: must have 3 to 3 entries"):
        load_machine(p)
    p.write_text("controller: grbl\ntool_changer: maybe\n")
    with pytest.raises(SpecError, match="tool_changer: must be true"):
        load_machine(p)


@pytest.mark.parametrize("text, words", [
    (DUMP + "$110=4000\n", "$110: set twice: line 9 and line 19"),
    (INI + "[AXIS_X]\nMAX_VELOCITY = 3\n", "[AXIS_X]: the section appears twice: line 12 and line 27"),
    (INI.replace("MAX_VELOCITY = 0.5\n", "MAX_VELOCITY = 0.5\nMAX_VELOCITY = 9\n"),
     "[AXIS_Z]MAX_VELOCITY: set twice: line 25 and line 26"),
    (DUMP.replace("$121=400.000", "$121=0.0000000001"), "$121: 1e-10 mm/s^2 is outside the physical range 0.1 to"),
    (DUMP.replace("$100=800.000", "$100=0.000000001"), "$100: 1e-09 steps/mm is outside the physical range 1 to"),
    (DUMP.replace("$110=5000.000", "$110=0.000001"), "$110: 1e-06 mm/min is outside the physical range 1 to"),
    (INI.replace("MAX_ACCELERATION = 10.0", "MAX_ACCELERATION = 1e-300"),
     "[AXIS_Z]MAX_ACCELERATION: 2.54e-299 mm/s^2 is outside the physical range 0.1 to"),
    (INI.replace("MAX_VELOCITY = 0.5", "MAX_VELOCITY = fast"), "[AXIS_Z]MAX_VELOCITY: line 25: not a number"),
])
def test_hostile_settings_exit_2(tmp_path, capsys, text, words):
    test_bad_settings_exit_2(tmp_path, capsys, text, words)


def test_numbers_read_as_the_controller_reads_them(tmp_path):
    # LinuxCNC reads numbers with sscanf("%lf"): 1_000 is 1 (then refused: 60 in/min... is
    # in range, so it stands, as the controller would run it); a byte-order mark is accepted
    m = parse_linuxcnc_ini("\ufeff" + INI.replace("MAX_VELOCITY = 0.5", "MAX_VELOCITY = 1_000"), "m.ini")
    assert m.max_rate[2] == pytest.approx(1 * 25.4 * 60)
    from fabkit.machine.profile import c_double

    assert [c_double(s) for s in ("2.5 # c", "0x10", "1e3x", ".5", "-7,5", "abc")] == [2.5, 16.0, 1000.0, 0.5,
                                                                                        -7.0, None]
    p = tmp_path / "bom.txt"
    p.write_bytes(b"\xef\xbb\xbf" + DUMP.encode())
    assert load_machine(p).max_rate == (5000.0, 4000.0, 1000.0)


def test_joint_limits_imported():
    # [JOINT_1] slower than [AXIS_Y]: Y runs at the joint's limits
    ini = INI + "[KINS]\nKINEMATICS = trivkins coordinates=XYZ\n[JOINT_1]\nMAX_VELOCITY = 1.0\n" \
                "MAX_ACCELERATION = 5.0\nMIN_LIMIT = 0\nMAX_LIMIT = 6\n"
    m = parse_linuxcnc_ini(ini, "m.ini")
    assert m.max_rate[1] == pytest.approx(1.0 * 25.4 * 60) and m.acceleration[1] == pytest.approx(5 * 25.4)
    assert m.max_rate[0] == pytest.approx(1.5 * 25.4 * 60)


def test_profile_names_and_hostile_paths(tmp_path, capsys):
    from fabkit.machine.profile import resolve_machine

    assert resolve_machine("grbl").max_rate == (500.0,) * 3
    assert main(["machine", "list"]) == 0 and "grbl-router" in capsys.readouterr().out
    with pytest.raises(SpecError, match="not a shipped profile"):
        resolve_machine("grbl-nosuch")
    spec = tmp_path / "s.yaml"
    spec.write_text("surface:\n  height: x\nmachining:\n  feed: 100\n")
    with pytest.raises(SpecError, match="a spec without a machine section"):
        load_machine(spec)
    # a file name with control characters: the profile loads back, the summary is escaped
    src = tmp_path / "we\x1b[31mird\x07.txt"
    src.write_text(DUMP)
    out = tmp_path / "w.yaml"
    assert main(["machine", "import", str(src), "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert "\x1b" not in said and "\\x1b" in said
    assert load_machine(out).to_dict() == {**parse_grbl(DUMP, str(src)).to_dict()}
    # the --machine file is an input: no output may replace it
    before = out.read_bytes()
    bowl = str(Path(__file__).resolve().parents[1] / "specs" / "bowl.yaml")
    for argv in (["gcode", bowl, "-o", str(out)], ["gcode", bowl, "-o", str(tmp_path / "w.ngc")],
                 ["report", bowl, "-o", str(out)]):
        target = tmp_path / "w.setup.json" if argv[-1].endswith(".ngc") else out
        if target != out:
            target.write_bytes(before)           # the setup sheet's own path given as the profile
        assert main(argv + ["--machine", str(target)]) == 2
        assert "is the input" in capsys.readouterr().err and target.read_bytes() == before


def test_dialect_from_the_machine(tmp_path):
    from fabkit.machine.profile import dialect_for_machine
    from fabkit.spec import load_spec

    p = tmp_path / "s.yaml"
    p.write_text("name: s\nmachining:\n  feed: 1000\n")
    spec = load_spec(p)
    grbl, lcnc = parse_grbl(DUMP, "dump.txt"), parse_linuxcnc_ini(INI, "mill.ini")
    assert dialect_for_machine(spec, grbl).machining.dialect == "grbl"
    assert dialect_for_machine(spec, lcnc).machining.dialect == "linuxcnc"
    assert dialect_for_machine(spec, None).machining.dialect == "linuxcnc"          # the default
    p.write_text("name: s\nmachining:\n  feed: 1000\n  dialect: linuxcnc\n")
    with pytest.raises(SpecError, match="machining.dialect is linuxcnc, the machine grbl .dump.txt.* runs grbl"):
        dialect_for_machine(load_spec(p), grbl)
    p.write_text("name: s\nmachining:\n  feed: 1000\n  dialect: grbl\n")
    with pytest.raises(SpecError, match="machining.dialect is grbl, the machine LinuxCNC .mill.ini.* runs linuxcnc"):
        dialect_for_machine(load_spec(p), lcnc)
