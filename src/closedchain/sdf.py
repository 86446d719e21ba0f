r"""Read SDF models (SDFormat, 1.6 frame semantics) into mechanism descriptions.

An SDF ``<model>`` is a graph of links and joints that may hold cycles; a
Pinocchio model is a tree. :func:`read_sdf` cuts the graph into a spanning tree
plus loop joints and fills a :class:`closedchain.description.TreeDescription`
(built by :func:`closedchain.build.build_model`, no URDF text in between) with
one loop per cut joint beside it, so ``load("robot.sdf")`` works as
``load("robot.urdf")`` does.

Frames (SDFormat 1.6, with the 1.7 ``relative_to`` attribute where present):

- a link's ``<pose>`` is in the model frame; a joint's ``<pose>`` is in its
  child link's frame; the ``<pose>`` of an inertial or visual is in its link's
  frame; ``relative_to`` (or the 1.6 ``frame`` attribute, when not empty) names
  another link or joint frame, ``__model__`` the model;
- a joint axis ``<xyz>`` is in the joint frame, or in the model frame with
  ``<use_parent_model_frame>1`` (1.6) or ``expressed_in="__model__"`` (1.7).

Every body's frame is its link's SDF frame, whichever way the tree runs through
its joint: the inertial and visuals are placed in it as the SDF places them, and
the joint's anchor and axes are the SDF joint frame's expressed in it. So the
BODY frame Pinocchio names after a link sits at the link's SDF pose when all
joint coordinates are zero. The root body, which :func:`closedchain.load` fixes
to Pinocchio's universe or moves with its root joint, is (as in Pinocchio's SDF
reader) the model's first ``<link>``: its frame is the world frame, its own
``<pose>`` (and the model's) only place it. When joints have ``world`` as
parent, the world is the model frame instead, and those joints' links hang from it.

Which joints are cut (a minimum spanning tree, Kruskal's algorithm): the joints
are taken in the order below and each is kept in the tree unless it would
close a cycle; the joints left out are cut and become loops.

1. joints named in ``cut_joints`` come last (the user's choice, as the
   ``parent_guidance`` of Pinocchio's SDF reader);
2. by type, :data:`KEEP_ORDER`: ``universal``, ``fixed``, ``prismatic``,
   ``revolute``, ``continuous``, ``ball``: a ball joint is cut first (it
   closes with 3 rows), a prismatic joint after the revolute ones (Pinocchio
   has no prismatic constraint to validate against), a universal joint never
   while another joint of its cycle can be (closedchain has no universal loop);
   ``gearbox`` joints are not in the graph (they couple two joints' angles and
   hold no link);
3. joints whose child link has one parent joint before joints whose child has
   several (the link keeps its own joint: Pinocchio's SDF rule);
4. file order.

The tree is then oriented from the root: a kept joint met from its child side
is *reversed* (its SDF parent is the body that moves, the SDF child holds it).
A reversed joint moves its body by the inverse of the SDF motion: its anchor is
the same point, each axis is negated, so each coordinate keeps the SDF's sign
(and its limits, spring reference and damping).

=================  ==============================================================
SDF joint          closedchain
=================  ==============================================================
``revolute``       revolute joint about ``<axis>``, ``<limit>`` lower and upper
                   (without: :data:`SDF_UNLIMITED`, SDF's own default)
``continuous``     revolute joint without limits (+-:data:`SDF_UNLIMITED`)
``prismatic``      prismatic joint along ``<axis>``, its ``<limit>``
``fixed``          the link welded to its tree parent (cut: a fixed loop)
``universal``      Pinocchio's universal joint (``JointModelUniversal``): the
                   child turns by Rot(``<axis>``, q[0]) Rot(``<axis2>``, q[1]) in
                   the joint frame, q in SDF axis order; its ``<limit>``
                   elements are not modelled (a logged warning). Reversed in the
                   tree (the body turns about ``<axis2>`` first): two revolute
                   joints at its anchor, ``<name>::axis2`` about ``<axis2>`` then
                   ``<name>`` about ``<axis>``, each with its axis' limits and
                   damping. Cut: refused
``ball``           spherical joint (q: a unit quaternion x, y, z, w; identity at
                   the SDF pose); cut: a spherical loop
``gearbox``        a coupling loop (below)
=================  ==============================================================

A gearbox couples a motor's rotor to its output; the SDFormat specification
(``joint.sdf``) defines it as :math:`\theta_2 = -r\,\theta_1` with ``r`` its
``<gearbox_ratio>``, :math:`\theta_1` the angle from the
``<gearbox_reference_body>`` to the ``<parent>`` link about ``<axis>`` and
:math:`\theta_2` the angle from it to the ``<child>`` link about ``<axis2>``
(Gazebo's ODE gearbox constraint has the same sign: child angle + ratio x parent
angle = 0). Each angle is read as the coordinate of the one revolute tree joint
between the reference body and that link, whose axis must be the gearbox's
(:data:`GEARBOX_AXIS_TOL`), signed by the axes' directions and which side is the
joint's SDF parent; the gearbox becomes the coupling loop
(:data:`closedchain.urdf.COUPLING`) ``q_child_joint = -r s1 s2 q_parent_joint`` of
the same name, so the rotor's inertia, reflected by 1/r^2, acts on the output. A
gearbox whose link has no such joint is refused naming it, as is a link held by
gearboxes only.

Held joints: ``fixed_joints`` names joints read as ``fixed`` at their zero
position (the pose the file draws), e.g. a spring joint held stiff, or a joint
of a linkage that only draws a part and would otherwise lock the mechanism at
a near-singular toggle (erd:cassie's knee springs; see
:data:`closedchain.robots.ERD_MODELS`). A spring on a held joint is left out
with the logged warning below.

Passive terms: a revolute or prismatic tree joint whose ``<axis><dynamics>`` has a
``spring_stiffness`` > 0 gets a :class:`closedchain.urdf.JointSpring` (its
``spring_reference``; the generalized force :func:`closedchain.spring_torque`); a
tree joint's ``<axis><dynamics><damping>`` > 0 a
:class:`closedchain.urdf.JointDamping` (a universal joint: when ``<axis2>``'s is the
same; a reversed one, one on each of its two revolute joints). A spring or damping
on a cut, gearbox or held joint, a spring on another joint type and a
(not reversed) universal joint's two different dampings are left out with a logged
warning. Friction is not read.

Inertials: mass, centre of mass and inertia in the link frame (SDF's default
without ``<inertial>``: 1 kg, the identity inertia at the link frame; inertias
that violate the triangle inequality are warned about). Visuals:
:data:`SDF_SHAPES` (a capsule as a cylinder and two spheres), coloured by
``<material><diffuse>`` (else ``<ambient>``, else :data:`SDF_DEFAULT_RGBA`); mesh
``model://name/sub`` URIs (and ``package://``) are looked up as ``sub`` in the
SDF's directory and its parents. Collisions are not read.

Parsing is as safe as for URDF (:func:`closedchain.urdf.read_xml`: no DTD, no
network, bounded size).
"""

