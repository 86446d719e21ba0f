"""The partition of the velocity coordinates into independent and dependent ones.

Column-pivoted QR of the kept-row Jacobian (Wehage & Haug 1982), with an
optional tie rule that makes the choice independent of round-off (both
backends re-partition alike).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg

#: Relative tolerance under which two candidate pivot columns of the re-partitioning QR
#: count as tied (:func:`partition_coordinates` with ``tie_rtol``): the Agile Eye's
#: columns tie exactly (platform columns of norm sqrt(2), distal ones of sqrt(2)/2), so
#: LAPACK's choice among them is decided by round-off, differently in the compiled core.
PIVOT_TIE_RTOL = 1e-9


def partition_coordinates(
    J: np.ndarray, tie_rtol: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    r"""Split the velocity coordinates into independent and dependent ones for J.

    Column-pivoted QR of J (Businger-Golub) picks, greedily, the ``nc``
    columns farthest from linearly dependent: they become the dependent
    coordinates, so :math:`\sigma_{\min}(J_D)` stays within a modest factor of
    :math:`\sigma_{\min}(J)` (not an exhaustive search of all partitions).

    Args:
        J: constraint Jacobian, shape (nc, nv), independent rows.
        tie_rtol: None: LAPACK's ``dgeqp3`` (the first largest remaining norm, so
            exact ties are broken by round-off). A number: columns whose remaining
            norm is within ``tie_rtol`` (relative) of the largest are tied and the
            lowest index wins, so the choice does not depend on round-off (the
            re-partitioning of both backends: :data:`PIVOT_TIE_RTOL`).

    Returns:
        ``(independent_idx_v, dependent_idx_v)``, sorted, shapes (nv - nc,) and (nc,).
    """
    nc, nv = J.shape
    if nc == 0:
        return np.arange(nv), np.arange(0)
    if tie_rtol is None:
        _, piv = scipy.linalg.qr(J, mode="r", pivoting=True)
    else:
        piv = _tie_pivots(J, tie_rtol)
    dep = np.sort(piv[:nc])
    return np.setdiff1d(np.arange(nv), dep), dep


def _tie_pivots(J: np.ndarray, rtol: float) -> np.ndarray:
    """Pivot columns of Householder QR of J, each the lowest-index column whose remaining
    norm is within ``rtol`` of the largest (the compiled core's Core::tie_pivots)."""
    A = np.array(J, dtype=float)
    nc, nv = A.shape
    free = np.ones(nv, dtype=bool)
    piv = np.zeros(nc, dtype=int)
    for k in range(nc):
        norms = np.where(free, np.linalg.norm(A[k:], axis=0), -1.0)
        p = int(np.argmax(norms >= (1.0 - rtol) * norms.max()))
        piv[k] = p
        free[p] = False
        u = A[k:, p].copy()  # the reflector that zeroes A[k+1:, p]
        u[0] += math.copysign(float(np.linalg.norm(u)), u[0])
        un = float(np.linalg.norm(u))
        if un > 0.0:
            u /= un
            A[k:] -= 2.0 * np.outer(u, u @ A[k:])
    return piv
