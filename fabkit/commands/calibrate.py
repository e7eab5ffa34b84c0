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


def run(args) -> int:
    from ..physics.calibrate import calibration_table, height_from_v_in, v_in_from_height

    timer = Timer()
    spec = load_spec(args.spec, need=("ball", "ramp"), command="calibrate")
    table = calibration_table(spec)
    g, k, units = table["g"], table["k"], table["units"]
    heights, v_in = table["heights"], table["v_in"]
    if args.height:
        heights = _check(args.height, "--height")
        v_in = _finite(v_in_from_height(heights, g, k), "--height", "entry speed")
    payload = {"heights": heights, "v_in": v_in, "g": g, "k": k, "units": units}
    lines = [f"calibrate: rolling without slipping, v_in = sqrt(2 g H / (1 + k)), g = {g:.6g} {units}/s^2, "
             f"k = {k:.6g}", f"{'H (' + units + ')':>14} {'v_in (' + units + '/s)':>16}"]
    rows = [f"{h:14.6g} {v:16.8g}" for h, v in zip(heights, v_in)]
    n_end = SHOWN_AT_EACH_END
    if getattr(args, "all", False) or len(rows) <= 2 * n_end + 1:
        lines += rows
    else:
        lines += rows[:n_end] + [f"{'...':>14} {'...':>16}   ({len(rows) - 2 * n_end} more rows; --all prints "
                                 "every row)"] + rows[-n_end:]
    lines.append(f"range: H {float(np.min(heights)):.6g} .. {float(np.max(heights)):.6g} {units}, v_in "
                 f"{float(np.min(v_in)):.8g} .. {float(np.max(v_in)):.8g} {units}/s, {len(rows)} rows")
    if args.v_in:
        vv = _check(args.v_in, "--v-in")
        hh = _finite(height_from_v_in(vv, g, k), "--v-in", "release height")
        payload["inverse"] = {"v_in": vv, "heights": hh}
        lines.append(f"inverse: {'v_in (' + units + '/s)':>16} {'H (' + units + ')':>14}")
        lines += [f"         {v:16.8g} {h:14.8g}" for v, h in zip(vv, hh)]
    if spec.has("surface") and spec.has("simulation"):
        entry = float(spec.surface_functions().h(spec.simulation.start, 0.0))
        if math.isfinite(entry):
            payload["entry_level"] = entry
            lines.append(f"entry level h(start={spec.simulation.start:g}, 0) = {entry:.6g} {units} "
                         "(heights are measured from it)")
    payload["seconds"] = timer.seconds
    lines.append(f"calibrate: exact closed form, error ~1e-16 relative (rounding), {len(heights)} heights, "
                 f"{timer.seconds:.3f} s")
    emit(lines, payload, args.json)
    return 0
