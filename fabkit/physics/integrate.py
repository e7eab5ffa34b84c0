"""fabkit's launch integrator: the public API (``launch_batch``, ``launch_stream``).

Every model (``full``, ``simplified`` and the finite ``ball``) runs on the compiled
engine (:mod:`fabkit.physics.engine`): one launch wholly in compiled code, each
with its own step, so a launch's result is bit-identical whatever the batch it is
in, its chunking, the number of threads or worker processes.

Method
------
An embedded explicit Runge-Kutta pair (default Dormand-Prince 8(5,3), the method
of scipy's ``DOP853``; ``method='RK45'`` gives Dormand-Prince 5(4)) with scipy's
error norm, step-size control and initial step (so tolerances mean the same);
tableaux from scipy's own coefficients (:mod:`fabkit.physics.rk`). The model is a
template of the engine (``engine/point.py``, ``engine/ball.py``); the step loop and
the events are shared (``engine/dop853.py``).

State per launch: (x, y, xd, yd, W) for the point models, (x, y, xd, yd, u, W) for
the ball ((x, y) its contact point, u its spin about the normal), with W the energy
dissipated by damping (it gives the energy-balance error; not in the error norm).

Events (checked on every accepted step, from its start and end states):

    bounce        xd crosses from + to -: a maximum of x(t). Located by Henon's trick:
                  one extra RK step from the step's start with xd as the independent
                  variable, to xd = 0 exactly. Not terminal; the first K times are kept.
    escaped       x crosses ``start`` moving toward -x. Henon step with x as the
                  independent variable to x = start exactly; v_out = |xd| there (the
                  ball: the centre's |x-velocity|). A step over which xd turns from - to
                  + (a minimum of x inside it) is checked too: the minimum is located
                  (Henon step to xd = 0) and where it lies at or beyond the start line, the
                  crossing before it by regula falsi on re-taken steps, so an excursion
                  beyond the line shorter than a step (a few micrometres, for a
                  millisecond) is an escape.
    flew_off      h(x, y) reaches top - margin (Henon step in z), or x or y leaves the
                  footprint shrunk by the margin (Henon step in x or y).
    lost_contact  (full model) the normal-force bracket B of eq. (xyODE) falls to 0 or
                  below; located by secant iterations on re-taken RK steps. The ball:
                  its guard min(N / (m g), 1 - r kappa_1, friction - |F_t| / N) falls
                  to 0 (``lost_contact``, ``bridged`` or ``slipped``), located to rounding
                  by Illinois iterations on re-taken steps.
    captured      still on the surface at ``t_max`` (including launches too slow to
                  arrive anywhere, and runs stopped by the step guard, ``status`` 1), or
                  with ``problem.stop_trapped`` its energy fell below every exit (status 4).

Where Henon's step fails (the event's quantity turns inside the step, as in one
long step holding a bounce and the escape), the event is located by Illinois
regula falsi on re-taken steps. Every event is as accurate as a step (it carries
the step's own local error), so bounce times and v_out carry the integrator's
tolerance.

Stiff cases: where the damping rate times ``t_max`` is so large that the explicit
method would need more than ``STIFF_STEPS`` stability-bound steps (mu above about
200 1/s at t_max = 60 s), the launches go to scipy's implicit Radau method (one launch
at a time, about a second each, same events), ``status`` 2.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from ..tolerances import DEFAULT
from .models import CAPTURED, MODELS, OUTCOMES
from .rk import tableau
from .trap import trap_energy

CHUNK = 16384         # launches per chunk of launch_stream (memory bound; results do not depend on it)
K_BOUNCES = 16        # bounce times kept per launch
STIFF_STEPS = 2_000   # stability-bound explicit steps beyond which a damped problem goes to Radau
#: right-hand-side evaluations one batch of implicit (Radau) launches may take, about 10 minutes
#: of CPU at the ~3600 evaluations/s measured on the paper's surface; a batch whose first launch
#: says it would take more is refused up front (deterministic: it counts evaluations, not time)
STIFF_EVALUATIONS = 2_000_000


# ----------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------
@dataclass
class LaunchResult:
    """Per-launch summaries, arrays of shape (N,) unless stated.

    outcome       int8, index into ``models.OUTCOMES``
    bounces       int, maxima of x(t) before the end
    v_out         |xd| at the escape crossing, design units/s (nan unless escaped)
    bounce_times  (N, K) the first K bounce times, s (nan padded)
    t_end, x_end, y_end, vx_end, vy_end   the final state (at the event that ended the run)
    max_z, max_abs_y   the largest height and |y| over the step points
    energy_error  |E(t_end) + W(t_end) - E(0)| / (E_kin(0) + g~ (z_max - z_min)): the
                  relative energy drift (undamped) or energy-balance error (damped, W =
                  dissipated energy); the scale is the largest kinetic energy the run can reach
    steps, rejected   accepted and rejected steps per launch
    status        0 normal, 1 stopped by the step guard (outcome captured), 2 stiff: run by Radau,
                  3 derivatives overflow at the launch (flew_off), 4 captured before t_max: its
                  energy fell below the trapping energy (``problem.stop_trapped``, see trap.py)
    trajectories  with record=True: per launch a dict of arrays t, x, y, vx, vy, ax, ay
    """

    v_in: np.ndarray
    outcome: np.ndarray
    bounces: np.ndarray
    v_out: np.ndarray
    bounce_times: np.ndarray
    t_end: np.ndarray
    x_end: np.ndarray
    y_end: np.ndarray
    vx_end: np.ndarray
    vy_end: np.ndarray
    max_z: np.ndarray
    max_abs_y: np.ndarray
    energy_error: np.ndarray
    max_slip: np.ndarray
    steps: np.ndarray
    rejected: np.ndarray
    status: np.ndarray
    method: str = "DOP853"
    rtol: float = 1e-10
    atol: float = 1e-12
    seconds: float = 0.0
    trajectories: list | None = field(default=None, repr=False)

    @property
    def outcome_names(self) -> list[str]:
        return [OUTCOMES[i] for i in self.outcome]

    def __len__(self) -> int:
        return len(self.v_in)


_FIELDS = ("outcome", "bounces", "v_out", "bounce_times", "t_end", "x_end", "y_end", "vx_end", "vy_end",
           "max_z", "max_abs_y", "energy_error", "max_slip", "steps", "rejected", "status")


def _empty(n: int, k: int) -> dict:
    nan = np.full(n, np.nan)
    return {
        "outcome": np.full(n, CAPTURED, dtype=np.int8), "bounces": np.zeros(n, dtype=np.int64),
        "v_out": nan.copy(), "bounce_times": np.full((n, k), np.nan), "t_end": nan.copy(),
        "x_end": nan.copy(), "y_end": nan.copy(), "vx_end": nan.copy(), "vy_end": nan.copy(),
        "max_z": nan.copy(), "max_abs_y": nan.copy(), "energy_error": nan.copy(), "max_slip": nan.copy(),
        "steps": np.zeros(n, dtype=np.int64), "rejected": np.zeros(n, dtype=np.int64),
        "status": np.zeros(n, dtype=np.int8),
    }


# ----------------------------------------------------------------------------
# stiff path
# ----------------------------------------------------------------------------
def stiffness_rate(problem) -> float:
    """An upper estimate of the damping rate (1/s) that limits an explicit step."""
    rate = float(problem.damping)
    if problem.nonlinear_damping:
        xs = np.linspace(problem.x_range[0], problem.x_range[1], 401) if np.all(
            np.isfinite(problem.x_range)) else np.linspace(-10, 10, 401)
        F = problem.fns.grad(xs, np.zeros_like(xs))[1]
        ym = max(abs(problem.y_range[0]), abs(problem.y_range[1])) if np.all(
            np.isfinite(problem.y_range)) else 10.0
        rate += float(problem.nonlinear_damping) * float(np.nanmax(F * F)) * ym * ym
    return rate


def is_stiff(problem, t_max: float) -> bool:
    """True when the explicit method's step is bounded by stability against the damping
    (|h mu| <= ~6 for DOP853) for more than STIFF_STEPS steps: then scipy's implicit
    Radau is cheaper per launch. Measured for one launch at mu = 3000 1/s, t_max = 60 s:
    explicit 18 s, Radau 0.7 s. The choice depends on the problem only (not on the batch
    size), so results stay identical for any batching."""
    return stiffness_rate(problem) * t_max / 6.0 > STIFF_STEPS


def _run_stiff(problem, v_in, y0, vy0, rtol, atol, t_max, k_keep):
    from .reference import solve_launch

    n = len(v_in)
    out = _empty(n, k_keep)
    for i in range(n):
        r = solve_launch(problem, float(v_in[i]), float(y0[i]), float(vy0[i]), method="Radau",
                         rtol=max(rtol, 1e-10), atol=max(atol, 1e-12), t_max=t_max)
        if i == 0 and n > 1 and r["nfev"] * n > STIFF_EVALUATIONS:
            from ..errors import DesignError

            raise DesignError(
                f"the damping makes every launch stiff (simulation.damping {problem.damping:g} 1/s, "
                f"simulation.nonlinear_damping {problem.nonlinear_damping:g}): the first launch took {r['nfev']} "
                f"evaluations of the implicit solver, so {n} launches would take about {r['nfev'] * n:.2g}, over "
                f"the budget of {STIFF_EVALUATIONS:.2g} (about 10 minutes); lower the damping or the number of "
                f"launches (ramp.samples, --v-in N)")
        out["outcome"][i] = OUTCOMES.index(r["outcome"])
        out["bounces"][i] = r["bounces"]
        tb = np.asarray(r["bounce_times"])[:k_keep]
        out["bounce_times"][i, :len(tb)] = tb
        out["v_out"][i] = r["v_out"]
        out["t_end"][i] = r["t_end"]
        out["x_end"][i], out["y_end"][i] = r["x_end"], r["y_end"]
        out["vx_end"][i], out["vy_end"][i] = r["xdot_end"], r["ydot_end"]
        out["max_z"][i], out["max_abs_y"][i] = r["max_z"], r["max_abs_y"]
        out["energy_error"][i] = np.nan  # the Radau path does not track the dissipated work
        out["max_slip"][i] = r.get("max_slip", np.nan)
        out["steps"][i] = r["nfev"]
        out["status"][i] = 2
    return out


# ----------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------
def _lanes(values, n, name):
    if values is None:
        return None
    a = np.asarray(values, dtype=float)
    a = np.broadcast_to(a, (n,)) if a.ndim == 0 or a.shape == (1,) else a
    if a.shape != (n,):
        raise SpecError(f"must be a number or one value per launch ({n}), got shape {a.shape}", key=name)
    if not np.all(np.isfinite(a)):
        raise SpecError("must be finite", key=name)
    return np.ascontiguousarray(a, dtype=float)


def _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol):
    """Validated lanes and tolerances: (v (N,), y0 (N,), vy0 (N,), rtol, atol, t_max)."""
    v = np.atleast_1d(np.asarray(v_in, dtype=float)).ravel()
    n = v.size
    if n > tol.max_launches:
        raise SpecError(f"too many launches: {n} (limit {tol.max_launches})", key="v_in")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise SpecError("entry speeds must be finite and >= 0", key="v_in")
    y0a = _lanes(problem.y0 if y0 is None else y0, n, "y0")
    vy0a = _lanes(problem.vy0 if vy0 is None else vy0, n, "vy0")
    rtol = float(problem.rtol if rtol is None else rtol)
    atol = float(problem.atol if atol is None else atol)
    t_max = float(problem.t_max if t_max is None else t_max)
    if not (rtol > 0 and atol > 0 and t_max > 0):
        raise SpecError("rtol, atol and t_max must be > 0", key="simulation")
    return v, y0a, vy0a, rtol, atol, t_max


def launch_stream(problem, v_in, y0=None, vy0=None, *, rtol: float | None = None, atol: float | None = None,
                  t_max: float | None = None, max_bounces: int = K_BOUNCES, method: str = "DOP853",
                  chunk: int = CHUNK, tol=DEFAULT):
    """Like :func:`launch_batch`, but yields one :class:`LaunchResult` per chunk of at
    most ``chunk`` launches, in order, as each finishes.

    For studies of any size: memory is bounded by one chunk (plus the N input
    speeds), whatever N; a caller writes or reduces each chunk and lets it go. Each
    launch's result is bit-identical to :func:`launch_batch` (lanes do not interact).
    """
    v, y0a, vy0a, rtol, atol, t_max = _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol)
    chunk = max(1, int(chunk))
    for a in range(0, v.size, chunk):
        b = min(a + chunk, v.size)
        yield launch_batch(problem, v[a:b], y0a[a:b], vy0a[a:b], rtol=rtol, atol=atol, t_max=t_max,
                           max_bounces=max_bounces, method=method, workers=1, chunk=chunk, tol=tol)


_JOB = None


def _run_job(ab):
    return _JOB(ab)


def _fork_pool(workers: int):
    """A process pool by fork (None where fork is unavailable)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    import threading

    # fork only from a single-threaded main program (forking a threaded process, e.g. a
    # Dask worker, can deadlock): elsewhere the chunks run serially
    if "fork" not in mp.get_all_start_methods() or threading.active_count() > 1 \
            or threading.current_thread() is not threading.main_thread():
        return None
    try:
        return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"))
    except (OSError, ValueError):
        return None


