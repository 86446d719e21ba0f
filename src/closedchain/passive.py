r"""Passive joint terms: springs, viscous damping and armature, as terms of the dynamics.

Every reader fills :class:`~closedchain.urdf.JointSpring`,
:class:`~closedchain.urdf.JointDamping` and :class:`~closedchain.urdf.JointArmature`
(``MechanismDescription.springs``, ``dampings``, ``armatures``); :func:`closedchain.load` turns
them into the mechanism's :class:`PassiveTerms` and the model's armature. The
equations of motion every method, integrator and the inverse dynamics solve are then

.. math::

    (M(q) + \operatorname{diag}(r))\, a + h(q, v) = \tau + \tau_p(q, v) + J^\top \lambda,
    \qquad
    \tau_p(q, v) = -K (q - q_0) - D v,

MuJoCo's and Pinocchio's conventions: the armature r (a motor rotor's reflected
inertia [kg m^2 or kg]) on the diagonal of the mass matrix (Pinocchio's
``model.armature``: ``crba``, ``aba``, ``rnea`` and the kinetic energy include it);
K the joint springs' stiffness on their coordinate [N m/rad or N/m], q_0 their
reference; D the viscous damping per velocity coordinate [N m s/rad or N s/m]
(MuJoCo's ``qfrc_passive`` without friction loss). The methods take
:math:`h - \tau_p` as their bias forces, so a caller of
:func:`~closedchain.forward_dynamics` or :func:`~closedchain.simulate` passes only
the actuators' ``tau``.

Energy: the springs' potential :math:`\tfrac12 (q - q_0)^\top K (q - q_0)` is part of
the mechanical energy a simulation records; the damping does the work
:math:`-\int v^\top D v\, dt \le 0`, recorded with the work of ``tau`` (so
``Trajectory.energy_balance`` stays zero for an exact solution of a damped motion).

Friction loss (URDF ``<dynamics friction>``, MJCF ``frictionloss``) is not modelled:
the readers name it in a log line.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .exceptions import ModelFileError
from .urdf import MechanismDescription, name_list

__all__ = ["PassiveTerms", "passive_terms"]


@dataclass(frozen=True)
class PassiveTerms:
    r"""The joint springs and viscous damping of a mechanism, and its armature.

    Attributes:
        spring_idx_q: configuration index of each spring's joint, shape (ns,).
        spring_idx_v: its velocity index, shape (ns,).
        stiffness: K, shape (ns,) [N m/rad or N/m].
        reference: q_0, shape (ns,) [rad or m].
        damping: D per velocity coordinate, shape (nv,) [N m s/rad or N s/m].
        armature: r per velocity coordinate, shape (nv,) [kg m^2 or kg] (the
            model's ``armature``, set by :func:`passive_terms`).
        armature_joints: ``(joint index, velocity slice)`` of the joints with armature.
    """

    spring_idx_q: np.ndarray
    spring_idx_v: np.ndarray
    stiffness: np.ndarray
    reference: np.ndarray
    damping: np.ndarray
    armature: np.ndarray
    armature_joints: tuple[tuple[int, slice], ...] = ()

    @property
    def has_springs(self) -> bool:
        """True when a spring of nonzero stiffness acts."""
        return bool(np.any(self.stiffness != 0.0))

    @property
    def has_damping(self) -> bool:
        """True when a joint is damped."""
        return bool(np.any(self.damping != 0.0))

    @property
    def acts(self) -> bool:
        """True when tau_p is not identically zero (springs or damping)."""
        return self.has_springs or self.has_damping

    def spring_force(self, q: np.ndarray) -> np.ndarray:
        """Return -K (q - q_0), shape (nv,) [N m or N], at q (shape (nq,))."""
        out = np.zeros(len(self.damping))
        out[self.spring_idx_v] = -self.stiffness * (q[self.spring_idx_q] - self.reference)
        return out

    def force(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return tau_p = -K (q - q_0) - D v, shape (nv,) [N m or N], at (q, v)."""
        return self.spring_force(q) - self.damping * v

    def added_to(self, tau: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return tau + tau_p(q, v), shape (nv,) [N m or N] (``tau`` itself when no spring
        or damper acts): the generalized force to give Pinocchio's ``aba`` or
        ``constraintDynamics``, which have no springs or damping."""
        return tau + self.force(q, v) if self.acts else tau

    def subtract_from_bias(self, q: np.ndarray, v: np.ndarray, h: np.ndarray) -> None:
        """Set h to h - tau_p(q, v) in place (the bias forces the methods solve with)."""
        if self.acts:
            h[self.spring_idx_v] += self.stiffness * (q[self.spring_idx_q] - self.reference)
            h += self.damping * v

    def kinetic_energy(self, model: pin.Model, data: pin.Data, q: np.ndarray, v: np.ndarray):
        r"""Return the kinetic energy :math:`\tfrac12 v^\top (M + \operatorname{diag}(r))
        v` [J] at (q, v) (shapes (nq,), (nv,)).

        Pinocchio 4.1's ``computeKineticEnergy`` adds :math:`\tfrac12 r_j \dot q_j^2`
        with the joint data's velocity, which a revolute joint about an unaligned axis
        leaves at 0: its armature's part is taken from v here.
        """
        T = pin.computeKineticEnergy(model, data, q, v)
        for j, cols in self.armature_joints:
            vj, counted = v[cols], np.asarray(data.joints[j].joint_v)
            T += 0.5 * float(self.armature[cols] @ (vj * vj - counted * counted))
        return T

    def spring_energy(self, q: np.ndarray) -> float:
        r"""Return the springs' potential :math:`\tfrac12 \sum_j k_j (q_j - q_{0,j})^2` [J]."""
        dq = q[self.spring_idx_q] - self.reference
        return 0.5 * float(self.stiffness @ (dq * dq))

    def spring_energies(self, q: np.ndarray) -> np.ndarray:
        """Return :meth:`spring_energy` at each row of q (shape (N, nq)), shape (N,) [J]."""
        dq = np.asarray(q)[:, self.spring_idx_q] - self.reference
        return 0.5 * (dq * dq) @ self.stiffness


def _joint(model: pin.Model, urdf: MechanismDescription, name: str, what: str, line: int):
    """The model's joint ``name``, or ModelFileError naming the element and the valid joints."""
    if not model.existJointName(name):
        at = f"line {line}: " if line else ""
        raise ModelFileError(
            f"{urdf.path}: {at}{what} names joint {name!r}, which is not a joint of the tree; "
            f"joints: {name_list(tuple(model.names[1:]))}"
        )
    return model.joints[model.getJointId(name)]


def _per_coordinate(model: pin.Model, urdf: MechanismDescription, entries, attr: str) -> np.ndarray:
    """One value per velocity coordinate from ``entries`` (JointDamping or JointArmature):
    each joint's value on all its coordinates, 0 elsewhere; a joint named twice is refused."""
    out = np.zeros(model.nv)
    seen: set[str] = set()
    for e in entries:
        if e.joint in seen:
            raise ModelFileError(f"{urdf.path}: joint {e.joint!r} has more than one {attr}")
        seen.add(e.joint)
        value = float(getattr(e, attr))
        if not (np.isfinite(value) and value >= 0.0):
            raise ModelFileError(
                f"{urdf.path}: {attr} of joint {e.joint!r} is {value!r}; valid: a finite "
                "number >= 0"
            )
        jm = _joint(model, urdf, e.joint, attr, e.line)
        out[jm.idx_v : jm.idx_v + jm.nv] = value
    return out


def passive_terms(model: pin.Model, urdf: MechanismDescription) -> PassiveTerms:
    """Return the mechanism's passive terms, and set ``model.armature`` and ``model.damping``.

    Args:
        model: the Pinocchio model built from ``urdf`` (its ``armature`` and ``damping``,
            shape (nv,), are overwritten with the file's; Pinocchio's ``crba``, ``aba``,
            ``rnea`` and kinetic energy add the armature to M's diagonal).
        urdf: the reader's description (``springs``, ``dampings``, ``armatures``).

    Raises:
        ModelFileError: a term names no joint of the tree, a spring's joint is not a
            1-dof joint, a joint has two values of one term, or a value is negative
            or not finite (the message names the joint and the valid joints).
    """
    idx_q, idx_v, k, ref = [], [], [], []
    seen: set[str] = set()
    for s in urdf.springs:
        if s.joint in seen:
            raise ModelFileError(f"{urdf.path}: joint {s.joint!r} has more than one spring")
        seen.add(s.joint)
        jm = _joint(model, urdf, s.joint, "a spring", s.line)
        if not (jm.nq == jm.nv == 1):
            raise ModelFileError(
                f"{urdf.path}: the spring of joint {s.joint!r} needs one coordinate without "
                f"wrap-around; this joint is {jm.shortname()} (nq = {jm.nq}, nv = {jm.nv})"
            )
        if not (np.isfinite(s.stiffness) and s.stiffness >= 0.0 and np.isfinite(s.reference)):
            raise ModelFileError(
                f"{urdf.path}: the spring of joint {s.joint!r} has stiffness {s.stiffness!r} "
                f"and reference {s.reference!r}; valid: finite, stiffness >= 0"
            )
        idx_q.append(jm.idx_q)
        idx_v.append(jm.idx_v)
        k.append(s.stiffness)
        ref.append(s.reference)
    damping = _per_coordinate(model, urdf, urdf.dampings, "damping")
    armature = _per_coordinate(model, urdf, urdf.armatures, "armature")
    armature_joints = tuple(
        (j, slice(jm.idx_v, jm.idx_v + jm.nv))
        for j, jm in enumerate(model.joints)
        if j > 0 and np.any(armature[jm.idx_v : jm.idx_v + jm.nv])
    )
    model.armature = armature.copy()
    model.damping = damping.copy()
    return PassiveTerms(
        spring_idx_q=np.array(idx_q, dtype=int),
        spring_idx_v=np.array(idx_v, dtype=int),
        stiffness=np.array(k, dtype=float),
        reference=np.array(ref, dtype=float),
        damping=damping,
        armature=armature,
        armature_joints=armature_joints,
    )
