"""``fabkit analyze SPEC TRACK [TRACK ...] [--json] [--plot PNG]``: tracked launches and releases."""

from __future__ import annotations

import sys

from ..lab.summary import NotWritten, fitted_spec_text, summary_lines
from ..spec import load_spec
from ._common import Timer, check_paths, emit, plot_format, prepare_simulator, quiet, stage_bar


def _video_map(args):
    from ..lab.tracks import VideoMap, check_options

    check_options(fps=args.fps, scale=args.scale, origin=args.origin, rotate=args.rotate)
    return VideoMap(scale=args.scale if args.scale is not None else 1.0,
                    origin=tuple(args.origin) if args.origin else (0.0, 0.0),
                    rotate=float(args.rotate or 0.0), flip_y=bool(args.flip_y))


def _public(d):
    """A result without its plotting arrays (keys starting with '_')."""
    if isinstance(d, dict):
        return {k: _public(v) for k, v in d.items() if not str(k).startswith("_")}
    if isinstance(d, list):
        return [_public(v) for v in d]
    return d


def run(args) -> int:
    from ..lab.analyze import analyze, screen_tracks
    from ..lab.tracks import read_track
    from ..physics.models import problem_from_spec

    timer = Timer()
    check_paths(args, {"--plot": args.plot})
    # the figure must not overwrite a track
    from ..io import check_outputs

    check_outputs({"--plot": args.plot, "--output": args.output}, inputs=[*args.tracks, args.spec])
    spec = load_spec(args.spec, need=("surface", "simulation"), command="analyze")
    vm = _video_map(args)
    # stages: the tracks, the simulator, the analysis and the fit (, the figure, the spec)
    stage, close = stage_bar(3 + bool(args.plot) + bool(args.output), quiet(args), "analyze")
    try:
        stage(f"reading {len(args.tracks)} track{'s' if len(args.tracks) != 1 else ''}")
        tracks = [read_track(p, fps=args.fps, video=vm, units=spec.units) for p in args.tracks]
        problem = problem_from_spec(spec)
        screens = screen_tracks(problem, tracks)     # refusals before the simulator loads
        if any(sc["kind"] in ("launch", "release") for sc in screens):   # the fits run on the engine too
            stage("compiling or loading the simulator")
            prepare_simulator(problem, say=None if quiet(args) else (lambda m: stage(m, advance=False)))
        stage("simulating the tracks and fitting the losses")
        res = analyze(problem, tracks, screens)
        for r, tr in zip(res["tracks"], tracks):
            r["_track"] = {"t": tr.t, "x": tr.x, "y": tr.y}
        res["seconds"] = timer.seconds
        payload = _public(res)
        lines = summary_lines(res, spec.units)
        if problem.model != "ball" and spec.has("ball"):
            # a camera (fabkit track, Tracker) sees the ball's centre; a point model moves a point
            # on the surface: its fit of a centre track is biased (benchmarks/lab_loop_video.py)
            note = (f"note: simulation.model {problem.model} takes each track as the path of a point on the "
                    f"surface, while a camera (fabkit track, Tracker) sees the ball's centre, "
                    f"{float(spec.ball.diameter) / 2:g} {spec.units} above it along the normal: on tracked "
                    "video its speeds and losses come out biased (rendered launches: v_in 3-5 % high, damping "
                    "+39 %); analyze centre tracks with simulation.model: ball")
            lines.append(note)
            payload["model_note"] = note
        refused = None
        fitted_text = None
        if args.output:
            try:
                fitted_text = fitted_spec_text(spec, res, tracks)    # refused before any write
            except NotWritten as exc:
                refused = str(exc)
        if args.plot:
            from ..io import write_atomic
            from ..plots import analyze_figure

            stage("drawing the figure")
            png = analyze_figure(res["tracks"], title=f"{spec.name}: tracks and the {problem.model} model",
                                 units=spec.units, fmt=plot_format(args.plot))
            write_atomic(args.plot, png)
            payload["plot"] = str(args.plot)
            lines.append(f"wrote {args.plot}")
        if args.output and refused is None:
            from ..io import write_atomic

            stage("writing the fitted spec")
            write_atomic(args.output, fitted_text)
            payload["output"] = str(args.output)
            lines.append(f"wrote {args.output} (the spec with the {res['losses']['chosen']} law's losses)")
    finally:
        close()
    if refused is not None:
        payload["output"] = None
        payload["output_refused"] = refused
    emit(lines, payload, args.json)
    if refused is not None:
        # the analysis is printed first; then the refusal, nothing written, exit 1
        sys.stderr.write(f"fabkit analyze: --output {args.output}: {refused}\n")
        return 1
    return 0