def launch_batch(problem, v_in, y0=None, vy0=None, *, rtol: float | None = None, atol: float | None = None,
                 t_max: float | None = None, max_bounces: int = K_BOUNCES, record: bool = False,
                 progress=None, method: str = "DOP853", workers: int | None = None,
                 chunk: int = CHUNK, tol=DEFAULT) -> LaunchResult:
    """Launch N balls at x = ``problem.start`` with xd = ``v_in`` (N,), y = ``y0``, yd = ``vy0``.

    Parameters
    ----------
    problem : models.Problem
    v_in : (N,) entry speeds, design units/s (>= 0)
    y0, vy0 : scalars or (N,): transverse offset and speed (default problem.y0, problem.vy0)
    rtol, atol : tolerances (default problem.rtol, problem.atol: 1e-10, 1e-12)
    t_max : time limit, s (default problem.t_max)
    max_bounces : K, bounce times kept per launch (>= 8)
    record : keep each launch's step points (for plots; only for small N)
    progress : callable(done, total) called as launches finish (at most 5 times a second,
               and once at the end of each chunk)
    method : 'DOP853' (default) or 'RK45'
    workers : threads over blocks of launches on the compiled engine (default 1); for
              the stiff Radau path, forked processes over chunks (only from a
              single-threaded main program, else serial); results do not depend on it
    chunk : launches per chunk of the stiff path (results do not depend on it)

    Returns a :class:`LaunchResult`. Accuracy: each launch is integrated to the
    given tolerances; events are located to the same accuracy (see the module doc).
    """
    t0 = time.perf_counter()
    v, y0a, vy0a, rtol, atol, t_max = _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol)
    n = v.size
    k_keep = max(8, int(max_bounces))
    tableau(method)   # refuses an unknown method
    max_steps = int(tol.max_sim_steps)
    if record and n > 64:
        raise SpecError(f"record=True keeps every step: at most 64 launches, got {n}", key="v_in")
    stiff = is_stiff(problem, t_max)
    if not stiff:
        # every model runs on the compiled engine (fabkit/physics/engine)
        out = _run_engine(problem, v, y0a, vy0a, rtol, atol, t_max, max_steps, method, record, k_keep,
                          progress, 1 if workers is None else int(workers))
        trajs = out.pop("_traj", None)
        return LaunchResult(v_in=v, **out, method=method, rtol=rtol, atol=atol,
                            seconds=time.perf_counter() - t0, trajectories=trajs)

    # the stiff path: scipy's Radau, one launch at a time, in chunks (processes with workers > 1)
    chunk = max(1, int(chunk))
    workers = 1 if workers is None else int(workers)
    n_chunks = max(1, math.ceil(n / chunk))
    bounds = np.linspace(0, n, n_chunks + 1).round().astype(int)
    pieces = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]

    def job(ab):
        a, b = ab
        return _run_stiff(problem, v[a:b], y0a[a:b], vy0a[a:b], rtol, atol, t_max, k_keep)

    results = []
    done = 0
    pool = None
    if workers > 1 and len(pieces) > 1 and not record:
        pool = _fork_pool(workers)
    if pool is not None:
        # Processes: scipy's Radau holds the GIL. Forked workers inherit the problem (its
        # compiled functions do not pickle); only the per-launch summaries come back.
        global _JOB
        _JOB = job
        try:
            with pool:
                for (a, b), r in zip(pieces, pool.map(_run_job, pieces)):
                    results.append(r)
                    done += b - a
                    if progress is not None:
                        progress(done, n)
        finally:
            _JOB = None
    else:
        for a, b in pieces:
            results.append(job((a, b)))
            done += b - a
            if progress is not None:
                progress(done, n)

    if not results:
        merged = _empty(0, k_keep)
    else:
        merged = {f: np.concatenate([r[f] for r in results]) for f in _FIELDS}
    return LaunchResult(v_in=v, **merged, method="Radau", rtol=rtol, atol=atol,
                        seconds=time.perf_counter() - t0, trajectories=[] if record else None)


