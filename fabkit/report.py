"""The design report: one self-contained HTML page (no network: data, figures and
scripts inlined). It takes results and computes nothing; ``fabkit report`` computes them.

``render(results) -> str`` with ``results`` a dict:

    name, units, spec_path, generated_at
    check        the pre-fabrication check (physics.check.check), with ``seconds``
    surface      {"x" (nx,), "y" (ny,), "z" (nx, ny) clipped heights, "top", "start", "y0"}
    sweep        {"png": bytes, "v_critical", "v_critical_error", "windows", "error_estimate", "seconds",
                  "launches"}
    toolpath     {"png": bytes, "sheet": setup-sheet dict, "seconds": {...}, "verify": {...} or None,
                  "stock_png": {"rough"|"finish": bytes} (a job with roughing simulated on the stock; optional)}
    calibration  {"heights", "v_in", "g", "k", "units", "seconds"}
    ramp_marks   optional list of {height, v_in, label, observable (optional: False sets it apart)}
    scale        optional: mm per design unit (the windows' width in release height, in mm)
    min_width    optional: the observable windows' least width in release height (design units)

The 3-D view is a small hand-written canvas renderer (painter's algorithm, Lambert
shading): drag to turn it, wheel to zoom; when it has drawn it sets
``data-rendered`` on its canvas (the tests read it back from the DOM).
"""

from __future__ import annotations

import base64
import html
import json
import math

import numpy as np


def _e(s) -> str:
    return html.escape(str(s), quote=True)


def _n(v, fmt=".5g", none="—") -> str:
    if v is None:
        return none
    try:
        f = float(v)
    except (TypeError, ValueError):
        return _e(v)
    if not math.isfinite(f):
        return none
    return format(int(round(f)), fmt) if fmt.endswith("d") else format(f, fmt)


def _img(png: bytes | None, alt: str) -> str:
    if not png:
        return f"<p class=missing>({_e(alt)}: not available)</p>"
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


CSS = """
body{font:15px/1.45 system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:0;color:#1d232a;background:#f6f7f9}
header{padding:18px 28px;background:#24303c;color:#fff}header h1{margin:0;font-size:22px}
header p{margin:4px 0 0;color:#c9d3dd;font-size:13px}
main{padding:10px 28px 40px;max-width:1150px}
section{background:#fff;border:1px solid #dde2e7;border-radius:6px;padding:14px 18px;margin:16px 0}
h2{font-size:17px;margin:0 0 8px}
.verdict{font-size:28px;font-weight:700;padding:10px 16px;border-radius:6px;display:inline-block}
.safe{background:#dff3e3;color:#11622a;border:2px solid #2f9e4f}
.unsafe{background:#fbe3e1;color:#8c1d13;border:2px solid #d9453a}
table{border-collapse:collapse;font-size:13px}td,th{border-bottom:1px solid #e3e7eb;padding:3px 10px;text-align:right}
th{background:#f0f3f6}td.l,th.l{text-align:left}
.meta{color:#5b6875;font-size:12.5px}img{max-width:100%;border:1px solid #e3e7eb}
canvas{border:1px solid #d0d6dc;background:linear-gradient(#fbfcfd,#e9eef2);cursor:grab;max-width:100%}
.grid2{display:grid;grid-template-columns:1fr 1fr;gap:12px}
tr.narrow td,table.narrow td{color:#8a949e;font-style:italic}h4{margin:14px 0 4px;font-size:14px}
"""

