"""The stock as a height field, cut by each tool's own shape, and the whole job verified.

:class:`Stock` is the material's top surface Z(X, Y) on a regular grid of nodes over
the footprint [0, L] x [0, W] (work mm, the top face Z = 0, edges included). :func:`cut`
lowers it to the lower envelope of a tool (:class:`~fabkit.toolpath.tools.Tool`: flat
end mill, bull nose or ball) swept along straight moves. The envelope is EXACT at the
nodes (closed forms for the flat end mill and the ball, a bisection to ~1e-12 mm for
the bull nose; see :mod:`fabkit.toolpath.cut.stock_kernels`); between nodes nothing is
checked, so the grid spacing h sets the sharpness: a smooth cut surface of curvature
radius rho is sampled with a chordal error below h^2 / (8 rho), a feature narrower than
h can fall between nodes, and a ridge (a scallop's crest, flanks of slope m) between
two nodes is under-read by up to m h / 2 (the paper's 6.35 mm ball at its largest
stepover, 1.09 mm: m = 0.17, 0.02 mm at h = 0.25 mm). :func:`grid_spacing` picks h so
that the chordal error is at most the tolerance for the tools' smallest corner radius,
and at most :data:`SPACING_MAX` (the paper's block: 0.25 mm, 2001 x 1001 nodes).

Rapids never cut: a rapid whose tool would pass below the stock present at that moment
(by more than :data:`RAPID_TOL`) is reported, and the stock is left as it was.

:func:`verify_job` replays the operations of a job (roughing, rest, finishing, each
with its tool) on one stock, snapshots it after each, and checks against the clipped
design surface (:class:`~fabkit.toolpath.finish.compensate.WorkSurface`, min(H, 0), as
:func:`~fabkit.toolpath.cut.verify.verify_cut` uses):

* gouge: stock below the design by more than the tolerance, after any operation;
* roughing: material above the design within [leave - tolerance, leave + cusp +
  tolerance + the planner's stated allowance error] where the operation's tool reaches
  design + leave (cusp: ``info["cusp_mm"]``, the Z-level staircase plus the stepover cusp;
  else ``info["stepdown_mm"]``; the error: ``info["allowance_excess_mm"]`` vertical plus
  ``info["allowance_offset_mm"]`` x the design's slope); above it where the tool cannot
  reach is reported apart;
* rest: material above the design within [leave - tolerance, the finishing tool's depth
  of cut + tolerance] where the rest tool reaches design + leave (rest passes leave the
  roughing's staircase where the roughing tool reached);
* finishing: material left at most scallop + tolerance where the ball reaches;
* per operation the largest thickness it removes at a node (for rest passes, in Z
  levels: the largest one move removes) against the tool's allowed depth of cut when
  one is given.

Where a tool "reaches" is the grey-scale opening of the target surface by the tool
over the grid nodes (:func:`~fabkit.toolpath.cut.stock_kernels.reach_at`): centres and
contacts at the nodes only, so the reach is known to about the chordal error above,
either way (a ball in a 45-degree V groove at h = 0.1 mm: 2e-4 mm low, tested; for a
flat bottom on a slope s, to about s x h).
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field

import numpy as np

from ...errors import DesignError, SpecError
from ..path import RAPID
from ..tools import Tool

__all__ = ["RAPID_TOL", "MAX_NODES", "Stock", "CutResult", "OperationCut", "JobCut", "grid_spacing",
           "make_stock", "cut", "design_heights", "operations_from_program", "verify_job", "stock_png"]

#: a rapid passing this far (mm) or less into the stock is not reported (floating point)
RAPID_TOL = 1e-6
#: grid nodes at most (a 500 x 250 mm block at 0.1 mm: 12.5 million, 100 MB a snapshot)
MAX_NODES = 20_000_000
#: nodes above their bound whose reach is computed one by one (beyond: sampled, see reach_height)
MAX_REACH_NODES = 200_000
#: node visits (or node-offset pairs) per call of a compiled kernel: between calls Python
#: sees Ctrl-C (about 0.1-0.3 s of work on the reference machine)
KERNEL_CHUNK_WORK = 5e7
#: grid spacing bounds, mm
SPACING_MIN, SPACING_MAX = 0.05, 0.25
#: design_heights: points evaluated at a time
DESIGN_BLOCK = 1 << 18


# ----------------------------------------------------------------------------
# the height field
# ----------------------------------------------------------------------------
@dataclass
class Stock:
    """Material top Z (work mm) at the nodes (i hx, j hy), i < nx, j < ny, covering
    [0, L] x [0, W] edges included. ``z`` is (nx, ny), 0 on the uncut top face."""

    L: float
    W: float
    hx: float
    hy: float
    z: np.ndarray

    @property
    def shape(self):
        return self.z.shape

    @property
    def x(self) -> np.ndarray:
        return np.arange(self.z.shape[0]) * self.hx

    @property
    def y(self) -> np.ndarray:
        return np.arange(self.z.shape[1]) * self.hy

    def grid(self):
        """(X, Y): (nx, ny) node coordinates, work mm."""
        return np.meshgrid(self.x, self.y, indexing="ij")

    def copy(self) -> "Stock":
        return Stock(self.L, self.W, self.hx, self.hy, self.z.copy())


def grid_spacing(tools, tolerance: float) -> float:
    """Spacing (mm) whose chordal error on a surface cut by the smallest corner radius
    rho among ``tools`` is at most ``tolerance``: sqrt(8 rho tol) (h^2 / (8 rho) <= tol),
    within [SPACING_MIN, SPACING_MAX]. Flat end mills (no corner) count with their
    radius (their cut floors are flat; their walls are placed to h / 2 either way)."""
    rho = min((t.corner_radius if t.corner_radius > 0 else t.radius) for t in tools)
    h = math.sqrt(8.0 * rho * float(tolerance))
    return float(min(max(h, SPACING_MIN), SPACING_MAX))


def make_stock(L: float, W: float, spacing: float, top: float = 0.0) -> Stock:
    """An uncut block: nodes at most ``spacing`` apart, edges on the grid."""
    if not (spacing > 0 and math.isfinite(spacing)):
        raise SpecError(f"stock grid spacing {spacing!r}: must be a positive number of mm")
    nx = max(2, int(math.ceil(L / spacing - 1e-9)) + 1)
    ny = max(2, int(math.ceil(W / spacing - 1e-9)) + 1)
    if nx * ny > MAX_NODES:
        raise SpecError(f"stock grid of {nx} x {ny} nodes at {spacing:g} mm exceeds {MAX_NODES} nodes; "
                        "use a coarser spacing")
    return Stock(float(L), float(W), L / (nx - 1), W / (ny - 1), np.full((nx, ny), float(top)))


def design_heights(surface, stock: Stock) -> np.ndarray:
    """The clipped design min(H, 0) at the stock's nodes (work mm; WorkSurface, as the
    verification of the finishing program uses)."""
    from ..finish.compensate import WorkSurface

    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    x, y = stock.x, stock.y
    out = np.empty((len(x), len(y)))
    # in blocks of rows (the design is evaluated point by point: the same values; no
    # full-grid coordinate arrays)
    rows = max(1, DESIGN_BLOCK // max(len(y), 1))
    for i in range(0, len(x), rows):
        X, Y = np.meshgrid(x[i:i + rows], y, indexing="ij")
        np.minimum(ws.H(np.ascontiguousarray(X.ravel()), np.ascontiguousarray(Y.ravel())), 0.0,
                   out=out[i:i + rows].reshape(-1))
    return out


# ----------------------------------------------------------------------------
# cutting
# ----------------------------------------------------------------------------
@dataclass
class CutResult:
    """What one run of moves did to the stock (work mm).

    moves: moves replayed; feeds: feed moves
    engagement: (n,) per move the largest thickness it removed at a node (0 for rapids)
    max_engagement, engagement_at: the largest of them and the move's index
    rapids_into_stock: rapids whose tool would have passed below the stock present then
    rapid_depth, rapid_at, rapid_move: the deepest such, its node (X, Y) and move index
    unlocated_low: moves from or to a position not fully known that go below the top face
    deepest_cut: mm below the top face (work Z = 0) of the deepest tip of a move that
        removed material
    """

    moves: int
    feeds: int
    engagement: np.ndarray
    max_engagement: float
    engagement_at: int | None
    deepest_cut: float
    rapids_into_stock: int
    rapid_depth: float
    rapid_at: tuple | None
    rapid_move: int | None
    unlocated_low: int


def _tool_shape(tool: Tool):
    return float(tool.radius), float(tool.corner_radius), float(tool.flat_radius)


def cut(stock: Stock, tool: Tool, points, kinds, start=None) -> CutResult:
    """Lower ``stock`` (in place) to the lower envelope of ``tool`` swept along the moves:
    move i goes from points[i-1] (``start`` for the first; default: straight down from
    above the first point, like a program's first rapid) to points[i], a RAPID (0) or a
    feed (any other kind). Tip positions, work mm. nan coordinates (a program's axes
    never set yet) take the end point's value; such moves below the top face are
    counted in ``unlocated_low``. Rapids do not cut; those that would are reported."""
    from .stock_kernels import cut_moves

    P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    K = np.asarray(kinds).reshape(-1)
    if len(P) != len(K):
        raise ValueError("points and kinds differ in length")
    n = len(P)
    if start is None:
        start = P[0] if n else np.zeros(3)
    A = np.vstack([np.asarray(start, dtype=float)[None, :], P[:-1]]) if n else P.copy()
    unknown = ~(np.isfinite(A).all(axis=1) & np.isfinite(P).all(axis=1))
    A = np.where(np.isfinite(A), A, P)
    A_all = A
    located = np.isfinite(A).all(axis=1) & np.isfinite(P).all(axis=1)
    zlow = np.fmin(A[:, 2], P[:, 2])
    top = float(stock.z.max()) if stock.z.size else 0.0
    unlocated_low = int(np.sum(unknown & ~(zlow >= top)))
    A, B = np.ascontiguousarray(A[located]), np.ascontiguousarray(P[located])
    feed = np.ascontiguousarray(K[located] != RAPID)
    m = len(A)
    engage = np.zeros(m)
    rdepth = np.zeros(m)
    rnode = np.full((m, 2), -1, dtype=np.int64)
    R, r, f = _tool_shape(tool)
    if m:
        # in chunks of about KERNEL_CHUNK_WORK node visits (a move visits the nodes within R
        # of it): the kernel returns between them, so Ctrl-C is honoured within a chunk
        seg = np.hypot(B[:, 0] - A[:, 0], B[:, 1] - A[:, 1])
        work = np.cumsum((seg + 2.0 * R + 2.0 * stock.hx) * (2.0 * R + 2.0 * stock.hy)
                         / (stock.hx * stock.hy) + 1.0)
        cuts = np.searchsorted(work, np.arange(KERNEL_CHUNK_WORK, work[-1], KERNEL_CHUNK_WORK))
        bounds = np.unique(np.r_[0, cuts + 1, m].clip(0, m))
        for a, b in zip(bounds[:-1], bounds[1:]):
            cut_moves(stock.z, stock.hx, stock.hy, A[a:b], B[a:b], feed[a:b], R, r, f, RAPID_TOL,
                      engage[a:b], rdepth[a:b], rnode[a:b])
    idx = np.nonzero(located)[0]
    eng = np.zeros(n)
    eng[idx] = engage
    rap = np.zeros(n)
    rap[idx] = rdepth
    bad = rap > RAPID_TOL
    cutting = eng > 0
    deepest = float(max(0.0, -np.min(np.fmin(A_all[cutting, 2], P[cutting, 2])))) if cutting.any() else 0.0
    ie = int(np.argmax(eng)) if n else None
    ir = int(np.argmax(rap)) if bad.any() else None
    rat = None
    if ir is not None:
        k = int(np.searchsorted(idx, ir))
        rat = (float(rnode[k, 0] * stock.hx), float(rnode[k, 1] * stock.hy))
    return CutResult(moves=n, feeds=int(np.sum(K != RAPID)), engagement=eng,
                     max_engagement=float(eng.max()) if n else 0.0,
                     engagement_at=ie if n and eng.max() > 0 else None,
                     rapids_into_stock=int(bad.sum()), rapid_depth=float(rap.max()) if n else 0.0,
                     rapid_at=rat, rapid_move=ir, unlocated_low=unlocated_low,
                     deepest_cut=deepest)


def reach_height(target: np.ndarray, stock: Stock, tool: Tool, mask: np.ndarray,
                 max_nodes: int = MAX_REACH_NODES, beyond: float | None = None) -> np.ndarray:
    """Lowest height ``tool`` can cut at the nodes where ``mask`` holds without cutting
    below ``target`` (nx, ny) anywhere (nan elsewhere); see the module's accuracy note.
    Over ``max_nodes`` masked nodes (a job that left much of the block), the reach is
    computed on every k-th node of the mask in each direction and the others take the
    value of the nearest computed node. ``beyond`` (mm, default R): how far outside the
    block the tool's centre may stand."""
    from .stock_kernels import reach_at

    out = np.full(target.shape, np.nan)
    n = int(mask.sum())
    if not n:
        return out
    R, r, f = _tool_shape(tool)
    sub = mask
    if n > max_nodes:
        k = int(math.ceil(math.sqrt(n / max_nodes)))
        grid = np.zeros_like(mask)
        grid[::k, ::k] = True
        sub = mask & grid
        if not sub.any():
            sub = mask
    pi, pj = np.nonzero(sub)
    pi, pj = pi.astype(np.int64), pj.astype(np.int64)
    T = np.ascontiguousarray(target, dtype=float)
    nx, ny = T.shape
    ci, cj = int(math.ceil(R / stock.hx)), int(math.ceil(R / stock.hy))
    i0, j0 = int(pi.min()), int(pj.min())
    # the drops, shared by the chunks: the centres within R of the nodes' bounding box
    D = np.full((int(pi.max()) - i0 + 1 + 2 * ci, int(pj.max()) - j0 + 1 + 2 * cj), np.nan)
    # chunks of about KERNEL_CHUNK_WORK node-offset pairs (a drop not yet known costs as
    # many again): the kernel returns between them, so Ctrl-C is honoured within a chunk
    # (in the nodes' row order a node adds about 2 R / h + 2 centres to the drops known)
    n_off = max(1.0, math.pi * (R / stock.hx + 1.0) * (R / stock.hy + 1.0))
    step = max(1, int(KERNEL_CHUNK_WORK / (n_off * (2.0 * R / min(stock.hx, stock.hy) + 2.0))))
    vals = np.empty(len(pi))
    for a in range(0, len(pi), step):
        vals[a:a + step] = reach_at(T, stock.hx, stock.hy, R, r, f, pi[a:a + step], pj[a:a + step], D,
                                    float(R if beyond is None else min(beyond, R)), i0, j0)
    out[pi, pj] = vals
    if sub is not mask:
        from scipy.ndimage import distance_transform_edt

        ii, jj = distance_transform_edt(~sub, return_distances=False, return_indices=True)
        rest = mask & ~sub
        out[rest] = out[ii[rest], jj[rest]]
    return out


# ----------------------------------------------------------------------------
# the whole job
# ----------------------------------------------------------------------------
def operations_from_program(program, tools: dict, kinds: dict | None = None, info: dict | None = None):
    """Operations (:class:`~fabkit.toolpath.operations.Operation`) from a program read
    back (:func:`~fabkit.toolpath.program.reader.read_program`), one per run of one tool.
    ``tools``: {tool number: Tool} (-1: the moves before any M6); ``kinds``: {tool
    number: "rough" | "rest" | "finish"} (default: the last tool finishes, the first
    roughs, any other rests); ``info``: {tool number: dict} merged into each
    operation's info (leave, cusp, ...: ``leave`` also sets Operation.leave)."""
    from ..operations import Operation
    from ..path import Toolpath

    runs = program.split()
    order = []
    for t, _ in runs:
        if t not in order:
            order.append(t)
    ops = []
    for t, run in runs:
        if t not in tools:
            raise DesignError(f"program uses tool {t} (line {int(run.line[0])}) that the job does not list")
        if kinds and t in kinds:
            kind = kinds[t]
        else:
            kind = "finish" if t == order[-1] else ("rough" if t == order[0] else "rest")
        inf = dict((info or {}).get(t, {}))
        tp = Toolpath(run.points, run.kinds, tools[t].radius, safe_z=np.nan)
        tp.info["start"] = run.start
        tp.info["line"] = run.line
        ops.append(Operation(kind, tools[t], tp, leave=float(inf.get("leave", 0.0)), info=inf))
    return ops


@dataclass
class OperationCut:
    """One operation's cut, checked on the stock after it (work mm, (X, Y) work mm).

    kind, tool: the operation and its tool (described)
    max_gouge, gouge_at: largest depth of the stock below the design (any node)
    min_left, max_left, left_at: material above the design (stock - design) where the
        tool reaches its target (design + leave): smallest, largest and where the largest is
    bounds: (low, high) allowed for that material
    over_reachable, over_area, over_at: largest excess above ``high`` where the tool
        reaches, the area (mm^2) of nodes above it, and where the largest is
    unreachable, unreachable_area, unreachable_at: largest material above ``high`` where
        the tool cannot reach (a valley narrower than it), its area (mm^2), and where
    max_removed, removed_at: largest thickness the operation removed at a node
    max_engagement: largest thickness a single move removed at a node
    depth_of_cut_limit: allowed thickness (None: not checked)
    deepest_cut: deepest tip below the top face of a move that cut (checked against the
        tool's reach)
    rapids_into_stock, rapid_depth, rapid_at: rapids that would have cut
    unlocated_low: moves from an unknown position below the top face
    moves, feeds: moves replayed
    """

    kind: str
    tool: str
    max_gouge: float
    gouge_at: tuple
    min_left: float
    max_left: float
    left_at: tuple
    bounds: tuple
    over_reachable: float
    over_area: float
    unreachable: float
    unreachable_area: float
    over_at: tuple | None
    unreachable_at: tuple | None
    max_removed: float
    removed_at: tuple
    max_engagement: float
    depth_of_cut_limit: float | None
    deepest_cut: float
    rapids_into_stock: int
    rapid_depth: float
    rapid_at: tuple | None
    unlocated_low: int
    moves: int
    feeds: int

    def to_json(self) -> dict:
        out = {}
        for k, v in self.__dict__.items():
            out[k] = list(v) if isinstance(v, tuple) else v
        return out


@dataclass
class JobCut:
    """The whole job's simulated cut: per operation its :class:`OperationCut` and the
    stock after it (``snapshots``), the design at the nodes, and the verdict."""

    operations: list
    snapshots: list
    design: np.ndarray
    spacing: tuple
    tolerance: float
    seconds: float
    failures: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def message(self) -> str:
        if self.ok:
            worst = max((o.max_gouge for o in self.operations), default=0.0)
            parts = [f"{o.kind}: material left {o.min_left:.3f}-{o.max_left:.3f} mm (bound {o.bounds[1]:.3f})"
                     for o in self.operations]
            return (f"stock simulation on a {self.design.shape[0]} x {self.design.shape[1]} grid "
                    f"({self.spacing[0]:.3g} x {self.spacing[1]:.3g} mm): largest gouge {worst:.4f} mm; "
                    + "; ".join(parts))
        return "; ".join(self.failures)

    def pictures(self, **kw) -> dict:
        """{"rough": PNG after the last roughing or rest operation, "finish": PNG after the
        last finishing one} (:func:`stock_png`; keys only for the operations the job has)."""
        out = {}
        for key, kinds, title in (("rough", ("rough", "rest"), "after roughing"),
                                  ("finish", ("finish",), "after finishing")):
            idx = [i for i, o in enumerate(self.operations) if o.kind in kinds]
            if idx:
                out[key] = stock_png(self.snapshots[idx[-1]], self.design, title=title,
                                     tolerance=self.tolerance, **kw)
        return out

    def to_json(self) -> dict:
        return {"ok": self.ok, "message": self.message, "failures": list(self.failures),
                "grid": list(self.design.shape),
                "spacing": list(self.spacing), "tolerance": self.tolerance, "seconds": self.seconds,
                "operations": [o.to_json() for o in self.operations]}


def _max3(a: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """The 3 x 3 maximum of ``a`` at every node, the edges repeated (scipy.ndimage's
    maximum_filter(a, size=3, mode="nearest"), without its import); ``overwrite``: into
    ``a`` itself (C-contiguous float)."""
    from .stock_kernels import window_max

    return window_max(a, (3, 3), out=a if overwrite else None)


def _at(stock, flat_index):
    i, j = np.unravel_index(int(flat_index), stock.z.shape)
    return (float(i * stock.hx), float(j * stock.hy))


#: nodes over their bound after the finish whose reach is computed exactly (the worst first;
#: beyond them the grid's reach stands, which only ever reports more material)
MAX_EXACT_REACH_NODES = 2000


def _finish_along(points, kinds) -> str:
    """The finish's pass direction read from its feed moves: "x" when more of their
    length runs along X than along Y."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(P) < 2:
        return "x"
    d = np.abs(np.diff(P[:, :2], axis=0))
    feed = (np.asarray(kinds)[1:] != RAPID) & np.isfinite(d).all(axis=1)
    return "x" if d[feed, 0].sum() >= d[feed, 1].sum() else "y"


def _finish_reach_exact(ws, stock, op, z, dz, scale_f, slack, reach) -> int:
    """Replace, in ``reach`` (in place), the grid's reach at the nodes the finish leaves
    over their bound by the exact one (:func:`~fabkit.toolpath.cut.reach.reachable_height`:
    exact drop-cutter heights of the ball on the clipped design, its centres up to the
    finish verification's overhang beyond the footprint, every centre a real position).
    The grid's opening (:func:`reach_height`) takes the design at the nodes only: on a V
    whose walls are steeper than a cell resolves (``20*abs(x - y) - 8`` at 0.25 mm: the
    rim lies between the nodes at -3 mm and 0) it lets a ball down 0.12 mm below any real
    position. Returns the number of nodes recomputed (the worst
    :data:`MAX_EXACT_REACH_NODES`)."""
    from .reach import OVERHANG, OVERHANG_ALONG, reachable_height

    R = float(op.tool.radius)
    zf, dzf, rf = z.ravel(), dz.ravel(), reach.ravel()
    with np.errstate(invalid="ignore"):
        m = np.where(np.isfinite(rf), np.maximum(np.minimum(dzf, 0.0), rf), np.minimum(dzf, 0.0))
        ex = (zf - m) * scale_f - slack
    k = np.nonzero(ex > 0.0)[0]
    if not k.size:
        return 0
    k = k[np.argsort(-ex[k], kind="stable")[:MAX_EXACT_REACH_NODES]]
    i, j = np.unravel_index(k, z.shape)
    along = _finish_along(op.toolpath.points, op.toolpath.kinds)
    hang = (OVERHANG_ALONG * R if along == "x" else OVERHANG * R,
            OVERHANG_ALONG * R if along == "y" else OVERHANG * R)
    exact, _ = reachable_height(ws, i * stock.hx, j * stock.hy, R, overhang=hang)
    rf[k] = exact
    return int(k.size)


def verify_job(surface, operations, tolerance: float, *, spacing: float | None = None,
               scallop: float | None = None, depth_of_cut: dict | None = None,
               design: np.ndarray | None = None, measure: str = "normal") -> JobCut:
    """Simulate ``operations`` (Operation list, in order; toolpath points are tool tips,
    work mm; a toolpath's ``info["start"]`` is where its first move starts, else straight
    above its first point) on an uncut block and check each (see the module).

    surface: the design (Surface or WorkSurface; its stock_size_mm is the block)
    tolerance: mm; scallop: mm allowed above the design after finishing (default the
        finishing operation's info["scallop"], else 0)
    spacing: grid spacing, mm (default :func:`grid_spacing` of the tools)
    depth_of_cut: {kind: mm} allowed thickness an operation removes at a node
        (default each operation's info["depth_of_cut_mm"], else not checked)
    design: the clipped design at the nodes (computed when None)
    measure: "normal" | "vertical": how the material left after FINISHING is measured
        against the scallop (normal: the vertical height times 1 / sqrt(1 + |grad H|^2) of
        the design, its slope by central differences on the grid, like
        ``machining.scallop_measure``); roughing allowances are vertical heights
    """
    import time

    from ..finish.compensate import WorkSurface

    t0 = time.perf_counter()
    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    tol = float(tolerance)
    tools = [op.tool for op in operations]
    h = float(spacing) if spacing is not None else grid_spacing(tools, tol)
    stock = make_stock(ws.L, ws.W, h)
    dz = design_heights(ws, stock) if design is None else np.asarray(design, dtype=float)
    if dz.shape != stock.z.shape:
        raise ValueError(f"design grid {dz.shape} differs from the stock grid {stock.z.shape}")
    area = stock.hx * stock.hy
    if measure not in ("normal", "vertical"):
        raise ValueError(f"measure {measure!r}: normal or vertical")
    from .stock_kernels import node_bounds, node_verdicts, slope_grids

    dz = np.ascontiguousarray(dz, dtype=float)
    # numpy.gradient's differences of the design, one pass (stock_kernels.slope_grids, to the
    # bit): 1 / sqrt(1 + gx^2 + gy^2) for the normal measure, and the slope's norm, whose
    # 3 x 3 maximum is for all but the finish
    none = np.empty((0, 0))
    want_slope = any(op.kind != "finish" for op in operations)
    normal_scale = np.empty_like(dz) if measure == "normal" else none
    slope = np.empty_like(dz) if want_slope else none
    if normal_scale.size or slope.size:
        slope_grids(dz, stock.hx, stock.hy, normal_scale, slope)
    if not normal_scale.size:
        normal_scale = np.ones_like(dz)
    slope = _max3(slope, overwrite=True) if want_slope else None
    dzf, scale_f = dz.ravel(), np.ascontiguousarray(normal_scale, dtype=float).ravel()
    empty = np.empty(0)
    reports, snaps, failures = [], [], []
    for n, op in enumerate(operations, start=1):
        name = f"operation {n} ({op.kind}, {op.tool.describe()})"
        before = snaps[-1].z if snaps else stock.z.copy()     # the stock before it (snapshots are copies)
        tp = op.toolpath
        start = tp.info.get("start") if isinstance(tp.info, dict) else None
        if start is None and len(tp.points) and np.isfinite(tp.safe_z):
            # the first point is reached by a rapid from the safe height (path.Toolpath)
            start = np.array([tp.points[0, 0], tp.points[0, 1], max(float(tp.safe_z), tp.points[0, 2])])
        res = cut(stock, op.tool, tp.points, tp.kinds, start=start)
        snaps.append(stock.copy() if n < len(operations) else stock)   # the last: nothing cuts it after
        z = stock.z
        extra_v = extra_h = 0.0
        fin_doc = (depth_of_cut or {}).get("finish", op.info.get("finish_depth_of_cut_mm"))
        if op.kind == "finish":
            allowed = float(scallop if scallop is not None else op.info.get("scallop", 0.0))
            leave, cusp = 0.0, allowed
        elif op.kind == "rest" and fin_doc is not None:
            # rest passes cut only where the roughing tool could not reach: elsewhere its
            # staircase stays. What they owe the finish: at most the finishing tool's depth
            # of cut where their tool reaches (and never less than the allowance)
            leave = float(op.leave)
            cusp = max(float(fin_doc) - leave, 0.0)
        else:
            leave = float(op.leave)
            cusp = float(op.info.get("cusp_mm", op.info.get("stepdown_mm", 0.0)))
            # the planner's stated allowance error: vertical, and horizontal (times the slope)
            extra_v = float(op.info.get("allowance_excess_mm", 0.0))
            extra_h = float(op.info.get("allowance_offset_mm", 0.0))
        lo, hi = leave - tol, leave + cusp + extra_v + tol
        slack = cusp + tol + extra_v
        # per node (stock_kernels.node_bounds / node_verdicts, one pass each): the target is
        # design + leave, clipped at the top face (no material above it); the bounds hold
        # relative to the target: [T - tol, T + slack] - design, slack raised by extra_h x
        # the design's slope (3 x 3 maximum of its gradient's norm) for all but the finish.
        # Material above the bound is excused where the tool cannot reach the target: the
        # allowance then holds above the tool's reach (z - max(T, reach) <= slack). The
        # reach takes contacts at the nodes only: a flat bottom's rim or a corner touching
        # a wall between nodes is missed, the reach up to the slope x half a cell's
        # diagonal too low (not the finish's: its bound stays the chordal one). The finish
        # is measured with normal_scale, and judged where its ball can stand: its passes
        # end EDGE_NODES[-1] x R beyond the stock (passes.u_grid), as its own verification
        # judges it.
        finish = op.kind == "finish"
        slope_k = empty if finish else slope.ravel()
        high = np.empty(z.shape, dtype=np.bool_)
        zf, bf = z.ravel(), before.ravel()
        ig, gouge, irm, removed_max = node_bounds(zf, dzf, bf, scale_f, finish, slope_k, extra_h, slack, leave,
                                                  tol, high.ravel())
        gouge = float(gouge)
        if not high.any():
            # no node above its bound: the reach is asked nowhere (node_verdicts reads it at
            # the nodes above their bound only)
            reach = np.full(1, np.nan)
        elif finish:
            target = np.minimum(dz + leave, 0.0)
            from ..finish.scallop import EDGE_NODES

            reach = reach_height(target, stock, op.tool, high, beyond=float(EDGE_NODES[-1]) * op.tool.radius)
            # the finish is judged where its ball reaches the design (within the tolerance),
            # as its own verification judges it: its passes are spaced for the scallop on the
            # design, not on the ball's envelope over a groove narrower than the ball, where
            # the material left is the unreachable figure (a 3 mm ball over a groove of
            # curvature radius 0.3 mm: 0.07 mm above the envelope, 1.3 mm above the design)
            with np.errstate(invalid="ignore"):
                reach = np.where(reach > target + tol, np.inf, reach)
        else:
            target = np.minimum(dz + leave, 0.0)
            reach = reach_height(target, stock, op.tool, high)
        verdicts = node_verdicts(zf, dzf, scale_f, finish, slope_k, extra_h, slack, leave, tol, reach.ravel(),
                                 -1.0 if finish else math.hypot(stock.hx, stock.hy), high.ravel())
        if finish and verdicts[0]:
            # the grid's reach sees the design at the nodes only: beside a wall steeper than
            # the grid resolves (a rim between nodes) it lets the ball down too far. The
            # nodes it finds over their bound are judged again against the exact reach
            if _finish_reach_exact(ws, stock, op, z, dz, scale_f, slack, reach):
                verdicts = node_verdicts(zf, dzf, scale_f, finish, slope_k, extra_h, slack, leave, tol,
                                         reach.ravel(), -1.0, high.ravel())
        (n_over, over_max, over_k, n_unre, unre_max, unre_k, low_k, _low, min_left, max_left,
         il) = verdicts
        if il < 0:
            il, min_left, max_left = 0, 0.0, 0.0
        limit = None
        if depth_of_cut and op.kind in depth_of_cut:
            limit = float(depth_of_cut[op.kind])
        elif "depth_of_cut_mm" in op.info:
            limit = float(op.info["depth_of_cut_mm"])
        rep = OperationCut(
            kind=op.kind, tool=op.tool.describe(), max_gouge=max(gouge, 0.0) + 0.0, gouge_at=_at(stock, ig),
            min_left=float(min_left), max_left=float(max_left), left_at=_at(stock, il), bounds=(lo, hi),
            over_reachable=float(over_max) if n_over else 0.0,
            over_area=float(n_over * area),
            unreachable=float(unre_max) if n_unre else 0.0,
            unreachable_area=float(n_unre * area),
            over_at=_at(stock, over_k) if n_over else None,
            unreachable_at=_at(stock, unre_k) if n_unre else None,
            max_removed=float(removed_max), removed_at=_at(stock, irm),
            max_engagement=res.max_engagement, depth_of_cut_limit=limit, deepest_cut=res.deepest_cut,
            rapids_into_stock=res.rapids_into_stock, rapid_depth=res.rapid_depth, rapid_at=res.rapid_at,
            unlocated_low=res.unlocated_low, moves=res.moves, feeds=res.feeds)
        reports.append(rep)
        if rep.max_gouge > tol:
            failures.append(f"{name}: gouge {rep.max_gouge:.4f} mm at X{rep.gouge_at[0]:.3f} "
                            f"Y{rep.gouge_at[1]:.3f} (tolerance {tol:g} mm)")
        if op.kind != "finish" and low_k >= 0:
            k = int(low_k)
            above_k = z.flat[k] - dz.flat[k]
            lo_k = (np.minimum(dz.flat[k] + leave, 0.0) - dz.flat[k]) - tol
            failures.append(f"{name}: material left {float(above_k):.4f} mm at X{_at(stock, k)[0]:.3f} "
                            f"Y{_at(stock, k)[1]:.3f}, below the allowance's bound {float(lo_k):.4f} mm")
        if n_over:
            failures.append(f"{name}: material left {rep.over_reachable:.4f} mm above its bound ({hi:.4f} mm "
                            + (f"+ {extra_h:.4f} x the slope " if extra_h > 0 else "")
                            + f"above the design) where the tool reaches, at X{rep.over_at[0]:.3f} "
                            f"Y{rep.over_at[1]:.3f}, over {rep.over_area:.1f} mm^2")
        if limit is not None and op.kind == "rest":
            # rest passes cut in Z levels: what one move removes at a node is their depth of cut
            if rep.max_engagement > limit + 1e-9:
                failures.append(f"{name}: one move (number {res.engagement_at}) removes {rep.max_engagement:.3f} mm "
                                f"at a node, more than its depth of cut {limit:g} mm")
        elif limit is not None and rep.max_removed > limit + 1e-9:
            failures.append(f"{name}: removes {rep.max_removed:.3f} mm at X{rep.removed_at[0]:.3f} "
                            f"Y{rep.removed_at[1]:.3f}, more than its depth of cut {limit:g} mm")
        if rep.deepest_cut > op.tool.reach + 1e-9:
            failures.append(f"{name}: cuts {rep.deepest_cut:.3f} mm below the top face, deeper than the "
                            f"tool's reach {op.tool.reach:g} mm")
        if rep.rapids_into_stock:
            failures.append(f"{name}: {rep.rapids_into_stock} rapid(s) pass through the stock, up to "
                            f"{rep.rapid_depth:.3f} mm deep (at X{rep.rapid_at[0]:.3f} Y{rep.rapid_at[1]:.3f})")
        if rep.unlocated_low:
            failures.append(f"{name}: {rep.unlocated_low} move(s) below the top face from an unknown position")
    return JobCut(operations=reports, snapshots=snaps, design=dz, spacing=(stock.hx, stock.hy),
                  tolerance=tol, seconds=time.perf_counter() - t0, failures=failures)


# ----------------------------------------------------------------------------
# the picture
# ----------------------------------------------------------------------------
#: zlib level of the stock pictures: 3 encodes the paper's in half the time of the default 6
#: (0.011 against 0.025 s a picture) for 16 % more bytes
PNG_COMPRESS_LEVEL = 3
#: diverging colours: deep blue (gouge) - white (on the design) - deep orange (material left)
_GOUGE = np.array([33.0, 102.0, 172.0])
_LEFT = np.array([202.0, 86.0, 0.0])
_ZERO = np.array([247.0, 247.0, 247.0])


def _pool(a: np.ndarray, k: int, signed: bool):
    """Blocks of k x k nodes to one pixel: the value of largest magnitude (signed) or
    the mean (heights)."""
    nx, ny = a.shape
    mx, my = nx // k * k, ny // k * k
    if k == 1:
        return a
    b = a[:mx, :my].reshape(mx // k, k, my // k, k)
    if not signed:
        return b.mean(axis=(1, 3))
    hi, lo = b.max(axis=(1, 3)), b.min(axis=(1, 3))
    return np.where(-lo > hi, lo, hi)


def stock_png(stock: Stock, design: np.ndarray, *, title: str = "", tolerance: float = 0.0,
              left_max: float | None = None, gouge_max: float | None = None, width: int = 900,
              envelope: float = 1.5) -> bytes:
    """Top view of the simulated stock: the height field hill-shaded (light from the
    upper left, 45 degrees up) and coloured by its deviation from the design, blue where
    the stock is below it (gouge), orange where material is left, white on it, with a
    scale in mm. Each side of the scale is linear up to ``gouge_max`` / ``left_max``
    (default: the largest gouge, at least 2 x tolerance; the 99.5th percentile of the
    material left); a pixel shows the deviation of largest magnitude within ``envelope``
    mm of it (the height of the scallops there rather than stripes aliased from them; an
    isolated gouge stays visible). A scale clipped at either end says so (an arrow in the
    end's colour, the bound marked >= or <=, and the largest value and share beyond it);
    the legend shows the grey of a flat face on the design (the uncut top face), the scale's
    white as the hill shade lights it. PNG bytes (numpy, the window filters of :mod:`~fabkit.toolpath.cut.stock_kernels` and Pillow)."""
    from PIL import Image, ImageDraw, ImageFont

    from .stock_kernels import window_mean, window_minmax

    z = stock.z
    dev = z - np.asarray(design, dtype=float)
    nx, ny = z.shape
    k = max(1, int(math.ceil(max(nx / width, ny / (0.75 * width)))))
    # the colour is the local envelope of the deviation over ``envelope`` mm (scallops
    # finer than a pixel would alias into stripes): the highest material and the deepest
    # gouge within it, whichever is larger
    w = (max(1, int(round(envelope / stock.hx))) | 1, max(1, int(round(envelope / stock.hy))) | 1)
    zm = z if w == (1, 1) else window_mean(z, w)
    if k == 1:
        lo_env, hi_env = (dev, dev) if w == (1, 1) else window_minmax(dev, w)
        dv = np.where(-lo_env > hi_env, lo_env, hi_env)
        zz = zm
    else:                     # compiled: the blocks' extremes and means (_pool's, to the bit)
        from .stock_kernels import pool_envelope, pool_mean, pool_window_envelope

        dv, zz = np.empty((nx // k, ny // k)), np.empty((nx // k, ny // k))
        if w == (1, 1):
            pool_envelope(np.ascontiguousarray(dev), np.ascontiguousarray(dev), k, dv)
        elif not np.isnan(dev).any():      # the windows' envelope pooled in one pass (the same values)
            pool_window_envelope(np.ascontiguousarray(dev, dtype=float), k, w[0], w[1], dv)
        else:                              # a window of nan nodes only makes its block -inf
            lo_env, hi_env = window_minmax(dev, w)
            pool_envelope(np.ascontiguousarray(lo_env), np.ascontiguousarray(hi_env), k, dv)
        pool_mean(np.ascontiguousarray(zm, dtype=float), k, zz)
    hx, hy = stock.hx * k, stock.hy * k
    up = max(1, min(width // nx, int(0.75 * width) // ny)) if k == 1 else 1   # small grids: enlarged
    if up > 1:
        dv = np.repeat(np.repeat(dv, up, axis=0), up, axis=1)
        zz = np.repeat(np.repeat(zz, up, axis=0), up, axis=1)
        hx, hy = hx / up, hy / up
    # hill shade of the height field (smoothed over the envelope: the shape, not the scallops)
    gx, gy = np.gradient(zz, hx, hy)
    nrm = np.sqrt(1.0 + gx * gx + gy * gy)
    lx, ly, lz = -0.5, 0.5, math.sqrt(0.5)                     # from -X, +Y (upper left), 45 deg up
    shade = np.clip((-gx * lx - gy * ly + lz) / nrm, 0.0, 1.0)
    shade = 0.5 + 0.5 * shade
    gmax = gouge_max if gouge_max is not None else max(2.0 * tolerance, float(max(-dev.min(), 0.0)), 1e-6)
    pos = dev[dev > tolerance]
    lmax = left_max if left_max is not None else (float(np.percentile(pos, 99.5)) if pos.size else
                                                  max(2.0 * tolerance, 1e-6))
    lmax = max(lmax, 1e-6)

    def colour(d):
        d = np.asarray(d, float)
        tg = np.clip(-d / gmax, 0.0, 1.0)[..., None]
        tl = np.clip(d / lmax, 0.0, 1.0)[..., None]
        return np.where(d[..., None] < 0, _ZERO + (_GOUGE - _ZERO) * tg, _ZERO + (_LEFT - _ZERO) * tl)

    if np.isfinite(dv).all() and np.isfinite(shade).all():
        from .stock_kernels import shaded_rgb

        # colour(dv) x shade, rounded, clipped, rows +Y up: compiled, the same bytes
        plot = np.empty((dv.shape[1], dv.shape[0], 3), np.uint8)
        shaded_rgb(np.ascontiguousarray(dv, dtype=float), np.ascontiguousarray(shade, dtype=float), float(gmax),
                   float(lmax), _ZERO, _GOUGE, _LEFT, plot)
    else:
        rgb = colour(dv) * shade[..., None]
        plot = np.clip(np.rint(rgb), 0, 255).astype(np.uint8).transpose(1, 0, 2)[::-1]  # rows: +Y up
    ph, pw = plot.shape[:2]
    left, top, bottom, right = 60, 34, 86, 30
    img = np.full((top + ph + bottom, left + pw + right, 3), 255, np.uint8)
    img[top:top + ph, left:left + pw] = plot
    # the scale: gouge_max ... 0 ... left_max
    bw = max(60, min(pw - 152, 520))     # room beside the bar for its end labels (and arrows)
    bx0, by0 = left + (pw - bw) // 2, top + ph + 34
    half = bw // 2
    tb = np.concatenate([-np.linspace(1, 0, half) * gmax, np.linspace(0, 1, bw - half) * lmax])
    img[by0:by0 + 14, bx0:bx0 + bw] = np.clip(np.rint(colour(tb)), 0, 255).astype(np.uint8)[None, :, :]
    im = Image.fromarray(img)
    dr = ImageDraw.Draw(im)
    font = ImageFont.load_default()
    dr.rectangle([left - 1, top - 1, left + pw, top + ph], outline=(0, 0, 0))
    dr.rectangle([bx0 - 1, by0 - 1, bx0 + bw, by0 + 14], outline=(0, 0, 0))
    head = (f"{title}: " if title else "") + "simulated stock, coloured by deviation from the design"
    dr.text((left, 10), head, fill=(0, 0, 0), font=font)
    dr.text((left, top + ph + 4), f"X 0 .. {stock.L:g} mm, Y 0 .. {stock.W:g} mm; grid {nx} x {ny} at "
            f"{stock.hx:.3g} mm; largest gouge {max(-dev.min(), 0.0) + 0.0:.4f} mm, most material left "
            f"{max(dev.max(), 0.0) + 0.0:.4f} mm (vertical)", fill=(0, 0, 0), font=font)
    # a scale clipped at either end says so: an arrow in the end's colour beyond the bar (the
    # deviations past it are drawn in that colour) and the largest value it stands for
    gouge_all, left_all = max(-float(dev.min()), 0.0), max(float(dev.max()), 0.0)
    over_lo, over_hi = gouge_all > gmax * (1 + 1e-9), left_all > lmax * (1 + 1e-9)
    for clipped, x_end, d, val in ((over_lo, bx0 - 1, -1, -gmax), (over_hi, bx0 + bw, 1, lmax)):
        if clipped:
            tip = x_end + d * 12
            dr.polygon([(x_end, by0 - 1), (tip, by0 + 7), (x_end, by0 + 15)],
                       fill=tuple(int(c) for c in np.clip(np.rint(colour(val)), 0, 255)), outline=(0, 0, 0))
    for val, u in ((-gmax, bx0), (0.0, bx0 + half), (lmax, bx0 + bw)):
        dr.line([(u, by0 + 14), (u, by0 + 18)], fill=(0, 0, 0))
        label = f"{val:+.3g}" if val else "0"
        if (val < 0 and over_lo) or (val > 0 and over_hi):
            label = ("<= " if val < 0 else ">= ") + label
        dr.text((u - 3 * len(label), by0 + 20), label, fill=(0, 0, 0), font=font)
    dr.text((bx0 - 2 - 6 * 20 - (14 if over_lo else 0), by0 + 2), "below design (gouge)", fill=(0, 0, 0), font=font)
    dr.text((bx0 + bw + 6 + (14 if over_hi else 0), by0 + 2), "material left", fill=(0, 0, 0), font=font)
    dr.text((bx0 + half - 60, by0 + 32), "stock - design (mm)", fill=(0, 0, 0), font=font)
    # every colour the picture uses: the scale's, hill-shaded; the flat faces (the uncut top
    # face above all) show the scale's colour as lit flat, the on-design white as this grey
    flat = 0.5 + 0.5 * lz
    grey = tuple(int(c) for c in np.clip(np.rint(_ZERO * flat), 0, 255))
    dr.rectangle([left, by0 + 32, left + 12, by0 + 44], fill=grey, outline=(0, 0, 0))
    dr.text((left + 16, by0 + 32), "flat, on the design (top face)", fill=(0, 0, 0), font=font)
    notes = []
    if over_lo:
        notes.append(f"{100.0 * float(np.mean(dev < -gmax)):.2g} % below, to {-gouge_all:+.4g}")
    if over_hi:
        notes.append(f"{100.0 * float(np.mean(dev > lmax)):.2g} % above, to {left_all:+.4g}")
    if notes:
        note = "clipped: " + "; ".join(notes) + " mm"
        dr.text((img.shape[1] - 4 - dr.textlength(note, font=font), by0 + 32), note, fill=(0, 0, 0), font=font)
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=False, compress_level=PNG_COMPRESS_LEVEL)
    return buf.getvalue()
