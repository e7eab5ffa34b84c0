"""Machine profiles: grbl $$ dumps and LinuxCNC INIs -> profile, the shipped
grbl 1.1 defaults, the spec's machine section, and bad files (exit 2)."""

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
