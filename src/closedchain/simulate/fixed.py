"""Fixed-step integrators on the configuration manifold (through ``pin.integrate``).

Each stepper advances (q, v) by one step ``dt`` given the acceleration ``a`` at
the start of the step and ``deriv(t, q, v) -> (v, a)`` for further stages.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import scipy.linalg

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


# -- rk4 with stage projection near singular positions -------------------------------------
#
# Where the constraint manifold crosses itself (a flat position of the N-four-bar, the
# change point of the 4-bar) the projection onto phi = 0, J v = 0 and the accelerations
# are ill-conditioned at distance d from the crossing: a residual p of phi (within
# projection_tol) leaves the state on the level set phi = p, which near the crossing is
# a hyperbola p / d away from the branch, and the velocity projected onto it is off by
# about p v / d^2; within about 3e-6 rad the augmented Lagrangian's penalty no longer
# enforces the lost row at all (Gauss's accelerations there differ from the branch's
# limit by O(g)). Which grid point lands how close to the crossing is chance (it depends
# on the step and the period): on the N-four-bar at N = 5 the step ending 4.7e-5 rad from
# a flat position turned a spread of 1.2e-10 rad between the cranks into a velocity error
# of 1.3e-5 rad/s and an energy error of 1.5e-5. A step is therefore retaken when one of
# its evaluation points would land within ``SimulationSettings.singular_zone`` steps of
# the crossing: the crossing time is extrapolated from the rank indicator rho (about
# linear in the distance to it) at the step's start and projected midpoint, and the step
# is redone as two unequal substeps whose evaluation points keep away from it; when the
# crossing is at the grid point, two steps are taken together and the state at the grid
# point is interpolated (cubic Hermite) for the output only.

#: Cap of the rank indicator (a regular configuration): see :func:`rank_indicator`.
RANK_INDICATOR_CAP = 1e-2
#: Candidate split fractions of a re-split step (k / 40): the one whose evaluation points
#: are farthest from the estimated crossing is taken.
SPLIT_CANDIDATES = tuple(k / 40 for k in range(4, 37))
#: Smallest split of a double step (its first substep contains the skipped grid point).
DOUBLE_SPLIT_MIN = 0.5
#: Inverse iterations of :func:`rank_indicator`.
RANK_INDICATOR_ITERS = 4


def rank_indicator(J: np.ndarray) -> float:
    """Return sqrt(mu / mean eigenvalue of J J^T), capped at RANK_INDICATOR_CAP.

    mu is the Rayleigh quotient of J J^T after RANK_INDICATOR_ITERS inverse iterations
    from the vector of ones: about the smallest eigenvalue, so the result is about
    sigma_min / sigma_rms of J, which near a crossing of branches grows linearly with the
    distance to it. 0 when J J^T is not positive definite (exactly singular).
    """
    nc = J.shape[0]
    if nc == 0:
        return RANK_INDICATOR_CAP
    A = J @ J.T
    ref = float(np.trace(A)) / nc
    if not ref > 0.0:
        return 0.0
    try:
        factor = scipy.linalg.cho_factor(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return 0.0
    x = np.full(nc, 1.0 / math.sqrt(nc))
    for _ in range(RANK_INDICATOR_ITERS):
        x = scipy.linalg.cho_solve(factor, x, check_finite=False)
        x /= np.linalg.norm(x)
    mu = float(x @ A @ x)
    return min(math.sqrt(max(mu, 0.0) / ref), RANK_INDICATOR_CAP)


def crossing_estimate(rho_start: float, rho_mid: float) -> float:
    """Return the time [steps from the step's start] at which the rank indicator,
    linear between the start and the midpoint, reaches 0; inf when it does not decrease."""
    if not rho_mid < rho_start:
        return math.inf
    return rho_start / (2.0 * (rho_start - rho_mid))


def best_split(tau: float, double: bool) -> float:
    """Return the split fraction f keeping the substeps' evaluation points farthest from
    the crossing at tau steps from the step's start.

    A split step has evaluation points f/2, f, (1 + f)/2; a double step (two grid steps,
    substeps 2 f and 2 (1 - f)) f, 2 f, 1 + f.
    """
    best, best_d = SPLIT_CANDIDATES[0], -1.0
    for f in SPLIT_CANDIDATES:
        if double and f < DOUBLE_SPLIT_MIN:
            continue
        points = (f, 2 * f, 1 + f) if double else (f / 2, f, (1 + f) / 2)
        d = min(abs(p - tau) for p in points)
        if d > best_d:
            best, best_d = f, d
    return best


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

    if stab.projects_stages and spec.step is step_rk4 and mech.nc:
        return _run_rk4_stage_projected(
            problem, recorder, q, v, a, dt, n_steps, outputs, progress, info
        )

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


def _run_rk4_stage_projected(problem, recorder, q, v, a, dt, n_steps, outputs, progress, info):
    """rk4 with stage projection whose evaluation points keep away from singular positions.

    See the comment above :data:`RANK_INDICATOR_CAP`. ``info["singular_splits"]``
    counts the steps taken as substeps.
    """
    mech = problem.mech
    model = mech.model

    def stage(t, q, v):
        q, v = project(problem, q, v, t)
        return q, v, problem.accel(t, q, v)

    def rk4(t, q, v, a, h):
        """One projected rk4 step; return (q+, v+) projected and the projected midpoint q."""
        stages = []

        def deriv(ts, qs, vs):
            qs, vs, acc = stage(ts, qs, vs)
            stages.append(qs)  # the first is the midpoint (stage 2)
            return vs, acc

        q_new, v_new = step_rk4(model, deriv, t, q, v, a, h)
        q2 = stages[0]
        t_new = t + h
        if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
            raise SimulationError(f"{mech.name}: non-finite state at t = {t_new:.9g} s", t_new)
        q_new, v_new = project(problem, q_new, v_new, t_new)
        return q_new, v_new, q2

    def settle(t, q, v):
        """Check the state reached at t and return its accelerations."""
        problem.check_regular(q, t)  # checks every declared row too
        recorder.declared_residual(t, q)  # drift limit, every declared row, every step
        return problem.accel(t, q, v)

    def rho(q):
        return rank_indicator(problem.jacobian(q))

    zone = problem.settings.singular_zone
    splits = 0
    t = 0.0
    rho_start = rho(q)
    k = 1
    while k <= n_steps:
        q_new, v_new, q_mid = rk4(t, q, v, a, dt)
        tau = crossing_estimate(rho_start, rho(q_mid))
        if abs(tau - 1.0) < zone:
            # The crossing is near grid point k: two steps in two unequal substeps
            # around it, the state at k interpolated for the output.
            f = best_split(tau, double=True)
            h1, h2 = 2 * f * dt, 2 * (1 - f) * dt
            q1, v1, _ = rk4(t, q, v, a, h1)
            a1 = settle(t + h1, q1, v1)
            q_new, v_new, _ = rk4(t + h1, q1, v1, a1, h2)
            splits += 1
            if outputs.take(k):
                _record_interpolated(problem, recorder, k * dt, dt / h1, h1, q, v, a, q1, v1, a1)
            if progress is not None:
                progress(k * dt)
            if k == n_steps:  # the step beyond t_final only served the output
                break
            k += 1
        elif abs(tau - 0.5) < zone:
            # The crossing is near the midpoint.
            f = best_split(tau, double=False)
            q1, v1, _ = rk4(t, q, v, a, f * dt)
            a1 = settle(t + f * dt, q1, v1)
            q_new, v_new, _ = rk4(t + f * dt, q1, v1, a1, (1 - f) * dt)
            splits += 1
        t = k * dt
        a = settle(t, q_new, v_new)
        q, v = q_new, v_new
        rho_start = rho(q)
        if outputs.take(k):
            recorder.add(t, q, v, a, problem.lam)
        if progress is not None:
            progress(t)
        k += 1
    info["singular_splits"] = splits
    return n_steps


def _record_interpolated(problem, recorder, t, s, h, q0, v0, a0, q1, v1, a1) -> None:
    """Record the state at t = t0 + s h of the substep (q0, v0, a0) -> (q1, v1, a1) of
    length h by cubic Hermite interpolation; q is projected onto phi = 0 (v is not:
    near the crossing its projection is the ill-conditioned step avoided)."""
    model = problem.mech.model
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    dq = h10 * h * v0 + h01 * pin.difference(model, q0, q1) + h11 * h * v1
    q = pin.integrate(model, q0, dq)
    v = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1
    q, _ = project(problem, q, v, t)
    problem.check_regular(q, t)
    recorder.declared_residual(t, q)
    a = problem.accel(t, q, v)
    recorder.add(t, q, v, a, problem.lam)
