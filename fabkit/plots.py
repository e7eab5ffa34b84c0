"""Matplotlib figures (Agg), returned as bytes; the caller writes them atomically.

Imported only when a plot is asked for. A flat module of functions, one per figure.
Each takes ``fmt``: the file format the output's extension names (png, pdf, svg,
jpg, ...; see :data:`fabkit.commands._common.PLOT_FORMATS`); metadata that would
carry a date is left out, so the same data gives the same bytes.
"""

from __future__ import annotations

import io

import numpy as np

from .physics.outcomes import ESCAPED, OUTCOMES, Outcome


class _Figures:
    """What the figures' callers use of pyplot: ``close(fig)`` (a figure made here is
    held by nothing else: closing it releases its canvas)."""

    @staticmethod
    def close(fig) -> None:
        fig.clear()


def new_figure(**kw):
    """(closer, Figure) on the Agg canvas, without pyplot (whose import and figure
    manager cost 0.15-0.2 s of CPU more; the same renderer, the same bytes)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kw)
    FigureCanvasAgg(fig)
    return _Figures, fig


#: metadata that would change from run to run or name the software version, per format
_NO_STAMP = {"png": {"Software": None}, "pdf": {"CreationDate": None, "Producer": None, "Creator": None},
             "svg": {"Date": None, "Creator": None}, "eps": {"CreationDate": None, "Creator": None},
             "ps": {"CreationDate": None, "Creator": None}}


def png_bytes(plt, fig, fmt: str = "png") -> bytes:
    """The figure as bytes in ``fmt`` (the name is historical: png by default)."""
    fmt = {"jpeg": "jpg", "tif": "tiff"}.get(fmt, fmt)
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=120, metadata=_NO_STAMP.get(fmt))
    plt.close(fig)
    return buf.getvalue()


_figure, _png = new_figure, png_bytes      # the names this module's figures use


def hermite_samples(traj: dict, n: int = 2000) -> dict:
    """Dense samples of a recorded trajectory: cubic Hermite between the step points
    (positions from positions and velocities, velocities from velocities and
    accelerations). Accurate to plotting precision, not to the integrator's."""
    t = np.asarray(traj["t"], dtype=float)
    if t.size < 2:
        return {k: np.asarray(v, dtype=float) for k, v in traj.items()}
    ts = np.linspace(t[0], t[-1], n)
    i = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, t.size - 2)
    h = t[i + 1] - t[i]
    s = np.where(h > 0, (ts - t[i]) / np.where(h > 0, h, 1.0), 0.0)
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2

    def herm(p, d):
        p, d = np.asarray(p, dtype=float), np.asarray(d, dtype=float)
        return h00 * p[i] + h10 * h * d[i] + h01 * p[i + 1] + h11 * h * d[i + 1]

    return {"t": ts, "x": herm(traj["x"], traj["vx"]), "y": herm(traj["y"], traj["vy"]),
            "vx": herm(traj["vx"], traj["ax"]), "vy": herm(traj["vy"], traj["ay"])}


