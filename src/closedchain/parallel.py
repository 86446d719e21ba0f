r"""The parallel-robot workflow: motors to pose, pose to motors, and actuation singularities.

What users of parallel robots (Gepetto's toolbox-parallel-robots) do with a closed-chain
model, on closedchain's loops:

* forward kinematics: the configuration with the actuated joints at given motor values
    and every loop closed (:func:`forward_kinematics`: the assembly holding the actuated
    coordinates, :func:`closedchain.assemble`);

* closed-loop inverse kinematics: a configuration with every loop closed and a frame at a
    target placement, position or orientation (:func:`inverse_kinematics`), a
    least-squares solve on the stacked

    .. math::

        r(q) = \begin{bmatrix} e(q) \\ \epsilon(q) \end{bmatrix}, \qquad
        \epsilon_{6d} = \log_6\bigl(T^{-1}\, {}^oM_f(q)\bigr), \quad
        \epsilon_{3d} = p_f(q) - p_T, \quad
        \epsilon_{rot} = \log_3\bigl(R_T^\top R_f(q)\bigr),

    with e the closure residual of every loop (zero exactly at the closure,
    :meth:`closedchain.constraints.ConstraintLayer.closure_residuals`) and exact Jacobians
    (:math:`J_{\log_6}\, J_f^{local}`, the frame's world-aligned linear Jacobian and
    :math:`J_{\log_3}\, J_f^{\omega, local}`);

* motor torques: :func:`closedchain.inverse_dynamics` with the accelerations prescribed
    on the actuated coordinates (``coordinates="actuated"``; the torques act on the
    actuated joints, ``actuated="actuated"``, by default);

* actuation singularities (:func:`actuation_singularities`; the rank of J and the choice
    of independent coordinates of the 4-bar and the 3-leg wrist in the lesson cited in
    the references): the smallest singular value of :math:`J_D`, the non-actuated
    columns of J (parallel, type II: the motors no longer determine the motion) and of
    the output map (serial, type I: the output frame no longer determines the motors),
    :func:`closedchain.kinematics.actuation_sigma_min`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import pinocchio as pin

from ._locking import exclusive
from .closure import (
    DEFAULT_ASSEMBLY_SETTINGS,
    AssemblySettings,
    _clip_into,
    _free_bounds,
    _least_squares,
    closure_error,
)
from .exceptions import (
    AssemblyError,
    InvalidArgumentError,
    SingularConfigurationError,
    UnknownChoiceError,
    _one_line,
    check_count,
    check_positive,
    check_settings,
    resolve_choice,
    shorten,
)
from .kinematics import actuation_sigma_min, assemble, compute_jacobian
from .mechanism import Mechanism
from .pindata import frame_jacobian
from .urdf import name_list

__all__ = [
    "ActuationSingularities",
    "ForwardKinematicsResult",
    "InverseKinematicsResult",
    "actuation_singularities",
    "forward_kinematics",
    "inverse_kinematics",
]

#: Task-error modes of :func:`inverse_kinematics`: the full placement, the position, or
#: the orientation.
IK_MODES = ("6d", "3d", "orientation")
#: A coordinate within this of a joint limit [rad or m] counts as stopped by it when
#: :func:`inverse_kinematics` misses its target (the message names the limit).
IK_LIMIT_TOL = 1e-6
#: Largest frame error [m or rad] (max |epsilon|) an inverse-kinematics solution may keep.
IK_TOL = 1e-10
#: Residual evaluations of the inverse-kinematics least-squares solve.
IK_MAX_NFEV = 200
#: Largest deviation of R^T R from the identity of a rotation-matrix target [-].
IK_ROTATION_TOL = 1e-8
#: Forward kinematics refuses a configuration where sigma_min(J_D) <= this times
#: ||J||_2 [-]: the motors' error is amplified 1 / TYPE_II_RTOL times in the passive joints.
TYPE_II_RTOL = 1e-8
#: A target's rotation R is a rotation matrix when max |R^T R - I| is at most this [-]
#: (a rotation written with 9 printed digits is within 1e-8).
ROTATION_TOL = 1e-6

_LOCAL = pin.ReferenceFrame.LOCAL
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


@dataclass(frozen=True)
class _ClosedConfiguration:
    """A configuration with every loop closed, its motors and its closure residual.

    Attributes:
        q: configuration, shape (nq,).
        motors: the actuated coordinates' values, shape (na,) [rad or m], in the order
            of ``mech.actuated_joints``.
        closure_residual: max |e| of every loop's closure residual at q [m or rad].
    """

    q: np.ndarray
    motors: np.ndarray
    closure_residual: float


@dataclass(frozen=True)
class ForwardKinematicsResult(_ClosedConfiguration):
    """A closed configuration with the motors at given values.

    Attributes:
        q: configuration, shape (nq,).
        motors: the motor values held, shape (na,) [rad or m].
        closure_residual: max |e| of every loop's closure residual at q [m or rad].
        sigma_min_JD: smallest singular value of J_D, the non-actuated columns of J
            [m or -] (zero at a type II singularity).
    """

    sigma_min_JD: float


@dataclass(frozen=True)
class InverseKinematicsResult(_ClosedConfiguration):
    """A closed configuration with a frame at a target.

    Attributes:
        q: configuration, shape (nq,).
        motors: the motor values reached, shape (na,) [rad or m], in the order of
            ``mech.actuated_joints``.
        closure_residual: max |e| of every loop's closure residual at q [m or rad].
        frame: the frame placed.
        mode: ``"6d"`` (placement), ``"3d"`` (position) or ``"orientation"``.
        frame_error: max |epsilon| of the frame's error (6 entries of log6 in 6d,
            the position's 3 in 3d, log3 of the rotation error's 3 in orientation)
            [m or rad].
    """

    frame: str
    mode: str
    frame_error: float


@dataclass(frozen=True)
class ActuationSingularities:
    """How far a configuration is from the two actuation singularities.

    Attributes:
        parallel: sigma_min of J_D, the non-actuated columns of J (type II) [m or -].
        serial: sigma_min of the output map of ``frame`` (type I) [m or -], NaN
            without a frame.
        frame: the output frame, or None.
    """

    parallel: float
    serial: float
    frame: str | None


def _motor_joints(mech: Mechanism) -> list[pin.JointModel]:
    """The actuated joints in ``mech.actuated_joints`` order, each one coordinate."""
    if not mech.actuated_joints:
        raise InvalidArgumentError(
            f"{mech.path}: no actuated joint (no <transmission> element): forward "
            "kinematics needs the motors; valid: a URDF with <transmission> elements"
        )
    out = []
    for name in mech.actuated_joints:
        jm = mech.model.joints[mech.model.getJointId(name)]
        if jm.nv != 1 or jm.nq not in (1, 2):
            raise InvalidArgumentError(
                f"{mech.path}: actuated joint {name!r} ({jm.shortname()}) has {jm.nv} "
                "coordinates; valid: revolute, continuous or prismatic motors"
            )
        out.append(jm)
    return out


def _motor_values(mech: Mechanism, q: np.ndarray) -> np.ndarray:
    """Return the actuated coordinates of q, shape (na,) [rad or m], in
    ``mech.actuated_joints`` order (a continuous joint's angle from its cos, sin)."""
    return np.array(
        [
            q[jm.idx_q] if jm.nq == 1 else np.arctan2(q[jm.idx_q + 1], q[jm.idx_q])
            for jm in _motor_joints(mech)
        ]
    )


def _with_motors(mech: Mechanism, q: np.ndarray, motors: np.ndarray) -> np.ndarray:
    """Return q with the actuated coordinates set to ``motors`` [rad or m]."""
    q = q.copy()
    for jm, x in zip(_motor_joints(mech), motors, strict=True):
        if jm.nq == 1:
            q[jm.idx_q] = x
        else:
            q[jm.idx_q : jm.idx_q + 2] = np.cos(x), np.sin(x)
    return q


def _numbers(value) -> np.ndarray | None:
    """Return ``value`` as a float array, or None unless it holds numbers only (strings,
    dicts, bools and objects are refused, not converted)."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):  # ragged
        return None
    if array.dtype.kind not in "iuf":
        return None
    return array.astype(float)


def _check_motors(mech: Mechanism, motors) -> np.ndarray:
    na = len(_motor_joints(mech))
    m = _numbers(motors)
    if m is None or m.ndim > 1 or m.size != na or not np.all(np.isfinite(m)):
        raise InvalidArgumentError(
            f"motors must be {na} finite numbers [rad or m], one per actuated joint "
            f"({name_list(mech.actuated_joints, keep_order=True)}), got {shorten(motors)}"
        )
    return m.reshape(na)


def _frame_id(mech: Mechanism, frame: str) -> int:
    names = [f.name for f in mech.model.frames][1:]  # not the universe
    if not isinstance(frame, str) or frame not in names:
        raise UnknownChoiceError(f"{mech.name} frame", frame, names)
    return mech.model.getFrameId(frame)


def _output_jacobian(mech: Mechanism, fid: int, mode: str) -> np.ndarray:
    """The frame's Jacobian, shape (6 or 3, nv): LOCAL in 6d, the world-aligned linear
    rows in 3d, the LOCAL angular rows in orientation (``data`` holds the joint
    Jacobians at q)."""
    if mode == "6d":
        return frame_jacobian(mech.model, mech.data, fid, _LOCAL)
    if mode == "orientation":
        return frame_jacobian(mech.model, mech.data, fid, _LOCAL)[3:]
    return frame_jacobian(mech.model, mech.data, fid, _LWA)[:3]


@exclusive
def actuation_singularities(
    mech: Mechanism, q: np.ndarray, *, frame: str | None = None, mode: str = "6d"
) -> ActuationSingularities:
    """Return sigma_min of J_D (type II) and of a frame's output map (type I) at q.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        frame: the output frame (the platform, the end effector), or None (no serial
            measure).
        mode: ``"6d"``: the frame's placement is the output; ``"3d"``: its position;
            ``"orientation"``: its orientation.

    Returns:
        The two measures (:func:`closedchain.kinematics.actuation_sigma_min`).

    Raises:
        UnknownChoiceError: unknown frame or mode (lists the valid ones).
    """
    q = mech.check_q(q, "q")
    mode = resolve_choice("actuation-singularity mode", mode, IK_MODES)
    J = compute_jacobian(mech, q, backend="numpy")  # fills mech.data's joint Jacobians at q
    J_out = None
    if frame is not None:
        fid = _frame_id(mech, frame)
        pin.updateFramePlacements(mech.model, mech.data)
        J_out = _output_jacobian(mech, fid, mode)
    parallel, serial = actuation_sigma_min(J, mech.actuated_idx_v, J_output=J_out)
    return ActuationSingularities(parallel, serial, frame)


@exclusive
def forward_kinematics(
    mech: Mechanism,
    motors: np.ndarray,
    *,
    q_guess: np.ndarray | None = None,
    settings: AssemblySettings = DEFAULT_ASSEMBLY_SETTINGS,
    type_ii_rtol: float = TYPE_II_RTOL,
) -> ForwardKinematicsResult:
    """Close every loop with the actuated joints held at ``motors``.

    Args:
        mech: the mechanism.
        motors: the actuated coordinates, shape (na,) [rad or m], in the order of
            ``mech.actuated_joints``.
        q_guess: start of the assembly, shape (nq,) (default ``mech.q_ref``): the
            assembly mode reached is the one nearest to it.
        settings: tolerances of the assembly (:class:`closedchain.AssemblySettings`).
        type_ii_rtol: refuse a result with sigma_min(J_D) <= this times ||J||_2.

    Returns:
        The configuration, its closure residual and sigma_min of J_D.

    Raises:
        InvalidArgumentError: wrong number of motor values, or no actuated joint.
        AssemblyError: the motors admit no closed configuration near ``q_guess``.
        SingularConfigurationError: the result is at a type II (parallel) singularity.
    """
    check_settings("settings", settings, AssemblySettings)
    type_ii_rtol = check_positive("type_ii_rtol", type_ii_rtol, "the type II threshold [-]")
    m = _check_motors(mech, motors)
    q0 = mech.q_ref if q_guess is None else mech.check_q(q_guess, "q_guess")
    try:
        q = assemble(mech, _with_motors(mech, q0, m), fixed="actuated", settings=settings)
    except AssemblyError as exc:
        raise AssemblyError(
            f"{mech.name}: no closed configuration with motors "
            f"{', '.join(f'{n} = {x:.6g}' for n, x in zip(mech.actuated_joints, m, strict=True))}"
            f" near q_guess: {str(exc).removeprefix(f'{mech.name}: ')}",
            residual=exc.residual,
            q=exc.q,
        ) from None
    J = compute_jacobian(mech, q, backend="numpy")  # as actuation_singularities
    sigma, _ = actuation_sigma_min(J, mech.actuated_idx_v)
    scale = float(np.linalg.norm(J, 2)) if J.size else 0.0
    if sigma <= type_ii_rtol * scale:
        raise SingularConfigurationError.build(
            mech.name,
            "J_D (the constraint-Jacobian columns of the non-actuated coordinates)",
            q=q,
            cond=scale / sigma if sigma > 0 else float("inf"),
            bound=1.0 / type_ii_rtol,
            bound_name="1 / type_ii_rtol",
            hint="a type II (parallel) singularity: the motors "
            + ", ".join(mech.actuated_joints)
            + " do not determine the motion here",
        )
    res = closure_error(mech.model, mech.data, mech.declared, q)
    return ForwardKinematicsResult(q, _motor_values(mech, q), res, sigma)


def _task(mech: Mechanism, fid: int, target: pin.SE3, mode: str) -> Callable:
    """The frame-error rows of :func:`inverse_kinematics` for ``_least_squares``."""

    def task(model, data, jacobian: bool):
        oMf = pin.updateFramePlacement(model, data, fid)
        if mode == "6d":
            err = target.actInv(oMf)
            eps = pin.log6(err).vector
            E = pin.Jlog6(err) @ _output_jacobian(mech, fid, mode) if jacobian else None
        elif mode == "orientation":
            err = target.rotation.T @ oMf.rotation
            eps = pin.log3(err)
            E = pin.Jlog3(err) @ _output_jacobian(mech, fid, mode) if jacobian else None
        else:
            eps = oMf.translation - target.translation
            E = _output_jacobian(mech, fid, mode) if jacobian else None
        return eps, E

    return task


def _check_se3(name: str, M: pin.SE3) -> pin.SE3:
    """Return ``M``; raise InvalidArgumentError unless it is finite with a rotation matrix
    (orthonormal to :data:`ROTATION_TOL`, determinant +1)."""
    R, p = M.rotation, M.translation
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(p))):
        raise InvalidArgumentError(
            f"{name} must be a finite pinocchio.SE3, got rotation {_one_line(R)} and "
            f"translation {_one_line(p)}"
        )
    error = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if error > ROTATION_TOL or np.linalg.det(R) < 0:
        raise InvalidArgumentError(
            f"{name}'s rotation must be a rotation matrix (R^T R = I to {ROTATION_TOL:g}, "
            f"det R = +1), got max |R^T R - I| = {error:.3g}, det R = {np.linalg.det(R):.6g}; "
            "pinocchio.SE3(R, p) with R from pinocchio.rpy.rpyToMatrix or "
            "pinocchio.Quaternion(...).matrix()"
        )
    return M


def _check_target(target, mode: str) -> pin.SE3:
    if isinstance(target, pin.SE3):
        return _check_se3("target", target)
    if mode == "orientation":
        return pin.SE3(_rotation_target(target), np.zeros(3))
    p = _numbers(target) if mode == "3d" else None
    if p is None or p.shape != (3,) or not np.all(np.isfinite(p)):
        valid = "a pinocchio.SE3" + (" or a position, shape (3,) [m]" if mode == "3d" else "")
        raise InvalidArgumentError(
            f"target of mode {mode!r} must be {valid}, got {shorten(target)}"
        )
    return pin.SE3(np.eye(3), p)


def _rotation_target(target) -> np.ndarray:
    """A target of mode ``"orientation"``: a rotation matrix, shape (3, 3)."""
    try:
        R = None if isinstance(target, (str, dict)) else np.asarray(target, dtype=float)
    except (TypeError, ValueError):
        R = None
    if (
        R is None
        or R.shape != (3, 3)
        or not np.all(np.isfinite(R))
        or not np.allclose(R.T @ R, np.eye(3), atol=IK_ROTATION_TOL)
        or np.linalg.det(R) <= 0
    ):
        raise InvalidArgumentError(
            "target of mode 'orientation' must be a pinocchio.SE3 (its rotation counts) or "
            f"a rotation matrix, shape (3, 3), got {shorten(target)}"
        )
    return R


def _limits_reached(mech: Mechanism, q: np.ndarray, lower, upper) -> list[str]:
    """The coordinates at a limit at q (within IK_LIMIT_TOL), as ``"name at its lower
    limit 0.2"``; ``lower``, ``upper``: the limits per velocity coordinate (``_free_bounds``
    of every coordinate)."""
    model = mech.model
    idx_q = np.asarray(model.idx_qs)[np.repeat(np.arange(model.njoints), np.asarray(model.nvs))]
    out = []
    for i, name in enumerate(mech.coordinate_names):
        for side, bound in (("lower", lower[i]), ("upper", upper[i])):
            if np.isfinite(bound) and abs(q[idx_q[i]] - bound) <= IK_LIMIT_TOL:
                out.append(f"{name} at its {side} limit {bound:g}")
    return out


@exclusive
def inverse_kinematics(
    mech: Mechanism,
    frame: str,
    target: pin.SE3 | np.ndarray,
    *,
    q_guess: np.ndarray | None = None,
    mode: str = "6d",
    tol: float = IK_TOL,
    max_nfev: int = IK_MAX_NFEV,
    settings: AssemblySettings = DEFAULT_ASSEMBLY_SETTINGS,
) -> InverseKinematicsResult:
    """Find a configuration with every loop closed and ``frame`` at ``target``.

    A trust-region least-squares solve (``scipy.optimize.least_squares``, ``trf``, exact
    Jacobians) of the stacked closure residual and frame error over every coordinate,
    in the chart ``q_guess (+) x`` (``pin.integrate``), within the joint limits.

    Args:
        mech: the mechanism.
        frame: name of the frame to place (a link, a loop side ``"P::predecessor"``).
        target: its placement in the world (``pin.SE3``); in 3d its position, shape (3,)
            [m], or an SE3 whose translation counts; in orientation its rotation
            matrix, shape (3, 3), or an SE3 whose rotation counts.
        q_guess: start, shape (nq,) (default ``mech.q_ref``): the working mode reached
            is the one nearest to it.
        mode: ``"6d"`` (placement), ``"3d"`` (position) or ``"orientation"``
            (rotation only, the position free).
        tol: largest frame error accepted, max |epsilon| [m or rad].
        max_nfev: residual evaluations of the solve.
        settings: ``closure_tol`` (largest closure residual accepted [m or rad]) and
            ``lsq_tol`` (the solve's ftol, xtol, gtol).

    Returns:
        The configuration, its motor values and residuals.

    Raises:
        UnknownChoiceError: unknown frame or mode (lists the valid ones).
        InvalidArgumentError: a target of the wrong kind.
        AssemblyError: the target is out of reach from ``q_guess``: the message gives
            the frame, the residuals reached, the joint limits that stop the solve
            (the joints at a limit at the end; none: the linkage's own reach or another
            working mode), and ``exc.q`` their configuration.
    """
    check_settings("settings", settings, AssemblySettings)
    tol = check_positive("tol", tol, "the largest frame error [m or rad]")
    max_nfev = check_count("max_nfev", max_nfev, "residual evaluations of the solve")
    mode = resolve_choice("inverse-kinematics mode", mode, IK_MODES)
    fid = _frame_id(mech, frame)
    target = _check_target(target, mode)
    q0 = mech.q_ref if q_guess is None else mech.check_q(q_guess, "q_guess")
    model = mech.model
    free = np.arange(mech.nv)
    bounds = (model.lowerPositionLimit, model.upperPositionLimit)
    lower, upper = _free_bounds(model, free, bounds)
    q0 = _clip_into(model, q0, free, lower, upper)
    task = _task(mech, fid, target, mode)
    lsq = replace(settings, max_iter=max_nfev)
    q = _least_squares(model, mech.data, mech.declared, q0, free, lsq, lower, upper, task=task)
    res = closure_error(model, mech.data, mech.declared, q)
    err = float(np.max(np.abs(task(model, mech.data, False)[0])))
    if res > settings.closure_tol or err > tol:
        limits = _limits_reached(mech, q, lower, upper)
        stop = (
            "stopped by the joint limits: " + ", ".join(limits)
            if limits
            else "no joint at a limit: beyond the linkage's reach from q_guess"
        )
        raise AssemblyError(
            f"{mech.name}: frame {frame!r} cannot reach the target ({mode}) from q_guess: "
            f"frame error {err:.3e} (tol {tol:.1e}), closure residual {res:.3e} "
            f"(closure_tol {settings.closure_tol:.1e}); {stop}",
            residual=max(res, err),
            q=q,
        )
    return InverseKinematicsResult(q, _motor_values(mech, q), res, frame, mode, err)
