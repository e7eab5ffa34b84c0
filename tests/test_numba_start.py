"""numba's short start-up for fabkit's cached code (fabkit/numba_start.py).

Every check runs in a fresh Python process (the start-up is once per process). The
references are numba's own loader (``FABKIT_NUMBA_FULL_START=1``) and numpy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytest.importorskip("numba")

# run a command in process, then say what was imported and how the cached code loaded
DRIVER = textwrap.dedent("""
    import json, sys
    from fabkit.cli import main
    try:
        rc = main(sys.argv[2:])
    except SystemExit as e:
        rc = e.code
    from fabkit import numba_start
    json.dump({"rc": rc, "light": numba_start.light_loads(),
               "arraymath": "numba.np.arraymath" in sys.modules,
               "random": "numba.np.random.generator_methods" in sys.modules},
              open(sys.argv[1], "w"))
""")

SPEC = textwrap.dedent("""
    name: short-start
    units: mm
    surface:
      height: 0.6*x + 0.1*sin(y)
      x: [0, 4]
      y: [0, 6]
      top: 3
    stock:
      thickness: 10
    tool:
      shape: ball
      diameter: 3
      reach: 20
    machining:
      scallop: 0.1
      tolerance: 0.02
      direction: y
""")


def _run(args, env_extra, tmp_path, tag):
    env = dict(os.environ, SOURCE_DATE_EPOCH="1700000000", **env_extra)
    env.pop("FABKIT_NUMBA_FULL_START", None)
    env.update(env_extra)
    out = tmp_path / f"{tag}.json"
    p = subprocess.run([sys.executable, "-c", DRIVER, str(out), *args], env=env, cwd=tmp_path,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(out.read_text())


def test_warm_gcode_takes_the_short_path_and_writes_the_same_program(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC)
    args = lambda o: ["gcode", str(spec), "-o", str(tmp_path / o), "--no-progress"]  # noqa: E731
    first = _run(args("warm.ngc"), {}, tmp_path, "warm")          # compiles what the cache lacks
    assert first["rc"] == 0
    short = _run(args("short.ngc"), {}, tmp_path, "short")
    full = _run(args("full.ngc"), {"FABKIT_NUMBA_FULL_START": "1"}, tmp_path, "full")
    assert short["rc"] == 0 and full["rc"] == 0
    # numba's own loader imports its whole lowering (array math, random, ...); the short path none
    assert full["light"] == 0 and full["arraymath"] and full["random"]
    assert short["light"] >= 3 and not short["arraymath"] and not short["random"]
    # the same compiled code: the same program, byte for byte
    a, b = (tmp_path / "short.ngc").read_bytes(), (tmp_path / "full.ngc").read_bytes()
    assert a == b and a == (tmp_path / "warm.ngc").read_bytes()


KERNEL = textwrap.dedent("""
    import math
    import numpy as np
    from numba import njit

    @njit(cache=True)
    def work(a, b):
        # arrays made in compiled code (numba's runtime), the math library, a reduction
        out = np.empty(a.size)
        for i in range(a.size):
            out[i] = math.exp(-a[i] * a[i]) + math.sqrt(abs(b[i % b.size]))
        return out, np.cumsum(a), out.sum()
""")

LOADER = textwrap.dedent("""
    import json, sys
    import numpy as np
    from fabkit import numba_start
    from fabkit.physics.engine.batch import _import
    from pathlib import Path
    mod = _import(Path(sys.argv[2]))
    rng = np.random.default_rng(7)
    a = rng.normal(size=9)
    b = rng.normal(size=4)
    out, c, t = mod.work(a, b)
    ref = np.exp(-a * a) + np.sqrt(np.abs(b[np.arange(9) % 4]))
    json.dump({"light": numba_start.light_loads(),
               "arraymath": "numba.np.arraymath" in sys.modules,
               "exp": float(np.max(np.abs(out - ref))),
               "cumsum": float(np.max(np.abs(c - np.cumsum(a)))),
               "sum": abs(t - ref.sum())},
              open(sys.argv[1], "w"))
""")


def _load(tmp_path, modfile, tag, cache):
    out = tmp_path / f"{tag}.json"
    env = dict(os.environ, FABKIT_CACHE_DIR=str(cache))
    env.pop("FABKIT_NUMBA_FULL_START", None)
    env.pop("NUMBA_CACHE_DIR", None)
    p = subprocess.run([sys.executable, "-c", LOADER, str(out), str(modfile)], env=env, cwd=tmp_path,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(out.read_text())


def _checks(r):
    assert r["exp"] < 1e-15 and r["cumsum"] < 1e-14 and r["sum"] < 1e-13


def test_a_miss_compiles_with_the_full_context_and_a_hit_loads_short(tmp_path):
    """A module in fabkit's cache of generated code: the first process misses (numba
    compiles, with everything it needs), the next loads the compiled code by the short
    path and still computes what numpy does. (Its cached code names numba's array
    math, for cumsum and sum, in its environment, which imports that module itself
    on loading: the short path needs no list of what cached code uses.)"""
    cache = tmp_path / "cache"
    (cache / "engine").mkdir(parents=True)
    modfile = cache / "engine" / "fk_test_short_start.py"
    modfile.write_text(KERNEL)
    cold = _load(tmp_path, modfile, "cold", cache)
    _checks(cold)
    assert cold["light"] == 0 and cold["arraymath"]
    warm = _load(tmp_path, modfile, "warm", cache)
    _checks(warm)
    assert warm["light"] == 1


def test_other_code_keeps_numbas_own_loader(tmp_path):
    """A cached function outside fabkit (and its cache) loads through numba's loader."""
    cache = tmp_path / "cache"
    (cache / "engine").mkdir(parents=True)
    other = tmp_path / "elsewhere"
    other.mkdir()
    modfile = other / "someone_elses.py"
    modfile.write_text(KERNEL)
    _checks(_load(tmp_path, modfile, "cold", cache))
    warm = _load(tmp_path, modfile, "warm", cache)
    _checks(warm)
    assert warm["light"] == 0 and warm["arraymath"]