ENGINE_MODELS = MODELS   # models the compiled engine serves: all of them


def _run_engine(problem, v, y0, vy0, rtol, atol, t_max, max_steps, method, record, k_keep, progress,
                threads):
    """All the launches on the compiled engine (engine/): the per-launch summary dict."""
    from .engine import batch

    n = v.size
    eng = batch.engine(problem)
    e_star = trap_energy(problem, 100.0 * rtol) if problem.stop_trapped else None
    last = [0.0]

    def tick(done):  # at most 5 times a second, and at the end
        now = time.perf_counter()
        if now - last[0] >= 0.2 or done >= n:
            last[0] = now
            progress(done, n)

    FO, IO, BT, trajs = batch.run(eng, problem, v, y0, vy0, rtol=rtol, atol=atol, t_max=t_max,
                                  max_steps=max_steps, k_keep=k_keep, method=method, record=record,
                                  e_star=e_star, threads=max(1, threads),
                                  progress=tick if progress is not None else None)
    if progress is not None and n == 0:
        progress(0, 0)
    out = {
        "outcome": IO[:, 0].astype(np.int8), "bounces": IO[:, 1].copy(), "v_out": FO[:, 0].copy(),
        "bounce_times": BT, "t_end": FO[:, 1].copy(), "x_end": FO[:, 2].copy(), "y_end": FO[:, 3].copy(),
        "vx_end": FO[:, 4].copy(), "vy_end": FO[:, 5].copy(), "max_z": FO[:, 6].copy(),
        "max_abs_y": FO[:, 7].copy(), "energy_error": FO[:, 8].copy(), "max_slip": FO[:, 9].copy(),
        "steps": IO[:, 2].copy(), "rejected": IO[:, 3].copy(), "status": IO[:, 4].astype(np.int8),
    }
    if record:
        out["_traj"] = trajs
    return out


def simulate_one(problem, v_in: float, record: bool = True, **kw) -> dict:
    """One launch as a dict of plain values (and its trajectory when ``record``)."""
    r = launch_batch(problem, [float(v_in)], record=record, workers=1, **kw)
    nb = int(r.bounces[0])
    bt = r.bounce_times[0]
    out = {
        "outcome": OUTCOMES[int(r.outcome[0])],
        "bounces": nb,
        "bounce_times": [float(b) for b in bt[: min(nb, bt.size)]],
        "v_out": float(r.v_out[0]),
        "t_end": float(r.t_end[0]),
        "x_end": float(r.x_end[0]), "y_end": float(r.y_end[0]),
        "vx_end": float(r.vx_end[0]), "vy_end": float(r.vy_end[0]),
        "max_height": float(r.max_z[0]),
        "max_abs_y": float(r.max_abs_y[0]),
        "energy_error": float(r.energy_error[0]),
        "max_slip": float(r.max_slip[0]),
        "steps": int(r.steps[0]), "rejected": int(r.rejected[0]), "status": int(r.status[0]),
        "method": r.method, "rtol": r.rtol, "atol": r.atol,
    }
    if record and r.trajectories:
        out["trajectory"] = r.trajectories[0]
    return out
