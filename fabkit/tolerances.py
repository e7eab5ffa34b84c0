"""Numerical tolerances and guards, in one place.

Every tolerance a module uses comes from a :class:`Tolerances` instance passed
explicitly (``DEFAULT`` unless a caller chooses otherwise). Guards bound the
sizes derived from user numbers so that a hostile spec is refused with a
message instead of allocating without limit.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerances:
    # surface evaluation
    grid_samples: int = 401            # per axis, for sampling searches (lowest point, curvature)
    root_xtol: float = 1e-12           # relative, root finds on the surface (crease, minima)
    # solid
    mesh_tolerance_mm: float = 0.01    # default chordal tolerance of the STL
    # expression sandbox
    expr_max_chars: int = 2000
    expr_max_nodes: int = 400
    expr_max_depth: int = 40            # nesting; compile time grows ~quadratically with it (~4 s at 40)
    expr_max_exponent: float = 64.0    # |constant exponent| in a ** b
    expr_max_number: float = 1e12      # |numeric literal|
    expr_max_compiled_nodes: int = 50_000  # h and its 5 derivatives, tree nodes (expr.derivative_size)
    # guards on sizes derived from user numbers
    max_mesh_triangles: int = 1_000_000    # ~25 s and 50 MB of STL on a 2-core machine
    max_program_points: int = 4_000_000  # a program this size plans, verifies and writes in < 2 GB
    max_roughing_levels: int = 2_000
    max_plan_seconds: float = 60.0     # estimated planning time (toolpath.finish.guards), reference machine
    max_passes: int = 200_000
    max_verify_points: int = 2_000_000
    max_launches: int = 10_000_000
    max_sim_steps: int = 2_000_000     # per launch
    max_rough_levels: int = 2_000      # roughing z-levels (stock.depth_limit / machining.stepdown)


DEFAULT = Tolerances()
