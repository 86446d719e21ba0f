r"""Augmented-Lagrangian forward dynamics: well posed where J loses rank.

The index-1 augmented Lagrangian formulation (Bayo, Garcia de Jalon, Serna
1988; Bayo and Ledesma 1996) replaces the saddle-point KKT system by a
sequence of symmetric positive definite solves with the penalized mass matrix

.. math::

    P = M + \alpha J^\top J, \qquad
    P\, a_{k+1} = \tau - h - J^\top \lambda_k - \alpha J^\top \gamma, \qquad
    \lambda_{k+1} = \lambda_k + \alpha (J a_{k+1} + \gamma),

from :math:`\lambda_0 = 0`. P stays positive definite whatever the rank of J
(M is), so the iteration is defined at singular configurations and with
redundant rows. While the rows of J are consistent (J a + gamma = 0 has a
solution, as on the constraint manifold) the accelerations converge to the
unique minimizer of Gauss's principle, :math:`(a - M^{-1}(\tau - h))^\top M
(\cdot)` subject to :math:`J a + \gamma = 0`, i.e. the KKT accelerations when J
has full rank; each iteration shrinks the error along a constraint direction
of singular value sigma by :math:`m / (m + \alpha \sigma^2)`, so regular
directions converge in one or two iterations and a direction of a nearly
singular J more slowly but boundedly. The multipliers of redundant rows are
not unique (their generalized force J^T lam is).

The penalty starts relative, :math:`\alpha = \rho\, \mathrm{tr}(M) /
\mathrm{tr}(J^\top J)` with :math:`\rho` = ``SolverSettings.al_penalty``, and is
then chosen from P's Cholesky (:meth:`PenalizedSolver.factor_relative`): lowered
while the factorization fails or shows a relative pivot :math:`L_{ii}^2 / P_{ii}`
below :data:`PIVOT_MIN`, where :math:`\alpha J^\top J` has cancelled M's diagonal
(near-massless links, long chains: M's small eigenvalues, not its trace, bound
what P can take). Cholesky is invariant under diagonal scaling, so these pivots
measure the digits lost whatever the units.

:class:`PenalizedSolver` factorizes P (dense Cholesky, or banded Cholesky in
a bandwidth-reducing order when the structure of M + J^T J is banded, as for
the N-four-bar: cost linear in nv); the ALI3-P integrator
(``closedchain.simulate.ali3p``) uses it too.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.csgraph
from scipy.linalg import lapack

from ..constraints import support_mask
from ..exceptions import SingularConfigurationError
from .base import (
    MethodCapabilities,
    SolverSettings,
    compute_terms,
    register,
    workspace,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)

_NAME = "augmented-lagrangian"

#: Use the banded factorization when the half bandwidth (after reverse
#: Cuthill-McKee) is at most this fraction of nv; dense LAPACK otherwise.
BANDED_FRACTION = 0.25
#: Matrices of at most this size are factored dense, never as a band.
BANDED_MIN_SIZE = 8


#: Relative regularization of the normal equations that polish the multipliers.
NORMAL_EQ_REG = 1e-14

#: Smallest relative pivot R_ii^2 / P_ii of P's Cholesky accepted by
#: :meth:`PenalizedSolver.factor_relative`: a pivot that alpha J^T J has cancelled to
#: this fraction of P_ii keeps about log10(PIVOT_MIN / eps) = 4 digits, which the
#: iteration, in residual form, refines (chains of 30 links at 1e-14 did not converge).
PIVOT_MIN = 1e-13
#: A lowered penalty aims at relative pivots this many times :data:`PIVOT_MIN`.
PENALTY_MARGIN = 10.0
#: The largest lowering of alpha in one step (and the step after a failed Cholesky).
PENALTY_DROP = 1e-4
#: How many times :meth:`PenalizedSolver.factor_relative` may lower alpha before it
#: reports P as not positive definite (M singular).
MAX_PENALTY_LOWERINGS = 8

#: The iteration has diverged (:func:`solve_augmented_lagrangian` raises) when a
#: correction is more than DIVERGENCE_GROWTH times the previous one while above
#: DIVERGENCE_RTOL (1 + max |a|). In exact arithmetic the corrections shrink (by
#: 1 / (1 + alpha sigma^2) along each direction of J): they stall near a singular
#: position (robot_delta: 2.082e-2 then 2.083e-2 rad/s^2, iterate 4) and stop shrinking
#: at the round-off floor of an ill-conditioned P (about cond(P) eps times the previous
#: correction); they grow by more only when the solve with P is wrong by more than its
#: own size, and the iterate then carries that error.
DIVERGENCE_GROWTH = 2.0
#: See :data:`DIVERGENCE_GROWTH` [-].
DIVERGENCE_RTOL = 1e-6
#: What a diverged iteration's message says of the cause and the remedy (the compiled
#: core's too).
DIVERGED_HINT = (
    "the penalized mass matrix M + alpha J^T J is too ill-conditioned for its solve: lower "
    "the penalty (SolverSettings.al_penalty) or use method='kkt'"
)

_TINY = float(np.finfo(float).tiny)


def structure(mech: Mechanism) -> np.ndarray:
    """Return the structural nonzero pattern of M + J^T J, shape (nv, nv), bool.

    M_ij is structurally nonzero when joint i supports joint j or the converse
    (CRBA); a row of a loop depends on the joints supporting its two cut frames.
    """
    model = mech.model
    nv = mech.nv
    pattern = np.zeros((nv, nv), dtype=bool)
    for j in range(1, model.njoints):
        cols = _support_columns(model, j)
        pattern[np.ix_(cols, cols)] = True
    for blk, _ in mech.constraints.per_loop():
        cols = np.union1d(
            _support_columns(model, model.frames[blk.fid_p].parentJoint),
            _support_columns(model, model.frames[blk.fid_s].parentJoint),
        )
        pattern[np.ix_(cols, cols)] = True
    return pattern


def _support_columns(model, joint: int) -> np.ndarray:
    return np.flatnonzero(support_mask(model, joint))


class PenalizedSolver:
    """Factorize and solve with P = M + alpha J^T J (symmetric positive definite).

    Built once per mechanism. Chooses a banded Cholesky (LAPACK ``dpbtrf``,
    O(nv b^2)) in reverse Cuthill-McKee order when the
    structural half bandwidth b is small (:data:`BANDED_FRACTION`), else a dense
    LAPACK Cholesky.

    Attributes:
        banded: whether the banded path is used.
        bandwidth: structural half bandwidth in the chosen order.
        perm: the order, shape (nv,).
    """

    def __init__(self, mech: Mechanism) -> None:
        nv = mech.nv
        pattern = structure(mech)
        perm = scipy.sparse.csgraph.reverse_cuthill_mckee(
            scipy.sparse.csr_matrix(pattern), symmetric_mode=True
        )
        # Keep the natural order when it is at least as narrow (it often is).
        self.perm = np.arange(nv)
        self.bandwidth = _bandwidth(pattern)
        b_rcm = _bandwidth(pattern[np.ix_(perm, perm)])
        if b_rcm < self.bandwidth:
            self.perm, self.bandwidth = np.asarray(perm), b_rcm
        self.banded = nv > BANDED_MIN_SIZE and self.bandwidth <= BANDED_FRACTION * nv
        self.nv = nv
        #: The kept rows this solver is for (see :func:`penalized_solver`).
        self.layer = mech.constraints
        self._fac: np.ndarray | None = None  # the Cholesky factor (band or dense)
        self.alpha = 0.0
        #: How many times :meth:`factor_relative` lowered alpha for this factorization.
        self.lowerings = 0
        #: The normal equations of the kept rows (multiplier polish, projections).
        self.normal = NormalSolver(mech)

    def factor(self, M: np.ndarray, J: np.ndarray, alpha: float, mech, q) -> None:
        """Factorize P = M + alpha J^T J.

        Args:
            M: mass matrix, shape (nv, nv), symmetric (full).
            J: constraint Jacobian, shape (nc, nv).
            alpha: penalty [same units as M / (J^T J)].
            mech: the mechanism, for the error message.
            q: configuration, shape (nq,), for the error message.

        Raises:
            SingularConfigurationError: P is not positive definite (M singular).
        """
        if self._factor(M, J, alpha) <= 0.0:
            raise self._error(mech, q)

    def _factor(self, M: np.ndarray, J: np.ndarray, alpha: float) -> float:
        """Factorize P = M + alpha J^T J; return its smallest relative pivot
        min_i R_ii^2 / P_ii (in (0, 1]), or 0.0 when P is not numerically positive definite
        (then no factorization is kept)."""
        self.lowerings = 0
        self.alpha = alpha
        P = M + alpha * (J.T @ J)
        if self.banded:
            # Cholesky of the band of P in the order perm (LAPACK's band storage).
            ab = upper_band(P[np.ix_(self.perm, self.perm)], self.bandwidth)
            self._fac, info = lapack.dpbtrf(ab, lower=0)
            diag_p, diag_r = ab[-1], self._fac[-1]
        else:
            self._fac, info = lapack.dpotrf(P, lower=0, clean=0)
            diag_p, diag_r = np.diagonal(P), np.diagonal(self._fac)
        if info != 0:
            self._fac = None
            return 0.0
        return float(np.min(diag_r * diag_r / diag_p, initial=1.0))

    def factor_relative(self, M: np.ndarray, J: np.ndarray, rho: float, mech, q) -> float:
        """Factorize P = M + alpha J^T J with the penalty that P can take and return alpha.

        alpha starts at :func:`relative_penalty` (M, J, rho); while P's Cholesky fails or
        shows a relative pivot R_ii^2 / P_ii below :data:`PIVOT_MIN` (the digits
        that alpha J^T J cancels are lost), alpha is lowered (:func:`lowered_penalty`)
        and P factorized again, at most :data:`MAX_PENALTY_LOWERINGS` times;
        :attr:`lowerings` counts them.

        Args: as :meth:`factor`, with ``rho`` the dimensionless relative penalty.

        Raises:
            SingularConfigurationError: P is not positive definite even at the lowest
                alpha (M singular: a massless subtree).
        """
        alpha = relative_penalty(M, J, rho)
        for lowerings in range(MAX_PENALTY_LOWERINGS + 1):
            pivot = self._factor(M, J, alpha)
            if pivot >= PIVOT_MIN:
                break
            if lowerings == MAX_PENALTY_LOWERINGS:
                self._fac = None
                raise self._error(mech, q, lowered=True)
            alpha = lowered_penalty(alpha, pivot)
        self.lowerings = lowerings
        return alpha

    def max_iter(self, base: int) -> int:
        """Return the iteration cap of the current factorization: ``base`` times one plus
        :attr:`lowerings` (a lowered penalty converges more slowly)."""
        return base * (1 + self.lowerings)

    def _error(self, mech, q, *, lowered: bool = False):
        if lowered:
            state = (
                f"is not numerically positive definite even at alpha = {self.alpha:.3g} "
                f"(lowered {MAX_PENALTY_LOWERINGS} times)"
            )
            hint = "M is singular (a massless subtree); use method='kkt' to confirm"
        else:
            state = f"is not numerically positive definite (alpha = {self.alpha:.3g})"
            hint = (
                "M is singular (a massless subtree) or so ill-conditioned that alpha J^T J "
                "swamps it; lower the penalty or use method='kkt'"
            )
        return SingularConfigurationError.build(
            mech.name,
            "the penalized mass matrix M + alpha J^T J",
            q=q,
            cond=float("inf"),
            state=state,
            hint=hint,
        )

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """Return P^-1 rhs for rhs of shape (nv,) or (nv, k)."""
        if self.banded:
            x = lapack.dpbtrs(self._fac, rhs[self.perm], lower=0)[0]
            out = np.empty_like(x)
            out[self.perm] = x
            return out
        return lapack.dpotrs(self._fac, rhs)[0]


def penalized_solver(mech: Mechanism) -> PenalizedSolver:
    """Return the mechanism's :class:`PenalizedSolver` of its kept rows (made on first use
    and after the rows are re-selected), shared by the method and the stage projection."""
    buffers = workspace(mech).method_buffers
    solver = buffers.get(_NAME)
    if solver is None or solver.layer is not mech.constraints:
        solver = buffers[_NAME] = PenalizedSolver(mech)
    return solver


def row_structure(mech: Mechanism, layer=None) -> np.ndarray:
    """Return the structural nonzero pattern of J J^T, shape (nc, nc), bool.

    Rows i and j couple when their loops' cut frames are moved by a common joint.

    Args:
        mech: the mechanism.
        layer: the constraint layer (default: the kept rows, ``mech.constraints``).
    """
    return _couplings(_row_columns(mech, layer))


def _couplings(cols: np.ndarray) -> np.ndarray:
    """Return which rows share a column, shape (nc, nc), bool (cols: shape (nc, nv))."""
    return (cols.astype(np.int64) @ cols.T.astype(np.int64)) > 0


def _row_columns(mech: Mechanism, layer=None) -> np.ndarray:
    """Return where each row of J can be nonzero, shape (nc, nv), bool: the velocity
    columns of the joints supporting either cut frame of its loop (``layer``: default the
    kept rows)."""
    model = mech.model
    layer = mech.constraints if layer is None else layer
    cols = np.zeros((layer.nc, mech.nv), dtype=bool)
    for blk, sl in layer.per_loop():
        support = np.union1d(
            _support_columns(model, model.frames[blk.fid_p].parentJoint),
            _support_columns(model, model.frames[blk.fid_s].parentJoint),
        )
        cols[sl.start : sl.stop, support] = True
    return cols


class NormalSolver:
    """Solve the regularized normal equations (J J^T + eps I) x = b of the kept rows.

    Banded Cholesky (LAPACK ``dpbsv``, O(nc b^2)) in the natural row
    order when the structural half bandwidth b of J J^T is at most
    :data:`BANDED_FRACTION` of nc (many loops in a chain, as the N-four-bar);
    dense LAPACK otherwise. eps = :data:`NORMAL_EQ_REG` tr(J J^T) / nc keeps the
    equations solvable where J loses rank; a right-hand side in the range of J
    is solved to round-off elsewhere (the minimum-norm correction J^T x).

    Attributes:
        banded: whether the banded path is used.
        bandwidth: structural half bandwidth of J J^T.
    """

    def __init__(self, mech: Mechanism, layer=None) -> None:
        cols = _row_columns(mech, layer)
        pattern = _couplings(cols)
        self.nc = len(pattern)
        self.bandwidth = _bandwidth(pattern)
        self.banded = self.nc > BANDED_MIN_SIZE and self.bandwidth <= BANDED_FRACTION * self.nc

    def solve(self, J: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Return x with (J J^T + eps I) x = rhs.

        Args:
            J: constraint Jacobian, shape (nc, nv).
            rhs: shape (nc,).
        """
        nc = self.nc
        if not self.banded:
            JJ = J @ J.T
            JJ[np.diag_indices(nc)] += NORMAL_EQ_REG * max(float(np.trace(JJ)), 1.0) / max(nc, 1)
            c, x, info = lapack.dposv(JJ, rhs, lower=0)
            if info != 0:
                return scipy.linalg.lstsq(JJ, rhs, check_finite=False)[0]
            return x
        ab = self.band(J)
        b = self.bandwidth
        ab[b] += NORMAL_EQ_REG * max(float(np.sum(ab[b])), 1.0) / nc
        _, x, info = lapack.dpbsv(ab, rhs, lower=0)  # LAPACK directly: no wrappers
        if info != 0:
            raise np.linalg.LinAlgError(f"J J^T + eps I is not positive definite (info {info})")
        return x

    def band(self, J: np.ndarray) -> np.ndarray:
        """Return J J^T in LAPACK's upper band storage, shape (b + 1, nc): ab[b - k, j] =
        (J J^T)[j - k, j] (a new array; banded solvers only).

        Args:
            J: constraint Jacobian, shape (nc, nv).
        """
        return upper_band(J @ J.T, self.bandwidth)


