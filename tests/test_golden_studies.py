"""Same outputs, byte for byte, before and after the design studies were split into
one module per concern (fabkit/vary.py, cluster.py, launches.py, robustness.py,
tables.py; explore.py and design.py on top) and ``fabkit sweep``'s result became a
typed report: the ``--json`` output and the per-launch tables of ``explore``,
``robustness`` and ``sweep``, and the JSON and the written spec of ``design``, for a
cheap variant of the paper's apparatus (tests/conftest.py's SMALL_STUDY).

The reference files in tests/fixtures/golden/ (``study_*``) were written ONCE by the
code before the split, with ``python tests/test_golden_studies.py --write``: the
contract is "unchanged output", so the comparison is against what the code produced
before the change, not against its own current output. Removed before comparing:
every wall time (``seconds``, ``timings_s``), which differs run to run; the run's
folder is written as TMP. Floats are compared to 1e-9 relative (tests/golden.py's
``numbers_close``): other builds of numpy, scipy and LLVM change their last digits.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
import sys
from pathlib import Path

import pytest
import yaml
from golden import numbers_close, strip_volatile

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "fixtures" / "golden"
sys.path.insert(0, str(HERE))



def _small(drop=()) -> dict:
    from conftest import SMALL_STUDY, mutated

    return mutated(SMALL_STUDY, drop=drop)


#: name -> (spec, command and options); every run adds --json and --no-progress
CASES = {
    "explore": (_small, ["explore", "--vary", "surface.params.eps=0.24:0.26:2", "--v-in", "30", "80", "16",
                         "--out", "rows.csv"]),
    "explore_model": (_small, ["explore", "--vary", "simulation.model=full,simplified", "--v-in", "40", "60", "5"]),
    "robustness": (_small, ["robustness", "--v-in", "40", "44", "5", "--sigma-y", "0.05", "--sigma-vy", "0.3",
                            "--samples", "12", "--out", "rows.csv"]),
    "sweep": (_small, ["sweep", "--v-in", "30", "80", "16"]),
    "design": (lambda: _small(drop=("stock", "tool", "machining")),
               ["design", "--vary", "surface.params.eps=0.22:0.28", "--budget", "5", "--top", "1",
                "--min-width", "0.2", "--seed", "3", "-o", "w.yaml"]),
}



def produce(name: str, folder: Path) -> dict[str, str]:
    """The outputs of case ``name`` run in ``folder``: file name -> text."""
    from fabkit.cli import main

    make, argv = CASES[name]
    raw = copy.deepcopy(make())
    old = os.getcwd()
    os.chdir(folder)
    try:
        Path("small.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([argv[0], "small.yaml", *argv[1:], "--json", "--no-progress"])
        text = json.dumps({"exit": code, "stderr": err.getvalue().strip().splitlines(),
                           "payload": strip_volatile(json.loads(out.getvalue()))}, indent=1, sort_keys=False) + "\n"
        files = {f"study_{name}.json": text.replace(str(folder), "TMP")}
        for extra in ("rows.csv", "w.yaml"):
            if Path(extra).exists():
                files[f"study_{name}.{extra}"] = Path(extra).read_text().replace(str(folder), "TMP")
    finally:
        os.chdir(old)
    return files


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CASES))
def test_study_outputs_unchanged(name, tmp_path):
    got = produce(name, tmp_path)
    want = sorted(p.name for p in GOLDEN.glob(f"study_{name}.*"))
    assert sorted(got) == want
    for fname, text in got.items():
        diff = numbers_close(text, (GOLDEN / fname).read_text())
        assert diff is None, f"{fname} differs from the output of the code before the split: {diff}"


if __name__ == "__main__":      # python tests/test_golden_studies.py --write [NAME...]
    import tempfile

    if "--write" not in sys.argv[1:]:
        raise SystemExit("usage: python tests/test_golden_studies.py --write [NAME...]")
    names = [a for a in sys.argv[1:] if a != "--write"] or sorted(CASES)
    for n in names:
        with tempfile.TemporaryDirectory() as d:
            for fname, text in produce(n, Path(d)).items():
                (GOLDEN / fname).write_text(text)
                print("wrote", GOLDEN / fname)
