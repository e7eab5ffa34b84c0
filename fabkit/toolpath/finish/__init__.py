"""Finishing with the ball-end mill: the passes, their exact tip heights, the program's points.

Phase: after the spec and its surface, before the program is written.
In: the spec (``machining``, ``tool``, ``stock``) and the :class:`fabkit.surface.Surface`
(h and its exact derivatives; compiled functions when the formula has them).
Out: a :class:`fabkit.toolpath.path.Toolpath` of tool-tip positions in work mm
(:func:`raster.plan_toolpath`), the estimates and guards that refuse a job too large
before any work (:mod:`.guards`), and the added passes where verification found material
left (:func:`raster.add_passes`).

    compensate.py        exact drop cutter against the clipped design (the numpy code)
    dropcut.py           its compiled kernel: a template written to the user cache
    kernels.py           loading / building the compiled kernels for a surface
    passes.py            pass placement with the slope-aware stepover
    scallop.py           the material two passes leave between them (+ scallop_kernels.py)
    spacing.py           points along a pass within the chord tolerance (+ spacing_kernels.py)
    links.py, snap.py    links between cut runs; points on the grid the controller reads back
    guards.py            size and planning-time estimates from the spec alone, and refusals
    raster.py            the stages in order: plan_toolpath
"""
