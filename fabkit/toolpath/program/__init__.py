"""The program: the text a controller runs, read back independently, and its setup sheet.

Phase: after planning (finish, rough), around the verification of the cut.
In: a :class:`fabkit.toolpath.path.Toolpath` or the job's operations and a
:class:`gcode.MachineProfile` (dialect, units, feeds as data).
Out: program text (:mod:`.gcode`, a pure writer); the moves read back from ANY text
(:mod:`.reader`, sharing no code with the writer); the setup sheet (JSON, Markdown,
preview) for the operator (:mod:`.setup_sheet`).
"""