VIEWER_JS = r"""
(function(){
  const D = JSON.parse(document.getElementById('surface-data').textContent);
  const cv = document.getElementById('surface3d'), ctx = cv.getContext('2d');
  const nx = D.x.length, ny = D.y.length;
  const cx = (D.x[0]+D.x[nx-1])/2, cy = (D.y[0]+D.y[ny-1])/2;
  let zmin = Infinity, zmax = -Infinity;
  for (const r of D.z) for (const v of r) { zmin = Math.min(zmin, v); zmax = Math.max(zmax, v); }
  const cz = (zmin+zmax)/2;
  const span = Math.max(D.x[nx-1]-D.x[0], D.y[ny-1]-D.y[0]);
  let yaw = -0.6, pitch = 0.9, zoom = 1.0;
  function col(t, shade){ // height colour: blue (low) -> sand (high)
    const a=[38,84,140], b=[225,196,140]; const c=a.map((v,i)=>Math.round((v+(b[i]-v)*t)*shade));
    return 'rgb('+c.join(',')+')'; }
  function draw(){
    const W = cv.width, H = cv.height, s = zoom*0.8*Math.min(W,H)/span;
    const cyw=Math.cos(yaw), syw=Math.sin(yaw), cp=Math.cos(pitch), sp=Math.sin(pitch);
    const P = new Array(nx*ny);
    for (let i=0;i<nx;i++) for (let j=0;j<ny;j++){
      const X=D.x[i]-cx, Y=D.y[j]-cy, Z=(D.z[i][j]-cz);
      const x1 = cyw*X - syw*Y, y1 = syw*X + cyw*Y;
      const y2 = cp*y1 - sp*Z, z2 = sp*y1 + cp*Z;
      P[i*ny+j] = [W/2 + s*x1, H/2 - s*z2, y2]; }
    const quads = [];
    const L = [0.35,-0.45,0.82], ln = Math.hypot(...L);
    for (let i=0;i<nx-1;i++) for (let j=0;j<ny-1;j++){
      const a=P[i*ny+j], b=P[(i+1)*ny+j], c=P[(i+1)*ny+j+1], d=P[i*ny+j+1];
      const dx=D.x[i+1]-D.x[i], dy=D.y[j+1]-D.y[j];
      const zx=((D.z[i+1][j]+D.z[i+1][j+1])-(D.z[i][j]+D.z[i][j+1]))/(2*dx);
      const zy=((D.z[i][j+1]+D.z[i+1][j+1])-(D.z[i][j]+D.z[i+1][j]))/(2*dy);
      const n=[-zx,-zy,1], nn=Math.hypot(...n);
      const lam = Math.max(0,(n[0]*L[0]+n[1]*L[1]+n[2]*L[2])/(nn*ln));
      const zc=(D.z[i][j]+D.z[i+1][j+1])/2;
      quads.push([(a[2]+b[2]+c[2]+d[2])/4, [a,b,c,d], col((zc-zmin)/Math.max(zmax-zmin,1e-12), 0.45+0.55*lam)]); }
    quads.sort((p,q)=>q[0]-p[0]);
    ctx.clearRect(0,0,W,H);
    for (const [_, v, c] of quads){ ctx.beginPath(); ctx.moveTo(v[0][0],v[0][1]);
      for (let k=1;k<4;k++) ctx.lineTo(v[k][0],v[k][1]); ctx.closePath(); ctx.fillStyle=c; ctx.fill();
      ctx.strokeStyle=c; ctx.lineWidth=0.6; ctx.stroke(); }
    // the launch line y = y0 from the entry x to the far end
    ctx.strokeStyle='#d9453a'; ctx.lineWidth=2; ctx.beginPath();
    let first=true;
    for (let i=0;i<nx;i++){ if (D.x[i] < D.start) continue;
      const j = D.jl, p = P[i*ny+j]; if (first){ctx.moveTo(p[0],p[1]); first=false;} else ctx.lineTo(p[0],p[1]); }
    ctx.stroke();
    cv.dataset.rendered = String(quads.length);
  }
  let drag=null;
  cv.addEventListener('mousedown', e=>{drag=[e.clientX,e.clientY,yaw,pitch]; cv.style.cursor='grabbing';});
  window.addEventListener('mouseup', ()=>{drag=null; cv.style.cursor='grab';});
  window.addEventListener('mousemove', e=>{ if(!drag) return; yaw=drag[2]+(e.clientX-drag[0])*0.01;
    pitch=Math.max(0.05,Math.min(1.55,drag[3]+(e.clientY-drag[1])*0.01)); draw(); });
  cv.addEventListener('wheel', e=>{ e.preventDefault(); zoom*=Math.exp(-e.deltaY*0.001); draw(); }, {passive:false});
  draw();
})();
"""


