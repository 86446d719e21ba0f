r"""Pinocchio's proximal constrained dynamics as a method: ``pinocchio.constraintDynamics``.

Pinocchio solves the loops as its own rigid constraint models (a revolute
loop as two CONTACT_3D points on the axis, see
:func:`closedchain.constraints.build_pinocchio_constraints`) with a proximal
(augmented Lagrangian) iteration,

.. math::

    \lambda_{k+1} = \arg\min_\lambda \; \tfrac12 \lambda^\top D \lambda
    + \lambda^\top b + \tfrac{\mu}{2} \lVert \lambda - \lambda_k \rVert^2,

which copes with redundant rows through the regularization ``mu``. Its forces
``lambda_c`` (constraint frames, Pinocchio's sign: ``M a + h = tau + J_c^T
lambda_c``) become the generalized constraint force of our convention,
:math:`f = -J_c^\top \lambda_c`, and our multipliers of the independent rows
are the least-squares solution of :math:`J^\top \lambda = f` (LAPACK
``dgels``, QR of :math:`J^\top`).

Convergence is judged by the answer, not by Pinocchio's flags: with
redundant rows (every loop here) Pinocchio's ``absolute_residual`` stays of
order 1-1000 and ``iter`` reaches ``max_iter`` even when the accelerations
agree with an exact KKT solve to 1e-13 (pin 4.1). The answer is accepted when
it is finite and satisfies the acceleration constraint,

.. math::

    \lVert J a + \gamma \rVert_\infty \le
    \mathtt{PINOCCHIO\_RESIDUAL\_RTOL}\,
    \bigl(1 + \lVert \gamma \rVert_\infty + \lVert J \rVert_\infty \lVert a \rVert_\infty\bigr),

otherwise (NaN, divergence, or a regularized answer that no longer closes the
loops near a singularity) :class:`SingularConfigurationError` is raised. The
same happens when J has lost rank, where our multipliers are undefined: the
1-norm condition estimate (LAPACK ``dtrcon``) of the triangular factor of
:math:`J^\top = Q R`, equal to cond(J) up to a factor of order nc, above
``settings.cond_max``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from ..exceptions import ClosedChainError, SingularConfigurationError
from .base import (
    MethodCapabilities,
    SolverSettings,
    compute_terms,
    method_buffers,
    register,
    workspace,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

_NAME = "pinocchio"

#: Relative bound on the acceleration-constraint residual |J a + gamma| of
#: Pinocchio's answer (see the module docstring); converged answers reach ~1e-13.
PINOCCHIO_RESIDUAL_RTOL = 1e-8


_NON_FINITE = (
    "it returned non-finite accelerations or forces (with redundant rows, mu = 0 gives NaN)"
)


class _PinocchioBuffers:
    """The proximal settings object, rebuilt only when the solver settings change."""

    def __init__(self) -> None:
        self.settings: SolverSettings | None = None
        self.prox: pin.ProximalSettings | None = None

    def proximal(self, settings: SolverSettings) -> pin.ProximalSettings:
        if settings is not self.settings and settings != self.settings:
            self.prox = settings.pinocchio_proximal()
            self.settings = settings
        assert self.prox is not None
        return self.prox


def pinocchio_constrained_dynamics(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(a, J^T lam)`` from ``pinocchio.constraintDynamics``, in our sign convention.

    Uses the mechanism's Pinocchio constraint models and data (built once) and
    a cached ``ProximalSettings``; does not touch ``mech.data``.

    Args:
        mech: the mechanism (no prismatic loops).
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``pinocchio_mu``, ``pinocchio_accuracy``, ``pinocchio_max_iter``.

    Returns:
        Accelerations, shape (nv,) [rad/s^2 or m/s^2], and the generalized
        constraint force :math:`J^\\top\\lambda = -J_c^\\top\\lambda_c`, shape (nv,)
        [N m or N] (NaN when Pinocchio fails: the caller checks).

    Raises:
        ValidationUnavailableError: a prismatic loop.
    """
    cms, cds, _, data = mech.pinocchio_constraints()
    ws = workspace(mech)
    buf = method_buffers(ws, _NAME, _PinocchioBuffers)
    prox = buf.proximal(settings)
    model = mech.model
    tau = mech.passive.added_to(tau, q, v)  # Pinocchio has no joint springs or damping
    a = pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox).copy()
    # (nc, nv) also for nv = 1, which Pinocchio returns as a vector.
    Jc = np.reshape(pin.getConstraintsJacobian(model, data, cms, cds), (-1, model.nv))
    # Pinocchio: M a + h = tau + J_c^T lambda_c  ->  ours: J^T lam = -J_c^T lambda_c.
    force = data.lambda_c @ Jc
    np.negative(force, out=force)
    return a, force


