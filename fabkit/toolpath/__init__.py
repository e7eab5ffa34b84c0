"""Toolpath stage: from the spec and its surface to verified programs and a setup sheet.

The job (:func:`fabkit.toolpath.job.run_job`, returning a JobResult with its verdict)
runs the phases in order; each subpackage's docstring says what comes in and goes out:

    rough/      roughing with its own tool, rest passes, the ball's Z levels (Operations)
    finish/     the ball's passes with exact compensation, their points, the guards (Toolpath)
    program/    the G-code writer, the independent reader, the setup sheet (text, Program, sheet)
    cut/        the stock simulated and the cut verified from the program read back (verdicts)

    job.py         the whole job once: gcode, report and precision call run_job
    operations.py  an Operation: what one tool does (rough, rest, finish)
    path.py        the Toolpath passed between the phases (tool-tip positions, work mm)
    tools.py       cutting tools as shapes (flat end mill, bull nose, ball)
"""
