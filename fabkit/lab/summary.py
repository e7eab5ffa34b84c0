"""The lab stage's summary: what a person reads of an analysis (one line a track and its
fits, the loss laws compared, eq. (tn)) and the spec with the fitted losses that ``-o``
writes.

Pure functions on :func:`fabkit.lab.analyze.analyze`'s result; no printing, no files
(the command writes them).
"""

from __future__ import annotations

import math


def _num(v, fmt=".5g"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def summary_lines(res, units) -> list[str]:
    """The lines a person reads: each track, the loss laws, eq. (tn), the run's time."""
    u = units
    out = [f"analyze: {len(res['tracks'])} track(s), {res['model']} model; launches simulated with damping "
           f"{res['launch_damping']:.5g} 1/s ({res['launch_damping_source']})"]
    for r in res["tracks"]:
        bt = ", ".join(f"{t:.4f}" for t in r["bounce_times"])
        out.append(f"{r['file']}: {r['kind']}, {r['frames']} frames at {r['fps']:.4g}/s, noise {r['noise_sigma']:.2g} {u}"
                   + (f"; {'; '.join(r['notes'])}" if r["notes"] else ""))
        if r["kind"] == "still":
            continue
        out.append(f"  bounces {r['bounces']}" + (f" at t = {bt} s" if bt else "") + f", outcome {r['outcome']}"
                   + (f" (turns of x that fall back less than {r['bounce_min_dip']:.2g} {u} are below the noise "
                      f"and not counted)" if r["outcome"] == "captured" and r["kind"] == "launch" else ""))
        if r["kind"] == "release":
            if r.get("damping") is None:
                out.append(f"  not fitted: {r.get('fit_status')} (residual rms {r['residual_rms']:.2g} {u} at the "
                           f"best point reached)")
                continue
            out.append(f"  damping {r['damping']:.5g} ± {r['damping_error']:.2g} 1/s (model fit, residual rms "
                       f"{r['residual_rms']:.2g} {u}), omega {_num(r['omega'])} rad/s")
            out.append(f"  paper's log-decrement: damping {_num(r['damping_logdec'])} 1/s, omega "
                       f"{_num(r['omega_logdec'])} rad/s; on the fitted model itself the log-decrement reads "
                       f"{_num(r['logdec_ratio'], '.3f')} x the damping (anharmonic at this amplitude)")
            if r.get("paper_form"):
                out.append(f"  as in the paper: {r['paper_form']}")
        else:
            out.append(f"  v_in {_num(r['v_in'], '.6g')} ± {_num(r.get('v_in_error'), '.2g')} {u}/s, v_out "
                       f"{_num(r['v_out'], '.6g')}" + (f" ± {r['v_out_error']:.2g}" if r.get("v_out_error") else "")
                       + f" {u}/s")
            s = r.get("simulation")
            if s:
                sbt = ", ".join(f"{t:.4f}" for t in s["bounce_times"])
                out.append(f"  simulation: bounces {s['bounces']}" + (f" at t = {sbt} s" if sbt else "")
                           + f", {s['outcome']}, v_out {_num(s['v_out'], '.6g')} {u}/s")
            s = r.get("simulation_fitted_losses")
            if s:
                sbt = ", ".join(f"{t:.4f}" for t in s["bounce_times"][:16])
                out.append(f"  simulation with the fitted {s['law']} losses: bounces {s['bounces']}"
                           + (f" at t = {sbt} s" if sbt else "") + f", {s['outcome']}, v_out "
                           f"{_num(s['v_out'], '.6g')} {u}/s")
            if r.get("T_n") is not None:
                out.append(f"  T_n = {r['T_n']:.4f} s between the bounces, n = {r['n']} transverse maxima")
    lo = res.get("losses")
    if lo and lo.get("laws"):
        kinds = ", ".join(sorted({s.rsplit(": ", 1)[-1] for s in lo["segments"]}))   # release, launch, entry leg...
        head = f"losses ({lo['criterion']} over {len(lo['segments'])} segment(s): {kinds}): "
        out.append(head + (f"the data support {lo['chosen']} (evidence {lo['evidence']})" if lo.get("chosen")
                           else "no law's fit converged: none fitted"))
        for law, f in lo["laws"].items():
            c, e = f["coefficients"], f["errors"]
            if c is None:
                out.append(f"  {law}: not fitted ({f['fit_status']}); not ranked")
                continue
            parts = []
            if "damping" in _LAW_KEYS[law]:
                parts.append(f"damping {c['damping']:.5g} ± {_num(e['damping'], '.2g')} 1/s")
            if "rolling_resistance" in _LAW_KEYS[law]:
                parts.append(f"rolling resistance {c['rolling_resistance']:.5g} ± {_num(e['rolling_resistance'], '.2g')}")
            out.append(f"  {law}: {', '.join(parts)}; residual rms {f['residual_rms']:.3g} {u}, "
                       f"BIC {lo['delta_bic'][law]:+.1f}")
    tn = res.get("tn_fit")
    if tn:
        err = f" (± {tn['T_error']:.2g}, ± {tn['delta_error']:.2g})" if "T_error" in tn else ""
        out.append(f"eq. (tn): T_n = {tn['T']:.4f} n + {tn['delta']:.4f} s{err} over {len(tn['n'])} two-bounce "
                   f"launches, residual max {tn['residual_max']:.2g} s")
    errs = [e for r in res["tracks"] for e in r["bounce_time_errors"]]
    out.append("analyze: " + (f"bounce times ± {max(errs):.1g} s (1 sigma), " if errs else "")
               + f"{res['seconds']:.2f} s")
    return out


_LAW_KEYS = {"viscous": ("damping",), "rolling": ("rolling_resistance",), "both": ("damping", "rolling_resistance")}


class NotWritten(Exception):
    """``-o`` refused: no law was fitted (the reason, one line). The analysis is still
    printed; nothing is written and the command exits 1."""


def fitted_spec_text(spec, res, tracks) -> str:
    """The spec's YAML with the losses of the law the tracks support (simulation.damping,
    ball.rolling_resistance; the other set to 0), validated before it is written. Raises
    :class:`NotWritten` when no law was fitted (no segment, or no law's fit converged with
    its error bars)."""
    import yaml

    from ..io import read_regular
    from ..spec import validate

    lo = res.get("losses") or {}
    law = lo.get("chosen")
    if not law:
        if not lo.get("laws"):
            raise NotWritten("no release or launch to fit the losses to (none, or none whose fit converged): "
                             "nothing written")
        why = "; ".join(f"{k}: {f['fit_status']}" for k, f in lo["laws"].items())
        raise NotWritten(f"no loss law's fit converged ({why}): nothing written")
    coef = lo["laws"][law]["coefficients"]
    err = lo["laws"][law]["errors"]
    for k in ("damping", "rolling_resistance"):
        if not (math.isfinite(coef[k]) and coef[k] >= 0 and math.isfinite(err[k])):
            raise NotWritten(f"the {law} law's fitted {k} is {coef[k]:.4g} ± {err[k]:.2g} (negative or not finite): "
                             "nothing written")
    raw = yaml.safe_load(read_regular(spec.path, 1 << 20, "spec").decode("utf-8-sig"))
    raw.setdefault("simulation", {})["damping"] = float(coef["damping"])
    if not isinstance(raw.get("ball"), dict):
        raw["ball"] = {}
    raw["ball"]["rolling_resistance"] = float(coef["rolling_resistance"])
    validate(raw, str(spec.path))
    head = [f"# {spec.path} with the losses fitted by fabkit analyze to {', '.join(t.file for t in tracks)}:",
            f"# the {law} law ({lo['criterion']}, evidence {lo['evidence']} over the next law); damping "
            f"{coef['damping']:.6g} ± {err['damping']:.2g} 1/s, rolling resistance {coef['rolling_resistance']:.6g} "
            f"± {err['rolling_resistance']:.2g} (one sigma)"]
    class _Dumper(yaml.SafeDumper):
        """Sections as blocks, lists in one line (as the shipped specs write them)."""

    _Dumper.add_representer(list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))
    body = yaml.dump(raw, Dumper=_Dumper, sort_keys=False, default_flow_style=False, allow_unicode=True)
    return "\n".join(head) + "\n" + body
