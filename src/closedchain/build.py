"""Build the Pinocchio model of a :class:`~closedchain.description.TreeDescription`.

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
:data:`closedchain.urdf.WORLD_LINK` when the description asks for one (MJCF).

What Pinocchio's URDF reader (``pinocchio.buildModelFromUrdf``) makes of a URDF
tree, this builder makes of its description (``tests/test_build.py`` compares
the two): a continuous joint is a RevoluteUnbounded joint (cos, sin in q,
within +-:data:`UNIT_ENTRY_BOUND`), a body welded by a fixed joint gets a
FIXED_JOINT frame named after the joint (holding the body's inertia) and its
BODY frame below it, its inertia appended to the parent's joint, and an axis
along +x, +y or +z gives the axis-aligned joint (any other, the unaligned one).
"""

from __future__ import annotations

import functools

import numpy as np
import pinocchio as pin

from .description import JOINT_KINDS, LIMITED_KINDS, JointDescription, TreeDescription
from .exceptions import ModelFileError
from .urdf import WORLD_LINK, check_tree_size

__all__ = [
    "build_model",
    "check_size",
    "configuration",
    "joint_model",
]

#: Tolerance on an axis' components to use Pinocchio's axis-aligned joints [-].
ALIGNED_TOL = 1e-15

#: Bound Pinocchio's URDF reader puts on the unit-complex entries (cos, sin) of a
#: continuous or planar joint and the quaternion entries of a floating one [-].
UNIT_ENTRY_BOUND = 1.01

#: Axis-aligned joint models of each one-axis kind (x, y, z), and the unaligned one.
_ALIGNED = {
    "revolute": (pin.JointModelRX, pin.JointModelRY, pin.JointModelRZ),
    "prismatic": (pin.JointModelPX, pin.JointModelPY, pin.JointModelPZ),
    "continuous": (pin.JointModelRUBX, pin.JointModelRUBY, pin.JointModelRUBZ),
}


@functools.lru_cache(maxsize=64)
def _unbounded_unaligned(axis: tuple[float, float, float]):
    """Return Pinocchio's RevoluteUnboundedUnaligned joint model about a unit axis.

    Pinocchio 4.1's Python bindings construct this joint only with its default
    axis, so it is taken from Pinocchio's URDF reader given a one-joint tree (a
    text written here from three numbers: nothing of the user's file).
    """
    xyz = " ".join(repr(float(a)) for a in axis)
    text = (
        '<robot name="axis"><link name="a"/><link name="b"/>'
        '<joint name="j" type="continuous"><parent link="a"/><child link="b"/>'
        f'<axis xyz="{xyz}"/></joint></robot>'
    )
    return pin.buildModelFromXML(text).joints[1]


def joint_model(joint: JointDescription):
    """Return the Pinocchio joint model of a joint description."""
    if joint.kind == "spherical":
        return pin.JointModelSpherical()
    if joint.kind in ("free", "floating"):
        return pin.JointModelFreeFlyer()
    if joint.kind == "universal":
        first, second = np.asarray(joint.axis, dtype=float)
        return pin.JointModelUniversal(first, second)
    if joint.kind == "planar":
        return pin.JointModelPlanar()
    axis = np.asarray(joint.axis, dtype=float)
    for k, aligned in enumerate(_ALIGNED[joint.kind]):
        if np.linalg.norm(axis - np.eye(3)[k]) <= ALIGNED_TOL:
            return aligned()
    if joint.kind == "revolute":
        return pin.JointModelRevoluteUnaligned(axis)
    if joint.kind == "prismatic":
        return pin.JointModelPrismaticUnaligned(axis)
    return _unbounded_unaligned(tuple(float(a) for a in axis))


def _rotation_z(cos: float, sin: float) -> np.ndarray:
    """Return the rotation about z of the angle whose (cos, sin) are given (normalized)."""
    return pin.exp3(np.array([0.0, 0.0, np.arctan2(sin, cos)]))


