"""Toolpath stage: exact ball-end compensation, raster planning, G-code, verification, setup sheet.

    compensate.py   drop-cutter tip heights against the analytic clipped surface
    raster.py       passes, slope-aware stepover, adaptive point spacing, air skipping, links
    path.py         the Toolpath data passed between the stages
    gcode.py        pure G-code writer (dialects as data)
    verify.py       read a program back, sweep the ball, measure gouge and material left
    setup.py        the setup sheet (JSON + Markdown)
    job.py          the whole job once (plan, write, read back, verify, add passes, estimate,
                    sheet): run_job -> JobResult with its verdict; gcode, report, precision call it
"""
