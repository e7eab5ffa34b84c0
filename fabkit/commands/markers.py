"""``fabkit markers SPEC [-o markers.pdf|.svg|.png] [--json]``: the page to print for `fabkit track`.

ArUco markers 0-3 of OpenCV's DICT_4X4_50 at true size (``lab.marker_size``: the
black square's side, default 30 mm), each with its white quiet zone one module wide
and a thin cut line around it, and where each goes: its centre in work mm
(``lab.markers``, or by default at the block's corners on the uncut top face, clear of
the milled surface by the tool's radius and off the ramp:
:func:`fabkit.lab.camera.marker_layout`), its top edge toward +Y, and a plan of the
block to scale with the milled region (the surface below the top face, shaded), the
ramp's footprint and the markers' papers. The page is A4 (larger when the markers need
it); PDF and SVG are vector (the markers are drawn module by module, never rasterised),
PNG is 600 dpi up to MAX_PNG_PIXELS (a larger page is rendered at the dpi that fits, and
said: print the PDF for true size). Print at 100 % ("actual size"), then measure the
100 mm scale bar.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np

from ..errors import SpecError
from ..units import MM_PER_INCH
from ._common import Timer, check_paths, default_output, emit, warn

FORMATS = {".pdf": "pdf", ".svg": "svg", ".png": "png"}
A4 = (210.0, 297.0)
PNG_DPI = 600
MAX_PNG_PIXELS = 40_000_000      # an A4 page at 600 dpi is 35 Mpx (140 MB of RGBA while drawn)


def png_dpi(page_mm: tuple[float, float]) -> int:
    """The PNG's resolution: PNG_DPI, or less so that the page stays within MAX_PNG_PIXELS."""
    w, h = (v / MM_PER_INCH for v in page_mm)
    return int(min(PNG_DPI, math.floor(math.sqrt(MAX_PNG_PIXELS / (w * h)))))


def page_size(layout) -> tuple[float, float]:
    """The page (width, height) in mm for the layout's markers (A4 or larger)."""
    s, m = layout.size, layout.module
    cell = s + 2 * m + 12.0
    margin = 15.0
    return max(A4[0], 2 * cell + 2 * margin), max(A4[1], 2 * (cell + 16.0) + 70.0 + 60.0 + 2 * margin)


def _bits(i: int) -> np.ndarray:
    """(6, 6) bool: marker i's modules, True = black, row 0 at the top."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    return cv2.aruco.generateImageMarker(d, int(i), 6) < 128


def sheet(layout, L: float, W: float, name: str, camera_height, fmt: str, plan=None) -> bytes:
    """The page as bytes (see the module doc). Lengths in mm; ``layout`` a MarkerLayout;
    ``plan`` the block's top face (:func:`fabkit.lab.camera.top_face_plan`) to draw the
    milled region and the ramp on the block's plan."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    s, m = layout.size, layout.module
    paper = s + 2 * m                              # the square and its quiet zone
    cell = paper + 12.0                            # room for the label under each
    margin = 15.0
    plan_h = 70.0
    pw, ph = page_size(layout)
    fig = plt.figure(figsize=(pw / MM_PER_INCH, ph / MM_PER_INCH))
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(0, pw)
    ax.set_ylim(0, ph)
    ax.set_aspect("equal")
    ax.set_axis_off()
    y = ph - margin
    ax.text(margin, y, f"{name}: ArUco markers for fabkit track (DICT_4X4_50, ids 0-3)", fontsize=11,
            va="top", weight="bold")
    y -= 7
    ax.text(margin, y, f"Print at 100 % (actual size). Black square {s:g} mm; the 100 mm bar below must "
            "measure 100 mm.", fontsize=8, va="top")
    y -= 5
    ax.text(margin, y, "Cut along the grey line (the white border is part of the marker) and stick each "
            "flat on the block's top face,", fontsize=8, va="top")
    y -= 4
    ax.text(margin, y, "its centre at the work coordinates given, the arrow (its top edge) toward +Y.",
            fontsize=8, va="top")
    y -= 8
    ax.add_patch(Rectangle((margin, y - 2), 100, 2, color="black", lw=0))
    for k in range(11):
        ax.plot([margin + 10 * k] * 2, [y - 2, y + (1.5 if k % 5 == 0 else 0.8)], color="black", lw=0.4)
    ax.text(margin + 102, y - 1, "100 mm", fontsize=7, va="center")
    top = y - 10
    for i in range(4):
        col, row = i % 2, i // 2
        x0 = margin + col * (pw - 2 * margin - cell) + (cell - paper) / 2
        y0 = top - (row + 1) * (cell + 16.0) + 16.0
        ax.add_patch(Rectangle((x0, y0), paper, paper, fill=False, ec="0.6", lw=0.3, ls="--"))
        bits = _bits(i)
        for r in range(6):
            for c in range(6):
                if bits[r, c]:
                    ax.add_patch(Rectangle((x0 + m + c * m, y0 + m + (5 - r) * m), m, m, color="black", lw=0,
                                           antialiased=False))
        cx, cy = layout.centres[i]
        ax.annotate("", xy=(x0 + paper / 2, y0 + paper + 6), xytext=(x0 + paper / 2, y0 + paper + 1),
                    arrowprops={"arrowstyle": "->", "lw": 0.6})
        ax.text(x0 + paper / 2 + 2, y0 + paper + 3.5, "+Y", fontsize=6, va="center")
        ax.text(x0 + paper / 2, y0 - 3, f"marker {i}: centre X = {cx:.1f} mm, Y = {cy:.1f} mm", fontsize=7,
                ha="center", va="top")
    # the plan of the block, to scale
    k = min((pw - 2 * margin) / L, plan_h / W)
    bx, by = margin, margin + 12
    ax.add_patch(Rectangle((bx, by), L * k, W * k, fill=False, ec="black", lw=0.6))
    legend = []
    if plan is not None:
        if plan.cut.any():
            # the milled region: the surface below the top face (vector polygons, 0.05 mm and deeper)
            ax.contourf(bx + plan.X * k, by + plan.Y * k, plan.depth_mm, levels=[0.0, np.inf], colors=["0.82"])
            ax.contour(bx + plan.X * k, by + plan.Y * k, plan.depth_mm, levels=[0.0], colors=["0.45"],
                       linewidths=0.3)
            legend.append("grey: milled (the surface below the top face)")
        if plan.ramp is not None:
            X0, X1, Y0, Y1 = plan.ramp
            ax.add_patch(Rectangle((bx + X0 * k, by + Y0 * k), (X1 - X0) * k, (Y1 - Y0) * k, fill=False,
                                   ec="0.3", lw=0.4, hatch="////"))
            legend.append("hatched: the ramp's footprint")
    for i, (cx, cy) in enumerate(layout.centres):
        ax.add_patch(Rectangle((bx + (cx - paper / 2) * k, by + (cy - paper / 2) * k), paper * k, paper * k,
                               fill=True, fc="white", ec="0.4", lw=0.3))
        ax.add_patch(Rectangle((bx + (cx - s / 2) * k, by + (cy - s / 2) * k), s * k, s * k, color="black", lw=0))
        ax.text(bx + cx * k, by + (cy + s / 2) * k + 1, str(i), fontsize=7, ha="center", va="bottom")
    ax.annotate("", xy=(bx + 14, by - 4), xytext=(bx, by - 4), arrowprops={"arrowstyle": "->", "lw": 0.6})
    ax.text(bx + 15, by - 4, "X", fontsize=7, va="center")
    ax.annotate("", xy=(bx - 4, by + 14), xytext=(bx - 4, by), arrowprops={"arrowstyle": "->", "lw": 0.6})
    ax.text(bx - 4, by + 15, "Y", fontsize=7, ha="center", va="bottom")
    ax.text(bx, by + W * k + 4, f"the block's top face from above: {L:g} x {W:g} mm, origin (0, 0) at the "
            "corner of smallest x and y of the design (the work origin)" , fontsize=7, va="bottom")
    cam = (f"camera: about {camera_height:g} mm above the top face (lab.camera_height), looking down"
           if camera_height else "camera: 1 to 1.6 m above the top face, looking down; measure its height "
           "(lab.camera_height) to improve the calibration")
    ax.text(bx, by - 9, cam, fontsize=7, va="top")
    if legend:
        ax.text(bx, by - 13, "; ".join(legend) + "; each marker's paper outlined", fontsize=7, va="top")
    buf = io.BytesIO()
    meta = {"pdf": {"CreationDate": None, "Producer": None, "Creator": None},
            "svg": {"Date": None, "Creator": None}, "png": {"Software": None}}[fmt]
    fig.savefig(buf, format=fmt, dpi=png_dpi((pw, ph)) if fmt == "png" else PNG_DPI, metadata=meta)
    plt.close(fig)
    return buf.getvalue()


