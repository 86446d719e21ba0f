r"""Assembly onto phi(q) = 0, velocity projection and singularity measures.

Assembly is Gauss-Newton with a backtracking line search on the Lie group of
configurations:

.. math::

    \delta v_F = -J_F(q_k)^{+} \phi(q_k), \qquad
    q_{k+1} = q_k \oplus \alpha\, \delta v,

where F are the free (not held) velocity coordinates, ``+`` the minimum-norm
least-squares pseudo-inverse (so redundant rows do no harm) and
:math:`\oplus` is ``pin.integrate``; where it fails (far from the closure),
a trust-region least-squares solve on the closure residual, zero exactly at the
closure, then the same Gauss-Newton to polish
(:func:`closedchain.closure.assemble_closure`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from ._locking import exclusive
from ._percall import backend_name, rows_evaluator
from .closure import (
    DEFAULT_ASSEMBLY_SETTINGS,
    RowFunctions,
    SelectionSettings,
    assemble_closure,
    closure_error,
    layer_jacobian,
    layer_phi,
)
from .closure import AssemblySettings as AssemblySettings  # re-exported
from .closure import partition_coordinates as partition_coordinates  # re-exported
from .closure import solve_closure as solve_closure  # re-exported
from .compiled import declared_core, has, jacobian_rows
from .exceptions import AssemblyError, ClosedChainError, check_settings

__all__ = [
    "SingularityMeasures",
    "actuation_sigma_min",
    "assemble",
    "compute_gamma",
    "compute_jacobian",
    "compute_phi",
    "project_velocity",
    "random_consistent_state",
    "singularity_measures",
]

if TYPE_CHECKING:
    from .mechanism import Mechanism


#: Largest relative |J v| (against |J| |v|) a projected velocity may keep.
VELOCITY_TOL = 1e-12
#: The row selection's rank tolerance (:class:`SelectionSettings`), read once.
_RANK_TOL = SelectionSettings.rank_tol
#: At an aligned closure with max |phi| <= tol the closure residual is at most sqrt(3) tol
#: (:func:`_assemble_compiled`); the compiled assembly returns without evaluating it when
#: ``closure_tol`` is at least this times ``tol`` (the rest of the factor covers e's
#: round-off, eps times the cut frames' distance from the origin).
CLOSURE_PER_PHI = 10.0
#: The compiled core has the assembly's Gauss-Newton (src/cpp/closure_newton.hpp; a core
#: built from an older tree does not).
_COMPILED_ASSEMBLY = has("assemble_checked")


@exclusive
def assemble(
    mech: Mechanism,
    q_guess: np.ndarray,
    *,
    fixed: Iterable[str | int] | str = (),
    settings: AssemblySettings = DEFAULT_ASSEMBLY_SETTINGS,
    backend: str = "auto",
) -> np.ndarray:
    """Bring a configuration onto the constraint manifold phi(q) = 0.

    Args:
        mech: the mechanism.
        q_guess: start configuration, shape (nq,); the assembly mode (branch)
            reached is the one Newton finds from here.
        fixed: coordinates held at their value in ``q_guess``: joint names,
            velocity indices, or ``"actuated"`` / ``"independent"``.
        settings: tolerances (defaults: :class:`AssemblySettings`).
        backend: as :func:`compute_phi`. On the compiled core Gauss-Newton and the
            alignment check run in C++; where they fail, the far-from-closure
            least-squares solve is numpy's (on the compiled rows).

    Returns:
        q with max |phi(q)| <= settings.tol over every declared row (the
        independent ones and those dropped as redundant), shape (nq,); on a model
        loaded with redundant rows that disagree (``mech.closure.mismatch_tol``),
        the least-squares minimum of the closure residual with the kept rows closed.

    Raises:
        AssemblyError: no closure found from q_guess (the message gives the
            smallest closure residual reached, ``exc.q`` its configuration).
    """
    check_settings("settings", settings, AssemblySettings)
    if (
        _COMPILED_ASSEMBLY
        and mech.closure.mismatch_tol <= settings.mismatch_tol
        and rows_evaluator(mech, backend_name(backend)) is not None
    ):
        q = _assemble_compiled(mech, q_guess, fixed, settings)
        if q is not None:
            return q
    rows = _declared_rows(mech, backend)
    q_guess = mech.check_q(q_guess, "q_guess")
    free, held, _ = _free_coordinates(mech, fixed)
    try:
        # Every declared row, not only the independent ones: a configuration on
        # another solution branch of the kept rows with a dropped row open is
        # never returned as closed (redundant rows do no harm to the
        # minimum-norm Gauss-Newton step).
        polish = None
        if mech.closure.mismatch_tol > settings.mismatch_tol:
            # A model whose redundant rows disagree (loaded with a warning): the least-squares
            # minimum, with the kept rows closed.
            settings = replace(settings, mismatch_tol=mech.closure.mismatch_tol)
            polish = mech.constraints
        return assemble_closure(
            mech.model, mech.data, mech.declared, q_guess, free, settings, polish=polish, rows=rows
        )
    except AssemblyError as exc:
        raise AssemblyError(
            f"{mech.name}: {exc} (holding {len(held)} coordinates: "
            f"{', '.join(mech.coordinate_names[i] for i in held) or 'none'})",
            residual=exc.residual,
            q=exc.q,
        ) from None


@exclusive
def compute_phi(mech: Mechanism, q: np.ndarray, *, backend: str = "auto") -> np.ndarray:
    """Return the loop-closure residual phi(q), shape (nc,), [m] or [-] per row.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        backend: ``"auto"`` (compiled when built and it holds the rows), ``"compiled"``
            or ``"numpy"``, as :func:`~closedchain.forward_dynamics`.
    """
    rows = rows_evaluator(mech, backend_name(backend))
    if rows is not None:
        return rows.core.phi_checked(q)
    q = mech.check_q(q, "q")
    return layer_phi(mech.model, mech.data, mech.constraints, q)


@exclusive
def compute_jacobian(mech: Mechanism, q: np.ndarray, *, backend: str = "auto") -> np.ndarray:
    """Return the constraint Jacobian J(q), shape (nc, nv).

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        backend: as :func:`compute_phi`.
    """
    rows = rows_evaluator(mech, backend_name(backend))
    if rows is not None:
        return jacobian_rows(rows.core.jacobian_checked(q), mech.nv)
    q = mech.check_q(q, "q")
    return layer_jacobian(mech.model, mech.data, mech.constraints, q)


@exclusive
def compute_gamma(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, *, backend: str = "auto"
) -> np.ndarray:
    """Return gamma(q, v) = Jdot(q, v) v, shape (nc,), [m/s^2] or [1/s^2] per row.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        backend: as :func:`compute_phi`.
    """
    rows = rows_evaluator(mech, backend_name(backend))
    if rows is not None:
        return rows.core.gamma_checked(q, v)
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    pin.forwardKinematics(mech.model, mech.data, q, v, np.zeros(mech.nv))
    out = np.zeros(mech.nc)
    mech.constraints.evaluate(mech.model, mech.data, gamma=out)
    return out


@exclusive
def project_velocity(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    *,
    fixed: Iterable[str | int] | str = (),
    backend: str = "auto",
) -> np.ndarray:
    """Project a velocity onto the constraint tangent space J(q) v = 0.

    Without ``fixed`` this is the Euclidean orthogonal projection
    :math:`v - J^+ J v`; with ``fixed`` those coordinates keep their value and
    the others take the minimum-norm correction.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        fixed: coordinates to keep (as in :func:`assemble`).
        backend: where J is evaluated, as :func:`compute_phi` (the projection itself is
            a small least-squares solve by numpy).

    Returns:
        The projected velocity, shape (nv,), with J v = 0 for every declared row.

    Raises:
        ClosedChainError: the held coordinates admit no velocity with J v = 0.
    """
    compiled_rows = rows_evaluator(mech, backend_name(backend)) is not None
    free, held, free32 = _free_coordinates(mech, fixed)
    # The declared rows are redundant (rank < rows): singular values below the
    # rank tolerance of the row selection are round-off, not directions to project
    # along (lstsq's default cutoff, ~1e-15, amplified Bricard's 1e-13 one to 1e-3).
    rcond = _RANK_TOL
    # Every declared row: the same tangent space as the independent rows
    # wherever they describe the loops, and the right one where they do not.
    if compiled_rows:
        core = declared_core(mech)
        v, residual, row, sigma_max = core.project_checked(q, v, free32, rcond)
        if mech.nc == 0:
            return v
    else:
        q = mech.check_q(q, "q")
        v = np.array(mech.check_v(v, "v"), dtype=float)
        if mech.nc == 0:
            return v
        J = layer_jacobian(mech.model, mech.data, mech.declared, q)
        v[free] -= np.linalg.lstsq(J[:, free], J @ v, rcond=rcond)[0]
        Jv = np.abs(J @ v)
        row, residual = int(np.argmax(Jv)), float(np.max(Jv, initial=0.0))
        sigma_max = float(np.linalg.norm(J, 2))
    scale = max(1.0, sigma_max * math.sqrt(float(v @ v)))  # np.linalg.norm's formula
    if residual > VELOCITY_TOL * scale:
        raise ClosedChainError(
            f"{mech.name}: no velocity with J v = 0 keeps the held coordinates "
            f"({', '.join(mech.coordinate_names[i] for i in held)}): row "
            f"{mech.declared.declared_rows[row].label} keeps |J v| = {residual:.3e}"
        )
    return v


def _assemble_compiled(
    mech: Mechanism, q_guess, fixed, settings: AssemblySettings
) -> np.ndarray | None:
    """:func:`assemble`'s first try on the compiled core: Gauss-Newton on every declared row
    and the alignment check in C++ (``Core.assemble_checked``). Returns the closed
    configuration, shape (nq,), or None where Gauss-Newton did not converge or reached a
    spurious closure (:func:`assemble` then runs :func:`assemble_closure`, its messages)."""
    try:
        free, _, free32 = _free_coordinates(mech, fixed)
    except ClosedChainError:
        mech.check_q(q_guess, "q_guess")  # the numpy path's order: q_guess's errors first
        raise
    q = declared_core(mech).assemble_checked(
        q_guess,
        free32,
        settings.tol,
        int(settings.max_iter),
        int(settings.max_halvings),
        settings.fallback_rcond,
        settings.contraction,
    )
    # assemble_closure also asks max |e| <= closure_tol of the closure residual e
    # (constraints.closure_residual). At an aligned point with max |phi| <= tol over every
    # declared row, e is bounded by phi, loop by loop, with p = (R_p^T (p_s - p_p)) the
    # position of c2 in c1 and R = R_p^T R_s: the translation rows are -p's components
    # along the orthonormal (n1, n2, a), so |p| <= sqrt(3) tol (spherical e = p; revolute
    # e = (p, R a - a); prismatic e's n1.p, n2.p are rows themselves). The tilt rows are
    # (R a)'s components along n1, n2, and aligned means a.R a > 0, so
    # |R a - a| = |(r1, r2, a.R a - 1)| <= sqrt(2) tol + tol^2. Fixed and prismatic loops add
    # the twist r3 = n1.R n2; with n1.R n1, n2.R n2 > 0 too, R is within O(tol) of I and
    # |log3(R)| = |(r1, r2, r3)| (1 + O(tol)) <= sqrt(3) tol (1 + O(tol)), and log6's
    # translation is p to 1 + O(tol). So max |e| <= sqrt(3) tol (1 + O(tol)) for every
    # frame loop type, and a coupling's e is its row itself (|e| <= tol);
    # tests/test_percall.py checks it on each frame loop type.
    if q is None or (
        settings.closure_tol < CLOSURE_PER_PHI * settings.tol
        and closure_error(mech.model, mech.data, mech.declared, q) > settings.closure_tol
    ):
        return None
    return q


def _free_coordinates(mech: Mechanism, fixed) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(free, held, free as int32) velocity indices of ``fixed`` (as :func:`assemble`'s),
    resolved once per constraint layer for a hashable ``fixed`` (controllers project every
    step; a new row selection may change the independent coordinates)."""
    entry = mech.__dict__.get("_free_coordinates")
    if entry is None or entry[0] is not mech.constraints:
        entry = mech.__dict__["_free_coordinates"] = (mech.constraints, {})
    cache = entry[1]
    try:
        key = fixed if isinstance(fixed, str) else tuple(fixed)
        hit = cache.get(key)
    except TypeError:
        key, hit = None, None
    if hit is None:
        held = mech.coordinate_indices(fixed)
        free = np.setdiff1d(np.arange(mech.nv), held)
        hit = (free, held, free.astype(np.int32))
        for x in hit:
            x.setflags(write=False)  # shared by later calls
        if key is not None:
            cache[key] = hit
    return hit