def trajectory_png(traj: dict, summary: dict, *, title: str = "", units: str = "", fmt: str = "png") -> bytes:
    """x(t) and y(t) of one launch with its bounces marked (the paper's trajectory figure)."""
    plt, fig = _figure(figsize=(8, 5.5))
    d = hermite_samples(traj) if traj else {"t": np.zeros(1), "x": np.zeros(1), "y": np.zeros(1)}
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    ax1.plot(d["t"], d["x"], lw=1.2, color="C0")
    ax2.plot(d["t"], d["y"], lw=1.2, color="C1")
    for k, tb in enumerate(summary.get("bounce_times", [])):
        for a in (ax1, ax2):
            a.axvline(tb, color="0.5", lw=0.8, ls="--", label="bounce" if (k == 0 and a is ax1) else None)
    ax1.set_ylabel(f"x ({units})" if units else "x")
    ax2.set_ylabel(f"y ({units})" if units else "y")
    ax2.set_xlabel("t (s)")
    out = summary.get("outcome", "")
    extra = f", v_out = {summary['v_out']:.4g} {units + '/s' if units else ''}".rstrip() if out == OUTCOMES[ESCAPED] else ""
    ax1.set_title(f"{title}\n{out}, {summary.get('bounces', 0)} bounce(s){extra}", fontsize=10)
    if summary.get("bounce_times"):
        ax1.legend(loc="best", fontsize=8)
    for a in (ax1, ax2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    return _png(plt, fig, fmt)


#: one marker and colour per outcome of a launch that does not escape (escaped
#: launches are coloured by bounce count); the same everywhere a figure shows outcomes
#: (sweep, robustness, design, compare): captured is grey, one bounce black
OUTCOME_STYLE = {Outcome.CAPTURED: ("x", "0.6"), Outcome.FLEW_OFF: ("^", "tab:orange"),
                 Outcome.LOST_CONTACT: ("v", "tab:cyan"), Outcome.BRIDGED: ("s", "tab:pink"),
                 Outcome.SLIPPED: ("D", "darkgoldenrod")}
#: escaped launches by bounce count, as the seed paper's Fig. 1 colours them
BOUNCE_COLOURS = {1: "black", 2: "tab:blue", 3: "tab:green", 4: "tab:red"}
MANY_BOUNCES = "tab:brown"
CAPTURED_COLOUR = OUTCOME_STYLE[Outcome.CAPTURED][1]


def sweep_figure(result: dict, title: str = "", *, units: str = "", fmt: str = "png",
                 speed_units: str | None = None) -> bytes:
    """v_out against v_in (the paper's Fig. 1 for the apparatus): escaped launches
    coloured by bounce count; below, on the same v_in axis, one row per outcome
    without a v_out (captured, flew_off, lost_contact), each its own marker;
    v_critical marked with its value, error and unit."""
    plt, fig = _figure(figsize=(8.5, 5), dpi=120)
    vu = speed_units or (f"{units}/s" if units else "design units/s")   # speed_units: e.g. "c" (phi^4)
    v = np.asarray(result["v_in"], dtype=float)
    vo = np.asarray([np.nan if x is None else x for x in result["v_out"]], dtype=float)
    nb = np.asarray(result["bounces"])
    outcome = np.asarray(result["outcome"], dtype=object)
    esc = outcome == OUTCOMES[ESCAPED]
    other = sorted(set(outcome[~esc].tolist()),
                   key=lambda o: list(OUTCOME_STYLE).index(o) if o in OUTCOME_STYLE else 99)
    if other:
        gs = fig.add_gridspec(2, 1, height_ratios=[5, 0.5 + 0.35 * len(other)], hspace=0.08)
        ax = fig.add_subplot(gs[0])
        strip = fig.add_subplot(gs[1], sharex=ax)
    else:
        ax, strip = fig.add_subplot(1, 1, 1), None
    for n in sorted(set(nb[esc].tolist())):
        m = esc & (nb == n)
        label = f"escaped after {n} bounce{'s' if n != 1 else ''}" if n <= 4 else None
        ax.plot(v[m], vo[m], "o", ms=2.5, color=BOUNCE_COLOURS.get(n, MANY_BOUNCES), label=label)
    if (esc & (nb > 4)).any():
        ax.plot([], [], "o", ms=2.5, color=MANY_BOUNCES, label="escaped after 5+ bounces")
    handles = []
    for k, o in enumerate(other):
        m = outcome == o
        marker, colour = OUTCOME_STYLE.get(o, ("s", "tab:olive"))
        strip.plot(v[m], np.full(m.sum(), k), marker, ms=4, color=colour, ls="none")
        handles.append(ax.plot([], [], marker, ms=4, color=colour, ls="none",
                               label=f"{o.replace('_', ' ')} ({m.sum()} launches, no v_out: lower panel)")[0])
    vc = result.get("v_critical")
    if vc is not None:
        err = result.get("v_critical_error")
        pm = f" ± {err:.1e}" if err else ""
        for a in (ax, strip) if strip is not None else (ax,):
            a.axvline(vc, color="tab:orange", lw=1, ls="--",
                      label=f"v_critical = {vc:.5g}{pm} {vu}" if a is ax else None)
    ax.set_ylabel(f"v_out, exit speed ({vu})")
    xlabel = f"v_in, entry speed ({vu})"
    if strip is not None:
        strip.set_yticks(range(len(other)), [o.replace("_", " ") for o in other], fontsize=8)
        strip.set_ylim(-0.6, len(other) - 0.4)
        strip.set_xlabel(xlabel)
        strip.grid(alpha=0.3, axis="x")
        ax.tick_params(labelbottom=False)
    else:
        ax.set_xlabel(xlabel)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.09, right=0.64, top=0.93, bottom=0.1)
    return _png(plt, fig, fmt)


