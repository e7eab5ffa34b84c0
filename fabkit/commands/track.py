"""``fabkit track SPEC VIDEO [VIDEO ...] [-o OUT | --out-dir DIR] [--json] [--plot PNG]
[--review PNG] [--no-progress]``: videos of the block -> the ball centre's calibrated trajectories.

Per video: the markers calibrate the camera, the ball is found in every frame and its
centre placed on the ball-centre offset surface (:mod:`fabkit.lab.track`). Each track
is written as ``t,x,y,sigma_x,sigma_y`` (s, design units), the text `fabkit analyze`
reads. Every video is tracked before anything is written: a bad one (not a video,
markers not found, ball never found) is one line, exit 2, and no track is written.

The summary says how many frames were left out and why (the gap's reasons), and warns
(on stderr, exit still 0) when more than DOUBTFUL_SHARE of a video's frames had a ball
seen but not separable (partly hidden, merged with the surface or its shadow, a bad
fit). ``--review PNG`` writes a contact sheet of the first video: crops around the ball
for a spread of frames with the fitted silhouette, the rejected shadow and the gaps.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import SpecError
from ..lab.track import DOUBTFUL_SHARE
from ._common import DEFAULT_OUTPUT_DIR, Timer, check_paths, emit, plot_format, progress_bar, warn

SUFFIX = ".track.csv"


def _outputs(args) -> list[Path]:
    if args.output and args.out_dir:
        raise SpecError("give -o/--output (one video) or --out-dir (any number), not both", key="--output")
    if args.output:
        if len(args.videos) != 1:
            raise SpecError(f"names one track file but {len(args.videos)} videos are given: use --out-dir",
                            key="--output")
        return [Path(args.output)]
    folder = Path(args.out_dir) if args.out_dir else DEFAULT_OUTPUT_DIR
    outs = [folder / (Path(v).stem + SUFFIX) for v in args.videos]
    seen = {}
    for v, o in zip(args.videos, outs):
        if o in seen:
            raise SpecError(f"{v} and {seen[o]} would both write {o}: rename one", key="--out-dir")
        seen[o] = v
    return outs


def track_figure(result, fmt: str = "png") -> bytes:
    """A frame of the video with the track (every tracked centre, px), the markers'
    corners as found (+) and as the calibrated camera reprojects them (o), and the
    ball's disc in that frame."""
    import numpy as np

    from ..plots import new_figure as _figure, png_bytes as _png
    from ..lab.camera import MARKER_IDS

    img = result.snapshot
    h, w = img.shape
    plt, fig = _figure(figsize=(8.0, 8.0 * h / w + 0.3))
    ax = fig.add_axes([0.0, 0.0, 1.0, 1.0 - 0.3 / (8.0 * h / w + 0.3)])
    ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    ok = np.all(np.isfinite(result.uv), axis=1)
    ax.plot(result.uv[ok, 0], result.uv[ok, 1], "-", color="tab:red", lw=0.8, alpha=0.8)
    ax.plot(result.uv[ok, 0], result.uv[ok, 1], ".", color="tab:red", ms=2)
    cal = result.calibration
    rep = cal.camera.project(np.concatenate([np.c_[c, np.zeros(4)] for c in _layout_corners(cal)]))
    ax.plot(rep[:, 0], rep[:, 1], "o", mfc="none", mec="tab:cyan", ms=6, mew=1.0)
    for i in MARKER_IDS:
        c = np.asarray(result.corners_px[i])
        ax.plot(c[:, 0], c[:, 1], "+", color="tab:orange", ms=8, mew=1.0)
        ax.text(c[:, 0].mean(), c[:, 1].min() - 6, f"{i}", color="tab:orange", ha="center", va="bottom",
                fontsize=9, weight="bold")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_axis_off()
    j = result.to_json()
    fig.suptitle(f"{Path(result.path).name}: {j['tracked']}/{j['frames']} frames tracked; markers "
                 f"{j['reprojection_rms_px']:.2f} px rms; camera {j['camera']['height_mm']:.0f} mm up"
                 + ("" if j["camera_height_constrained"] else " (assumed)"),
                 fontsize=9, y=0.995, va="top")
    return _png(plt, fig, fmt)


def _layout_corners(cal):
    """The layout's corners (4 markers x 4, 2) work mm, from the calibration's own record."""
    return [c[:, :2] for c in cal.layout_corners]


