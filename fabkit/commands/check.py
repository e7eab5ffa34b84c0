"""``fabkit check SPEC [--json] [--no-progress]``: the pre-fabrication check.

Exit 0 when every ramp height keeps the ball on the milled part (and the cut
is machinable), 1 (DesignError, one line naming the first failing height and
why) otherwise, 2 on bad input.
"""

from __future__ import annotations

from ..errors import DesignError
from ..first_run import prepare
from ._common import Timer, emit, prepare_simulator
from .sweep import completeness_line

#: reachable windows listed in the summary (--json lists every one)
SHOW = 24


def run(args) -> int:
    from ..physics.calibrate import ramp_heights
    from ..physics.check import check
    from ..spec import load_spec
    from ._common import launch_stages, quiet

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "ball", "ramp", "simulation"), command="check")
    # stages: the simulator, the ramp's launches, the highest safe height (when one fails),
    # the refinement of v_critical and the windows, the windows' release heights
    stage, launches, close = launch_stages(5, quiet(args), "check")
    try:
        stage("compiling or loading the simulator")
        say = None if quiet(args) else (lambda m: stage(m, advance=False))
        prepare(spec, need=("simulator",), say=say, quiet=quiet(args))   # a first run: gcode and report too
        prepare_simulator(spec, say=say)
        n = len(ramp_heights(spec))
        r = check(spec, progress=launches(f"launching the ramp's {n} heights", n), stage=stage)
    finally:
        close()
    r.seconds = timer.seconds
    u = spec.units
    H, v = r.heights, r.v_in
    lines = [f"check: {len(H)} release heights {H[0]:.4g}..{H[-1]:.4g} {u} "
             f"(v_in {v[0]:.4g}..{v[-1]:.4g} {u}/s), {r.model} model, damping {r.damping:g} 1/s"]
    vc = r.v_critical
    if vc is not None:
        lines.append(f"check: v_critical {vc:.6f} {u}/s at release height {r.critical_height:.4f} {u}")
    else:
        lines.append(f"check: no v_critical over the ramp's speeds ({r.v_critical_reason})")
    wins = r.reachable_windows
    lines.append(f"check: {len(wins)} two-bounce window{'' if len(wins) == 1 else 's'} reachable from the ramp"
                 + (f" (the first {SHOW} listed; all in --json)" if len(wins) > SHOW else "")
                 + (":" if wins else ""))
    for w in wins[:SHOW]:
        lines.append(f"  release height {w['height_lo']:.4f}..{w['height_hi']:.4f} {u} "
                     f"(v_in {w['lo']:.6f}..{w['hi']:.6f} {u}/s)")
    c = completeness_line("check", r.window_completeness, u)
    if c:
        lines.append(c)
    b = r.ball
    if b is not None:
        cnt = b["unsafe_counts"]
        txt = (f"check: ball radius {b['radius']:g} {u}: largest |F_t|/N {b['max_slip']:.4g} at release height "
               f"{b['max_slip_height']:.4f} {u}" if b["max_slip"] is not None else
               f"check: ball radius {b['radius']:g} {u}")
        txt += (f" (ball.friction {b['friction']:g})" if b["friction"] is not None else
                " (no ball.friction given: slip not tested)")
        named = [f"{n} {c}" for n, c in cnt.items() if c]
        txt += "; " + (", ".join(named) + " of the heights" if named else "no bridging, lost contact or slip")
        lines.append(txt)
    m = r.machining
    if m is not None:
        txt = f"check: cut depth {m['depth_mm']:.2f} mm"
        if m["limits_mm"]:
            txt += " (limits " + ", ".join(f"{kk} {vv:g}" for kk, vv in m["limits_mm"].items() if vv is not None) + " mm)"
        if "tool_radius_mm" in m:
            mr = m["min_concave_radius_mm"]
            txt += (f"; tool radius {m['tool_radius_mm']:.3f} mm vs smallest concave radius "
                    f"{mr:.3f} mm" if mr is not None else "; no concave curvature")
            if not m["radius_ok"]:
                txt += " (TOOL TOO LARGE: concave regions will be undercut)"
        lines.append(txt)
    hs = r.highest_safe_height
    tols = r.tolerances
    lines.append(f"check: highest safe release height "
                 + (f"{hs:.4f} {u}" if hs is not None else "none (the lowest height already fails)")
                 + f"; error: heights bracketed to {tols['rel_tol']:g}, v_critical to {tols['v_rel_tol']:g}, "
                 f"window edges to {tols['edge_rel_tol']:g} relative"
                 + (f" (gaps over {tols['gap_rel_tol']:g} seen)" if tols.get("gap_rel_tol") else "")
                 + f", {r.seconds:.1f} s")
    if not args.json:
        lines.append(f"check: {'SAFE' if r.safe else 'UNSAFE'} ({r.model} model)")
    emit(lines, r.to_json(), args.json)
    if not r.safe:
        raise DesignError(r.reason)
    return 0
