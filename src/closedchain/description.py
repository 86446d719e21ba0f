"""A plain description of a mechanism: its tree (bodies, joints, sites, visuals), loops and motors.

Every reader ("file -> description": URDF, SDF, MJCF through MuJoCo's own
compiler, a loops YAML file) fills these frozen dataclasses: a
:class:`MechanismDescription` holding its :class:`TreeDescription`, and
:func:`closedchain.build.build_model` turns the tree into the Pinocchio model:
no URDF text in between. The loops (:class:`closedchain.urdf.LoopSpec`), actuated
joints and passive terms travel in the :class:`MechanismDescription` beside the tree.

Conventions: every placement is an SE3 in the frame of what holds it (a body
in its parent body's frame, a joint's anchor, a site and a visual in their
body's frame); configurations are Pinocchio's (a quaternion as x, y, z, w).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

if TYPE_CHECKING:
    from .urdf import JointArmature, JointDamping, JointSpring, LoopSpec, SceneSpec

__all__ = [
    "BodyDescription",
    "JOINT_KINDS",
    "JOINT_NV",
    "JointDescription",
    "LIMITED_KINDS",
    "MechanismDescription",
    "NEUTRAL_Q0",
    "SiteDescription",
    "TreeDescription",
    "UNIVERSAL_SECOND_SUFFIX",
    "VISUAL_KINDS",
    "Visual",
]

#: Joint kinds and their number of configuration entries: MJCF's hinge, slide, ball and
#: free joints; URDF's continuous (an angle as cos, sin: Pinocchio's RevoluteUnbounded),
#: planar (x, y, cos, sin about the frame's z) and floating joints; SDF's universal
#: joint (two angles about its two axes: Pinocchio's JointModelUniversal).
JOINT_KINDS = {
    "revolute": 1,
    "prismatic": 1,
    "spherical": 4,
    "free": 7,
    "continuous": 2,
    "planar": 4,
    "floating": 7,
    "universal": 2,
}

#: Each joint kind's neutral configuration (its ``q0`` when the file gives none).
NEUTRAL_Q0 = {
    "revolute": (0.0,),
    "prismatic": (0.0,),
    "spherical": (0.0, 0.0, 0.0, 1.0),
    "free": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    "continuous": (1.0, 0.0),
    "planar": (0.0, 0.0, 1.0, 0.0),
    "floating": (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
    "universal": (0.0, 0.0),
}

#: Each joint kind's number of velocity entries.
JOINT_NV = {
    "revolute": 1,
    "prismatic": 1,
    "spherical": 3,
    "free": 6,
    "continuous": 1,
    "planar": 3,
    "floating": 6,
    "universal": 2,
}

#: Suffix of the name of a universal joint's second axis where it is a joint of its own
#: (a reversed SDF universal joint; a universal joint exported to MJCF as two hinges).
UNIVERSAL_SECOND_SUFFIX = "::axis2"

#: Joint kinds whose position limits are ``lower`` and ``upper`` (one coordinate each).
LIMITED_KINDS = ("revolute", "prismatic")

#: The kinds of drawn shapes (see :class:`Visual`).
VISUAL_KINDS = ("sphere", "box", "cylinder", "mesh")


@dataclass(frozen=True)
class JointDescription:
    """One joint between a body and its parent.

    The body moves about its joint's anchor: at configuration ``q0`` it sits at
    its :attr:`BodyDescription.placement`, and at q its frame is
    ``placement * T(position) * S(q) S(q0)^-1 * T(-position)`` (``S``: the
    joint's motion). A free joint (MJCF's: the only joint of a top-level body)
    places the body in the world: its q is the body's pose. A floating joint
    (URDF's) follows the rule above, anywhere in the tree.

    Attributes:
        name: the joint's name.
        kind: one of :data:`JOINT_KINDS`.
        axis: unit axis in the body frame, shape (3,) (revolute and prismatic); a
            universal joint's two axes, shape (2, 3): the body turns by
            Rot(axis[0], q[0]) Rot(axis[1], q[1]) (Pinocchio's ``JointModelUniversal``).
        position: the anchor in the body frame [m], shape (3,).
        q0: the configuration at which the body is at its placement, shape
            (nq,) [rad, m, or a unit quaternion x, y, z, w].
        lower: lower position limit [rad or m] (revolute and prismatic).
        upper: upper position limit [rad or m].
        effort: largest |force or torque| [N or N m] (1-dof kinds; Pinocchio's
            ``effortLimit``).
        velocity: largest |velocity| [rad/s or m/s] (1-dof kinds; ``velocityLimit``).
        friction: dry friction [N or N m] (1-dof kinds; Pinocchio's ``friction``,
            not modelled by closedchain).
        damping: viscous damping [N m s/rad or N s/m] (1-dof kinds; Pinocchio's
            ``damping``; the dynamics take theirs from
            :class:`closedchain.urdf.JointDamping`).
    """

    name: str
    kind: str
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q0: tuple[float, ...] = (0.0,)
    lower: float = -np.inf
    upper: float = np.inf
    effort: float = np.inf
    velocity: float = np.inf
    friction: float = 0.0
    damping: float = 0.0


@dataclass(frozen=True)
class Visual:
    """A drawn shape of a body.

    Attributes:
        kind: one of :data:`VISUAL_KINDS`.
        dims: sphere (radius,), box (x, y, z full lengths), cylinder (radius,
            length along its z axis) [m]; mesh: its scale (3 factors).
        placement: the shape's frame in the body frame.
        rgba: colour (r, g, b, a) in [0, 1], or None (none given: the drawing's default).
        mesh_file: the mesh file (mesh only), drawn in ``placement`` after scaling:
            a path (MJCF: as MuJoCo found it), or a URDF's filename as written
            (``package://``, ``file://`` or relative), looked up beside the file
            that names the link.
    """

    kind: str
    dims: tuple[float, ...]
    placement: pin.SE3
    rgba: tuple[float, float, float, float] | None
    mesh_file: Path | str | None = None


@dataclass(frozen=True)
class BodyDescription:
    """A rigid body: where it hangs, how it moves, its inertia and shapes.

    Attributes:
        name: the body's name (its BODY frame in the built model).
        parent: the parent body's name (:data:`closedchain.urdf.WORLD_LINK` for
            the world of a description with :attr:`TreeDescription.world_frame`),
            or None: the body hangs from Pinocchio's universe (a URDF's root link,
            on the root joint if the model has one).
        placement: the body frame in the parent's body frame at the joints' ``q0``.
        joints: its joints to the parent, applied in order (none: welded).
        inertia: mass, centre of mass and rotational inertia in the body frame.
        visuals: its drawn shapes.
        fixed_joint: the name of the fixed joint that welds it (URDF; "": none),
            a FIXED_JOINT frame between the parent's frame and the body's, as
            Pinocchio's URDF reader makes it.
    """

    name: str
    parent: str | None
    placement: pin.SE3
    joints: tuple[JointDescription, ...] = ()
    inertia: pin.Inertia = field(default_factory=pin.Inertia.Zero)
    visuals: tuple[Visual, ...] = ()
    fixed_joint: str = ""


@dataclass(frozen=True)
class SiteDescription:
    """A named frame fixed to a body (an OP_FRAME in the built model).

    Attributes:
        name: the site's name.
        body: the body it is fixed to.
        placement: the site frame in the body frame.
    """

    name: str
    body: str
    placement: pin.SE3


@dataclass(frozen=True)
class TreeDescription:
    """A mechanism's tree as its reader found it.

    Attributes:
        name: the model's name.
        path: the file it was read from.
        bodies: the moving and welded bodies, every parent before its children
            (the world is implicit: :data:`closedchain.urdf.WORLD_LINK`).
        world_visuals: shapes fixed to the world.
        sites: named frames on bodies or the world.
        keyframes: named configurations, each joint name -> its values in
            Pinocchio's convention, in the file's order.
        inactive: equalities the file declares inactive (kind and name): kept
            out of the loops, listed in the mechanism's summary.
        world_frame: whether the built model has a BODY frame
            :data:`closedchain.urdf.WORLD_LINK` for the universe (MJCF's world
            body); a URDF's tree has none (its root link is a body).
    """

    name: str
    path: Path
    bodies: tuple[BodyDescription, ...]
    world_visuals: tuple[Visual, ...] = ()
    sites: tuple[SiteDescription, ...] = ()
    keyframes: dict[str, dict[str, tuple[float, ...]]] = field(default_factory=dict)
    inactive: tuple[str, ...] = ()
    world_frame: bool = True

    def joints(self) -> tuple[JointDescription, ...]:
        """Return every joint, in tree order."""
        return tuple(j for b in self.bodies for j in b.joints)

    def nv(self) -> int:
        """Return the number of velocity entries of the tree (without a root joint)."""
        return sum(JOINT_NV.get(j.kind, 0) for j in self.joints())

    def reference_values(self) -> dict[str, tuple[float, ...]]:
        """Return each joint's ``q0`` (the configuration the file draws the model in)."""
        return {j.name: j.q0 for j in self.joints()}


@dataclass(frozen=True)
class MechanismDescription:
    """A mechanism as read from its files: the tree, its loops, motors and passive terms.

    Every reader fills one (:func:`closedchain.urdf.parse_urdf`,
    :func:`closedchain.sdf.read_sdf`, :func:`closedchain.mjcf.read_mjcf`, a loops
    YAML file and overlays on top), and :func:`closedchain.load` builds the
    mechanism from it (:attr:`closedchain.Mechanism.description`). The element
    names below are URDF+'s; the other formats' equivalents fill the same fields.

    Attributes:
        path: the file read.
        robot_name: the ``<robot name>`` (an SDF ``<model>``'s, an MJCF ``model``'s).
        links: names of all ``<link>`` elements (bodies).
        joints: joint name -> joint kind of every tree joint.
        loops: the ``<loop>`` elements (and couplings: mimic joints, gearboxes,
            MJCF joint equalities).
        actuated: joints named by ``<transmission>`` elements, in file order.
        independent: joints marked ``independent="true"``, in file order.
        scene: the ``<scene>`` element (default scene), or None.
        springs: the joint springs (``<dynamics spring_stiffness>``), in file order.
        dampings: the joints' viscous damping (:class:`JointDamping`), in file order.
        armatures: the joints' armature (:class:`JointArmature`), in file order.
        tree: the tree as a :class:`TreeDescription`
            (a URDF's read by :func:`parse_urdf`, an SDF model's by
            :func:`closedchain.sdf.read_sdf`, an MJCF model's through MuJoCo's
            compiler), which :func:`closedchain.build.build_model` builds.
        link_files: link name -> the file whose ``<link>`` element it is, for the
            links of another file than ``path`` (a base URDF under an overlay or a
            loops YAML file): their meshes are looked up beside that file.
    """

    path: Path
    robot_name: str
    links: tuple[str, ...]
    joints: dict[str, str] = field(default_factory=dict)
    loops: tuple[LoopSpec, ...] = ()
    actuated: tuple[str, ...] = ()
    independent: tuple[str, ...] = ()
    scene: SceneSpec | None = None
    springs: tuple[JointSpring, ...] = ()
    dampings: tuple[JointDamping, ...] = ()
    armatures: tuple[JointArmature, ...] = ()
    tree: TreeDescription | None = None
    link_files: dict[str, Path] = field(default_factory=dict)
