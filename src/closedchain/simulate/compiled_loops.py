"""Whole-trajectory integration in the compiled core (``backend="compiled"`` entries).

The loops of :mod:`.fixed` and :mod:`.adaptive` (same output grid, projection,
regularity check, drift limit, error control of scipy's RK45/DOP853 with the
same dense output) run in C++; the right-hand side never enters Python unless
``tau`` is a callable (then it is called from C++ under the GIL), and a
progress callback is called after each step. Ctrl-C interrupts a run.
"""

from __future__ import annotations

import numpy as np

from .. import compiled
from .fixed import output_grid
from .problem import Problem


def _prepare(problem: Problem, info: dict):
    core = compiled.make_core(problem.mech)
    compiled.configure(core, info["method"], problem.solver_settings, problem.settings)
    core.set_tau(problem.tau_input)
    return core


def _finish(problem: Problem, recorder, out: dict) -> int:
    problem.n_evals += int(out["evaluations"])
    recorder.extend(out)
    return int(out["steps"])


def run_fixed_compiled(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Fixed-step loop in C++ (euler, semi-implicit, rk4); return the number of steps."""
    core = _prepare(problem, info)
    dt, n_steps, out_steps = output_grid(t_final, control.dt, t_eval)
    info["dt"] = dt
    out = core.run_fixed(
        compiled.INTEGRATOR_CODES[spec.name],
        np.asarray(q, dtype=float),
        np.asarray(v, dtype=float),
        float(dt),
        int(n_steps),
        # None: every step is an output.
        np.arange(n_steps + 1, dtype=np.int32)
        if out_steps is None
        else np.asarray(out_steps, dtype=np.int32),
        bool(stab.projects),
        progress,
    )
    return _finish(problem, recorder, out)


def run_adaptive_compiled(
    problem: Problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Adaptive Dormand-Prince loop in C++ (RK45, DOP853); return the number of steps."""
    core = _prepare(problem, info)
    out = core.run_adaptive(
        compiled.INTEGRATOR_CODES[spec.name],
        np.asarray(q0, dtype=float),
        np.asarray(v0, dtype=float),
        float(t_final),
        float(control.rtol),
        float(control.atol),
        None if t_eval is None else np.asarray(t_eval, dtype=float),
        bool(stab.projects),
        progress,
    )
    return _finish(problem, recorder, out)
