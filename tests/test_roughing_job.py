"""The whole rough-then-finish job end to end through `fabkit gcode`, checked by an
independent cut simulation of LinuxCNC's own reading of the program.

A small block (40 x 30 mm) holds a bowl with a groove narrower than the 6 mm roughing
end mill. The program is read by ``rs274 -g`` (the LinuxCNC interpreter, M6 included),
and its canonical moves are replayed here by brute force: each tool (6 mm flat end mill,
3 mm ball) placed every ``STEP`` mm along every feed move and lowering a height field of
nodes ``H`` mm apart to its own shape (flat bottom, or the ball's lift
``R - sqrt(R^2 - rho^2)``). Nothing of fabkit.toolpath.cut.stock is used. Sampling a move
only leaves more material than the swept envelope (the ball by at most
``STEP^2 / (8 R)`` = 0.0008 mm), so a gouge found here is real and material found left
is at most that much too high.

The checks are those of the job's acceptance: no gouge beyond the tolerance by any tool;
after roughing, material left within [leave - tolerance, leave + stepdown + the planner's
stated allowance error] where the end mill reaches; after finishing, material left within
scallop + tolerance where the ball reaches (normal to the design); the groove gets rest
passes, and the finishing ball removes at most its depth of cut there (and everywhere);
no rapid passes through the stock its operation leaves. The grbl dialect writes one
program per tool, named ``<stem>.1-rough.nc`` ... .

The job runs with FABKIT_NO_KERNELS=1 (the numpy drop cutter, the same program): a cold
compile of this surface's formula would add about 10 s. About 10-17 s in all.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from conftest import run_cli

RS274 = shutil.which("rs274")

H = 0.2          # mm between the simulation's nodes
STEP = 0.1       # mm between the tool's placements along a move
LEAVE, STEPDOWN, TOL, SCALLOP, DOC_FINISH = 0.3, 2.0, 0.01, 0.05, 3.0
L, W = 40.0, 30.0

RAW = {
    "name": "groove", "units": "mm",
    "surface": {"height": "0.02*(x**2 + y**2) - 10 - 5*exp(-(x - 5)**2/17.64)",
                "x": [-20, 20], "y": [-15, 15], "top": 0.0},
    "stock": {"thickness": 30},
    "tool": {"shape": "ball", "diameter": 3, "reach": 25, "number": 2, "depth_of_cut": DOC_FINISH},
    "tools": [{"number": 1, "shape": "flat", "diameter": 6, "reach": 25, "depth_of_cut": 6,
               "feed": 2000, "plunge": 600, "spindle": 14000}],
    "roughing": {"tool": 1, "stepdown": STEPDOWN, "stepover": 2.5, "leave": LEAVE},
    "machining": {"scallop": SCALLOP, "tolerance": TOL, "feed": 1500, "plunge": 500, "spindle": 16000,
                  "safe_height": 5},
}
#: the tools by number: (shape, radius mm)
TOOLS = {1: ("flat", 3.0), 2: ("ball", 1.5)}


def design(X, Y):
    """The spec's surface in work mm (X0 Y0 at the footprint's corner, Z0 the top face),
    clipped at the top face; and its slope |grad H| (exact derivatives)."""
    x, y = X - 20.0, Y - 15.0
    g = 5.0 * np.exp(-(x - 5.0) ** 2 / 17.64)
    h = 0.02 * (x * x + y * y) - 10.0 - g
    hx = 0.04 * x + g * 2.0 * (x - 5.0) / 17.64
    hy = 0.04 * y
    return np.minimum(h, 0.0), np.hypot(hx, hy)


def lift(shape, R, rho):
    """Height of the cutting surface above the tip at radius rho (<= R)."""
    if shape == "flat":
        return np.zeros_like(rho)
    if shape.startswith("bull"):            # "bull<r>": a corner radius r, a flat of R - r
        r = float(shape[4:])
        u = np.maximum(rho - (R - r), 0.0)
        return r - np.sqrt(np.maximum(r * r - u * u, 0.0))
    return R - np.sqrt(np.maximum(R * R - rho * rho, 0.0))


# ----------------------------------------------------------------------------
# rs274's moves
# ----------------------------------------------------------------------------
_LINE = re.compile(r"(STRAIGHT_FEED|STRAIGHT_TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)"
                   r"|CHANGE_TOOL\((\d+)\)|COMMENT\(\"operation: \d+ of \d+, (\w+), T\d+\"\)")


def rs274_operations(path):
    """The program as LinuxCNC's interpreter executes it: [(kind, tool number,
    points (n, 3), feed flags (n,), start point)] per operation, in order."""
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr.strip() in ("", "executing"), run.stderr
    ops, tool, kind, at = [], None, None, None
    for m in _LINE.finditer(run.stdout):
        if m.group(5):
            tool = int(m.group(5))
        elif m.group(6):
            kind = m.group(6)
            ops.append([kind, None, [], [], at])
        else:
            p = (float(m.group(2)), float(m.group(3)), float(m.group(4)))
            if ops:
                op = ops[-1]
                op[1] = tool if op[1] is None else op[1]
                assert op[1] == tool, "a tool change inside an operation"
                if op[4] is None:
                    op[4] = at if at is not None else p
                op[2].append(p)
                op[3].append(m.group(1) == "STRAIGHT_FEED")
            at = p
    changes = re.findall(r"CHANGE_TOOL\((\d+)\)", run.stdout)
    return [(k, t, np.array(p, float), np.array(f, bool), np.array(s, float)) for k, t, p, f, s in ops], changes


# ----------------------------------------------------------------------------
# the brute-force cut
# ----------------------------------------------------------------------------
def samples(start, points, feeds, step=STEP, want_feed=True):
    """Tool tips every ``step`` mm along the moves of one kind (feeds or rapids)."""
    out = []
    prev = start
    for p, f in zip(points, feeds):
        if f == want_feed:
            n = max(1, int(math.ceil(np.linalg.norm(p - prev) / step)))
            t = np.linspace(0.0, 1.0, n + 1)[:, None]
            out.append(prev + t * (p - prev))
        prev = p
    return np.vstack(out) if out else np.zeros((0, 3))


def stencil(R, h):
    k = int(math.ceil(R / h)) + 1
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    return di.ravel(), dj.ravel()


def lowest_tool(S, h, tips, shape, R, reduce=np.minimum, chunk=4000):
    """For every node, the lowest tool surface over it among ``tips`` (reduce=minimum,
    returned as an array, inf where no tip covers it)."""
    nx, ny = S.shape
    out = np.full(S.shape, np.inf)
    di, dj = stencil(R, h)
    flat_out = out.ravel()
    for a in range(0, len(tips), chunk):
        c = tips[a:a + chunk]
        i = np.rint(c[:, 0] / h).astype(np.int64)[:, None] + di[None, :]
        j = np.rint(c[:, 1] / h).astype(np.int64)[:, None] + dj[None, :]
        rho = np.hypot(i * h - c[:, :1], j * h - c[:, 1:2])
        ok = (rho <= R) & (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        z = c[:, 2:3] + lift(shape, R, np.minimum(rho, R))
        np.minimum.at(flat_out, (i[ok] * ny + j[ok]), z[ok])
    return out


def replay(S, h, op):
    """Cut ``S`` (in place) by one operation; returns the deepest rapid into the stock
    the operation leaves (mm, 0 if none)."""
    kind, tool, pts, feeds, start = op
    shape, R = TOOLS[tool]
    env = lowest_tool(S, h, samples(start, pts, feeds), shape, R)
    np.minimum(S, env, out=S)
    rap = lowest_tool(S, h, samples(start, pts, feeds, want_feed=False), shape, R)
    return float(max(0.0, np.max(S - rap)))


def reach(T, h, shape, R):
    """The lowest surface the tool's underside reaches over the target T (the grey-scale
    closing of T by the tool, brute force over the grid; no material beyond it)."""
    from scipy.ndimage import grey_dilation, grey_erosion

    k = int(math.ceil(R / h))
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    rho = np.hypot(di, dj) * h
    inside = rho <= R
    st = np.where(inside, -lift(shape, R, np.minimum(rho, R)), 0.0)
    pad = np.pad(T, k, constant_values=-1e6)
    top = grey_dilation(pad, footprint=inside, structure=st, mode="nearest")
    low = grey_erosion(top, footprint=inside, structure=st, mode="nearest")
    return low[k:-k, k:-k]


def simulate(ngc):
    """The whole job replayed from rs274's moves: dict of stocks and figures."""
    ops, changes = rs274_operations(ngc)
    x, y = np.arange(0.0, L + 1e-9, H), np.arange(0.0, W + 1e-9, H)
    X, Y = np.meshgrid(x, y, indexing="ij")
    D, slope = design(X, Y)
    S = np.zeros_like(D)
    after, rapids = [], []
    for op in ops:
        rapids.append(replay(S, H, op))
        after.append(S.copy())
    return {"ops": ops, "changes": changes, "X": X, "Y": Y, "D": D, "slope": slope, "after": after,
            "rapids": rapids}


