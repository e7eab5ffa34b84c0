"""Every number the README and docs/ give is classified: a command's output is checked.

tests/test_doc_numbers.py checks the passages marked ``<!-- numbers: JOB -->`` against the
outputs docs/regenerate.py records. Every other number in README.md and docs/*.md must sit in
a passage that says what kind of figure it is, so that no command's output can be quoted
unchecked:

    <!-- figures: KIND[ ARGUMENTS][, KIND ...] -->
    ... the passage (a paragraph, a table, a list, or a few of them) ...
    <!-- /figures -->

The kinds (``KINDS`` below):

* ``benchmark benchmarks/X.py`` -- measured by a script run by hand (never in the tests); the
  passage gives its command (``python benchmarks/X.py ...``), so a reader can rerun it.
* ``test tests/X.py`` -- measured in a test of the suite, which the passage names.
* ``reference`` -- published values and other programs' figures (the seed paper, grbl,
  rs274, LinuxCNC, scipy, the literature), and hardware or format facts.
* ``history`` -- figures of earlier code, before a change (``was``, ``before``).
* ``input`` -- what is given, not computed: spec values, defaults, options and their
  ranges, the interface's constants (exit codes, limits), the parameters of a study.
* ``timing`` -- wall or CPU times, memory and load averages measured by hand: they depend on
  the machine, not on the command.
* ``closed-form`` -- worked by hand from a formula or a derivation the passage gives.
* ``derived NAME [from JOB[ JOB]]`` -- computed by hand from the quoted outputs of the jobs
  named (a percentage, a fit, a ratio), or written by a script from the repository itself
  (docs/architecture.py's line counts): ``DERIVATIONS[NAME]`` recomputes each such figure
  from the jobs' printed numbers, the passage's own checked numbers or the files, and fails
  when one differs.
* ``unchecked`` -- said plainly: a figure read by hand from a command's output (its JSON, a
  fit through its numbers) that nothing here checks yet. Each is a debt, counted by
  ``test_unchecked_figures_do_not_grow``, whose budget is zero.

A passage with a number outside every mark fails here. Numbers that are names rather than
figures are left out by the rules of ``strip_names``: headings, link targets, identifiers
(T_5, DOP853, x86_64, G64, P0.01, $110, 0.ngc), versions (grbl 1.1, Python 3.11), issue and
item numbers, exponents and subscripts in formulas (y^2, x**2, e_1), ordered-list labels, and
code spans and code blocks that are commands, options, spec keys or G-code. A code block or a
code span that shows what a command prints is a passage like any other. This test reads text
only: it runs no command.
"""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path

import pytest

from test_doc_numbers import DOCS, OUT, ROOT, _regenerate, decimals, whole_numbers

FIGURES = re.compile(r"<!-- figures: (.*?) -->(.*?)<!-- /figures -->", re.S)
NUMBERS = re.compile(r"<!-- numbers: .*?-->.*?<!-- /numbers -->", re.S)
KINDS = ("benchmark", "test", "reference", "history", "input", "timing", "closed-form", "derived", "unchecked")

# a line that is a command a user types (a code block of these shows no output)
_COMMAND = re.compile(r"^\s*(\$ )?(fabkit|python3?|pip|pytest|nice|dask|sed|git|cd|\.|apt-get|"
                      r"PYTHONPATH=|GRBLTIME=|LCNCTIME=|FABKIT_\w+=|export)\b")
_VERSIONED = re.compile(r"\b(grbl|Python|numpy|scipy|numba|LinuxCNC|linuxcnc|Debian|Chromium|trimesh|PyAV|"
                        r"matplotlib|manifold3d|OpenCV|x264|grbl-sim|Dask|dask)(\s+v?\d[\d.]*\w*)")


def _blank(m: re.Match) -> str:
    return re.sub(r"[^\n]", " ", m.group(0))


def _commands_only(lines: list[str]) -> bool:
    follows = False
    for line in (x for x in lines if x.strip()):
        if not (follows or _COMMAND.match(line)):
            return False
        follows = line.rstrip().endswith("\\")
    return True


def _code_span(m: re.Match) -> str:
    """A code span that is a name, an option, a command, a spec key or G-code holds no figure."""
    s = m.group(1)
    if re.fullmatch(r"\s*[-+]?\d[\d.,]*(?:[eE][-+]?\d+)?\s*", s):
        return m.group(0)                    # a bare number is a figure, in a code span too
    if (not re.search(r"\s", s.strip()) or _COMMAND.match(s) or s.lstrip().startswith("-")
            or re.fullmatch(r"[\w.\[\]]+:\s+\S+(\s\w+)?", s)
            or re.fullmatch(r"(\s*[A-Z$#]-?[\d.]+)+\s*", s)):
        return _blank(m)
    return m.group(0)


