"""The cut: what a program READ BACK removes from the stock, against the design.

Phase: after the program is written and read back, before the setup sheet.
In: a :class:`fabkit.toolpath.program.reader.Program` (the moves read from the text),
the tool(s) and the surface.
Out: the verification's figures (gouge, material left, where the ball cannot reach:
:func:`verify.verify_cut`, :func:`reach.reachable_height`) and the height-field stock
after each operation with its verdict and pictures (:func:`stock.verify_job`).
"""
