"""The seed's dense KKT (saddle-point) system, Section 3.

.. math::

    \\begin{bmatrix} M & J^\\top \\\\ J & 0 \\end{bmatrix}
    \\begin{bmatrix} a \\\\ \\lambda \\end{bmatrix}
    = \\begin{bmatrix} \\tau - h \\\\ -\\gamma \\end{bmatrix}

solved by LU with partial pivoting (LAPACK ``dgesv``); the 1-norm condition
number is estimated from the factors (``dgecon``) and a singular or
ill-conditioned matrix raises :class:`SingularConfigurationError`.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .base import MethodCapabilities, SolverSettings, check_condition, compute_terms, register


def solve_kkt(
    M: np.ndarray,
    J: np.ndarray,
    tau_minus_h: np.ndarray,
    gamma: np.ndarray,
    *,
    K: np.ndarray | None = None,
    rhs: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Solve the KKT system of the seed's C++ ``solveKKT`` (Section 8).

    Args:
        M: mass matrix, shape (nv, nv), symmetric positive definite.
        J: constraint Jacobian, shape (nc, nv).
        tau_minus_h: tau - h, shape (nv,).
        gamma: Jdot v, shape (nc,).
        K: optional preallocated buffer, shape (nv + nc, nv + nc), Fortran order
            (C order works, at the cost of a copy inside LAPACK's wrapper).
        rhs: optional preallocated buffer, shape (nv + nc,).

    Returns:
        ``(a, lam, rcond, info)``: accelerations (nv,), multipliers (nc,), the
        LAPACK reciprocal 1-norm condition estimate of K and dgesv's info
        (> 0: K exactly singular). Callers decide what condition is acceptable.
    """
    nv, nc = M.shape[0], J.shape[0]
    K = np.empty((nv + nc, nv + nc), order="F") if K is None else K
    rhs = np.empty(nv + nc) if rhs is None else rhs
    K[:nv, :nv] = M
    K[:nv, nv:] = J.T
    K[nv:, :nv] = J
    K[nv:, nv:] = 0.0
    rhs[:nv] = tau_minus_h
    rhs[nv:] = -gamma
    anorm = lapack.dlange("1", K)  # K in Fortran order: no copy
    lu, _, x, info = lapack.dgesv(K, rhs)
    rcond = lapack.dgecon(lu, anorm)[0] if info == 0 else 0.0
    return x[:nv], x[nv:], float(rcond), int(info)


@register("kkt", MethodCapabilities(compiled=True))
def kkt(mech, q, v, tau, settings: SolverSettings):
    """Solve the dense KKT system; return (a, lam)."""
    ws = compute_terms(mech, q, v, settings.baumgarte)
    a, lam, rcond, info = solve_kkt(ws.M, ws.J, tau - ws.h, ws.gamma, K=ws.K, rhs=ws.rhs)
    check_condition(mech, q, "the KKT matrix [[M, J^T], [J, 0]]", rcond, info, settings)
    return a, lam
