"""Fixed-step integrators on the configuration manifold (through ``pin.integrate``).

Each stepper advances (q, v) by one step ``dt`` given the acceleration ``a`` at
the start of the step and ``deriv(t, q, v) -> (v, a)`` for further stages.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

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


def step_rk4(model, deriv, t, q, v, a, dt, last_stage=None):
    """Classical Runge-Kutta 4 in the chart x -> q (+) x about q (order 4; chart.py).

    The stages' position rates are D(x_i)^-1 v_i (the identity but on free-flyer,
    spherical and planar joints), so that they add up in one tangent space.

    Args:
        last_stage: a list to which the fourth stage's rates (k4x [rad/s or m/s] in the
            chart about q, k4a [rad/s^2 or m/s^2]), shape (nv,) each, are appended (the
            embedded error estimate of :mod:`.rk43`); None: not kept.
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
    if last_stage is not None:
        last_stage.append((k4x, k4a))
    q_new = pin.integrate(model, q, dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x))
    return q_new, v + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)


# -- rk4 with stage projection near singular positions -------------------------------------
#
# Where the constraint manifold crosses itself (a flat position of the N-four-bar, the
# change point of the 4-bar) the projection onto phi = 0, J v = 0 and the accelerations
# are ill-conditioned at distance d from the crossing: the position projection stops at a
# residual p of phi (at most projection_tol, often a few 1e-15), which leaves the state
# p / sigma ~ p / d off the branch (sigma the smallest singular value of J, linear in
# d), and the velocity projected onto J v = 0 there is off by about p v / d^2 along the
# branch-switch direction; the stage accelerations amplify that again by 1 / d, and the
# next projection's correction (not mass-orthogonal) changes the energy. On the
# N-four-bar at N = 1, a stage 0.085 steps (4.2e-4 rad) from a flat position with
# abs(phi) = 2e-14 gave a crank spread of 1e-11 rad, a crank-rate spread of 1.2e-7
# rad/s, a velocity correction of 4e-6 at the step's end and an energy error of 1.3e-7.
# Steps are therefore retaken so that no evaluation point (stage or step end) lands
# within ``SimulationSettings.stage_singular_zone`` steps of a crossing: its time is
# estimated from the rank indicator rho (proportional to abs(d) near it) at the step's
# start, projected midpoint and end (:func:`crossing_estimate`), and a step with a
# point too close is retaken as two substeps of one grid step, or of two grid steps
# together (the state at the skipped grid point interpolated, cubic Hermite, for the
# output only), whichever keeps its points farthest away (:func:`retake_plan`; at 0.3
# steps some plan always keeps them at least 0.3 steps away).

#: Cap of the rank indicator (a regular configuration): see :func:`rank_indicator`.
RANK_INDICATOR_CAP = 1e-2
#: Resolution of the retake plans: a single step split at k / RETAKE_GRID, two grid
#: steps split at 2 k / RETAKE_GRID (k = RETAKE_GRID: one substep of two steps).
RETAKE_GRID = 40
#: Inverse iterations of :func:`rank_indicator`.
RANK_INDICATOR_ITERS = 4
#: Largest residual of the fit rho = s abs(t - tau) of :func:`crossing_estimate`,
#: relative to the largest sample (a crossing behind the step, rho increasing, fits with
#: a residual of about half of it).
CROSSING_FIT_RTOL = 0.5
#: Where the plain step's evaluation points are [steps from its start].
PLAIN_POINTS = (0.5, 1.0)


def rank_indicator(J: np.ndarray, normal=None, cap: float = RANK_INDICATOR_CAP) -> float:
    """Return sqrt(mu / mean eigenvalue of J J^T), capped at ``cap``.

    mu is the Rayleigh quotient of J J^T after RANK_INDICATOR_ITERS inverse iterations
    from the vector of ones: about the smallest eigenvalue, so the result is about
    sigma_min / sigma_rms of J, which near a crossing of branches grows linearly with the
    distance to it. 0 when J J^T is not positive definite (exactly singular).

    Args:
        J: constraint Jacobian, shape (nc, nv).
        normal: the rows' :class:`~closedchain.dynamics.augmented_lagrangian.
            NormalSolver`, or None (dense). A banded one factorizes J J^T as a band
            (LAPACK ``dpbtrf``) and takes x^T J J^T x = |J^T x|^2: O(nc) instead of the
            dense product and Cholesky, the same quantity to round-off (as the compiled
            core).
        cap: the largest value returned (math.inf: none; dop853-rk43 follows its trend).
    """
    nc = J.shape[0]
    if nc == 0:
        return cap
    banded = normal is not None and normal.banded
    if banded:
        A = normal.band(J)  # upper band storage, diagonal last
        ref = float(np.sum(A[-1])) / nc
        factor, info = lapack.dpbtrf(A, lower=0)
        solve = functools.partial(lapack.dpbtrs, factor, lower=0)
    else:
        A = J @ J.T
        ref = float(np.trace(A)) / nc
        factor, info = lapack.dpotrf(A, lower=1)  # LAPACK directly: no wrappers
        solve = functools.partial(lapack.dpotrs, factor, lower=1)
    if not ref > 0.0 or info != 0:
        return 0.0
    x = np.full(nc, 1.0 / math.sqrt(nc))
    for _ in range(RANK_INDICATOR_ITERS):
        x = solve(x)[0]
        x /= np.linalg.norm(x)
    if banded:
        y = J.T @ x
        mu = float(y @ y)
    else:
        mu = float(x @ A @ x)
    return min(math.sqrt(max(mu, 0.0) / ref), cap)


