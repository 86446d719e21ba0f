"""The lesson's dense KKT (saddle-point) system, Section 3.

.. math::

    \\begin{bmatrix} M & J^\\top \\\\ J & 0 \\end{bmatrix}
    \\begin{bmatrix} a \\\\ \\lambda \\end{bmatrix}
    = \\begin{bmatrix} \\tau - h \\\\ -\\gamma \\end{bmatrix}

solved by LU with partial pivoting (LAPACK ``dgetrf``/``dgetrs``, as ``dgesv``) of K
as it stands; a singular or ill-conditioned K raises
:class:`SingularConfigurationError`. What is judged is the 1-norm condition number of
the equilibrated matrix D K D (:func:`kkt_scaling`), estimated from K's own factors
(:func:`estimate_scaled_inverse_norm`): it does not depend on the units (scaling every
mass and inertia by s scales M by s and leaves D K D unchanged), so a heavy mechanism
(the 5-bar of example-parallel-robots, 6.5e5 kg spheres: 2.7e11 unscaled, 1.0e6
equilibrated at rest) is not reported singular for its mass unit. The solve itself is
not equilibrated: near a singular J, solving D K D loses digits that the pivoted LU of
K keeps (tests/test_validation.py compares both with a 40-digit solve).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .base import (
    KKT_HINT,
    MethodCapabilities,
    SolverSettings,
    check_condition,
    compute_terms,
    register,
)

#: Equilibration floor of the KKT matrix (:func:`kkt_scaling`): a diagonal entry of M, or a
#: row norm of J D_v, below this fraction of the largest is scaled as if it were that
#: fraction, so that a row holding only round-off (a lost rank) is not blown up to unit
#: norm and still shows in the condition number [-].
KKT_SCALE_FLOOR = 1e-8


def kkt_scaling(M: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""Return the symmetric equilibration D = diag(d_v, d_c) of K = [[M, J^T], [J, 0]].

    .. math::

        d_{v,i} = M_{ii}^{-1/2}, \qquad d_{c,r} = \lVert (J D_v)_{r,:} \rVert_2^{-1},

    so that D K D has a unit diagonal in its M block and unit-norm rows in its J block
    (each with the floor :data:`KKT_SCALE_FLOOR` relative to the largest). D K D is
    the same matrix for every choice of mass unit (M -> s M) and of each row's unit.

    Args:
        M: mass matrix, shape (nv, nv), symmetric positive definite.
        J: constraint Jacobian, shape (nc, nv).

    Returns:
        ``(d_v, d_c)``: shapes (nv,) and (nc,), positive.
    """
    diag = np.diagonal(M)
    top = float(np.max(diag, initial=0.0))
    d_v = 1.0 / np.sqrt(np.maximum(diag, KKT_SCALE_FLOOR * top)) if top > 0 else np.ones(len(diag))
    norms = np.linalg.norm(J * d_v, axis=1)
    top = float(np.max(norms, initial=0.0))
    d_c = 1.0 / np.maximum(norms, KKT_SCALE_FLOOR * top) if top > 0 else np.ones(len(norms))
    return d_v, d_c


#: Sign iterations of :func:`estimate_scaled_inverse_norm` at most (LAPACK's dlacn2 ITMAX).
ESTIMATE_MAX_ITER = 5


