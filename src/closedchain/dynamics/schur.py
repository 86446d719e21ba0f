r"""Range-space (Schur complement) method: multipliers first, then accelerations.

Eliminating the accelerations from the lesson's KKT system (Section 3) with the
Cholesky factor of the mass matrix, :math:`M = R^\top R`, leaves the
Delassus (operational-space inverse inertia) matrix of the loops:

.. math::

    D = J M^{-1} J^\top, \qquad
    D\,\lambda = J M^{-1} (\tau - h) + \gamma, \qquad
    a = M^{-1} (\tau - h - J^\top \lambda).

With :math:`Y = M^{-1} [\,J^\top \;|\; \tau - h\,]` from one triangular
solve pair, :math:`D` and the right-hand side come from one product
:math:`J Y`, and :math:`a = y - X \lambda` with :math:`X = M^{-1} J^\top`.
``D`` is symmetric positive definite while J has full row rank; both Cholesky
factorizations (LAPACK ``dpotrf``) are followed by a 1-norm condition estimate
(``dpocon``), and a condition number above ``settings.cond_max`` raises
:class:`SingularConfigurationError`. Since :math:`\mathrm{cond}(D)` grows like
:math:`\mathrm{cond}(J)^2`, this method refuses a configuration closer to a
singularity than the null-space method does.
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

_NAME = "schur"


@register(_NAME, MethodCapabilities(compiled=True))
def schur(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics by the range-space (Delassus) method.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``cond_max`` bounds the condition numbers of M and D.

    Returns:
        ``(a, lam)``: accelerations, shape (nv,) [rad/s^2 or m/s^2], and
        multipliers of the independent rows, shape (nc,), with
        ``M a + h + J^T lam = tau``.

    Raises:
        SingularConfigurationError: M or D is singular or ill-conditioned at q.
    """
    ws = compute_terms(mech, q, v, settings.baumgarte)
    nc = mech.nc
    M = ws.M
    # M is symmetric: its transpose is a Fortran-ordered view LAPACK reads without a copy.
    R, info = lapack.dpotrf(M.T, lower=0, clean=0)
    rcond = lapack.dpocon(R, lapack.dlange("1", M.T))[0] if info == 0 else 0.0
    check_condition(mech, q, "the mass matrix M", rcond, info, settings, MASS_HINT)
    f = tau - ws.h
    if nc == 0:
        return lapack.dpotrs(R, f)[0], np.zeros(0)
    Y = lapack.dpotrs(R, np.column_stack([ws.J.T, f]))[0]  # M^-1 [J^T | tau - h]
    JY = ws.J @ Y  # [D | J M^-1 (tau - h)]
    D = JY[:, :nc]
    b = JY[:, nc] + ws.gamma
    # D is symmetric (up to round-off in its lower triangle, which dpotrf with
    # lower=0 never reads): factor its upper triangle.
    Rd, info = lapack.dpotrf(D, lower=0, clean=0)
    rcond = lapack.dpocon(Rd, lapack.dlange("1", D))[0] if info == 0 else 0.0
    check_condition(mech, q, "the Delassus matrix J M^-1 J^T", rcond, info, settings)
    lam = lapack.dpotrs(Rd, b)[0]
    return Y[:, nc] - Y[:, :nc] @ lam, lam
