"""The compiled launch engine: one launch wholly in compiled code (numba), for every model.

    codegen.py   sympy -> plain ``math`` source for the surface, written once per formula
                 and template to the user cache (``FABKIT_CACHE_DIR`` overrides)
    point.py     the point-particle models' template (full, simplified, damping)
    ball.py      the finite-radius rolling ball's template (third derivatives of h, the
                 spin about the normal, the contact guard: lost contact, bridging, slip)
    dop853.py    the step loop, shared: Dormand-Prince 8(5,3) / 5(4) with scipy's step
                 control, the events, the per-launch summaries
    batch.py     loading (compile on first use, then cache loads), serial and threaded runs

A model is a template (NV, NE, W, GUARD_ITERS, rhs, GUARD_OUTCOME, INIT, VEL, energy,
kinetic, FULL, GT; see dop853.py) declared as a ``codegen.Template`` with the surface
derivatives it needs (``("x", "x", "y")`` is h_xxy) and the number of its run-time
parameters; :func:`codegen.template_of` picks it from ``problem.model`` and
``batch.MODEL_PARAMS`` builds its run-time parameter vector. The step loop, the
events and the batch drivers are shared.

Importing this package does not import numba; :func:`batch.engine` does.
"""