def strip_names(text: str) -> str:
    """The text with every mark, every marked passage and every number that is a name blanked
    (line numbers kept)."""
    text = NUMBERS.sub(_blank, text)
    text = FIGURES.sub(_blank, text)
    text = re.sub(r"<!--.*?-->", _blank, text, flags=re.S)
    lines, out, fence = text.split("\n"), [], None
    for line in lines:                       # fenced code blocks of commands only
        if fence is None and line.lstrip().startswith("```"):
            fence = [line]
        elif fence is not None:
            fence.append(line)
            if line.lstrip().startswith("```"):
                out += [""] * len(fence) if _commands_only(fence[1:-1]) else fence
                fence = None
        else:
            out.append(line)
    lines, out, k = out + (fence or []), [], 0
    while k < len(lines):                    # indented code blocks of commands only
        if lines[k].startswith("    ") and (not out or not out[-1].strip()):
            j = k
            while j < len(lines) and (lines[j].startswith("    ") or not lines[j].strip()):
                j += 1
            out += [""] * (j - k) if _commands_only(lines[k:j]) else lines[k:j]
            k = j
        else:
            out.append(lines[k])
            k += 1
    text = "\n".join("" if re.match(r"\s*#+ ", line) else line for line in out)   # headings
    text = re.sub(r"!\[[^\]]*\]\([^)]*\)", _blank, text)          # images: a caption is the figure's
    text = re.sub(r"\]\([^)]*\)", _blank, text)                  # link targets
    text = re.sub(r"https?://\S+", _blank, text)
    text = re.sub(r"`([^`\n]+)`", _code_span, text)
    text = _VERSIONED.sub(lambda m: m.group(1) + " " * len(m.group(2)), text)
    text = re.sub(r"([#$]|\b(?:issues?|wave|round|stop|items?|Fig\.|Figure|figure|eq\.|section)\s+)\d+", _blank, text)
    text = re.sub(r"[A-Za-z]-\d+|\d+-D\b", _blank, text)         # MPEG-4, 3-D
    text = re.sub(r"(\^|_|\*\*)\{?-?\d+", _blank, text)           # y^2, e_1, x**2
    text = re.sub(r"^\s*\d+\.\s", _blank, text, flags=re.M)      # ordered-list labels
    text = re.sub(r"\d{4}-\d{2}-\d{2}|\b\d{1,2}:\d{2}\b", _blank, text)
    return text


def unclassified(text: str) -> list[tuple[int, list[str]]]:
    """(line, numbers) of each passage that gives a number outside every mark."""
    text, found, start = strip_names(text), [], 0
    for m in re.finditer(r"(?:\n[ \t]*){2,}|\Z", text):
        chunk = text[start:m.start()]
        numbers = decimals(chunk) + whole_numbers(chunk)
        if numbers:
            found.append((text.count("\n", 0, start) + 1, numbers))
        start = m.end()
    return found


def marks(text: str):
    """(line, [(kind, arguments)], passage) of each figures mark."""
    for m in FIGURES.finditer(text):
        kinds = []
        for part in m.group(1).split(","):
            kind, _, args = part.strip().partition(" ")
            kinds.append((kind, args.split()))
        yield text.count("\n", 0, m.start()) + 1, kinds, m.group(2)


# ---------------------------------------------------------------------------------------------
# derivations: each recomputes the figures of a ``derived`` passage from what the jobs print

def _half(q: str) -> Decimal:
    return Decimal(1).scaleb(Decimal(q).as_tuple().exponent) / 2


def _close(quoted: str, value: float) -> bool:
    return abs(Decimal(quoted) - Decimal(repr(value))) <= _half(quoted) * Decimal("1.0001")


def _lab_line(n: int) -> float:
    """The seed paper's published fit, T_n = 0.961 n + 0.755 s (n = 2..6)."""
    return 0.961 * n + 0.755


def _paper_rows(text: str) -> list[tuple[list[str], list[str]]]:
    """docs/paper.md's table: (the windows' T_n at n = 3..6, the percentages against the lab)."""
    rows = []
    for line in text.splitlines():
        cells = [c for c in line.split("|")][1:-1]
        if len(cells) == 6 and re.search(r"\d\.\d", cells[3]):
            rows.append((re.findall(r"\d+\.\d+", cells[3]), re.findall(r"[-+]?\d+(?:\.\d+)?(?= %)", cells[4])))
    return rows


