"""What the golden-output tests leave out of a comparison: the fields that differ between
two runs of the same spec (wall and CPU timings, the generation date)."""

from __future__ import annotations

#: keys whose values are timings or dates, dropped from JSON before comparing
DROP = ("generated_at", "timings_s", "seconds")


def strip_volatile(obj):
    """``obj`` (parsed JSON) without the :data:`DROP` keys, at any depth."""
    if isinstance(obj, dict):
        return {k: strip_volatile(v) for k, v in obj.items() if k not in DROP}
    if isinstance(obj, list):
        return [strip_volatile(v) for v in obj]
    return obj
