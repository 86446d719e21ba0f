r"""Read MuJoCo MJCF models: the body tree and ``<equality>`` constraints as URDF+.

An MJCF file (root ``<mujoco>``) is translated into a URDF+ ``<robot>``
element, which then goes through the same reader, checks and loop layer as a
URDF (:func:`closedchain.urdf.parse_urdf`), so every command works on it.
The rule:

=================================  =============================================
MJCF                               URDF+
=================================  =============================================
``<worldbody>``                    link ``world`` (every top-level body hangs
                                   from it: sibling root bodies are kept)
``<body>``                         link of the body's name, its ``<inertial>``
                                   (``diaginertia`` + ``quat`` or
                                   ``fullinertia``) as a URDF inertia
body without joint                 ``fixed`` joint
``hinge`` / ``slide``              ``revolute`` / ``prismatic`` (``range`` as
                                   limits; unlimited: +-:data:`UNLIMITED_RANGE`)
``free`` / ``<freejoint>``         ``floating`` (top-level bodies only)
several joints in one body         a chain through massless links
                                   ``body__joint``, each joint at its ``pos``
``connect`` (bodies or sites)      ``spherical`` loop at the anchor
``weld`` (bodies or sites)         ``fixed`` loop (``relpose``, else the pose
                                   at qpos0)
``joint`` (``polycoef`` c0 c1)     ``coupling`` loop q1 = c1 q2 + c0
actuator with ``joint=``           ``<transmission>`` (the joint is actuated)
``<option gravity>``               the mechanism's gravity
geoms sphere, box, cylinder,       visuals (a capsule is drawn as a cylinder);
capsule                            mesh, plane, ellipsoid, hfield geoms are
                                   left out
=================================  =============================================

Orientations: ``quat``, ``axisangle``, ``euler`` (``<compiler eulerseq>``),
``xyaxes``, ``zaxis``; angles in ``<compiler angle>`` units (MuJoCo's default,
degrees, included). A body with joints and no ``<inertial>`` is refused when
it has geoms (MuJoCo would infer its inertia from them; closedchain does not),
and so is ``<compiler inertiafromgeom="true">``.

Refused with a message naming the element: ``ball`` joints, a free joint
below the top level, joint ``ref`` other than 0, ``<include>``, ``<frame>``,
``<default>`` classes that set joint, inertial or equality attributes,
equality types other than connect, weld and joint, a ``joint`` equality
without ``joint2`` or with nonzero ``polycoef`` beyond c1. Ignored:
``solref``/``solimp`` (closedchain's constraints are exact), joint
``damping``, ``stiffness``, ``armature`` and ``frictionloss`` (logged), contacts,
tendons, sensors, cameras, lights, and inactive (``active="false"``)
equalities (logged).

Parsing is as safe as the URDF reader's (no DTD, no network, size-bounded):
:func:`closedchain.urdf.read_xml`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin
from lxml import etree

from .exceptions import URDFError
from .urdf import WORLD_LINK, read_xml

logger = logging.getLogger(__name__)

#: Root element of an MJCF file.
MJCF_ROOT = "mujoco"

#: Limits [rad or m] written for an unlimited hinge or slide (URDF's revolute and
#: prismatic joints need limits): beyond any motion, within closedchain's bound on
#: coordinates (``closedchain.mechanism.COORDINATE_BOUND``).
UNLIMITED_RANGE = 1e4

#: MuJoCo's default gravity [m/s^2].
MJCF_GRAVITY = (0.0, 0.0, -9.81)

#: Joint types of MJCF and their URDF counterparts.
JOINT_TYPES = {"hinge": "revolute", "slide": "prismatic", "free": "floating"}

#: Equality types read (the others are refused).
EQUALITY_TYPES = ("connect", "weld", "joint")

#: Elements refused anywhere in the file (their content would change the model).
REFUSED_ELEMENTS = ("include", "frame", "composite", "flexcomp", "replicate", "attach")

#: Children of ``<default>`` that would change the mechanism (closedchain applies no defaults).
REFUSED_DEFAULTS = ("joint", "inertial", "equality", "connect", "weld")

#: Number of polynomial coefficients of a ``joint`` equality (c0..c4).
POLYCOEF_SIZE = 5

#: Joint attributes of passive forces and rotor inertia that closedchain does not model:
#: nonzero values are logged as ignored (the dynamics differ from MuJoCo's by them).
IGNORED_JOINT_ATTRIBUTES = ("damping", "stiffness", "armature", "frictionloss")

#: Geom types drawn as visuals.
VISUAL_GEOMS = ("sphere", "box", "cylinder", "capsule")


@dataclass(frozen=True)
class MjcfModel:
    """An MJCF file translated to URDF+.

    Attributes:
        robot: the ``<robot>`` element (for :func:`closedchain.urdf.parse_urdf`).
        gravity: ``<option gravity>`` [m/s^2], shape (3,).
    """

    robot: etree._Element
    gravity: np.ndarray


def read_model(path: Path) -> tuple[etree._Element, np.ndarray | None]:
    """Read a URDF or MJCF file safely; return its ``<robot>`` element and the file's gravity.

    Args:
        path: a URDF file (root ``<robot>``) or an MJCF file (root ``<mujoco>``).

    Returns:
        The URDF+ root element (MJCF translated by :func:`mjcf_to_urdf`) and the
        gravity the file sets [m/s^2], shape (3,), or None (URDF sets none).

    Raises:
        URDFError: unsafe or malformed XML, or an MJCF element closedchain cannot read.
    """
    root = read_xml(path)
    if root.tag != MJCF_ROOT:
        return root, None
    model = mjcf_to_urdf(path, root)
    return model.robot, model.gravity


class _Reader:
    """The state of one translation: compiler settings, bodies, sites, joints."""

    def __init__(self, path: Path, root) -> None:
        self.path = path
        self.root = root
        compiler = root.find("compiler")
        get = (lambda k, d: compiler.get(k, d)) if compiler is not None else (lambda k, d: d)
        angle = get("angle", "degree")
        if angle not in ("degree", "radian"):
            self.fail(compiler, f"angle={angle!r}; valid: degree, radian")
        self.angle_scale = math.pi / 180.0 if angle == "degree" else 1.0
        self.eulerseq = get("eulerseq", "xyz")
        if len(self.eulerseq) != 3 or any(c not in "xyzXYZ" for c in self.eulerseq):
            self.fail(compiler, f"eulerseq={self.eulerseq!r}; valid: three of x, y, z, X, Y, Z")
        if get("coordinate", "local") != "local":
            self.fail(compiler, 'coordinate="global" is not supported; valid: local')
        self.inertia_from_geom = get("inertiafromgeom", "auto")
        if self.inertia_from_geom == "true":
            self.fail(
                compiler,
                'inertiafromgeom="true" replaces the <inertial> elements by geom inertias, '
                'which closedchain does not compute; valid: "auto" or "false"',
            )
        self.robot = etree.Element("robot", name=root.get("model", path.stem))
        #: body name -> (link name, link_from_body SE3, oMb at qpos0 SE3).
        self.bodies: dict[str, tuple[str, pin.SE3, pin.SE3]] = {}
        #: site name -> (link name, placement in the link frame).
        self.sites: dict[str, tuple[str, pin.SE3]] = {}
        self.count = 0

    # -- messages ------------------------------------------------------------
    def where(self, element) -> str:
        name = element.get("name") if element is not None else None
        tag = (
            "<?>"
            if element is None
            else f"<{element.tag}" + (f" name={name!r}>" if name is not None else ">")
        )
        line = element.sourceline if element is not None else "?"
        return f"{self.path}: line {line}: {tag}"

    def fail(self, element, message: str):
        raise URDFError(f"{self.where(element)}: {message}")

    # -- numbers -------------------------------------------------------------
    def numbers(self, element, attribute: str, n: int, default: str | None = None):
        text = element.get(attribute, default)
        if text is None:
            return None
        try:
            values = np.array([float(x) for x in text.split()])
        except ValueError:
            values = np.array([])
        if values.shape != (n,) or not np.all(np.isfinite(values)):
            self.fail(element, f"{attribute}={text!r} must be {n} finite numbers")
        return values

    def rotation(self, element) -> np.ndarray:
        """Return the rotation of a body, geom, site or inertial (MJCF's orientation rules)."""
        given = [a for a in ("quat", "axisangle", "euler", "xyaxes", "zaxis") if element.get(a)]
        if len(given) > 1:
            self.fail(element, f"more than one orientation ({', '.join(given)}); give one")
        if not given:
            return np.eye(3)
        kind = given[0]
        if kind == "quat":
            w, x, y, z = self.numbers(element, "quat", 4)
            q = pin.Quaternion(w, x, y, z)
            if q.norm() == 0.0:
                self.fail(element, "quat is zero; valid: a non-zero quaternion w x y z")
            q.normalize()
            return q.toRotationMatrix()
        if kind == "axisangle":
            values = self.numbers(element, "axisangle", 4)
            return pin.exp3(self.unit(element, values[:3]) * values[3] * self.angle_scale)
        if kind == "euler":
            angles = self.numbers(element, "euler", 3) * self.angle_scale
            R = np.eye(3)
            for axis, a in zip(self.eulerseq, angles, strict=True):
                Ri = pin.exp3(np.eye(3)["xyz".index(axis.lower())] * a)
                R = R @ Ri if axis.islower() else Ri @ R
            return R
        if kind == "xyaxes":
            values = self.numbers(element, "xyaxes", 6)
            x = self.unit(element, values[:3])
            y = values[3:] - x * float(x @ values[3:])
            y = self.unit(element, y)
            return np.column_stack([x, y, np.cross(x, y)])
        z = self.unit(element, self.numbers(element, "zaxis", 3))
        return pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), z).toRotationMatrix()

    def unit(self, element, v: np.ndarray) -> np.ndarray:
        norm = float(np.linalg.norm(v))
        if norm == 0.0 or not math.isfinite(norm):
            self.fail(element, "a direction is zero; valid: a non-zero vector")
        return v / norm

    def pose(self, element) -> pin.SE3:
        """Return the ``pos`` + orientation of an element as an SE3 (in its parent's frame)."""
        return pin.SE3(self.rotation(element), self.numbers(element, "pos", 3, "0 0 0"))

    # -- URDF output ---------------------------------------------------------
    def add(self, parent, tag: str, source=None, **attributes):
        e = etree.SubElement(parent, tag, {k: str(v) for k, v in attributes.items()})
        if source is not None:
            e.sourceline = source.sourceline
        return e

    def origin(self, parent, M: pin.SE3, tag: str = "origin") -> None:
        """Add ``<tag xyz=... rpy=...>`` (a URDF origin) placing M under ``parent``."""
        rpy = pin.rpy.matrixToRpy(M.rotation)
        self.add(parent, tag, xyz=_fmt(M.translation), rpy=_fmt(rpy))

    def name(self, element, prefix: str) -> str:
        name = element.get("name")
        if name:
            return name
        self.count += 1
        return f"{prefix}{self.count}"

    # -- the tree ------------------------------------------------------------
    def link(self, name: str, source, L: pin.SE3 | None, body) -> None:
        """Add a link; with ``body``, its inertial and visuals (``L``: link_from_body)."""
        link = self.add(self.robot, "link", source, name=name)
        if body is None:
            return
        inertial = body.find("inertial")
        if inertial is not None:
            self.inertial(link, inertial, L)
        elif (
            body.tag == "body"
            and body.findall("geom")
            and self.inertia_from_geom != "false"
            and (body.findall("joint") or body.findall("freejoint"))
        ):
            self.fail(
                body,
                "has joints and geoms but no <inertial>: MuJoCo infers its inertia "
                "from the geoms, which closedchain does not; valid: give an <inertial>",
            )
        for geom in body.findall("geom"):
            self.visual(link, geom, L)

    def inertial(self, link, inertial, L: pin.SE3) -> None:
        mass = self.numbers(inertial, "mass", 1)
        if mass is None:
            self.fail(inertial, "missing mass=")
        R = self.rotation(inertial)
        diag = self.numbers(inertial, "diaginertia", 3)
        full = self.numbers(inertial, "fullinertia", 6)
        if (diag is None) == (full is None):
            self.fail(inertial, "give one of diaginertia= and fullinertia=")
        if diag is not None:
            I_body = R @ np.diag(diag) @ R.T
        else:
            ixx, iyy, izz, ixy, ixz, iyz = full
            I_body = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        # Inertia about the centre of mass in link-aligned axes (L only translates).
        com = L.act(self.numbers(inertial, "pos", 3, "0 0 0"))
        I_link = L.rotation @ I_body @ L.rotation.T
        e = self.add(link, "inertial", inertial)
        self.origin(e, pin.SE3(np.eye(3), com))
        self.add(e, "mass", inertial, value=repr(float(mass[0])))
        keys = {"ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2)}
        keys["izz"] = (2, 2)
        self.add(e, "inertia", inertial, **{k: repr(float(I_link[ij])) for k, ij in keys.items()})

    def visual(self, link, geom, L: pin.SE3) -> None:
        kind = geom.get("type", "sphere")
        if kind not in VISUAL_GEOMS:
            logger.info("%s: geom type %r is not drawn", self.where(geom), kind)
            return
        text = geom.get("size", "0")
        try:
            size = [float(x) for x in text.split()]
        except ValueError:
            size = []
        if not 1 <= len(size) <= 3 or not all(map(math.isfinite, size)):
            self.fail(geom, f"size={text!r} must be 1 to 3 finite numbers")
        fromto = self.numbers(geom, "fromto", 6)
        if fromto is not None and kind in ("cylinder", "capsule", "box"):
            a, b = fromto[:3], fromto[3:]
            length = float(np.linalg.norm(b - a))
            if length == 0.0:
                return
            R = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), (b - a) / length)
            M = pin.SE3(R.toRotationMatrix(), (a + b) / 2.0)
            half = length / 2.0
        else:
            M = self.pose(geom)
            half = size[1] if len(size) > 1 else 0.0
        visual = self.add(link, "visual", geom)
        self.origin(visual, L * M)
        shape = self.add(visual, "geometry", geom)
        if kind == "sphere":
            self.add(shape, "sphere", geom, radius=repr(float(size[0])))
        elif kind == "box":
            sizes = (size * 3)[:3] if len(size) < 3 else size[:3]
            if fromto is not None:
                sizes = [size[0], size[-1] if len(size) > 1 else size[0], half]
            self.add(shape, "box", geom, size=_fmt(2.0 * np.array(sizes)))
        else:  # cylinder, capsule (drawn as its cylinder)
            self.add(
                shape, "cylinder", geom, radius=repr(float(size[0])), length=repr(float(2.0 * half))
            )

    def body(self, body, parent_link: str, parent_L: pin.SE3, oMparent: pin.SE3, top: bool) -> None:
        """Translate one ``<body>`` and its subtree (see the module docstring)."""
        name = self.name(body, "body")
        X = self.pose(body)  # body frame in the parent body frame
        oMb = oMparent * X
        joints = [j for j in body if isinstance(j.tag, str) and j.tag in ("joint", "freejoint")]
        specs = []
        for j in joints:
            kind = "free" if j.tag == "freejoint" else j.get("type", "hinge")
            if kind == "ball":
                self.fail(
                    j,
                    "ball joints are not supported (URDF has no spherical joint); valid: "
                    "hinge, slide, free (write a ball as three hinges)",
                )
            if kind not in JOINT_TYPES:
                self.fail(j, f"unknown joint type {kind!r}; valid: {', '.join(JOINT_TYPES)}")
            if kind == "free" and not (top and len(joints) == 1):
                self.fail(j, "a free joint must be the only joint of a top-level body")
            ref = self.numbers(j, "ref", 1, "0")
            if ref[0] != 0.0:
                self.fail(j, "ref= other than 0 is not supported (qpos0 is the zero of q)")
            specs.append((j, kind, self.numbers(j, "pos", 3, "0 0 0")))
        shift = np.zeros(3)
        link = parent_link
        origin = parent_L * X
        for k, (j, kind, pos) in enumerate(specs):
            jname = self.name(j, f"{name}_joint")
            child = name if k == len(specs) - 1 else f"{name}__{jname}"
            self.add_joint(j, jname, JOINT_TYPES[kind], link, child, origin * _shift(pos - shift))
            if child != name:
                self.link(child, j, None, None)
            link, origin, shift = child, pin.SE3.Identity(), pos
        L = _shift(-shift)  # link frame from body frame
        if not specs:
            fixed = self.add(self.robot, "joint", body, name=f"{name}_fixed", type="fixed")
            self.origin(fixed, origin)
            self.add(fixed, "parent", body, link=parent_link)
            self.add(fixed, "child", body, link=name)
        self.link(name, body, L, body)
        self.bodies[name] = (name, L, oMb)
        self.collect_sites(body, name, L)
        for child in body.findall("body"):
            self.body(child, name, L, oMb, top=False)

    def add_joint(self, j, name: str, kind: str, parent: str, child: str, M: pin.SE3) -> None:
        joint = self.add(self.robot, "joint", j, name=name, type=kind)
        self.origin(joint, M)
        self.add(joint, "parent", j, link=parent)
        self.add(joint, "child", j, link=child)
        ignored = [a for a in IGNORED_JOINT_ATTRIBUTES if self.numbers(j, a, 1, "0")[0] != 0.0]
        if ignored:
            logger.warning(
                "%s: %s ignored (closedchain models no joint damping, stiffness, friction "
                "or armature)",
                self.where(j),
                ", ".join(f"{a}={j.get(a)}" for a in ignored),
            )
        if kind == "floating":
            return
        self.add(joint, "axis", j, xyz=_fmt(self.numbers(j, "axis", 3, "0 0 1")))
        rng = self.numbers(j, "range", 2, "0 0")
        limited = j.get("limited", "auto")
        if limited not in ("auto", "true", "false"):
            self.fail(j, f"limited={limited!r}; valid: auto, true, false")
        if limited == "true" or (limited == "auto" and j.get("range") is not None):
            if kind == "revolute":
                rng = rng * self.angle_scale
            if rng[0] >= rng[1]:
                self.fail(j, f"range={j.get('range')!r} is empty; valid: lower < upper")
        else:
            rng = np.array([-UNLIMITED_RANGE, UNLIMITED_RANGE])
        self.add(
            joint,
            "limit",
            j,
            lower=repr(float(rng[0])),
            upper=repr(float(rng[1])),
            effort="0",
            velocity="0",
        )

    def collect_sites(self, body, link: str, L: pin.SE3) -> None:
        for site in body.findall("site"):
            name = site.get("name")
            if name:
                self.sites[name] = (link, L * self.pose(site))

    # -- equalities ----------------------------------------------------------
    def frame_of(self, eq, side: str) -> tuple[str, pin.SE3, pin.SE3]:
        """Return (link, link_from_body, oMb) of ``body1``/``body2`` (body2 defaults to world)."""
        default = WORLD_LINK if side == "body2" else None
        body = eq.get(side, default)
        if body not in self.bodies:
            self.fail(
                eq, f"{side}={body!r} names no body; bodies: {', '.join(sorted(self.bodies))}"
            )
        return self.bodies[body]

    def site(self, eq, side: str) -> tuple[str, pin.SE3]:
        name = eq.get(side)
        if name not in self.sites:
            self.fail(eq, f"{side}={name!r} names no site; sites: {', '.join(sorted(self.sites))}")
        return self.sites[name]

    def loop(self, eq, kind: str, ends) -> None:
        loop = self.add(self.robot, "loop", eq, name=self.name(eq, f"{eq.tag}"), type=kind)
        for (link, M), side in zip(ends, ("predecessor", "successor"), strict=True):
            self.add(loop, side, eq, link=link)
            self.origin(loop, M, f"{side}_origin")

    def equality(self, eq) -> None:
        if eq.get("active", "true") == "false":
            logger.warning('%s: inactive (active="false"): left out', self.where(eq))
            return
        if eq.tag not in EQUALITY_TYPES:
            self.fail(
                eq, f"equality type <{eq.tag}> is not supported; valid: {', '.join(EQUALITY_TYPES)}"
            )
        if eq.tag == "joint":
            self.coupling(eq)
            return
        if eq.get("site1") is not None or eq.get("site2") is not None:
            ends = [self.site(eq, "site1"), self.site(eq, "site2")]
        else:
            (l1, L1, o1), (l2, L2, o2) = self.frame_of(eq, "body1"), self.frame_of(eq, "body2")
            if eq.tag == "connect":
                anchor = pin.SE3(np.eye(3), self.numbers(eq, "anchor", 3, "0 0 0"))
                # body2's point is where the anchor is at qpos0 (MuJoCo's rule).
                ends = [(l1, L1 * anchor), (l2, L2 * o2.inverse() * o1 * anchor)]
            else:
                relpose = self.numbers(eq, "relpose", 7, "0 1 0 0 0 0 0")
                if np.any(relpose[3:] != 0.0):  # body2's pose in body1
                    b1Mb2 = pin.SE3(pin.Quaternion(*relpose[3:]).normalized().matrix(), relpose[:3])
                else:  # the pose at qpos0
                    b1Mb2 = o1.inverse() * o2
                ends = [(l1, L1 * b1Mb2), (l2, L2)]
        self.loop(eq, "spherical" if eq.tag == "connect" else "fixed", ends)

    def coupling(self, eq) -> None:
        j1, j2 = eq.get("joint1"), eq.get("joint2")
        if j2 is None:
            self.fail(eq, "a joint equality without joint2 (a locked joint) is not supported")
        coef = self.numbers(eq, "polycoef", POLYCOEF_SIZE, "0 1 0 0 0")
        if np.any(coef[2:] != 0.0):
            self.fail(
                eq,
                f"polycoef={eq.get('polycoef')!r}: only a linear coupling q1 = c0 + c1 q2 is "
                "supported; valid: c2 = c3 = c4 = 0",
            )
        loop = self.add(self.robot, "loop", eq, name=self.name(eq, "joint"), type="coupling")
        self.add(loop, "joint", eq, name=j1)
        self.add(
            loop,
            "mimics",
            eq,
            joint=j2,
            multiplier=repr(float(coef[1])),
            offset=repr(float(coef[0])),
        )

    # -- the whole file ------------------------------------------------------
    def translate(self) -> MjcfModel:
        root = self.root
        for tag in REFUSED_ELEMENTS:
            for e in root.iter(tag):
                self.fail(e, f"<{tag}> is not supported by closedchain's MJCF reader")
        for default in root.iter("default"):
            for e in default:
                if isinstance(e.tag, str) and e.tag in REFUSED_DEFAULTS:
                    self.fail(
                        e,
                        f"a <default> <{e.tag}> would change the mechanism and closedchain "
                        f"applies no defaults; valid defaults: those of {', '.join(VISUAL_GEOMS)} "
                        "geoms, sites and visuals (write the attributes on the elements)",
                    )
        worldbodies = root.findall("worldbody")
        if len(worldbodies) != 1:
            self.fail(root, f"needs exactly one <worldbody>, found {len(worldbodies)}")
        world = worldbodies[0]
        self.link(WORLD_LINK, world, pin.SE3.Identity(), world)
        self.bodies[WORLD_LINK] = (WORLD_LINK, pin.SE3.Identity(), pin.SE3.Identity())
        self.collect_sites(world, WORLD_LINK, pin.SE3.Identity())
        for body in world.findall("body"):
            self.body(body, WORLD_LINK, pin.SE3.Identity(), pin.SE3.Identity(), top=True)
        for equality in root.findall("equality"):
            for eq in equality:
                if isinstance(eq.tag, str):
                    self.equality(eq)
        self.transmissions()
        gravity = np.array(MJCF_GRAVITY)
        for option in root.findall("option"):
            gravity = self.numbers(option, "gravity", 3, _fmt(gravity))
        return MjcfModel(robot=self.robot, gravity=gravity)

    def transmissions(self) -> None:
        seen = []
        for actuator in self.root.findall("actuator"):
            for act in actuator:
                joint = act.get("joint") if isinstance(act.tag, str) else None
                if joint is None or joint in seen:
                    continue
                seen.append(joint)
                t = self.add(self.robot, "transmission", act, name=self.name(act, "actuator"))
                self.add(t, "type", act).text = "transmission_interface/SimpleTransmission"
                self.add(t, "joint", act, name=joint)


def mjcf_to_urdf(path: Path, root) -> MjcfModel:
    """Translate a parsed MJCF ``<mujoco>`` element to URDF+ (rule: module docstring).

    Args:
        path: the file, for messages.
        root: its ``<mujoco>`` element.

    Raises:
        URDFError: an element closedchain cannot read (the message names file, line,
            element and the valid choices).
    """
    return _Reader(path, root).translate()


def _shift(p: np.ndarray) -> pin.SE3:
    return pin.SE3(np.eye(3), np.asarray(p, dtype=float))


def _fmt(x) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(x))
