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

The scheme is second-order accurate and fixed-step; its settings are
``SimulationSettings.ali3p_tol``, ``ali3p_max_iter`` and ``ali3p_penalty``.
"""

from __future__ import annotations

import logging

import numpy as np
import pinocchio as pin

from ..dynamics.augmented_lagrangian import (
    PenalizedSolver,
    relative_penalty,
    solve_augmented_lagrangian,
)
from ..dynamics.base import method_buffers, workspace
from .fixed import OutputSteps, output_grid
from .problem import Problem
from .settings import SimulationError

logger = logging.getLogger(__name__)

_BUFFERS = "augmented-lagrangian"  # shares the method's factorization buffers
#: Newton stops below ali3p_tol once a correction is this fraction of it, or once the
#: corrections stop shrinking by at least ALI3P_STALL per iteration (round-off floor).
ALI3P_TOL_FLOOR = 1e-4
ALI3P_STALL = 0.5


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
    ws = workspace(mech)
    solver = method_buffers(ws, _BUFFERS, lambda: PenalizedSolver(mech))
    M, J, phi, gamma = np.zeros((nv, nv)), np.zeros((nc, nv)), np.zeros(nc), np.zeros(nc)
    h_vec = np.zeros(nv)
    lower = np.tril_indices(nv, -1)

    def evaluate(qk: np.ndarray, vk: np.ndarray) -> None:
        """M, h at (qk, vk); phi, J at qk (one computeAllTerms)."""
        pin.computeAllTerms(model, data, qk, vk)
        M[:] = data.M
        M[lower] = M.T[lower]
        h_vec[:] = data.nle
        if nc:
            layer.evaluate(model, data, phi=phi, J=J)

    t = 0.0
    a = problem.accel(t, q, v)
    evaluate(q, v)
    alpha = relative_penalty(M, J, rho) if nc else 0.0
    info["ali3p_alpha"] = alpha
    # mu = h^2 / 4 lambda*: the multiplier estimate, warm-started from the method's
    # multipliers and carried from step to step (the augmented-Lagrangian memory).
    mu = dt * dt / 4.0 * np.array(problem.lam, dtype=float) if nc else np.zeros(0)
    outputs = OutputSteps(out_steps)
    if outputs.take(0):
        recorder.add(t, q, v, a, problem.lam)
    newton_total = 0
    zero_v = np.zeros(nv)
    for k in range(1, n_steps + 1):
        t_new = k * dt
        tau = problem.torque(t_new, q, v)
        # Predictor: Taylor to second order.
        delta = dt * v + 0.5 * dt * dt * a
        converged = False
        last = np.inf
        for it in range(s.ali3p_max_iter):
            q_new = pin.integrate(model, q, delta)
            v_new = 2.0 / dt * delta - v
            a_new = 4.0 / (dt * dt) * delta - 4.0 / dt * v - a
            evaluate(q_new, v_new)
            if nc and it:
                # Bayo-Ledesma: lambda*_{i+1} = lambda*_i + alpha phi(q_{i+1}), then the
                # residual at q_{i+1} with lambda*_{i+1} (Cuadrado et al. 2000).
                mu += alpha * phi
            f = dt * dt / 4.0 * (M @ a_new + h_vec - tau)
            if nc:
                f += J.T @ (mu + alpha * phi)
                solver.factor(M, J, alpha, mech, q_new)
            else:
                solver.factor(M, np.zeros((0, nv)), 0.0, mech, q_new)
            if converged:
                break
            step = solver.solve(-f)
            delta += step
            newton_total += 1
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
        lam = 4.0 / (dt * dt) * (mu + alpha * phi) if nc else np.zeros(0)
        if nc:
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
        q, v, a = q_new, v_new, a_new
        t = t_new
        if outputs.take(k):
            recorder.add(t, q, v, a, lam)
        if progress is not None:
            progress(t)
    info["newton_iterations"] = newton_total
    return n_steps
