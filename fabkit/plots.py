"""Matplotlib figures (Agg), returned as PNG bytes; the caller writes them atomically.

Imported only when a plot is asked for. A flat module of functions, one per figure.
"""

from __future__ import annotations

import io

import numpy as np


def _figure(**kw):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt, plt.figure(**kw)


def _png(plt, fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


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


def trajectory_png(traj: dict, summary: dict, *, title: str = "", units: str = "") -> bytes:
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
    extra = f", v_out = {summary['v_out']:.4g}" if out == "escaped" else ""
    ax1.set_title(f"{title}\n{out}, {summary.get('bounces', 0)} bounce(s){extra}", fontsize=10)
    if summary.get("bounce_times"):
        ax1.legend(loc="best", fontsize=8)
    for a in (ax1, ax2):
        a.grid(alpha=0.3)
    fig.tight_layout()
    return _png(plt, fig)


def sweep_figure(result: dict, title: str = "") -> bytes:
    """PNG bytes: v_out against v_in coloured by bounce count, v_critical marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    v = np.asarray(result["v_in"], dtype=float)
    vo = np.asarray([np.nan if x is None else x for x in result["v_out"]], dtype=float)
    nb = np.asarray(result["bounces"])
    esc = np.array([o == "escaped" for o in result["outcome"]])
    colors = {1: "black", 2: "tab:blue", 3: "tab:green", 4: "tab:red"}
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    for n in sorted(set(nb[esc].tolist())):
        m = esc & (nb == n)
        ax.plot(v[m], vo[m], ".", ms=3, color=colors.get(n, "tab:gray"),
                label=f"{n} bounce{'s' if n > 1 else ''}" if n <= 4 else None)
    if (esc & (nb > 4)).any():
        ax.plot([], [], ".", color="tab:gray", label="5+ bounces")
    lost = ~esc
    if lost.any():
        ax.plot(v[lost], np.zeros(lost.sum()), "|", color="0.6", ms=6, label="captured / off")
    vc = result.get("v_critical")
    if vc is not None:
        ax.axvline(vc, color="tab:orange", lw=1, ls="--", label=f"v_critical {vc:.4f}")
    ax.set_xlabel("v_in")
    ax.set_ylabel("v_out")
    if title:
        ax.set_title(title)
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