def crossing_estimate(rho_start: float, rho_mid: float, rho_end: float) -> float:
    """Return the time [steps from the step's start] of the crossing that the rank
    indicator at the step's start, midpoint and end points to; inf when none is ahead.

    Near a crossing rho = s abs(t - tau): for tau in [0, 0.5), [0.5, 1) and [1, inf)
    the signs of t - tau at the three samples are known, (s, s tau) follow by linear
    least squares, and the hypothesis with tau in its interval and the smallest
    residual is taken (and only when that residual is at most CROSSING_FIT_RTOL of the
    largest sample). (A line through the start and the midpoint alone, the rule
    before, put a crossing at 0.43 steps at 0.6 once the midpoint was past it.)
    """
    r = np.array([rho_start, rho_mid, rho_end])
    if np.max(r) >= RANK_INDICATOR_CAP:
        return math.inf  # far from any crossing
    t = np.array([0.0, 0.5, 1.0])
    best, best_res = math.inf, math.inf
    for lo, hi, signs in (
        (0.0, 0.5, (-1.0, 1.0, 1.0)),
        (0.5, 1.0, (-1.0, -1.0, 1.0)),
        (1.0, math.inf, (-1.0, -1.0, -1.0)),
    ):
        sg = np.array(signs)
        A = np.column_stack([sg * t, -sg])  # r = sg (s t - s tau)
        (slope, st), *_ = np.linalg.lstsq(A, r, rcond=None)
        if not slope > 0.0:
            continue
        tau = st / slope
        if not lo <= tau < hi:
            continue
        res = float(np.linalg.norm(A @ [slope, st] - r))
        if res < best_res and res <= CROSSING_FIT_RTOL * float(np.max(r)):
            best, best_res = tau, res
    return best


def _plan_points(double: bool, h1: float) -> tuple[float, ...]:
    """Evaluation points [steps] of a retake: substeps h1 and (2 if double else 1) - h1."""
    end = 2.0 if double else 1.0
    if h1 >= end:
        return (end / 2, end)
    return (h1 / 2, h1, (h1 + end) / 2, end)


def retake_plan(tau: float, zone: float) -> tuple[bool, float] | None:
    """Return None when the plain step keeps its evaluation points at least ``zone``
    steps from a crossing at ``tau`` steps, else (double, h1): the retake (one grid step
    split at h1, or two grid steps split at h1; h1 = 2 is one substep of two steps)
    whose evaluation points are farthest from it (ties: the single step)."""
    if min(abs(p - tau) for p in PLAIN_POINTS) >= zone:
        return None
    best, best_d = None, -1.0
    for double in (False, True):
        for k in range(1, RETAKE_GRID + (1 if double else 0)):
            h1 = (2.0 if double else 1.0) * k / RETAKE_GRID
            d = min(abs(p - tau) for p in _plan_points(double, h1))
            if d > best_d:
                best, best_d = (double, h1), d
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
    problem.step_end(t, q, v, a)
    outputs = OutputSteps(out_steps)
    if outputs.take(0):
        recorder.add(t, q, v, a, problem.lam)

    def deriv(t, q, v):
        if partition:
            q, v = problem.complete(q, v[problem.ind], t)
        elif stab.projects_stages:
            # Accelerations only on phi = 0, J v = 0: off the manifold a nearly
            # rank-deficient J amplifies the inconsistency of J a + gamma = 0.
            q, v = project(problem, q, v, t, mass_orthogonal=True)
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
            q_new, v_new = project(problem, q_new, v_new, t, mass_orthogonal=stab.projects_stages)
        elif partition:
            q_new, v_new = problem.complete(q_new, v_new[problem.ind], t)
            if problem.cond_JD(q_new) > problem.settings.repartition_cond and problem.repartition(
                q_new, t
            ):
                info["repartitions"].append([t, [mech.coordinate_names[i] for i in problem.ind]])
        phi = recorder.declared_phi(q_new)
        if not partition:
            problem.check_regular(q_new, t, phi)  # checks every declared row too
        else:
            problem.check_rows(q_new, t, phi=phi)
        recorder.declared_residual(t, q_new, phi)  # drift limit, every declared row, every step
        q, v = q_new, v_new
        a = problem.accel(t, q, v)
        problem.step_end(t, q, v, a)
        if outputs.take(k):
            recorder.add(t, q, v, a, problem.lam)
        if progress is not None:
            progress(t)
    return n_steps


