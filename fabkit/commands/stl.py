"""``fabkit stl SPEC [-o PATH] [--tolerance MM] [--json]``: the milled block as a solid.

Reads only the ``surface`` and ``stock`` sections (and ``tool`` if present, for
the depth check), refuses a cut deeper than the limits (exit 2), builds the
watertight block (:func:`fabkit.solid.build_solid`) and writes it atomically:
binary STL by default, other formats by extension through trimesh.
"""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import SpecError
from ..tolerances import DEFAULT
from ._common import Timer, check_paths, default_output, emit


#: the finest --tolerance, mm (1 nm): far below any machine, and above the numbers whose
#: triangle estimate overflows (a subnormal tolerance)
MIN_TOLERANCE_MM = 1e-6


def _tolerance(value) -> float:
    if value is None:
        return DEFAULT.mesh_tolerance_mm
    if not (math.isfinite(value) and value > 0):
        raise SpecError(f"must be a finite number of mm > 0, got {value!r}", key="--tolerance")
    if value < MIN_TOLERANCE_MM:
        raise SpecError(f"must be >= {MIN_TOLERANCE_MM:g} mm (the finest tolerance), got {value:g}", key="--tolerance")
    return float(value)


def run(args) -> int:
    timer = Timer()
    from ..solid import EXPORT_FORMATS, build_solid, export_bytes
    from ..io import atomic_outputs
    from ..spec import load_spec
    from ..surface import Surface, check_depth

    tolerance = _tolerance(args.tolerance)
    spec = load_spec(args.spec, need=("surface", "stock"), command="stl")
    path = default_output(spec, ".stl", args.output)
    check_paths(args, {"--output": path})
    fmt = path.suffix.lower().lstrip(".") or "stl"
    if fmt not in EXPORT_FORMATS:
        raise SpecError(f"unknown mesh format '{path.suffix}' (use one of: "
                        f"{', '.join('.' + f for f in EXPORT_FORMATS)})", key="--output")
    surface = Surface.from_spec(spec)
    check_depth(spec, surface)
    solid = build_solid(surface, spec.stock.thickness, tolerance)
    data = export_bytes(solid.vertices, solid.faces, fmt)
    with atomic_outputs() as out:
        out.write(path, data)
    seconds = timer.seconds
    payload = {
        "path": str(path),
        "triangles": solid.triangles,
        "volume_mm3": solid.volume_mm3,
        "max_deviation_mm": solid.max_deviation_mm,
        "tolerance_mm": solid.tolerance_mm,
        "checked_points": solid.checked_points,
        "seconds": seconds,
        "watertight": solid.watertight,
    }
    line = (f"stl: {Path(path)}, {solid.triangles} triangles, volume {solid.volume_mm3:.6e} mm^3, "
            f"largest deviation {solid.max_deviation_mm:.2g} mm (tolerance {tolerance:g}, checked at "
            f"{solid.checked_points} points), {seconds:.1f} s")
    emit(line, payload, args.json)
    return 0