def _verdict(check: dict, units: str) -> str:
    safe = bool(check.get("safe"))
    ff = check.get("first_failure")
    mach = check.get("machining") or {}
    why = []
    if safe:
        why.append(f"every release height of the ramp keeps the ball on the milled part (highest safe "
                   f"height {_n(check.get('highest_safe_height'))} {units}, the top of the ramp)")
    else:
        hs = check.get("highest_safe_height")
        why.append(f"release height {_n(ff['height'])} {units} (v_in {_n(ff['v_in'], '.4g')} {units}/s) "
                   f"{_e(ff['outcome'])} at x={_n(ff['x'], '.4g')}, y={_n(ff['y'], '.4g')}, t={_n(ff['t'], '.3g')} s "
                   f"({_e(ff['reason'])}); highest safe release height "
                   f"{_n(hs) if hs is not None else 'none'} {units}")
    if mach:
        why.append("machining: cut depth " + _n(mach.get("depth_mm"), ".4g") + " mm "
                   + ("within" if mach.get("depth_ok") else "<b>beyond</b>") + " the stock and tool limits"
                   + ("" if mach.get("radius_ok", True) else "; the tool is wider than the smallest concave radius"))
    cls = "safe" if safe else "unsafe"
    word = "SAFE" if safe else "UNSAFE"
    return (f'<div id="verdict" class="verdict {cls}">{word}</div>'
            f'<p id="why">{"; ".join(why)}.</p>')


def _tolerances(check: dict) -> dict:
    """The relative tolerances the check ran with (``CheckReport.tolerances``); the
    check's defaults for a result that does not carry them."""
    from .physics.check import TOLERANCES

    return {**TOLERANCES, **(check.get("tolerances") or {})}


def _observable(w: dict, min_width: float | None) -> bool | None:
    """A window is observable when at least ``min_width`` wide in release height (design
    units; ``fabkit design``'s default, 1 mm); None when the page was given no minimum."""
    if min_width is None:
        return None
    return bool(w["height_hi"] - w["height_lo"] >= min_width * (1 - 1e-12))


def _completeness_note(check: dict, units: str) -> str:
    """Which windows the check is certain to have found (the ramp's sampling)."""
    c = check.get("window_completeness") or {}
    if c.get("certain_width") is None:
        return ""
    dh = c.get("certain_height_width")
    wide = (f"{_n(dh, '.4g')} {units} in release height" if dh is not None
            else f"{_n(c['certain_width'], '.4g')} {units}/s in v_in")
    near = c.get("spacing_near_critical")
    return (f"<p class=meta>Every window wider than {wide} (the sampling's largest spacing) is listed; a narrower "
            f"one only where a launch of the ramp's sampling fell in it"
            + (f" (launches {_n(near, '.4g')} {units}/s apart at v_critical, where the windows narrow)"
               if near is not None else "") + ".</p>")


def _windows_table(check: dict, units: str, scale: float | None = None, min_width: float | None = None) -> str:
    """The reachable two-bounce windows, each column with its unit; with ``min_width``
    (design units of release height) and ``scale`` (mm per design unit) the observable
    ones are marked and the narrower ones set apart (class ``narrow``)."""
    ws = check.get("reachable_windows") or []
    vmax = any(w.get("v_out_max") is not None for w in ws)
    obs = [_observable(w, min_width) for w in ws]
    width_col = scale is not None

    def row(i, w, o):
        width = (w["height_hi"] - w["height_lo"]) * scale if width_col else None
        cls = "" if o is not False else " class=narrow"
        return (f"<tr{cls}><td>{i}</td><td>{_n(w['lo'], '.6g')}</td><td>{_n(w['hi'], '.6g')}</td>"
                f"<td>{_n(w['height_lo'], '.5g')}</td><td>{_n(w['height_hi'], '.5g')}</td>"
                + (f"<td>{_n(width, '.3g')}</td>" if width_col else "")
                + (f"<td>{_n(w.get('v_out_max'), '.5g')}</td>" if vmax else "")
                + ("" if o is None else f"<td class=l>{'<b>yes</b>' if o else 'no: too narrow to hit'}</td>")
                + "</tr>")

    rows = "".join(row(i, w, o) for i, (w, o) in enumerate(zip(ws, obs), start=1))
    if not rows:
        return "<p>No two-bounce window lies inside the ramp's range.</p>" + _completeness_note(check, units)
    count = ""
    if min_width is not None:
        n_obs = sum(bool(o) for o in obs)
        mm = f" ({_n(min_width * scale, 'g')} mm)" if scale is not None else ""
        count = (f"<p id=observable>{n_obs} of {len(ws)} windows are observable: at least "
                 f"{_n(min_width, '.4g')} {units}{mm} wide in release height, the width <code>fabkit design</code> "
                 f"requires of an observable window; the others (greyed) are narrower than a release can be set "
                 f"by hand.</p>")
    return (f"<p>Two-bounce windows the ramp can reach (edges to {_tolerances(check)['edge_rel_tol']:.0e} "
            f"relative in v_in):</p>"
            f"<table id=windows><tr><th>window</th><th>v_in lo ({units}/s)</th><th>v_in hi ({units}/s)</th>"
            f"<th>H lo ({units})</th><th>H hi ({units})</th>"
            + ("<th>width in H (mm)</th>" if width_col else "")
            + (f"<th>v_out max ({units}/s)</th>" if vmax else "")
            + ("" if min_width is None else "<th class=l>observable</th>")
            + f"</tr>{rows}</table>{count}{_completeness_note(check, units)}")


