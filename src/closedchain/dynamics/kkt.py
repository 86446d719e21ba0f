"""The seed's dense KKT (saddle-point) system, Section 3.

.. math::

    \\begin{bmatrix} M & J^\\top \\\\ J & 0 \\end{bmatrix}
    \\begin{bmatrix} a \\\\ \\lambda \\end{bmatrix}
    = \\begin{bmatrix} \\tau - h \\\\ -\\gamma \\end{bmatrix}

solved by LU with partial pivoting (LAPACK ``dgesv``) after a symmetric
equilibration (:func:`kkt_scaling`); the 1-norm condition number of the
equilibrated matrix is estimated from the factors (``dgecon``) and a singular or
ill-conditioned one raises :class:`SingularConfigurationError`. Equilibrated, the
estimate does not depend on the units: scaling every mass and inertia by s scales
M by s and leaves the equilibrated matrix unchanged, so a heavy mechanism (the
5-bar of example-parallel-robots, 6.5e5 kg spheres: 2.7e11 unscaled, 1.0e6
equilibrated at rest) is not reported singular for its mass unit.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .base import MethodCapabilities, SolverSettings, check_condition, compute_terms, register

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
        LAPACK reciprocal 1-norm condition estimate of the equilibrated K (D K D,
        :func:`kkt_scaling`, which is the matrix factorized: K x = r is solved as
        (D K D) y = D r, x = D y) and dgesv's info (> 0: K exactly singular).
        Callers decide what condition is acceptable.
    """
    nv, nc = M.shape[0], J.shape[0]
    K = np.empty((nv + nc, nv + nc), order="F") if K is None else K
    rhs = np.empty(nv + nc) if rhs is None else rhs
    d_v, d_c = kkt_scaling(M, J)
    Js = d_c[:, None] * J * d_v
    K[:nv, :nv] = d_v[:, None] * M * d_v
    K[:nv, nv:] = Js.T
    K[nv:, :nv] = Js
    K[nv:, nv:] = 0.0
    rhs[:nv] = d_v * tau_minus_h
    rhs[nv:] = -d_c * gamma
    anorm = lapack.dlange("1", K)  # K in Fortran order: no copy
    lu, _, x, info = lapack.dgesv(K, rhs)
    rcond = lapack.dgecon(lu, anorm)[0] if info == 0 else 0.0
    return d_v * x[:nv], d_c * x[nv:], float(rcond), int(info)


@register("kkt", MethodCapabilities(compiled=True))
def kkt(mech, q, v, tau, settings: SolverSettings):
    """Solve the dense KKT system; return (a, lam)."""
    ws = compute_terms(mech, q, v, settings.baumgarte)
    a, lam, rcond, info = solve_kkt(ws.M, ws.J, tau - ws.h, ws.gamma, K=ws.K, rhs=ws.rhs)
    check_condition(
        mech, q, "the KKT matrix [[M, J^T], [J, 0]] (equilibrated)", rcond, info, settings
    )
    return a, lam
