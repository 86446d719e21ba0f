"""Build the Pinocchio model of a :class:`~closedchain.description.MechanismDescription`.

One depth-first pass over the bodies (every parent before its children, as
Pinocchio's algorithms need joints numbered): each joint with
``Model.addJoint`` and a JOINT frame, each body's inertia with
``appendBodyToJoint`` and a BODY frame named after it, each site as an
OP_FRAME. A body whose joints sit at anchor p with reference q0 gets

.. math::

    {}^{parent}M_{joint} = X \\, T(p), \\qquad
    {}^{joint}M_{body} = S(q_0)^{-1} \\, T(-p),

so that at q = q0 it sits at its placement X and turns about its anchor
(MuJoCo's rule for several joints in one body: each joint moves the frame the
previous ones left). The world is Pinocchio's universe, with a BODY frame
:data:`closedchain.urdf.WORLD_LINK`.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from .description import JOINT_KINDS, JointDescription, MechanismDescription
from .exceptions import URDFError
from .urdf import WORLD_LINK

__all__ = [
    "build_model",
    "configuration",
    "joint_model",
]

#: Tolerance on an axis' components to use Pinocchio's axis-aligned joints [-].
ALIGNED_TOL = 1e-15


def joint_model(joint: JointDescription):
    """Return the Pinocchio joint model of a joint description."""
    if joint.kind == "spherical":
        return pin.JointModelSpherical()
    if joint.kind == "free":
        return pin.JointModelFreeFlyer()
    axis = np.asarray(joint.axis, dtype=float)
    revolute = joint.kind == "revolute"
    for k, aligned in enumerate(
        (pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ)
        if revolute
        else (pin.JointModelPX, pin.JointModelPY, pin.JointModelPZ)
    ):
        if np.linalg.norm(axis - np.eye(3)[k]) <= ALIGNED_TOL:
            return aligned()
    return (
        pin.JointModelRevoluteUnaligned(axis)
        if revolute
        else pin.JointModelPrismaticUnaligned(axis)
    )


def _motion(joint: JointDescription) -> pin.SE3:
    """Return the joint's motion S(q0) (a revolute, prismatic or spherical joint)."""
    axis = np.asarray(joint.axis, dtype=float)
    if joint.kind == "revolute":
        return pin.SE3(pin.exp3(axis * joint.q0[0]), np.zeros(3))
    if joint.kind == "prismatic":
        return pin.SE3(np.eye(3), axis * joint.q0[0])
    x, y, z, w = joint.q0
    return pin.SE3(pin.Quaternion(w, x, y, z).normalized().matrix(), np.zeros(3))


def _shift(p) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(p, dtype=float))


def build_model(description: MechanismDescription, root_joint=None) -> pin.Model:
    """Return the Pinocchio model of a mechanism description (see the module docstring).

    Args:
        description: the tree.
        root_joint: a Pinocchio joint model between the world and the top-level
            bodies (named ``root_joint``), or None (fixed).

    Raises:
        URDFError: a free joint below the top level or beside other joints, a
            body whose parent is not described before it, or a duplicate name.
    """
    where = description.path
    model = pin.Model()
    model.name = description.name
    world = model.addFrame(
        pin.Frame(WORLD_LINK, 0, 0, pin.SE3.Identity(), pin.FrameType.BODY), False
    )
    top = 0
    top_frame = world
    if root_joint is not None:
        top = model.addJoint(0, root_joint, pin.SE3.Identity(), "root_joint")
        top_frame = model.addJointFrame(top, world)
    #: body name -> (joint id, body frame in the joint frame, BODY frame id)
    bodies: dict[str, tuple[int, pin.SE3, int]] = {WORLD_LINK: (0, pin.SE3.Identity(), world)}
    joint_names: set[str] = set()
    for body in description.bodies:
        if body.name in bodies:
            raise URDFError(f"{where}: body name {body.name!r} is used more than once")
        if body.parent not in bodies:
            raise URDFError(
                f"{where}: body {body.name!r}: parent {body.parent!r} is not described before it"
            )
        parent, pX, parent_frame = bodies[body.parent]
        if body.parent == WORLD_LINK:
            parent, parent_frame = top, top_frame
        X = pX * body.placement
        for joint in body.joints:
            if joint.kind not in JOINT_KINDS:
                raise URDFError(
                    f"{where}: joint {joint.name!r}: kind {joint.kind!r}; valid: "
                    f"{', '.join(JOINT_KINDS)}"
                )
            if joint.name in joint_names or joint.name == "root_joint" and root_joint is not None:
                raise URDFError(f"{where}: joint name {joint.name!r} is used more than once")
            joint_names.add(joint.name)
            jmodel = joint_model(joint)
            if joint.kind == "free":
                if body.parent != WORLD_LINK or len(body.joints) != 1 or root_joint is not None:
                    raise URDFError(
                        f"{where}: joint {joint.name!r}: a free joint must be the only joint of "
                        "a top-level body (and the model has no root joint)"
                    )
                placement, X = pin.SE3.Identity(), pin.SE3.Identity()
            else:
                placement = X * _shift(joint.position)
                X = _motion(joint).inverse() * _shift(-np.asarray(joint.position, dtype=float))
            if joint.kind in ("revolute", "prismatic"):
                parent = model.addJoint(
                    parent,
                    jmodel,
                    placement,
                    joint.name,
                    np.zeros(1),
                    np.zeros(1),
                    np.array([joint.lower]),
                    np.array([joint.upper]),
                )
            else:
                parent = model.addJoint(parent, jmodel, placement, joint.name)
            parent_frame = model.addJointFrame(parent, parent_frame)
        model.appendBodyToJoint(parent, body.inertia, X)
        frame = model.addBodyFrame(body.name, parent, X, parent_frame)
        bodies[body.name] = (parent, X, frame)
    for site in description.sites:
        if site.body not in bodies:
            raise URDFError(f"{where}: site {site.name!r}: body {site.body!r} is not described")
        joint, X, frame = bodies[site.body]
        model.addFrame(
            pin.Frame(site.name, joint, frame, X * site.placement, pin.FrameType.OP_FRAME), False
        )
    return model


def configuration(model: pin.Model, values: dict[str, tuple[float, ...]]) -> np.ndarray:
    """Return the neutral configuration with the given joints' values set.

    Args:
        model: the built model.
        values: joint name -> its configuration entries (Pinocchio's convention).

    Raises:
        URDFError: a joint the model lacks, or values of the wrong length.
    """
    q = pin.neutral(model)
    for name, vals in values.items():
        if not model.existJointName(name):
            raise URDFError(f"joint {name!r} is not a joint of the model {model.name!r}")
        joint = model.joints[model.getJointId(name)]
        if len(vals) != joint.nq:
            raise URDFError(
                f"joint {name!r}: {len(vals)} values for its {joint.nq} configuration entries"
            )
        q[joint.idx_q : joint.idx_q + joint.nq] = vals
    return q