def explore_figure(result: dict, keys: list[str], *, title: str = "", units: str = "", fmt: str = "png") -> bytes:
    """PNG bytes for ``fabkit explore``: v_critical (with its error bar) and the
    two-bounce windows (vertical bars lo..hi) against the first varied key, one
    series per value of the other keys; filled markers safe, hollow unsafe. A design
    without a v_critical is a triangle at the bottom of the upper panel; a panel with
    nothing to show says why."""
    plt, fig = _figure(figsize=(8, 6))
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2, sharex=ax1)
    designs = [d for d in result["designs"] if "error" not in d]
    xkey = keys[0] if keys else None
    series: dict = {}
    all_x: list = []
    missing = False
    bottom = ax1.get_xaxis_transform()          # x in data, y in axes fraction
    for i, d in enumerate(designs):
        rest = tuple((kk, d["params"][kk]) for kk in keys[1:])
        series.setdefault(rest, []).append((i, d))
    # a choice key (simulation.model=full,ball) is categorical: one tick per value, no line
    # joining the values, as if they were points on a numeric axis
    values = [d["params"][xkey] for d in designs] if xkey else []
    categories = list(dict.fromkeys(values)) if values and not all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in values) else None
    for s, (rest, items) in enumerate(sorted(series.items(), key=lambda kv: repr(kv[0]))):
        color = f"C{s % 10}"
        label = ", ".join(f"{kk}={vv:g}" if isinstance(vv, float) else f"{kk}={vv}" for kk, vv in rest) or None
        xs = [d["params"][xkey] if xkey else i for i, d in items]
        if categories is not None:
            xs = [categories.index(x) for x in xs]
        vc = [np.nan if d["v_critical"] is None else d["v_critical"] for _, d in items]
        ax1.plot(xs, vc, ls="none" if categories is not None else "-", color=color, lw=0.8, label=label)
        all_x += list(xs)
        for x, (_, d), y in zip(xs, items, vc):
            if d["v_critical"] is None:
                missing = True
                ax1.plot([x], [0.04], "^", color=color, mfc=color if d["safe"] else "white", ms=7,
                         transform=bottom, clip_on=False)
                continue
            ax1.errorbar([x], [y], yerr=[d.get("v_critical_error") or 0.0], fmt="o", color=color,
                         mfc=color if d["safe"] else "white", ms=6)
            for w in d["windows"]:
                if w["bounces"] == 2:
                    ax2.plot([x, x], [w["lo"], w["hi"]], "-", color=color, lw=4, solid_capstyle="butt")
    ax1.ticklabel_format(axis="y", useOffset=False)
    ax1.set_ylabel(f"v_critical ({units}/s)" if units else "v_critical")
    ax2.set_ylabel(f"2-bounce windows, v_in ({units}/s)" if units else "2-bounce windows")
    ax2.set_xlabel(xkey or "design")
    if categories is not None:
        ax2.set_xticks(range(len(categories)), [str(c) for c in categories])
    if all_x:
        lo, hi = float(min(all_x)), float(max(all_x))
        pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo) * 0.05, 0.5)
        ax1.set_xlim(lo - pad, hi + pad)
    ax1.set_title((title + "\n" if title else "") + "filled: safe, hollow: unsafe"
                  + ("; triangle at the bottom: no v_critical" if missing else ""), fontsize=10)
    if len(series) > 1:
        ax1.legend(fontsize=7, loc="best")
    note = dict(transform=None, ha="center", va="center", fontsize=9, color="0.3", wrap=True)
    if not any(d["v_critical"] is not None for d in designs):
        reasons = sorted({str(d.get("v_critical_reason") or "") for d in designs} - {""})
        ax1.text(0.5, 0.5, "no v_critical in this grid" + (f":\n{reasons[0]}" if reasons else ""),
                 **{**note, "transform": ax1.transAxes})
        ax1.set_yticks([])
    if not any(w["bounces"] == 2 for d in designs for w in d["windows"]):
        ax2.text(0.5, 0.5, "no two-bounce window in this grid", **{**note, "transform": ax2.transAxes})
        ax2.set_yticks([])
    for a in (ax1, ax2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    return _png(plt, fig, fmt)


def robustness_figure(result: dict, *, title: str = "", units: str = "", fmt: str = "png") -> bytes:
    """PNG bytes for ``fabkit robustness``: stacked probabilities of each bounce
    count (escaped) and of capture / flying off against v_in, and the nominal
    (zero-scatter) bounce count on a second axis."""
    plt, fig = _figure(figsize=(9.5, 4.5))
    ax = fig.add_subplot(1, 1, 1)
    rows = result["rows"]
    v = np.array([r["v_in"] for r in rows], dtype=float)
    counts = sorted({int(b) for r in rows for b in r["p_bounces"]})
    # the sweep's colours: one per count up to 4, then 5 and more share a layer
    layers = [(f"escaped, {b} bounce{'s' if b > 1 else ''}",
               np.array([r["p_bounces"].get(str(b), 0.0) for r in rows]), BOUNCE_COLOURS[b])
              for b in counts if b in BOUNCE_COLOURS]
    if any(b not in BOUNCE_COLOURS for b in counts):
        many = np.array([sum(p for b, p in r["p_bounces"].items() if int(b) not in BOUNCE_COLOURS) for r in rows])
        layers.append(("escaped, 5+ bounces", many, MANY_BOUNCES))
    for name, (_, color) in OUTCOME_STYLE.items():
        p = np.array([r["p_outcome"].get(name, 0.0) for r in rows])
        if p.any():
            layers.append((name.replace("_", " "), p, color))
    if len(v) > 1:
        ax.stackplot(v, *[p for _, p, _ in layers], labels=[n for n, _, _ in layers], step="mid",
                     colors=[c for _, _, c in layers], alpha=0.85)
    else:
        bottom = 0.0
        for n, p, c in layers:
            ax.bar(v, p, bottom=bottom, label=n, width=1.0, color=c)
            bottom += p
    ax.set_ylim(0, 1)
    ax.set_xlabel(f"v_in ({units}/s)" if units else "v_in")
    ax.set_ylabel("probability")
    ax2 = ax.twinx()
    nb = np.array([r["nominal_bounces"] if r["nominal_outcome"] == OUTCOMES[ESCAPED] else np.nan for r in rows], dtype=float)
    # white with a black edge: visible on the one-bounce layer, which is black
    ax2.plot(v, nb, "o", ms=4, mfc="white", mec="black", mew=0.8, ls="none", label="nominal bounces")
    ax2.set_ylabel("nominal bounce count")
    from matplotlib.ticker import MaxNLocator

    ax2.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax2.set_ylim(0, (np.nanmax(nb) if np.isfinite(nb).any() else 1) + 1)
    ax.set_title((title + "\n" if title else "")
                 + f"sigma_y {result['sigma_y']:g} {units or 'design units'}, sigma_vy {result['sigma_vy']:g} "
                 f"{units + '/s' if units else 'design units/s'}, {result['samples']} samples per speed",
                 fontsize=10)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="upper left", bbox_to_anchor=(1.1, 1.0),
              ncol=1 if len(h1) + len(h2) <= 14 else 2)
    fig.tight_layout()
    return _png(plt, fig, fmt)


