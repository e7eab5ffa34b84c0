"""Roughing jobs of the kind the planner was not built against (benchmarks/specs/hidden37
has the full set), end to end through `fabkit gcode`, checked by an independent cut of
LinuxCNC's own reading of the program (the brute force of tests/test_roughing_job.py:
each tool's own shape placed every STEP mm along every feed move, nodes H mm apart;
nothing of fabkit.toolpath.cut.stock).

- A groove narrower than an 8 mm bull nose runs out through both ends of the block: the
  bull reaches the groove's end only with its corner, from beyond the stock's edge. After
  roughing the material stands within [leave - tol, leave + stepdown + tol] wherever the
  bull reaches the allowance (its levels stopped at the lowest allowance and left the
  groove's ends 0.2 mm over the bound).
- A slot with steep ends (slope up to 3.7) after a 6 mm flat end mill: a 3 mm bull nose
  rests, then the 2 mm ball. Wherever the bull nose reaches the allowance it leaves at
  most the finishing ball's depth of cut above the design (it left 1.1 mm more beside
  the slot's ends, standing on a coarse bound of the design), nothing enters the
  allowance, the finish removes at most its depth of cut, and the rest keeps the tool
  down from pass to pass where the link is clear (feed moves across the passes).

Both jobs run with FABKIT_NO_KERNELS=1 (the numpy drop cutter: no compile of the formula).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from conftest import run_cli
from test_roughing_job import RS274, lowest_tool, reach, rs274_operations, samples

H, STEP, TOL = 0.2, 0.2, 0.01

TOOLS_COMMON = {"feed": 1800, "plunge": 500, "spindle": 15000}
MACHINING = {"scallop": 0.15, "tolerance": TOL, "feed": 1500, "plunge": 500, "spindle": 16000, "safe_height": 4}

EDGE_GROOVE = {
    "name": "edge_groove", "units": "mm",
    "surface": {"height": "-2.5 - 0.1*x - 4*exp(-(y - 1)**2/2)", "x": [-8, 8], "y": [-6, 6], "top": 0.0},
    "stock": {"thickness": 15},
    "tool": {"shape": "ball", "diameter": 2, "reach": 12, "number": 2, "depth_of_cut": 2},
    "tools": [{"number": 1, "shape": "bull", "diameter": 8, "corner_radius": 2, "reach": 12, **TOOLS_COMMON}],
    "roughing": {"tool": 1, "stepdown": 2, "stepover": 3, "leave": 0.3},
    "machining": {**MACHINING, "direction": "x"},
}

STEEP_SLOT = {
    "name": "steep_slot", "units": "mm",
    "surface": {"height": "-8*exp(-((x/4.5)**4 + (y/6)**4))", "x": [-8, 8], "y": [-9, 9], "top": 0.0},
    "stock": {"thickness": 15},
    "tool": {"shape": "ball", "diameter": 2, "reach": 14, "number": 3, "depth_of_cut": 2.5},
    "tools": [{"number": 1, "shape": "flat", "diameter": 6, "reach": 14, **TOOLS_COMMON},
              {"number": 2, "shape": "bull", "diameter": 3, "corner_radius": 0.75, "reach": 14, **TOOLS_COMMON}],
    "roughing": {"tool": 1, "stepdown": 3, "stepover": 2.5, "leave": 0.4, "rest": [2, 3]},
    "machining": {**MACHINING, "direction": "x"},
}


#: the surfaces' formulas (units mm, top face 0), independently of fabkit's expression compiler
DESIGN = {"edge_groove": lambda x, y: -2.5 - 0.1 * x - 4.0 * np.exp(-(y - 1.0) ** 2 / 2.0),
          "steep_slot": lambda x, y: -8.0 * np.exp(-((x / 4.5) ** 4 + (y / 6.0) ** 4))}


def _shape(tool: dict):
    if tool["shape"] == "bull":
        return f"bull{float(tool['corner_radius'])!r}", tool["diameter"] / 2
    return tool["shape"], tool["diameter"] / 2


def _job(tmp_path, raw):
    spec = tmp_path / f"{raw['name']}.yaml"
    spec.write_text(yaml.safe_dump(raw, sort_keys=False))
    code, out, err = run_cli(["gcode", spec, "-o", tmp_path / "job.ngc", "--no-progress", "--json"])
    assert code == 0, err
    shapes = {t["number"]: _shape(t) for t in [*raw["tools"], raw["tool"]]}
    ops, _ = rs274_operations(tmp_path / "job.ngc")
    L = raw["surface"]["x"][1] - raw["surface"]["x"][0]
    W = raw["surface"]["y"][1] - raw["surface"]["y"][0]
    X, Y = np.meshgrid(np.arange(0.0, L + 1e-9, H), np.arange(0.0, W + 1e-9, H), indexing="ij")
    x, y = X + raw["surface"]["x"][0], Y + raw["surface"]["y"][0]
    D = np.minimum(DESIGN[raw["name"]](x, y), 0.0)          # the formula, written here in numpy
    S = np.zeros_like(D)
    after = []
    for kind, num, pts, feeds, start in ops:
        shape, R = shapes[num]
        np.minimum(S, lowest_tool(S, H, samples(start, pts, feeds, step=STEP), shape, R), out=S)
        after.append((kind, num, S.copy(), pts, feeds, start))
    return json.loads(out), D, after, shapes


@pytest.fixture(autouse=True)
def _numpy_drop_cutter(monkeypatch):
    monkeypatch.setenv("FABKIT_NO_KERNELS", "1")      # no compile of these formulas


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_bull_nose_reaches_a_groove_running_out_through_the_stock_edge(tmp_path):
    raw = EDGE_GROOVE
    summary, D, after, shapes = _job(tmp_path, raw)
    assert summary["ok"] is True
    kind, num, S, *_ = after[0]
    assert kind == "rough" and num == 1
    leave, step = raw["roughing"]["leave"], raw["roughing"]["stepdown"]
    T = np.minimum(D + leave, 0.0)
    assert float(np.min(S - T)) >= -TOL                                   # never into the allowance
    shape, R = shapes[1]
    there = reach(T, H, shape, R) <= T + TOL                               # where the bull reaches T
    ends = there & ((np.arange(S.shape[0]) == 0) | (np.arange(S.shape[0]) == S.shape[0] - 1))[:, None]
    assert ends.sum() > 10                                                 # the groove's ends, at the edges
    assert float(np.max((S - T)[there])) <= step + TOL
    assert float(np.max((S - T)[there])) > 0.5 * step                      # the staircase is there


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_bull_nose_rest_beside_steep_walls_and_runs_linked_into_passes(tmp_path):
    raw = STEEP_SLOT
    summary, D, after, shapes = _job(tmp_path, raw)
    assert summary["ok"] is True
    assert [(k, n) for k, n, *_ in after] == [("rough", 1), ("rest", 2), ("rest", 3), ("finish", 3)]
    leave, doc = raw["roughing"]["leave"], raw["tool"]["depth_of_cut"]
    T = np.minimum(D + leave, 0.0)
    rough, bull, ball, fin = (a[2] for a in after)
    for S in (rough, bull, ball):
        assert float(np.min(S - T)) >= -TOL                               # nothing enters the allowance
    assert float(np.min(fin - D)) >= -TOL                                  # no gouge
    shape, R = shapes[2]
    there = reach(T, H, shape, R) <= T + TOL
    # the flat end mill left more there than the finish may take; the bull nose takes it
    assert float(np.max((rough - D)[there])) > doc + 1.0
    assert float(np.max((bull - D)[there])) <= doc + TOL
    assert float(np.max(ball - fin)) <= doc + TOL                          # the finish's depth of cut
    # the rest keeps the tool down between passes where it can: feed moves across the
    # passes (along y; the passes run along x)
    for _, _, _, pts, feeds, start in after[1:3]:
        prev = np.vstack([start[None, :], pts[:-1]])
        d = pts - prev
        across = feeds & (np.abs(d[:, 1]) > 0.3) & (np.abs(d[:, 0]) < 1e-6) & (pts[:, 2] < -0.5)
        assert across.sum() >= 3
