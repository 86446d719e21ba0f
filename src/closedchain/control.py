r"""Computed-torque control of closed chains: a ``tau(t, q, v)`` for :func:`simulate`.

The controller prescribes the accelerations of ``mobility`` coordinates P
(the independent ones, or e.g. a platform's orientation joints) as the
reference acceleration plus a PD correction,

.. math::

    a_P^\star = \ddot q_P^{ref}(t) + K_d (\dot q_P^{ref}(t) - v_P)
                + K_p (q_P^{ref}(t) - q_P),

and returns the actuator torques that produce them by closed-chain inverse
dynamics (:func:`closedchain.inverse_dynamics`). With an exact model the
tracking error e = q_P^ref - q_P obeys :math:`\ddot e + K_d \dot e + K_p e = 0`,
so it stays at the level of the integration error.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ._locking import exclusive
from .dynamics.base import DEFAULT_SETTINGS, SolverSettings
from .exceptions import ClosedChainError, check_settings
from .inverse import _resolve_ordered, inverse_dynamics

if TYPE_CHECKING:
    from .mechanism import Mechanism
    from .urdf import SinusoidSpec

__all__ = [
    "Scene",
    "computed_torque_controller",
    "default_scene",
    "gravity_torque",
    "sinusoid_reference",
    "spring_torque",
]

#: A reference: t [s] -> (q_P, v_P, a_P), each of shape (mobility,) [rad, rad/s, rad/s^2].
Reference = Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]


@exclusive
def computed_torque_controller(
    mech: Mechanism,
    reference: Reference,
    *,
    kp: float,
    kd: float,
    coordinates: Iterable[str | int] | str = "independent",
    settings: SolverSettings = DEFAULT_SETTINGS,
) -> Callable[[float, np.ndarray, np.ndarray], np.ndarray]:
    """Build a computed-torque (inverse dynamics + PD) controller ``tau(t, q, v)``.

    Args:
        mech: the mechanism; the controlled coordinates must be 1-dof joints
            (one entry of q and one of v each).
        reference: ``reference(t) -> (q_P, v_P, a_P)``, each of shape
            (mobility,) [rad, rad/s, rad/s^2 or m, m/s, m/s^2], in the order
            of ``coordinates``.
        kp: position gain [1/s^2].
        kd: velocity gain [1/s]; ``kd = 2 sqrt(kp)`` is critically damped.
        coordinates: the controlled coordinates, as ``coordinates`` of
            :func:`closedchain.inverse_dynamics`: ``"independent"`` or
            ``mobility`` joint names / velocity indices.
        settings: settings of the inverse dynamics (condition-number bounds).

    Returns:
        ``tau(t, q, v) -> (nv,)``: generalized forces [N m or N], nonzero only
        at the actuated coordinates; pass it as ``tau`` to :func:`simulate`.

    Raises:
        ClosedChainError: a controlled coordinate is not a 1-dof joint, or
            the number of coordinates is not the mobility.
    """
    check_settings("settings", settings, SolverSettings)
    idx_v = _resolve_ordered(mech, coordinates, "coordinates")
    if len(idx_v) != mech.mobility:
        raise ClosedChainError(
            f"{mech.name}: computed-torque control needs exactly {mech.mobility} coordinates "
            f"(the mobility), got {len(idx_v)}"
        )
    v_to_q = {}
    for joint in mech.model.joints[1:]:
        if joint.nq == 1 and joint.nv == 1:
            v_to_q[joint.idx_v] = joint.idx_q
    missing = [mech.coordinate_names[i] for i in idx_v if int(i) not in v_to_q]
    if missing:
        raise ClosedChainError(
            f"{mech.name}: computed-torque control needs 1-dof joints; not one: {missing}"
        )
    idx_q = np.array([v_to_q[int(i)] for i in idx_v], dtype=int)
    names = [mech.coordinate_names[i] for i in idx_v]
    kp, kd = float(kp), float(kd)

    def tau(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        # An overflow at a runaway state is reported by inverse_dynamics' finiteness
        # checks (NonFiniteError naming v and a_cmd), not as a RuntimeWarning.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            q_ref, v_ref, a_ref = (np.asarray(x, dtype=float) for x in reference(t))
            a_cmd = a_ref + kd * (v_ref - v[idx_v]) + kp * (q_ref - q[idx_q])
            return inverse_dynamics(mech, q, v, a_cmd, coordinates=names, settings=settings).tau

    return tau


def spring_torque(mech: Mechanism, q: np.ndarray) -> np.ndarray:
    r"""Return the generalized forces of the mechanism's joint springs at q.

    .. math::

        \tau_{s,j} = -k_j\, (q_j - q_{0,j})

    on each joint j with a spring (:class:`closedchain.urdf.JointSpring`: URDF
    ``<dynamics spring_stiffness spring_reference>``, SDF and MJCF springs), zero
    elsewhere. The springs are a term of the dynamics (:mod:`closedchain.passive`):
    :func:`forward_dynamics`, :func:`simulate` and :func:`inverse_dynamics` apply them
    without being given this force; it is here to be read.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).

    Returns:
        tau_s, shape (nv,) [N m or N].
    """
    return mech.passive.spring_force(mech.check_q(q, "q"))


@exclusive
def gravity_torque(
    mech: Mechanism, q: np.ndarray, *, settings: SolverSettings = DEFAULT_SETTINGS
) -> np.ndarray:
    """Return the actuator torques that hold the mechanism at rest at q against gravity.

    Closed-chain inverse dynamics (:func:`closedchain.inverse_dynamics`) with
    v = 0 and zero accelerations, the joint springs' forces
    (:func:`spring_torque`, a term of the dynamics) acting besides the actuators: a
    constant ``tau`` under which q is an equilibrium (not necessarily a stable one)
    of :func:`simulate`.

    Args:
        mech: the mechanism (its actuators must control every degree of freedom).
        q: assembled configuration, shape (nq,).
        settings: settings of the inverse dynamics.

    Returns:
        tau, shape (nv,) [N m or N], zero off the actuated coordinates.
    """
    check_settings("settings", settings, SolverSettings)
    zero_v = np.zeros(mech.nv)
    return inverse_dynamics(mech, q, zero_v, np.zeros(mech.mobility), settings=settings).tau


def sinusoid_reference(specs: Sequence[SinusoidSpec]) -> Reference:
    """Return ``reference(t) -> (q, v, a)`` of ``offset + amplitude sin(2 pi frequency t)``."""
    c = np.array([s.offset for s in specs], dtype=float)
    amp = np.array([s.amplitude for s in specs], dtype=float)
    w = 2.0 * np.pi * np.array([s.frequency for s in specs], dtype=float)

    def reference(t: float):
        sin, cos = np.sin(w * t), np.cos(w * t)
        return c + amp * sin, amp * w * cos, -amp * w * w * sin

    return reference


@dataclass(frozen=True)
class Scene:
    """The initial state and inputs of a mechanism's default scene.

    Attributes:
        q0: initial configuration, shape (nq,), assembled (phi = 0).
        v0: initial velocity, shape (nv,), with J v0 = 0.
        tau: generalized forces for :func:`simulate` (None: passive).
        description: one line saying what the scene shows.
    """

    q0: np.ndarray
    v0: np.ndarray
    tau: Callable[[float, np.ndarray, np.ndarray], np.ndarray] | None
    description: str


def default_scene(mech: Mechanism) -> Scene:
    """Return the mechanism's default scene, from its URDF's ``<scene>`` element.

    Without one: released from rest at ``q_ref``. With one: the ``<initial>``
    values are a guess assembled onto phi = 0 holding the tracked joints at
    their reference (else the independent coordinates); their ``velocity=``
    values (passive scenes) are held while the other coordinates take the
    velocity with J v = 0 (else the scene starts from rest); with a ``<track>``,
    the computed-torque controller drives the tracked joints along their
    sinusoids from a matching initial velocity.

    Raises:
        ClosedChainError: the scene cannot be assembled, its tracked joints
            are not ``mobility`` many, or a sinusoid's peak position, velocity or
            acceleration overflows (the message names the file).
    """
    from .kinematics import assemble, project_velocity

    spec = mech.description.scene
    if spec is None:
        return Scene(mech.q_ref.copy(), np.zeros(mech.nv), None, "released from rest at q_ref")
    q = mech.q_ref.copy()
    for name, value in spec.initial.items():
        q[mech.model.joints[mech.model.getJointId(name)].idx_q] = value
    mech.check_limits(q, "<scene> <initial>")
    if not spec.track:
        q0 = assemble(mech, q, fixed="independent")
        if not spec.velocity:
            return Scene(q0, np.zeros(mech.nv), None, "released from rest (<scene> initial)")
        v = np.zeros(mech.nv)
        for name, rate in spec.velocity.items():
            v[mech.model.joints[mech.model.getJointId(name)].idx_v] = rate
        v0 = project_velocity(mech, q0, v, fixed=list(spec.velocity))
        given = ", ".join(f"{n} = {r:g}" for n, r in spec.velocity.items())
        return Scene(q0, v0, None, f"passive motion from <scene> initial velocity ({given})")
    names = [s.joint for s in spec.track]
    if len(names) != mech.mobility:
        raise ClosedChainError(
            f"{mech.path}: line {spec.line}: <scene> <track> drives {len(names)} joints "
            f"({', '.join(names)}); it needs the mobility, {mech.mobility}"
        )
    for s in spec.track:
        # Python floats: an overflow gives inf here, not a numpy RuntimeWarning later.
        w = 2.0 * math.pi * s.frequency
        peaks = (abs(s.offset) + abs(s.amplitude), abs(s.amplitude) * w, abs(s.amplitude) * w * w)
        if not all(math.isfinite(x) for x in peaks):
            raise ClosedChainError(
                f"{mech.path}: line {spec.line}: <scene> <sinusoid joint={s.joint!r}>: "
                f"offset {s.offset:g}, amplitude {s.amplitude:g}, frequency {s.frequency:g} Hz "
                "overflow the reference's position, velocity or acceleration; valid: values "
                "whose amplitude (2 pi frequency)^2 is a finite number"
            )
    reference = sinusoid_reference(spec.track)
    q_ref0, v_ref0, _ = reference(0.0)
    idx = [mech.model.joints[mech.model.getJointId(n)] for n in names]
    q[[j.idx_q for j in idx]] = q_ref0
    q0 = assemble(mech, q, fixed=names)
    v = np.zeros(mech.nv)
    v[[j.idx_v for j in idx]] = v_ref0
    v0 = project_velocity(mech, q0, v, fixed=names)
    tau = computed_torque_controller(mech, reference, kp=spec.kp, kd=spec.kd, coordinates=names)
    return Scene(q0, v0, tau, f"computed-torque tracking of sinusoids on {', '.join(names)}")
