"""``fabkit analyze``'s loss-law fits on independent tracks: the right law, each
coefficient within 3 sigma and 5 % (10 % for ``both``) of the truth, the CPU time of
one release and one launch with all three laws, and the same output under load.

Tracks: one release and one launch per case, made by an independent model and filmed
at 125 frames/s with 0.3 mm of Gaussian noise (written as ``t,x,y,sigma_x,sigma_y``):

* the point model (tests/lab_sim.py: the paper's eq. xyODE and the rolling resistance
  written out by hand, scipy DOP853 at rtol 1e-12) on tests/fixtures/paper_full.yaml;
* the finite ball (tests/ball_newton_euler.py: Newton-Euler in 3-D, the contact force
  solved; its centre filmed) on specs/surface.yaml.

Values none of the tests use: viscous 0.09 1/s; rolling 0.0035; both 0.06 1/s with
0.0022. Each case runs ``fabkit analyze SPEC release.csv launch.csv --json -o
fitted.yaml`` as a child process (its CPU time from the kernel's accounting), then
``fabkit check fitted.yaml``. With ``--load N`` the same runs are repeated with N
CPU-bound processes running (``python -c "while 1: pass"``) and the two JSON outputs
compared byte for byte (the ``seconds`` fields, wall clocks, left out).

    python benchmarks/lab_fits.py [--load 2] [--model point|ball|both] [--seed K]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))           # this tree's fabkit, not an installed one
sys.path.insert(0, str(ROOT / "tests"))

import lab_sim as L  # noqa: E402

FPS = 125.0
NOISE = 0.03          # cm
CASES = {"viscous": (0.09, 0.0), "rolling": (0.0, 0.0035), "both": (0.06, 0.0022)}
LIMIT = {"viscous": 0.05, "rolling": 0.05, "both": 0.10}
PAPER = ROOT / "tests" / "fixtures" / "paper_full.yaml"
SURFACE = ROOT / "specs" / "surface.yaml"


def _csv(path, t, x, y, seed):
    rng = np.random.default_rng(seed)
    x = x + rng.normal(0, NOISE, t.size)
    y = y + rng.normal(0, NOISE, t.size)
    path.write_text("t,x,y,sigma_x,sigma_y\n" + "".join(
        f"{a:.6f},{b:.6f},{c:.6f},{NOISE:.3g},{NOISE:.3g}\n" for a, b, c in zip(t, x, y)))


SEED = [0]      # the noise seeds' offset (--seed)


def point_tracks(folder: Path, mu: float, crr: float) -> list[Path]:
    rel = L.run((-27.0, 5.5, 0.0, 0.0), mu, 3.0, escape=False, crr=crr)
    la = L.run((L.START, 0.0, 44.0, 0.0), mu, 15.0, crr=crr)
    out = []
    for name, truth, seed in (("release.csv", rel, 11), ("launch.csv", la, 12)):
        t = np.arange(0.0, truth["t_end"], 1.0 / FPS)
        x, y = truth["sol"].sol(t)[:2]
        _csv(folder / name, t, x, y, seed + SEED[0])
        out.append(folder / name)
    return out


def ball_tracks(folder: Path, mu: float, crr: float) -> list[Path]:
    from test_lab_analyze_ball import RollingNewtonEuler, _problem, centre_track

    ne = RollingNewtonEuler(_problem(), mu, crr)
    out = []
    t, X, Y, _ = centre_track(ne, np.array([-27.0, 5.5, 0.0, 0.0, 0.0]), 3.0, 21, noise=0.0)
    _csv(folder / "release.csv", t, X, Y, 21 + SEED[0])
    out.append(folder / "release.csv")
    truth = ne.launch(44.0, t_max=8.0, rtol=1e-10, atol=1e-12)
    t_end = float(truth["t_end"])         # filmed to its escape (or t_max), as the point's
    t, X, Y, _ = centre_track(ne, ne.initial(44.0), t_end, 22, noise=0.0)
    _csv(folder / "launch.csv", t, X, Y, 22 + SEED[0])
    out.append(folder / "launch.csv")
    return out


def run(cmd, cwd) -> tuple[int, str, str, float]:
    """A child process: (code, stdout, stderr, its CPU seconds)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return p.returncode, p.stdout, p.stderr, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def _strip(d):
    if isinstance(d, dict):
        return {k: _strip(v) for k, v in d.items() if k not in ("seconds", "fit_seconds")}
    if isinstance(d, list):
        return [_strip(v) for v in d]
    return d