from __future__ import annotations

import logging
import math
import urllib.parse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from .description import (
    UNIVERSAL_SECOND_SUFFIX,
    BodyDescription,
    JointDescription,
    TreeDescription,
    Visual,
)
from .exceptions import MESSAGE_MAX, ModelFileError, quoted, shorten
from .urdf import (
    COUPLING,
    COUPLING_MULTIPLIER_MAX,
    ORIGIN_RPY_MAX,
    ORIGIN_XYZ_MAX,
    WORLD_LINK,
    JointDamping,
    JointSpring,
    LoopSpec,
    MechanismDescription,
    _check_name,
    _unique_names,
    _where,
    check_inertia,
    check_tree_size,
    name_list,
    read_xml,
    unit_vector,
)

__all__ = ["SDFTree", "is_sdf", "read_sdf"]

logger = logging.getLogger(__name__)

#: The SDF name of the world, as a joint's parent.
SDF_WORLD = "world"

#: The SDF name of the model frame, in ``relative_to`` and ``expressed_in``.
SDF_MODEL_FRAME = "__model__"

#: SDF versions read: 1.5 introduced ``use_parent_model_frame`` (1.4 wrote axes
#: in the model frame), 1.7 ``relative_to``; 1.6 is what robots ship in.
SDF_VERSIONS = ("1.5", "1.6", "1.7", "1.8", "1.9", "1.10", "1.11")

#: Joint types read (others, e.g. ``revolute2`` and ``screw``, are refused).
SDF_JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed", "universal", "ball", "gearbox")

#: Joint types that need both ``<axis>`` and ``<axis2>``.
TWO_AXIS_TYPES = ("universal", "gearbox")

#: Joint types in the order they are kept in the spanning tree (see the module doc).
KEEP_ORDER = ("universal", "fixed", "prismatic", "revolute", "continuous", "ball")

#: Loop type of each cut joint type (``universal`` cannot be cut).
LOOP_TYPE_OF = {
    "revolute": "revolute",
    "continuous": "revolute",
    "prismatic": "prismatic",
    "fixed": "fixed",
    "ball": "spherical",
}

#: Joint kind (:data:`closedchain.description.JOINT_KINDS`) of each movable tree joint type.
KIND_OF = {
    "revolute": "revolute",
    "continuous": "revolute",
    "prismatic": "prismatic",
    "universal": "universal",
    "ball": "spherical",
}

#: Degrees of freedom of each joint kind (a fixed joint: none).
KIND_NV = {"revolute": 1, "prismatic": 1, "universal": 2, "spherical": 3, None: 0}

#: SDF joint types whose ``<dynamics>`` spring is read (one coordinate, no wrap).
SPRING_TYPES = ("revolute", "prismatic")

#: SDF's default joint limits (``lower``, ``upper`` [rad or m]) when ``<limit>``
#: leaves them out.
SDF_UNLIMITED = 1e16

#: Joint types that ``fixed_joints`` may hold (read as ``fixed``).
HOLDABLE_TYPES = ("revolute", "continuous", "prismatic")

#: Model children that cannot be read (they would change the mechanism if ignored).
SDF_REFUSED_ELEMENTS = ("model", "include", "frame")

#: Largest 1 - |cos| between a gearbox's axis and the axis of the joint whose
#: coordinate is its angle: the axes of erd:cassie are written alike, to the digit.
GEARBOX_AXIS_TOL = 1e-9

#: Smallest sine of the angle between a universal joint's two axes: nearer parallel,
#: its two coordinates turn the child about one axis.
UNIVERSAL_AXES_MIN_SINE = 1e-6

#: Default ``<inertial>`` of SDF: mass 1 kg, inertia the identity [kg m^2].
SDF_DEFAULT_MASS = 1.0

#: SDF geometries drawn (others: a logged warning).
SDF_SHAPES = ("box", "sphere", "cylinder", "capsule", "mesh")

#: Colour (r, g, b, a) of a visual without ``<material>``: the drawing's grey
#: (:attr:`closedchain.visualize.AnimationSettings.default_rgba`).
SDF_DEFAULT_RGBA = (0.6, 0.6, 0.6, 1.0)


