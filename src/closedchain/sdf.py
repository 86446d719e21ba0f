r"""Read SDF models (SDFormat, 1.6 frame semantics) as URDF+ mechanisms.

An SDF ``<model>`` is a graph of links and joints that may hold cycles; URDF
holds a tree. :func:`read_sdf` cuts the graph into a spanning tree plus loop
joints and writes the URDF+ document closedchain loads (``<link>``,
``<joint>`` and one ``<loop>`` per cut joint), so ``load("robot.sdf")`` works
as ``load("robot.urdf")`` does.

Frames (SDFormat 1.6, with the 1.7 ``relative_to`` attribute where present):

- a link's ``<pose>`` is in the model frame; a joint's ``<pose>`` is in its
  child link's frame; the ``<pose>`` of an inertial, visual or collision is
  in its link's frame; ``relative_to`` (or the 1.6 ``frame`` attribute, when
  not empty) names another link or joint frame, ``__model__`` the model;
- a joint axis ``<xyz>`` is in the joint frame, or in the model frame with
  ``<use_parent_model_frame>1`` (1.6) or ``expressed_in="__model__"`` (1.7).

Every link's URDF frame is its SDF frame, whichever way the tree runs
through it: inertials, visuals, joint origins and loop origins are expressed
in it, and where the link's tree joint frame is not the link's frame (a
joint ``<pose>``, or a reversed joint, whose frame sits on its SDF child),
the joint moves a massless link ``J::frame`` at the joint frame and a fixed
joint ``J::pose`` places the link in it (Pinocchio folds both into the
joint's body). So the frame Pinocchio names after a link sits at the link's
SDF pose when all joint coordinates are zero. The URDF root, which :func:`closedchain.load` fixes to
Pinocchio's universe or moves with its root joint, is (as in Pinocchio's SDF
reader) the model's first ``<link>``: its frame is the world frame, its own
``<pose>`` (and the model's) only place it. When joints have ``world`` as
parent, the root is instead a massless link ``world`` (the model frame, as in
URDFs that have one) from which those joints hang.

Which joints are cut (a minimum spanning tree, Kruskal's algorithm): the joints
are taken in the order below and each is kept in the tree unless it would
close a cycle; the joints left out are cut and become ``<loop>`` elements.

1. joints named in ``cut_joints`` come last (the user's choice, as the
   ``parent_guidance`` of Pinocchio's SDF reader);
2. by type, :data:`KEEP_ORDER`: ``universal``, ``fixed``, ``prismatic``,
   ``revolute``, ``continuous``, ``ball``: a ball joint is cut first (it
   closes with 3 rows and a URDF tree cannot hold it), a prismatic joint after
   the revolute ones (Pinocchio has no prismatic constraint to validate
   against), a universal joint never while another joint of its cycle can be
   (URDF+ has no universal loop); ``gearbox`` joints are not in the graph
   (they couple two joints' angles and hold no link);
3. joints whose child link has one parent joint before joints whose child has
   several (the link keeps its own joint: Pinocchio's SDF rule);
4. file order.

The tree is then oriented from the root: a kept joint met from its child
side is *reversed* (the SDF child becomes the URDF parent; the axis is negated,
so its coordinate keeps the SDF's sign, and its limits are kept).

Joint types: ``revolute`` (URDF ``revolute``; without ``<limit>`` its range
is :data:`SDF_UNLIMITED`, SDF's own default), ``continuous``, ``prismatic``,
``fixed``, ``universal`` (in the tree: two revolute joints ``J``, about
``<axis>``, and ``J::axis2``, about ``<axis2>``, through a massless link
``J::cross``; reversed, ``J::axis2`` comes first and each keeps its axis's
angle; cut: refused), ``ball`` (cut: a ``spherical`` loop; in the tree:
refused), ``gearbox``. A gearbox couples a motor's rotor to its output; the
SDFormat specification (``joint.sdf``) defines it as
:math:`\theta_2 = -r\,\theta_1` with ``r`` its ``<gearbox_ratio>``,
:math:`\theta_1` the angle from the ``<gearbox_reference_body>`` to the
``<parent>`` link about ``<axis>`` and :math:`\theta_2` the angle from it to
the ``<child>`` link about ``<axis2>`` (Gazebo's ODE gearbox constraint has
the same sign: child angle + ratio x parent angle = 0). Each angle is read
as the coordinate of the one revolute tree joint between the reference body
and that link, whose axis must be the gearbox's (:data:`GEARBOX_AXIS_TOL`),
signed by the axes' directions and which side is the joint's SDF parent; the
gearbox becomes the coupling loop (:data:`closedchain.urdf.COUPLING`)
``q_child_joint = -r s1 s2 q_parent_joint`` of the same name, so the rotor's
inertia, reflected by 1/r^2, acts on the output. A gearbox whose link has no
such joint is refused naming it, as is a link held by gearboxes only.

Held joints: ``fixed_joints`` names joints read as ``fixed`` at their zero
position (the pose the file draws), e.g. a spring joint held stiff, or a joint
of a linkage that only draws a part and would otherwise lock the mechanism at
a near-singular toggle (erd:cassie's knee springs; see
:data:`closedchain.robots.ERD_MODELS`). A spring on a held joint is left out
with the logged warning below.

Joint springs: a revolute or prismatic tree joint whose ``<axis><dynamics>`` has a
``spring_stiffness`` > 0 gets ``<dynamics spring_stiffness spring_reference>`` in the
URDF+ (:class:`closedchain.urdf.JointSpring`; the generalized force
:func:`closedchain.spring_torque`); a spring on a cut joint, a gearbox or another
joint type is left out with a logged warning. Viscous damping: a tree joint's
``<axis><dynamics><damping>`` > 0 (``<axis2>``'s for a universal joint's
``J::axis2``) is written as URDF ``<dynamics damping>`` and listed in
:attr:`SDFTree.dampings` (:class:`closedchain.urdf.JointDamping`; ``load`` puts
them in ``URDFPlus.dampings``); on a cut, gearbox or held joint it is left out
with a logged warning. Friction is not read.

Parsing is as safe as for URDF (:func:`closedchain.urdf.read_xml`: no DTD, no
network, bounded size). Mesh ``model://name/sub`` URIs become
``package://name/sub`` and are then looked up as URDF meshes are.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pinocchio as pin
from lxml import etree

from .exceptions import MESSAGE_MAX, URDFError, quoted, shorten
from .urdf import (
    COUPLING,
    ORIGIN_RPY_MAX,
    ORIGIN_XYZ_MAX,
    SPRING_JOINT_TYPES,
    JointDamping,
    _check_name,
    _unique_names,
    _where,
    check_inertia,
    name_list,
    read_xml,
    unit_vector,
)

logger = logging.getLogger(__name__)

#: The SDF name of the world, as a joint's parent (and the URDF root link then).
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

#: URDF+ loop type of each cut joint type (``universal`` cannot be cut).
LOOP_TYPE_OF = {
    "revolute": "revolute",
    "continuous": "revolute",
    "prismatic": "prismatic",
    "fixed": "fixed",
    "ball": "spherical",
}

#: SDF's default joint limits (``lower``, ``upper`` [rad or m], ``effort`` [N m
#: or N], ``velocity`` [rad/s or m/s]) when ``<limit>`` leaves them out or
#: gives SDF's "unlimited" (-1 for effort and velocity).
SDF_UNLIMITED = 1e16

#: Joint types that ``fixed_joints`` may hold (read as ``fixed``).
HOLDABLE_TYPES = ("revolute", "continuous", "prismatic")

#: Model children that cannot be read (they would change the mechanism if ignored).
SDF_REFUSED_ELEMENTS = ("model", "include", "frame")

#: Largest 1 - |cos| between a gearbox's axis and the axis of the joint whose
#: coordinate is its angle: the axes of erd:cassie are written alike, to the digit.
GEARBOX_AXIS_TOL = 1e-9

#: Default ``<inertial>`` of SDF: mass 1 kg, inertia the identity [kg m^2].
SDF_DEFAULT_MASS = 1.0


@dataclass(frozen=True)
class SDFJoint:
    """One SDF joint, with its frame at the reference configuration.

    Attributes:
        name: joint name.
        type: one of :data:`SDF_JOINT_TYPES`.
        parent: parent link name (``world`` for the SDF world).
        child: child link name.
        oMj: joint frame in the world frame, all coordinates zero.
        axis: unit axis in the joint frame, shape (3,) (``<axis>``).
        axis2: unit second axis in the joint frame, shape (3,) (``<axis2>``, universal).
        limits: ``(lower, upper, effort, velocity)`` of ``<axis><limit>`` (see
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
    limits: tuple[float, float, float, float]
    spring: tuple[float, float] | None
    index: int
    line: int
    limits2: tuple[float, float, float, float] = (
        -SDF_UNLIMITED,
        SDF_UNLIMITED,
        SDF_UNLIMITED,
        SDF_UNLIMITED,
    )
    damping: float = 0.0
    damping2: float = 0.0
    gearbox_ratio: float = 0.0
    gearbox_reference: str = ""


@dataclass(frozen=True)
class SDFTree:
    """How an SDF model's joint graph was cut (see the module doc for the rule).

    Attributes:
        model_name: the ``<model name>``.
        root: the URDF root link: the model's first link, or ``world`` when
            joints hang from it.
        tree_joints: joints kept in the spanning tree, in URDF order.
        reversed_joints: tree joints whose SDF child is their URDF parent.
        cut_joints: joints cut, each a ``<loop>`` of the same name.
        gearboxes: gearbox joints, each a coupling loop of the same name.
        held_joints: joints read as ``fixed`` (``fixed_joints`` of :func:`read_sdf`).
        dampings: the viscous damping of the tree joints (``<dynamics><damping>`` > 0),
            in tree order (filled by :meth:`_Reader.robot`).
    """

    model_name: str
    root: str
    tree_joints: tuple[str, ...]
    reversed_joints: tuple[str, ...]
    cut_joints: tuple[str, ...]
    gearboxes: tuple[str, ...]
    held_joints: tuple[str, ...] = ()
    dampings: tuple[JointDamping, ...] = ()


def read_sdf(
    path: str | Path, *, cut_joints: tuple[str, ...] = (), fixed_joints: tuple[str, ...] = ()
) -> tuple[object, SDFTree]:
    """Read an SDF file and write its URDF+ ``<robot>`` element.

    Args:
        path: the SDF file (one ``<model>``, under ``<sdf>`` or ``<sdf><world>``).
        cut_joints: joints to cut in preference to the rule's choice (see the
            module doc); each must be a joint of the model.
        fixed_joints: joints read as ``fixed`` at their zero position (see the
            module doc); each must be a revolute, continuous or prismatic joint.

    Returns:
        ``(robot, tree)``: the URDF+ ``<robot>`` element (lxml) and how the
        graph was cut.

    Raises:
        URDFError: unsafe or malformed XML, an unsupported version, element or
            joint type, a bad number, a link not connected to the root, a
            ``cut_joints`` name that is not a joint, a ``fixed_joints`` name that is
            not a revolute, continuous or prismatic joint, a ball joint the tree
            needs or a universal joint that has to be cut. The message names
            the file, line and element and the valid choices.
    """
    path = Path(path)
    root = read_xml(path, what="SDF file")
    if root.tag != "sdf":
        raise URDFError(f"{path}: root element is <{root.tag}>, expected <sdf>")
    version = root.get("version")
    if version not in SDF_VERSIONS:
        raise URDFError(
            f"{path}: <sdf version={version!r}> is not read; valid: {', '.join(SDF_VERSIONS)}"
        )
    models = root.findall("model") + root.findall("world/model")
    if len(models) != 1:
        raise URDFError(f"{path}: {len(models)} <model> elements; valid: exactly one")
    reader = _Reader(path, models[0], tuple(fixed_joints))
    return reader.robot(tuple(cut_joints))


def _numbers(path: Path, element, count: int) -> np.ndarray:
    """Return the ``count`` finite numbers of an element's text, or raise naming it."""
    text = element.text or ""
    try:
        values = np.array([float(x) for x in text.split()])
    except ValueError:
        values = np.array([])
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise URDFError(f"{_where(path, element)}: {text.strip()!r} must be {count} finite numbers")
    return values


def _scalar(path: Path, parent, tag: str, default: float, *, minimum: float | None = None):
    """Return the number held by child ``tag`` of ``parent`` (``default`` when absent)."""
    element = parent.find(tag)
    if element is None:
        return default
    value = float(_numbers(path, element, 1)[0])
    if minimum is not None and value < minimum:
        raise URDFError(f"{_where(path, element)}: {value:g} must be >= {minimum:g}")
    return value


def _origin(element, M: pin.SE3, tag: str = "origin") -> None:
    """Add ``<origin xyz rpy>`` (or another ``tag``) of placement ``M`` to a URDF element."""
    origin = etree.SubElement(element, tag)
    origin.set("xyz", _vector(M.translation))
    origin.set("rpy", _vector(pin.rpy.matrixToRpy(M.rotation)))


def _vector(values) -> str:
    """Return numbers as URDF attribute text, all digits."""
    return " ".join(repr(float(x)) for x in values)


class _Reader:
    """One SDF ``<model>``: its frames, joint graph, spanning tree and URDF+ text."""

    def __init__(self, path: Path, model, fixed_joints: tuple[str, ...] = ()) -> None:
        self.path = path
        self.model = model
        self.name = _check_name(path, model, "model")
        for child in model:
            if isinstance(child.tag, str) and child.tag in SDF_REFUSED_ELEMENTS:
                raise URDFError(
                    f"{_where(path, child)}: <{child.tag}> inside <model> is not supported; "
                    "valid: <link> and <joint> (write the model out flat)"
                )
        self.link_elements = model.findall("link")
        if not self.link_elements:
            raise URDFError(f"{_where(path, model)}: has no <link> elements")
        self.links = {e.get("name"): e for e in self.link_elements}
        _unique_names(path, self.link_elements, "link")
        joint_elements = model.findall("joint")
        _unique_names(path, joint_elements, "joint")
        self.joint_elements = {e.get("name"): e for e in joint_elements}
        holdable = [n for n, e in self.joint_elements.items() if e.get("type") in HOLDABLE_TYPES]
        for name in fixed_joints:
            if name not in holdable:
                raise URDFError(
                    f"{path}: fixed_joints names {name!r}, which is not a "
                    f"{', '.join(HOLDABLE_TYPES)} joint; valid: {', '.join(holdable)}"
                )
        self.fixed_joints = fixed_joints
        self._poses: dict[str, pin.SE3] = {}
        self.joints = [self._joint(i, e) for i, e in enumerate(joint_elements)]

    # -- frames ----------------------------------------------------------------
    def _pose_value(self, element) -> pin.SE3:
        """Return the placement written in a ``<pose>`` element (x y z roll pitch yaw)."""
        if element.get("rotation_format", "euler_rpy") != "euler_rpy":
            raise URDFError(
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
                raise URDFError(
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
            URDFError: unknown frame name (lists the valid ones), or poses
                relative to each other in a cycle.
        """
        chain: list[tuple[str, object]] = []  # (frame, its element), from ``name`` down
        on_chain: set[str] = set()
        current = name
        while current not in self._poses and current not in ("", SDF_MODEL_FRAME):
            if current in on_chain:
                cycle = " -> ".join([*(n for n, _ in chain), current])
                raise URDFError(
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
                raise URDFError(
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
            raise URDFError(
                f"{where}: joint type {jtype!r} is not read; valid: {', '.join(SDF_JOINT_TYPES)}"
            )
        ends = {}
        for tag in ("parent", "child"):
            link = (element.findtext(tag) or "").strip()
            valid = (*self.links, SDF_WORLD) if tag == "parent" else tuple(self.links)
            if link not in valid:
                raise URDFError(
                    f"{where}: <{tag}>{link}</{tag}> is not a link; valid: {', '.join(valid)}"
                )
            ends[tag] = link
        if ends["parent"] == ends["child"]:
            raise URDFError(f"{where}: parent and child are the same link {ends['child']!r}")
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
            raise URDFError(f"{where}: a {jtype} joint needs <axis2>")
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
                raise URDFError(
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

    def _limits(self, joint, tag: str) -> tuple[float, float, float, float]:
        """Return ``(lower, upper, effort, velocity)`` of ``<tag><limit>`` (SDF's defaults)."""
        limit = joint.find(f"{tag}/limit")
        if limit is None:
            return (-SDF_UNLIMITED, SDF_UNLIMITED, SDF_UNLIMITED, SDF_UNLIMITED)
        lower = _scalar(self.path, limit, "lower", -SDF_UNLIMITED)
        upper = _scalar(self.path, limit, "upper", SDF_UNLIMITED)
        if lower > upper:
            raise URDFError(f"{_where(self.path, limit)}: lower={lower:g} exceeds upper={upper:g}")
        effort = _scalar(self.path, limit, "effort", -1.0)
        velocity = _scalar(self.path, limit, "velocity", -1.0)
        return (
            lower,
            upper,
            effort if effort >= 0 else SDF_UNLIMITED,
            velocity if velocity >= 0 else SDF_UNLIMITED,
        )

    def _axis(self, joint, tag: str, oMj: pin.SE3, *, required: bool) -> np.ndarray:
        """Return the unit axis ``tag`` of a joint in the joint frame, shape (3,)."""
        axis = joint.find(tag)
        if axis is None or axis.find("xyz") is None:
            if required:
                raise URDFError(f"{_where(self.path, joint)}: missing <{tag}><xyz>")
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
                raise URDFError(
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
        # Orient from the root, breadth first.
        adjacent: dict[str, list[SDFJoint]] = {}
        for j in kept:
            adjacent.setdefault(j.parent, []).append(j)
            adjacent.setdefault(j.child, []).append(j)
        order, reversed_, seen = [], [], {root}
        queue = [root]
        while queue:
            link = queue.pop(0)
            for j in sorted(adjacent.get(link, []), key=lambda j: j.index):
                other = j.child if j.parent == link else j.parent
                if other in seen:
                    continue
                seen.add(other)
                order.append(j)
                if other != j.child:
                    reversed_.append(j.name)
                queue.append(other)
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
            raise URDFError(
                f"{self.path}: link {missing[0]!r} is not connected to the root link {root!r}{hint}"
            )
        for j in cut:
            if j.type == "universal":
                raise URDFError(
                    f"{_where(self.path, self.joint_elements[j.name])}: a universal joint "
                    "cannot be cut (URDF+ loops are revolute, prismatic, spherical or "
                    "fixed); keep it out of cut_joints, or give its cycle a joint of another "
                    "type"
                )
        for j in order:
            if j.type == "ball":
                raise URDFError(
                    f"{_where(self.path, self.joint_elements[j.name])}: the spanning tree "
                    "needs this ball joint (it closes no cycle) and a URDF tree cannot hold "
                    "one; valid: ball joints that close a cycle"
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

    # -- the URDF+ document ----------------------------------------------------
    def robot(self, cut_joints: tuple[str, ...]):
        """Return the URDF+ ``<robot>`` element and the :class:`SDFTree`."""
        tree = self.spanning_tree(cut_joints)
        joints = {j.name: j for j in self.joints}
        # Every link's URDF frame is its SDF frame (the world frame for the world).
        frames = {SDF_WORLD: pin.SE3.Identity()}
        for element in self.link_elements:
            frames[element.get("name")] = self.frame(element.get("name"), where=str(self.path))

        robot = etree.Element("robot", name=self.name)
        if tree.root == SDF_WORLD:
            etree.SubElement(robot, "link", name=SDF_WORLD)
        materials: list = []
        for element in self.link_elements:
            robot.append(self._link(element, frames[element.get("name")], materials))
        for material in materials:
            robot.insert(0, material)
        dampings: list[JointDamping] = []
        for name in tree.tree_joints:
            elements, damped = self._tree_joint(joints[name], name in tree.reversed_joints, frames)
            robot.extend(elements)
            dampings.extend(damped)
        for name in tree.cut_joints:
            robot.append(self._loop(joints[name], frames))
        for name in tree.gearboxes:
            robot.append(self._gearbox_loop(joints[name], tree))
        for what, verb, left_out in (
            (
                "springs",
                "are",
                [
                    j.name
                    for j in self.joints
                    if j.spring is not None
                    and (j.name not in tree.tree_joints or j.type not in SPRING_JOINT_TYPES)
                ],
            ),
            (
                "damping",
                "is",
                [
                    j.name
                    for j in self.joints
                    if (j.damping > 0.0 or j.damping2 > 0.0)
                    and (j.name not in tree.tree_joints or j.type == "fixed")
                ],
            ),
        ):
            if left_out:
                logger.warning(
                    "%s: the %s of %s %s left out: a cut joint (a <loop>), a gearbox or a "
                    "held (fixed_joints) joint has no coordinate of its own%s; valid: tree "
                    "joints (cut_joints chooses which joint of a cycle is cut)",
                    self.path,
                    what,
                    ", ".join(left_out),
                    verb,
                    ", nor has a continuous or universal joint a spring"
                    if what == "springs"
                    else "",
                )
        return robot, replace(tree, dampings=tuple(dampings))

    def _gearbox_loop(self, g: SDFJoint, tree: SDFTree):
        r"""Return the coupling ``<loop>`` of gearbox joint ``g``.

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
                raise URDFError(
                    f"{where}: the gearbox angle of link {link!r} is the coordinate of the joint "
                    f"between it and the gearbox_reference_body {g.gearbox_reference!r}, and "
                    f"{len(between)} joints join them; valid: exactly one revolute joint"
                )
            j = between[0]
            if j.type != "revolute" or j.name not in tree.tree_joints:
                state = "cut (a <loop> has no coordinate)" if j.type != "fixed" else "fixed"
                raise URDFError(
                    f"{where}: joint {j.name!r} between {link!r} and the "
                    f"gearbox_reference_body is "
                    f"{state if j.type in ('revolute', 'fixed') else j.type}; valid: a revolute "
                    "tree joint (cut_joints chooses which joint of a cycle is cut; a "
                    "continuous joint's angle wraps)"
                )
            dot = float((j.oMj.rotation @ j.axis) @ direction)
            if abs(abs(dot) - 1.0) > GEARBOX_AXIS_TOL:
                raise URDFError(
                    f"{where}: joint {j.name!r} turns about another axis than the gearbox's "
                    f"<{tag}> (cosine {dot:.6g}); valid: parallel axes"
                )
            ends.append((j.name, math.copysign(1.0, dot) * (1.0 if j.parent != link else -1.0)))
        (mimics, s1), (driven, s2) = ends
        loop = etree.Element("loop", name=g.name, type=COUPLING)
        etree.SubElement(loop, "joint", name=driven)
        etree.SubElement(
            loop,
            "mimics",
            joint=mimics,
            multiplier=repr(-g.gearbox_ratio * s1 * s2),
            offset="0.0",
        )
        return loop

    def _link(self, element, oMl_urdf: pin.SE3, materials: list):
        """Return the URDF ``<link>`` of an SDF link whose URDF frame is ``oMl_urdf``."""
        name = element.get("name")
        link = etree.Element("link", name=name)
        inverse = oMl_urdf.inverse()
        inertial = element.find("inertial")
        out = etree.SubElement(link, "inertial")
        names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
        # SDF's defaults: 1 kg, identity inertia [kg m^2], at the link frame.
        values = {n: 1.0 if n[1] == n[2] else 0.0 for n in names}
        if inertial is None:
            M, mass = self.frame(name, where=_where(self.path, element)), SDF_DEFAULT_MASS
        else:
            M = self.placed(inertial, name)
            mass = _scalar(self.path, inertial, "mass", SDF_DEFAULT_MASS, minimum=0.0)
            inertia = inertial.find("inertia")
            if inertia is not None:
                values = {n: _scalar(self.path, inertia, n, values[n]) for n in names}
            where = f"{self.path}: line {inertial.sourceline}: <link name={name!r}> <inertial>"
            check_inertia(where, values, triangle="warn")
        _origin(out, inverse * M)
        etree.SubElement(out, "mass", value=repr(mass))
        etree.SubElement(out, "inertia", **{n: repr(v) for n, v in values.items()})
        for kind in ("visual", "collision"):
            for i, shape in enumerate(element.findall(kind)):
                urdf_shape = self._shape(shape, name, inverse, f"{name}_{kind}_{i}", materials)
                if urdf_shape is not None:
                    link.append(urdf_shape)
        return link

    def _shape(self, element, link: str, inverse: pin.SE3, label: str, materials: list):
        """Return the URDF ``<visual>``/``<collision>`` of an SDF one (None: no URDF shape)."""
        geometry = element.find("geometry")
        kinds = [g for g in (geometry if geometry is not None else []) if isinstance(g.tag, str)]
        if not kinds:
            return None
        g = kinds[0]
        out = etree.Element(element.tag)
        _origin(out, inverse * self.placed(element, link))
        urdf_geometry = etree.SubElement(out, "geometry")
        if g.tag == "box":
            etree.SubElement(
                urdf_geometry, "box", size=_vector(_numbers(self.path, g.find("size"), 3))
            )
        elif g.tag == "sphere":
            etree.SubElement(
                urdf_geometry,
                "sphere",
                radius=repr(_scalar(self.path, g, "radius", 1.0, minimum=0.0)),
            )
        elif g.tag == "cylinder":
            etree.SubElement(
                urdf_geometry,
                "cylinder",
                radius=repr(_scalar(self.path, g, "radius", 1.0, minimum=0.0)),
                length=repr(_scalar(self.path, g, "length", 1.0, minimum=0.0)),
            )
        elif g.tag == "mesh":
            uri = (g.findtext("uri") or "").strip()
            scheme, sep, rest = uri.partition("://")
            if sep and scheme == "model":
                uri = "package://" + rest
            mesh = etree.SubElement(urdf_geometry, "mesh", filename=uri)
            if g.find("scale") is not None:
                mesh.set("scale", _vector(_numbers(self.path, g.find("scale"), 3)))
        else:
            logger.warning(
                "%s: <%s> geometry has no URDF counterpart; not drawn", _where(self.path, g), g.tag
            )
            return None
        colour = element.find("material/diffuse")
        if colour is None:
            colour = element.find("material/ambient")
        if element.tag == "visual" and colour is not None:
            rgba = _numbers(self.path, colour, 4)
            material = etree.Element("material", name=label)
            etree.SubElement(material, "color", rgba=_vector(np.clip(rgba, 0.0, 1.0)))
            materials.append(material)
            etree.SubElement(out, "material", name=label)
        return out

    def _tree_joint(
        self, j: SDFJoint, reverse: bool, frames: dict[str, pin.SE3]
    ) -> tuple[list, list[JointDamping]]:
        """Return the URDF elements of a tree joint, and the damping of its URDF joints.

        The elements: its ``<joint>`` elements (two for a universal joint, through a
        massless ``J::cross`` link) and, where its URDF child's SDF frame is not the
        joint frame, a massless ``J::frame`` link that the joint moves and a fixed
        ``J::pose`` joint placing the link in it.
        """
        parent, child = j.parent, j.child
        sign = 1.0
        if reverse:  # the axes negated: each coordinate keeps the SDF's sign
            parent, child, sign = child, parent, -1.0
        origin = frames[parent].inverse() * j.oMj
        # (name, type, axis, parent, child, origin, limits, damping)
        steps = [(j.name, j.type, j.axis, parent, child, origin, j.limits, j.damping)]
        if j.type == "universal":
            # R = Rot(axis, q1) Rot(axis2, q2) from the SDF parent; from the SDF child,
            # Rot(-axis2, q2) Rot(-axis, q1): J::axis2 comes first, each keeps its angle.
            cross = f"{j.name}::cross"
            first = (j.name, "revolute", j.axis, j.limits, j.damping)
            second = (f"{j.name}::axis2", "revolute", j.axis2, j.limits2, j.damping2)
            if reverse:
                first, second = second, first
            steps = [
                (*first[:3], parent, cross, origin, *first[3:]),
                (*second[:3], cross, child, pin.SE3.Identity(), *second[3:]),
            ]
        offset = j.oMj.inverse() * frames[child]
        if not np.array_equal(offset.homogeneous, np.eye(4)):
            held = f"{j.name}::frame"
            steps[-1] = (*steps[-1][:4], held, *steps[-1][5:])
            steps.append((f"{j.name}::pose", "fixed", j.axis, held, child, offset, j.limits, 0.0))
        out, damped = [], []
        for name, jtype, axis, p, c, M, limits, damping in steps:
            if c.startswith(f"{j.name}::"):
                out.append(etree.Element("link", name=c))
            joint = etree.Element("joint", name=name, type=jtype)
            etree.SubElement(joint, "parent", link=p)
            etree.SubElement(joint, "child", link=c)
            _origin(joint, M)
            if jtype != "fixed":
                etree.SubElement(joint, "axis", xyz=_vector(sign * axis))
            if jtype in ("revolute", "prismatic"):
                lower, upper, effort, velocity = limits
                etree.SubElement(
                    joint,
                    "limit",
                    lower=repr(lower),
                    upper=repr(upper),
                    effort=repr(effort),
                    velocity=repr(velocity),
                )
            spring = j.spring if j.type in SPRING_JOINT_TYPES else None
            if jtype != "fixed" and (damping > 0.0 or spring is not None):
                # urdfdom wants damping or friction in <dynamics>; a reversed joint keeps
                # the SDF's coordinate (its axis is negated), so its spring too.
                dynamics = etree.SubElement(joint, "dynamics", damping=repr(damping))
                if spring is not None:
                    dynamics.set("spring_stiffness", repr(spring[0]))
                    dynamics.set("spring_reference", repr(spring[1]))
            if jtype != "fixed" and damping > 0.0:
                damped.append(JointDamping(name, damping, j.line))
            out.append(joint)
        return out, damped

    def _loop(self, j: SDFJoint, frames: dict[str, pin.SE3]):
        """Return the URDF+ ``<loop>`` of a cut joint (its frame seen from both links)."""
        loop = etree.Element("loop", name=j.name, type=LOOP_TYPE_OF[j.type])
        etree.SubElement(loop, "predecessor", link=j.parent)
        etree.SubElement(loop, "successor", link=j.child)
        for tag, link in (("predecessor_origin", j.parent), ("successor_origin", j.child)):
            _origin(loop, frames[link].inverse() * j.oMj, tag)
        if j.type in ("revolute", "continuous", "prismatic"):
            etree.SubElement(loop, "axis", xyz=_vector(j.axis))
        return loop


def is_sdf(path: str | Path) -> bool:
    """Return whether a model path names an SDF file (by its suffix)."""
    return Path(path).suffix.lower() == ".sdf"
