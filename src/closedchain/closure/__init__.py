r"""The loop rows of a mechanism and its coordinate partition: one object, built at load.

:class:`LoopClosure` owns the declared rows of every loop, the subset kept as
independent (the rows every dynamics method uses) and the partition of the
velocity coordinates into independent and dependent ones. It is built once by
:func:`closedchain.load`; the simulator asks it for a new partition
(:meth:`LoopClosure.partition_at`) and, when the kept rows stop describing the
loops, for a new row selection (:meth:`LoopClosure.check_rows`).

Row selection (:meth:`LoopClosure.select_rows`) works on the declared
Jacobian at many configurations spread along the motion: random assembled
configurations (every joint drawn at random, so base joints such as a
turntable or a free flyer take random poses) and short walks from each of
them along the null space of J. The generic rank r is the largest numerical
rank met; samples of lower rank are singular configurations and are set
aside. The kept rows are chosen greedily, each time the declared row that
maximizes the worst case, over the regular samples, of the smallest singular
value of the kept rows' Jacobian:

.. math::

    k_{j+1} = \arg\max_{i \notin K_j} \min_s \sigma_{\min}(J_s[K_j \cup \{i\}]),

until r rows are kept (a rank-revealing selection over all samples at once,
not at one pose); when there are few subsets of r rows (at most
:data:`MAX_EXHAUSTIVE_SUBSETS`, e.g. one loop) the max-min is taken over all of them.

It also holds the model-level tools both it and :mod:`kinematics` need: the
Gauss-Newton solve onto phi = 0 (:func:`solve_closure`), the assembly that also
closes loops from far away (:func:`assemble_closure`: least squares on the
closure residual, zero exactly at the closure) and the pivoted-QR partition
(:func:`partition_coordinates`). Module dependencies:
:mod:`constraints` only; :mod:`mechanism` builds the object and
:mod:`kinematics` (the Mechanism-level functions) builds on it: no cycle.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import scipy.linalg
import scipy.optimize

from ..constraints import ConstraintLayer, RowInfo
from ..exceptions import AssemblyError, LoopClosureError, SingularConfigurationError, URDFError
from ..pindata import new_data

logger = logging.getLogger(__name__)

#: Relative margin by which a later candidate row must beat an earlier one in the
#: max-min greedy choice: near ties keep the declared order (deterministic choice).
_TIE_RTOL = 1e-9
#: Up to this many row subsets of the generic rank, the max-min choice is exhaustive.
MAX_EXHAUSTIVE_SUBSETS = 500


@dataclass(frozen=True)
class SelectionSettings:
    """Settings of the load-time row selection (:func:`sample_configurations`,
    :meth:`LoopClosure.select_rows`).

    Attributes:
        n_samples: random assembled configurations (random base poses included).
        max_attempts: random starts tried to get them.
        walk_steps: steps of the walk along the motion from each sample.
        walk_step: length of one walk step in velocity space [rad or m].
        rank_tol: a singular value counts towards the rank when it exceeds
            ``rank_tol`` times max(1, the largest singular value of J).
        margin_min: smallest acceptable worst-case ratio sigma_min(J_kept) /
            sigma_max(J_declared) over the samples; below it the selection is
            logged as weak.
        prismatic_range: sampling range [m] of unbounded prismatic coordinates.
        seed: seed of the sampling.
    """

    n_samples: int = 8
    max_attempts: int = 60
    walk_steps: int = 3
    walk_step: float = 0.3
    rank_tol: float = 1e-8
    margin_min: float = 1e-4
    prismatic_range: float = 1.0
    seed: int = 0


@dataclass(frozen=True)
class RowSelection:
    """How the independent rows were chosen (what ``closedchain info`` reports).

    Attributes:
        kept: labels of the kept rows.
        dropped: labels of the declared rows left out.
        rank: generic rank of the declared Jacobian.
        n_samples: configurations examined.
        n_singular: samples whose declared Jacobian had a lower rank (set aside).
        margin: worst case over the regular samples of sigma_min(J_kept) /
            sigma_max(J_declared) (0 < margin <= 1; larger is better).
        reason: ``"load"`` or the re-selection's cause.
    """

    kept: tuple[str, ...]
    dropped: tuple[str, ...]
    rank: int
    n_samples: int
    n_singular: int
    margin: float
    reason: str = "load"

    def as_dict(self) -> dict:
        return {
            "kept": list(self.kept),
            "dropped": list(self.dropped),
            "rank": self.rank,
            "n_samples": self.n_samples,
            "n_singular": self.n_singular,
            "margin": self.margin,
            "reason": self.reason,
        }


@dataclass(frozen=True)
class RowCheckSettings:
    """Tolerances of :meth:`LoopClosure.check_rows`.

    Attributes:
        dropped_tol: a dropped row open by more than this [m or -] ...
        dropped_ratio: ... and by more than ``dropped_ratio`` times the largest
            kept-row residual means the kept rows no longer describe the loop.
        cond_max: a kept Jacobian whose condition number exceeds this while
            the declared rows still have their generic rank, with a condition
            number (of their r largest singular values) below it, means the
            kept rows degenerate where the mechanism does not.
        open_tol: when no re-selection can take in an open dropped row, a
            residual above this [m or -] is an error (below it, the residual
            is only reported: every output's residual covers all declared rows).
    """

    dropped_tol: float = 1e-9
    dropped_ratio: float = 100.0
    cond_max: float = 1e3
    open_tol: float = 1e-6


#: The defaults, shared (frozen).
DEFAULT_ROW_CHECK_SETTINGS = RowCheckSettings()


@dataclass(frozen=True)
class AssemblySettings:
    """Settings of :func:`assemble_closure` (and of the Newton solve :func:`solve_closure`).

    Attributes:
        tol: convergence threshold on max |phi| [m or -].
        max_iter: iterations of each solve: Gauss-Newton steps, and residual
            evaluations of the least-squares solve (its trust-region steps).
        max_halvings: line-search step halvings per iteration.
        fallback_rcond: relative singular-value cut-off of the second step
            tried when the full Gauss-Newton step does not contract the residual.
        contraction: the full step is taken alone when it multiplies the sum of
            squares of phi by at most this (the usual, quadratic, case).
        closure_tol: a configuration is closed when, besides max |phi| <= tol,
            its closure residual (zero exactly at the closure:
            :func:`closedchain.constraints.closure_residual`) is at most this
            [m or rad].
        lsq_tol: ``ftol``, ``xtol`` and ``gtol`` of ``scipy.optimize.least_squares``
            (its minimum is then polished by Gauss-Newton on phi).
        mismatch_tol: a least-squares minimum of the closure residual at most this
            large [m or rad] is accepted as closed: redundant rows that disagree by a
            rounding (a CAD export). 0 (the default): none; :func:`closedchain.load`
            sets ``LoadSettings.mismatch_tol`` and warns naming the loop.
    """

    tol: float = 1e-12
    max_iter: int = 60
    max_halvings: int = 12
    fallback_rcond: float = 1e-2
    contraction: float = 0.25
    closure_tol: float = 1e-9
    lsq_tol: float = 1e-15
    mismatch_tol: float = 0.0


#: The defaults, shared (frozen).
DEFAULT_ASSEMBLY_SETTINGS = AssemblySettings()


def layer_phi(model, data, layer: ConstraintLayer, q: np.ndarray) -> np.ndarray:
    """Return phi(q) of every row of ``layer``, shape (layer.nc,) [m or -]."""
    pin.forwardKinematics(model, data, q)
    out = np.zeros(layer.nc)
    layer.evaluate(model, data, phi=out)
    return out


def max_declared_residual(mech, qs: np.ndarray) -> float:
    """Return max |phi| over every declared row and every configuration of ``qs``.

    Args:
        mech: the mechanism (its declared rows, dropped ones included).
        qs: configurations, shape (n, nq).
    """
    data = new_data(mech.model)  # callers may run beside a simulation using mech.data
    return max(
        (
            float(np.max(np.abs(layer_phi(mech.model, data, mech.declared, q)), initial=0.0))
            for q in qs
        ),
        default=0.0,
    )


def layer_jacobian(model, data, layer: ConstraintLayer, q: np.ndarray) -> np.ndarray:
    """Return J(q) of every row of ``layer``, shape (layer.nc, nv)."""
    pin.computeJointJacobians(model, data, q)
    out = np.zeros((layer.nc, model.nv))
    layer.evaluate(model, data, J=out)
    return out


def solve_closure(
    model: pin.Model,
    data: pin.Data,
    layer: ConstraintLayer,
    q_guess: np.ndarray,
    free: np.ndarray,
    settings: AssemblySettings,
) -> np.ndarray:
    """Gauss-Newton onto phi(q) = 0 moving only the ``free`` velocity coordinates.

    Args:
        model: Pinocchio model with the loop frames.
        data: its data (overwritten).
        layer: rows to zero (redundant rows allowed).
        q_guess: start configuration, shape (nq,).
        free: velocity indices allowed to move.
        settings: tolerances.

    Returns:
        The assembled configuration, shape (nq,).

    Raises:
        AssemblyError: max |phi| stays above ``settings.tol``; carries the
            residual reached and the configuration.
    """
    q = np.array(q_guess, dtype=float)
    if layer.nc == 0:
        return q
    q = _newton(model, data, layer, q, free, settings)
    pin.forwardKinematics(model, data, q)
    flipped = layer.misaligned_loops(model, data)
    if flipped:
        raise AssemblyError(
            f"assembly reached phi = 0 on a spurious closure of loop(s) {', '.join(flipped)}: "
            "the cut-joint frames are turned by 180 degrees against each other; start "
            "from a guess closer to the intended assembly",
            residual=float("inf"),
            q=q,
        )
    return q


def assemble_closure(
    model: pin.Model,
    data: pin.Data,
    layer: ConstraintLayer,
    q_guess: np.ndarray,
    free: np.ndarray,
    settings: AssemblySettings,
    *,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    polish: ConstraintLayer | None = None,
) -> np.ndarray:
    r"""Close every loop from a guess, also far from the closure.

    First Gauss-Newton on the rows phi (:func:`solve_closure`: fast, and the
    branch nearest the guess). When it fails (the rotation rows ``(R_p u).(R_s w)``
    also vanish away from the closure, and Gauss-Newton from far away stalls on
    them), a trust-region least-squares solve (``scipy.optimize.least_squares``,
    ``trf`` with the exact Jacobian; rank-deficient directions handled by its
    SVD) minimizes the closure residual e, zero exactly at the closure
    (:meth:`ConstraintLayer.closure_residuals`), over the free coordinates in the
    chart :math:`q(x) = q_0 \oplus x` at the start (``pin.integrate``: nq != nv
    is fine), within ``bounds``; its minimum is then polished by Gauss-Newton on
    phi to ``settings.tol``.

    Args:
        model: Pinocchio model with the loop frames.
        data: its data (overwritten).
        layer: every declared row of the loops to close.
        q_guess: start configuration, shape (nq,).
        free: velocity indices allowed to move.
        settings: tolerances.
        bounds: ``(lower, upper)`` configuration limits, shape (nq,) each, kept on
            the 1-dof coordinates where finite (the start is clipped into them),
            or None.
        polish: with ``settings.mismatch_tol``, the consistent rows (the kept ones)
            that Gauss-Newton closes from a least-squares minimum below it, or None.

    Returns:
        A closed configuration, shape (nq,): max |phi| <= ``settings.tol`` and max
        |e| <= ``settings.closure_tol``; or, with ``settings.mismatch_tol``, where the
        least-squares minimum of e is below that, the minimum (``polish``'s rows closed
        from it to ``settings.tol`` when given).

    Raises:
        AssemblyError: no closure found; carries the smallest max |e| reached and
            its configuration.
    """
    q_guess = np.array(q_guess, dtype=float)
    if layer.nc == 0:
        return q_guess
    lower, upper = _free_bounds(model, free, bounds)
    q0 = q_guess.copy()
    if bounds is not None:
        q0 = _clip_into(model, q0, free, lower, upper)
    try:
        q = solve_closure(model, data, layer, q0, free, settings)
        if closure_error(model, data, layer, q) <= settings.closure_tol and _inside(
            model, q, free, lower, upper
        ):
            return q
    except AssemblyError:
        pass
    q_ls = _least_squares(model, data, layer, q0, free, settings, lower, upper)
    res = closure_error(model, data, layer, q_ls)
    try:
        q = solve_closure(model, data, layer, q_ls, free, settings)
        if closure_error(model, data, layer, q) <= settings.closure_tol:
            return q
    except AssemblyError:
        pass
    if res <= settings.mismatch_tol:
        # Redundant rows that disagree: the consistent rows (the kept ones) close exactly.
        try:
            q = solve_closure(model, data, polish, q_ls, free, settings) if polish else q_ls
            if closure_error(model, data, layer, q) <= settings.mismatch_tol:
                return q
        except AssemblyError:
            pass
        return q_ls
    raise AssemblyError(
        f"assembly did not converge: max |phi| = {res:.3e} > tol {settings.tol:.1e}",
        residual=res,
        q=q_ls,
    )


def closure_error(model, data, layer: ConstraintLayer, q: np.ndarray) -> float:
    """Return max |e| of the closure residual of every loop of ``layer`` at q [m or rad]."""
    pin.forwardKinematics(model, data, q)
    e, _ = layer.closure_residuals(model, data)
    return float(np.max(np.abs(e), initial=0.0))


def _least_squares(model, data, layer, q0, free, settings, lower, upper, task=None) -> np.ndarray:
    """The least-squares minimum of the closure residual from q0 (chart q0 + x).

    ``task(model, data, jacobian)``, when given, returns more residual rows and, with
    ``jacobian``, their derivative along v (data current at q, as for the closure rows),
    appended to the closure's: :func:`closedchain.parallel.inverse_kinematics`.
    """
    if len(free) == 0:
        return q0
    held_q = _held_q(model, free)
    q_held = q0[held_q].copy()
    dv = np.zeros(model.nv)

    def config(x):
        dv[free] = x
        q = pin.integrate(model, q0, dv)
        q[held_q] = q_held
        return q

    def fun(x):
        pin.forwardKinematics(model, data, config(x))
        e = layer.closure_residuals(model, data)[0]
        return e if task is None else np.concatenate([e, task(model, data, False)[0]])

    def jac(x):
        pin.computeJointJacobians(model, data, config(x))
        _, E = layer.closure_residuals(model, data, jacobian=True)
        if task is not None:
            E = np.vstack([E, task(model, data, True)[1]])
        return E @ pin.dIntegrate(model, q0, dv, pin.ArgumentPosition.ARG1)[:, free]

    k = _q_of_v(model, free)
    sol = scipy.optimize.least_squares(
        fun,
        np.zeros(len(free)),
        jac=jac,
        bounds=(lower - q0[k], upper - q0[k]),
        method="trf",
        ftol=settings.lsq_tol,
        xtol=settings.lsq_tol,
        gtol=settings.lsq_tol,
        max_nfev=settings.max_iter,
    )
    return config(sol.x)


def _free_bounds(model: pin.Model, free: np.ndarray, bounds) -> tuple[np.ndarray, np.ndarray]:
    """Return, per free coordinate, its (lower, upper) configuration limit [rad or m]:
    finite on 1-dof joints whose limits in ``bounds`` are finite and non-empty, else
    (-inf, inf)."""
    lower = np.full(len(free), -np.inf)
    upper = np.full(len(free), np.inf)
    if bounds is None:
        return lower, upper
    lo, hi = bounds
    for n, i in enumerate(free):
        jm = model.joints[_joint_of_v(model, int(i))]
        k = jm.idx_q
        if jm.nq == jm.nv == 1 and max(abs(lo[k]), abs(hi[k])) < _UNBOUNDED and hi[k] > lo[k]:
            lower[n], upper[n] = lo[k], hi[k]
    return lower, upper


def _q_of_v(model: pin.Model, free: np.ndarray) -> np.ndarray:
    """Configuration index of each free velocity coordinate's joint (its first entry)."""
    return np.array([model.joints[_joint_of_v(model, int(i))].idx_q for i in free], dtype=int)


def _joint_of_v(model: pin.Model, i: int) -> int:
    """Return the joint id owning velocity coordinate i."""
    for j in range(1, model.njoints):
        jm = model.joints[j]
        if jm.idx_v <= i < jm.idx_v + jm.nv:
            return j
    raise IndexError(f"velocity index {i} out of range 0..{model.nv - 1}")


def _clip_into(model, q, free, lower, upper) -> np.ndarray:
    """Return q with its bounded free coordinates clipped into [lower, upper]."""
    q = q.copy()
    k = _q_of_v(model, free)
    q[k] = np.clip(q[k], lower, upper)
    return q


def _inside(model, q, free, lower, upper) -> bool:
    """Whether the free coordinates of q are within [lower, upper]."""
    k = _q_of_v(model, free)
    return bool(np.all((q[k] >= lower) & (q[k] <= upper)))


def _held_q(model: pin.Model, free: np.ndarray) -> np.ndarray:
    """Configuration entries of the joints none of whose velocity coordinates is free."""
    moving = np.zeros(model.nv, dtype=bool)
    moving[free] = True
    return np.concatenate(
        [
            np.arange(model.joints[j].idx_q, model.joints[j].idx_q + model.joints[j].nq)
            for j in range(1, model.njoints)
            if not moving[model.joints[j].idx_v : model.joints[j].idx_v + model.joints[j].nv].any()
        ]
        or [np.zeros(0, dtype=int)]
    )


#: Limits at least this large [rad or m] count as none (Pinocchio's default is the
#: largest double).
_UNBOUNDED = 1e300


def _newton(model, data, layer, q, free, settings) -> np.ndarray:
    phi = layer_phi(model, data, layer, q)
    res = float(np.max(np.abs(phi)))
    dv = np.zeros(model.nv)
    # Configuration entries of joints held entirely: pin.integrate with zero
    # velocity may renormalize them (continuous joints' cos, sin); keep them exact.
    held_q = _held_q(model, free)
    q_held = q[held_q].copy()
    for _ in range(settings.max_iter):
        if res <= settings.tol:
            return q
        J = layer_jacobian(model, data, layer, q)
        # Accept on the sum of squares, the merit function the Gauss-Newton step
        # descends (the max norm need not decrease along it).
        sq = float(phi @ phi)
        best = None
        for rcond in (None, settings.fallback_rcond):
            # Two candidate steps: the full minimum-norm Gauss-Newton step, and, unless
            # the full step contracts the residual at once (sum of squares times
            # <= contraction), the step without J's directions below fallback_rcond of
            # its largest singular value; the one whose line search ends lower is
            # taken. Off the motion of an overconstrained loop (Bricard: 5 rows, rank
            # 4 on the manifold) J's smallest singular value is of the order of the
            # distance to it, and the full step along it overshoots into another
            # basin (a quarter of the starts 0.05 rad away failed).
            step = np.linalg.lstsq(J[:, free], -phi, rcond=rcond)[0]
            dv[:] = 0.0
            dv[free] = step
            alpha = 1.0
            for _ in range(settings.max_halvings):
                q_try = pin.integrate(model, q, alpha * dv)
                q_try[held_q] = q_held
                phi_try = layer_phi(model, data, layer, q_try)
                res_try = float(np.max(np.abs(phi_try)))
                sq_try = float(phi_try @ phi_try)
                if sq_try < sq or res_try <= settings.tol:
                    if best is None or sq_try < best[0]:
                        best = (sq_try, q_try, phi_try, res_try)
                    break
                alpha *= 0.5
            if best is not None and (
                best[3] <= settings.tol or best[0] <= settings.contraction * sq
            ):
                break
        if best is None:
            break
        _, q_try, phi_try, res_try = best
        q, phi, res = q_try, phi_try, res_try
    if res <= settings.tol:
        return q
    raise AssemblyError(
        f"assembly did not converge: max |phi| = {res:.3e} > tol {settings.tol:.1e}",
        residual=res,
        q=q,
    )


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


def _null_space(J: np.ndarray, tol: float) -> np.ndarray:
    """Orthonormal basis of the null space of J, shape (nv, nv - rank)."""
    _, s, Vt = np.linalg.svd(J)
    rank = int(np.sum(s > tol))
    return Vt[rank:].T


def sample_configurations(
    model: pin.Model,
    data: pin.Data,
    declared: ConstraintLayer,
    draw: Callable[[np.random.Generator], np.ndarray],
    settings: SelectionSettings,
    *,
    first: Sequence[np.ndarray] = (),
    assembly: AssemblySettings = DEFAULT_ASSEMBLY_SETTINGS,
) -> tuple[list[np.ndarray], AssemblyError | None]:
    """Return assembled configurations spread along the motion.

    Roots: the starts ``first``, closed by :func:`assemble_closure` (from far
    away too), then random starts ``draw(rng)``, closed by Gauss-Newton only
    (:func:`solve_closure`: cheap, and a uniformly random start almost never
    closes a many-dof leg anyway), until ``n_samples`` roots or ``max_attempts``
    starts (the starts ``first`` always tried). From each root, ``walk_steps``
    steps of length ``walk_step`` along a random direction of the null space of
    J, each closed again (a short stretch of the motion). When fewer roots were
    found, the walk goes on from random samples until ``n_samples * (1 +
    walk_steps)`` samples (or as many failed walks): one closed configuration
    is enough.

    Args:
        model: the model with the loop frames.
        data: its data (overwritten).
        declared: every declared row.
        draw: random start, ``draw(rng)`` -> q, shape (nq,).
        settings: sampling settings.
        first: starts tried first, shape (nq,) each.
        assembly: assembly settings (``mismatch_tol`` for a rounded model).

    Returns:
        The configurations (shape (nq,) each) and the best failed assembly
        (None when every start assembled), for error messages.
    """
    rng = np.random.default_rng(settings.seed)
    free = np.arange(model.nv)
    samples: list[np.ndarray] = []
    best: AssemblyError | None = None
    starts = list(first)
    roots = 0

    def walk(q: np.ndarray) -> bool:
        """Append up to walk_steps closed steps from q; False when a step failed."""
        for _ in range(settings.walk_steps):
            J = layer_jacobian(model, data, declared, q)
            N = _null_space(J, settings.rank_tol * max(1.0, float(np.linalg.norm(J, 2))))
            if N.shape[1] == 0:
                return False
            step = N @ rng.standard_normal(N.shape[1])
            step *= settings.walk_step / max(float(np.linalg.norm(step)), np.finfo(float).tiny)
            try:
                q = assemble_closure(
                    model, data, declared, pin.integrate(model, q, step), free, assembly
                )
            except AssemblyError:
                return False
            samples.append(q)
        return True

    for attempt in range(len(starts) + settings.max_attempts):
        if roots >= settings.n_samples or (attempt >= settings.max_attempts and samples):
            break
        try:
            if attempt < len(starts):
                q = assemble_closure(model, data, declared, starts[attempt], free, assembly)
            else:
                q = solve_closure(model, data, declared, draw(rng), free, assembly)
        except AssemblyError as exc:
            if best is None or exc.residual < best.residual:
                best = exc
            continue
        roots += 1
        samples.append(q)
        walk(q)
    target = settings.n_samples * (1 + settings.walk_steps)
    failures = 0
    while samples and len(samples) < target and failures < target:
        failures += not walk(samples[int(rng.integers(len(samples)))])
    return samples, best


class LoopClosure:
    """A mechanism's loop rows, their independent subset and its coordinate partition.

    Attributes:
        declared: every declared row.
        active: the kept (independent) rows, the ones every method uses.
        selection: how ``active`` was chosen (:class:`RowSelection`).
        history: every selection made, the load-time one first.
        independent_idx_v: velocity indices of the independent coordinates, shape (mobility,).
        dependent_idx_v: the others, shape (nc,).
        independent_source: ``"urdf"``, ``"actuated"`` or ``"automatic"``.
    """

    def __init__(self, declared: ConstraintLayer, nv: int, *, name: str = "") -> None:
        self.declared = declared
        self.active = declared
        self.nv = nv
        self.name = name
        self.rank = declared.nc
        self.selection = RowSelection(
            tuple(r.label for r in declared.rows), (), declared.nc, 0, 0, 1.0
        )
        self.history: list[RowSelection] = []
        self.independent_idx_v = np.arange(nv)
        self.dependent_idx_v = np.arange(0)
        self.independent_source = "automatic"
        self._Js: list[np.ndarray] = []  # declared J at the regular samples
        self._tol = 0.0
        self._n_singular = 0
        #: Closure residual [m or rad] accepted where the declared rows disagree (a
        #: rounded model loaded with a warning: ``LoadSettings.mismatch_tol``); 0 when
        #: every loop closes exactly.
        self.mismatch_tol = 0.0

    # -- row selection ---------------------------------------------------------------
    @property
    def selected_rows(self) -> tuple[int, ...]:
        """Indices of the kept rows in ``declared.declared_rows``."""
        return self.active.selected

    @property
    def rows(self) -> tuple[RowInfo, ...]:
        return self.active.rows

    def select_rows(
        self,
        model: pin.Model,
        data: pin.Data,
        samples: Sequence[np.ndarray],
        *,
        rank_tol: float,
        margin_min: float = SelectionSettings.margin_min,
    ) -> RowSelection:
        """Choose the independent rows from the declared Jacobian at ``samples``.

        Args:
            model: the mechanism's Pinocchio model (with loop frames).
            data: its data.
            samples: assembled configurations, shape (nq,) each.
            rank_tol: relative rank threshold (see :class:`SelectionSettings`).
            margin_min: below this worst-case margin the choice is logged as weak.

        Returns:
            The selection (also stored in :attr:`selection`).
        """
        Js = [layer_jacobian(model, data, self.declared, q) for q in samples]
        self._tol = rank_tol * max([1.0] + [float(np.linalg.norm(J, 2)) for J in Js])
        return self._select(Js, reason="load", margin_min=margin_min)

    def _select(
        self, Js: list[np.ndarray], *, reason: str, margin_min: float, prefer=()
    ) -> RowSelection:
        tol = self._tol
        ranks = [int(np.sum(np.linalg.svd(J, compute_uv=False) > tol)) for J in Js]
        rank = max(ranks, default=0)
        regular = [J for J, r in zip(Js, ranks, strict=True) if r == rank]
        n_singular = len(Js) - len(regular)
        self._Js = regular
        self._n_singular = n_singular
        keep = self._greedy(regular, rank, prefer)
        scale = [max(float(np.linalg.norm(J, 2)), np.finfo(float).tiny) for J in regular]
        margin = (
            min((_sigma_min(J[keep]) / s for J, s in zip(regular, scale, strict=True)), default=1.0)
            if keep
            else 1.0
        )
        self.rank = rank
        self.active = self.declared.restricted(keep)
        labels = [r.label for r in self.declared.declared_rows]
        self.selection = RowSelection(
            kept=tuple(labels[i] for i in keep),
            dropped=tuple(lb for i, lb in enumerate(labels) if i not in keep),
            rank=rank,
            n_samples=len(Js),
            n_singular=n_singular,
            margin=float(margin),
            reason=reason,
        )
        self.history.append(self.selection)
        log = logger.warning if margin < margin_min else logger.info
        log(
            "%s: kept rows %s of %d declared "
            "(rank %d over %d samples, %d singular; margin %.3g; %s)",
            self.name,
            ", ".join(self.selection.kept),
            self.declared.nc,
            rank,
            len(Js),
            n_singular,
            margin,
            reason,
        )
        return self.selection

    def _greedy(self, Js: list[np.ndarray], rank: int, prefer) -> list[int]:
        """Max-min choice of ``rank`` rows over all ``Js`` (module docstring).

        Exhaustive over every row subset of size ``rank`` when there are at most
        :data:`MAX_EXHAUSTIVE_SUBSETS` of them (a planar or single spatial loop),
        greedy otherwise.
        """
        n = self.declared.nc
        if not prefer and 0 < rank and math.comb(n, rank) <= MAX_EXHAUSTIVE_SUBSETS:
            best_set, best_val = [], -1.0
            for subset in itertools.combinations(range(n), rank):
                val = min(_sigma_min(J[list(subset)]) for J in Js)
                if val > best_val * (1.0 + _TIE_RTOL):
                    best_set, best_val = list(subset), val
            return best_set
        keep: list[int] = []
        # Rows of the previous selection that still have full rank together come first,
        # so a re-selection changes as few rows as it can.
        for i in prefer:
            if len(keep) < rank and all(_sigma_min(J[keep + [i]]) > self._tol for J in Js):
                keep.append(i)
        while len(keep) < rank:
            cand = [i for i in range(self.declared.nc) if i not in keep]
            stack = np.stack(Js)
            vals = np.min(_sigma_min_with_each_row(stack[:, keep], stack[:, cand]), axis=0)
            best, best_val = -1, -1.0
            for i, val in zip(cand, vals, strict=True):
                if val > best_val * (1.0 + _TIE_RTOL):
                    best, best_val = i, float(val)
            keep.append(best)
        return sorted(keep)

    # -- run-time checks -------------------------------------------------------------
    def dropped_row_tol(self, tol: float) -> float:
        """Return the residual [m or -] above which a dropped row counts as open: ``tol``,
        or the disagreement accepted at load (:attr:`mismatch_tol`) when larger (the
        dropped rows of a rounded model stay open by it)."""
        return max(tol, self.mismatch_tol)

    def declared_residuals(self, model: pin.Model, data: pin.Data, q: np.ndarray) -> np.ndarray:
        """Return phi(q) of every declared row, shape (n_declared,) [m or -]."""
        return layer_phi(model, data, self.declared, q)

    def worst_row(self, phi_declared: np.ndarray) -> tuple[str, float]:
        """Return the label and |phi| of the most open declared row."""
        i = int(np.argmax(np.abs(phi_declared)))
        return self.declared.declared_rows[i].label, float(abs(phi_declared[i]))

    def check_rows(
        self,
        model: pin.Model,
        data: pin.Data,
        q: np.ndarray,
        *,
        t: float | None = None,
        kept_cond: float | None = None,
        settings: RowCheckSettings = DEFAULT_ROW_CHECK_SETTINGS,
        phi: np.ndarray | None = None,
    ) -> bool:
        """Check that the kept rows still describe every loop at q; re-select if not.

        The kept rows stop describing the loops when a dropped row is open while
        the kept ones are not (``settings.dropped_tol``, ``dropped_ratio``), or
        when the kept rows' Jacobian degenerates (``kept_cond``, computed by the
        caller, above ``settings.cond_max``) while the declared rows keep their
        generic rank. Then the rows are re-selected with q added to the samples
        (logged, recorded in :attr:`history`).

        Args:
            model: the mechanism's Pinocchio model.
            data: its data (overwritten).
            q: configuration, shape (nq,).
            t: simulation time [s] for messages, if any.
            kept_cond: condition number of the kept rows' J at q, if known.
            settings: tolerances (default :class:`RowCheckSettings`).
            phi: phi(q) of every declared row, shape (n_declared,), if known (the
                compiled core's, ``closedchain.compiled.declared_rows``); else computed.

        Returns:
            True when the rows were re-selected.

        Raises:
            SingularConfigurationError: the declared rows themselves lost rank
                (a singular configuration of the mechanism).
            LoopClosureError: a declared row is open by more than
                ``settings.open_tol`` and no selection of rows of the generic rank
                takes it in (names loop, row, time and residual).
        """
        if self.declared.nc == self.active.nc:
            return False
        when = f" at t = {t:.9g} s" if t is not None else ""
        if phi is None:
            phi = self.declared_residuals(model, data, q)
        sel = np.zeros(self.declared.nc, dtype=bool)
        sel[list(self.selected_rows)] = True
        kept_res = float(np.max(np.abs(phi[sel]), initial=0.0))
        dropped = np.where(sel, 0.0, np.abs(phi))
        drop_res = float(np.max(dropped))
        open_row = drop_res > max(settings.dropped_tol, settings.dropped_ratio * kept_res)
        degenerate = kept_cond is not None and kept_cond > settings.cond_max
        if not (open_row or degenerate):
            return False
        J = layer_jacobian(model, data, self.declared, q)
        s_all = np.linalg.svd(J, compute_uv=False)
        r = self.rank
        cond_all = s_all[0] / s_all[r - 1] if s_all[r - 1] > self._tol else np.inf
        if cond_all > settings.cond_max:
            raise SingularConfigurationError.build(
                self.name,
                f"the constraint Jacobian of the declared loop rows (its {r} largest "
                "singular values)",
                q=q,
                cond=float(cond_all),
                bound=settings.cond_max,
                bound_name="singular_cond",
                state="is close to losing rank",
                hint="a singular configuration of the mechanism",
                t=t,
            )
        worst = self.declared.declared_rows[int(np.argmax(dropped))].label
        reason = (
            f"dropped row {worst} open by {drop_res:.3e} (kept rows {kept_res:.3e}){when}"
            if open_row
            else f"kept rows degenerate (condition number {kept_cond:.3e}){when}"
        )
        # The previous rows describe the loops no more: choose afresh (max-min over the
        # load-time samples and this configuration).
        previous = self.selected_rows
        if tuple(self._greedy(self._Js + [J], r, ())) != previous:
            self._select(self._Js + [J], reason=reason, margin_min=0.0)
            return True
        if open_row and drop_res > settings.open_tol:
            label, res = self.worst_row(phi)
            raise LoopClosureError(
                f"{self.name}{when}: loop row {label} is open by {res:.3e} while the kept rows "
                f"({', '.join(self.selection.kept)}) are closed to {kept_res:.3e}, and no other "
                "choice of independent rows describes the loop here"
            )
        return False

    # -- coordinate partition --------------------------------------------------------
    def choose_partition(
        self,
        *,
        independent: np.ndarray | None,
        actuated: np.ndarray,
        J_ref: np.ndarray,
        cond_max: float,
        where: str = "",
        marked_names: Sequence[str] = (),
    ) -> None:
        """Choose the independent coordinates at load.

        The URDF's ``independent="true"`` joints when given, else the actuated
        joints when they fit (count = mobility, J_D regular at every regular
        sample), else column-pivoted QR of ``J_ref``.

        Args:
            independent: velocity indices marked ``independent="true"`` in the
                URDF, or None.
            actuated: velocity indices of the actuated joints.
            J_ref: kept-row Jacobian at the reference configuration, shape (nc, nv).
            cond_max: largest acceptable cond(J_D) at the regular samples.
            where: the file, for error messages.
            marked_names: the joints marked independent, for error messages.

        Raises:
            URDFError: the marked coordinates do not match the mobility or
                leave a singular J_D.
        """
        all_idx = np.arange(self.nv)
        kept = list(self.selected_rows)
        samples = [J[kept] for J in self._Js]
        mobility = self.nv - self.active.nc

        def cond_ok(dep: np.ndarray) -> bool:
            return len(dep) == self.active.nc and all(
                np.linalg.cond(J[:, dep]) < cond_max for J in samples
            )

        if independent is not None:
            dep = np.setdiff1d(all_idx, independent)
            if len(independent) != mobility:
                raise URDFError(
                    f"{where}: {len(independent)} coordinates are marked independent="
                    f'"true" ({", ".join(marked_names)}) but the mobility is {mobility}'
                )
            if not cond_ok(dep):
                raise URDFError(
                    f'{where}: the joints marked independent="true" '
                    f"({', '.join(marked_names)}) leave a singular J_D "
                    f"(condition number >= {cond_max:.0e} at a sampled configuration)"
                )
            ind, source = independent, "urdf"
        else:
            ind, source = actuated, "actuated"
            dep = np.setdiff1d(all_idx, ind)
            if len(ind) != mobility or not cond_ok(dep):
                ind, dep = partition_coordinates(J_ref)
                source = "automatic"
        self.independent_idx_v = np.asarray(ind, dtype=int)
        self.dependent_idx_v = np.asarray(dep, dtype=int)
        self.independent_source = source

    @staticmethod
    def partition_at(J: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Return the best-conditioned partition for the kept-row Jacobian J.

        Column-pivoted QR (Wehage & Haug), see :func:`kinematics.partition_coordinates`,
        with ties (:data:`PIVOT_TIE_RTOL`) to the lowest index.

        Returns:
            ``(independent_idx_v, dependent_idx_v, cond(J_D))``.
        """
        ind, dep = partition_coordinates(J, PIVOT_TIE_RTOL)
        return ind, dep, float(np.linalg.cond(J[:, dep])) if len(dep) else 1.0


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


__all__ = [
    "LoopClosure",
    "RowCheckSettings",
    "RowSelection",
    "SelectionSettings",
    "layer_jacobian",
    "layer_phi",
    "partition_coordinates",
    "solve_closure",
    "AssemblySettings",
    "assemble_closure",
    "closure_error",
    "sample_configurations",
]