def estimate_scaled_inverse_norm(lu: np.ndarray, piv: np.ndarray, s: np.ndarray) -> float:
    """Estimate the 1-norm of S A^-1 S, S = diag(s), from the LU factors of A (``dgetrf``).

    Hager's method as refined by Higham (LAPACK's ``dlacn2``, which ``dgecon`` runs with
    S = I) on B = S A^-1 S: from x = (1/n, ..., 1/n), at most :data:`ESTIMATE_MAX_ITER`
    steps of y = B x, z = B^T sign(y), x = the unit vector at the largest abs(z_j), while
    the 1-norm of y grows; then the alternating test vector
    :math:`x_i = (-1)^i (1 + i / (n - 1))`. Each product with B is a solve with A's
    factors wrapped by S on both sides. A lower bound of the norm, almost always within a
    factor 3 of it (Higham, Accuracy and Stability of Numerical Algorithms, 2002, Sec.
    15.3). The compiled core runs the same steps (dense_lu.hpp ``inverse_norm_estimate``).

    Args:
        lu: LU factors of A, shape (n, n), as ``dgetrf`` returns them (regular).
        piv: ``dgetrf``'s pivot indices, shape (n,).
        s: the scaling, shape (n,), positive.

    Returns:
        The estimate (inf where a solve overflows).
    """
    n = len(s)
    if n == 0:
        return 0.0

    def apply(x: np.ndarray, trans: int) -> np.ndarray:
        return s * lapack.dgetrs(lu, piv, s * x, trans=trans)[0]

    x = np.full(n, 1.0 / n)
    est = 0.0
    j_last = -1
    with np.errstate(over="ignore", invalid="ignore"):
        for it in range(ESTIMATE_MAX_ITER):
            y = apply(x, 0)
            e = float(np.abs(y).sum())
            if it > 0 and e <= est:
                break
            est = e
            z = apply(np.where(y >= 0, 1.0, -1.0), 1)
            j = int(np.argmax(np.abs(z)))
            if it > 0 and j == j_last:
                break
            j_last = j
            x = np.zeros(n)
            x[j] = 1.0
        alternating = (-1.0) ** np.arange(n) * (1.0 + np.arange(n) / max(n - 1, 1))
        est = max(est, 2.0 * float(np.abs(apply(alternating, 0)).sum()) / (3.0 * n))
    return est if np.isfinite(est) else float("inf")


def solve_kkt(
    M: np.ndarray,
    J: np.ndarray,
    tau_minus_h: np.ndarray,
    gamma: np.ndarray,
    *,
    K: np.ndarray | None = None,
    rhs: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    r"""Solve the KKT system of the lesson's C++ ``solveKKT`` (Section 8).

    K is factorized and solved as it stands (one ``dgetrf``); its condition is judged on
    the equilibrated D K D (:func:`kkt_scaling`), independent of the units:

    .. math::

        \kappa_1(D K D) = \lVert D K D \rVert_1 \, \lVert D^{-1} K^{-1} D^{-1} \rVert_1,

    the second factor estimated with K's factors (:func:`estimate_scaled_inverse_norm`).

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
        reciprocal of the estimate of the equilibrated matrix's 1-norm condition number
        above and dgetrf's info (> 0: K exactly singular). Callers decide what condition
        is acceptable.
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
    d = np.concatenate(kkt_scaling(M, J))
    scaled_norm = float(np.max(d * (d @ np.abs(K)), initial=0.0))  # ||D K D||_1
    lu, piv, info = lapack.dgetrf(K)
    x = lapack.dgetrs(lu, piv, rhs)[0] if info == 0 else np.full(nv + nc, np.nan)
    rcond = 0.0
    if info == 0 and scaled_norm > 0:
        est = estimate_scaled_inverse_norm(lu, piv, 1.0 / d)
        rcond = 1.0 / (est * scaled_norm) if 0 < est < float("inf") else 0.0
    return x[:nv], x[nv:], float(rcond), int(info)


@register("kkt", MethodCapabilities(compiled=True))
def kkt(mech, q, v, tau, settings: SolverSettings):
    """Solve the dense KKT system; return (a, lam)."""
    ws = compute_terms(mech, q, v, settings.baumgarte)
    a, lam, rcond, info = solve_kkt(ws.M, ws.J, tau - ws.h, ws.gamma, K=ws.K, rhs=ws.rhs)
    check_condition(
        mech, q, "the KKT matrix [[M, J^T], [J, 0]] (equilibrated)", rcond, info, settings, KKT_HINT
    )
    return a, lam
