"""The compiled launch engine: one launch wholly in compiled code (numba).

    codegen.py   sympy -> plain ``math`` source for the surface, written once per formula
                 to the user cache (``FABKIT_CACHE_DIR`` overrides), with the model template
    point.py     the point-particle model template (full, simplified, damping)
    dop853.py    the step loop template: Dormand-Prince 8(5,3) / 5(4) with scipy's step
                 control, the events, the per-launch summaries
    batch.py     loading (compile on first use, then cache loads), serial and threaded runs

Adding a model (the finite-radius ball, say: state (x, y, xd, yd, u, W), third
derivatives of h): write its template next to ``point.py`` (NV, NE, W, rhs, energy,
kinetic, FULL, GT; see dop853.py), declare a ``codegen.Template`` with the surface
derivatives it needs (``("x", "x", "y")`` is h_xxy) and the number of its run-time
parameters, and let :func:`batch.engine` pick the template from ``problem.model``.
The step loop, the events and the batch drivers are shared; ``Engine.params`` builds
the run-time parameter vector of the template.

Importing this package does not import numba; :func:`batch.engine` does.
"""
