"""``fabkit ramp SPEC [-o PATH] [--json]``: the launch ramp with calibrated release marks."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import SpecError
from ..spec import load_spec
from ._common import Timer, check_paths, default_output, emit, launch_stages, prepare_simulator, quiet


def run(args) -> int:
    from ..errors import DesignError
    from ..io import atomic_outputs
    from ..lab.ramp import (GROOVE_CLEAR_MM, GROOVE_DEPTH_MM, GROOVE_WIDTH_MM, build_ramp, mark_targets, mesh_verdict, place_marks,
                            ramp_angle, ramp_profile)
    from ..physics.calibrate import ball_k, entry, ramp_heights
    from ..physics.check import check
    from ..solid import EXPORT_FORMATS, export_bytes
    from ..units import gravity

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "stock", "ball", "ramp", "simulation"), command="ramp")
    if spec.ramp.profile != "fabkit":
        raise SpecError("fabkit ramp builds fabkit's own ramp; for your straight ramp, fabkit calibrate gives "
                        "the release heights (--v-in) to mark on it", file=spec.path, key="ramp.profile")
    path = default_output(spec, ".ramp.stl", args.output)
    check_paths(args, {"--output": path})
    fmt = path.suffix.lower().lstrip(".") or "stl"
    if fmt not in EXPORT_FORMATS:
        raise SpecError(f"unknown mesh format '{path.suffix}' (use one of: "
                        f"{', '.join('.' + f for f in EXPORT_FORMATS)})", key="--output")
    g, k = gravity(spec.units), ball_k(spec)
    # stages: the calibration, the simulator, the check's (launches, highest safe height,
    # refinement, the windows' heights), the marks, the solid
    stage, launches, close = launch_stages(8, quiet(args), "ramp")
    try:
        stage("calibrating the ramp")
        # the ball must reach the block from the ramp before the block is worth simulating
        H = ramp_heights(spec)
        ent = entry(spec, H)
        if not ent.reached.any():
            raise DesignError(f"{spec.path}: no release height on the ramp reaches the block: {ent.why}")
        prof = ramp_profile(spec)
        stage("compiling or loading the simulator")
        prepare_simulator(spec, say=None if quiet(args) else (lambda m: stage(m, advance=False)))
        chk = check(spec, progress=launches(f"checking: launching the ramp's {len(H)} heights", len(H)),
                    stage=stage).to_json()
        t_check = timer.seconds
        stage("placing the marks")
        targets = mark_targets(chk, g, k, spec=spec)
        reach = [math.isfinite(t["height"]) and t["height"] <= prof.top for t in targets]
        beyond = [t for t, ok in zip(targets, reach) if not ok]
        targets = [t for t, ok in zip(targets, reach) if ok]
        marks = place_marks(spec, prof, targets)
        stage("building the solid")
        solid = build_ramp(spec, prof, marks)
        data = export_bytes(solid.vertices, solid.faces, fmt)
        # the bytes about to be written, read back as a slicer reads them
        verdict = mesh_verdict(data, fmt)
        if not verdict.ok:
            raise DesignError(f"{spec.path}: the ramp's mesh is not one watertight body ({verdict.message}); "
                              "nothing written")
    finally:
        close()
    with atomic_outputs() as out:
        out.write(path, data)
    u = spec.units
    pub = [{"height": m["height"], "v_in": m["v_in"], "label": m["label"], "X": m["X"], "Y": m["Y"], "Z": m["Z"],
            "along_mm": m["along_mm"], "groove": "double" if m["double"] else "single", "side": m["side"],
            "crowded": m["crowded"], "engraved": m["engraved"], "groove_depth_mm": m["groove_depth_mm"],
            "lane": {side: [m["lane"][side], m["lanes"][side]] for side in m["lane"]}} for m in marks]
    payload = {
        "path": str(path), "marks": pub, "triangles": int(len(solid.faces)), "volume_mm3": solid.volume_mm3,
        "bodies": verdict.bodies, "genus": solid.genus, "watertight": verdict.watertight,
        "degenerate_triangles": verdict.degenerate,
        "angle_deg": ramp_angle(spec), "transition_length": prof.L, "length": prof.u_end,
        "damping": ent.mu, "rolling_resistance": ent.c, "calibration": ent.method,
        "beyond_reach": [{"v_in": t["v_in"], "label": t["label"]} for t in beyond],
        "top_height": float(prof.drop(prof.u_end)), "profile_error_mm": solid.profile_error_mm,
        "extent_mm": solid.extent_mm, "safe": chk["safe"], "highest_safe_height": chk["highest_safe_height"], "model": chk["model"],
        "units": u, "seconds": timer.seconds, "check_seconds": t_check,
    }
    lo, hi = float(min(H)), float(max(H))
    lines = [f"ramp: {Path(path)}, one watertight body (read back: {verdict.bodies} body, {verdict.triangles} "
             f"triangles, none degenerate, volume {solid.volume_mm3:.6e} mm^3), {prof.u_end:.4g} {u} long; its "
             f"top is a release height of {payload['top_height']:.4g} {u} (the spec's release heights "
             f"{lo:.4g}-{hi:.4g} {u}, the ball's room above), incline {ramp_angle(spec):g} deg, "
             f"curvature-continuous at the launch point (work X {solid.extent_mm['launch_point'][0]:.2f} mm)",
             f"{'mark':<44} {'H (' + u + ')':>10} {'v_in (' + u + '/s)':>14} {'X (mm)':>9} {'along (mm)':>11}"]
    lines += [f"{m['label']:<44} {m['height']:10.5f} {m['v_in']:14.5f} {m['X']:9.2f} {m['along_mm']:11.2f}"
              for m in pub]
    if not pub:
        lines.append("no marks: the ramp reaches no two-bounce window and not v_critical")
    apart = [m for m in pub if m["crowded"] and m["engraved"]]
    if apart:
        where = "; ".join(f"{m['label'].split(' (')[0]}: " + ", ".join(
            f"{side} side lane {j + 1} of {n}" for side, (j, n) in sorted(m["lane"].items())) for m in apart)
        lines.append(f"set apart: marks closer along the ramp than a groove's width ({GROOVE_WIDTH_MM:g} mm) plus "
                     f"{GROOVE_CLEAR_MM:g} mm are engraved in separate lanes across it, lane 1 nearest the "
                     f"ball's path, each at its own place along it ({where})")
    for m, mk in zip(pub, marks):
        if mk.get("too_thin"):
            lines.append(f"not engraved: {m['label']}: the ramp is too thin there for a groove (it thins to nothing "
                         "at the launch point); measure it off by 'along (mm)'")
        elif not m["engraved"]:
            lines.append(f"not engraved: {m['label']}: no room across the ramp for another lane of grooves "
                         "(too close to a neighbouring mark); measure it off by 'along (mm)'")
        elif mk["groove_depth_mm"] < GROOVE_DEPTH_MM:
            lines.append(f"shallow groove: {m['label']}: {mk['groove_depth_mm']:.2g} mm deep (half the ramp's "
                         "thickness there)")
    for t in beyond:
        lines.append(f"not marked: {t['label']} at {t['v_in']:.5f} {u}/s is beyond the ramp's reach (its top, "
                     f"H = {payload['top_height']:.4g} {u}, gives less with the ramp's losses)")
    if ent.why:
        lines.append(f"note: {ent.why}")
    if not chk["safe"]:
        hs = chk['highest_safe_height']
        lines.append(f"warning: UNSAFE above release height {hs:.5g} {u} (fabkit check)" if hs is not None else
                     "warning: UNSAFE at every release height (fabkit check)")
    cal = ("exact (closed-form calibration, no losses)" if ent.closed_form else
           f"from the ball's descent of this ramp with damping {ent.mu:g} 1/s and rolling resistance {ent.c:g} "
           f"(to ~{ent.error:.0e} relative)")
    lines.append(f"ramp: marks from fabkit check on the {chk['model']} model; mark heights {cal}, contact point "
                 f"by root finding to 1e-12, running surface within {solid.profile_error_mm:.1g} mm of the profile, "
                 f"{timer.seconds:.1f} s (check {t_check:.1f} s)")
    emit(lines, payload, args.json)
    return 0