def _motion(joint: JointDescription) -> pin.SE3:
    """Return the joint's motion S(q0) (the body frame in the joint frame at ``q0``)."""
    axis = np.asarray(joint.axis, dtype=float)
    q0 = joint.q0
    if joint.kind == "universal":
        rotation = pin.exp3(axis[0] * q0[0]) @ pin.exp3(axis[1] * q0[1])
        return pin.SE3(rotation, np.zeros(3))
    if joint.kind == "revolute":
        return pin.SE3(pin.exp3(axis * q0[0]), np.zeros(3))
    if joint.kind == "continuous":
        return pin.SE3(pin.exp3(axis * np.arctan2(q0[1], q0[0])), np.zeros(3))
    if joint.kind == "prismatic":
        return pin.SE3(np.eye(3), axis * q0[0])
    if joint.kind == "planar":
        return pin.SE3(_rotation_z(q0[2], q0[3]), np.array([q0[0], q0[1], 0.0]))
    x, y, z, w = q0[-4:]
    rotation = pin.Quaternion(w, x, y, z).normalized().matrix()
    return pin.SE3(rotation, np.asarray(q0[:3], dtype=float) if len(q0) == 7 else np.zeros(3))


def _limits(joint: JointDescription, jmodel) -> tuple[np.ndarray, ...] | None:
    """Return the bounds ``Model.addJoint`` takes, as Pinocchio's URDF reader gives them:
    (min_effort, max_effort, min_velocity, max_velocity, min_config, max_config,
    min_friction, max_friction, damping); None: Pinocchio's defaults (spherical, free,
    universal)."""
    nq, nv = jmodel.nq, jmodel.nv
    if joint.kind in ("spherical", "free", "universal"):
        return None
    one = np.ones(nv)
    if joint.kind in LIMITED_KINDS:
        lower, upper = np.array([joint.lower]), np.array([joint.upper])
    else:  # the unit-complex or quaternion entries are bounded, the others free
        unit = {"continuous": 2, "planar": 2, "floating": 4}[joint.kind]
        lower = np.concatenate([np.full(nq - unit, -np.inf), np.full(unit, -UNIT_ENTRY_BOUND)])
        upper = -lower
    effort, velocity, friction, damping = (
        (joint.effort, joint.velocity, joint.friction, joint.damping)
        if nv == 1
        else (np.inf, np.inf, 0.0, 0.0)
    )
    return (
        -effort * one,
        effort * one,
        -velocity * one,
        velocity * one,
        lower,
        upper,
        -friction * one,
        friction * one,
        damping * one,
    )


def _shift(p) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(p, dtype=float))


def _depth_first(description: TreeDescription) -> list:
    """Return the bodies in depth-first order, children in the description's order.

    Pinocchio numbers a subtree's joints in a row (its algorithms take a subtree's
    velocity entries as one range): a breadth-first order builds a model whose mass
    matrix is wrong without an error.

    Raises:
        ModelFileError: bodies no top-level body reaches (their parents form a cycle).
    """
    names = {b.name for b in description.bodies}
    children: dict[str | None, list] = {}
    for body in description.bodies:
        children.setdefault(body.parent, []).append(body)
    stack = [b for b in description.bodies if b.parent not in names][::-1]
    order = []
    while stack:
        body = stack.pop()
        order.append(body)
        stack.extend(reversed(children.pop(body.name, [])))
    if len(order) < len(description.bodies):
        reached = {id(b) for b in order}
        cycle = [b.name for b in description.bodies if id(b) not in reached]
        raise ModelFileError(
            f"{description.path}: bodies {', '.join(map(repr, cycle[:5]))} hang from each "
            "other in a cycle: no top-level body reaches them; valid: a tree"
        )
    return order