def _calibration_table(cal: dict, marks: list | None, units: str, every: int) -> str:
    H, V = list(cal["heights"]), list(cal["v_in"])
    idx = sorted(set(list(range(0, len(H), max(1, every))) + [len(H) - 1]))
    rows = "".join(f"<tr><td>{_n(H[i], '.5g')}</td><td>{_n(V[i], '.8g')}</td></tr>" for i in idx)
    mk = ""
    if marks:
        head = f"<tr><th class=l>mark</th><th>H ({units})</th><th>v_in ({units}/s)</th></tr>"

        def mark_rows(ms):
            return "".join(f"<tr><td class=l>{_e(m['label'])}</td><td>{_n(m['height'], '.6g')}</td>"
                           f"<td>{_n(m['v_in'], '.7g')}</td></tr>" for m in ms)

        hit = [m for m in marks if m.get("observable", True)]
        narrow = [m for m in marks if not m.get("observable", True)]
        mk = "<h3>Release marks</h3><table id=marks>" + head + mark_rows(hit) + "</table>"
        if narrow:
            mk += ("<h4>Windows too narrow to hit</h4><p class=meta>Their centres, for reference: each window is "
                   "narrower in release height than a release can be set (not observable).</p>"
                   "<table id=marks-narrow class=narrow>" + head + mark_rows(narrow) + "</table>")
    e = cal.get("entry")
    if e is None or getattr(e, "closed_form", True):
        how = (f"v_in = sqrt(2 g H / (1 + k)), g = {_n(cal['g'], '.7g')} {units}/s², k = {_n(cal['k'], '.4g')}; "
               f"H the drop of the ball's centre. Exact closed form (no losses on the ramp; rounding only, "
               f"~1e-16 relative); ")
    else:
        how = (f"v_in from the ball's descent of the ramp with its losses ({_e(e.method)}), "
               f"g = {_n(cal['g'], '.7g')} {units}/s², " if e.method else
               f"v_in from the ball's descent of the ramp ({_e(e.profile)}) with damping {_n(e.mu, 'g')} 1/s and "
               f"rolling resistance {_n(e.c, 'g')}, g = {_n(cal['g'], '.7g')} {units}/s², ")
        how += (f"k = {_n(cal['k'], '.4g')}; H the drop of the ball's centre; to ~{_n(e.error, '.0e')} relative "
                f"(the lossless closed form sqrt(2 g H / (1 + k)) would say more); ")
    return (f"<p class=meta>{how}"
            f"{len(H)} heights" + (f", every {every}th shown" if every > 1 else "") + f"; {_n(cal.get('seconds'), '.2g')} s.</p>"
            f"<div class=grid2><table><tr><th>H ({units})</th><th>v_in ({units}/s)</th></tr>{rows}</table>"
            f"<div>{mk}</div></div>")


def _inline(text: str) -> str:
    """Markdown's inline `code` and **bold**, on escaped text."""
    import re

    t = _e(text)
    t = re.sub(r"`([^`]+)`", r"<code>\1</code>", t)
    return re.sub(r"\*\*([^*]+)\*\*", r"<b>\1</b>", t)