def rk4_projected(problem: Problem, t, q, v, a, h, last_stage=None):
    """One rk4 step of length h [s] from (q, v) with accelerations a at t, every stage and
    the end projected (mass-orthogonal); return (q+, v+, J at the projected midpoint).

    Each projected stage is checked for a singular position
    (:meth:`~.problem.Problem.check_stage_regular`).

    Args:
        last_stage: passed to :func:`step_rk4`.
    """
    mech = problem.mech
    stages = []

    def deriv(ts, qs, vs):
        qs, vs = project(problem, qs, vs, ts, mass_orthogonal=True)
        stages.append(problem.jacobian(qs))  # the projection's; the first: stage 2's
        problem.check_stage_regular(qs, ts, stages[-1])  # the ends can straddle a singularity
        return vs, problem.accel(ts, qs, vs, multipliers=False)  # lam of stages: unread

    q_new, v_new = step_rk4(mech.model, deriv, t, q, v, a, h, last_stage)
    t_new = t + h
    if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
        raise SimulationError(f"{mech.name}: non-finite state at t = {t_new:.9g} s", t_new)
    q_new, v_new = project(problem, q_new, v_new, t_new, mass_orthogonal=True)
    return q_new, v_new, stages[0]


def settle(problem: Problem, recorder, t, q, v):
    """Check the state reached at t (a step's or substep's end) and return its
    accelerations (the work of tau advanced to it)."""
    phi = recorder.declared_phi(q)
    problem.check_regular(q, t, phi)  # checks every declared row too
    recorder.declared_residual(t, q, phi)  # drift limit, every declared row, every step
    a = problem.accel(t, q, v)
    problem.step_end(t, q, v, a)
    return a


def _run_rk4_stage_projected(problem, recorder, q, v, a, dt, n_steps, outputs, progress, info):
    """rk4 with stage projection whose evaluation points keep away from singular positions.

    See the comment above :data:`RANK_INDICATOR_CAP`. ``info["singular_splits"]``
    counts the steps taken as substeps.
    """

    def rho(q):
        return rank_indicator(problem.jacobian(q), problem.normal_solver())

    zone = problem.settings.stage_singular_zone
    splits = 0
    t = 0.0
    rho_start = rho(q)
    k = 1
    while k <= n_steps:
        q_new, v_new, J_mid = rk4_projected(problem, t, q, v, a, dt)
        rho_new = rho(q_new)
        plan = None
        if zone > 0:
            rho_mid = rank_indicator(J_mid, problem.normal_solver())
            plan = retake_plan(crossing_estimate(rho_start, rho_mid, rho_new), zone)
        if plan is not None:
            double, f = plan
            span = 2 if double else 1
            h1, h2 = f * dt, span * dt - f * dt
            if f < span:
                q1, v1, _ = rk4_projected(problem, t, q, v, a, h1)
                a1 = settle(problem, recorder, t + h1, q1, v1)
                q_new, v_new, _ = rk4_projected(problem, t + h1, q1, v1, a1, h2)
            else:  # one substep of two grid steps
                h1, h2, q1, v1, a1 = 0.0, span * dt, q, v, a
                q_new, v_new, _ = rk4_projected(problem, t, q, v, a, h2)
            rho_new = rho(q_new)
            splits += 1
            if double:
                if outputs.take(k):  # the skipped grid point, from the substep holding it
                    if h1 >= dt:
                        sub = (t, h1, q, v, a, q1, v1, a1)
                    else:
                        a_end = settle(problem, recorder, t + 2 * dt, q_new, v_new)
                        sub = (t + h1, h2, q1, v1, a1, q_new, v_new, a_end)
                    t0, h = sub[0], sub[1]
                    _record_interpolated(problem, recorder, k * dt, (k * dt - t0) / h, h, *sub[2:])
                if progress is not None:
                    progress(k * dt)
                if k == n_steps:  # the step beyond t_final only served the output
                    break
                k += 1
        t = k * dt
        a = settle(problem, recorder, t, q_new, v_new)
        q, v = q_new, v_new
        rho_start = rho_new
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
