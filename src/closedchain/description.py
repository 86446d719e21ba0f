"""A plain description of a mechanism's tree: bodies, joints, sites, visuals.

A reader that has its format's own compiler (MJCF through MuJoCo, see
:mod:`closedchain.mjcf`) fills these frozen dataclasses, and
:func:`closedchain.build.build_model` turns them into the Pinocchio model:
no URDF text in between. Loops, actuated joints and passive terms keep
travelling in :class:`closedchain.urdf.URDFPlus` beside the description.

Conventions: every placement is an SE3 in the frame of what holds it (a body
in its parent body's frame, a joint's anchor, a site and a visual in their
body's frame); configurations are Pinocchio's (a quaternion as x, y, z, w).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

__all__ = [
    "BodyDescription",
    "JOINT_KINDS",
    "JointDescription",
    "MechanismDescription",
    "SiteDescription",
    "VISUAL_KINDS",
    "Visual",
]

#: Joint kinds and their number of configuration entries.
JOINT_KINDS = {"revolute": 1, "prismatic": 1, "spherical": 4, "free": 7}

#: The kinds of drawn shapes (see :class:`Visual`).
VISUAL_KINDS = ("sphere", "box", "cylinder", "mesh")


@dataclass(frozen=True)
class JointDescription:
    """One joint between a body and its parent.

    The body moves about its joint's anchor: at configuration ``q0`` it sits at
    its :attr:`BodyDescription.placement`, and at q its frame is
    ``placement * T(position) * S(q) S(q0)^-1 * T(-position)`` (``S``: the
    joint's motion). A free joint (the only joint of a top-level body) places
    the body in the world: its q is the body's pose.

    Attributes:
        name: the joint's name.
        kind: one of :data:`JOINT_KINDS`.
        axis: unit axis in the body frame, shape (3,) (revolute and prismatic).
        position: the anchor in the body frame [m], shape (3,).
        q0: the configuration at which the body is at its placement, shape
            (nq,) [rad, m, or a unit quaternion x, y, z, w].
        lower: lower position limit [rad or m] (revolute and prismatic).
        upper: upper position limit [rad or m].
    """

    name: str
    kind: str
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    q0: tuple[float, ...] = (0.0,)
    lower: float = -np.inf
    upper: float = np.inf


@dataclass(frozen=True)
class Visual:
    """A drawn shape of a body.

    Attributes:
        kind: one of :data:`VISUAL_KINDS`.
        dims: sphere (radius,), box (x, y, z full lengths), cylinder (radius,
            length along its z axis) [m]; mesh: its scale (3 factors).
        placement: the shape's frame in the body frame.
        rgba: colour (r, g, b, a) in [0, 1].
        mesh_file: the mesh file (mesh only), drawn in ``placement`` after scaling.
    """

    kind: str
    dims: tuple[float, ...]
    placement: pin.SE3
    rgba: tuple[float, float, float, float]
    mesh_file: Path | None = None


@dataclass(frozen=True)
class BodyDescription:
    """A rigid body: where it hangs, how it moves, its inertia and shapes.

    Attributes:
        name: the body's name (its BODY frame in the built model).
        parent: the parent body's name (:data:`closedchain.urdf.WORLD_LINK` for the world).
        placement: the body frame in the parent's body frame at the joints' ``q0``.
        joints: its joints to the parent, applied in order (none: welded).
        inertia: mass, centre of mass and rotational inertia in the body frame.
        visuals: its drawn shapes.
    """

    name: str
    parent: str
    placement: pin.SE3
    joints: tuple[JointDescription, ...] = ()
    inertia: pin.Inertia = field(default_factory=pin.Inertia.Zero)
    visuals: tuple[Visual, ...] = ()


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
class MechanismDescription:
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
    """

    name: str
    path: Path
    bodies: tuple[BodyDescription, ...]
    world_visuals: tuple[Visual, ...] = ()
    sites: tuple[SiteDescription, ...] = ()
    keyframes: dict[str, dict[str, tuple[float, ...]]] = field(default_factory=dict)
    inactive: tuple[str, ...] = ()

    def joints(self) -> tuple[JointDescription, ...]:
        """Return every joint, in tree order."""
        return tuple(j for b in self.bodies for j in b.joints)

    def reference_values(self) -> dict[str, tuple[float, ...]]:
        """Return each joint's ``q0`` (the configuration the file draws the model in)."""
        return {j.name: j.q0 for j in self.joints()}