@dataclass(frozen=True)
class SDFJoint:
    """One SDF joint, with its frame at the reference configuration.

    Attributes:
        name: joint name.
        type: one of :data:`SDF_JOINT_TYPES`.
        parent: parent link name (``world`` for the SDF world).
        child: child link name.
        oMj: joint frame in the model frame, all coordinates zero.
        axis: unit axis in the joint frame, shape (3,) (``<axis>``).
        axis2: unit second axis in the joint frame, shape (3,) (``<axis2>``).
        limits: ``(lower, upper)`` [rad or m] of ``<axis><limit>`` (see
            :data:`SDF_UNLIMITED`).
        limits2: the same of ``<axis2><limit>`` (universal joints).
        spring: ``(stiffness [N m/rad or N/m], reference [rad or m])`` of
            ``<axis><dynamics>`` ``spring_stiffness`` and ``spring_reference``, or
            None (no stiffness, or 0).
        damping: ``<axis><dynamics><damping>`` [N m s/rad or N s/m] (0: none).
        damping2: ``<axis2><dynamics><damping>`` (universal joints).
        index: position in the file among the joints.
        line: source line of the ``<joint>``.
        gearbox_ratio: ``<gearbox_ratio>`` (gearbox joints; else 0).
        gearbox_reference: ``<gearbox_reference_body>`` (gearbox joints; else "").
    """

    name: str
    type: str
    parent: str
    child: str
    oMj: pin.SE3
    axis: np.ndarray
    axis2: np.ndarray
    limits: tuple[float, float]
    spring: tuple[float, float] | None
    index: int
    line: int
    limits2: tuple[float, float] = (-SDF_UNLIMITED, SDF_UNLIMITED)
    damping: float = 0.0
    damping2: float = 0.0
    gearbox_ratio: float = 0.0
    gearbox_reference: str = ""


@dataclass(frozen=True)
class SDFTree:
    """How an SDF model's joint graph was cut (see the module doc for the rule).

    Attributes:
        model_name: the ``<model name>``.
        root: the root body: the model's first link, or ``world`` when joints
            hang from it.
        tree_joints: joints kept in the spanning tree, depth first from the root.
        reversed_joints: tree joints whose SDF parent is the body they move.
        cut_joints: joints cut, each a loop of the same name.
        gearboxes: gearbox joints, each a coupling loop of the same name.
        held_joints: joints read as ``fixed`` (``fixed_joints`` of :func:`read_sdf`).
    """

    model_name: str
    root: str
    tree_joints: tuple[str, ...]
    reversed_joints: tuple[str, ...]
    cut_joints: tuple[str, ...]
    gearboxes: tuple[str, ...]
    held_joints: tuple[str, ...] = ()


def read_sdf(
    path: str | Path,
    *,
    cut_joints: tuple[str, ...] = (),
    fixed_joints: tuple[str, ...] = (),
    max_nv: int | None = None,
) -> tuple[MechanismDescription, SDFTree]:
    """Read an SDF file into a mechanism description, its loops and passive terms.

    Args:
        path: the SDF file (one ``<model>``, under ``<sdf>`` or ``<sdf><world>``).
        cut_joints: joints to cut in preference to the rule's choice (see the
            module doc); each must be a joint of the model.
        fixed_joints: joints read as ``fixed`` at their zero position (see the
            module doc); each must be a revolute, continuous or prismatic joint.
        max_nv: largest supported number of degrees of freedom of the tree (a
            larger one is refused once the tree is cut, before it is described).

    Returns:
        ``(model, tree)``: the model (its ``description`` set, ``xml`` None; the
        cut joints and gearboxes as ``loops``, the springs and dampings) and how
        the graph was cut.

    Raises:
        ModelFileError: unsafe or malformed XML, an unsupported version, element or
            joint type, a bad number, a link not connected to the root, a
            ``cut_joints`` name that is not a joint, a ``fixed_joints`` name that is
            not a revolute, continuous or prismatic joint, a universal joint that
            has to be cut or whose axes are parallel. The message names the file,
            line and element and the valid choices.
        ModelTooLargeError: the tree has more than ``max_nv`` degrees of freedom.
    """
    path = Path(path)
    root = read_xml(path, what="SDF file")
    if root.tag != "sdf":
        raise ModelFileError(f"{path}: root element is <{root.tag}>, expected <sdf>")
    version = root.get("version")
    if version not in SDF_VERSIONS:
        raise ModelFileError(
            f"{path}: <sdf version={version!r}> is not read; valid: {', '.join(SDF_VERSIONS)}"
        )
    models = root.findall("model") + root.findall("world/model")
    if len(models) != 1:
        raise ModelFileError(f"{path}: {len(models)} <model> elements; valid: exactly one")
    reader = _Reader(path, models[0], tuple(fixed_joints))
    return reader.read(tuple(cut_joints), max_nv)


def _numbers(path: Path, element, count: int) -> np.ndarray:
    """Return the ``count`` finite numbers of an element's text, or raise naming it."""
    text = element.text or ""
    try:
        values = np.array([float(x) for x in text.split()])
    except ValueError:
        values = np.array([])
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise ModelFileError(
            f"{_where(path, element)}: {text.strip()!r} must be {count} finite numbers"
        )
    return values


def _scalar(path: Path, parent, tag: str, default: float, *, minimum: float | None = None):
    """Return the number held by child ``tag`` of ``parent`` (``default`` when absent)."""
    element = parent.find(tag)
    if element is None:
        return default
    value = float(_numbers(path, element, 1)[0])
    if minimum is not None and value < minimum:
        raise ModelFileError(f"{_where(path, element)}: {value:g} must be >= {minimum:g}")
    return value