def analyze_case(spec: Path, files, folder: Path) -> dict:
    exe = [sys.executable, "-m", "fabkit.cli"]
    fitted = folder / "fitted.yaml"
    fitted.unlink(missing_ok=True)
    code, out, err, cpu = run([*exe, "analyze", str(spec), *map(str, files), "--json", "-o", str(fitted)], folder)
    res = {"code": code, "cpu": cpu, "json": json.loads(out) if out.strip() else None, "err": err.strip()}
    if code == 0 and fitted.exists():
        c2, o2, e2, _ = run([*exe, "check", str(fitted), "--json"], folder)
        res["check"] = c2
        res["check_err"] = e2.strip()[-300:]
    return res


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--load", type=int, default=0, help="also run with N CPU-bound processes and diff")
    ap.add_argument("--seed", type=int, default=0, help="offset of the noise seeds")
    ap.add_argument("--case", choices=tuple(CASES), action="append", help="only these cases")
    ap.add_argument("--model", choices=("point", "ball", "both"), default="point",
                    help="the point model on the paper's spec, the finite ball on specs/surface.yaml, or both")
    args = ap.parse_args()
    SEED[0] = args.seed
    models = [m for m in (("point", PAPER, point_tracks), ("ball", SURFACE, ball_tracks))
              if args.model in (m[0], "both")]
    print(f"load average before: {os.getloadavg()[0]:.2f} (2 cores)")
    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        for model, spec, make in models:
            for case, (mu, crr) in CASES.items():
                if args.case and case not in args.case:
                    continue
                folder = Path(tmp) / f"{model}-{case}"
                folder.mkdir()
                files = make(folder, mu, crr)
                r = analyze_case(spec, files, folder)
                lo = r["json"]["losses"] if r["json"] else {}
                chosen = lo.get("chosen")
                line = [f"{model:5s} {case:7s}: exit {r['code']}, CPU {r['cpu']:.1f} s, chosen {chosen}"]
                good = r["code"] == 0 and chosen == case
                if chosen:
                    f = lo["laws"][chosen]
                    for k, truth in (("damping", mu), ("rolling_resistance", crr)):
                        if truth == 0:
                            continue
                        v, e = f["coefficients"][k], f["errors"][k]
                        if k not in f["coefficients"] or not e > 0:
                            good = False
                            line.append(f"{k} not in the chosen law")
                            continue
                        rel = v / truth - 1
                        within = abs(v - truth) <= 3 * e and abs(rel) <= LIMIT[case]
                        good &= within
                        line.append(f"{k} {v:.5g} ± {e:.2g} (truth {truth:g}: {rel:+.2%}, "
                                    f"{abs(v - truth) / e:.1f} sigma)")
                good &= r.get("check") == 0
                line.append(f"check on the fitted spec: exit {r.get('check')}")
                if args.load:
                    hogs = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(args.load)]
                    try:
                        time.sleep(1.0)
                        la = os.getloadavg()[0]
                        r2 = analyze_case(spec, files, folder)
                    finally:
                        for h in hogs:
                            h.kill()
                            h.wait()
                    same = r["json"] is not None and r2["json"] is not None and \
                        json.dumps(_strip(r["json"])) == json.dumps(_strip(r2["json"]))
                    good &= same
                    line.append(f"under load ({args.load} hogs, load {la:.1f}): CPU {r2['cpu']:.1f} s, "
                                f"output {'identical' if same else 'DIFFERENT'}")
                ok &= good
                print(("ok   " if good else "FAIL ") + "; ".join(line), flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