def _table_html(rows: list[str]) -> str:
    """A Markdown table (header, |---| rule, rows) as HTML."""
    cells = [[c.strip() for c in r.strip().strip("|").split("|")] for r in rows]
    body = [c for c in cells[1:] if not all(set(x) <= set("-: ") for x in c)]
    head = "".join(f"<th>{_inline(c)}</th>" for c in cells[0])
    return ("<table><tr>" + head + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in r) + "</tr>" for r in body) + "</table>")


def markdown_html(md: str, top: int = 3, after_title: str = "") -> str:
    """The operator's setup sheet (``setup.md``, :func:`fabkit.toolpath.program.setup_sheet.sheet_markdown`)
    as HTML: the same lines, each with its unit, so the page and the file beside the
    program say the same thing. Handles what the sheet uses: headings, bullet lists,
    paragraphs, inline code and bold; its preview image is shown elsewhere on the page.
    ``top``: the HTML level of the sheet's first-level heading; ``after_title``: HTML put
    right after the first heading."""
    import re

    out: list[str] = []
    in_list = False
    table: list[str] = []
    numbered: list[str] = []
    for line in md.splitlines() + [""]:
        if line.startswith("|"):                 # a table (the operations of a job with roughing)
            table.append(line)
            continue
        if table:
            out.append(_table_html(table))
            table = []
        m = re.match(r"\d+\. (.*)", line)
        if m:                                    # a numbered list (the steps per tool)
            numbered.append(f"<li>{_inline(m.group(1))}</li>")
            continue
        if numbered:
            out.append("<ol>" + "".join(numbered) + "</ol>")
            numbered = []
        if line.startswith("- "):
            if not in_list:
                out.append("<ul>")
                in_list = True
            out.append(f"<li>{_inline(line[2:])}</li>")
            continue
        if in_list:
            out.append("</ul>")
            in_list = False
        if not line.strip() or line.startswith("!["):
            continue
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            h = min(level + top - 1, 6)
            out.append(f"<h{h}>{_inline(line[level:].strip())}</h{h}>")
            if after_title:
                out.append(after_title)
                after_title = ""
        else:
            out.append(f"<p>{_inline(line)}</p>")
    if in_list:
        out.append("</ul>")
    return after_title + "".join(out)


def _sheet_section(sheet: dict) -> str:
    """The setup sheet as the operator reads it (setup.md's text), or a note without one."""
    if not sheet:
        return "<h2>Setup sheet</h2><p class=missing>(setup sheet: not available)</p>"
    from .toolpath.program.setup_sheet import sheet_markdown

    refusals = (sheet.get("machine_check") or {}).get("refusals") or []
    refused = ("".join(f"<p class=unsafe><b>The machine cannot run this program:</b> {_e(r)} "
                       f"(<code>fabkit gcode</code> refuses it, exit 2)</p>" for r in refusals))
    # the sheet's own title ("Setup sheet: PROGRAM") heads the section: one heading
    return f'<div id="setup-sheet">{markdown_html(sheet_markdown(sheet, None), top=2, after_title=refused)}</div>'


def _stock_section(pictures: dict) -> list[str]:
    """The shaded stock after roughing and after finishing (a job with roughing whose
    whole job was simulated on the stock); nothing otherwise."""
    if not pictures:
        return []
    names = {"rough": "after roughing", "finish": "after finishing"}
    imgs = "".join(f"<h3>Stock {names[k]}</h3>{_img(pictures[k], 'simulated stock ' + names[k])}"
                   for k in ("rough", "finish") if k in pictures)
    return [f"<section><h2>Simulated stock</h2><p class=meta>The stock height field after each "
            f"operation, every tool with its own shape, coloured by the deviation from the design."
            f"</p>{imgs}</section>"]


