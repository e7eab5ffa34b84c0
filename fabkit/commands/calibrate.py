"""``fabkit calibrate SPEC [--height H...] [--v-in V...] [--all] [--json]``: ramp height <-> entry speed.

The table printed is short unless ``--all`` is given: the first and last rows
(a few of each) and the number left out; JSON always has every row."""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError
from ..spec import load_spec
from ._common import Timer, emit

#: rows printed at each end of a long table (without --all)
SHOWN_AT_EACH_END = 4


def _check(values, key):
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise SpecError(f"must be finite and >= 0, got {', '.join(f'{v:g}' for v in a)}", key=key)
    return a


def _finite(values, key, what):
    """Refuse an input whose converted value overflows a double."""
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise SpecError(f"too large: the {what} overflows (largest finite is {np.finfo(float).max:.3g})", key=key)
    return a


def _row(h, v) -> str:
    return f"{h:14.6g} {v:16.8g}" if math.isfinite(v) else f"{h:14.6g} {'does not reach':>16}"


def run(args) -> int:
    from ..errors import DesignError
    from ..physics.calibrate import calibration_table, entry, height_resolution, release_height

    timer = Timer()
    spec = load_spec(args.spec, need=("ball", "ramp"), command="calibrate")
    table = calibration_table(spec)
    ent = table["entry"]
    g, k, units = table["g"], table["k"], table["units"]
    heights, v_in = table["heights"], table["v_in"]
    if args.height:
        heights = _check(args.height, "--height")
        if np.any(heights > ent.top):
            raise SpecError(f"{float(np.max(heights)):g} is above the ramp's top ({ent.top:.6g} {units}; the ramp "
                            "is sized from ramp.heights)", key="--height")
        res = height_resolution(spec)
        if np.any((heights > 0) & (heights < res)):
            raise SpecError(f"{float(np.min(heights[heights > 0])):.3g} is below what the ramp's line resolves "
                            f"({res:.3g} {units})", key="--height")
        ent = entry(spec, heights)
        _finite(ent.v_in[ent.reached], "--height", "entry speed")
        v_in = ent.v_in
    if not np.any(ent.reached):
        raise DesignError(f"{spec.path}: no release height reaches the block: {ent.why}")
    payload = {"heights": heights, "v_in": v_in, "g": g, "k": k, "units": units, "profile": ent.profile,
               "damping": ent.mu, "rolling_resistance": ent.c, "closed_form": ent.closed_form,
               "v_in_lossless": ent.lossless, "v_in_error": ent.error, "top_height": ent.top,
               "not_reached": ent.why, "method": ent.method,
               "height_definition": "drop of the ball's centre from release to resting on the block at the "
                                    "launch point"}
    if ent.closed_form:
        head = (f"calibrate: rolling without slipping, no losses: v_in = sqrt(2 g H / (1 + k)), "
                f"g = {g:.6g} {units}/s^2, k = {k:.6g}")
    else:
        head = (f"calibrate: the ball rolled down the {ent.profile} ramp with damping {ent.mu:g} 1/s and rolling "
                f"resistance {ent.c:g}, g = {g:.6g} {units}/s^2, k = {k:.6g}")
    lines = [head, f"{'H (' + units + ')':>14} {'v_in (' + units + '/s)':>16}"]
    rows = [_row(h, v) for h, v in zip(heights, v_in)]
    n_end = SHOWN_AT_EACH_END
    if getattr(args, "all", False) or len(rows) <= 2 * n_end + 1:
        lines += rows
    else:
        lines += rows[:n_end] + [f"{'...':>14} {'...':>16}   ({len(rows) - 2 * n_end} more rows; --all prints "
                                 "every row)"] + rows[-n_end:]
    ok = np.isfinite(v_in)
    lines.append(f"range: H {float(np.min(heights)):.6g} .. {float(np.max(heights)):.6g} {units}, v_in "
                 f"{float(np.min(v_in[ok])):.8g} .. {float(np.max(v_in[ok])):.8g} {units}/s, {len(rows)} rows")
    if not ent.closed_form:
        both = ok & (ent.lossless > 0)
        rel = (v_in[both] / ent.lossless[both]) - 1.0 if both.any() else np.zeros(1)
        lines.append(f"losses: v_in {100 * float(np.max(rel)):+.3f} .. {100 * float(np.min(rel)):+.3f} % against "
                     "the lossless closed form")
    if ent.why:
        lines.append(f"note: {ent.why}")
    if args.v_in:
        vv = _check(args.v_in, "--v-in")
        hh = release_height(spec, vv)
        if ent.closed_form:
            hh = _finite(hh, "--v-in", "release height")
        if np.any(np.isnan(hh)):
            bad = float(vv[np.isnan(hh)][0])
            raise SpecError(f"{bad:g} {units}/s is beyond the ramp's reach (its top, H = {ent.top:.6g} {units}, "
                            "gives less)", key="--v-in")
        payload["inverse"] = {"v_in": vv, "heights": hh}
        lines.append(f"inverse: {'v_in (' + units + '/s)':>16} {'H (' + units + ')':>14}")
        lines += [f"         {v:16.8g} {h:14.8g}" for v, h in zip(vv, hh)]
    lines.append("H is the drop of the ball's centre from its release to resting on the block at the launch point")
    if spec.has("surface") and spec.has("simulation"):
        entry_level = float(spec.surface_functions().h(spec.simulation.start, spec.simulation.y0))
        if math.isfinite(entry_level):
            payload["entry_level"] = entry_level
            lines.append(f"entry level h(start={spec.simulation.start:g}, y0={spec.simulation.y0:g}) = "
                         f"{entry_level:.6g} {units} (the contact's height at the launch point)")
    payload["seconds"] = timer.seconds
    acc = ("exact closed form, error ~1e-16 relative (rounding)" if ent.closed_form else
           f"{ent.method}, error ~{ent.error:.0e} relative")
    lines.append(f"calibrate: {acc}, {len(heights)} heights, {timer.seconds:.3f} s")
    emit(lines, payload, args.json)
    return 0