# ----------------------------------------------------------------------------
# the test
# ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def job(tmp_path_factory):
    d = tmp_path_factory.mktemp("rjob")
    spec = d / "groove.yaml"
    spec.write_text(yaml.safe_dump(RAW, sort_keys=False))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FABKIT_NO_KERNELS", "1")      # the numpy drop cutter: no compile of this formula
        code, out, err = run_cli(["gcode", spec, "-o", d / "groove.ngc", "--no-progress", "--json"])
    assert code == 0, err
    return d, json.loads(out)


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_rough_rest_finish_job_by_an_independent_cut_of_rs274_moves(job):
    d, summary = job
    sim = simulate(d / "groove.ngc")
    kinds = [op[0] for op in sim["ops"]]
    assert kinds == ["rough", "rest", "finish"]
    assert sim["changes"] == ["1", "2"]                    # M6 to T1, then T2 (kept for the finish)
    assert [op[1] for op in sim["ops"]] == [1, 2, 2]
    D, slope = sim["D"], sim["slope"]
    rough, rest, fin = sim["after"]

    # no gouge beyond the tolerance, by any tool
    for S in sim["after"]:
        assert float(np.min(S - D)) >= -TOL
    # no rapid through the stock its operation leaves
    assert max(sim["rapids"]) <= 1e-6

    # after roughing: within [leave - tol, leave + stepdown + the stated allowance error]
    # where the end mill reaches the target T = min(design + leave, 0)
    T = np.minimum(D + LEAVE, 0.0)
    left = rough - T
    assert float(left.min()) >= -TOL
    flat = reach(T, H, "flat", TOOLS[1][1])
    reaches = flat <= T + TOL
    rough_op = [o for o in summary["operations"] if o["kind"] == "rough"][0]
    assert rough_op["levels"] == 7                          # -2 ... -14, above the groove's allowance -14.7
    # the planner's stated error: 0.02 mm of loop inset and dilation chords horizontally (x the
    # slope), its level sets' vertical bound below the tolerance (docs/toolpath.md)
    err = TOL + 0.025 * slope
    assert reaches.mean() > 0.5
    assert float(np.max((left - STEPDOWN - err)[reaches])) <= TOL
    # where it cannot reach T (the bowl's curve under a flat bottom, the groove), the same
    # bound holds above the lowest surface it reaches
    assert float(np.max(rough - np.maximum(T, flat) - STEPDOWN - err)) <= TOL
    # the staircase is really there: material left reaches leave + most of a stepdown
    assert float(np.max(left[reaches])) > 0.8 * STEPDOWN

    # the groove (x = 25 mm in work, 2 mm either side; y inside the bowl): the roughing
    # left more than the finishing ball may cut, the rest passes cut there, and the
    # finish removed at most its depth of cut
    groove = (np.abs(sim["X"] - 25.0) < 2.0) & (np.abs(sim["Y"] - 15.0) < 8.0)
    deep = groove & (rough - D > DOC_FINISH + TOL)
    assert deep.sum() > 100
    assert float(np.min((rough - rest)[deep])) > 0.5
    rest_pts = sim["ops"][1][2]
    low = rest_pts[:, 2] < -1.0
    assert np.mean(np.abs(rest_pts[low, 0] - 25.0) < 6.0) > 0.5      # the rest passes go mostly there
    removed = rest - fin
    assert float(removed.max()) <= DOC_FINISH + TOL
    assert float(np.max((rough - fin)[deep])) > DOC_FINISH + TOL        # without rest passes: too deep

    # after finishing: within scallop + tolerance (normal to the design) where the ball reaches
    ball = reach(D, H, "ball", TOOLS[2][1])
    there = ball <= D + TOL
    assert there.mean() > 0.95
    normal_left = (fin - D) / np.sqrt(1.0 + slope ** 2)
    assert float(np.max(normal_left[there])) <= SCALLOP + TOL
    assert summary["ok"] is True


def test_grbl_job_writes_one_program_per_tool(tmp_path, monkeypatch):
    raw = json.loads(json.dumps(RAW))
    raw["machining"]["dialect"] = "grbl"
    spec = tmp_path / "groove.yaml"
    spec.write_text(yaml.safe_dump(raw, sort_keys=False))
    monkeypatch.setenv("FABKIT_NO_KERNELS", "1")
    code, out, err = run_cli(["gcode", spec, "-o", tmp_path / "job.nc", "--no-progress", "--no-verify"])
    assert code == 0, err
    names = sorted(p.name for p in tmp_path.glob("job*.nc"))
    assert names == ["job.1-rough.nc", "job.2-rest.nc", "job.3-finish.nc"]
    for name, n in zip(names, (1, 2, 2)):
        text = (tmp_path / name).read_text()
        code_lines = [ln for ln in text.splitlines() if not ln.startswith("(")]
        assert not any(re.search(r"M6\b|\bT\d|G43", ln) for ln in code_lines)
        assert f"load T{n} by hand" in text                 # the tool, in a comment
