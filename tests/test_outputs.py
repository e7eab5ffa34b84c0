"""Output files: permission bits, paths refused before any work, long names,
figure formats by extension, and what a program and its setup sheet tell a shop."""

from __future__ import annotations

import json
import os
import stat

import pytest

from fabkit.io import write_atomic

from conftest import SPECS, mutated, write_spec
from test_gcode_cli import plain_planner, small_raw  # noqa: F401 (a fixture)


@pytest.fixture
def umask():
    """Set the process umask for the test; restored after."""
    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_new_files_follow_the_umask_and_replaced_files_keep_their_mode(tmp_path, umask, mask):
    """The bits are read back from the file system, whoever runs the test (root included)."""
    umask(mask)
    new = write_atomic(tmp_path / "new.ngc", "G0 X0\n")
    assert mode(new) == 0o666 & ~mask
    for kept in (0o644, 0o640, 0o604):
        old = tmp_path / f"old{kept:o}.ngc"
        old.write_text("old\n")
        os.chmod(old, kept)
        write_atomic(old, "new\n")
        assert old.read_text() == "new\n" and mode(old) == kept


def test_a_valid_name_of_249_characters_is_written(tmp_path):
    name = "p" * 245 + ".ngc"
    assert len(name) == 249
    out = write_atomic(tmp_path / name, "M2\n")
    assert out.read_text() == "M2\n"
    assert [p.name for p in tmp_path.iterdir()] == [name]   # no temporary left


@pytest.fixture
def no_planning(monkeypatch):
    """Fail the test if the command starts its real work (planning, launching)."""
    import fabkit.physics.sweep as sweep
    import fabkit.toolpath.finish.raster as raster

    def boom(*a, **k):
        raise AssertionError("the work started before the output path was checked")

    monkeypatch.setattr(raster, "plan_toolpath", boom)
    monkeypatch.setattr(sweep, "sweep", boom)


def test_output_that_is_the_input_is_refused(cli, tmp_path, no_planning):
    spec = write_spec(tmp_path, small_raw())
    before = spec.read_bytes()
    (tmp_path / "link.yaml").symlink_to(spec)
    for argv in (("gcode", spec, "-o", spec), ("gcode", spec, "-o", "link.yaml"),
                 ("gcode", spec, "-o", tmp_path / "." / "spec.yaml"), ("stl", spec, "-o", "spec.yaml")):
        code, out, err = cli(*argv)
        assert code == 2 and "is the input" in err and "\n" not in err.strip(), err
        assert spec.read_bytes() == before and not (tmp_path / "toolpaths").exists()
    paper = write_spec(tmp_path, mutated({}), "paper.yaml")
    code, out, err = cli("sweep", paper, "--v-in", "30", "40", "3", "--plot", paper)
    assert code == 2 and "--plot" in err and "is the input" in err


def test_output_that_is_not_a_regular_file_is_refused(cli, tmp_path, no_planning):
    spec = write_spec(tmp_path, small_raw())
    fifo = tmp_path / "pipe.ngc"
    os.mkfifo(fifo)
    code, out, err = cli("gcode", spec, "-o", fifo)
    assert code == 2 and "not a regular file" in err
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    # a setup-sheet path in the way counts too
    (tmp_path / "prog.setup.json").mkdir()
    code, out, err = cli("gcode", spec, "-o", "prog.ngc")
    assert code == 2 and "folder" in err and not (tmp_path / "prog.ngc").exists()


def test_output_folder_that_cannot_be_created_is_refused_first(cli, tmp_path, no_planning):
    spec = write_spec(tmp_path, small_raw())
    (tmp_path / "afile").write_text("x")
    code, out, err = cli("gcode", spec, "-o", "afile/sub/p.ngc")
    assert code == 2 and "not a folder" in err and "afile" in err
    code, out, err = cli("gcode", spec, "-o", "q" * 300 + ".ngc")
    assert code == 2 and "too long" in err and "file name" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "spec.yaml"]


def test_plot_format_follows_the_extension(cli, tmp_path):
    from fabkit.commands._common import plot_format
    from fabkit.plots import sweep_figure

    paper = write_spec(tmp_path, mutated({}), "paper.yaml")
    code, out, err = cli("simulate", paper, "--v-in", "40", "--plot", "t.jpg")
    assert code == 0, err
    assert (tmp_path / "t.jpg").read_bytes().startswith(b"\xff\xd8\xff")      # JPEG, not PNG bytes
    res = {"v_in": [1.0, 2.0], "v_out": [None, 1.5], "bounces": [0, 1], "outcome": ["captured", "escaped"],
           "v_critical": None}
    magic = {"a.png": b"\x89PNG", "a.PDF": b"%PDF", "a.svg": b"<?xml", "a.tiff": b"II*\x00", "a": b"\x89PNG"}
    for name, head in magic.items():
        assert sweep_figure(res, fmt=plot_format(name)).startswith(head), name
    code, out, err = cli("simulate", paper, "--v-in", "40", "--plot", "t.gif")
    assert code == 2 and "--plot" in err and ".gif" in err and not (tmp_path / "t.gif").exists()


