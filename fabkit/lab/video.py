"""Decoding videos with PyAV: grey frames and their presentation times.

Each frame's time is its presentation timestamp (pts x the stream's time base), never
frame index / fps: phones record at a variable frame rate. Times are in seconds as
the container gives them (most recordings start at t = 0), computed exactly (a
Fraction) before the one rounding to a float. Grey is the decoder's luma plane (Y of YUV,
read in place without a colour conversion); other pixel formats are converted.

A file PyAV cannot open, or one without a video stream, is a :class:`SpecError`
naming the file (exit 2). So is a video whose timestamps jump back (two recordings
joined: the time restarts), refused with the frame where it happens rather than
tracked in part: each recording is to be tracked on its own. A repeated timestamp is
one frame shown twice, kept once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SpecError

JUMP_BACK_S = 1e-6          # a timestamp this far before the last one: the time restarts (refused)
LUMA_FORMATS = ("yuv420p", "yuvj420p", "yuv422p", "yuvj422p", "yuv444p", "yuvj444p", "nv12", "nv21", "gray")


@dataclass(frozen=True)
class VideoInfo:
    """What the container says: size in px, the frame count (an estimate for some
    containers: 0 when unknown), the nominal rate (1/s) and the codec's name."""

    path: str
    width: int
    height: int
    frames: int
    rate: float
    codec: str


def _open(path):
    import av

    try:
        container = av.open(str(path))
    except FileNotFoundError:
        raise SpecError("no such file", file=str(path)) from None
    except IsADirectoryError:
        raise SpecError("is a directory, not a video", file=str(path)) from None
    except (av.FFmpegError, ValueError, OSError) as exc:
        raise SpecError(f"not a video PyAV can read ({type(exc).__name__})", file=str(path)) from None
    if not container.streams.video:
        container.close()
        raise SpecError("has no video stream", file=str(path))
    return container


def info(path) -> VideoInfo:
    """The video's :class:`VideoInfo` (reads the header only)."""
    with _open(path) as c:
        s = c.streams.video[0]
        rate = float(s.average_rate or s.guessed_rate or 0.0)
        return VideoInfo(str(path), int(s.codec_context.width), int(s.codec_context.height),
                         int(s.frames or 0), rate, s.codec_context.name)


def grey(frame) -> np.ndarray:
    """The frame's grey image (h, w) uint8: the luma plane in place when there is one."""
    if frame.format.name in LUMA_FORMATS:
        p = frame.planes[0]
        a = np.frombuffer(p, dtype=np.uint8)
        return a.reshape(frame.height, p.line_size)[:, :frame.width]
    return frame.to_ndarray(format="gray")


def frames(path, keyframes_only: bool = False):
    """Yield (t, grey) for each frame in presentation order: t in s from the first frame's
    time, grey (h, w) uint8 (valid until the next frame is read: copy it to keep it).

    ``keyframes_only``: decode only the key frames (fast: a sample of the video)."""
    import av

    with _open(path) as c:
        s = c.streams.video[0]
        s.thread_type = "AUTO"
        if keyframes_only:
            s.codec_context.skip_frame = "NONKEY"
        first = True
        last = None
        index = -1
        try:
            for frame in c.decode(s):
                index += 1
                pts = frame.pts
                if pts is None or frame.time_base is None:
                    raise SpecError(f"a frame without a presentation timestamp (after t = {last} s)",
                                    file=str(path))
                first = False
                t = float(pts * frame.time_base)     # exact: a Fraction until here
                if last is not None and t < last - JUMP_BACK_S:
                    where = "" if keyframes_only else f" at frame {index}"
                    raise SpecError(f"the timestamps jump back{where} (t = {t:.4f} s after {last:.4f} s): "
                                    "two recordings joined? Split it where the time restarts and track each part",
                                    file=str(path))
                if last is not None and t <= last:
                    continue      # a repeated or out-of-order timestamp: the frame is shown once
                last = t
                yield t, grey(frame)
        except av.FFmpegError as exc:
            if first:
                raise SpecError(f"not a video PyAV can decode ({type(exc).__name__})", file=str(path)) from None
            # a truncated file: the frames decoded so far stand


def frames_ahead(path, depth: int = 16):
    """:func:`frames` decoded in a thread ahead of the caller (up to ``depth`` frames):
    the decoder (PyAV, which releases the GIL) and the caller's work on the previous
    frames overlap on two cores. Yields (t, grey) with grey a copy the caller may keep.
    An error while decoding is raised here, in the caller's thread."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()
    done = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def work():
        try:
            for t, g in frames(path):
                if not put((t, g.copy())):
                    return
            put(done)
        except BaseException as exc:  # handed to the caller's thread
            put(exc)

    th = threading.Thread(target=work, name="fabkit-decode", daemon=True)
    th.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        th.join(timeout=5)
