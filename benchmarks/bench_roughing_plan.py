"""Time the roughing and rest planning (fabkit/toolpath/rough/roughing.py) against the
finishing plan, and print each operation's figures.

    python benchmarks/bench_roughing_plan.py [SPEC] (default specs/surface_roughing.yaml)

CPU seconds (time.process_time, not wall time, which a loaded machine inflates) of
``plan_toolpath`` (the finish) and of ``plan_operations`` (rough + rest); levels,
loops or runs, points, cutting length and the time by length / feed of each.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fabkit.spec import load_spec  # noqa: E402
from fabkit.surface import Surface  # noqa: E402
from fabkit.toolpath.finish.raster import plan_toolpath  # noqa: E402
from fabkit.toolpath.rough.roughing import plan_operations  # noqa: E402


def main(argv):
    path = argv[0] if argv else str(ROOT / "specs" / "surface_roughing.yaml")
    spec = load_spec(path)
    surf = Surface.from_spec(spec)
    c0 = time.process_time()
    finish = plan_toolpath(spec, surf)
    c1 = time.process_time()
    ops = plan_operations(spec, surf, finish)
    c2 = time.process_time()
    print(f"{path}: finish plan {c1 - c0:.2f} s CPU, rough + rest plan {c2 - c1:.2f} s CPU")
    feed = float(spec.machining.feed)
    for o in ops:
        i = o.info
        print(f"  {o.kind:6s} {o.tool.describe():32s} levels {o.levels:3d}  loops/runs {o.passes:5d}  "
              f"points {i['points']:7d}  cutting {i['cutting_length_mm'] / 1000:6.1f} m  "
              f"{i['time_by_length_feed_s'] / 60:5.1f} min by length/feed  cusp {i['cusp_mm']:.3f} mm")
    print(f"  finish {'':32s} points {len(finish):7d}  cutting {finish.info['cutting_length_mm'] / 1000:6.1f} m  "
          f"{finish.info['cutting_length_mm'] / feed:5.1f} min by length/feed (feed moves at machining.feed)")


if __name__ == "__main__":
    main(sys.argv[1:])