def _paper_against_lab(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """Each percentage is 100 (T_n / lab's T_n - 1), from the row's own checked T_n."""
    bad, rows = [], _paper_rows(text)
    assert len(rows) == 5
    for tns, pcts in rows:
        assert len(tns) == len(pcts) == 4
        for n, tn, pct in zip(range(3, 7), tns, pcts):
            if not _close(pct, 100 * (float(tn) / _lab_line(n) - 1)):
                bad.append(f"{pct} % against the lab at n = {n} (T_n {tn})")
    return bad


def _slope(tns: list[str]) -> float:
    ns = [3, 4, 5, 6]
    return sum((n - 4.5) * float(t) for n, t in zip(ns, tns)) / sum((n - 4.5) ** 2 for n in ns)


def _table_slopes(doc: str) -> list[float]:
    """The fits' slopes in docs/paper.md's table (its second column, "T n + delta")."""
    return [float(re.search(r"(\d+\.\d+) n \+", line.split("|")[2]).group(1))
            for line in doc.splitlines() if line.count("|") == 7 and re.search(r"\d n \+", line)]


def _paper_slopes(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The slopes over the lab's n alone: least squares through the table's T_n at n = 3..6."""
    slopes = [_slope(tns) for tns, _ in _paper_rows(doc)]   # full cm, ball cm, full in, ball in, ball in 2.5 cm
    m = re.search(r"the slopes are (\S+) and (\S+) s \(full and ball, cm\) and (\S+), (\S+) and\s+(\S+) s", text)
    return [f"slope over n = 3..6: {q} against {s:.4f}" for q, s in zip(m.groups(), slopes)
            if not _close(q.rstrip(","), s)]


def _paper_ranges(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The ranges the prose gives: the fits' slopes in cm and in inches, and the percentages
    against the lab at n = 3..6 (the table's)."""
    rows, slopes, bad = _paper_rows(doc), _table_slopes(doc), []
    m = re.search(r"fabkit gives (\S+)-(\S+) s\s+in cm and (\S+)-(\S+) s in inches", text)
    for q, v in zip(m.groups(), (min(slopes[:2]), max(slopes[:2]), min(slopes[2:]), max(slopes[2:]))):
        if not _close(q, v):
            bad.append(f"slope range: {q} against {v}")
    pct = [[abs(float(p)) for p in ps] for _, ps in rows]
    m = re.search(r"within (\S+) % at n = 3..6 \(point model\) and within (\S+) %", text)
    for q, row in zip(m.groups(), (pct[2], pct[4])):
        if not _close(q, max(row)):
            bad.append(f"within {q} % against {max(row)}")
    m = re.search(r"centimetre reading is (\d+)-(\d+) % short", text)
    cm = pct[0] + pct[1]
    if not (_close(m.group(1), min(cm)) and _close(m.group(2), max(cm))):
        bad.append(f"centimetre reading {m.group(1)}-{m.group(2)} % against {min(cm)}-{max(cm)}")
    return bad


def _paper_flat(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The flattened reading against the lab (its T_n at n = 3..6), and v_critical in inches
    per second written in cm/s."""
    plain = re.sub(r"<!--.*?-->", "", text)
    tns = re.search(r"s: (\S+), (\S+), (\S+), (\S+) at n = 3..6", plain).groups()
    pcts = [100 * (float(t.rstrip(",")) / _lab_line(n) - 1) for n, t in zip(range(3, 7), tns)]
    m = re.search(r"(-?[\d.]+) % to (-?[\d.]+) %", plain)
    bad = [f"{q} % against {v:+.3f}" for q, v in zip(m.groups(), (min(pcts), max(pcts))) if not _close(q, v)]
    m = re.search(r"v_critical is (\S+) in/s = (\S+) cm/s", plain)
    if not _close(m.group(2), float(m.group(1)) * 2.54):
        bad.append(f"{m.group(1)} in/s is not {m.group(2)} cm/s")
    return bad


def _output(job: str) -> str:
    text = (OUT / f"{job}.txt").read_text()
    return text[:text.rindex("\n[exit ")]


#: the published critical velocity of the phi^4 kink-antikink collision (Anninos et al. 1991)
PHI4_PUBLISHED = 0.2598


def _phi4_against_published(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """v_critical and its extrapolation as the sweep prints them, their difference (the t_max
    bias) and each one's distance above the published 0.2598."""
    out = _output(jobs[0])
    vc, ex = (float(x) for x in re.search(r"v_critical (\S+) c .*extrapolation (\S+) c", out).groups())
    want = {"v_critical = ": vc, "strict value at ": ex, "t_max bias is +": vc - ex,
            "this is\n  ": vc - PHI4_PUBLISHED, "above for v_critical and ": ex - PHI4_PUBLISHED}
    bad = []
    for before, value in want.items():
        m = re.search(re.escape(before) + r"([\d.e-]+)", text)
        if not m or not _close(m.group(1), value):
            bad.append(f"{before.strip()!r} {m and m.group(1)} against {value:.6g}")
    return bad


def _percent_of_previous_cell(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """In each table row, a cell "X (+p %)" states X against the cell before it:
    p = 100 (X / previous - 1), to the digits quoted."""
    bad = []
    for line in re.sub(r"<!--.*?-->", "", text).splitlines():
        cells = [c.replace(" ", "").replace("\u2212", "-") for c in line.split("|")[1:-1]]
        for prev, cell in zip(cells, cells[1:]):
            m = re.fullmatch(r"([\d.]+)\(([-+][\d.]+)%\)", cell)
            if m:
                xq, p, rq = m.group(1), m.group(2), re.match(r"[\d.]+", prev).group(0)
                # the two figures are rounded: p may be any value they round from
                x, hx, ref, hr = float(xq), float(_half(xq)), float(rq), float(_half(rq))
                lo, hi = 100 * ((x - hx) / (ref + hr) - 1), 100 * ((x + hx) / (ref - hr) - 1)
                hp = float(_half(p))
                if not (lo - hp <= float(p) <= hi + hp):
                    bad.append(f"{cell} against {prev}: {lo:+.4f}..{hi:+.4f} %")
    return bad


def _ball_against_full(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The finite ball's v_critical and release height against the point models', in per
    cent, from benchmarks/ball_compare.py's table (the job ball-compare): each "X % above the
    `full` model" (or `simplified`) and "X % above it in release height" / "X % higher"."""
    rows = {m.group(1): (float(m.group(2)), float(m.group(3)))
            for m in re.finditer(r"^\| (\w+) \| ([\d.]+) \| ([\d.]+) \|", _output(jobs[0]), re.M)}
    plain = re.sub(r"\*\*", "", text)
    want = {r"(\S+) % above the (?:paper's )?`full` model": rows["ball"][0] / rows["full"][0],
            r"(\S+) % above the\s+`simplified` model": rows["ball"][0] / rows["simplified"][0],
            r"(\S+) % (?:above it in\s+release height|higher)": rows["ball"][1] / rows["full"][1]}
    bad, found = [], 0
    for pattern, ratio in want.items():
        for m in re.finditer(pattern, plain):
            found += 1
            if not _close(m.group(1), 100 * (ratio - 1)):
                bad.append(f"{m.group(0)!r} against {100 * (ratio - 1):.3f} %")
    return bad if found else ["no figure against the point models found"]


def _ramp_lanes(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """How far apart along the ramp two windows' marks are: the difference of their places
    along it, as `fabkit ramp` prints them."""
    along = {int(m.group(1)): float(m.group(2)) for m in re.finditer(
        r"^2-bounce window (\d+) centre .*\s([\d.]+)$", _output(jobs[0]), re.M)}
    m = re.search(r"windows (\d+) and (\d+) are (\S+) mm apart", text)
    a, b, q = int(m.group(1)), int(m.group(2)), m.group(3)
    # both places are printed to 0.01 mm: their difference is good to 0.01
    d = along[b] - along[a]
    return [] if abs(float(q) - d) <= 0.01 + float(_half(q)) else [f"{q} mm against {d:.2f} mm"]


def _json_output(job: str) -> dict:
    import json

    text = _output(job)
    return json.loads(text[text.index("\n") + 1:])


def _roughing_times(job: str) -> tuple[float, list[float], int]:
    """(the whole job's seconds, each operation's seconds, lines) of a ``gcode --json`` job: by the
    machine's planner when it has one, else by length/feed."""
    d = _json_output(job)
    ops = [o.get("machine_s") or o["time_s"] for o in d.get("operations") or []]
    total = sum(ops) if ops else (d["run_time"]["total_s"] if d.get("run_time") else d["estimated_time_s"])
    return total, ops, d["lines"]


def _hours_minutes(q: str) -> int:
    h, m = re.fullmatch(r"(\d+) h (\d+) min", q).groups()
    return 60 * int(h) + int(m)


def _roughing_table(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """README.md's roughing table and the ratios under it, from ``fabkit gcode --json`` on each
    job (length/feed, grbl-router, linuxcnc-mill): lines, the whole job's time in h and min,
    each operation's in minutes, and the planner's time over length/feed."""
    plain, bad = re.sub(r"<!--.*?-->|\*\*", "", text), []
    names = {"one ball": "gcode-ball-stepdown", "`specs/surface_roughing.yaml`": "gcode-roughing"}
    times = {}
    for line in plain.splitlines():
        cells = [c.strip() for c in line.split("|")[1:-1]]
        job = next((j for k, j in names.items() if cells and cells[0].startswith(k)), None)
        if job is None:
            continue
        runs = [_roughing_times(job + suffix) for suffix in ("", "-router", "-mill")]
        times[job] = runs
        lines = [int(x.replace(" ", "")) for x in re.findall(r"\d[\d ]*\d", cells[3])]
        if lines[0] != runs[0][2] or (len(lines) > 1 and lines[1] != runs[1][2]):
            bad.append(f"{cells[0]}: lines {cells[3]} against {runs[0][2]} (grbl {runs[1][2]})")
        for cell, (total, ops, _) in zip(cells[4:7], runs):
            hm = re.match(r"\d+ h \d+ min", cell).group(0)
            if _hours_minutes(hm) != round(total / 60):
                bad.append(f"{cells[0]}: {hm} against {total / 60:.2f} min")
            per = re.search(r"\(([\d. +]+?)(?: min)?\)", cell)
            if per:
                for q, sec in zip(per.group(1).split(" + "), ops):
                    if not _close(q, sec / 60):
                        bad.append(f"{cells[0]}: {q} min against {sec / 60:.3f}")
    rough = [_json_output(f"gcode-roughing{s}")["operations"] for s in ("-router", "-mill")]
    ratio = [[o["machine_s"] / o["length_over_feed_s"] for o in ops] for ops in rough]
    m = re.search(r"rough at (\S+)x \(grbl-router\) and (\S+)x \(linuxcnc-mill\) its length/feed time,\s+"
                  r"against (\S+)x and (\S+)x for the finish", plain)
    for q, v in zip(m.groups(), (ratio[0][0], ratio[1][0], ratio[0][-1], ratio[1][-1])):
        if not _close(q, v):
            bad.append(f"planner over length/feed {q}x against {v:.4f}")
    m = re.search(r"run\s+time is (\S+)x the finishing program's by length/feed, (\S+)x on grbl-router, "
                  r"(\S+)x on linuxcnc-mill", plain)
    whole = times["gcode-roughing"]
    for q, (total, ops, _) in zip(m.groups(), whole):
        if not _close(q, total / ops[-1]):
            bad.append(f"whole job over the finish {q}x against {total / ops[-1]:.4f}")
    m = re.search(r"The roughing program has (\d[\d ]*) lines", plain)
    if int(m.group(1).replace(" ", "")) != _json_output("gcode-roughing")["operations"][0]["lines"]:
        bad.append(f"the roughing program's {m.group(1)} lines")
    return bad


def _architecture_lines(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """docs/architecture.py's table of modules: each one's line count is the file's today
    (rerun ``python docs/architecture.py --write`` when it is not)."""
    bad, rows = [], 0
    for m in re.finditer(r"\[`([\w/.]+\.py)`\]\([^)]*\) \| (\d+) \|", text):
        rows += 1
        n = (ROOT / m.group(1)).read_text().count("\n")
        if n != int(m.group(2)):
            bad.append(f"{m.group(1)} has {n} lines, the page says {m.group(2)} (python docs/architecture.py --write)")
    return bad if rows else ["no module rows found"]


def _lossless_calibration(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The closed form v_in = sqrt(2 g H / (1 + k)) at the heights and speed the calibrate job
    was given, with the g and k it prints."""
    out = _output(jobs[0])
    g, k = (float(x) for x in re.search(r"g = ([\d.]+) cm/s\^2, k = ([\d.]+)", out).groups())
    heights = [float(h) for h in re.search(r"--height (\S+) (\S+)", out).groups()]
    v = float(re.search(r"--v-in (\S+)", out).group(1))
    m = re.search(r"the same heights give (\S+) and (\S+) cm/s, and (\S+) cm/s comes from (\S+) cm", text)
    want = [(2 * g * h / (1 + k)) ** 0.5 for h in heights] + [v, (1 + k) * v * v / (2 * g)]
    return [f"{q} against {w:.7g}" for q, w in zip(m.groups(), want) if not _close(q, w)]


def _lossless_heights(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The release heights the lossless closed form H = (1 + k) v^2 / (2 g) gives for the point
    model's and the ball's v_critical (ball-compare's), with calibrate's g and k, and how much
    higher the ramp's losses put them (ball-compare's heights)."""
    out = _output("calibrate")
    g, k = (float(x) for x in re.search(r"g = ([\d.]+) cm/s\^2, k = ([\d.]+)", out).groups())
    v = {m.group(1): float(m.group(2)) for m in re.finditer(r"^(\w+): v_critical ([\d.]+)", _output("ball-compare"), re.M)}
    h = {m.group(1): float(m.group(3)) for m in re.finditer(r"^\| (\w+) \| ([\d.]+) \| ([\d.]+) \|",
                                                            _output("ball-compare"), re.M)}
    lossless = {model: (1 + k) * v[model] ** 2 / (2 * g) for model in ("full", "ball")}
    higher = {model: 10 * (h[model] - lossless[model]) for model in lossless}      # mm
    plain = re.sub(r"<!--.*?-->", "", text)
    checks = [(r"stands (\S+) mm higher for the point model and (\S+) mm higher for the ball",
               (higher["full"], higher["ball"])),
              (r"Lossless, the same speeds need (\S+) and (\S+) cm", (lossless["ball"], lossless["full"])),
              (r"1\.9910 cm instead of (\S+) \((\S+) mm\)", (lossless["full"], higher["full"])),
              (r"1\.9910 cm against (\S+) cm lossless: (\S+) mm", (lossless["full"], higher["full"]))]
    bad, found = [], 0
    for pattern, want in checks:
        for m in re.finditer(pattern, plain):
            found += 1
            for q, w in zip(m.groups(), want):
                # the heights are printed to 1e-4 cm: a difference of two is good to 1e-3 mm
                if abs(float(q) - w) > float(_half(q)) + 1e-3:
                    bad.append(f"{q} against {w:.5f}")
    return bad if found else ["no lossless height found"]


def _speed_ranges(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """v_in / v_critical over the ramp, "(full model: A..B against C..D in cm)": each job's
    printed range of v_in over its v_critical (the first job in inches, the second in cm)."""
    want = []
    for job in jobs:
        out = _output(job)
        lo, hi = (float(x) for x in re.search(r"v_in ([\d.]+)\.\.([\d.]+) ", out).groups())
        vc = float(re.search(r"v_critical ([\d.]+)", out.splitlines()[-1]).group(1))
        want += [lo / vc, hi / vc]
    m = re.search(r"model: (\S+)\.\.(\S+)\s+against (\S+)\.\.(\S+) in cm", re.sub(r"<!--.*?-->", "", text))
    # the speeds are printed to 0.01: the ratios are good to 2e-4 more than their rounding
    return [f"{q} against {w:.4f}" for q, w in zip(m.groups(), want) if abs(float(q) - w) > float(_half(q)) + 2e-4]


def _constant(path: str, name: str) -> float:
    """A module-level constant ``NAME = 1.5`` read from a source file's text (nothing imported)."""
    return float(re.search(rf"^{name} = ([\d.]+)", (ROOT / path).read_text(), re.M).group(1))


def _first_run_estimate(text: str, jobs: list[str], doc: str = "") -> list[str]:
    """The first run's message on a fresh clone (every kernel cold), as fabkit.first_run.prepare
    writes it: the simulator's part is the engine's measured guess (physics/engine/batch.py
    COMPILE_GUESS_S), the toolpath's the sum of the cold builds kernels.cold_build_seconds
    adds (toolpath/finish/kernels.py BUILD_*_S), each rounded by Python's round(), the total
    too (at least 1)."""
    simulator = _constant("fabkit/physics/engine/batch.py", "COMPILE_GUESS_S")
    toolpath = sum(_constant("fabkit/toolpath/finish/kernels.py", f"BUILD_{part}_S")
                   for part in ("KERNEL", "FORMULA", "MATERIAL", "SPACING"))
    source = (ROOT / "fabkit" / "first_run.py").read_text()
    if ('f"compiling fabkit\'s kernels for this surface (once, about {max(1, round(total))} s of CPU in all: "'
            not in source or 'f"{name} about {round(cold[p])} s"' not in source):
        return ["fabkit/first_run.py's message is not the one this derivation rebuilds"]
    want = (f"compiling fabkit's kernels for this surface (once, about {max(1, round(simulator + toolpath))} s "
            f"of CPU in all: the simulator about {round(simulator)} s, the toolpath's kernels about "
            f"{round(toolpath)} s; then gcode, check and report load them)")
    plain = " ".join(re.sub(r"<!--.*?-->", "", text).split())
    return [] if want in plain else [f"the first run's message is {want!r}"]


#: NAME -> check(passage, jobs) -> list of figures that are not what the derivation gives
DERIVATIONS = {"paper-against-lab": _paper_against_lab, "paper-slopes": _paper_slopes,
               "paper-ranges": _paper_ranges, "paper-flat": _paper_flat,
               "phi4-against-published": _phi4_against_published,
               "percent-of-previous-cell": _percent_of_previous_cell, "ball-against-full": _ball_against_full,
               "ramp-lanes": _ramp_lanes, "roughing-table": _roughing_table,
               "architecture-lines": _architecture_lines, "lossless-calibration": _lossless_calibration,
               "lossless-heights": _lossless_heights, "speed-ranges": _speed_ranges,
               "first-run-estimate": _first_run_estimate}


# ---------------------------------------------------------------------------------------------

def test_every_number_in_the_docs_is_classified():
    bad = []
    total = 0
    for doc in DOCS:
        for line, numbers in unclassified(doc.read_text()):
            total += 1
            bad.append(f"{doc.relative_to(ROOT)}:{line}: {' '.join(numbers[:8])}")
    assert not bad, (f"{total} passages give numbers outside any mark (mark them <!-- numbers: JOB --> or "
                     "<!-- figures: KIND -->, tests/test_doc_figures.py):\n" + "\n".join(bad))


def mark_problems(docs) -> list[str]:
    """What is wrong with the figures marks of these docs: an unknown kind, a benchmark without
    its command, a derivation that does not give the figures quoted."""
    jobs = _regenerate().JOBS_BY_NAME
    bad = []
    for doc in docs:
        name = doc.relative_to(ROOT).as_posix() if doc.is_relative_to(ROOT) else doc.name
        whole = doc.read_text()
        for line, kinds, text in marks(whole):
            where = f"{name}:{line}"
            if not (decimals(text) or whole_numbers(text)):
                bad.append(f"{where}: a figures mark around no number")
            for kind, args in kinds:
                if kind not in KINDS:
                    bad.append(f"{where}: unknown kind {kind!r} (one of {', '.join(KINDS)})")
                elif kind in ("benchmark", "test"):
                    folder = "benchmarks" if kind == "benchmark" else "tests"
                    if not args:
                        bad.append(f"{where}: {kind} names no script")
                    for script in args:
                        if not script.startswith(folder + "/") or not (ROOT / script).is_file():
                            bad.append(f"{where}: {script} is not a file under {folder}/")
                        elif kind == "benchmark" and not re.search(
                                rf"python3?\s+{re.escape(script)}(?![\w/])", text):
                            bad.append(f"{where}: the passage does not give the command python {script}")
                        elif kind == "test" and script not in text:
                            bad.append(f"{where}: the passage does not name {script}")
                elif kind == "derived":
                    if not args or (len(args) > 1 and (args[1] != "from" or len(args) < 3)):
                        bad.append(f"{where}: derived NAME [from JOB[ JOB]]")
                        continue
                    if args[0] not in DERIVATIONS:
                        bad.append(f"{where}: no derivation {args[0]!r} in DERIVATIONS")
                    unknown = [j for j in args[2:] if j not in jobs]
                    if unknown:
                        bad.append(f"{where}: unknown job(s) {unknown}")
                    else:
                        bad += [f"{where}: {b}" for b in DERIVATIONS[args[0]](text, args[2:], whole)]
                elif args:
                    bad.append(f"{where}: {kind} takes no arguments ({' '.join(args)})")
    return bad


def test_each_mark_is_a_known_kind_with_its_source():
    bad = mark_problems(DOCS)
    assert not bad, "\n".join(bad)


def test_the_rules_leave_out_names_and_keep_figures():
    text = ("## 3 Section 4\n\nissue 39, wave 4, grbl 1.1h, Python 3.11.7, T_5, DOP853, x86_64, G64 P0.01, "
            "$110 and [docs](docs/x2.md), `--v-in 20 90 200`, `surface.top: 2.0`, y^2, MPEG-4, 3-D\n\n"
            "1. first\n\n"
            "    fabkit sweep specs/surface.yaml --v-in 10 90 5\n\n"
            "the sweep finds 9 windows\n\n"
            "    $ fabkit check specs/surface.yaml\n    check: v_critical 59.2241\n\n"
            "`check: 400 release heights 0.2..4.5 cm`\n\n"
            "the ratio is `0.7232`\n\n"
            "<!-- figures: history -->was 12.5 s<!-- /figures --> and <!-- numbers: check -->9<!-- /numbers -->\n")
    got = unclassified(text)
    assert [line for line, _ in got] == [9, 11, 14, 16], got
    assert got[0][1] == ["9"] and got[1][1] == ["59.2241"] and got[2][1] == ["0.2", "4.5", "400"]
    assert got[3][1] == ["0.7232"]


def test_a_derivation_fails_a_figure_it_does_not_give():
    row = "| full, cm | 0.643 n + 0.370 | 3-14 | 2.259, 2.926, 3.587, 4.242 | {} | 51.743 cm/s |\n"
    good = "| h | h | h | h | h | h |\n|---|---|---|---|---|---|\n" + row.format("-38 %, -36 %, -35 %, -35 %") * 5
    assert _paper_against_lab(good, []) == []
    drifted = good.replace("-36 %", "-37 %", 1)
    assert _paper_against_lab(drifted, []) == ["-37 % against the lab at n = 4 (T_n 2.926)"]


def test_the_derivations_fail_a_drifted_figure():
    # a percentage against the cell before it, both rounded: +0.06 % (and +0.07 %, within their
    # rounding) holds for 941.0 against 940.4, +0.09 % does not
    assert _percent_of_previous_cell("| unequal | 940.4 | 941.0 (+0.06 %) |", []) == []
    assert _percent_of_previous_cell("| unequal | 940.4 | 941.0 (+0.09 %) |", []) != []
    # the lossless heights from ball-compare and calibrate's g and k
    good = "stands 0.8 mm higher for the point model and 1.0 mm higher for the ball"
    assert _lossless_heights(good, []) == []
    assert _lossless_heights(good.replace("1.0 mm", "1.2 mm"), []) != []
    # a module's line count on the architecture page
    row = "| spec | [`fabkit/spec.py`](../fabkit/spec.py) | {} | The spec |"
    n = (ROOT / "fabkit" / "spec.py").read_text().count("\n")
    assert _architecture_lines(row.format(n), []) == [] and _architecture_lines(row.format(n + 1), []) != []
    # the first run's message, from the compile estimates' constants
    msg = ("(`compiling fabkit's kernels for this surface (once, about 24 s of CPU in all: the simulator about\n"
           "12 s, the toolpath's kernels about 12 s; then gcode, check and report load them)`")
    assert _first_run_estimate(msg, []) == []
    assert _first_run_estimate(msg.replace("about 24 s", "about 26 s"), []) != []
    # the roughing table: the linuxcnc-mill total the page had (1 h 15 min) is not the job's
    readme = (ROOT / "README.md").read_text()
    table, jobs = next((t, a[2:]) for _, k, t in marks(readme) for _, a in k if a and a[0] == "roughing-table")
    assert _roughing_table(table, jobs) == []
    m = re.search(r"\*\*1 h (\d+) min\*\* \(28", table)
    drifted = table.replace(m.group(0), f"**1 h {int(m.group(1)) - 1:02d} min** (28")
    assert any("against" in b for b in _roughing_table(drifted, jobs))


@pytest.mark.parametrize("kind", ["benchmark benchmarks/bench_time.py", "test tests/test_doc_numbers.py"])
def test_a_benchmark_mark_without_its_command_fails(kind, tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text(f"<!-- figures: {kind} -->\n100 000 lines take 1.00 s\n<!-- /figures -->\n")
    assert [b.split(": ", 1)[1] for b in mark_problems([doc])] == \
        [f"the passage does not {'give the command python' if 'bench' in kind else 'name'} {kind.split()[1]}"]
    doc.write_text(f"<!-- figures: {kind} -->\n`python {kind.split()[1]}`: 100 000 lines take 1.00 s\n"
                   "<!-- /figures -->\n<!-- figures: measured -->\n3 s\n<!-- /figures -->\n")
    assert [b.split(": ", 1)[1] for b in mark_problems([doc])] == \
        ["unknown kind 'measured' (one of benchmark, test, reference, history, input, timing, closed-form, derived, unchecked)"]


#: figures of five or more significant digits, outside a numbers mark, that an output happens to
#: print too: (doc, figure) -> why it is not that output
COINCIDENCES = {
    ("docs/simulator.md", "980.665"): "g, the standard gravity: an input calibrate prints back",
    ("docs/machine.md", "4.5725"): "LinuxCNC's arc speed in a benchmark (a sweep prints the same digits)",
    ("docs/machine.md", "162.80"): "a hand program's run time in time_reference.py's table (the mm formula's "
                                   "sweep starts at v_in 162.8 mm/s)",
    ("docs/paper.md", "1.0112"): "the issue's old fit, history (precision prints the same digits)",
    ("docs/phi4.md", "0.25132"): "a window edge at dt = 1/10, history (unchanged at dt = 1/20)",
    ("docs/phi4.md", "0.25377"): "a window edge at dt = 1/10, history (unchanged at dt = 1/20)",
    ("docs/sweep_check.md", "50.484"): "the merged run before the windows were resolved, history: its ends "
                                       "are today's first and last windows' ends",
    ("docs/sweep_check.md", "50.930"): "the merged run before the windows were resolved, history",
    ("README.md", "5.4958"): "roughing_acceptance.py's independent cut of rs274's moves; the whole job's own "
                             "check (max_left) agrees with it to these digits",
    ("docs/toolpath.md", "5.4960"): "roughing_acceptance.py's figure when the bound was made strict, history "
                                    "(the sheet's own largest left rounds to the same digits)",
}


def test_a_figure_an_output_prints_is_in_a_numbers_mark():
    """Any figure of five or more significant digits that sits in a figures mark (a benchmark,
    history, an input ...) and that some regenerated output prints is that output's, unless it is
    a known coincidence: quote it in a numbers mark so that it is checked."""
    import bisect

    values = sorted((Decimal(m), p.stem) for p in OUT.glob("*.txt")
                    for m in re.findall(r"\d+\.\d+", _output(p.stem)))
    keys = [v for v, _ in values]
    bad = []
    for doc in DOCS:
        name = doc.relative_to(ROOT).as_posix()
        for line, kinds, text in marks(doc.read_text()):
            if any(k == "derived" for k, _ in kinds):
                continue
            for q in decimals(NUMBERS.sub(" ", text)):
                q = q.lstrip("+-")
                if len(re.split("[eE]", q)[0].replace(".", "").lstrip("0")) < 5 or (name, q) in COINCIDENCES:
                    continue
                half = _half(q)      # printed to more digits, quoted rounded: the same figure
                lo, hi = bisect.bisect_left(keys, Decimal(q) - half), bisect.bisect_right(keys, Decimal(q) + half)
                if hi > lo:
                    bad.append(f"{name}:{line}: {q} is printed by {', '.join(sorted({s for _, s in values[lo:hi]}))}")
    assert not bad, "\n".join(bad)


#: the numbers in passages marked ``unchecked``: the debt is paid, and none may come back
UNCHECKED_BUDGET = {"regions": 0, "numbers": 0}


def test_unchecked_figures_do_not_grow():
    regions = numbers = 0
    for doc in DOCS:
        for _, kinds, text in marks(doc.read_text()):
            if any(k == "unchecked" for k, _ in kinds):
                plain = NUMBERS.sub(" ", text)
                regions += 1
                numbers += len(decimals(plain)) + len(whole_numbers(plain))
    assert regions <= UNCHECKED_BUDGET["regions"] and numbers <= UNCHECKED_BUDGET["numbers"], \
        (f"{regions} unchecked passages with {numbers} numbers, over the budget {UNCHECKED_BUDGET}: "
         "quote a command's figure in a numbers mark, or derive it (tests/test_doc_figures.py)")


def test_each_output_names_exactly_the_docs_that_quote_it():
    """docs/outputs/JOB.txt's last line, "quoted by ...", is the job's doc list, and that list is
    the docs whose marks (numbers: or derived ... from) name the job: no more, no fewer."""
    jobs = _regenerate().JOBS_BY_NAME
    quoting: dict[str, set[str]] = {j: set() for j in jobs}
    for doc in DOCS:
        name, text = doc.relative_to(ROOT).as_posix(), doc.read_text()
        for m in re.finditer(r"<!-- numbers: ([\w\-., ]+?)\s*(?:;[^>]*)?-->", text):
            for j in m.group(1).split(","):
                quoting.setdefault(j.strip(), set()).add(name)
        for _, kinds, _ in marks(text):
            for kind, args in kinds:
                if kind == "derived":
                    for j in args[2:]:
                        quoting.setdefault(j, set()).add(name)
    bad = []
    for j, job in jobs.items():
        listed = {d.strip() for d in job.doc.split(",")}
        if listed != quoting[j]:
            bad.append(f"{j}: regenerate lists {sorted(listed)}, the docs that quote it are {sorted(quoting[j])}")
        out = OUT / f"{j}.txt"
        if not out.is_file():
            bad.append(f"{j}: no docs/outputs/{j}.txt")
            continue
        last = out.read_text().rstrip("\n").rsplit("\n", 1)[-1]
        said = {d.strip() for d in last.rsplit("quoted by ", 1)[-1].rstrip("]").split(",")}
        if said != listed:
            bad.append(f"docs/outputs/{j}.txt says quoted by {sorted(said)}, regenerate lists {sorted(listed)}")
    stray = sorted(p.stem for p in OUT.glob("*.txt") if p.stem not in jobs)
    assert not bad and not stray, "\n".join(bad + [f"docs/outputs/{s}.txt: no such job" for s in stray])


def test_the_new_variant_specs_differ_from_their_sources_only_where_they_say():
    """docs/paper.md's flattened reading and README.md's single-ball stepdown row run on specs
    that are not shipped: each is its source with only the keys its header names changed."""
    import yaml

    point = yaml.safe_load((ROOT / "tests" / "fixtures" / "paper_full.yaml").read_text())
    flat = yaml.safe_load((ROOT / "tests" / "fixtures" / "sweep" / "paper_full_flat.yaml").read_text())
    want = {**point, "name": "paper_full_flat"}
    scaled = {("surface", "top"), ("simulation", "margin")}
    for section, key in scaled:
        assert flat[section][key] == pytest.approx(point[section][key] / 2.54, rel=2e-6)
    for key in ("eta", "c", "eps"):
        assert flat["surface"]["params"][key] == pytest.approx(point["surface"]["params"][key] / 2.54, rel=2e-6)
    assert flat["ramp"]["heights"] == pytest.approx([h / 2.54 for h in point["ramp"]["heights"]], rel=2e-6)
    want["surface"] = {**point["surface"], "top": flat["surface"]["top"],
                       "params": {**point["surface"]["params"],
                                  **{k: flat["surface"]["params"][k] for k in ("eta", "c", "eps")}}}
    want["ramp"] = {**point["ramp"], "heights": flat["ramp"]["heights"]}
    want["simulation"] = {**point["simulation"], "margin": flat["simulation"]["margin"]}
    assert flat == want
    shipped = yaml.safe_load((ROOT / "specs" / "surface.yaml").read_text())
    ball = yaml.safe_load((ROOT / "tests" / "fixtures" / "roughing" / "ball_stepdown.yaml").read_text())
    assert ball == {**shipped, "name": "surface_ball_stepdown",
                    "machining": {**shipped["machining"], "stepdown": 6.35, "leave": 0.5}}


def test_the_error_examples_are_one_line_and_exit_2():
    """docs/errors.md's examples (the error-* jobs) are what the commands printed on bad input:
    nothing on stdout, exactly one line on stderr naming the file or the option, and exit 2."""
    jobs = [j for j in _regenerate().JOBS_BY_NAME if j.startswith("error-")]
    assert len(jobs) >= 15
    bad = []
    for job in jobs:
        text = (OUT / f"{job}.txt").read_text()
        m = re.fullmatch(r"\$ [^\n]*\n\[stderr\]\n([^\n]+)\n\[exit (\d+);[^\n]*\]\n", text)
        if not m or m.group(2) != "2" or "Traceback" in text:
            bad.append(f"{job}: not one stderr line and exit 2")
    assert not bad, "\n".join(bad)
