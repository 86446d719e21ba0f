"""Fixed-step integrators on the configuration manifold (through ``pin.integrate``).

Each stepper advances (q, v) by one step ``dt`` given the acceleration ``a`` at
the start of the step and ``deriv(t, q, v) -> (v, a)`` for further stages.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from .chart import tangent_rate
from .problem import Problem, project
from .settings import SimulationError


def step_euler(model, deriv, t, q, v, a, dt):
    """Explicit Euler: q+ = q (+) dt v, v+ = v + dt a (order 1)."""
    return pin.integrate(model, q, dt * v), v + dt * a


def step_semi_implicit(model, deriv, t, q, v, a, dt):
    """Semi-implicit (symplectic) Euler: v+ = v + dt a, q+ = q (+) dt v+ (order 1)."""
    v_new = v + dt * a
    return pin.integrate(model, q, dt * v_new), v_new


def step_rk4(model, deriv, t, q, v, a, dt):
    """Classical Runge-Kutta 4 in the chart x -> q (+) x about q (order 4; chart.py).

    The stages' position rates are D(x_i)^-1 v_i (the identity but on free-flyer,
    spherical and planar joints), so that they add up in one tangent space.
    """
    k1x, k1a = v, a
    x2 = dt / 2 * k1x
    v2, k2a = deriv(t + dt / 2, pin.integrate(model, q, x2), v + dt / 2 * k1a)
    k2x = tangent_rate(model, q, x2, v2)
    x3 = dt / 2 * k2x
    v3, k3a = deriv(t + dt / 2, pin.integrate(model, q, x3), v + dt / 2 * k2a)
    k3x = tangent_rate(model, q, x3, v3)
    x4 = dt * k3x
    v4, k4a = deriv(t + dt, pin.integrate(model, q, x4), v + dt * k3a)
    k4x = tangent_rate(model, q, x4, v4)
    q_new = pin.integrate(model, q, dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x))
    return q_new, v + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)


def output_grid(t_final: float, dt: float, t_eval: np.ndarray | None):
    """Return (dt, n_steps, output step indices) with every output time on the step grid.

    ``dt`` is shortened so that each output interval is a whole number of steps.
    The output step indices are a strictly increasing integer array, or None for
    "every step": memory is proportional to the outputs, never to the steps.
    """
    if t_eval is None:
        n_steps = int(math.ceil(t_final / dt - 1e-9))
        return t_final / n_steps, n_steps, None
    gaps = np.diff(np.concatenate([[0.0], t_eval]))
    per = np.where(gaps > 0, np.maximum(1, np.ceil(gaps / dt - 1e-9)), 0)
    # Uniform grid when outputs are uniform (the common case).
    h = float(np.min(gaps[per > 0] / per[per > 0])) if np.any(per > 0) else dt
    n_steps = int(round(t_eval[-1] / h))
    if n_steps == 0:  # t_eval == [0]: the initial state only
        return dt, 0, np.zeros(1, dtype=np.int64)
    dt = t_eval[-1] / n_steps
    return dt, n_steps, np.unique(np.rint(t_eval / dt).astype(np.int64))


class OutputSteps:
    """The output step indices of :func:`output_grid`, walked in step order.

    Memory follows the outputs, never the steps (no set of every step index).
    """

    def __init__(self, steps: np.ndarray | None) -> None:
        self.steps = steps  # sorted unique indices, or None: every step
        self.j = 0

    def take(self, k: int) -> bool:
        """Return True when step ``k`` (called with increasing k) is an output."""
        if self.steps is None:
            return True
        if self.j < len(self.steps) and self.steps[self.j] == k:
            self.j += 1
            return True
        return False


def run_fixed(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Integrate with the fixed-step ``spec.step`` and stabilization ``stab``; return steps.

    Args:
        control: the step control; ``control.dt`` is the step [s].
    """
    mech = problem.mech
    model = mech.model
    dt, n_steps, out_steps = output_grid(t_final, control.dt, t_eval)
    info["dt"] = dt
    partition = stab.partitions
    if partition:
        q, v = problem.complete(q, v[problem.ind], 0.0)
    t = 0.0
    a = problem.accel(t, q, v)
    outputs = OutputSteps(out_steps)
    if outputs.take(0):
        recorder.add(t, q, v, a, problem.lam)

    def deriv(t, q, v):
        if partition:
            q, v = problem.complete(q, v[problem.ind], t)
        elif stab.projects_stages:
            # Accelerations only on phi = 0, J v = 0: off the manifold a nearly
            # rank-deficient J amplifies the inconsistency of J a + gamma = 0.
            q, v = project(problem, q, v, t)
        return v, problem.accel(t, q, v)

    for k in range(1, n_steps + 1):
        q_new, v_new = spec.step(model, deriv, t, q, v, a, dt)
        t = k * dt
        if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
            raise SimulationError(f"{mech.name}: non-finite state at t = {t:.9g} s", t)
        if stab.projects:
            q_new, v_new = project(problem, q_new, v_new, t)
        elif partition:
            q_new, v_new = problem.complete(q_new, v_new[problem.ind], t)
            if problem.cond_JD(q_new) > problem.settings.repartition_cond and problem.repartition(
                q_new, t
            ):
                info["repartitions"].append([t, [mech.coordinate_names[i] for i in problem.ind]])
        if not partition:
            problem.check_regular(q_new, t)  # checks every declared row too
        else:
            problem.check_rows(q_new, t)
        recorder.declared_residual(t, q_new)  # drift limit, every declared row, every step
        q, v = q_new, v_new
        a = problem.accel(t, q, v)
        if outputs.take(k):
            recorder.add(t, q, v, a, problem.lam)
        if progress is not None:
            progress(t)
    return n_steps
