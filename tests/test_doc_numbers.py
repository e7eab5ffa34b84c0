"""The numbers the README and docs/ quote from a command are the command's own.

docs/regenerate.py runs every documented command and keeps its summary in
docs/outputs/<job>.txt. A passage that quotes one is marked in the Markdown source:

    <!-- numbers: check, ball-compare -->
    ... | `ball` | 59.2241 | 2.6063 | 34.346..50.886; ...
    <!-- /numbers -->

and every decimal number inside it (59.2241, 2.6063, 34.346, ...) must be one that those
outputs print, to the digits quoted (59.2241 matches a printed 59.224142). A time or a load inside a
marked passage depends on the machine, not on the command, and is named in the mark:

    <!-- numbers: gcode-surface; timings: 65.4 54.7 0.7 4.7 0.4 -->

those numbers (each must occur in the passage) are not checked. Every whole number inside a
marked passage (a count of lines, passes, windows, launches, triangles; "34 273" is one number)
must be one the outputs print as a whole number ("1e-4" is compared by value). A number the
passage gives that the command does not print, a spec's input (the 25 mm ball, `surface.top: 2`)
or a year, is named in the mark after the timings:

    <!-- numbers: ball-compare, check; inputs: 25 -->

and, like a timing, must occur in the passage and is not checked. So a number that
drifts from what the command prints fails here, without re-running the heavy commands:
regenerating an output (``python docs/regenerate.py JOB``) and not the docs, or the docs and
not the output, is caught. One cheap job is re-run to show the outputs are the commands'.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "outputs"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"<!-- numbers: ([\w\-., ]+?)\s*(?:;\s*timings:([-+\d.eE ]+?))?"
                   r"\s*(?:;\s*inputs:([-+\d.eE ]+?))?\s*-->"
                   r"(.*?)<!-- /numbers -->", re.S)
# a decimal number (not part of a word, a version like 3.11.7 or a file name like 0.ngc);
# "a..b" is a range of two numbers
_DECIMAL = re.compile(r"(?<![\w.])[-+]?\d+\.\d+(?:[eE][-+]?\d+)?(?![\w.]*\d)")


# a decimal with its thousands set apart by spaces, as tables write them: "12 726.1"
_GROUPED = re.compile(r"(?<![\d.])\d{1,3}(?: \d{3})+(?=\.\d)")


def decimals(text: str) -> list[str]:
    text = _GROUPED.sub(lambda m: m.group(0).replace(" ", ""), text)
    return _DECIMAL.findall(text.replace("..", " .. "))


# a whole number with its thousands set apart ("34 273 lines"); a power of ten written
# "1e-4" (a whole mantissa) is a number of its own, compared by value
_GROUPED_INT = re.compile(r"(?<![\d.])\d{1,3}(?: \d{3})+(?![\d.])")
_SCIENTIFIC = re.compile(r"(?<![\w.])\d+[eE][-+]?\d+(?![\w.]*\d)")
_WHOLE = re.compile(r"(?<![\w.])\d+(?![\w.]*\d)(?!\.\w)")


def whole_numbers(text: str) -> list[str]:
    """The whole numbers of a text (a count, a year, "1e-4"): not the parts of a decimal, a
    version (3.11.7), a name (0.ngc, n2, T_5) or a range's ends read as one ("3..17" is 3 and 17;
    "10-12" is 10 and 12, the dash read as "to")."""
    text = _GROUPED.sub(lambda m: m.group(0).replace(" ", ""), text)
    text = _GROUPED_INT.sub(lambda m: m.group(0).replace(" ", ""), text).replace("..", " .. ")
    text = _DECIMAL.sub(" ", text)
    found = _SCIENTIFIC.findall(text)
    return found + _WHOLE.findall(_SCIENTIFIC.sub(" ", text))
#: passages that must stay marked: (doc, an output it quotes)
REQUIRED = [("README.md", "check"), ("README.md", "ball-compare"), ("docs/ball.md", "ball-compare"),
            ("docs/ball.md", "check"), ("docs/sweep_check.md", "sweep"), ("README.md", "check-as-built"),
            ("README.md", "design"), ("README.md", "stl"), ("README.md", "gcode-surface"), ("README.md", "phi4"),
            ("docs/gcode.md", "gcode-surface"), ("docs/gcode.md", "gcode-bowl"), ("docs/stl.md", "stl"),
            ("docs/numerics.md", "precision"), ("docs/phi4.md", "compare"), ("docs/design.md", "design"),
            ("docs/simulator.md", "calibrate"), ("docs/explore.md", "explore"),
            ("docs/machine.md", "time-defaults"), ("docs/machine.md", "time-router"),
            ("docs/machine.md", "gcode-router"),
            ("docs/sweep_check.md", "check-clipped-top2"), ("docs/phi4.md", "phi4"), ("docs/paper.md", "sweep"),
            ("README.md", "calibrate-range"), ("README.md", "time-defaults"), ("README.md", "gcode-router"),
            ("docs/toolpath.md", "gcode-surface"), ("docs/machine.md", "time-fast"),
            ("docs/machine.md", "time-unequal"), ("docs/sweep_check.md", "sweep-undamped-full"),
            ("docs/sweep_check.md", "sweep-undamped-simplified"), ("docs/paper.md", "sweep-full"),
            ("docs/paper.md", "sweep-full-in"), ("docs/paper.md", "sweep-ball-in"),
            ("docs/paper.md", "sweep-ball-in-2p5cm")]


def _regenerate():
    spec = importlib.util.spec_from_file_location("regenerate", ROOT / "docs" / "regenerate.py")
    if "regenerate" not in sys.modules:
        mod = importlib.util.module_from_spec(spec)
        sys.modules["regenerate"] = mod          # its dataclasses look their module up
        spec.loader.exec_module(mod)
    return sys.modules["regenerate"]


def _printed(job: str) -> list[Decimal]:
    text = (OUT / f"{job}.txt").read_text()
    text = text[:text.rindex("\n[exit ")]             # not the wall time and load of the run
    # a sign only where a number starts ("0.22-1.09 mm" is a range, not 0.22 and -1.09)
    return [Decimal(m) for m in re.findall(r"(?:(?<![\w.])[-+])?(?:\d+\.\d+(?:[eE][-+]?\d+)?|\d+)", text)]


def _printed_whole(job: str) -> set[Decimal]:
    text = (OUT / f"{job}.txt").read_text()
    return {Decimal(w) for w in whole_numbers(text[:text.rindex("\n[exit ")])}


def _blocks():
    for doc in DOCS:
        for m in BLOCK.finditer(doc.read_text()):
            yield (doc.relative_to(ROOT).as_posix(), [j.strip() for j in m.group(1).split(",")],
                   m.group(4), (m.group(2) or "").split() + (m.group(3) or "").split())


def checked_decimals(text: str, timings: list[str]) -> tuple[list[str], list[str]]:
    """The passage's decimals less one occurrence of each named timing, and the timings
    the passage does not hold."""
    (quoted, _), missing = checked_numbers(text, timings)
    return quoted, missing


def checked_numbers(text: str, named: list[str]) -> tuple[tuple[list[str], list[str]], list[str]]:
    """The passage's (decimals, whole numbers), less one occurrence of each number the mark
    names (a timing, a spec's input, a year), and the named numbers the passage does not hold."""
    quoted, whole, missing = decimals(text), whole_numbers(text), []
    for t in named:
        if t in quoted:
            quoted.remove(t)
        elif t in whole:
            whole.remove(t)
        else:
            missing.append(t)
    return (quoted, whole), missing


def _matches(quoted: str, printed: list[Decimal]) -> bool:
    q = Decimal(quoted)
    half = Decimal(1).scaleb(q.as_tuple().exponent) / 2     # half a unit of the last digit quoted
    # a sign the prose gives in words ("2.0-2.7 % slower" for a printed -1.959 .. -2.721) is
    # read from the words: the magnitude must match
    return any(abs(abs(p) - abs(q)) <= half for p in printed)


def test_every_quoted_number_is_printed_by_its_command():
    blocks = list(_blocks())
    have = {(doc, j) for doc, jobs, _, _ in blocks for j in jobs}
    assert not [r for r in REQUIRED if r not in have], "a quoting passage lost its marks"
    jobs = _regenerate().JOBS_BY_NAME
    bad, checked, whole_checked = [], 0, 0
    for doc, names, text, timings in blocks:
        assert all(n in jobs for n in names), f"{doc}: unknown output {names} (docs/regenerate.py --list)"
        printed = [p for n in names for p in _printed(n)]
        printed_whole = set().union(*(_printed_whole(n) for n in names))
        (quoted, whole), missing = checked_numbers(text, timings)
        bad += [f"{doc}: {t} named in the mark is not in the passage" for t in missing]
        for q in quoted:
            checked += 1
            if not _matches(q, printed):
                bad.append(f"{doc}: {q} is not printed by {', '.join(names)}")
        for w in whole:
            whole_checked += 1
            # a count must be printed as one; a power of ten as any number of its value
            if Decimal(w) not in printed_whole and not ("e" in w.lower() and Decimal(w) in printed):
                bad.append(f"{doc}: whole number {w} is not printed by {', '.join(names)}")
    assert checked >= 60 and whole_checked >= 100 and not bad, "\n".join(bad)


def test_each_job_names_the_docs_that_quote_it():
    """An output file's last line says which docs quote it: the marks are that list."""
    jobs = _regenerate().JOBS_BY_NAME
    missing = [f"{doc} quotes {n}" for doc, names, _, _ in _blocks() for n in names
               if n in jobs and doc not in [d.strip() for d in jobs[n].doc.split(",")]]
    assert not missing, "docs/regenerate.py does not list: " + "; ".join(missing)


def test_the_check_rejects_a_drifted_number():
    # the comparison itself: 0.7232 is printed (check), 0.745 is not; 59.2241 matches a
    # printed 59.224142, 59.2242 does not
    printed = _printed("check")
    assert _matches("0.7232", printed) and not _matches("0.745", printed)
    assert _matches("2.0", [Decimal("-1.959")]) and _matches("-2.7", [Decimal("2.721")])
    assert not _matches("2.8", [Decimal("-2.721")])
    assert _matches("59.2241", printed) and not _matches("59.2242", printed)
    assert decimals("v 34.346..50.886; python 3.11.7, file 0.ngc, -1.5 cm, < 1.2e-07") == \
        ["34.346", "50.886", "-1.5", "1.2e-07"]
    assert decimals("| 12 726.1 | 2 540.9 | 34 273 lines, 0.2 100.5 |") == ["12726.1", "2540.9", "0.2", "100.5"]
    assert Decimal("1.09") in _printed("gcode-surface") and Decimal("-1.09") not in _printed("gcode-surface")
    assert _matches("1.2e-07", [Decimal("1.2e-07")]) and not _matches("1.3e-07", [Decimal("1.2e-07")])


def test_a_named_timing_is_skipped_once_and_must_be_there():
    m = BLOCK.search("<!-- numbers: gcode-surface; timings: 65.4 0.4 -->\n"
                     "gouge 0.0051 mm; 65.4 s (sheet 0.4), 0.4\n<!-- /numbers -->")
    assert m.group(1) == "gcode-surface" and m.group(2).split() == ["65.4", "0.4"]
    assert checked_decimals(m.group(4), m.group(2).split()) == (["0.0051", "0.4"], [])
    assert checked_decimals("65.4 s", ["66.0"]) == (["65.4"], ["66.0"])
    plain = BLOCK.search("<!-- numbers: check, sweep -->x 1.5<!-- /numbers -->")
    assert plain.group(1) == "check, sweep" and plain.group(2) is None and plain.group(3) is None


def test_whole_numbers_are_read_apart_from_decimals_versions_and_names():
    assert whole_numbers("34 273 lines, 251 passes, 0.22-1.09 mm, python 3.11.7, 0.ngc, T_5, n2") == \
        ["34273", "251"]
    assert whole_numbers("n = 3..17: none for n = 10-12, 14-16; to 1e-4 relative, 12 726.1 s") == \
        ["1e-4", "3", "17", "10", "12", "14", "16"]
    m = BLOCK.search("<!-- numbers: check; timings: 264; inputs: 25 2026 -->\n"
                     "the 25 mm ball, 9 windows, 264 s in 2026, 25 launches\n<!-- /numbers -->")
    assert m.group(2).split() == ["264"] and m.group(3).split() == ["25", "2026"]
    assert checked_numbers(m.group(4), ["264", "25", "2026", "7"]) == (([], ["9", "25"]), ["7"])
    # a drifted count fails: check prints 9 two-bounce windows, not 10
    assert Decimal(9) in _printed_whole("check") and Decimal(10) not in _printed_whole("check")
    assert Decimal("1e-4") in {Decimal("0.0001")}


def test_regenerating_a_small_output_reproduces_its_file():
    """The cheapest job (calibrate: two heights, about 1 s of CPU) run again gives its file,
    but for the run's own time."""
    reg = _regenerate()
    job = reg.JOBS_BY_NAME["calibrate"]
    proc = subprocess.run(reg.command(job), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    want = (OUT / "calibrate.txt").read_text()
    want = want[:want.rindex("[exit ")]

    def timeless(t):
        return re.sub(r"\d+(\.\d+)? s$", "N s", t, flags=re.M)

    assert timeless(reg.body(job, proc.stdout)) == timeless(want)


def test_the_variant_specs_differ_from_the_shipped_one_only_where_the_docs_say():
    """docs/sweep_check.md's undamped table and docs/machine.md's profiles come from specs and
    profiles that are not shipped: each differs from the shipped one only in the keys named."""
    import yaml

    shipped = yaml.safe_load((ROOT / "specs" / "surface.yaml").read_text())
    for model in ("full", "simplified"):
        variant = yaml.safe_load((ROOT / "tests" / "fixtures" / "sweep" / f"undamped_{model}.yaml").read_text())
        assert variant["simulation"] == {**shipped["simulation"], "model": model, "damping": 0}
        assert {k: v for k, v in variant.items() if k not in ("name", "simulation")} == \
            {k: v for k, v in shipped.items() if k not in ("name", "simulation")}
    # docs/paper.md's inch rows: units only, and the ball put back to 2.5 cm in one
    point = yaml.safe_load((ROOT / "tests" / "fixtures" / "paper_full.yaml").read_text())
    for name, source, ball in (("paper_full_in", point, None), ("paper_ball_in", shipped, None),
                               ("paper_ball_in_2p5cm", shipped, 0.98425)):   # 2.5 cm to 5 digits
        variant = yaml.safe_load((ROOT / "tests" / "fixtures" / "sweep" / f"{name}.yaml").read_text())
        want = {**source, "name": name, "units": "in"}
        if ball is not None:
            assert variant["ball"]["diameter"] == ball == pytest.approx(2.5 / 2.54, abs=5e-6)
            want["ball"] = {**source["ball"], "diameter": variant["ball"]["diameter"]}
        assert variant == want, name
    # the grbl $$ dumps are benchmarks/time_reference.py's profiles, setting for setting
    spec = importlib.util.spec_from_file_location("time_reference", ROOT / "benchmarks" / "time_reference.py")
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    for name in ("router", "unequal"):
        assert (ROOT / "tests" / "fixtures" / "machine" / f"{name}.grbl.txt").read_text() == ref.PROFILES[name]


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
