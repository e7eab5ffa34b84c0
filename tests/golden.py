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


_NUMBER = None


def numbers_close(got: str, want: str, rel: float = 1e-9) -> str | None:
    """None when ``got`` equals ``want`` but for floating-point numbers that agree within
    ``rel`` (relative, or absolute below 1e-300); else the first difference, said.

    The words, keys, integers' digits and layout must match exactly: only the last digits of
    a float may differ, as they do between two builds of numpy, scipy or LLVM (the same code,
    the same inputs, another libm or vectorisation: a few ulps, which a float's shortest repr
    shows in full). A golden output is a contract on the results, not on the last ulp."""
    import re

    global _NUMBER
    if _NUMBER is None:
        _NUMBER = re.compile(r"-?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
    ga, wa = _NUMBER.split(got), _NUMBER.split(want)
    gn, wn = _NUMBER.findall(got), _NUMBER.findall(want)
    if ga != wa or len(gn) != len(wn):
        for i, (a, b) in enumerate(zip(got.splitlines(), want.splitlines())):
            if _NUMBER.sub("#", a) != _NUMBER.sub("#", b):
                return f"line {i + 1}: {a[:160]!r} != {b[:160]!r}"
        return "the texts differ in their words or layout"
    for a, b in zip(gn, wn):
        if a == b:
            continue
        is_float = any(c in a + b for c in ".eE")
        x, y = float(a), float(b)
        if not is_float or abs(x - y) > rel * max(abs(x), abs(y), 1e-300):
            return f"{a} != {b} (beyond {rel:g} relative)"
    return None
