"""Roughing: the material removed before the finishing passes.

Phase: after the spec and its surface, before the finish (the job runs rough, rest, finish).
In: the spec's ``roughing`` and ``tools`` sections (a flat end mill, bull nose or ball
of its own) and the surface; for the rest passes the rough operation and the finishing
toolpath.
Out: :class:`fabkit.toolpath.operations.Operation` s (``plan_operations``: rough, rest),
tool-tip positions in work mm; and, with the finishing ball itself, the Z levels along
the finishing passes every ``machining.stepdown`` (:mod:`.ball_levels`).
"""
