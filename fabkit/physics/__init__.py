"""Physics stage: ramp calibration and the rolling-ball simulator.

    calibrate.py    release height <-> entry speed (rolling without slipping)
    models.py       Problem, right-hand sides of eq. (xyODE) and eq. (xyODE_simp), energy, outcomes
    integrate.py    launch_batch / launch_stream: the public API of the simulator
    ball.py         the finite rolling ball's equations as array functions (docs/ball.md)
    engine/         the compiled launch engine (numba) of every model: generated surface code,
                    the point and ball templates, DOP853 with scipy's step control, the events,
                    serial and threaded batches
    rk.py           the Runge-Kutta tableaux (scipy's DOP853 and RK45 coefficients)
    reference.py    single-launch scipy solve_ivp path (peers and converged references)
    sweep.py        v_out(v_in), v_critical by bisection, n-bounce windows, the T_n fit (eq. tn)
    check.py        the pre-fabrication check over the ramp's heights
    cc.py           the collective-coordinate model eq. (CCODE) and its separatrix map eq. (themap)
"""
