"""`fabkit time` against grbl 1.1h's own gcode parser, arcs, planner and segment
generator, on programs made here (not used by the tests): arcs in the three planes
(I J K and R, helical, full circles), dwells, incremental moves, inch programs,
spindle and coolant changes, programs in the styles of hand-written code and of
other CAM tools, on three profiles.

The reference is built from grbl's public sources outside this repository (see
docs/machine.md, "Against grbl 1.1h's own planner"): set GRBLTIME to its driver, a
program that reads `$N=value` lines then G-code and prints the run time in seconds.

    GRBLTIME=/path/to/grbltime python benchmarks/time_reference.py [--seed N]
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile

import numpy as np

from fabkit.errors import SpecError
from fabkit.machine.planner import run_time
from fabkit.machine.profile import parse_grbl

PROFILES = {
    "defaults": "$11=0.010\n$12=0.002\n$100=250\n$101=250\n$102=250\n$110=500\n$111=500\n$112=500\n"
                "$120=10\n$121=10\n$122=10\n$130=200\n$131=200\n$132=200\n",
    "router": "$11=0.010\n$12=0.002\n$100=80\n$101=80\n$102=400\n$110=5000\n$111=5000\n$112=1500\n"
              "$120=500\n$121=500\n$122=200\n$130=800\n$131=800\n$132=150\n",
    "unequal": "$11=0.020\n$12=0.010\n$100=320\n$101=160\n$102=1600\n$110=2400\n$111=1200\n$112=400\n"
               "$120=150\n$121=60\n$122=25\n$130=600\n$131=400\n$132=100\n",
}


def _f(v):
    return f"{v:.4f}".rstrip("0").rstrip(".")


def arcs_program(rng, plane: int, inch: bool = False) -> str:
    """Arcs in one plane: I J K and R, both directions, helical, full circles, joined
    by lines; spindle on, a coolant change."""
    k = 1 / 25.4 if inch else 1.0
    a0, a1, al = {17: "XYZ", 18: "ZXY", 19: "YZX"}[plane]
    ia = {"X": "I", "Y": "J", "Z": "K"}
    out = [f"G{20 if inch else 21} G90 G{plane} G94", "M3 S12000", "M8", f"G0 {a0}0 {a1}0 {al}0"]
    p = [0.0, 0.0]
    lin = 0.0
    for i in range(int(rng.integers(25, 45))):
        f = float(rng.choice([300, 800, 1500, 3000, 6000]))
        kind = rng.integers(0, 4)
        cw = rng.integers(0, 2)
        if kind == 0:           # a line
            p = [p[0] + rng.uniform(-20, 20), p[1] + rng.uniform(-20, 20)]
            out.append(f"G1 {a0}{_f(p[0] * k)} {a1}{_f(p[1] * k)} F{_f(f * k)}")
            continue
        r = rng.uniform(0.5, 30)
        phi = rng.uniform(0, 2 * math.pi)
        c = [p[0] - r * math.cos(phi), p[1] - r * math.sin(phi)]
        sweep = rng.uniform(0.1, 5.5) * (-1 if cw else 1)
        if kind == 3:
            sweep = 0.0         # full circle
        end = [c[0] + r * math.cos(phi + sweep), c[1] + r * math.sin(phi + sweep)]
        dl = rng.uniform(-3, 3) if rng.random() < 0.3 else 0.0
        lin += dl
        g = "G2" if cw else "G3"
        if kind == 2 and sweep != 0.0 and abs(sweep) < math.pi:
            out.append(f"{g} {a0}{_f(end[0] * k)} {a1}{_f(end[1] * k)} {al}{_f(lin * k)} R{_f(r * k)} F{_f(f * k)}")
            end = None
        if end is not None:
            out.append(f"{g} {a0}{_f(end[0] * k)} {a1}{_f(end[1] * k)} {al}{_f(lin * k)} "
                       f"{ia[a0]}{_f((c[0] - p[0]) * k)} {ia[a1]}{_f((c[1] - p[1]) * k)} F{_f(f * k)}")
        else:
            end = [c[0] + r * math.cos(phi + sweep), c[1] + r * math.sin(phi + sweep)]
        p = [float(round(end[0] * k, 4) / k), float(round(end[1] * k, 4) / k)]
    out += ["M9", "M5", "M30"]
    return "\n".join(out) + "\n"


def hand_program(rng) -> str:
    """A hand-written style: incremental moves, dwells, spindle speed and coolant changes,
    repeated M3, comments, line numbers, a % line."""
    out = ["%", "(hand written)", "N10 G21 G17 G90", "N20 M3 S8000 ; spindle on", "N30 G4 P1.5"]
    n = 40
    out.append(f"N{n} G0 X5 Y5 Z2")
    out.append("G91")
    for i in range(int(rng.integers(80, 160))):
        n += 10
        r = rng.random()
        if r < 0.08:
            out.append(f"N{n} M3 S{int(rng.choice([8000, 8000, 12000, 16000]))}")
        elif r < 0.12:
            out.append(f"N{n} M3")
        elif r < 0.16:
            out.append(f"N{n} {rng.choice(['M8', 'M9', 'M7', 'M8'])}")
        elif r < 0.2:
            out.append(f"N{n} G4 P{rng.uniform(0.01, 2):.2f}")
        elif r < 0.25:
            dx = round(rng.uniform(1, 8), 3)
            out.append(f"N{n} G{rng.choice([2, 3])} X{dx:.3f} Y0 I{dx / 2:.4f} J0 F{rng.integers(200, 2000)}")
        elif r < 0.3:
            out.append(f"N{n} G0 X{rng.uniform(-20, 20):.3f} Y{rng.uniform(-20, 20):.3f}")
        else:
            out.append(f"N{n} G1 X{rng.uniform(-6, 6):.3f} Y{rng.uniform(-6, 6):.3f} Z{rng.uniform(-0.5, 0.5):.3f} "
                       f"F{rng.integers(100, 4000)} (cut)")
    out += ["G90", "M5", "M9", "M2", "%"]
    return "\n".join(out) + "\n"


def cam_program(rng, inch: bool) -> str:
    """A CAM-style adaptive/contour program: header, modal G1 lines without G, arcs with
    R and IJK in the XY plane, plunges, ramps, S changes between operations."""
    k = 1 / 25.4 if inch else 1.0
    out = ["%", "O1001 (CAM)".replace("O1001 ", ""), f"N1 G{20 if inch else 21}", "N2 G90 G94 G17 G91.1",
           "N3 G53 G0 Z0", "N4 M3 S10000", "N5 G54", "N6 M8", "N7 G0 X0 Y0", "N8 G0 Z5"]
    x = y = 0.0
    z = 5.0
    for op in range(3):
        out.append(f"(operation {op + 1})")
        out.append(f"S{[10000, 14000, 18000][op]} M3")
        out.append(f"G1 Z{_f(-1 * k)} F{_f(300 * k)}")
        f = [1200, 2500, 4000][op]
        out.append(f"G1 X{_f(x * k)} F{_f(f * k)}")
        for i in range(int(rng.integers(150, 300))):
            if rng.random() < 0.15:
                r = rng.uniform(0.3, 6)
                ang = rng.uniform(0.2, 2.5)
                ccw = rng.random() < 0.5
                h = rng.uniform(0, 2 * math.pi)
                cx, cy = x - r * math.cos(h), y - r * math.sin(h)
                e = h + (ang if ccw else -ang)
                nx, ny = cx + r * math.cos(e), cy + r * math.sin(e)
                out.append(f"{'G3' if ccw else 'G2'} X{_f(nx * k)} Y{_f(ny * k)} I{_f((cx - x) * k)} J{_f((cy - y) * k)}")
                x, y = round(nx * k, 4) / k, round(ny * k, 4) / k
            else:
                x += rng.uniform(-2, 2)
                y += rng.uniform(-2, 2)
                out.append(f"{'G1 ' if out[-1][:2] in ('G2', 'G3') else ''}X{_f(x * k)} Y{_f(y * k)}")
        out.append(f"G0 Z{_f(z * k)}")
    out += ["M9", "M5", "G53 G0 Z0", "M30", "%"]
    return "\n".join(out) + "\n"


def cases(seed: int):
    """The programs (an R arc the generator rounds off its circle is refused by grbl and by
    fabkit alike: such a seed is skipped by the caller)."""
    rng = np.random.default_rng(seed)
    yield "arcs G17", arcs_program(rng, 17)
    yield "arcs G18", arcs_program(rng, 18)
    yield "arcs G19 (inch)", arcs_program(rng, 19, inch=True)
    yield "hand (incremental, dwells, M3/S/coolant)", hand_program(rng)
    yield "CAM style (mm)", cam_program(rng, False)
    yield "CAM style (inch)", cam_program(rng, True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=20261128)
    ap.add_argument("--keep", help="folder to keep the programs in")
    a = ap.parse_args()
    exe = os.environ.get("GRBLTIME")
    if not exe or not os.path.exists(exe):
        print("set GRBLTIME to grbl 1.1h's run-time driver (see the docstring)")
        return 2
    worst = 0.0
    print(f"| program | profile | grbl 1.1h (s) | fabkit time (s) | error |\n|---|---|---|---|---|")
    for name, text in cases(a.seed):
        if a.keep:
            with open(os.path.join(a.keep, "".join(c if c.isalnum() else "_" for c in name) + ".nc"), "w") as fh:
                fh.write(text)
        for pname, settings in PROFILES.items():
            m = parse_grbl(settings, pname)
            try:
                ours = run_time(text, m).total_s
            except SpecError as exc:          # grbl refuses it too (checked): not timed
                r = subprocess.run([exe, "/dev/stdin"], input=settings + text, capture_output=True, text=True)
                print(f"| {name} | {pname} | refused: {r.stderr.strip()[:40]} | refused: {exc.detail[:40]} | |")
                break
            with tempfile.NamedTemporaryFile("w", suffix=".nc", delete=False) as fh:
                fh.write(settings + text)
            try:
                r = subprocess.run([exe, fh.name], capture_output=True, text=True, check=True)
            finally:
                os.unlink(fh.name)
            ref = float(r.stdout.split()[0])
            err = 100 * (ours / ref - 1)
            worst = max(worst, abs(err))
            print(f"| {name} | {pname} | {ref:.2f} | {ours:.2f} | {err:+.2f} % |")
    print(f"\nworst |error| {worst:.2f} %")
    # the feed cap's cost: fabkit's stated cost against grbl's run time with the profile
    # minus grbl's run time with $110-$112 raised to the highest programmed feed
    print("\n| program | profile | stated cost (s) | grbl's difference (s) | error |\n|---|---|---|---|---|")
    worst_c = 0.0
    for name, text in cases(a.seed):
        for pname, settings in PROFILES.items():
            m = parse_grbl(settings, pname)
            try:
                rt = run_time(text, m)
            except SpecError:
                break
            if rt.rate_capped_fraction == 0:
                continue
            fmax = max(f for f in run_feeds(text, m))
            raised = settings
            for n, v in zip((110, 111, 112), m.max_rate):
                raised = raised.replace(f"${n}={v:g}\n", f"${n}={max(v, fmax):.3f}\n")
            d = _ref(exe, settings + text) - _ref(exe, raised + text)
            err = 100 * (rt.lost_rate_s / d - 1) if d > 0 else float("nan")
            if d > 1.0:
                worst_c = max(worst_c, abs(err))
            print(f"| {name} | {pname} | {rt.lost_rate_s:.2f} | {d:.2f} | {err:+.2f} % |")
    print(f"\nworst |error| of the cap's cost (differences over 1 s) {worst_c:.2f} %")
    return 0


def run_feeds(text, m):
    from fabkit.machine.program import read_moves

    f = read_moves(text, m.controller, m.arc_tolerance).feed
    return f[np.isfinite(f)]


def _ref(exe, text) -> float:
    with tempfile.NamedTemporaryFile("w", suffix=".nc", delete=False) as fh:
        fh.write(text)
    try:
        return float(subprocess.run([exe, fh.name], capture_output=True, text=True, check=True).stdout.split()[0])
    finally:
        os.unlink(fh.name)


if __name__ == "__main__":
    sys.exit(main())
