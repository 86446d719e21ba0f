"""Smallest singular values for the row selection, by the secular equation.

:func:`_sigma_min_with_each_row` gives the smallest singular value of a matrix
with each of many candidate rows appended, from one SVD of the matrix (Golub
1973), for the greedy row choice of :mod:`.selection`.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg


def _sigma_min(A: np.ndarray) -> float:
    if A.shape[0] == 0:
        return np.inf
    return float(scipy.linalg.svdvals(A)[-1]) if A.shape[0] <= A.shape[1] else 0.0


def _sigma_min_with_each_row(B: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Smallest singular value of ``B[s]`` with each row of ``A[s]`` appended.

    Args:
        B: kept rows at each sample, shape (n_samples, k, n).
        A: candidate rows at each sample, shape (n_samples, m, n).

    Returns:
        Shape (n_samples, m): ``_sigma_min(np.vstack([B[s], A[s, i]]))`` to round-off, from
        one SVD of each B[s] instead of one per candidate (the greedy row choice of a
        40-loop mechanism made 150,000 SVDs).

    With B = U diag(s) V^T, [B; a^T][B; a^T]^T is, in the basis of U, the arrowhead matrix
    [[diag(s^2), diag(s) w], [w^T diag(s), a.a]] with w = V^T a; its eigenvalues below
    s_k^2 are the roots of the secular equation f(lambda) = rho^2 - lambda (1 + sum_j
    w_j^2 / (s_j^2 - lambda)) = 0 with rho = |a - V w| (Golub 1973; LAPACK's dlaed4 solves
    the same). f is concave and decreasing on [0, s_k^2) with f(0) = rho^2 >= 0, so
    Newton steps started right of the smallest root approach it monotonically from the
    right; a few bisection steps first keep them away from the pole at s_k^2. When f stays
    positive up to s_k^2, the smallest singular value is B's own s_k.
    """
    n_samples, m, n = A.shape
    k = B.shape[1]
    if k == 0:
        return np.linalg.norm(A, axis=2)
    if k + 1 > n:
        return np.zeros((n_samples, m))
    _, s, vt = np.linalg.svd(B, full_matrices=False)
    s2 = (s * s)[:, None, :]  # (S, 1, k)
    w = A @ vt.transpose(0, 2, 1)  # (S, m, k)
    rho2 = np.sum((A - w @ vt) ** 2, axis=2)  # (S, m)
    w2 = w * w
    pole = s2[:, :, -1]  # (S, 1)
    degenerate = pole <= 0.0
    pole = np.where(degenerate, 1.0, pole)
    s2 = np.where(degenerate[:, :, None], 1.0, s2)

    def f(lam):
        return rho2 - lam * (1.0 + np.sum(w2 / (s2 - lam[..., None]), axis=2))

    # The root is below rho^2 / g(0) (g = 1 + sum w^2 / (s^2 - lambda) grows with
    # lambda) and below s_k^2.
    bound = rho2 / (1.0 + np.sum(w2 / s2, axis=2))
    cap = pole * (1.0 - 4.0 * _EPS)
    hi = np.minimum(bound, cap)
    positive_to_pole = (bound >= cap) & (f(hi) > 0.0)
    lo = np.zeros_like(hi)
    for _ in range(8):
        mid = 0.5 * (lo + hi)
        right = f(mid) <= 0.0
        hi = np.where(right, mid, hi)
        lo = np.where(right, lo, mid)
    for _ in range(_SECULAR_NEWTON_MAX):
        fh = f(hi)
        dfh = -(1.0 + np.sum(w2 * s2 / (s2 - hi[..., None]) ** 2, axis=2))
        new = np.maximum(hi - np.where(fh < 0.0, fh / dfh, 0.0), lo)
        done = np.all(hi - new <= 2.0 * _EPS * hi)
        hi = new
        if done:
            break
    lam = np.where(positive_to_pole, pole, hi)
    return np.where(degenerate, 0.0, np.sqrt(np.maximum(lam, 0.0)))


_EPS = float(np.finfo(float).eps)
#: Newton steps of the secular equation after bisection (quadratic convergence from the
#: right; 60 bisection-free steps suffice even when the start is next to the pole).
_SECULAR_NEWTON_MAX = 60