def run(args) -> int:
    from ..io import atomic_outputs
    from ..lab.camera import marker_layout, top_face_plan
    from ..spec import load_spec
    from ..surface import Surface

    timer = Timer()
    spec = load_spec(args.spec, need=("surface",), command="markers")
    path = default_output(spec, ".markers.pdf", args.output)
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise SpecError(f"cannot write the markers as '{Path(path).suffix}' (use .pdf, .svg or .png)",
                        key="--output")
    check_paths(args, {"--output": path})
    surface = Surface.from_spec(spec)
    layout = marker_layout(spec, surface)
    for n in layout.notes:
        warn(n)
    L, W = surface.stock_size_mm
    height = spec.lab.camera_height if spec.has("lab") else None
    plan = top_face_plan(spec, surface)
    data = sheet(layout, L, W, spec.name, height, fmt, plan=plan)
    dpi = png_dpi(page_size(layout)) if fmt == "png" else None
    with atomic_outputs() as out:
        out.write(path, data)
    payload = {"path": str(path), "dictionary": "DICT_4X4_50", "ids": [0, 1, 2, 3], "marker_size_mm": layout.size,
               "quiet_zone_mm": layout.module, "centres_mm": layout.centres.tolist(), "block_mm": [L, W],
               "camera_height_mm": height, "notes": list(layout.notes), "page_mm": list(page_size(layout)),
               "dpi": dpi, "tool_margin_mm": plan.margin_mm,
               "ramp_footprint_mm": list(plan.ramp) if plan.ramp is not None else None, "seconds": timer.seconds}
    where = "; ".join(f"{i}: [{c[0]:.1f}, {c[1]:.1f}]" for i, c in enumerate(layout.centres))
    where_from = "lab.markers" if spec.has("lab") and spec.lab.markers is not None else (
        "each paper on the uncut top face, clear of the milled surface"
        + (f" by the tool's radius {plan.margin_mm:g} mm" if plan.margin_mm else "")
        + (" and off the ramp" if plan.ramp is not None else ""))
    lines = [f"markers: {path}, 4 markers of {layout.size:g} mm (DICT_4X4_50), centres in work mm {where} "
             f"({where_from})"]
    if dpi is not None and dpi < PNG_DPI:
        lines.append(f"note: the page ({page_size(layout)[0]:.0f} x {page_size(layout)[1]:.0f} mm) is rendered at "
                     f"{dpi} dpi to stay within {MAX_PNG_PIXELS / 1e6:g} Mpx; print the PDF for true size")
    emit(lines, payload, args.json)
    return 0
