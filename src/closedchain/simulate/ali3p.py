r"""ALI3-P: index-3 augmented Lagrangian with mass-orthogonal projections, trapezoidal rule.

The scheme of Bayo and Ledesma (1996) with the projections of Cuadrado,
Cardenal, Morer and Bayo (2000), one of the reference solvers of the IFToMM
multibody benchmarks. The equations of motion are written at the position
level (index 3) with a penalty on phi and Lagrange multipliers that are
updated by the augmented-Lagrangian rule,

.. math::

    M \ddot q + h + J^\top (\lambda^* + \alpha \phi(q)) = \tau, \qquad
    \lambda^*_{i+1} = \lambda^*_i + \alpha\, \phi(q_{i+1}),

and integrated by the implicit trapezoidal rule (Newmark beta = 1/4,
gamma = 1/2) in the tangent space at q_n: with the displacement
:math:`\Delta` (shape (nv,), q_{n+1} = q_n (+) Delta through ``pin.integrate``)

.. math::

    v_{n+1} = \tfrac{2}{h} \Delta - v_n, \qquad
    a_{n+1} = \tfrac{4}{h^2} \Delta - \tfrac{4}{h} v_n - a_n .

Newton iterations on the residual scaled by h^2/4 use the approximate tangent
:math:`P = M + \tilde\alpha J^\top J` (Coriolis and stiffness terms dropped, as
in ALI3-P), :math:`\tilde\alpha = h^2 \alpha / 4 = \rho\,\mathrm{tr}(M) /
\mathrm{tr}(J^\top J)` with rho = ``SimulationSettings.ali3p_penalty``, and update
:math:`\lambda^*` after each iteration. P is positive definite whatever the
rank of J, so the scheme is defined at singular configurations and with
redundant rows; the position-level closure (not its derivative) keeps the
motion on the branch its momentum carries it to.

After convergence the velocities and accelerations are projected
mass-orthogonally onto J v = 0 and J a + Jdot v = 0:

.. math::

    \min_v \tfrac12 (v - v^*)^\top M (v - v^*) \;\text{s.t.}\; J v = 0, \qquad
    \min_a \tfrac12 (a - a^*)^\top M (a - a^*) \;\text{s.t.}\; J a + \dot J v = 0,

each solved by the augmented-Lagrangian iteration with the same P
(:func:`closedchain.dynamics.augmented_lagrangian.solve_augmented_lagrangian`),
iterated to convergence rather than one step, so the projected states satisfy
the constraints to round-off where J has full rank.

Near a singular position the multiplier update enforces the nearly lost row
ever more slowly, so no step ends within ``SimulationSettings.singular_zone``
steps of a crossing (see the comment in :func:`run_ali3p`).

The scheme is second-order accurate and fixed-step; its settings are
``SimulationSettings.ali3p_tol``, ``ali3p_max_iter`` and ``ali3p_penalty``.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pinocchio as pin

from ..dynamics.augmented_lagrangian import (
    penalized_solver,
    relative_penalty,
    solve_augmented_lagrangian,
)
from .fixed import (
    RANK_INDICATOR_CAP,
    OutputSteps,
    output_grid,
    rank_indicator,
)
from .problem import Problem
from .settings import SimulationError

logger = logging.getLogger(__name__)

#: Newton stops below ali3p_tol once a correction is this fraction of it, or once the
#: corrections stop shrinking by at least ALI3P_STALL per iteration (round-off floor).
ALI3P_TOL_FLOOR = 1e-4
ALI3P_STALL = 0.5
#: First substep of a step pair around a crossing that comes before the grid point, in
#: steps (its end is 0.5 step from the skipped grid point, near which the crossing is);
#: 2 - ALI3P_SPLIT when the crossing comes after it.
ALI3P_SPLIT = 1.5
#: The multiplier update enforces a row of relative singular value sigma at the rate
#: 1 / (1 + rho sigma^2) per Newton iteration (rho = ali3p_penalty): no step ends where
#: the rank indicator (about sigma) is predicted below sqrt(ALI3P_ENFORCED / rho), 1e-5
#: at rho = 1e11, even beyond singular_zone steps from the crossing (N-four-bar N = 40,
#: dt 0.2 ms: a step ending 0.095 step past the first flat position, indicator 2.9e-6,
#: rho sigma^2 = 0.8, stalled at corrections of 4e-10 for 500 iterations).
ALI3P_ENFORCED = 10.0
#: ... within at most this many steps of the crossing (the ends of the 1.5 + 0.5 or
#: 0.5 + 1.5 substeps then stay at least 0.5 step away from it).
ALI3P_ZONE_MAX = 0.5


def run_ali3p(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Integrate with ALI3-P at the fixed step ``control.dt``; return the number of steps."""
    mech = problem.mech
    model, data, layer = mech.model, mech.data, mech.constraints
    s = problem.settings
    rho = s.ali3p_penalty
    al_tol, al_max_iter = problem.solver_settings.al_tol, problem.solver_settings.al_max_iter
    dt, n_steps, out_steps = output_grid(t_final, control.dt, t_eval)
    info["dt"] = dt
    nv, nc = mech.nv, mech.nc
    # The method's factorization buffers, of the kept rows (made anew after a re-selection).
    solver = penalized_solver(mech)
    M, J, phi, gamma = np.zeros((nv, nv)), np.zeros((nc, nv)), np.zeros(nc), np.zeros(nc)
    h_vec = np.zeros(nv)
    lower = np.tril_indices(nv, -1)

    def evaluate(qk: np.ndarray, vk: np.ndarray) -> None:
        """M, h - tau_p at (qk, vk); phi, J at qk (one computeAllTerms)."""
        pin.computeAllTerms(model, data, qk, vk)
        M[:] = data.M
        M[lower] = M.T[lower]
        h_vec[:] = data.nle
        mech.passive.subtract_from_bias(qk, vk, h_vec)  # h - tau_p (springs, damping)
        if nc:
            layer.evaluate(model, data, phi=phi, J=J)

    t = 0.0
    a = problem.accel(t, q, v)
    problem.step_end(t, q, v, a)
    evaluate(q, v)
    alpha = relative_penalty(M, J, rho) if nc else 0.0
    info["ali3p_alpha"] = alpha
    # mu = h^2 / 4 lambda*: the multiplier estimate, warm-started from the method's
    # multipliers and carried from step to step (the augmented-Lagrangian memory).
    lam = np.array(problem.lam, dtype=float) if nc else np.zeros(0)
    outputs = OutputSteps(out_steps)
    if outputs.take(0):
        recorder.add(t, q, v, a, lam)
    counts = {"newton": 0}
    zero_v = np.zeros(nv)

    def advance(t_new, q, v, a, lam_star, h):
        """One trapezoidal step of length h ending at t_new from (q, v, a) with the
        multiplier estimate lam_star; return (q, v, a, lam_star, lam) at t_new."""
        tau = problem.torque(t_new, q, v)
        mu = h * h / 4.0 * lam_star
        # Predictor: Taylor to second order.
        delta = h * v + 0.5 * h * h * a
        converged = False
        last = np.inf
        for it in range(s.ali3p_max_iter):
            q_new = pin.integrate(model, q, delta)
            v_new = 2.0 / h * delta - v
            a_new = 4.0 / (h * h) * delta - 4.0 / h * v - a
            evaluate(q_new, v_new)
            if nc and it:
                # Bayo-Ledesma: lambda*_{i+1} = lambda*_i + alpha phi(q_{i+1}), then the
                # residual at q_{i+1} with lambda*_{i+1} (Cuadrado et al. 2000).
                mu += alpha * phi
            f = h * h / 4.0 * (M @ a_new + h_vec - tau)
            if nc:
                f += J.T @ (mu + alpha * phi)
                solver.factor(M, J, alpha, mech, q_new)
            else:
                solver.factor(M, np.zeros((0, nv)), 0.0, mech, q_new)
            if converged:
                break
            step = solver.solve(-f)
            delta += step
            counts["newton"] += 1
            size = float(np.max(np.abs(step)))
            # Below ali3p_tol, iterate on while the corrections still shrink (the
            # approximate tangent converges linearly): an error e left in Delta is an
            # error 2 e / h in v_{n+1}, and it accumulates over the steps.
            converged = (
                size <= s.ali3p_tol
                and (size <= s.ali3p_tol * ALI3P_TOL_FLOOR or size > ALI3P_STALL * last)
                and (not nc or float(np.max(np.abs(J.T @ phi))) <= s.ali3p_phi_tol)
            )
            last = size
        if not converged:
            raise SimulationError(
                f"{mech.name}: ALI3-P Newton iterations did not converge at t = {t_new:.9g} s "
                f"(last correction {float(np.max(np.abs(step))):.3e} > ali3p_tol "
                f"{s.ali3p_tol:.1e} after {s.ali3p_max_iter} iterations); use a smaller dt",
                t_new,
            )
        if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
            raise SimulationError(f"{mech.name}: non-finite state at t = {t_new:.9g} s", t_new)
        if not nc:
            return q_new, v_new, a_new, lam_star, lam_star
        lam_new = 4.0 / (h * h) * (mu + alpha * phi)
        # Mass-orthogonal projections (Cuadrado et al. 2000), with the factorization
        # of P at q_{n+1} from the last evaluation.
        v_new, _, _ = solve_augmented_lagrangian(
            solver,
            M,
            J,
            M @ v_new,
            np.zeros(nc),
            alpha,
            tol=al_tol,
            max_iter=al_max_iter,
            polish=False,
        )
        pin.forwardKinematics(model, data, q_new, v_new, zero_v)
        layer.evaluate(model, data, gamma=gamma)
        a_new, _, _ = solve_augmented_lagrangian(
            solver,
            M,
            J,
            M @ a_new,
            gamma,
            alpha,
            tol=al_tol,
            max_iter=al_max_iter,
            polish=False,
        )
        return q_new, v_new, a_new, 4.0 / (h * h) * mu, lam_new

    def indicator():
        """The rank indicator of J (fixed.rank_indicator) at the last evaluation."""
        return rank_indicator(J, solver.normal) if nc else RANK_INDICATOR_CAP

    # Singular positions: near a flat position the smallest singular value sigma of J
    # goes to zero linearly with the distance d to it, and the augmented-Lagrangian
    # update of lambda* converges along that row at the rate m / (m + h^2 alpha / 4
    # sigma^2) per Newton iteration: a step ending within about sqrt(4 m / (h^2 alpha))
    # of the crossing leaves the row unenforced (N-four-bar N = 5, dt 0.2 ms, a step
    # ending 0.002 step before the crossing: 27 iterations, crank angle off by 2.7e-6
    # rad). Steps therefore never end within singular_zone steps of a crossing, nor
    # where the rank indicator is predicted below sigma_min (ALI3P_ENFORCED; many loops
    # make the indicator grow slowly with the distance): the crossing's time is
    # extrapolated from the rank indicator at the last two states (before the first
    # step: q(-dt) by Taylor's expansion), and a step that would end near it is taken
    # with the next one as two unequal substeps, 1.5 and 0.5 steps (0.5 and 1.5 when
    # the crossing comes after the grid point; the skipped grid point's state is
    # interpolated for the output only), as rk4 does.
    zone = s.singular_zone
    sigma_min = math.sqrt(ALI3P_ENFORCED / s.ali3p_penalty)
    splits = 0
    lam_star = lam.copy()
    rho_now = indicator()  # J at q from the first evaluation
    # Before the first step, the previous grid point by Taylor's expansion backwards.
    evaluate(pin.integrate(model, q, -dt * v + 0.5 * dt * dt * a), v)
    rho_prev = indicator()
    gap = 1.0  # steps between the two indicators
    k = 1
    while k <= n_steps:
        # Crossing time [steps after t], linear through the last two grid points, and
        # the zone around it: singular_zone steps, or where the indicator is predicted
        # below sigma_min (slope: the indicator's change per step).
        tc, zone_k = math.inf, zone
        if rho_now < rho_prev:
            slope = (rho_prev - rho_now) / gap
            tc = rho_now / slope
            if zone > 0.0:
                zone_k = max(zone, min(ALI3P_ZONE_MAX, sigma_min / slope))
        gap = 1.0
        if abs(tc - 1.0) < zone_k:
            h1 = (ALI3P_SPLIT if tc <= 1.0 else 2.0 - ALI3P_SPLIT) * dt
            h2 = 2.0 * dt - h1
            q1, v1, a1, lam_star, lam1 = advance(t + h1, q, v, a, lam_star, h1)
            problem.step_end(t + h1, q1, v1, a1)
            q_new, v_new, a_new, lam_star, lam = advance(t + 2 * dt, q1, v1, a1, lam_star, h2)
            splits += 1
            gap = 2.0
            if outputs.take(k):
                if h1 > dt:
                    ends, s_k, h_k, lam_k = ((q, v, a), (q1, v1, a1)), dt / h1, h1, lam1
                else:
                    ends, s_k, h_k = ((q1, v1, a1), (q_new, v_new, a_new)), (dt - h1) / h2, h2
                    lam_k = lam
                _record_hermite(model, recorder, k * dt, s_k, h_k, *ends, lam_k)
            if progress is not None:
                progress(k * dt)
            if k == n_steps:  # the step beyond t_final only served the output
                break
            k += 1
        else:
            q_new, v_new, a_new, lam_star, lam = advance(k * dt, q, v, a, lam_star, dt)
        q, v, a = q_new, v_new, a_new
        t = k * dt
        problem.step_end(t, q, v, a)  # after the output between the substeps (split)
        rho_prev, rho_now = rho_now, indicator()  # J at q from advance's last evaluation
        if outputs.take(k):
            recorder.add(t, q, v, a, lam)
        if progress is not None:
            progress(t)
        k += 1
    info["newton_iterations"] = counts["newton"]
    info["singular_splits"] = splits
    return n_steps


def _record_hermite(model, recorder, t, s, h, start, end, lam) -> None:
    """Record the state at t = t0 + s h of the substep start -> end (each (q, v, a)) of
    length h by cubic Hermite interpolation, with the end's multipliers lam."""
    (q0, v0, a0), (q1, v1, a1) = start, end
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    dq = h10 * h * v0 + h01 * pin.difference(model, q0, q1) + h11 * h * v1
    q = pin.integrate(model, q0, dq)
    v = h00 * v0 + h10 * h * a0 + h01 * v1 + h11 * h * a1
    a = a0 + s * (a1 - a0)
    recorder.add(t, q, v, a, lam)