# pinocchio.constraintDynamics solves its own constraint equations: no Baumgarte terms.
@register(_NAME, MethodCapabilities(baumgarte=False))
def pinocchio_method(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics with ``pinocchio.constraintDynamics``.

    Args:
        mech: the mechanism (no prismatic loops: Pinocchio has no model for them).
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N].
        settings: the proximal settings and ``cond_max`` (bound on cond(J)).

    Returns:
        ``(a, lam)``: accelerations, shape (nv,) [rad/s^2 or m/s^2], and
        multipliers of our independent rows, shape (nc,), with
        ``M a + h + J^T lam = tau`` (least squares).

    Raises:
        SingularConfigurationError: Pinocchio's answer is not finite or does not
            satisfy the acceleration constraint, or J has lost rank, at q.
        ValidationUnavailableError: a prismatic loop.
    """
    if settings.baumgarte is not None:
        raise ClosedChainError(
            "method 'pinocchio' cannot apply Baumgarte gains (pinocchio.constraintDynamics "
            "solves J a + gamma = 0); use kkt, schur, nullspace or reduced"
        )
    a, force = pinocchio_constrained_dynamics(mech, q, v, tau, settings)
    ws = compute_terms(mech, q, v)  # our J and gamma, for lam and the residuals
    nc = mech.nc
    J, gamma = ws.J, ws.gamma
    # One finiteness test for both arrays: a NaN or inf propagates into the sum.
    if not math.isfinite(float(a.sum()) + float(force.sum())):
        _raise(mech, q, J, _NON_FINITE, settings)
    if nc == 0:
        return a, np.zeros(0)
    residual = J @ a
    residual += gamma
    r = float(np.abs(residual).max())
    scale = 1.0 + float(np.abs(gamma).max()) + float(np.abs(J).max()) * float(np.abs(a).max())
    if r > PINOCCHIO_RESIDUAL_RTOL * scale:
        # Off the manifold (an integrator's stage) Pinocchio's world-point rows and
        # our cut-frame rows R_p^T d have different second derivatives: they differ
        # by 2 dR_p^T/dt d' + d2R_p^T/dt2 d, bounded with |omega_p| <= |v|_1 by
        # 2 |v|_1 |J v| + 4 |v|_1^2 |phi| (constraints.py rows). Only that much is
        # not a convergence failure.
        mech.constraints.evaluate(mech.model, mech.data, phi=ws.phi)
        c = float(np.abs(v).sum())
        scale += (
            2.0 * c * float(np.linalg.norm(J @ v)) + 4.0 * c * c * float(np.linalg.norm(ws.phi))
        ) / PINOCCHIO_RESIDUAL_RTOL
    if r > PINOCCHIO_RESIDUAL_RTOL * scale:
        _raise(
            mech,
            q,
            J,
            f"its answer violates the acceleration constraint (max |J a + gamma| = "
            f"{r:.3e} > {PINOCCHIO_RESIDUAL_RTOL:.0e} x {scale:.3e}): the proximal "
            "iterations did not converge",
            settings,
        )
    lqr, x, info = lapack.dgels(J.T, force)
    rcond = lapack.dtrcon(lqr[:nc, :nc])[0] if info == 0 else 0.0
    if rcond * settings.cond_max <= 1.0:
        _raise(mech, q, J, "the constraint Jacobian J has lost rank", settings)
    return a, x[:nc]


def _raise(mech: Mechanism, q: np.ndarray, J: np.ndarray, why: str, settings) -> None:
    s = np.linalg.svd(J, compute_uv=False) if J.size else np.ones(1)
    cond = float(s[0] / s[-1]) if s[-1] > 0 and np.isfinite(s).all() else float("inf")
    raise SingularConfigurationError.build(
        mech.name,
        "pinocchio.constraintDynamics",
        q=q,
        cond=cond,
        bound=settings.cond_max,
        state="failed",
        detail=f" of J; mu = {settings.pinocchio_mu:.1e}",
        hint=why,
    )