def build_model(description: TreeDescription, root_joint=None) -> pin.Model:
    """Return the Pinocchio model of a mechanism description (see the module docstring).

    Args:
        description: the tree.
        root_joint: a Pinocchio joint model between the world and the top-level
            bodies (named ``root_joint``), or None (fixed).

    Raises:
        ModelFileError: a free joint below the top level or beside other joints, a
            body whose parent is not described before it, or a duplicate name.
    """
    where = description.path
    model = pin.Model()
    model.name = description.name
    world = 0  # the universe's frame
    if description.world_frame:
        world = model.addFrame(
            pin.Frame(WORLD_LINK, 0, 0, pin.SE3.Identity(), pin.FrameType.BODY), False
        )
    top = 0
    top_frame = world
    if root_joint is not None:
        top = model.addJoint(0, root_joint, pin.SE3.Identity(), "root_joint")
        top_frame = model.addJointFrame(top, world)
    #: body name -> (joint id, body frame in the joint frame, BODY frame id); the world
    #: stays fixed (its sites too) while its bodies hang from the root joint
    bodies: dict[str, tuple[int, pin.SE3, int]] = {}
    if description.world_frame:
        bodies[WORLD_LINK] = (0, pin.SE3.Identity(), world)
    joint_names: set[str] = set()
    for body in _depth_first(description):
        if body.name in bodies:
            raise ModelFileError(f"{where}: body name {body.name!r} is used more than once")
        if body.parent is None or body.parent == WORLD_LINK and description.world_frame:
            parent, pX, parent_frame = top, pin.SE3.Identity(), top_frame
        elif body.parent in bodies:
            parent, pX, parent_frame = bodies[body.parent]
        else:
            raise ModelFileError(
                f"{where}: body {body.name!r}: parent {body.parent!r} is not described before it"
            )
        X = pX * body.placement
        for joint in body.joints:
            if joint.kind not in JOINT_KINDS:
                raise ModelFileError(
                    f"{where}: joint {joint.name!r}: kind {joint.kind!r}; valid: "
                    f"{', '.join(JOINT_KINDS)}"
                )
            if joint.name in joint_names or joint.name == "root_joint" and root_joint is not None:
                raise ModelFileError(f"{where}: joint name {joint.name!r} is used more than once")
            joint_names.add(joint.name)
            jmodel = joint_model(joint)
            if joint.kind == "free":
                top_level = body.parent is None or body.parent == WORLD_LINK
                if not top_level or len(body.joints) != 1 or root_joint is not None:
                    raise ModelFileError(
                        f"{where}: joint {joint.name!r}: a free joint must be the only joint of "
                        "a top-level body (and the model has no root joint)"
                    )
                placement, X = pin.SE3.Identity(), pin.SE3.Identity()
            else:
                placement = X * _shift(joint.position)
                X = _motion(joint).inverse() * _shift(-np.asarray(joint.position, dtype=float))
            limits = _limits(joint, jmodel)
            if limits is None:
                parent = model.addJoint(parent, jmodel, placement, joint.name)
            else:
                parent = model.addJoint(parent, jmodel, placement, joint.name, *limits)
            parent_frame = model.addJointFrame(parent, parent_frame)
        # Pinocchio's URDF reader appends no inertia that is exactly zero.
        if not body.inertia.isZero(0.0):
            model.appendBodyToJoint(parent, body.inertia, X)
        if body.fixed_joint:
            parent_frame = model.addFrame(
                pin.Frame(
                    body.fixed_joint,
                    parent,
                    parent_frame,
                    X,
                    pin.FrameType.FIXED_JOINT,
                    body.inertia,
                ),
                False,
            )
        # The root body of a model without a world frame and root joint is the universe's
        # own body: its frame holds its inertia (as Pinocchio's URDF reader makes it).
        universe_body = body.parent is None and parent == 0 and not body.joints
        frame = model.addFrame(
            pin.Frame(
                body.name,
                parent,
                parent_frame,
                X,
                pin.FrameType.BODY,
                body.inertia if universe_body else pin.Inertia.Zero(),
            ),
            False,
        )
        bodies[body.name] = (parent, X, frame)
    for site in description.sites:
        if site.body not in bodies:
            raise ModelFileError(
                f"{where}: site {site.name!r}: body {site.body!r} is not described"
            )
        joint, X, frame = bodies[site.body]
        model.addFrame(
            pin.Frame(site.name, joint, frame, X * site.placement, pin.FrameType.OP_FRAME), False
        )
    return model


def check_size(description: TreeDescription, max_nv: int | None) -> None:
    """Refuse a tree of more than ``max_nv`` velocity entries (None: any size).

    Raises:
        ModelTooLargeError: the message names the file, the joints and nv.
    """
    check_tree_size(str(description.path), len(description.joints()), description.nv(), max_nv)


def configuration(model: pin.Model, values: dict[str, tuple[float, ...]]) -> np.ndarray:
    """Return the neutral configuration with the given joints' values set.

    Args:
        model: the built model.
        values: joint name -> its configuration entries (Pinocchio's convention).

    Raises:
        ModelFileError: a joint the model lacks, or values of the wrong length.
    """
    q = pin.neutral(model)
    for name, vals in values.items():
        if not model.existJointName(name):
            raise ModelFileError(f"joint {name!r} is not a joint of the model {model.name!r}")
        joint = model.joints[model.getJointId(name)]
        if len(vals) != joint.nq:
            raise ModelFileError(
                f"joint {name!r}: {len(vals)} values for its {joint.nq} configuration entries"
            )
        q[joint.idx_q : joint.idx_q + joint.nq] = vals
    return q