def render(results: dict) -> str:
    """The page (see the module doc for ``results``)."""
    u = results["units"]
    chk = results["check"]
    surf = results["surface"]
    sw = results.get("sweep") or {}
    tp = results.get("toolpath") or {}
    cal = results["calibration"]
    y = np.asarray(surf["y"], dtype=float)
    data = {"x": [round(float(v), 6) for v in surf["x"]], "y": [round(float(v), 6) for v in y],
            "z": [[round(float(v), 6) for v in row] for row in np.asarray(surf["z"])],
            "start": float(surf["start"]), "jl": int(np.argmin(np.abs(y - float(surf["y0"]))))}
    data_json = json.dumps(data, separators=(",", ":")).replace("</", "<\\/")
    vc, vce = chk.get("v_critical"), sw.get("v_critical_error")
    est = sw.get("error_estimate") or {}
    ver = tp.get("verify") or {}
    tps = tp.get("seconds") or {}
    sections = [
        f"<section><h2>Pre-fabrication check</h2>{_verdict(chk, u)}"
        f"<p class=meta>{_e(chk.get('model'))} model, damping {_n(chk.get('damping'))} 1/s; "
        f"{len(chk.get('heights', []))} release heights launched; highest safe height to "
        f"{_tolerances(chk)['rel_tol']:.0e} relative; "
        + (f"v_critical {_n(vc, '.7g')} {u}/s (release height {_n(chk.get('critical_height'), '.5g')} {u}, "
           f"to {_tolerances(chk)['v_rel_tol']:.0e} relative)" if vc is not None
           else f"no v_critical over the ramp's speeds ({_e(chk.get('v_critical_reason') or 'not found')})")
        + f"; {_n(chk.get('seconds'), '.3g')} s.</p>"
        f"{_windows_table(chk, u, results.get('scale'), results.get('min_width'))}</section>",
        f"<section><h2>The surface</h2><p class=meta>z = h(x, y) clipped at the top face ({_n(surf['top'])} {u}); "
        f"{len(data['x'])} × {len(data['y'])} exact samples (the view interpolates between them). Drag to turn, "
        f"wheel to zoom; red: the launch line from x = {_n(surf['start'])}.</p>"
        f'<canvas id="surface3d" width="900" height="480"></canvas></section>',
        f"<section><h2>Sweep: v_out against v_in</h2>{_img(sw.get('png'), 'sweep figure')}"
        f"<p class=meta>{_n(sw.get('launches'), 'd')} launches; "
        + (f"v_critical {_n(sw.get('v_critical'), '.7g')} ± {_n(vce, '.1e')} {u}/s"
           if sw.get("v_critical") is not None
           else f"no v_critical ({_e(sw.get('v_critical_reason') or 'not found')})")
        + "; v_out error "
        + (f"< {_n(est.get('v_out_abs'), '.1e')} {u}/s (estimated at rtol {_n(est.get('rtol_ref'), 'g')})"
           if est.get("v_out_abs") is not None else "not estimated")
        + f"; {_n(sw.get('seconds'), '.3g')} s.</p></section>",
        f"<section><h2>Toolpath preview</h2>{_img(tp.get('png'), 'toolpath preview')}"
        f"<p class=meta>verified cut: largest gouge {_n(ver.get('max_gouge'), '.4f')} mm, material left "
        f"{_n(ver.get('max_material_left'), '.4f')} mm (checked at {_n(ver.get('checked_points'), 'd')} points); "
        + ", ".join(f"{k} {_n(v, '.3g')} s" for k, v in tps.items()) + ".</p></section>",
        *_stock_section(tp.get("stock_png") or {}),
        f"<section><h2>Ramp calibration</h2>{_calibration_table(cal, results.get('ramp_marks'), u, max(1, len(cal['heights']) // 20))}</section>",
        f"<section>{_sheet_section(tp.get('sheet') or {})}</section>",
    ]
    title = f"fabkit report: {results['name']}"
    return ("<!DOCTYPE html>\n<html lang=en><head><meta charset=utf-8>"
            f"<meta name=viewport content='width=device-width, initial-scale=1'><title>{_e(title)}</title>"
            f"<style>{CSS}</style></head><body><header><h1>{_e(title)}</h1>"
            f"<p>{_e(results.get('spec_path', ''))} · generated {_e(results.get('generated_at', ''))} · "
            f"fabkit {_e(results.get('version', ''))} · total {_n(results.get('seconds'), '.3g')} s</p></header>"
            f"<main>{''.join(sections)}</main>"
            f'<script type="application/json" id="surface-data">{data_json}</script>'
            f"<script>{VIEWER_JS}</script></body></html>\n")