def upper_band(A: np.ndarray, b: int) -> np.ndarray:
    """Return the upper band of the symmetric matrix A in LAPACK's band storage.

    Args:
        A: symmetric matrix, shape (n, n), zero beyond the half bandwidth b.
        b: half bandwidth.

    Returns:
        ``ab``, shape (b + 1, n), with ``ab[b - k, j] = A[j - k, j]`` for 0 <= k <= b
        (``dpbtrf``'s ``lower=0`` layout; entries above the matrix are zero).
    """
    ab = np.zeros((b + 1, len(A)))
    for k in range(b + 1):
        ab[b - k, k:] = np.diagonal(A, k)
    return ab


def _bandwidth(pattern: np.ndarray) -> int:
    i, j = np.nonzero(pattern)
    return int(np.max(np.abs(i - j), initial=0))


def relative_penalty(M: np.ndarray, J: np.ndarray, rho: float) -> float:
    """Return alpha = rho tr(M) / tr(J^T J) (rho dimensionless; alpha in M's units per J^T J's)."""
    jj = float(np.einsum("ij,ij->", J, J))
    return rho * float(M.trace()) / max(jj, _TINY)


def lowered_penalty(alpha: float, pivot: float) -> float:
    """Return the next penalty after P = M + alpha J^T J showed ``pivot``, its smallest
    relative pivot (0.0: not positive definite).

    Where alpha J^T J dominates P's diagonal, the small relative pivots (directions
    that J does not constrain) scale as 1 / alpha: alpha is lowered to bring the
    smallest to :data:`PENALTY_MARGIN` times :data:`PIVOT_MIN`, and at least by
    ``1 / PENALTY_MARGIN``, at most by :data:`PENALTY_DROP`.
    """
    return alpha * max(PENALTY_DROP, pivot / (PENALTY_MARGIN * PIVOT_MIN))