def test_setup_sheet_states_what_the_machine_must_do(cli, tmp_path, plain_planner):
    """Largest feed, plunge, axis speeds, travel and spindle, checked against the
    program text parsed here independently; park and tool call in the program."""
    import re

    spec = write_spec(tmp_path, small_raw(spindle=12000, park=[-5, 7]) | {"tool": {"shape": "ball", "diameter": 6,
                                                                                   "reach": 25, "number": 2}})
    code, out, err = cli("gcode", spec, "-o", "p.ngc", "--json")
    assert code == 0, err
    sheet = json.loads((tmp_path / "p.setup.json").read_text())
    need = sheet["machine_needs"]
    text = (tmp_path / "p.ngc").read_text()
    code_lines = [ln for ln in text.splitlines() if not ln.startswith("(")]
    assert code_lines[0].split()[-1] == "G54" and code_lines[2] == "T2 M6 G43 H2"
    assert code_lines[-3] == "X-5 Y7" and code_lines[-2:] == ["M5", "M2"]
    feeds = [float(f) for f in re.findall(r"F([0-9.]+)", text)]
    assert need["feed_max"] == max(feeds) == 1200 and need["plunge_max"] == 300
    assert need["spindle_rpm"] == 12000
    # travel: every X, Y, Z word of the program (modal), the park included
    pos = {"X": [], "Y": [], "Z": []}
    for ln in code_lines:
        for letter, v in re.findall(r"([XYZ])(-?[0-9.]+)", ln):
            pos[letter].append(float(v))
    for ax in "XYZ":
        assert need["travel"][ax.lower()] == pytest.approx(max(pos[ax]) - min(pos[ax]), abs=1e-9)
    assert need["extent"]["x"][0] == -5 and need["travel"]["z"] > 3
    assert 0 < need["axis_rate_max"]["z"] <= 1200 and need["axis_rate_max"]["x"] == pytest.approx(1200, rel=1e-6)
    assert sheet["grbl_defaults"] == {"max_rate_mm_min": 500.0, "spindle_max_rpm": 1000.0, "max_travel_mm": 200.0}
    md = (tmp_path / "p.setup.md").read_text()
    assert "What the machine must do" in md and "Largest feed F 1200 mm/min (above grbl's default)" in md
    assert "Spindle 12000 rpm (above grbl's default)" in md and "T2" in md


def test_shipped_examples_pass_their_own_check(cli):
    with pytest.MonkeyPatch.context():
        code, out, err = cli("check", SPECS / "bowl.yaml", "--no-progress")
    assert code == 0, err + out


def test_every_command_checks_its_outputs_before_any_work(cli, tmp_path, monkeypatch):
    """phi4 and compare (no planning, no launch of the spec's simulator) and report refuse a
    figure or page path under a file, a device, or the wrong format before their work starts."""
    import fabkit.physics.check as check
    import fabkit.waves.compare as cmp
    import fabkit.waves.phi4 as phi4

    def boom(*a, **k):
        raise AssertionError("the work started before the output path was checked")

    for mod, name in ((phi4, "collide"), (cmp, "pde_panel"), (check, "check")):
        monkeypatch.setattr(mod, name, boom)
    paper = write_spec(tmp_path, mutated({}), "paper.yaml")
    (tmp_path / "afile").write_text("x")
    for argv, needle in ((("phi4", "--v-in", "0.2", "--plot", "afile/x.png"), "not a folder"),
                         (("phi4", "--v-in", "0.2", "0.3", "4", "--plot", os.devnull), "not a regular file"),
                         (("compare", paper, "--plot", os.devnull), "not a regular file"),
                         (("compare", paper, "--plot", paper), "is the input"),
                         (("report", paper, "-o", "afile/r.html"), "not a folder"),
                         (("report", paper, "-o", "r.pdf"), "HTML page")):
        code, out, err = cli(*argv)
        assert code == 2 and needle in err and "\n" not in err.strip() and out == "", (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "paper.yaml"]