class _Reader:
    """One SDF ``<model>``: its frames, joint graph, spanning tree and description."""

    def __init__(self, path: Path, model, fixed_joints: tuple[str, ...] = ()) -> None:
        self.path = path
        self.model = model
        self.name = _check_name(path, model, "model")
        for child in model:
            if isinstance(child.tag, str) and child.tag in SDF_REFUSED_ELEMENTS:
                raise ModelFileError(
                    f"{_where(path, child)}: <{child.tag}> inside <model> is not supported; "
                    "valid: <link> and <joint> (write the model out flat)"
                )
        self.link_elements = model.findall("link")
        if not self.link_elements:
            raise ModelFileError(f"{_where(path, model)}: has no <link> elements")
        self.links = {e.get("name"): e for e in self.link_elements}
        _unique_names(path, self.link_elements, "link")
        joint_elements = model.findall("joint")
        _unique_names(path, joint_elements, "joint")
        self.joint_elements = {e.get("name"): e for e in joint_elements}
        holdable = [n for n, e in self.joint_elements.items() if e.get("type") in HOLDABLE_TYPES]
        for name in fixed_joints:
            if name not in holdable:
                raise ModelFileError(
                    f"{path}: fixed_joints names {name!r}, which is not a "
                    f"{', '.join(HOLDABLE_TYPES)} joint; valid: {', '.join(holdable)}"
                )
        self.fixed_joints = fixed_joints
        self._poses: dict[str, pin.SE3] = {}
        self.joints = [self._joint(i, e) for i, e in enumerate(joint_elements)]
        #: link name (and ``world``) -> its frame in the model frame, all coordinates zero
        #: (filled by :meth:`read`).
        self.frames: dict[str, pin.SE3] = {}

    # -- frames ----------------------------------------------------------------
    def _pose_value(self, element) -> pin.SE3:
        """Return the placement written in a ``<pose>`` element (x y z roll pitch yaw)."""
        if element.get("rotation_format", "euler_rpy") != "euler_rpy":
            raise ModelFileError(
                f"{_where(self.path, element)}: rotation_format="
                f"{element.get('rotation_format')!r} is not read; valid: euler_rpy"
            )
        values = _numbers(self.path, element, 6)
        if element.get("degrees") == "true":
            values[3:] = np.deg2rad(values[3:])
        for part, bound, unit in (
            (values[:3], ORIGIN_XYZ_MAX, "m"),
            (values[3:], ORIGIN_RPY_MAX, "rad"),
        ):
            if float(np.max(np.abs(part))) > bound:
                raise ModelFileError(
                    f"{_where(self.path, element)}: {element.text.strip()!r} is beyond "
                    f"{bound:g} {unit}; valid: |components| <= {bound:g} {unit}"
                )
        return pin.SE3(pin.rpy.rpyToMatrix(values[3:]), values[:3])

    @staticmethod
    def _reference(element, default: str) -> str:
        """Return the name of the frame an element's ``<pose>`` is relative to."""
        pose = element.find("pose")
        if pose is None:
            return default
        return pose.get("relative_to") or pose.get("frame") or default

    def _relative(self, element, default: str) -> pin.SE3:
        """Return the world placement of the frame a ``<pose>`` is relative to."""
        name = self._reference(element, default)
        if name in ("", SDF_MODEL_FRAME):
            return pin.SE3.Identity()
        return self.frame(name, where=_where(self.path, element))

    def placed(self, element, default: str) -> pin.SE3:
        """Return the world placement of an element with an optional ``<pose>``.

        Args:
            element: a link, joint, inertial, visual or collision element.
            default: the frame its pose is relative to without ``relative_to``.
        """
        pose = element.find("pose")
        M = self._relative(element, default)
        return M if pose is None else M * self._pose_value(pose)

    def frame(self, name: str, *, where: str) -> pin.SE3:
        """Return the world placement of a link or joint frame, all coordinates zero.

        The chain of ``relative_to`` frames is walked in a loop, not by recursion:
        a chain of thousands of frames is as good as a short one.

        Raises:
            ModelFileError: unknown frame name (lists the valid ones), or poses
                relative to each other in a cycle.
        """
        chain: list[tuple[str, object]] = []  # (frame, its element), from ``name`` down
        on_chain: set[str] = set()
        current = name
        while current not in self._poses and current not in ("", SDF_MODEL_FRAME):
            if current in on_chain:
                cycle = " -> ".join([*(n for n, _ in chain), current])
                raise ModelFileError(
                    f"{where}: poses are relative to each other in a cycle: "
                    f"{shorten(cycle, MESSAGE_MAX)}"
                )
            if current in self.links:
                element, default = self.links[current], SDF_MODEL_FRAME
            elif current in self.joint_elements:
                element = self.joint_elements[current]
                default = element.findtext("child", "").strip()
            else:
                valid = [SDF_MODEL_FRAME, *self.links, *self.joint_elements]
                raise ModelFileError(
                    f"{where}: unknown frame {quoted(current)}; "
                    f"valid: {name_list(valid, keep_order=True)}"
                )
            on_chain.add(current)
            chain.append((current, element))
            where = _where(self.path, element)
            current = self._reference(element, default)
        M = self._poses.get(current, pin.SE3.Identity())
        for frame_name, element in reversed(chain):
            pose = element.find("pose")
            if pose is not None:
                M = M * self._pose_value(pose)
            self._poses[frame_name] = M
        return M

    # -- joints ------------------------------------------------------------------
    def _joint(self, index: int, element) -> SDFJoint:
        where = _where(self.path, element)
        jtype = "fixed" if element.get("name") in self.fixed_joints else element.get("type")
        if jtype not in SDF_JOINT_TYPES:
            raise ModelFileError(
                f"{where}: joint type {jtype!r} is not read; valid: {', '.join(SDF_JOINT_TYPES)}"
            )
        ends = {}
        for tag in ("parent", "child"):
            link = (element.findtext(tag) or "").strip()
            valid = (*self.links, SDF_WORLD) if tag == "parent" else tuple(self.links)
            if link not in valid:
                raise ModelFileError(
                    f"{where}: <{tag}>{link}</{tag}> is not a link; valid: {', '.join(valid)}"
                )
            ends[tag] = link
        if ends["parent"] == ends["child"]:
            raise ModelFileError(f"{where}: parent and child are the same link {ends['child']!r}")
        oMj = self.frame(element.get("name"), where=where)
        axes = []
        for tag in ("axis", "axis2"):
            axes.append(
                self._axis(
                    element,
                    tag,
                    oMj,
                    required=jtype in ("revolute", "continuous", "prismatic", *TWO_AXIS_TYPES)
                    and tag == "axis",
                )
            )
        if jtype in TWO_AXIS_TYPES and element.find("axis2") is None:
            raise ModelFileError(f"{where}: a {jtype} joint needs <axis2>")
        limits = tuple(self._limits(element, tag) for tag in ("axis", "axis2"))
        dampings = tuple(
            _scalar(self.path, dynamics, "damping", 0.0, minimum=0.0)
            if (dynamics := element.find(f"{tag}/dynamics")) is not None
            else 0.0
            for tag in ("axis", "axis2")
        )
        spring = None
        dynamics = element.find("axis/dynamics")
        if dynamics is not None:
            stiffness = _scalar(self.path, dynamics, "spring_stiffness", 0.0, minimum=0.0)
            if stiffness > 0.0:
                spring = (stiffness, _scalar(self.path, dynamics, "spring_reference", 0.0))
        ratio, reference = 0.0, ""
        if jtype == "gearbox":
            ratio = _scalar(self.path, element, "gearbox_ratio", 1.0)
            reference = (element.findtext("gearbox_reference_body") or "").strip()
            valid = (*self.links, SDF_WORLD)
            if reference not in valid:
                raise ModelFileError(
                    f"{where}: <gearbox_reference_body>{reference}</gearbox_reference_body> "
                    f"is not a link; valid: {', '.join(valid)}"
                )
        return SDFJoint(
            name=element.get("name"),
            type=jtype,
            parent=ends["parent"],
            child=ends["child"],
            oMj=oMj,
            axis=axes[0],
            axis2=axes[1],
            limits=limits[0],
            limits2=limits[1],
            spring=spring,
            damping=dampings[0],
            damping2=dampings[1],
            index=index,
            line=element.sourceline or 0,
            gearbox_ratio=ratio,
            gearbox_reference=reference,
        )

    def _limits(self, joint, tag: str) -> tuple[float, float]:
        """Return ``(lower, upper)`` of ``<tag><limit>`` (SDF's defaults: unlimited)."""
        limit = joint.find(f"{tag}/limit")
        if limit is None:
            return (-SDF_UNLIMITED, SDF_UNLIMITED)
        lower = _scalar(self.path, limit, "lower", -SDF_UNLIMITED)
        upper = _scalar(self.path, limit, "upper", SDF_UNLIMITED)
        if lower > upper:
            raise ModelFileError(
                f"{_where(self.path, limit)}: lower={lower:g} exceeds upper={upper:g}"
            )
        return lower, upper

    def _axis(self, joint, tag: str, oMj: pin.SE3, *, required: bool) -> np.ndarray:
        """Return the unit axis ``tag`` of a joint in the joint frame, shape (3,)."""
        axis = joint.find(tag)
        if axis is None or axis.find("xyz") is None:
            if required:
                raise ModelFileError(f"{_where(self.path, joint)}: missing <{tag}><xyz>")
            return np.array([0.0, 0.0, 1.0])
        xyz = axis.find("xyz")
        vec = unit_vector(xyz.text or "", f"{_where(self.path, xyz)} in <{tag}>")
        expressed = xyz.get("expressed_in")
        in_model = (axis.findtext("use_parent_model_frame") or "").strip() in ("1", "true")
        if in_model or expressed == SDF_MODEL_FRAME:
            R = np.eye(3)
        elif expressed:
            R = self.frame(expressed, where=_where(self.path, xyz)).rotation
        else:
            return vec
        return oMj.rotation.T @ R @ vec

    # -- the spanning tree ---------------------------------------------------------
    def spanning_tree(self, cut_joints: tuple[str, ...]) -> SDFTree:
        """Cut the joint graph into a spanning tree (the rule of the module doc)."""
        for name in cut_joints:
            if name not in self.joint_elements:
                raise ModelFileError(
                    f"{self.path}: cut_joints names {name!r}, which is not a joint; joints: "
                    + ", ".join(self.joint_elements)
                )
        graph = [j for j in self.joints if j.type != "gearbox"]
        gearboxes = tuple(j.name for j in self.joints if j.type == "gearbox")
        parents: dict[str, int] = {}
        for j in graph:
            parents[j.child] = parents.get(j.child, 0) + 1
        from_world = any(j.parent == SDF_WORLD for j in graph)
        root = SDF_WORLD if from_world else self.link_elements[0].get("name")

        def key(j: SDFJoint):
            return (j.name in cut_joints, KEEP_ORDER.index(j.type), parents[j.child] > 1, j.index)

        group = {name: name for name in (*self.links, SDF_WORLD)}

        def find(x: str) -> str:
            while group[x] != x:
                group[x] = group[group[x]]
                x = group[x]
            return x

        kept, cut = [], []
        for j in sorted(graph, key=key):
            a, b = find(j.parent), find(j.child)
            if a == b:
                cut.append(j)
            else:
                group[a] = b
                kept.append(j)
        # Orient from the root, depth first (Pinocchio's algorithms need each subtree's
        # joints in a row), children in file order.
        adjacent: dict[str, list[SDFJoint]] = {}
        for j in kept:
            adjacent.setdefault(j.parent, []).append(j)
            adjacent.setdefault(j.child, []).append(j)
        order, reversed_, seen = [], [], set()
        stack: list[tuple[str, SDFJoint | None]] = [(root, None)]
        while stack:
            link, through = stack.pop()
            seen.add(link)
            if through is not None:
                order.append(through)
                if link != through.child:
                    reversed_.append(through.name)
            below = sorted(adjacent.get(link, []), key=lambda j: j.index)
            ends = [(j.child if j.parent == link else j.parent, j) for j in below]
            stack.extend(reversed([(other, j) for other, j in ends if other not in seen]))
        missing = [name for name in self.links if name not in seen]
        if missing:
            through = [j.name for j in self.joints if j.type == "gearbox" and j.child in missing]
            hint = (
                f"; it hangs only on gearbox joints ({', '.join(through)}), which couple two "
                "joints' angles and hold no link: give it a revolute joint to the "
                "gearbox_reference_body"
                if through
                else "; join it with a <joint> or remove it"
            )
            raise ModelFileError(
                f"{self.path}: link {missing[0]!r} is not connected to the root link {root!r}{hint}"
            )
        for j in cut:
            if j.type == "universal":
                raise ModelFileError(
                    f"{_where(self.path, self.joint_elements[j.name])}: a universal joint "
                    "cannot be cut (closedchain's loops are revolute, prismatic, spherical "
                    "or fixed); keep it out of cut_joints, or give its cycle a joint of another "
                    "type"
                )
        return SDFTree(
            model_name=self.name,
            root=root,
            tree_joints=tuple(j.name for j in order),
            reversed_joints=tuple(reversed_),
            cut_joints=tuple(j.name for j in sorted(cut, key=lambda j: j.index)),
            gearboxes=gearboxes,
            held_joints=self.fixed_joints,
        )

    # -- the description ---------------------------------------------------------
    def read(
        self, cut_joints: tuple[str, ...], max_nv: int | None
    ) -> tuple[MechanismDescription, SDFTree]:
        """Return the model (its ``description`` set, ``xml`` None) and the :class:`SDFTree`."""
        tree = self.spanning_tree(cut_joints)
        joints = {j.name: j for j in self.joints}
        nv = sum(KIND_NV[KIND_OF.get(joints[n].type)] for n in tree.tree_joints)
        check_tree_size(str(self.path), len(tree.tree_joints), nv, max_nv)
        # Every body's frame is its link's SDF frame (the world's: the model frame).
        self.frames[SDF_WORLD] = pin.SE3.Identity()
        for element in self.link_elements:
            name = element.get("name")
            self.frames[name] = self.frame(name, where=_where(self.path, element))
        bodies = []
        if tree.root != SDF_WORLD:
            # The root link is the world frame: its own pose (and the model's) only place it.
            bodies.append(self._body(tree.root, WORLD_LINK, pin.SE3.Identity(), ()))
        #: tree joint -> the body that holds it (its SDF child, or its parent when reversed)
        holder: dict[str, str] = {}
        for name in tree.tree_joints:
            j = joints[name]
            reverse = name in tree.reversed_joints
            parent, child = (j.child, j.parent) if reverse else (j.parent, j.child)
            holder[name] = child
            placement = self.frames[parent].inverse() * self.frames[child]
            described = () if j.type == "fixed" else self._joint_descriptions(j, child, reverse)
            bodies.append(self._body(child, parent, placement, described))
        loops = [self._loop(joints[name]) for name in tree.cut_joints]
        loops += [self._gearbox_loop(joints[name], tree, holder) for name in tree.gearboxes]
        springs, dampings = self._passive(tree)
        description = TreeDescription(name=self.name, path=self.path, bodies=tuple(bodies))
        urdf = MechanismDescription(
            path=self.path,
            robot_name=self.name,
            links=(WORLD_LINK, *(b.name for b in bodies)),
            joints={j.name: j.kind for j in description.joints()},
            loops=tuple(loops),
            springs=springs,
            dampings=dampings,
            tree=description,
        )
        return urdf, tree

    def _body(self, name: str, parent: str, placement: pin.SE3, joints) -> BodyDescription:
        element = self.links[name]
        return BodyDescription(
            name=name,
            parent=WORLD_LINK if parent == SDF_WORLD else parent,
            placement=placement,
            joints=joints,
            inertia=self._inertia(element),
            visuals=self._visuals(element),
        )

    def _joint_descriptions(
        self, j: SDFJoint, body: str, reverse: bool
    ) -> tuple[JointDescription, ...]:
        """Return tree joint ``j`` as the joints of ``body`` (its SDF child, or parent if reversed).

        Its anchor and axes are the SDF joint frame's, expressed in the body's frame.
        Reversed, the body moves by the inverse motion: each axis is negated (so each
        coordinate keeps the SDF's sign, and its limits). A universal joint is
        Pinocchio's universal joint, turning by Rot(``<axis>``, q[0]) Rot(``<axis2>``,
        q[1]); reversed, the body turns about ``<axis2>`` first, so it becomes two
        revolute joints at the same anchor, ``<name>`` + :data:`UNIVERSAL_SECOND_SUFFIX`
        about ``<axis2>`` then ``<name>`` about ``<axis>``: each coordinate keeps its
        axis' name, limits and damping.
        """
        bMj = self.frames[body].inverse() * j.oMj
        sign = -1.0 if reverse else 1.0
        kind = KIND_OF[j.type]
        where = _where(self.path, self.joint_elements[j.name])
        lower, upper = j.limits if j.type != "continuous" else (-SDF_UNLIMITED, SDF_UNLIMITED)
        axis = sign * bMj.rotation @ j.axis
        q0: tuple[float, ...] = (0.0,)
        if kind == "universal":
            axis2 = sign * bMj.rotation @ j.axis2
            if np.linalg.norm(np.cross(axis, axis2)) < UNIVERSAL_AXES_MIN_SINE:
                raise ModelFileError(
                    f"{where}: <axis> and <axis2> are parallel, which leaves one rotation "
                    "for two coordinates; valid: two axes at an angle"
                )
            if reverse:
                position = bMj.translation.copy()
                return tuple(
                    JointDescription(
                        name=name, kind="revolute", axis=a, position=position, lower=lo, upper=up
                    )
                    for name, a, (lo, up) in (
                        (j.name + UNIVERSAL_SECOND_SUFFIX, axis2, j.limits2),
                        (j.name, axis, j.limits),
                    )
                )
            axis, q0 = np.array([axis, axis2]), (0.0, 0.0)
            if any(abs(x) < SDF_UNLIMITED for x in (*j.limits, *j.limits2)):
                logger.warning(
                    "%s: the <limit>s of universal joint %r are not modelled (Pinocchio's "
                    "universal joint has no position limits); valid: revolute and "
                    "prismatic limits",
                    where,
                    j.name,
                )
            lower, upper = -np.inf, np.inf
        elif kind == "spherical":
            q0, lower, upper = (0.0, 0.0, 0.0, 1.0), -np.inf, np.inf
        return (
            JointDescription(
                name=j.name,
                kind=kind,
                axis=axis,
                position=bMj.translation.copy(),
                q0=q0,
                lower=lower,
                upper=upper,
            ),
        )

    def _inertia(self, element) -> pin.Inertia:
        """Return a link's ``<inertial>`` in its frame (SDF's default: 1 kg, identity inertia)."""
        name = element.get("name")
        inertial = element.find("inertial")
        names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
        values = {n: 1.0 if n[1] == n[2] else 0.0 for n in names}
        if inertial is None:
            return pin.Inertia(SDF_DEFAULT_MASS, np.zeros(3), np.eye(3))
        lMi = self.frames[name].inverse() * self.placed(inertial, name)
        mass = _scalar(self.path, inertial, "mass", SDF_DEFAULT_MASS, minimum=0.0)
        inertia = inertial.find("inertia")
        if inertia is not None:
            values = {n: _scalar(self.path, inertia, n, values[n]) for n in names}
        where = f"{self.path}: line {inertial.sourceline}: <link name={name!r}> <inertial>"
        check_inertia(where, values, triangle="warn")
        ixx, ixy, ixz, iyy, iyz, izz = (values[n] for n in names)
        inertia_i = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        R = lMi.rotation
        return pin.Inertia(mass, lMi.translation.copy(), R @ inertia_i @ R.T)

    def _visuals(self, element) -> tuple[Visual, ...]:
        """Return a link's ``<visual>`` shapes in its frame (:data:`SDF_SHAPES`; others logged)."""
        name = element.get("name")
        out = []
        for visual in element.findall("visual"):
            geometry = visual.find("geometry")
            kinds = [g for g in ([] if geometry is None else geometry) if isinstance(g.tag, str)]
            if not kinds:
                continue
            g = kinds[0]
            if g.tag not in SDF_SHAPES:
                logger.warning(
                    "%s: <%s> geometry is not drawn; drawn: %s",
                    _where(self.path, g),
                    g.tag,
                    ", ".join(SDF_SHAPES),
                )
                continue
            placement = self.frames[name].inverse() * self.placed(visual, name)
            colour = visual.find("material/diffuse")
            if colour is None:
                colour = visual.find("material/ambient")
            rgba = SDF_DEFAULT_RGBA
            if colour is not None:
                rgba = tuple(float(c) for c in np.clip(_numbers(self.path, colour, 4), 0.0, 1.0))
            out.extend(self._shape(g, placement, rgba))
        return tuple(out)

    def _shape(self, g, placement: pin.SE3, rgba) -> list[Visual]:
        """Return the visuals of one SDF geometry (a capsule: a cylinder and two spheres)."""
        if g.tag == "box":
            return [Visual("box", tuple(_numbers(self.path, g.find("size"), 3)), placement, rgba)]
        if g.tag == "sphere":
            radius = _scalar(self.path, g, "radius", 1.0, minimum=0.0)
            return [Visual("sphere", (radius,), placement, rgba)]
        if g.tag in ("cylinder", "capsule"):
            default = 1.0 if g.tag == "cylinder" else 0.5  # SDFormat's radii [m]
            radius = _scalar(self.path, g, "radius", default, minimum=0.0)
            length = _scalar(self.path, g, "length", 1.0, minimum=0.0)
            out = [Visual("cylinder", (radius, length), placement, rgba)]
            if g.tag == "capsule":
                for end in (-length / 2.0, length / 2.0):
                    cap = placement * pin.SE3(np.eye(3), np.array([0.0, 0.0, end]))
                    out.append(Visual("sphere", (radius,), cap, rgba))
            return out
        uri = (g.findtext("uri") or "").strip()
        file = self._mesh_file(uri)
        if file is None:
            logger.warning(
                "%s: mesh <uri>%s</uri> is not a file, model:// or package:// path; not drawn",
                _where(self.path, g),
                uri,
            )
            return []
        scale = (1.0, 1.0, 1.0)
        if g.find("scale") is not None:
            scale = tuple(float(x) for x in _numbers(self.path, g.find("scale"), 3))
        return [Visual("mesh", scale, placement, rgba, file)]

    def _mesh_file(self, uri: str) -> Path | None:
        """Return the file a mesh ``<uri>`` names, or None (another scheme, no path).

        ``model://name/sub`` (and ``package://name/sub``) is ``sub`` looked up in the
        SDF's directory and then its parents (where a model's directory keeps its
        meshes); ``file://`` and plain paths are relative to the SDF's directory.
        """
        folder = self.path.resolve().parent
        scheme, sep, rest = uri.partition("://")
        if not sep:
            return folder / uri if uri else None
        if scheme == "file":
            return folder / urllib.parse.unquote(rest)
        if scheme not in ("model", "package"):
            return None
        sub = rest.partition("/")[2]
        if not sub:
            return None
        for root in (folder, *folder.parents):
            if (root / sub).is_file():
                return root / sub
        return folder / sub  # missing: the drawing names it

    def _loop(self, j: SDFJoint) -> LoopSpec:
        """Return the loop of a cut joint: its frame seen from both links."""
        return LoopSpec(
            name=j.name,
            type=LOOP_TYPE_OF[j.type],
            predecessor=j.parent,
            successor=j.child,
            predecessor_origin=self.frames[j.parent].inverse() * j.oMj,
            successor_origin=self.frames[j.child].inverse() * j.oMj,
            axis=j.axis,
            line=j.line,
        )

    def _passive(self, tree: SDFTree) -> tuple[tuple[JointSpring, ...], tuple[JointDamping, ...]]:
        """Return the springs and dampings of the tree joints; log those left out."""
        springs, dampings = [], []
        left_out: dict[str, list[str]] = {"springs": [], "damping": []}
        for j in self.joints:
            in_tree = j.name in tree.tree_joints and j.type != "fixed"
            if j.spring is not None:
                if in_tree and j.type in SPRING_TYPES:
                    springs.append(JointSpring(j.name, *j.spring, j.line))
                else:
                    left_out["springs"].append(j.name)
            if j.damping > 0.0 or j.damping2 > 0.0:
                if in_tree and j.name in tree.reversed_joints and j.type == "universal":
                    # Two revolute joints (see _joint_descriptions): one damping each.
                    for name, value in (
                        (j.name + UNIVERSAL_SECOND_SUFFIX, j.damping2),
                        (j.name, j.damping),
                    ):
                        if value > 0.0:
                            dampings.append(JointDamping(name, value, j.line))
                elif in_tree and j.type == "universal" and j.damping != j.damping2:
                    logger.warning(
                        "%s: universal joint %r: its axes' dampings %g and %g are left out: "
                        "closedchain's joint damping is one value on all its coordinates; "
                        "valid: the same <damping> on <axis> and <axis2>",
                        _where(self.path, self.joint_elements[j.name]),
                        j.name,
                        j.damping,
                        j.damping2,
                    )
                elif in_tree:
                    dampings.append(JointDamping(j.name, j.damping, j.line))
                else:
                    left_out["damping"].append(j.name)
        for what, names in left_out.items():
            if names:
                logger.warning(
                    "%s: the %s of %s %s left out: a cut joint (a loop), a gearbox or a held "
                    "(fixed_joints) joint has no coordinate of its own%s; valid: tree joints "
                    "(cut_joints chooses which joint of a cycle is cut)",
                    self.path,
                    what,
                    ", ".join(names),
                    "are" if what == "springs" else "is",
                    ", nor has a continuous, universal or ball joint a spring"
                    if what == "springs"
                    else "",
                )
        return tuple(springs), tuple(dampings)

    def _gearbox_loop(self, g: SDFJoint, tree: SDFTree, holder: dict[str, str]) -> LoopSpec:
        r"""Return the coupling loop of gearbox joint ``g``.

        SDFormat (``joint.sdf``, ``gearbox_ratio`` and ``gearbox_reference_body``):
        :math:`\theta_2 = -r\,\theta_1`, where :math:`\theta_1` is the angle from the
        reference body to the ``<parent>`` link about ``<axis>`` and :math:`\theta_2`
        the angle from the reference body to the ``<child>`` link about ``<axis2>``.
        Each angle is the coordinate of the joint between the reference body and
        that link (a revolute tree joint with the gearbox's axis), times
        :math:`s = \pm 1`: + when the joint's axis points along the gearbox's and
        its SDF parent is the reference body. So
        :math:`q_\mathrm{child} = -r\,s_1 s_2\,q_\mathrm{parent}`.
        """
        where = _where(self.path, self.joint_elements[g.name])
        ends = []
        for tag, link, axis in (("axis", g.parent, g.axis), ("axis2", g.child, g.axis2)):
            direction = g.oMj.rotation @ axis
            between = [
                j
                for j in self.joints
                if j.type != "gearbox" and {j.parent, j.child} == {g.gearbox_reference, link}
            ]
            if len(between) != 1:
                raise ModelFileError(
                    f"{where}: the gearbox angle of link {link!r} is the coordinate of the joint "
                    f"between it and the gearbox_reference_body {g.gearbox_reference!r}, and "
                    f"{len(between)} joints join them; valid: exactly one revolute joint"
                )
            j = between[0]
            if j.type != "revolute" or j.name not in tree.tree_joints:
                state = "cut (a loop has no coordinate)" if j.type != "fixed" else "fixed"
                raise ModelFileError(
                    f"{where}: joint {j.name!r} between {link!r} and the "
                    f"gearbox_reference_body is "
                    f"{state if j.type in ('revolute', 'fixed') else j.type}; valid: a revolute "
                    "tree joint (cut_joints chooses which joint of a cycle is cut; a "
                    "continuous joint's angle wraps)"
                )
            dot = float((j.oMj.rotation @ j.axis) @ direction)
            if abs(abs(dot) - 1.0) > GEARBOX_AXIS_TOL:
                raise ModelFileError(
                    f"{where}: joint {j.name!r} turns about another axis than the gearbox's "
                    f"<{tag}> (cosine {dot:.6g}); valid: parallel axes"
                )
            ends.append((j.name, math.copysign(1.0, dot) * (1.0 if j.parent != link else -1.0)))
        (mimics, s1), (driven, s2) = ends
        multiplier = -g.gearbox_ratio * s1 * s2
        if not abs(multiplier) <= COUPLING_MULTIPLIER_MAX:
            raise ModelFileError(
                f"{where}: <gearbox_ratio> {g.gearbox_ratio:g} is beyond the bound; valid: "
                f"|ratio| <= {COUPLING_MULTIPLIER_MAX:g} (COUPLING_MULTIPLIER_MAX)"
            )
        return LoopSpec(
            name=g.name,
            type=COUPLING,
            predecessor=holder[mimics],
            successor=holder[driven],
            predecessor_origin=pin.SE3.Identity(),
            successor_origin=pin.SE3.Identity(),
            axis=np.array([0.0, 0.0, 1.0]),
            line=g.line,
            joint=driven,
            mimics=mimics,
            multiplier=multiplier,
            offset=0.0,
        )


def is_sdf(path: str | Path) -> bool:
    """Return whether a model path names an SDF file (by its suffix)."""
    return Path(path).suffix.lower() == ".sdf"