def _place_labels(fig, ax, items, fontsize=6) -> None:
    """Annotate points without overlap: ``items`` [(x, y, text, colour)] in data
    coordinates; each label tries a few offsets around its point and is left out
    (its point stays) when every offset overlaps a marker or a label already placed,
    or leaves the axes."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    from matplotlib.transforms import Bbox

    # the markers themselves are obstacles too
    placed = [Bbox.from_extents(px - 3, py - 3, px + 3, py + 3)
              for px, py in ax.transData.transform([(x, y) for x, y, _, _ in items])] if items else []
    for x, y, text, colour in items:
        for dx, dy in ((4, 3), (4, -9), (-4, 3), (-4, -9), (4, 9), (4, -15)):
            ann = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy), fontsize=fontsize,
                              color=colour, ha="left" if dx > 0 else "right")
            box = ann.get_window_extent(renderer).expanded(1.05, 1.1)
            inside = (frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1)
            if inside and not any(box.overlaps(b) for b in placed):
                placed.append(box)
                break
            ann.remove()


def precision_png(sim_rows: list[dict], *, title: str = "", floor: float | None = None,
                  fmt: str = "png") -> bytes:
    """The work-precision diagram: error against wall time, log-log, one line per method
    (points labelled with their rtol where the label does not overlap another);
    ``floor`` marks the reference's own error bound (errors near it are not resolved)."""
    plt, fig = _figure(figsize=(7.5, 5))
    ax = fig.add_subplot(1, 1, 1)
    methods = list(dict.fromkeys(r["method"] for r in sim_rows))
    styles = {"fabkit": "-", "scipy": "--"}
    labels = []
    for k, m in enumerate(methods):
        rows = [r for r in sim_rows if r["method"] == m and r.get("error") is not None
                and r.get("seconds") is not None]
        if not rows:
            continue
        t = np.array([r["seconds"] for r in rows], dtype=float)
        e = np.maximum(np.array([r["error"] for r in rows], dtype=float), 1e-17)
        ax.loglog(t, e, styles.get(m.split(" ")[0], "-"), marker="o", ms=4, lw=1.3, color=f"C{k}", label=m)
        labels += [(ti, ei, f"rtol {r['rtol']:.0e}", f"C{k}") for ti, ei, r in zip(t, e, rows)]
    if floor:
        ax.axhline(floor, color="0.6", lw=0.8, ls=":", label="reference error bound")
    ax.set_xlabel("wall time for the launch set (s), best of several")
    ax.set_ylabel("error of v_out and bounce times (relative, dimensionless)")
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    # ticks at 1, 2, 5 x 10^k written as plain numbers: no crowded minor labels
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    _place_labels(fig, ax, labels)
    return _png(plt, fig, fmt)


