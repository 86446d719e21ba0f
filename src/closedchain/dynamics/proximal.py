r"""Proximal (regularized KKT) forward dynamics, as pinocchio.constraintDynamics does it.

The iterated proximal point method on the lesson's KKT system (Section 3)
regularizes the multipliers towards their previous iterate:

.. math::

    \begin{bmatrix} M & J^\top \\ J & -\mu I \end{bmatrix}
    \begin{bmatrix} a \\ \lambda_{k+1} \end{bmatrix}
    = \begin{bmatrix} \tau - h \\ -\gamma - \mu \lambda_k \end{bmatrix},

solved through its Schur complement, with :math:`D = J M^{-1} J^\top`,

.. math::

    (D + \mu I)\,\lambda_{k+1} = J M^{-1} (\tau - h) + \gamma + \mu \lambda_k,
    \qquad a = M^{-1} (\tau - h - J^\top \lambda_{k+1}),

from :math:`\lambda_0 = 0`. D + mu I is positive definite for any rank of J,
so the method is defined with redundant rows and at singular configurations.
When J a + gamma = 0 is consistent the iterates converge to the KKT solution
with the minimum-norm multipliers; the error along a direction of D with
eigenvalue d shrinks by :math:`\mu / (d + \mu)` per iteration. The bias is
that contraction: along a direction where J is nearly rank-deficient (d
small, a singular configuration) the iteration stops at ``prox_max_iter`` with
the constraint only partly enforced, by the factor
:math:`1 - (\mu / (d + \mu))^{k}` after k iterations. Measured on the
N-four-bar (N = 2, cranks at 3 rad/s, defaults mu_r = 1e-8, 50 iterations):
at the flat position itself (consistent, rank-deficient J) it converges
(|J a + gamma| 4e-15); at 1e-4 rad from it the iteration stops at the cap
with |J a + gamma| = 1.9e-12 and accelerations 3.8e-8 rad/s^2 from kkt; at
1e-2 rad it agrees with kkt to 5e-15 (tests/test_singular.py). The relative regularization is
:math:`\mu = \mu_r \max \mathrm{diag}(D)` with mu_r = ``SolverSettings.prox_mu``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import lapack

from .base import (
    MASS_HINT,
    MethodCapabilities,
    SolverSettings,
    check_condition,
    compute_terms,
    register,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

_NAME = "proximal"


def solve_proximal(
    M: np.ndarray,
    J: np.ndarray,
    rhs: np.ndarray,
    gamma: np.ndarray,
    *,
    mu_rel: float,
    tol: float,
    max_iter: int,
) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Iterate the proximal point method on the KKT system.

    Args:
        M: mass matrix, shape (nv, nv), symmetric positive definite.
        J: constraint Jacobian, shape (nc, nv) (any rank).
        rhs: tau - h, shape (nv,).
        gamma: shape (nc,).
        mu_rel: regularization relative to max diag(J M^-1 J^T).
        tol: stop when max |J^T (lam_{k+1} - lam_k)| <= tol (1 + max |rhs|).
        max_iter: iteration cap.

    Returns:
        ``(a, lam, iterations, rcond_M)``.
    """
    R, info = lapack.dpotrf(M, lower=0, clean=1)
    rcond = lapack.dpocon(R, lapack.dlange("1", M))[0] if info == 0 else 0.0
    if info != 0:
        return np.full(M.shape[0], np.nan), np.zeros(J.shape[0]), 0, 0.0
    Y = lapack.dpotrs(R, np.column_stack([J.T, rhs]))[0]  # M^-1 [J^T | tau - h]
    X, y = Y[:, :-1], Y[:, -1]
    if J.shape[0] == 0:  # no loop rows (an open chain): a = M^-1 (tau - h)
        return y, np.zeros(0), 0, float(rcond)
    D = J @ X
    mu = mu_rel * max(float(np.max(np.diag(D), initial=0.0)), np.finfo(float).tiny)
    Dm = D + mu * np.eye(D.shape[0])
    Rd, info = lapack.dpotrf(Dm, lower=0, clean=1)
    b0 = J @ y + gamma
    lam = np.zeros(J.shape[0])
    scale = 1.0 + float(np.max(np.abs(rhs), initial=0.0))
    it = 0
    while it < max_iter:
        lam_new = lapack.dpotrs(Rd, b0 + mu * lam)[0]
        it += 1
        change = float(np.max(np.abs(J.T @ (lam_new - lam)), initial=0.0))
        lam = lam_new
        if change <= tol * scale:
            break
    a = y - X @ lam
    return a, lam, it, float(rcond)


@register(_NAME, MethodCapabilities(baumgarte=True, singular_robust=False, redundant_rows=True))
def proximal(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics by the iterated proximal point method.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``prox_mu``, ``prox_tol``, ``prox_max_iter``; ``baumgarte``.

    Returns:
        ``(a, lam)``: accelerations (nv,) and multipliers (nc,), with
        ``M a + h + J^T lam = tau`` (minimum-norm lam with redundant rows).

    Raises:
        SingularConfigurationError: M is singular.
    """
    ws = compute_terms(mech, q, v, settings.baumgarte)
    a, lam, _, rcond = solve_proximal(
        ws.M,
        ws.J,
        tau - ws.h,
        ws.gamma,
        mu_rel=settings.prox_mu,
        tol=settings.prox_tol,
        max_iter=settings.prox_max_iter,
    )
    check_condition(mech, q, "the mass matrix M", rcond, 0 if rcond > 0 else 1, settings, MASS_HINT)
    return a, lam
