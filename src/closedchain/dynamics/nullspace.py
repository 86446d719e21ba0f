r"""Null-space method: accelerations in an orthonormal basis of the tangent space.

From one singular value decomposition of the constraint Jacobian,

.. math::

    J = U \Sigma V_r^\top, \qquad V = [\,V_r \;|\; N\,], \qquad J N = 0,
    \quad N^\top N = I,

every acceleration with :math:`J a + \gamma = 0` is :math:`a = a_p + N z`
with the minimum-norm particular solution
:math:`a_p = -V_r \Sigma^{-1} U^\top \gamma`. Projecting the equations of
motion onto the tangent space removes the multipliers (:math:`N^\top J^\top = 0`):

.. math::

    (N^\top M N)\, z = N^\top (\tau - h - M a_p), \qquad a = a_p + N z,

and the multipliers follow from the range-space equations in the least-squares
sense, exact when the motion is consistent:

.. math::

    J^\top \lambda = f := \tau - h - M a
    \quad\Rightarrow\quad \lambda = U \Sigma^{-1} V_r^\top f.

Rank loss of J is detected from its singular values: the method raises
:class:`SingularConfigurationError` when the 2-norm condition number
:math:`\sigma_{\max}/\sigma_{\min}` of J exceeds ``settings.cond_max`` (the
named threshold; rows are independent by construction, so this happens only
near a singular configuration). The reduced mass matrix :math:`N^\top M N` is
Cholesky-factored with a 1-norm condition check against the same bound. The
errors of ``a`` and ``lam`` grow like :math:`\mathrm{cond}(J)` (not its square,
as in the KKT and Schur methods), which keeps this method accurate closest to
a singularity.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import lapack

from ..exceptions import SingularConfigurationError
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

_NAME = "nullspace"


def check_rank(mech: Mechanism, q: np.ndarray, s: np.ndarray, settings: SolverSettings) -> None:
    """Raise when the singular values ``s`` of J say that J has lost rank.

    Args:
        mech: the mechanism (for the message).
        q: configuration, shape (nq,).
        s: singular values of J, descending, shape (nc,).
        settings: ``cond_max``, the bound on :math:`\\sigma_{\\max}/\\sigma_{\\min}`.
    """
    smax, smin = float(s[0]), float(s[-1])
    if smin * settings.cond_max <= smax:
        cond = smax / smin if smin > 0.0 else float("inf")
        raise SingularConfigurationError.build(
            mech.name,
            "the constraint Jacobian J",
            q=q,
            cond=cond,
            bound=settings.cond_max,
            state="has lost rank",
            detail=f"; sigma_min = {smin:.3e}, sigma_max = {smax:.3e}",
            hint="the configuration is a singularity",
        )


@register(_NAME, MethodCapabilities(compiled=True))
def nullspace(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics in an orthonormal null-space basis of J.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``cond_max`` bounds cond(J) and cond(N^T M N).

    Returns:
        ``(a, lam)``: accelerations, shape (nv,) [rad/s^2 or m/s^2], and
        multipliers of the independent rows, shape (nc,), with
        ``M a + h + J^T lam = tau``.

    Raises:
        SingularConfigurationError: J has lost rank, or N^T M N is singular, at q.
    """
    ws = compute_terms(mech, q, v, settings.baumgarte)
    nv, nc = mech.nv, mech.nc
    M = ws.M
    f = tau - ws.h  # then tau - h - M a_p, then tau - h - M a
    if nc == 0:
        N = np.eye(nv)
        a_p = np.zeros(nv)
        U = s = Vr = None
    else:
        U, s, Vt, info = lapack.dgesdd(ws.J)
        if info != 0:
            s = np.zeros(nc)
        check_rank(mech, q, s, settings)
        Vr, N = Vt[:nc], Vt[nc:].T
        a_p = -((ws.gamma @ U) / s) @ Vr  # the minimum-norm solution of J a = -gamma
        f = f - M @ a_p
    if N.shape[1]:
        MN = M @ N
        Mr = N.T @ MN
        R, info = lapack.dpotrf(Mr, lower=0, clean=0)
        rcond = lapack.dpocon(R, lapack.dlange("1", Mr))[0] if info == 0 else 0.0
        check_condition(
            mech, q, "the reduced mass matrix N^T M N", rcond, info, settings, MASS_HINT
        )
        z = lapack.dpotrs(R, f @ N)[0]
        a = a_p + N @ z
        f = f - MN @ z  # now tau - h - M a
    else:
        a = a_p
    if nc == 0:
        return a, np.zeros(0)
    return a, U @ ((Vr @ f) / s)