def _declared_rows(mech: Mechanism, backend: str) -> RowFunctions | None:
    """The compiled core's :class:`RowFunctions` of every declared row, or None where
    ``backend`` (as :func:`compute_phi`) has them evaluated by numpy."""
    if rows_evaluator(mech, backend_name(backend)) is None:
        return None
    core = declared_core(mech)
    return RowFunctions(
        core.phi_checked, lambda q: jacobian_rows(core.jacobian_checked(q), mech.nv)
    )


@dataclass(frozen=True)
class SingularityMeasures:
    """How close a configuration is to a singularity.

    Attributes:
        sigma_min: smallest singular value of J (independent rows).
        cond_J: 2-norm condition number of J.
        cond_JD: 2-norm condition number of J_D, the columns of the dependent
            coordinates (inf when J_D is singular).
    """

    sigma_min: float
    cond_J: float
    cond_JD: float


@exclusive
def singularity_measures(mech: Mechanism, q: np.ndarray) -> SingularityMeasures:
    """Return the singular-value measures of J(q) and J_D(q).

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
    """
    if mech.nc == 0:
        return SingularityMeasures(float("inf"), 1.0, 1.0)
    J = compute_jacobian(mech, q)
    s = np.linalg.svd(J, compute_uv=False)
    sd = np.linalg.svd(J[:, mech.dependent_idx_v], compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    cond_d = float(sd[0] / sd[-1]) if sd[-1] > 0 else float("inf")
    return SingularityMeasures(float(s[-1]), cond, cond_d)


def actuation_sigma_min(
    J: np.ndarray,
    actuated_idx_v: np.ndarray,
    *,
    output_idx_v: np.ndarray | None = None,
    J_output: np.ndarray | None = None,
) -> tuple[float, float]:
    r"""Return the smallest singular values of the two actuation maps.

    * parallel (type II): :math:`J_D`, the columns of J of the non-actuated
      coordinates; zero where the actuators no longer determine the motion.
    * serial (type I): the columns of the non-output coordinates of the closure
      written with the outputs as coordinates; zero where the output no longer
      determines the actuators. With output *coordinates* that is
      ``J[:, non-output]``; with an output *frame* of velocity
      :math:`\dot x = J_{out} v`, its coordinates x join q through the rows
      :math:`J_{out} v - \dot x = 0`, and the non-output columns are
      :math:`[J; J_{out}]`.

    Args:
        J: constraint Jacobian, shape (nc, nv).
        actuated_idx_v: velocity indices of the actuated coordinates, shape (na,).
        output_idx_v: velocity indices of output coordinates, or None.
        J_output: Jacobian of an output frame, shape (m, nv), or None.

    Returns:
        ``(parallel, serial)``: each the last of the min(rows, columns) singular values
        [m or -]; serial is NaN without an output.
    """
    nv = J.shape[1]
    parallel = _last_singular_value(J[:, np.setdiff1d(np.arange(nv), actuated_idx_v)])
    if J_output is not None:
        serial = _last_singular_value(np.vstack([J, J_output]))
    elif output_idx_v is not None:
        serial = _last_singular_value(J[:, np.setdiff1d(np.arange(nv), output_idx_v)])
    else:
        serial = float("nan")
    return parallel, serial


def _last_singular_value(A: np.ndarray) -> float:
    """Return the smallest of A's min(rows, columns) singular values (inf when empty)."""
    if A.size == 0:
        return float("inf")
    return float(np.linalg.svd(A, compute_uv=False)[-1])


@exclusive
def random_consistent_state(
    mech: Mechanism,
    rng: np.random.Generator,
    *,
    velocity_scale: float = 1.0,
    min_sigma: float = 1e-3,
    max_attempts: int = 1000,
    uniform_attempts: int = 20,
    local_scale: float = 0.1,
    assembly: AssemblySettings = DEFAULT_ASSEMBLY_SETTINGS,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw an assembled configuration within joint limits and a velocity with J v = 0.

    Starts are drawn uniformly within the joint limits. After
    ``uniform_attempts`` failed uniform starts, every other start is drawn
    near the assembled ``mech.q_ref`` instead (``q_ref`` moved along a random
    tangent vector, clipped to the limits): a legged robot welded to the
    ground almost never assembles from a uniformly random base orientation
    and leg configuration.

    Args:
        mech: the mechanism.
        rng: random generator.
        velocity_scale: standard deviation of the velocity before projection [rad/s or m/s].
        min_sigma: reject configurations where the smallest singular value of J
            is below this (draws away from singularities).
        max_attempts: random starts before giving up.
        uniform_attempts: uniform starts before starts near ``q_ref`` are mixed in.
        local_scale: standard deviation of the tangent vector moving ``q_ref``
            for those starts [rad or m].
        assembly: settings of the assembly onto phi = 0 (default
            :class:`AssemblySettings`); validation asks for a tighter ``tol``.

    Returns:
        (q, v), shapes (nq,) and (nv,).

    Raises:
        AssemblyError: no start assembled within ``max_attempts``.
    """
    last: AssemblyError | None = None
    lo, hi = mech.model.lowerPositionLimit, mech.model.upperPositionLimit
    for attempt in range(max_attempts):
        if attempt < uniform_attempts or attempt % 2 == 0:
            q0 = mech.random_configuration(rng)
        else:
            dv = local_scale * rng.standard_normal(mech.nv)
            q0 = pin.normalize(
                mech.model, np.clip(pin.integrate(mech.model, mech.q_ref, dv), lo, hi)
            )
        try:
            q = assemble(mech, q0, settings=assembly)
        except AssemblyError as exc:
            last = exc
            continue
        q = mech.wrap_angles(q)
        if not mech.within_limits(q):
            continue
        if mech.nc and singularity_measures(mech, q).sigma_min < min_sigma:
            continue
        v = project_velocity(mech, q, velocity_scale * rng.standard_normal(mech.nv))
        return q, v
    raise AssemblyError(
        f"{mech.name}: no random consistent state in {max_attempts} attempts",
        residual=last.residual if last else float("nan"),
        q=last.q if last else None,
    )