def solve_augmented_lagrangian(
    solver: PenalizedSolver,
    M: np.ndarray,
    J: np.ndarray,
    rhs: np.ndarray,
    gamma: np.ndarray,
    alpha: float,
    *,
    tol: float,
    max_iter: int,
    polish: bool = True,
    a0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    r"""Iterate the augmented Lagrangian at the acceleration level (P already factorized).

    Args:
        solver: factorization of M + alpha J^T J.
        M: mass matrix, shape (nv, nv) (for the residuals).
        J: shape (nc, nv).
        rhs: tau - h, shape (nv,).
        gamma: right-hand side of J a + gamma = 0, shape (nc,).
        alpha: the penalty used in ``solver``.
        tol: stop when max |a_k - a_{k-1}| <= tol (1 + max |a_k|) (or when that change
            no longer shrinks: the round-off floor).
        max_iter: iteration cap.
        polish: correct the multipliers by the normal equations (below); off
            when only ``a`` is wanted (the projections of ALI3-P).
        a0: where to start, shape (nv,), or None (from a = 0): the first iterate is
            P^-1 (rhs - alpha J^T gamma) either way, computed from a0 as a correction
            a0 + P^-1 (rhs - M a0 - alpha J^T (J a0 + gamma)), whose round-off (about
            rho eps times its size) is small when a0 is near the solution (the velocity
            projection from the velocity it projects).

    Returns:
        ``(a, lam, iterations)``.

    Raises:
        SingularConfigurationError: the iteration diverged (a correction grew more than
            :data:`DIVERGENCE_GROWTH` times while above :data:`DIVERGENCE_RTOL` (1 +
            max abs(a)): no stall and no round-off floor).
    """
    # Written as corrections, a_{k+1} = a_k + P^-1 (tau - h - M a_k - J^T lam_k
    # - alpha J^T (J a_k + gamma)), the same iteration in exact arithmetic: the
    # right-hand side shrinks with the residuals, so round-off of the badly
    # conditioned P (about rho eps) is not left in a (iterative refinement).
    solve = solver.solve
    if a0 is None:
        a = solve(rhs - alpha * (J.T @ gamma))
    else:  # the same first iterate from (a0, lam 0), by a correction of a0
        a = a0 + solve(rhs - M @ a0 - alpha * (J.T @ (J @ a0 + gamma)))
    r_c = J @ a + gamma  # the constraint residual at a
    lam = alpha * r_c
    step = lam  # alpha r_c: the last update of lam
    it = 1
    last_change = np.inf
    while it < max_iter:
        delta = solve(rhs - M @ a - J.T @ (lam + step))  # lam + alpha r_c
        a += delta
        r_c = J @ a + gamma
        step = alpha * r_c
        lam += step
        it += 1
        change = float(np.abs(delta).max())
        if change > DIVERGENCE_GROWTH * last_change and change > DIVERGENCE_RTOL * (
            1.0 + float(np.abs(a).max())
        ):
            raise SingularConfigurationError(diverged_message(last_change, change, it, alpha))
        # Converged, or the change stopped shrinking: the round-off floor of an
        # ill-conditioned M (as iterative refinement stops), which tol may lie below.
        if change <= tol * (1.0 + float(np.abs(a).max())) or change >= last_change:
            break
        last_change = change
    # The update alpha (J a + gamma) carries the round-off of J a times alpha (1e-4 N
    # on the 4-bar with rho = 1e11): correct lam so that J^T lam matches the dynamics,
    # J^T dlam = tau - h - M a - J^T lam, by regularized normal equations (the
    # right-hand side lies in the range of J^T up to round-off, so the tiny
    # regularization only keeps them solvable where J loses rank).
    if not polish:
        return a, lam, it
    r_d = rhs - M @ a - J.T @ lam
    lam += solver.normal.solve(J, J @ r_d)
    return a, lam, it


def diverged_message(last_change: float, change: float, it: int, alpha: float) -> str:
    """Return the one-line message of a diverged iteration (the compiled core's too).

    Args:
        last_change: the previous correction, max abs [rad/s^2 or m/s^2].
        change: the correction that grew, max abs.
        it: its iterate number.
        alpha: the penalty.
    """
    return (
        f"the augmented-Lagrangian iteration diverged: its correction grew from "
        f"{last_change:.3e} to {change:.3e} at iterate {it} (alpha = {alpha:.3e}); "
        f"{DIVERGED_HINT}"
    )


@register(
    _NAME,
    MethodCapabilities(baumgarte=True, singular_robust=True, redundant_rows=True, compiled=True),
)
def augmented_lagrangian(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics by the augmented-Lagrangian iteration.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``al_penalty``, ``al_tol``, ``al_max_iter``, ``al_polish``; ``baumgarte``.

    Returns:
        ``(a, lam)``: accelerations, shape (nv,), and multipliers, shape (nc,),
        with ``M a + h + J^T lam = tau`` (lam: one choice when rows are redundant).

    Raises:
        SingularConfigurationError: M itself is singular.
    """
    ws = compute_terms(mech, q, v, settings.baumgarte)
    if mech.nc == 0:
        # Non-finite terms (a diverged state) give non-finite a, which the callers
        # report with the state, not scipy's ValueError.
        a = scipy.linalg.solve(ws.M, tau - ws.h, assume_a="pos", check_finite=False)
        return a, np.zeros(0)
    solver = penalized_solver(mech)
    alpha = solver.factor_relative(ws.M, ws.J, settings.al_penalty, mech, q)
    a, lam, it = solve_augmented_lagrangian(
        solver,
        ws.M,
        ws.J,
        tau - ws.h,
        ws.gamma,
        alpha,
        tol=settings.al_tol,
        max_iter=solver.max_iter(settings.al_max_iter),
        polish=settings.al_polish,
    )
    return a, lam