def _lines(results, outs, units, seconds):
    lines = []
    for r, o in zip(results, outs):
        j = r.to_json()
        cam = j["camera"]
        lines.append(f"{r.path}: {j['tracked']}/{j['frames']} frames tracked ({100 * j['fraction_tracked']:.1f} %), "
                     f"video at {j['frame_rate']:.4g} frames/s" + (" (variable)" if j["variable_frame_rate"] else "")
                     + f" -> {o}")
        if j["camera_height_constrained"]:
            height = f"{cam['height_mm']:.0f} mm up (± {cam['height_sigma_mm']:.2g})"
        else:
            height = (f"height not fixed by the markers (no lab.camera_height): {cam['height_mm']:.0f} mm assumed, "
                      "give lab.camera_height;")
        lines.append(f"  camera {height} tilt "
                     f"{cam['tilt_deg']:.1f} deg, f {cam['focal_px']:.0f} px, k1 {cam['k1']:+.3f}; markers "
                     f"reprojected within {j['reprojection_rms_px']:.2f} px rms ({j['reprojection_rms_mm']:.2f} mm)")
        if j["left_out"]:
            why = ", ".join(f"{k} {v}" for k, v in j["gaps"].items() if v)
            lines.append(f"  left out: {j['left_out']} frames as gaps ({why}); {j['doubtful']} doubtful "
                         f"({100 * j['doubtful_fraction']:.1f} %, warned above {100 * DOUBTFUL_SHARE:.0f} %)")
        if not j["tracked"]:
            lines.append("  no position reported: the ball was never separated (see the reasons above)")
            for n in j["notes"]:
                lines.append(f"  note: {n}")
            continue
        lines.append(f"  ball centre ± {j['position_sigma_median']:.2g} {units} (median 1 sigma; the image noise's "
                     f"share {j['position_sigma_image_median']:.2g}, the calibration's "
                     f"{j['position_sigma_calibration_median']:.2g}; max {j['position_sigma_max']:.2g})")
        for n in j["notes"]:
            lines.append(f"  note: {n}")
    lines.append(f"track: {len(results)} video(s), {seconds:.1f} s")
    return lines


def run(args) -> int:
    from ..io import atomic_outputs, check_outputs
    from ..lab.track import review_png, track_video
    from ..spec import load_spec
    from ..surface import Surface

    timer = Timer()
    outs = _outputs(args)
    review = getattr(args, "review", None)
    check_paths(args, {"--plot": args.plot, "--review": review})
    if review is not None and Path(review).suffix.lower() not in ("", ".png"):
        raise SpecError(f"the review sheet is a PNG: '{Path(review).suffix}' cannot be written", key="--review")
    check_outputs({**{f"track of {v}": o for v, o in zip(args.videos, outs)}, "--plot": args.plot,
                   "--review": review}, inputs=[args.spec, *args.videos])
    spec = load_spec(args.spec, need=("surface", "ball"), command="track")
    surface = Surface.from_spec(spec)
    results = []
    for v in args.videos:
        from ..lab import video as vid

        info = vid.info(v)
        cb, close = progress_bar(info.frames or 1, args.no_progress, Path(v).name, unit="frame")
        try:
            results.append(track_video(spec, surface, v, progress=cb, review=review is not None and not results))
        finally:
            close()
    png = None
    if args.plot:
        png = track_figure(results[0], fmt=plot_format(args.plot))
    sheet = review_png(results[0]) if review is not None else None
    with atomic_outputs() as out:
        for r, o in zip(results, outs):
            out.write(o, r.csv_text())
        if png is not None:
            out.write(args.plot, png)
        if sheet is not None:
            out.write(review, sheet)
    payload = {"tracks": [dict(r.to_json(), output=str(o)) for r, o in zip(results, outs)],
               "units": spec.units, "seconds": timer.seconds}
    if args.plot:
        payload["plot"] = str(args.plot)
    if review is not None:
        payload["review"] = str(review)
    lines = _lines(results, outs, spec.units, timer.seconds)
    if args.plot:
        lines.append(f"wrote {args.plot}")
    if review is not None:
        lines.append(f"wrote {review} (the review sheet of {results[0].path})")
    emit(lines, payload, args.json)
    for r in results:
        j = r.to_json()
        if j["doubtful_warning"]:
            warn(f"{r.path}: {j['doubtful']} of {j['frames']} frames ({100 * j['doubtful_fraction']:.0f} %) had a ball "
                 f"seen but not separable (more than {100 * DOUBTFUL_SHARE:.0f} %): they are gaps; "
                 "check them with --review")
    return 0
