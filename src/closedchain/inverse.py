r"""Closed-chain inverse dynamics and the reaction wrenches of the loop joints.

Inverse dynamics (the lesson, Sections 3 and 6): given the state ``(q, v)`` and
the accelerations of ``mobility`` prescribed coordinates P (by default the
independent ones), the other accelerations follow from the acceleration
constraint, and the actuator torques and multipliers from the equations of
motion:

.. math::

    J_F\, a_F = -\gamma - J_P\, a_P, \qquad
    \begin{bmatrix} B & -J^\top \end{bmatrix}
    \begin{bmatrix} \tau_A \\ \lambda \end{bmatrix} = M a + h,

where B (nv x na) selects the actuated coordinates, M includes the joints' armature
and h the joint springs' and dampers' forces (:mod:`closedchain.passive`: h - tau_p);
with other passive generalized forces ``tau_passive`` the right-hand side is
:math:`M a + h - \tau_{passive}`. Projected onto an
orthonormal basis N of the null space of J (:math:`N^\top J^\top = 0`) the
second system splits into

.. math::

    (N^\top B)\, \tau_A = N^\top (M a + h), \qquad
    J^\top \lambda = B \tau_A - (M a + h),

so a square, nonsingular :math:`N^\top B` (as many actuators as degrees of
freedom, away from actuation singularities) gives the unique torques; with
more actuators than degrees of freedom (redundant actuation) the
minimum-norm torques are returned.

Reactions (the lesson's Problem 3): the multipliers of a loop's rows are the
components of the wrench its cut joint transmits. With the row formulas of
:mod:`closedchain.constraints` the virtual work :math:`-\lambda^\top \delta\phi`
of the constraint forces gives, on the successor link, the force (applied at
the origin of frame c2) and couple

.. math::

    f = \sum_{t} \lambda_t R_p n_t,
    \qquad
    \tau = \sum_{r} \lambda_r\, (R_p u_r) \times (R_s w_r),

in world coordinates, and the opposite wrench on the predecessor. Rows that the
row selection dropped as redundant carry no force: where a closure is
statically indeterminate (a planar loop's out-of-plane components, a spherical
wrist's forces along the legs) the reported wrench is the one carried by the
independent rows.

Tree joints (``joint_reactions(..., tree=True)``): with the loop wrenches applied to
their links as external forces, the recursive Newton-Euler algorithm (Pinocchio's
``rnea``, Featherstone 2008, Section 5.3) gives for every joint j the spatial force
:math:`f_j` its parent transmits to the subtree of j,

.. math::

    f_j = I_j a_j + v_j \times^* I_j v_j - f^{ext}_j + \sum_{c \in \text{children}(j)}
    {}^{j}X_{c}^{*} f_c, \qquad \tau_j = S_j^\top f_j,

in the joint's frame (``data.f[j]``, gravity included); its component along the motion
subspace S_j is the joint's generalized force tau_j (actuator torque, or zero on a
passive joint), the rest is the reaction the joint's structure carries (e.g. the normal
force of a slider on a prismatic joint).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from ._locking import exclusive
from ._percall import backend_name, rows_evaluator
from .dynamics.base import (
    DEFAULT_SETTINGS,
    SolverSettings,
    compute_terms,
    new_frozen,
    singular_error,
    workspace,
)
from .exceptions import ClosedChainError, NonFiniteError, check_settings
from .urdf import COUPLING

if TYPE_CHECKING:
    from .mechanism import Mechanism

__all__ = [
    "InverseDynamicsResult",
    "JointReaction",
    "LoopReaction",
    "inverse_dynamics",
    "joint_reactions",
]


@dataclass(frozen=True)
class InverseDynamicsResult:
    """Torques, accelerations and multipliers of one inverse-dynamics evaluation.

    Attributes:
        tau: generalized forces, shape (nv,) [N m or N]; nonzero only at the
            actuated coordinates.
        a: accelerations of every coordinate, shape (nv,) [rad/s^2 or m/s^2].
        lam: multipliers of the independent constraint rows, shape (nc,), in
            the convention ``M a + h + J^T lam = tau``.
        actuated_idx_v: velocity indices where tau acts, shape (na,).
        prescribed_idx_v: velocity indices whose accelerations were given, shape (mobility,).
        J: constraint Jacobian used, shape (nc, nv).
        gamma: Jdot v used, shape (nc,).
        dynamics_residual: max |M a + h + J^T lam - tau| [N m or N].
        constraint_residual: max |J a + gamma|.
    """

    tau: np.ndarray
    a: np.ndarray
    lam: np.ndarray
    actuated_idx_v: np.ndarray
    prescribed_idx_v: np.ndarray
    J: np.ndarray
    gamma: np.ndarray
    dynamics_residual: float
    constraint_residual: float

    def generalized_constraint_force(self) -> np.ndarray:
        """Return J^T lam, shape (nv,) [N m or N]: the generalized force the loops exert."""
        return self.J.T @ self.lam


@dataclass(frozen=True)
class LoopReaction:
    """The wrench a loop joint transmits, acting on its successor link.

    The predecessor link receives the opposite wrench (same point of application).

    Attributes:
        loop: loop name (the ``<loop name=...>``).
        type: loop type (``revolute``, ``spherical``, ``fixed``, ``prismatic``).
        frame: name of the model frame c1 (predecessor side) the components are given in.
        force: force on the successor, applied at the origin of c2, shape (3,) [N], in c1.
        torque: couple on the successor, shape (3,) [N m], in c1.
        force_world: the same force in world coordinates, shape (3,) [N].
        torque_world: the same couple in world coordinates, shape (3,) [N m].
    """

    loop: str
    type: str
    frame: str
    force: np.ndarray
    torque: np.ndarray
    force_world: np.ndarray
    torque_world: np.ndarray


@dataclass(frozen=True)
class JointReaction:
    """The wrench a tree joint transmits from its parent link to its child's subtree.

    Attributes:
        joint: joint name (the URDF ``<joint name=...>``).
        type: Pinocchio's joint model (``JointModelRY``, ``JointModelPX``, ...).
        frame: name of the model frame the components are given in: the joint frame
            (at the joint's origin, moving with the child).
        tau: the components along the joint's motion subspace, S^T f, shape (nv_j,)
            [N m or N]: the joint's generalized force, the actuator's torque plus the
            joint's spring and damper forces, less armature times a (the part of the
            motor's torque that turns its rotor); 0 for a joint without any.
        force: force on the child, applied at the joint's origin, shape (3,) [N], in
            the joint frame.
        torque: couple on the child about the joint's origin, shape (3,) [N m], in the
            joint frame.
        force_world: the same force in world axes, shape (3,) [N].
        torque_world: the same couple (about the joint's origin) in world axes, shape
            (3,) [N m].
    """

    joint: str
    type: str
    frame: str
    tau: np.ndarray
    force: np.ndarray
    torque: np.ndarray
    force_world: np.ndarray
    torque_world: np.ndarray


def _resolve_ordered(mech: Mechanism, spec: Iterable[str | int] | str, what: str) -> np.ndarray:
    """Resolve coordinates to velocity indices, keeping the caller's order."""
    if isinstance(spec, str):
        if spec in ("actuated", "independent", "dependent"):
            return mech.coordinate_indices(spec)
        spec = [spec]
    out: list[int] = []
    for item in spec:
        out += [int(i) for i in mech.coordinate_indices([item])]
    if len(set(out)) != len(out):
        names = [mech.coordinate_names[i] for i in out]
        raise ClosedChainError(f"{what} names a coordinate twice: {names}")
    return np.array(out, dtype=int)


class _Indices(NamedTuple):
    """Velocity indices of one (coordinates, actuated) spec: prescribed P, the others F,
    actuated A, and, for the compiled core, P, F, A and the unactuated Abar one after the
    other (int32)."""

    P: np.ndarray
    F: np.ndarray
    A: np.ndarray
    core: np.ndarray


def _cached_indices(mech: Mechanism, coordinates, actuated) -> _Indices:
    """Return the indices of these specs, resolved once per mechanism (controllers call
    inverse_dynamics every evaluation with the same specs)."""
    cache = workspace(mech).method_buffers.setdefault("inverse_indices", {})
    key = (coordinates, actuated)
    if isinstance(coordinates, str) and isinstance(actuated, str):
        hit = cache.get(key)  # the keywords: no conversion
    else:
        try:
            key = tuple(x if isinstance(x, str) else tuple(x) for x in key)
            hit = cache.get(key)
        except TypeError:
            key, hit = None, None
    if hit is not None:
        return hit
    P = _resolve_ordered(mech, coordinates, "coordinates")
    F = np.setdiff1d(np.arange(mech.nv), P)
    A = mech.coordinate_indices(actuated)
    Abar = np.setdiff1d(np.arange(mech.nv), A)
    out = _Indices(P, F, A, np.concatenate([P, F, A, Abar]).astype(np.int32))
    if key is not None:
        cache[key] = out
    return out


def _balance_weak_directions(b, s, V, A, Z, tau_A, settings: SolverSettings) -> np.ndarray:
    r"""Return the spare actuator torques that balance the load along J's near-null directions.

    With more actuators than degrees of freedom, the torques that produce the motion
    form the affine set tau_A + Z y (Z: orthonormal basis of the spare torques, which
    do nothing along the motion space). The loops carry the rest of the load b, with
    multipliers lam_i = v_i^T (B tau - b) / sigma_i along each right singular vector
    v_i of J. Along the weak directions W (sigma_i < ``weak_rcond`` sigma_1) that
    is load / sigma: a stance whose rows are nearly redundant then squeezes its loops
    with forces of 1e6 N, and the geometric stiffness of those forces makes it
    unstable at hundreds per second. y is the minimum-norm least-squares solution of

    .. math::

        W^T B Z\, y = W^T (b - B \tau_A)

    keeping only the singular values of W^T B Z (cosines between the spare torques
    and W) above ``weak_rcond``.

    Args:
        b: M a + h - tau_passive, shape (nv,).
        s: singular values of J, shape (nc,), largest first.
        V: right singular vectors of J, shape (nc, nv) (rows).
        A: actuated velocity indices, shape (n_act,).
        Z: spare torques, shape (n_act, n_act - mobility).
        tau_A: the minimum-norm torques, shape (n_act,).
        settings: ``weak_rcond``.

    Returns:
        Z y, shape (n_act,) [N m or N] (zero without weak directions).
    """
    W = V[s < settings.weak_rcond * s[0]]
    if not W.shape[0]:
        return np.zeros(len(A))
    Uc, sc, Vct = _svd(W[:, A] @ Z)
    k = int(np.count_nonzero(sc > settings.weak_rcond))
    r = W @ b - W[:, A] @ tau_A
    return Z @ (Vct[:k].T @ ((Uc[:, :k].T @ r) / sc[:k]))


def _svd(A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    U, s, Vt, info = lapack.dgesdd(A)
    if info != 0:  # pragma: no cover - LAPACK convergence failure
        raise ClosedChainError(f"SVD did not converge (LAPACK info {info})")
    return U, s, Vt


def _condition(s: np.ndarray) -> float:
    if s.size == 0:
        return 1.0
    return float(s[0] / s[-1]) if s[-1] > 0.0 else float("inf")


@exclusive
def inverse_dynamics(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    a_independent: Sequence[float] | np.ndarray,
    *,
    actuated: Iterable[str | int] | str = "actuated",
    coordinates: Iterable[str | int] | str = "independent",
    tau_passive: np.ndarray | None = None,
    settings: SolverSettings = DEFAULT_SETTINGS,
    backend: str = "auto",
) -> InverseDynamicsResult:
    """Compute the actuator torques that produce prescribed accelerations.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        a_independent: accelerations of ``coordinates``, shape (mobility,)
            [rad/s^2 or m/s^2], in the order of ``coordinates``.
        actuated: coordinates where torques may act: ``"actuated"`` (the
            ``<transmission>`` joints), or joint names / velocity indices.
        coordinates: the prescribed coordinates: ``"independent"``
            (``mech.independent_idx_v``) or ``mobility`` joint names / velocity
            indices, e.g. a platform's orientation joints.
        tau_passive: generalized forces that act besides the actuators and the
            model's own joint springs and damping (those are terms of the dynamics,
            :mod:`closedchain.passive`), shape (nv,) [N m or N], or None: the torques
            returned produce the motion with them.
        settings: ``cond_max`` bounds cond(J_F) (the other coordinates' block
            of J), cond(J) and cond(N^T B); over-actuated, the torques are the
            minimum-norm ones plus the spare torques that balance the load along J's
            near-null directions (``weak_rcond``), so that the multipliers stay of
            the size of the loads.
        backend: ``"auto"`` (the compiled core when it is built and holds the mechanism's
            rows; else numpy), ``"compiled"`` or ``"numpy"`` (the reference
            implementation), as :func:`~closedchain.forward_dynamics`. The two agree to
            round-off.

    Returns:
        The torques (zero off the actuated coordinates), full accelerations,
        multipliers and residuals.

    Raises:
        ClosedChainError: the mechanism has no degree of freedom (mobility 0),
            wrong number of prescribed coordinates or accelerations, or fewer
            actuators than degrees of freedom (names both).
        InvalidArgumentError: ``backend="compiled"`` where the core is not built or
            cannot hold the mechanism's rows.
        SingularConfigurationError: the prescribed coordinates do not determine
            the motion (J_F singular), J has lost rank, or the actuators cannot
            produce every motion at q (N^T B singular, an actuation singularity).
    """
    # The keyword specs of the last call (a controller's loop), checked then: reused.
    specs = (backend, coordinates, actuated)
    if not (isinstance(coordinates, str) and isinstance(actuated, str)):
        specs = None
    last = mech.__dict__.get("_inverse_last")
    if specs and last and last[0] is mech.constraints and last[1] is settings and last[2] == specs:
        mob, idx, fd = last[3]
    else:
        mob, idx, fd = _prepare(mech, coordinates, actuated, settings, backend)
        if specs:
            mech.__dict__["_inverse_last"] = (mech.constraints, settings, specs, (mob, idx, fd))
    P, A = idx.P, idx.A
    a_P = np.asarray(a_independent, dtype=float)
    if a_P.ndim != 1:
        a_P = a_P.reshape(-1)
    if fd is not None and len(a_P) == mob:
        # The core checks q, v and tau_passive, and solves the loop rows (percall.hpp). A
        # non-finite a_independent makes M a + h non-finite: a failure status, checked below.
        status, cond, a, tau, lam, J, gamma, dyn, con = fd.core.inverse_checked(
            q, v, a_P, idx.core, len(A), tau_passive, settings.cond_max, settings.weak_rcond
        )
        if status != INVERSE_OK:
            _check_accelerations(a_P, a_independent, mob)
            raise _failure(status, mech, np.asarray(q, dtype=float), v, a_P, idx, cond, settings)
    else:
        _check_accelerations(a_P, a_independent, mob)
        if len(A) < mob:
            raise ClosedChainError(
                f"{mech.name}: under-actuated: {len(A)} actuated coordinates "
                f"({', '.join(mech.coordinate_names[i] for i in A) or 'none'}) cannot produce "
                f"the accelerations of {mob} degrees of freedom; actuated must name at least "
                f"{mob}"
            )
        tau, a, lam, J, gamma, dyn, con = _inverse_numpy(
            mech, q, v, a_P, idx, tau_passive, settings
        )
    return _new_result(tau, a, lam, A, P, J, gamma, dyn, con)


def _new_result(tau, a, lam, A, P, J, gamma, dyn, con) -> InverseDynamicsResult:
    """The :class:`InverseDynamicsResult` of these fields (:func:`new_frozen`)."""
    return new_frozen(
        InverseDynamicsResult,
        tau=tau,
        a=a,
        lam=lam,
        actuated_idx_v=A,
        prescribed_idx_v=P,
        J=J,
        gamma=gamma,
        dynamics_residual=dyn,
        constraint_residual=con,
    )


def _prepare(mech: Mechanism, coordinates, actuated, settings, backend: str) -> tuple:
    """What :func:`inverse_dynamics` resolves from its specs: ``(mobility, indices, the
    compiled evaluator or None)``, after the checks that depend on nothing else.

    Raises:
        ClosedChainError: mobility 0, or ``coordinates`` names other than mobility many.
    """
    check_settings("settings", settings, SolverSettings)
    backend = backend_name(backend)
    mob = mech.mobility
    if mob == 0:
        raise ClosedChainError(
            f"{mech.name}: the mechanism has no degree of freedom (mobility 0): no actuator "
            "torque moves or holds it, the loops carry every load; valid: mobility >= 1"
        )
    idx = _cached_indices(mech, coordinates, actuated)
    if len(idx.P) != mob:
        raise ClosedChainError(
            f"{mech.name}: coordinates names {len(idx.P)} coordinates "
            f"({', '.join(mech.coordinate_names[i] for i in idx.P)}) but the mobility is "
            f"{mob}: give the accelerations of exactly {mob} coordinates"
        )
    return mob, idx, rows_evaluator(mech, backend) if len(idx.A) >= mob else None


def _check_accelerations(a_P: np.ndarray, a_independent, mob: int) -> None:
    """Raise unless ``a_P`` (``a_independent`` as a flat float array) is ``mob`` finite numbers."""
    if a_P.shape != (mob,) or not np.isfinite(a_P).all():
        raise ClosedChainError(
            f"a_independent must be {mob} finite numbers (one per prescribed coordinate), "
            f"got {np.asarray(a_independent)}"
        )


def _inverse_numpy(mech: Mechanism, q, v, a_P, idx, tau_passive, settings) -> tuple:
    """The numpy reference of :func:`inverse_dynamics`: (tau, a, lam, J, gamma, dynamics
    residual, constraint residual)."""
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    nv, nc, mob = mech.nv, mech.nc, mech.mobility
    P, F, A = idx.P, idx.F, idx.A
    ws = compute_terms(mech, q, v)
    M, h = ws.M.copy(), ws.h.copy()
    J, gamma = ws.J.copy(), ws.gamma.copy()

    # Accelerations of the other coordinates F from J_F a_F = -gamma - J_P a_P.
    a = np.zeros(nv)
    a[P] = a_P
    if nc:
        JF = J[:, F]
        lu, piv, info = lapack.dgetrf(JF)
        rcond = lapack.dgecon(lu, lapack.dlange("1", JF))[0] if info == 0 else 0.0
        cond = 1.0 / rcond if rcond > 0.0 else float("inf")
        if cond > settings.cond_max:
            raise _failure(INVERSE_JF_SINGULAR, mech, q, v, a_P, idx, cond, settings)
        a[F] = lapack.dgetrs(lu, piv, -gamma - J[:, P] @ a_P)[0]

    b = M @ a + h  # = B tau_A - J^T lam
    if tau_passive is not None:
        b -= mech.check_v(tau_passive, "tau_passive")
    if not np.all(np.isfinite(b)):
        raise _failure(INVERSE_NON_FINITE, mech, q, v, a_P, idx, 0.0, settings)
    if nc:
        U, s, Vt = _svd(J)
        cond = _condition(s)
        if cond > settings.cond_max:
            raise _failure(INVERSE_J_SINGULAR, mech, q, v, a_P, idx, cond, settings)
        N = Vt[nc:].T
    else:
        N = np.eye(nv)
    # (N^T B) tau_A = N^T b: unique when square, minimum-norm when over-actuated (plus
    # the spare torques that balance J's near-null directions, _balance_weak_directions).
    # The singular values of N^T B are the cosines of the principal angles
    # between the actuated directions and the motion space (N orthonormal, B a
    # selection), so 1 / sigma_min is its condition relative to the ideal 1;
    # a plain sigma_max / sigma_min would call a 1 x 1 zero well-conditioned.
    G = N[A, :].T
    Ug, sg, Vgt = _svd(G)
    cond = 1.0 / sg[-1] if sg[-1] > 0.0 else float("inf")
    if cond > settings.cond_max:
        raise _failure(INVERSE_ACTUATION_SINGULAR, mech, q, v, a_P, idx, cond, settings)
    tau_A = Vgt[:mob].T @ ((Ug.T @ (N.T @ b)) / sg)
    if nc and len(A) > mob:
        tau_A += _balance_weak_directions(b, s, Vt[:nc], A, Vgt[mob:].T, tau_A, settings)
    tau = np.zeros(nv)
    tau[A] = tau_A
    f = tau - b  # = J^T lam
    lam = U @ ((Vt[:nc] @ f) / s) if nc else np.zeros(0)
    dyn = float(np.max(np.abs(b + J.T @ lam - tau)))
    con = float(np.max(np.abs(J @ a + gamma), initial=0.0))
    return tau, a, lam, J, gamma, dyn, con


#: The outcomes of the compiled core's inverse_checked (src/cpp/percall.hpp), which the
#: numpy path reports with the same codes (:func:`_failure`).
INVERSE_OK = 0
INVERSE_JF_SINGULAR = 1
INVERSE_NON_FINITE = 2
INVERSE_J_SINGULAR = 3
INVERSE_ACTUATION_SINGULAR = 4


def _failure(
    status: int, mech: Mechanism, q, v, a_P, idx: _Indices, cond: float, settings
) -> ClosedChainError:
    """The error of inverse_dynamics' failure ``status``, shared by the two backends."""
    if status == INVERSE_NON_FINITE:
        return NonFiniteError(
            f"{mech.name}: inverse dynamics overflowed to non-finite M a + h at "
            f"max|v| = {np.max(np.abs(v), initial=0):.3g}, "
            f"max|a_independent| = {np.max(np.abs(a_P), initial=0):.3g}: the motion must be "
            "small enough for M a + h to stay finite in double precision"
        )

    def names(indices: np.ndarray) -> str:
        return ", ".join(mech.coordinate_names[i] for i in indices)

    what, hint = {
        INVERSE_JF_SINGULAR: (
            f"J_F (constraint-Jacobian columns of the coordinates not prescribed: {names(idx.F)})",
            f"the prescribed coordinates {names(idx.P)} do not determine the motion here; "
            "prescribe other coordinates",
        ),
        INVERSE_J_SINGULAR: (
            "the constraint Jacobian J",
            "the loops have lost rank, so their multipliers are not unique",
        ),
        INVERSE_ACTUATION_SINGULAR: (
            "N^T B (the actuators' reach into the motion space)",
            f"the actuated coordinates {names(idx.A)} cannot produce every motion here "
            "(an actuation singularity)",
        ),
    }[status]
    return singular_error(mech, q, what, cond, settings.cond_max, hint)


@exclusive
def joint_reactions(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, result, *, tree: bool = False
) -> list[LoopReaction | JointReaction]:
    """Return the wrench each loop joint (and, with ``tree``, each tree joint) transmits.

    Loop joints: the wrench acts on the loop's successor link, the force
    applied at the origin of the successor-side frame c2 (which coincides with
    the predecessor-side frame c1's origin when the loop is closed, except
    along a prismatic axis); components in c1. The predecessor receives the
    opposite wrench. See the module docstring for the formula.

    Tree joints (``tree=True``): the wrench the parent transmits to the child's
    subtree through the joint, in the joint frame, from the recursive Newton-Euler
    algorithm with the loop wrenches as external forces (module docstring); it needs
    the accelerations, so ``result`` must carry ``a``.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), the one the multipliers belong to.
        v: velocity, shape (nv,) [rad/s or m/s]; the loop reactions follow from q and
            lam alone, the tree joints' from (q, v, a, lam).
        result: a :class:`InverseDynamicsResult` or
            :class:`~closedchain.dynamics.ForwardDynamicsResult` (its ``lam``, and
            ``a`` for ``tree``), or the multipliers themselves, shape (nc,).
        tree: also report every tree joint (default False: the loops only).

    Returns:
        One :class:`LoopReaction` per loop with frames, in the URDF's order; with
        ``tree``, then one :class:`JointReaction` per tree joint, in tree order. A
        coupling loop transmits no wrench between two links: its reaction is the
        generalized force lam on its joint and -multiplier lam on the one it mimics
        (the rows of J^T lam), which act as motor torques do, so it is left out (the
        tree joints' wrenches, from their subtrees' motion, include it).

    Raises:
        ClosedChainError: lam of the wrong shape, or ``tree`` without accelerations.
    """
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    lam = np.asarray(getattr(result, "lam", result), dtype=float)
    if lam.shape != (mech.nc,):
        raise ClosedChainError(f"lam has shape {lam.shape}, expected ({mech.nc},)")
    a = getattr(result, "a", None)
    if tree and a is None:
        raise ClosedChainError(
            "joint_reactions(tree=True) needs the accelerations: pass the "
            "InverseDynamicsResult or ForwardDynamicsResult, not lam alone"
        )
    model, data = mech.model, mech.data
    pin.forwardKinematics(model, data, q)
    out: list[LoopReaction | JointReaction] = []
    # Loop wrenches as external forces on their links (Pinocchio's fext: per joint, in
    # the joint's local frame, about its origin): on the successor at c2's origin, the
    # opposite on the predecessor.
    fext = [pin.Force.Zero() for _ in range(model.njoints)]
    for blk, sl in mech.constraints.per_loop():
        if blk.spec.type == COUPLING:
            continue
        oMp = pin.updateFramePlacement(model, data, blk.fid_p)
        oMs = pin.updateFramePlacement(model, data, blk.fid_s)
        Rp, Rs = oMp.rotation, oMs.rotation
        lam_l = lam[sl]
        nt = blk.nt
        force = Rp @ (blk.trans.T @ lam_l[:nt])
        torque = np.zeros(3)
        for u, w, lr in zip(blk.rot_u, blk.rot_w, lam_l[nt:], strict=True):
            torque += lr * np.cross(Rp @ u, Rs @ w)
        out.append(
            LoopReaction(
                loop=blk.spec.name,
                type=blk.spec.type,
                frame=model.frames[blk.fid_p].name,
                force=Rp.T @ force,
                torque=Rp.T @ torque,
                force_world=force,
                torque_world=torque,
            )
        )
        # The wrench about the world origin, then into each link's joint frame.
        wrench = pin.Force(force, torque + np.cross(oMs.translation, force))
        js, jp = model.frames[blk.fid_s].parentJoint, model.frames[blk.fid_p].parentJoint
        fext[js] += data.oMi[js].actInv(wrench)
        fext[jp] -= data.oMi[jp].actInv(wrench)
    if not tree:
        return out
    a = mech.check_v(a, "result.a")
    pin.rnea(model, data, q, v, a, fext)
    for j in range(1, model.njoints):
        jm = model.joints[j]
        f = data.f[j]
        R = data.oMi[j].rotation
        out.append(
            JointReaction(
                joint=model.names[j],
                type=jm.shortname(),
                frame=model.names[j],
                force=f.linear.copy(),
                torque=f.angular.copy(),
                force_world=R @ f.linear,
                torque_world=R @ f.angular,
                # rnea's tau is S^T f + armature a (Pinocchio adds the rotor's inertia).
                tau=data.tau[jm.idx_v : jm.idx_v + jm.nv]
                - model.armature[jm.idx_v : jm.idx_v + jm.nv] * a[jm.idx_v : jm.idx_v + jm.nv],
            )
        )
    return out