def analyze_figure(rows: list[dict], *, title: str = "", units: str = "", fmt: str = "png") -> bytes:
    """Tracked and simulated x(t), y(t) overlaid, one pair of panels per track (the
    paper's trajectory figures): dots the track, lines the model (a release: the fitted
    model; a launch: the simulation of the same launch), dashes the tracked bounces."""
    n = max(1, len(rows))
    plt, fig = _figure(figsize=(10, 2.6 * n + 0.6))
    for k, r in enumerate(rows):
        ax1 = fig.add_subplot(n, 2, 2 * k + 1)
        ax2 = fig.add_subplot(n, 2, 2 * k + 2, sharex=ax1)
        tr = r.get("_track", {})
        model = r.get("_model") or (r.get("simulation") or {}).get("_model")
        for ax, key in ((ax1, "x"), (ax2, "y")):
            if tr:
                ax.plot(tr["t"], tr[key], ".", ms=2.0, color="0.35", label="track")
            if model is not None:
                ax.plot(model["t"], model[key], "-", lw=1.1, color="C3", alpha=0.85,
                        label="model fit" if r.get("kind") == "release" else "simulation")
            for j, tb in enumerate(r.get("bounce_times", [])):
                ax.axvline(tb, color="C0", lw=0.8, ls="--", label="bounce (track)" if j == 0 else None)
            ax.grid(alpha=0.3)
            ax.set_ylabel(f"{key} ({units})" if units else key)
        if k == n - 1:
            ax1.set_xlabel("t (s)")
            ax2.set_xlabel("t (s)")
        name = str(r.get("file", "")).rsplit("/", 1)[-1]
        if r.get("kind") == "release":
            nan = float("nan")
            head = (f"{name}: release, damping {nan if r.get('damping') is None else r['damping']:.4g} 1/s (fit), "
                    f"log-dec {r.get('damping_logdec') or nan:.4g}, omega "
                    f"{nan if r.get('omega') is None else r['omega']:.4g}")
        else:
            sim = r.get("simulation") or {}
            vo = r.get("v_out")
            vu = f" {units}/s" if units else ""
            head = (f"{name}: launch v_in {r.get('v_in') or float('nan'):.4g}{vu}, {r.get('bounces')} bounce(s), "
                    f"{r.get('outcome')}" + (f" v_out {vo:.4g}{vu}" if vo else "")
                    + (f" | sim: {sim.get('bounces')} bounce(s), {sim.get('outcome')}"
                       + (f" v_out {sim['v_out']:.4g}{vu}" if sim.get("v_out") else "") if sim else ""))
        ax1.set_title(head, fontsize=8, loc="left")
        if k == 0:
            ax1.legend(loc="best", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _png(plt, fig, fmt)



def phi4_trajectory_png(record: dict, summary: dict, *, fmt: str = "png") -> bytes:
    """The seed paper's Fig. 3 for one phi^4 collision: X(t) (solid, left axis) and the
    shape-mode amplitude A(t) (dashed, right axis; blank while X < 1, where the
    projection onto eq. ansatz is singular), bounces marked."""
    plt, fig = _figure(figsize=(8, 3.8))
    ax = fig.add_subplot(1, 1, 1)
    t = np.asarray(record["t"], dtype=float)
    X = np.asarray(record["X"], dtype=float)[0]
    A = np.asarray(record["A"], dtype=float)[0]
    m = np.isfinite(X)
    ax.plot(t[m], X[m], "-", color="black", lw=1.2, label="X(t)")
    ax.set_xlabel("t (the PDE's dimensionless time, c = 1)")
    ax.set_ylabel("X, half-separation (PDE length; kink width sqrt 2)")
    ax2 = ax.twinx()
    ax2.plot(t, A, "--", color="tab:blue", lw=1.0, label="A(t)")
    ax2.set_ylabel("A, shape-mode amplitude (dimensionless, as phi)", color="tab:blue")
    for k, tb in enumerate(summary.get("bounce_times", [])):
        ax.axvline(tb, color="0.6", lw=0.7, ls=":")
    out = summary.get("outcome", "")
    extra = f", v_out = {summary['v_out']:.4f}" if out == OUTCOMES[ESCAPED] and summary.get("v_out") else ""
    if extra and summary.get("v_out_error") is not None:
        extra += f" ± {summary['v_out_error']:.1g} (step halving)"
    ax.set_title(f"phi^4 kink-antikink, v_in = {summary.get('v_in', 0):g}: {out}, "
                 f"{summary.get('bounces', 0)} bounce(s){extra}", fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _png(plt, fig, fmt)


def compare_figure(panels: list[dict], *, title: str = "", span: tuple[float, float] | None = (0.65, 1.25),
                   fmt: str = "png") -> bytes:
    """The seed paper's Fig. 1 for an apparatus: one panel per model, v_out / v_c against
    v_in / v_c, coloured by the number of collisions (one black, two blue, three green,
    four red; more and captured in grey ticks on the axis). ``panels``: dicts with
    name, params (text), v_in, v_out, bounces, outcome, v_critical, units. ``span``: the
    x range (v_in / v_c) every panel shares (None: each its own); launches outside it
    are not drawn, and a panel that has some says how many it shows. A panel without a
    v_critical is drawn in its own units over its own range."""
    plt, fig = compare_axes(panels, title=title, span=span)
    return _png(plt, fig, fmt)


def compare_axes(panels: list[dict], *, title: str = "", span: tuple[float, float] | None = (0.65, 1.25)):
    """(pyplot, Figure) of :func:`compare_figure`, not yet rendered (tests read its axes)."""
    plt, fig = _figure(figsize=(11, 8.5))
    for p_i, p in enumerate(panels):
        ax = fig.add_subplot(2, 2, p_i + 1)
        vc = p.get("v_critical")
        scale = vc if vc else 1.0
        v = np.asarray(p["v_in"], dtype=float) / scale
        vo = np.asarray([np.nan if x is None else x for x in p["v_out"]], dtype=float) / scale
        nb = np.asarray(p["bounces"])
        esc = np.array([o == OUTCOMES[ESCAPED] for o in p["outcome"]])
        shown = np.ones(v.size, dtype=bool)
        if vc and span is not None:
            # a sample a hair outside (a panel sampled around a nominal v_critical) is drawn, clipped
            pad = 0.01 * (span[1] - span[0])
            shown = (v >= span[0] - pad) & (v <= span[1] + pad)
        for n in (1, 2, 3, 4):
            m = esc & (nb == n) & shown
            if m.any():
                ax.plot(v[m], vo[m], ".", ms=2.5, color=BOUNCE_COLOURS[n])
        rest = ~(esc & (nb >= 1) & (nb <= 4)) & shown
        if rest.any():
            ax.plot(v[rest], np.zeros(rest.sum()), "|", ms=5, color=CAPTURED_COLOUR)
        if vc:
            ax.axvline(1.0, color="tab:orange", lw=0.8, ls="--")
        u = p.get("units", "")
        vc_txt = f"v_critical = {vc:.5g} {u}" if vc else "v_critical: none in range"
        if not shown.all():
            vc_txt += (f"\n{int(shown.sum())} of {v.size} launches in this range "
                       f"(sampled {v.min():.3g}..{v.max():.3g} x v_critical)")
        ax.set_title(f"{p['name']}\n{p.get('params', '')}\n{vc_txt}", fontsize=8.5)
        ax.set_xlabel("v_in / v_critical" if vc else f"v_in ({u})")
        ax.set_ylabel("v_out / v_critical" if vc else f"v_out ({u})")
        ax.grid(alpha=0.3)
        if vc and span is not None:
            ax.set_xlim(*span)
        ax.set_ylim(bottom=-0.03)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker=".", ms=8, color=BOUNCE_COLOURS[n],
                      label=f"{n} collision{'s' if n > 1 else ''}") for n in (1, 2, 3, 4)]
    handles.append(Line2D([], [], ls="", marker="|", ms=8, color=CAPTURED_COLOUR, label="captured, or 5+ collisions"))
    handles.append(Line2D([], [], ls="--", color="tab:orange", label="v_critical"))
    fig.legend(handles=handles, loc="lower center", ncol=6, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return plt, fig


def design_figure(result: dict, bounds, *, title: str = "", units: str = "", fmt: str = "png") -> bytes:
    """Figure bytes (``fmt``) for ``fabkit design``: the objective of every screened design in the
    order of evaluation, the checked designs' own scores and the best checked so far (top), and the winner's v_out against
    release height from its check, coloured by bounce count, observable windows shaded
    (bottom)."""
    plt, fig = _figure(figsize=(8.5, 7.5))
    ax1 = fig.add_subplot(2, 1, 1)
    ax2 = fig.add_subplot(2, 1, 2)
    hist = result["history"]
    y = np.array([h["objective"] for h in hist], dtype=float)
    n = np.arange(1, y.size + 1)
    feas = np.array([h["feasible"] for h in hist], dtype=bool)
    score = np.where(feas, -y, np.nan)
    ax1.plot(n[feas], score[feas], "o", ms=3.5, color="C0", alpha=0.6, label="feasible (screen, unchecked)",
             zorder=3)
    if (~feas).any():
        ax1.plot(n[~feas], np.zeros((~feas).sum()), "x", ms=4, color="tab:red", label="infeasible (screen)")
    # what was checked: the baseline (before the search) and the verified finalists, each at
    # the evaluation that first screened it; the best so far is over checked designs only
    from .design import objective

    span = float(result.get("span") or 1.0)
    checked = [(0, result["baseline"])]
    for ev in result.get("finalists") or []:
        vals = list(ev["values"])
        idx = next((i + 1 for i, h in enumerate(hist) if list(h["values"]) == vals), None)
        if idx is not None:
            checked.append((idx, ev))
    pts = [(i, -objective(ev, span)) for i, ev in checked if ev is not None and ev["feasible"]]
    if pts:
        ax1.plot([i for i, _ in pts], [v for _, v in pts], "D", ms=6, mfc="none", mec="k", mew=1.2,
                 label="checked (fabkit check)", zorder=4)
        xs = np.arange(0, y.size + 1)
        best = np.full(xs.size, -np.inf)
        for i, v in pts:
            best[i:] = np.maximum(best[i:], v)
        ok = np.isfinite(best)
        ax1.step(xs[ok], best[ok], where="post", color="k", lw=1.2, label="best checked so far")
    pop = result["optimizer"]["population"]
    for g in range(pop, y.size, pop):
        ax1.axvline(g + 0.5, color="0.85", lw=0.8)
    base = result["baseline"]
    ax1.axhline(base["observable"], color="tab:orange", ls="--", lw=1,
                label=f"baseline (checked): {base['observable']} observable")
    ax1.set_xlabel("evaluation (grey lines: generations)")
    ax1.set_ylabel("observable windows + width / ramp range")
    ax1.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax1.grid(alpha=0.3)
    w = result["winner"]
    if w is not None and w.get("sweep") is not None:
        sw = w["sweep"]
        H = np.asarray(sw["heights"], dtype=float)
        vo = np.asarray([np.nan if v is None else v for v in sw["v_out"]], dtype=float) \
            if sw["v_out"] is not None else np.full(H.size, np.nan)
        nb = np.asarray(sw["bounces"])
        esc = np.array([o == OUTCOMES[ESCAPED] for o in sw["outcome"]])
        for k in sorted(set(nb[esc].tolist())):
            m = esc & (nb == k)
            ax2.plot(H[m], vo[m], ".", ms=3, color=BOUNCE_COLOURS.get(k, MANY_BOUNCES),
                     label=f"{k} bounce{'s' if k > 1 else ''}" if k <= 4 else None)
        if (esc & (nb > 4)).any():
            ax2.plot([], [], ".", color=MANY_BOUNCES, label="5+ bounces")
        if (~esc).any():
            ax2.plot(H[~esc], np.zeros((~esc).sum()), "|", color=CAPTURED_COLOUR, ms=6, label="captured / off")
        first = True
        for win in w["windows"]:
            if win["observable"]:
                ax2.axvspan(win["height_lo"], win["height_hi"], color="tab:blue", alpha=0.18, lw=0,
                            label="observable window" if first else None)
                first = False
        if w.get("critical_height") is not None:
            ax2.axvline(w["critical_height"], color="tab:orange", ls="--", lw=1, label="v_critical")
        vals = ", ".join(f"{b.key.removeprefix('surface.params.')}={v:g}" for b, v in zip(bounds, w["values"]))
        ax2.set_title(f"winner: {vals}: {w['observable']} observable", fontsize=9)
        ax2.legend(fontsize=7, loc="upper left")
    ax2.set_xlabel(f"release height ({units})" if units else "release height")
    ax2.set_ylabel(f"v_out ({units}/s)" if units else "v_out")
    ax2.grid(alpha=0.3)
    if title:
        ax1.set_title(title, fontsize=10)
    fig.tight_layout()
    return _png(plt, fig, fmt)
