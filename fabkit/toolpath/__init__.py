"""Toolpath stage: exact ball-end compensation, raster planning, G-code, verification, setup sheet.

    compensate.py   drop-cutter tip heights against the analytic clipped surface
    raster.py       passes, slope-aware stepover, adaptive point spacing, air skipping, links
    path.py         the Toolpath data passed between the stages
    gcode.py        pure G-code writer (dialects as data)
    reader.py       read a written program back (the text, independent of the writer)
    verify.py       sweep the ball along the moves read back, measure gouge and material left
    reach.py        the lowest height the ball can cut at a point (what the verification expects)
    setup.py        the setup sheet (JSON + Markdown)
    job.py          the whole job once (plan, write, read back, verify, add passes, estimate,
                    sheet): run_job -> JobResult with its verdict; gcode, report, precision call it
"""
