"""Closing the loops: Newton onto phi = 0, globalized assembly, sampling the motion.

:func:`solve_closure` is Gauss-Newton on the rows phi (minimum-norm steps, line
search); :func:`assemble_closure` globalizes it with a trust-region
least-squares solve of the closure residual when Gauss-Newton from far away
stalls; :func:`sample_configurations` closes random starts and walks from them
along the null space of J (the samples of the row selection,
:mod:`.selection`). Module dependencies: :mod:`closedchain.constraints` only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pinocchio as pin
import scipy.optimize

from ..constraints import ConstraintLayer
from ..exceptions import AssemblyError
from ..pindata import new_data


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


class RowFunctions(NamedTuple):
    """Evaluators of a layer's rows that Gauss-Newton may use in place of
    :func:`layer_phi` and :func:`layer_jacobian` (the compiled core's, for
    :func:`closedchain.assemble`): the same rows, equal to round-off.

    Attributes:
        phi: ``phi(q)``, shape (nc,) [m or -].
        jacobian: ``jacobian(q)``, shape (nc, nv).
    """

    phi: Callable[[np.ndarray], np.ndarray]
    jacobian: Callable[[np.ndarray], np.ndarray]


def layer_rows(model, data, layer: ConstraintLayer) -> RowFunctions:
    """The numpy :class:`RowFunctions` of ``layer`` (on ``data``, overwritten)."""
    return RowFunctions(
        lambda q: layer_phi(model, data, layer, q), lambda q: layer_jacobian(model, data, layer, q)
    )


def solve_closure(
    model: pin.Model,
    data: pin.Data,
    layer: ConstraintLayer,
    q_guess: np.ndarray,
    free: np.ndarray,
    settings: AssemblySettings,
    *,
    rows: RowFunctions | None = None,
) -> np.ndarray:
    """Gauss-Newton onto phi(q) = 0 moving only the ``free`` velocity coordinates.

    Args:
        model: Pinocchio model with the loop frames.
        data: its data (overwritten).
        layer: rows to zero (redundant rows allowed).
        q_guess: start configuration, shape (nq,).
        free: velocity indices allowed to move.
        settings: tolerances.
        rows: evaluators of ``layer``'s phi and J (None: :func:`layer_rows`).

    Returns:
        The assembled configuration, shape (nq,).

    Raises:
        AssemblyError: max |phi| stays above ``settings.tol``; carries the
            residual reached and the configuration.
    """
    q = np.array(q_guess, dtype=float)
    if layer.nc == 0:
        return q
    q = _newton(model, q, free, settings, rows or layer_rows(model, data, layer))
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
    rows: RowFunctions | None = None,
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
        rows: evaluators of ``layer``'s phi and J for Gauss-Newton (None: numpy's).

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
        q = solve_closure(model, data, layer, q0, free, settings, rows=rows)
        if closure_error(model, data, layer, q) <= settings.closure_tol and _inside(
            model, q, free, lower, upper
        ):
            return q
    except AssemblyError:
        pass
    q_ls = _least_squares(model, data, layer, q0, free, settings, lower, upper)
    res = closure_error(model, data, layer, q_ls)
    try:
        q = solve_closure(model, data, layer, q_ls, free, settings, rows=rows)
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
    owner = _joints_of_v(model)
    for n, i in enumerate(free):
        jm = model.joints[int(owner[i])]
        k = jm.idx_q
        if jm.nq == jm.nv == 1 and max(abs(lo[k]), abs(hi[k])) < _UNBOUNDED and hi[k] > lo[k]:
            lower[n], upper[n] = lo[k], hi[k]
    return lower, upper


def _q_of_v(model: pin.Model, free: np.ndarray) -> np.ndarray:
    """Configuration index of each free velocity coordinate's joint (its first entry)."""
    return np.asarray(model.idx_qs)[_joints_of_v(model)[free]]


def _joints_of_v(model: pin.Model) -> np.ndarray:
    """The joint id owning each velocity coordinate, shape (nv,)."""
    return np.repeat(np.arange(model.njoints), np.asarray(model.nvs))


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


def _newton(model, q, free, settings, rows: RowFunctions) -> np.ndarray:
    phi = rows.phi(q)
    res = float(np.max(np.abs(phi)))
    dv = np.zeros(model.nv)
    # Configuration entries of joints held entirely: pin.integrate with zero
    # velocity may renormalize them (continuous joints' cos, sin); keep them exact.
    held_q = _held_q(model, free)
    q_held = q[held_q].copy()
    for _ in range(settings.max_iter):
        if res <= settings.tol:
            return q
        J = rows.jacobian(q)
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
                phi_try = rows.phi(q_try)
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
