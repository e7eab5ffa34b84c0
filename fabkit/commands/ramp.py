"""``fabkit ramp SPEC [-o PATH] [--json]``: the launch ramp with calibrated release marks."""

from __future__ import annotations

from pathlib import Path

from ..errors import SpecError
from ..spec import load_spec
from ._common import Timer, check_paths, default_output, emit, prepare_simulator


def run(args) -> int:
    from ..io import atomic_outputs
    from ..lab.ramp import build_ramp, design_profile, mark_targets, place_marks
    from ..physics.calibrate import ball_k, ramp_heights
    from ..physics.check import check
    from ..solid import EXPORT_FORMATS, export_bytes
    from ..units import gravity

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "stock", "ball", "ramp", "simulation"), command="ramp")
    path = default_output(spec, ".ramp.stl", args.output)
    check_paths(args, {"--output": path})
    fmt = path.suffix.lower().lstrip(".") or "stl"
    if fmt not in EXPORT_FORMATS:
        raise SpecError(f"unknown mesh format '{path.suffix}' (use one of: "
                        f"{', '.join('.' + f for f in EXPORT_FORMATS)})", key="--output")
    g, k = gravity(spec.units), ball_k(spec)
    prepare_simulator(spec)
    chk = check(spec).to_json()
    t_check = timer.seconds
    targets = mark_targets(chk, g, k)
    h_max = max([float(max(ramp_heights(spec)))] + [t["height"] for t in targets])
    prof = design_profile(spec, h_max)
    marks = place_marks(spec, prof, targets)
    solid = build_ramp(spec, prof, marks)
    if solid.bodies != 1:
        raise RuntimeError(f"the ramp came out as {solid.bodies} bodies")
    data = export_bytes(solid.vertices, solid.faces, fmt)
    with atomic_outputs() as out:
        out.write(path, data)
    u = spec.units
    pub = [{"height": m["height"], "v_in": m["v_in"], "label": m["label"], "X": m["X"], "Y": m["Y"], "Z": m["Z"],
            "along_mm": m["along_mm"], "groove": "double" if m["double"] else "single", "side": m["side"],
            "crowded": m["crowded"]} for m in marks]
    payload = {
        "path": str(path), "marks": pub, "triangles": int(len(solid.faces)), "volume_mm3": solid.volume_mm3,
        "bodies": solid.bodies, "genus": solid.genus, "watertight": True,
        "angle_deg": 30.0, "transition_length": prof.L, "length": prof.u_end,
        "top_height": float(prof.drop(prof.u_end)), "profile_error_mm": solid.profile_error_mm,
        "extent_mm": solid.extent_mm, "safe": chk["safe"], "highest_safe_height": chk["highest_safe_height"], "model": chk["model"],
        "units": u, "seconds": timer.seconds, "check_seconds": t_check,
    }
    lines = [f"ramp: {Path(path)}, one watertight body ({len(solid.faces)} triangles, volume "
             f"{solid.volume_mm3:.6e} mm^3), {prof.u_end:.4g} {u} long, rises to release height "
             f"{payload['top_height']:.4g} {u}, incline {30:g} deg, curvature-continuous at the launch point "
             f"(work X {solid.extent_mm['launch_point'][0]:.2f} mm)",
             f"{'mark':<44} {'H (' + u + ')':>10} {'v_in (' + u + '/s)':>14} {'X (mm)':>9} {'along (mm)':>11}"]
    lines += [f"{m['label']:<44} {m['height']:10.5f} {m['v_in']:14.5f} {m['X']:9.2f} {m['along_mm']:11.2f}"
              for m in pub]
    if not pub:
        lines.append("no marks: the ramp reaches no two-bounce window and not v_critical")
    if not chk["safe"]:
        hs = chk['highest_safe_height']
        lines.append(f"warning: UNSAFE above release height {hs:.5g} {u} (fabkit check)" if hs is not None else
                     "warning: UNSAFE at every release height (fabkit check)")
    lines.append(f"ramp: marks from fabkit check on the {chk['model']} model; mark heights exact (closed-form calibration, contact point by root finding to "
                 f"1e-12), running surface within {solid.profile_error_mm:.1g} mm of the profile, "
                 f"{timer.seconds:.1f} s (check {t_check:.1f} s)")
    emit(lines, payload, args.json)
    return 0
