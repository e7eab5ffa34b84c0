"""fabkit: from a surface formula to a milled block.

The pipeline, one module per stage (data flows one way)::

    spec -> surface -> solid            (fabkit stl)
                    -> toolpath -> gcode -> verify   (fabkit gcode)
                    -> physics (calibrate, simulate, sweep, check)

Heavy libraries (sympy, manifold3d, matplotlib, dask) are imported lazily,
inside the functions that need them, so ``fabkit --help`` stays fast.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
