"""Read the URDF+ extension elements: ``<loop>``, ``<transmission>``, ``independent``.

This module reads, with a hardened lxml parser, the URDF tree into a
:class:`closedchain.description.TreeDescription` (placements as SE3 from the
origins, joints, limits, inertias and visuals, as Pinocchio's URDF reader takes
them; :func:`closedchain.build.build_model` builds it) and what URDF readers
ignore, URDF+ (Chignoli et al. 2024):

.. code-block:: xml

    <loop name="C" type="revolute">
      <predecessor link="coupler"/>
      <successor link="rocker"/>
      <predecessor_origin xyz="0.4 0 0" rpy="0 0 0"/>
      <successor_origin xyz="0.3 0 0" rpy="0 0 0"/>
      <axis xyz="0 0 1"/>
    </loop>

A *coupling* loop ties two 1-dof joints (a gear, a mimic joint) with the
one row ``q_j = multiplier q_i + offset``:

.. code-block:: xml

    <loop name="finger" type="coupling">
      <joint name="right_finger_joint"/>
      <mimics joint="left_finger_joint" multiplier="-1" offset="0"/>
    </loop>

and a standard URDF ``<mimic joint="i" multiplier="m" offset="c"/>`` inside
``<joint name="j">`` is read as the same loop, named ``j`` + :data:`MIMIC_SUFFIX`
(the joint itself stays an ordinary joint of the tree). See :func:`parse_urdf`.

A joint spring (:class:`JointSpring`, generalized force -k (q - q0)) is written in
the joint's ``<dynamics>``, with the names of SDF's elements:
``<dynamics damping="0" spring_stiffness="1500" spring_reference="0"/>``; its standard
``damping`` is the joint's viscous damping (:class:`JointDamping`, generalized force
-d v), and closedchain's ``armature`` its rotor inertia (:class:`JointArmature`, added
to the mass matrix's diagonal, as MuJoCo's joint ``armature``):
``<dynamics damping="0.5" armature="0.01"/>``. All act in the dynamics
(:mod:`closedchain.passive`).

A side may name any frame of the tree instead of a link, ``<predecessor
frame="closedloop1_A"/>`` (a link, or a joint's frame); the origin is then in
that frame, and :func:`closedchain.load` resolves the side to a link.

Parsing is safe: no DTD is accepted (so no entity expansion and no external
entities), no network access, no huge trees. What the parser accepts, refuses
and warns about is stated in :func:`parse_urdf`.
"""

from __future__ import annotations

import difflib
import logging
import math
import re
import unicodedata
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pinocchio as pin
from lxml import etree

from ._io import MAX_XML_BYTES, read_input_bytes
from .description import (
    LIMITED_KINDS,
    NEUTRAL_Q0,
    BodyDescription,
    JointDescription,
    MechanismDescription,
    TreeDescription,
    Visual,
)
from .exceptions import ModelFileError, ModelTooLargeError, quoted, shorten

__all__ = [
    "COUPLING",
    "LOOP_TYPES",
    "JointArmature",
    "JointDamping",
    "JointSpring",
    "LoopSpec",
    "SceneSpec",
    "SinusoidSpec",
    "parse_urdf",
    "read_xml",
]

logger = logging.getLogger(__name__)

#: Loop-joint types and the relative motion each allows.
LOOP_TYPES = ("revolute", "prismatic", "spherical", "fixed", "coupling")

#: Loop type of a joint coupling ``q_j = multiplier q_i + offset`` (one row, no frames).
COUPLING = "coupling"

#: Joint types a coupling may tie (one coordinate each, angle or length, no wrap).
COUPLING_JOINT_TYPES = ("revolute", "prismatic")

#: Joint types a spring may act on (one coordinate each, angle or length, no wrap).
SPRING_JOINT_TYPES = COUPLING_JOINT_TYPES

#: Attributes of a joint's ``<dynamics>`` that make a spring (closedchain's extension of
#: URDF, which has none; the names are SDF's ``<dynamics>`` children).
SPRING_ATTRIBUTES = ("spring_stiffness", "spring_reference")

#: Suffix of the name of the coupling loop a ``<mimic>`` element becomes.
MIMIC_SUFFIX = "_mimic"

#: Reserved link name a ``<loop>`` may use for the fixed world (Pinocchio's
#: universe) when the tree has no link of that name: with a free-flyer or
#: planar root the URDF's root link moves, and this is what stays put.
WORLD_LINK = "world"

#: Largest |multiplier| of a coupling ``q_j = m q_i + c`` (a URDF ``<mimic>``, an MJCF
#: ``polycoef``): a gear ratio of a million. Beyond it the coupling row dwarfs the others
#: in J and M + alpha J^T J overflows (1e150: divisions by zero in the step, 1e300:
#: overflow in the assembly).
COUPLING_MULTIPLIER_MAX = 1e6

#: Largest |offset| c of a coupling [rad or m]: the largest coordinate a configuration
#: may hold (``closedchain.mechanism.COORDINATE_BOUND``).
COUPLING_OFFSET_MAX = 1e6

#: Largest |component| [m] of an ``xyz`` origin: far beyond any mechanism, far
#: below where the squares of lengths overflow (1e154 m).
ORIGIN_XYZ_MAX = 1e6

#: Largest |angle| [rad] of an ``rpy`` origin: a few hundred turns, where the
#: angle still has all the digits a rotation needs.
ORIGIN_RPY_MAX = 1e3

#: Top-level elements of standard URDF (other top-level elements get a warning).
URDF_ELEMENTS = ("link", "joint", "material", "transmission", "gazebo")

#: Top-level elements URDF+ and closedchain add.
URDF_PLUS_ELEMENTS = ("loop", "scene")

#: Elements that are read only as children of ``<robot>`` (anywhere else they are refused).
TOP_LEVEL_ONLY = URDF_PLUS_ELEMENTS

#: Elements whose content is not URDF (SDF for Gazebo): nothing inside them is checked.
FOREIGN_ELEMENTS = ("gazebo",)

#: Children of the closedchain elements (any other child is refused).
LOOP_CHILDREN = ("predecessor", "successor", "predecessor_origin", "successor_origin", "axis")
COUPLING_CHILDREN = ("joint", "mimics")
SCENE_CHILDREN = ("initial", "track")
TRACK_CHILDREN = ("sinusoid",)

#: Children of a standard ``<transmission>`` (others get a warning, near misses are refused).
TRANSMISSION_CHILDREN = ("type", "joint", "actuator")

#: Similarity (difflib ratio, case folded) from which an unknown element name is
#: taken for a misspelling of a known one and refused: ``<Loop>``, ``<transmision>``
#: and ``<scnee>`` are, ``<plugin>`` (0.6 to ``link``) and ``<sensor>`` are not.
NEAR_MISS_CUTOFF = 0.75

#: Unicode categories refused in names: control characters (newline, tab, ...)
#: and line and paragraph separators, which would split a message.
NAME_REFUSED_CATEGORIES = ("Cc", "Zl", "Zp")

#: Relative tolerance of the positive-definiteness check of an ``<inertia>``:
#: its smallest eigenvalue must exceed ``-INERTIA_REL_TOL * max |eigenvalue|``
#: (zero eigenvalues are point masses and thin rods, which URDF allows).
INERTIA_REL_TOL = 1e-12

#: ``<limit>`` attributes and whether each must be non-negative.
#: Largest |velocity=| [rad/s or m/s] of a ``<scene>`` ``<initial>``: beyond it the
#: kinetic terms (quadratic in v) leave the range where a step resolves anything.
SCENE_RATE_BOUND = 1e6

LIMIT_ATTRIBUTES = {"lower": False, "upper": False, "effort": True, "velocity": True}


@dataclass(frozen=True)
class LoopSpec:
    """One loop-closure joint as written in the URDF.

    A side written ``<predecessor frame="..."/>`` names any frame of the tree
    (a link, or a joint's frame: fixed or movable); :func:`closedchain.load`
    resolves it to the link the frame is attached to and the origin in that
    link's frame, so that once loaded every side is a link and an origin.

    Attributes:
        name: loop name (the ``name`` attribute).
        type: one of :data:`LOOP_TYPES`.
        predecessor: name of the predecessor link (before ``load`` resolves a
            ``frame=`` side: the frame's name).
        successor: name of the successor link (idem).
        predecessor_origin: placement of the cut-joint frame c1 in the predecessor link
            frame (before ``load`` resolves a ``frame=`` side: in that frame).
        successor_origin: placement of the cut-joint frame c2 in the successor link frame
            (idem).
        axis: unit joint axis, shape (3,), in frame c1 (unused for spherical and fixed).
        joint: coupling loops: the driven joint j (``<joint name>``), else "".
        mimics: coupling loops: the driving joint i (``<mimics joint>``), else "".
        multiplier: coupling loops: m of ``q_j = m q_i + c`` [-, or m/rad, rad/m
            between a revolute and a prismatic joint].
        offset: coupling loops: c of ``q_j = m q_i + c`` [rad or m, as q_j].
        line: source line of the ``<loop>`` element, for error messages (0: none,
            e.g. a loop read from a YAML file).
        predecessor_frame: the frame ``<predecessor frame=...>`` names, or None
            (``link=``).
        successor_frame: idem for ``<successor>``.

    A coupling loop's predecessor and successor are the child links of ``mimics``
    and ``joint`` (where its frames are put; its row reads the joints' coordinates).
    """

    name: str
    type: str
    predecessor: str
    successor: str
    predecessor_origin: pin.SE3
    successor_origin: pin.SE3
    axis: np.ndarray
    line: int = 0
    joint: str = ""
    mimics: str = ""
    multiplier: float = 1.0
    offset: float = 0.0
    predecessor_frame: str | None = None
    successor_frame: str | None = None

    def where(self, path: Path | str) -> str:
        """Return ``"{path}: line {n}: <loop name='...'>"`` (without the line when unknown)."""
        line = f" line {self.line}:" if self.line else ""
        return f"{path}:{line} <loop name={quoted(self.name)}>"


@dataclass(frozen=True)
class SinusoidSpec:
    """A reference ``offset + amplitude sin(2 pi frequency t)`` for one joint of a scene.

    Attributes:
        joint: a 1-dof joint name.
        offset: [rad or m].
        amplitude: [rad or m].
        frequency: [Hz].
    """

    joint: str
    offset: float
    amplitude: float
    frequency: float


@dataclass(frozen=True)
class SceneSpec:
    """The default scene of a mechanism (closedchain's ``<scene>`` element).

    What ``closedchain simulate/animate/plot`` run when no ``--q0`` is given:
    the initial configuration guess, and optionally computed-torque tracking
    of sinusoidal references (see :mod:`closedchain.control`).

    .. code-block:: xml

        <scene>
          <initial joint="crank_joint" value="0.1745" velocity="0"/>
          <track kp="100" kd="20">
            <sinusoid joint="platform_yaw" offset="0" amplitude="0.8" frequency="0.1"/>
          </track>
        </scene>

    Attributes:
        initial: joint name -> initial value guess [rad or m] (assembled onto
            phi = 0 holding the tracked joints, else the independent ones).
        velocity: joint name -> initial velocity [rad/s or m/s] (``velocity=``
            of ``<initial>``, passive scenes only): held while the other
            coordinates take the velocity with J v = 0 (the joints given must
            determine it, e.g. the independent ones).
        track: the tracked joints' references (empty: a passive motion).
        kp: position gain [1/s^2] of the tracking controller.
        kd: velocity gain [1/s] of the tracking controller.
        line: source line of the ``<scene>`` element.
    """

    initial: dict[str, float] = field(default_factory=dict)
    velocity: dict[str, float] = field(default_factory=dict)
    track: tuple[SinusoidSpec, ...] = ()
    kp: float = 0.0
    kd: float = 0.0
    line: int = 0


@dataclass(frozen=True)
class JointSpring:
    """A linear spring on a 1-dof joint: generalized force -stiffness (q - reference).

    Written ``<dynamics damping="0" spring_stiffness="1500" spring_reference="0"/>``
    inside the ``<joint>`` (the SDF reader fills it from SDF's ``<dynamics>``).

    Attributes:
        joint: the joint's name (revolute or prismatic).
        stiffness: [N m/rad or N/m], >= 0.
        reference: the coordinate where it exerts no force [rad or m].
        line: source line of the ``<dynamics>`` (0: written by a reader).
    """

    joint: str
    stiffness: float
    reference: float
    line: int = 0


@dataclass(frozen=True)
class JointDamping:
    """Viscous damping on a joint: generalized force -damping v_j on each of its coordinates.

    Read from URDF ``<dynamics damping>``, SDF ``<dynamics><damping>`` and MJCF joint
    ``damping``.

    Attributes:
        joint: the joint's name.
        damping: [N m s/rad or N s/m], >= 0.
        line: source line (0: written by a reader without lines).
    """

    joint: str
    damping: float
    line: int = 0


@dataclass(frozen=True)
class JointArmature:
    """Reflected rotor inertia of a joint, added to the mass matrix diagonal.

    MuJoCo's joint ``armature`` and Pinocchio's ``model.armature`` (one value per
    coordinate of the joint): M[i, i] += armature for each of the joint's v indices.
    Read from MJCF joint ``armature`` and closedchain's URDF ``<dynamics armature>``.

    Attributes:
        joint: the joint's name.
        armature: [kg m^2 or kg], >= 0.
        line: source line (0: written by a reader without lines).
    """

    joint: str
    armature: float
    line: int = 0


#: Former name of :class:`closedchain.description.MechanismDescription` (the same
#: class), kept for existing code.
URDFPlus = MechanismDescription


#: One item of an XML prolog before a DOCTYPE: the XML declaration, a
#: processing instruction or a comment, with surrounding white space.
_PROLOG_ITEM = re.compile(rb"\s*(?:<\?.*?\?>|<!--.*?-->)", re.DOTALL)


def _declares_doctype(raw: bytes) -> bool:
    """Return whether the document's prolog holds a ``<!DOCTYPE``, before any parsing.

    libxml2 substitutes internal entities referenced in attribute values even
    with ``resolve_entities=False`` (bounded only by its amplification limit),
    so a DTD must be refused before the parser sees it.
    """
    pos = 3 if raw.startswith(b"\xef\xbb\xbf") else 0  # UTF-8 byte order mark
    while (m := _PROLOG_ITEM.match(raw, pos)) is not None:
        pos = m.end()
    return raw[pos:].lstrip().startswith(b"<!DOCTYPE")


def _safe_parser() -> etree.XMLParser:
    return etree.XMLParser(
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        huge_tree=False,
        remove_comments=False,
    )


def _tag(element) -> str:
    """Return ``<tag name='...'>`` (the name with ``repr``: one line), or ``<tag>``."""
    name = element.get("name")
    return f"<{element.tag} name={quoted(name)}>" if name is not None else f"<{element.tag}>"


def _line(element) -> str:
    """Return ``" line {n}:"`` of an element read from a file, or "" (one written by a
    conversion, such as a loops YAML file's)."""
    return f" line {element.sourceline}:" if element.sourceline else ""


def _where(path: Path, element) -> str:
    """Return ``"{path}: line {n}: <tag name='...'>"``: where a message is about (one line)."""
    return f"{path}:{_line(element)} {_tag(element)}"


def _three(text: str) -> np.ndarray | None:
    """Return the three numbers of an attribute's text, shape (3,), or None if it holds others."""
    try:
        values = [float(x) for x in text.split()]
    except ValueError:
        return None
    return np.array(values) if len(values) == 3 else None


def _floats(path: Path, element, attribute: str, default: str, where: str = "") -> np.ndarray:
    """Return an attribute of three finite numbers, shape (3,), or raise naming it."""
    text = element.get(attribute, default)
    values = _three(text)
    if values is None or not np.all(np.isfinite(values)):
        prefix = f"{where} <{element.tag}>" if where else _where(path, element)
        raise ModelFileError(
            f"{prefix}: attribute {attribute}={quoted(text)} must be three finite numbers"
        )
    return values


def _origin_values(path: Path, origin, where: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Return (xyz [m], rpy [rad]) of an origin element, each finite and within its bound.

    Raises:
        ModelFileError: an attribute is not three finite numbers, or is beyond
            :data:`ORIGIN_XYZ_MAX` or :data:`ORIGIN_RPY_MAX` (the message names
            the attribute and the bound).
    """
    prefix = f"{where} <{origin.tag}>" if where else _where(path, origin)
    out = []
    for attribute, name, bound, unit in (
        ("xyz", "ORIGIN_XYZ_MAX", ORIGIN_XYZ_MAX, "m"),
        ("rpy", "ORIGIN_RPY_MAX", ORIGIN_RPY_MAX, "rad"),
    ):
        values = _floats(path, origin, attribute, "0 0 0", where)
        if float(np.max(np.abs(values))) > bound:
            raise ModelFileError(
                f"{prefix}: attribute {attribute}={origin.get(attribute)!r} is beyond "
                f"{name} = {bound:g} {unit}; valid: |components| <= {bound:g} {unit}"
            )
        out.append(values)
    return out[0], out[1]


def _unit_axis(path: Path, axis, where: str) -> np.ndarray:
    """Return the unit vector of an ``<axis xyz=...>``, shape (3,), without overflow.

    The components are scaled by the largest |component| before the norm is
    taken, so every finite non-zero axis (1e308 or 1e-320 included) gives its
    direction; numpy's plain norm overflows to inf past 1e154 and the axis
    becomes zero.

    Raises:
        ModelFileError: the attribute is not three numbers, is not finite or is zero.
    """
    text = axis.get("xyz", "1 0 0")
    return unit_vector(text, f"{where}: <axis xyz={quoted(text)}>")


def unit_vector(text: str, what: str) -> np.ndarray:
    """Return the unit vector of a text of three numbers, shape (3,), without overflow.

    See :func:`_unit_axis`; shared with the SDF reader (:mod:`closedchain.sdf`).

    Args:
        text: three numbers separated by white space.
        what: where the text is, the start of every message (file, line, element).

    Raises:
        ModelFileError: the text is not three numbers, is not finite or is zero.
    """
    xyz = _three(text)
    if xyz is None:
        raise ModelFileError(f"{what} must be three numbers")
    if not np.all(np.isfinite(xyz)):
        raise ModelFileError(f"{what} is not finite; valid: three finite numbers")
    scale = float(np.max(np.abs(xyz)))
    if scale == 0.0:
        raise ModelFileError(f"{what} is zero; valid: a direction with a non-zero component")
    unit = xyz / scale  # largest |component| is 1: the norm below is in [1, sqrt(3)]
    return unit / math.sqrt(float(unit @ unit))


#: Names an error message lists before it shortens the list to "... and N more".
MAX_LISTED_NAMES = 30


def name_list(names, *, limit: int = MAX_LISTED_NAMES, keep_order: bool = False) -> str:
    """Return the sorted names, comma separated, the ones past ``limit`` counted, not listed.

    Args:
        names: the valid names (any iterable of str; duplicates are listed once).
        limit: names listed at most.
        keep_order: list them in the order given (first occurrences), not sorted.
    """
    unique = list(dict.fromkeys(names)) if keep_order else sorted(set(names))
    shown = ", ".join(shorten(name) for name in unique[:limit])
    return shown if len(unique) <= limit else f"{shown}, ... and {len(unique) - limit} more"


def _check_name(path: Path, element, kind: str) -> str:
    """Return the ``name`` of a robot, link, joint, loop or transmission, refusing control chars.

    Args:
        path: the file, for messages.
        element: the element.
        kind: what it is (``"joint"``), for messages.

    Raises:
        ModelFileError: no name, or a name holding a character of
            :data:`NAME_REFUSED_CATEGORIES` (shown with ``repr``, on one line).
    """
    name = element.get("name")
    if not name:
        raise ModelFileError(f"{_where(path, element)}: <{element.tag}> needs a name attribute")
    bad = [c for c in name if unicodedata.category(c) in NAME_REFUSED_CATEGORIES]
    if bad:
        raise ModelFileError(
            f"{_where(path, element)}: the {kind} name contains the control character "
            f"{bad[0]!r} (U+{ord(bad[0]):04X}); valid: names of printable characters"
        )
    return name


def _unique_names(path: Path, elements, kind: str) -> tuple[str, ...]:
    """Return the checked names of ``elements``, refusing one used twice (naming both lines)."""
    first: dict[str, int] = {}
    for e in elements:
        name = _check_name(path, e, kind)
        if name in first:
            raise ModelFileError(
                f"{_where(path, e)}: duplicate {kind} name"
                + (f", first used at line {first[name]}" if first[name] else "")
                + f"; every {kind} needs its own name"
            )
        first[name] = e.sourceline or 0
    return tuple(first)


def _near_miss(tag: str, known: tuple[str, ...]) -> str | None:
    """Return the known element name ``tag`` misspells (:data:`NEAR_MISS_CUTOFF`), or None."""
    match = difflib.get_close_matches(tag.casefold(), known, n=1, cutoff=NEAR_MISS_CUTOFF)
    return match[0] if match else None


def _check_children(path: Path, element, known: tuple[str, ...], *, strict: bool) -> None:
    """Refuse a child of ``element`` that misspells a known one; refuse or warn on others.

    Args:
        path: the file, for messages.
        element: the parent element.
        known: the valid child element names.
        strict: refuse every unknown child (closedchain's own elements), else
            warn about the ones that are not near misses (standard URDF
            elements, which tools may extend).
    """
    for child in element:
        if not isinstance(child.tag, str) or child.tag in known:  # comments, PIs
            continue
        where = _where(path, child)
        inside = "" if element.tag == "robot" else f" in <{element.tag}>"
        close = _near_miss(child.tag, known) if "}" not in child.tag else None
        if close is not None:
            raise ModelFileError(
                f"{where}: unknown element{inside} (it would be ignored); did you mean <{close}>?"
            )
        if strict:
            raise ModelFileError(
                f"{where}: unknown element{inside}; valid: {', '.join(f'<{k}>' for k in known)}"
            )
        logger.warning("%s: not a URDF or URDF+ element%s; ignored", where, inside)


def _check_layout(path: Path, root) -> None:
    """Refuse misplaced or misspelled URDF+ elements; warn about unknown top-level ones.

    See :func:`parse_urdf` for the rule.
    """
    _check_children(path, root, URDF_ELEMENTS + URDF_PLUS_ELEMENTS, strict=False)
    for e in root.iter(*TOP_LEVEL_ONLY):
        parent = e.getparent()
        if parent is root or any(a.tag in FOREIGN_ELEMENTS for a in e.iterancestors()):
            continue
        raise ModelFileError(
            f"{_where(path, e)}: inside {_tag(parent)}: a <{e.tag}> "
            "is read only as a child of <robot> (here it would be ignored)"
        )


def _number(
    where: str,
    element,
    attribute: str,
    *,
    minimum: float | None = None,
    bound: float | None = None,
) -> float | None:
    """Return a finite float attribute (None when absent), or raise naming where and attribute.

    Args:
        where: location prefix of the message (file, line, enclosing element).
        element: the element holding the attribute.
        attribute: attribute name.
        minimum: smallest valid value, or None.
        bound: largest valid absolute value, or None.
    """
    text = element.get(attribute)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or (minimum is not None and value < minimum):
        valid = "a finite number" if minimum is None else f"a finite number >= {minimum:g}"
        raise ModelFileError(f"{where} <{element.tag} {attribute}={quoted(text)}>: must be {valid}")
    if bound is not None and abs(value) > bound:
        raise ModelFileError(
            f"{where} <{element.tag} {attribute}={quoted(text)}>: must be within +-{bound:g}"
        )
    return value


def _check_inertial(path: Path, link) -> None:
    """Refuse an ``<inertial>`` whose mass or inertia is not a physical one.

    urdfdom only warns about these and Pinocchio then builds a massless or
    wrong link, so every dynamics result would be wrong without a word.
    """
    inertial = link.find("inertial")
    if inertial is None:
        return
    where = f"{path}:{_line(inertial)} {_tag(link)} <inertial>"
    origin = inertial.find("origin")
    if origin is not None:
        _origin_values(path, origin, where)
    mass = inertial.find("mass")
    if mass is None or mass.get("value") is None:
        raise ModelFileError(f"{where}: missing <mass value=...>")
    _number(where, mass, "value", minimum=0.0)
    inertia = inertial.find("inertia")
    if inertia is None:
        raise ModelFileError(f"{where}: missing <inertia ixx=... iyy=... izz=...>")
    values = {n: _number(where, inertia, n) or 0.0 for n in INERTIA_ATTRIBUTES}
    check_inertia(where, values)


#: Attributes of an ``<inertia>`` [kg m^2] (a missing one is 0).
INERTIA_ATTRIBUTES = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")

#: What :func:`check_inertia` does with a violated triangle inequality.
TRIANGLE_CHOICES = ("refuse", "warn")


def check_inertia(where: str, values: dict[str, float], *, triangle: str = "refuse") -> None:
    """Refuse a rotational inertia that no mass distribution has.

    Args:
        where: the start of every message (file, line, element).
        values: ``ixx, ixy, ixz, iyy, iyz, izz`` [kg m^2], finite.
        triangle: a violated triangle inequality is refused or logged as a
            warning (one of :data:`TRIANGLE_CHOICES`). The mass matrix stays
            positive definite either way: the SDF reader warns (Cassie ships such
            rotors).

    Raises:
        ModelFileError: not positive semi-definite, or principal moments that
            violate the triangle inequality (both within :data:`INERTIA_REL_TOL`).
    """
    inertia_matrix = np.array(
        [
            [values["ixx"], values["ixy"], values["ixz"]],
            [values["ixy"], values["iyy"], values["iyz"]],
            [values["ixz"], values["iyz"], values["izz"]],
        ]
    )
    eig = np.linalg.eigvalsh(inertia_matrix)
    if eig[0] < -INERTIA_REL_TOL * max(1.0, float(np.max(np.abs(eig)))):
        raise ModelFileError(
            f"{where}: <inertia> is not positive semi-definite (eigenvalues "
            f"{np.array2string(eig, precision=6)} kg m^2); a rigid body's rotational "
            "inertia has non-negative eigenvalues"
        )
    # Triangle inequality of principal moments (a real mass distribution).
    tol = INERTIA_REL_TOL * max(1.0, float(eig[-1]))
    if eig[0] + eig[1] < eig[2] - tol:
        message = (
            f"{where}: <inertia> principal moments {np.array2string(eig, precision=6)} kg m^2 "
            "violate the triangle inequality I1 + I2 >= I3 (no mass distribution has them)"
        )
        if triangle == "refuse":
            raise ModelFileError(message)
        logger.warning("%s; kept", message)


#: Joint types whose motion is defined by ``<axis>`` (its length must not vanish).
AXIS_JOINT_TYPES = ("revolute", "continuous", "prismatic", "planar")


def _check_joint(path: Path, joint) -> None:
    """Refuse a ``<joint>`` with a bad origin, a zero or non-finite axis or NaN limits.

    The axis is normalized by scaling first (:func:`unit_vector`), where a plain
    norm of e.g. ``0 -1e200 0`` overflows and leaves the axis zero.
    """
    where = _where(path, joint)
    origin = joint.find("origin")
    if origin is not None:
        _origin_values(path, origin, where)
    axis = joint.find("axis")
    # URDF ignores the axis of fixed and floating joints (Talos writes 0 0 0 there).
    if axis is not None and joint.get("type") in AXIS_JOINT_TYPES:
        _unit_axis(path, axis, where)
    elif axis is not None:
        _floats(path, axis, "xyz", "1 0 0", where)
    limit = joint.find("limit")
    if limit is not None:
        bounds = {
            a: _number(where, limit, a, minimum=0.0 if nonneg else None)
            for a, nonneg in LIMIT_ATTRIBUTES.items()
        }
        lower, upper = bounds["lower"], bounds["upper"]
        if lower is not None and upper is not None and lower > upper:
            raise ModelFileError(f"{where} <limit>: lower={lower:g} exceeds upper={upper:g}")


def _origin(path: Path, element) -> pin.SE3:
    xyz, rpy = _origin_values(path, element)
    return pin.SE3(pin.rpy.rpyToMatrix(rpy), xyz)


#: Velocity-space dimension of each URDF joint type (unknown types: Pinocchio refuses them).
URDF_JOINT_NV = {
    "revolute": 1,
    "continuous": 1,
    "prismatic": 1,
    "fixed": 0,
    "planar": 3,
    "floating": 6,
}


def read_xml(path: Path, *, what: str = "URDF file"):
    """Parse an XML file safely and return its root element.

    Args:
        path: the file.
        what: what the file is, for messages ("URDF file", "overlay file").

    Raises:
        ModelFileError: the file is missing, is not a regular file, is larger than
            :data:`closedchain._io.MAX_XML_BYTES`, is not well-formed XML or
            declares a DTD.
    """
    raw = read_input_bytes(path, limit=MAX_XML_BYTES, what=what, error=ModelFileError)
    if _declares_doctype(raw):
        raise ModelFileError(
            f"{path}: a DOCTYPE/DTD is not allowed in the {what} (entity expansion is refused)"
        )
    try:
        root = etree.fromstring(raw, _safe_parser(), base_url=str(path))
    except etree.XMLSyntaxError as exc:
        raise ModelFileError(f"{path}: malformed XML: {exc}") from exc
    docinfo = root.getroottree().docinfo
    if docinfo.internalDTD is not None or docinfo.doctype:
        raise ModelFileError(
            f"{path}: a DOCTYPE/DTD is not allowed in the {what} (entity expansion is refused)"
        )
    return root


def check_tree_size(where: str, joints: int, nv: int, max_nv: int | None) -> None:
    """Refuse a tree of ``joints`` joints with ``nv`` degrees of freedom beyond ``max_nv``.

    Raises:
        ModelTooLargeError: ``nv > max_nv`` (None: no bound); the message starts with
            ``where``.
    """
    if max_nv is not None and nv > max_nv:
        raise ModelTooLargeError(
            f"{where}: {joints} joints with nv = {nv} degrees of freedom are beyond "
            f"the supported size; valid: nv <= {max_nv}",
            nv=nv,
            max_nv=max_nv,
        )


def parse_urdf(
    path: str | Path, *, element=None, max_nv: int | None = None
) -> MechanismDescription:
    """Read a URDF file and its URDF+ extension elements.

    Args:
        path: URDF file.
        element: an already parsed ``<robot>`` element to read instead of the
            file (used by :func:`closedchain.robots.merge_overlay`); ``path``
            then only names it in messages.
        max_nv: largest supported number of degrees of freedom of the tree
            (sum over joints of :data:`URDF_JOINT_NV`); a larger tree is
            refused right after the XML is read, before any per-element work.

    Returns:
        The model: its tree as a description (see :func:`tree_order` for the
        order of its bodies) and the URDF+ extensions.

    Raises:
        ModelFileError: the file is missing, is not well-formed XML, declares a DTD,
            or an element is invalid (unknown loop type, unknown link, zero
            axis, transmission naming a missing joint, ...). The message names
            the file, line and element and the valid choices.

    Which elements are read, refused or warned about:

    - Top level (children of ``<robot>``): the URDF elements
      :data:`URDF_ELEMENTS` and the URDF+ ones :data:`URDF_PLUS_ELEMENTS`.
      An unknown name that misspells one of them (:data:`NEAR_MISS_CUTOFF`,
      case folded: ``<Loop>``, ``<transmision>``, ``<scnee>``) is refused with
      "did you mean"; any other unknown name gets a ``logging`` warning naming
      file and line, and is ignored (as URDF tools ignore it).
    - A ``<loop>`` or ``<scene>`` anywhere but as a child of ``<robot>`` is
      refused: ignoring it would silently change the mechanism. The content of
      ``<gazebo>`` (SDF) is not looked at.
    - Children of ``<loop>``, ``<scene>`` and ``<track>``: only
      :data:`LOOP_CHILDREN`, :data:`SCENE_CHILDREN`, :data:`TRACK_CHILDREN`.
      Children of ``<transmission>``: :data:`TRANSMISSION_CHILDREN`; a near
      miss of them is refused, any other child warned about.
    - Names of links, joints, loops and transmissions (and of the robot, if
      given): present, without control characters (:data:`NAME_REFUSED_CATEGORIES`); link and joint
      names unique (a duplicate names both lines). Messages quote names
      with ``repr``, so they stay one line.
    - ``<loop type="coupling">`` (see the module docstring): one ``<joint name>``
      and one ``<mimics joint multiplier offset>`` (defaults 1 and 0), two
      different revolute or prismatic joints (:data:`COUPLING_JOINT_TYPES`;
      continuous joints are refused: their angle wraps). A ``<mimic>`` inside a
      ``<joint>`` is the same loop (URDF's defaults: multiplier 1, offset 0),
      named after the joint with :data:`MIMIC_SUFFIX`; the ``<mimic>`` of a
      fixed joint couples nothing and is left out (logged).
    - ``<dynamics damping armature>`` of a movable joint: a :class:`JointDamping`
      (viscous damping on each of its coordinates) and a :class:`JointArmature`
      (closedchain's extension, as MuJoCo's joint ``armature``), each finite and >= 0,
      as ``friction``, which is not modelled (a log line names it); on a fixed joint
      they are logged and left out; an ``armature`` without ``damping`` or ``friction``
      beside it (urdfdom refuses that) is refused.
    - ``<dynamics spring_stiffness spring_reference>`` of a revolute or prismatic
      joint (:data:`SPRING_JOINT_TYPES`): a :class:`JointSpring`; a stiffness that is
      negative or not finite, a reference without a stiffness, another joint type, or
      no ``damping``/``friction`` beside them (urdfdom refuses that) is refused.
    - Numbers: origins finite and within :data:`ORIGIN_XYZ_MAX` [m] and
      :data:`ORIGIN_RPY_MAX` [rad]; axes finite and not zero, normalized by
      scaling first (an axis of 1e308 is a direction).
    - The tree, as urdfdom (Pinocchio's URDF reader) refuses what is not one:
      joint types :data:`URDF_JOINT_TYPES`; every joint's parent and child links
      exist, every link but one (the root) is the child of exactly one joint, no
      cycle; a revolute or prismatic joint has a ``<limit>``, and every ``<limit>``
      an ``effort`` and a ``velocity``. A missing ``lower`` or ``upper`` is 0 (as
      urdfdom reads it).
    - ``<visual>``: box, cylinder, sphere and mesh geometries (others are not
      drawn), their sizes finite and >= 0 (a mesh's scale may mirror), a
      ``<material>``'s colour inline or by the name of a top-level one.
    """
    path = Path(path)
    root = read_xml(path) if element is None else element
    if root.tag != "robot":
        raise ModelFileError(f"{path}: root element is <{root.tag}>, expected <robot>")

    link_elements, joint_elements = root.findall("link"), root.findall("joint")
    if not link_elements:
        raise ModelFileError(f"{path}: <robot> has no <link> elements")
    nv = sum(URDF_JOINT_NV.get(e.get("type"), 0) for e in joint_elements)
    check_tree_size(str(path), len(joint_elements), nv, max_nv)
    return _read_robot(path, root)


def read_overlay(base: MechanismDescription, path: Path, root) -> MechanismDescription:
    """Return a base model with an overlay's links, joints, loops and transmissions merged.

    The overlay's elements are checked as :func:`parse_urdf` checks a file's (messages
    name the overlay and its lines), may name the base's links and joints, and add
    bodies to its description; the base keeps its bodies, loops, transmissions,
    scene and passive terms.

    Args:
        base: the base model, read (any reader's: its ``description`` is merged into).
        path: the overlay file, for messages.
        root: the overlay's ``<robot>`` element (checked by the caller: only overlay
            elements, no name the base uses).
    Returns:
        The merged model, named after the overlay (``path``; ``robot_name``: the
        overlay's ``<robot name>``, else the base's).

    Raises:
        ModelFileError: see :func:`parse_urdf`; an overlay joint whose child is a link the
            base's tree already holds.
    """
    return _read_robot(path, root, base=base)


def _read_robot(
    path: Path, root, *, base: MechanismDescription | None = None
) -> MechanismDescription:
    """Return what a ``<robot>`` element says, merged into ``base`` (None: a whole file)."""
    _check_layout(path, root)
    if root.get("name") is not None:  # optional: the file's stem stands in
        _check_name(path, root, "robot")
    link_elements, joint_elements = root.findall("link"), root.findall("joint")
    links = (*(base.links if base else ()), *_unique_names(path, link_elements, "link"))
    _unique_names(path, joint_elements, "joint")
    joints = {
        **(base.joints if base else {}),
        **{e.get("name"): e.get("type") for e in joint_elements},
    }
    for link in link_elements:
        _check_inertial(path, link)
        for origin in (*link.findall("visual/origin"), *link.findall("collision/origin")):
            _origin_values(path, origin, f"{_where(path, link)} <{origin.getparent().tag}>")
    for joint in joint_elements:
        _check_joint(path, joint)

    # A loop may name the world (WORLD_LINK) even when no link has that name.
    loop_links = links if WORLD_LINK in links else (*links, WORLD_LINK)
    children = {} if base is None else _children(base.tree)
    children.update(
        {
            e.get("name"): e.find("child").get("link")
            for e in joint_elements
            if e.find("child") is not None
        }
    )
    loops = (base.loops if base else ()) + tuple(
        _parse_coupling(path, e, joints, children)
        if e.get("type") == COUPLING
        else _parse_loop(path, e, loop_links)
        for e in root.findall("loop")
    )
    mimicking = [e for e in joint_elements if e.find("mimic") is not None]
    for e in mimicking:
        if e.get("type") == "fixed":  # no coordinate to couple (Talos' reduced grippers)
            logger.info("%s: fixed joint: its <mimic> couples nothing", _where(path, e))
    loops += tuple(
        _parse_mimic(path, e, joints, children) for e in mimicking if e.get("type") != "fixed"
    )
    names = [lp.name for lp in loops]
    for name in set(names):
        if names.count(name) > 1:
            raise ModelFileError(f"{path}: loop name {quoted(name)} is used more than once")

    actuated = list(base.actuated if base else ())
    actuated += [j for j in _parse_transmissions(path, root, joints) if j not in actuated]

    independent: list[str] = list(base.independent if base else ())
    for je in root.findall("joint"):
        flag = je.get("independent")
        if flag is None:
            continue
        if flag not in ("true", "false"):
            raise ModelFileError(
                f'{_where(path, je)}: independent={quoted(flag)} must be "true" or "false"'
            )
        if flag == "true":
            if je.get("type") == "fixed":
                raise ModelFileError(f"{_where(path, je)}: a fixed joint cannot be independent")
            independent.append(je.get("name"))

    scenes = root.findall("scene")
    if len(scenes) > 1:
        raise ModelFileError(f"{_where(path, scenes[1])}: more than one <scene> (at most one)")
    scene = _parse_scene(path, scenes[0], joints) if scenes else (base.scene if base else None)
    springs = tuple(
        spring for je in joint_elements if (spring := _parse_spring(path, je, joints)) is not None
    )
    dynamics = [_parse_dynamics(path, je, joints) for je in joint_elements]
    dampings = tuple(d for d, _ in dynamics if d is not None)
    armatures = tuple(r for _, r in dynamics if r is not None)
    name = root.get("name", base.robot_name if base else path.stem)
    return MechanismDescription(
        path=path,
        tree=_describe(path, root, name, base.tree if base else None),
        robot_name=name,
        links=links,
        joints=joints,
        loops=loops,
        actuated=tuple(actuated),
        independent=tuple(independent),
        scene=scene,
        springs=(base.springs if base else ()) + springs,
        dampings=(base.dampings if base else ()) + dampings,
        armatures=(base.armatures if base else ()) + armatures,
        link_files=dict(base.link_files) if base else {},
    )


def _children(description: TreeDescription) -> dict[str, str]:
    """Return joint name -> the body it holds, for every joint of a description."""
    out = {b.fixed_joint: b.name for b in description.bodies if b.fixed_joint}
    out.update({j.name: b.name for b in description.bodies for j in b.joints})
    return out


#: Description joint kind of each movable URDF joint type.
URDF_JOINT_KINDS = {
    "revolute": "revolute",
    "continuous": "continuous",
    "prismatic": "prismatic",
    "planar": "planar",
    "floating": "floating",
}

#: Every URDF joint type (urdfdom refuses any other).
URDF_JOINT_TYPES = (*URDF_JOINT_KINDS, "fixed")

#: URDF joint types whose ``<limit>`` gives position limits, which they must have.
LIMITED_JOINT_TYPES = ("revolute", "prismatic")

#: URDF joint types whose ``<limit effort velocity>`` and ``<dynamics damping
#: friction>`` Pinocchio's URDF reader keeps (one coordinate each).
ONE_DOF_JOINT_TYPES = ("revolute", "continuous", "prismatic")


def _inertia(path: Path, link) -> pin.Inertia:
    """Return a checked ``<inertial>``'s inertia in the link frame (zero without one)."""
    inertial = link.find("inertial")
    if inertial is None:
        return pin.Inertia.Zero()
    origin = inertial.find("origin")
    placement = pin.SE3.Identity() if origin is None else _origin(path, origin)
    mass = float(inertial.find("mass").get("value"))
    values = {n: float(inertial.find("inertia").get(n, "0")) for n in INERTIA_ATTRIBUTES}
    rotational = np.array(
        [
            [values["ixx"], values["ixy"], values["ixz"]],
            [values["ixy"], values["iyy"], values["iyz"]],
            [values["ixz"], values["iyz"], values["izz"]],
        ]
    )
    rotation = placement.rotation
    # Set field by field: Pinocchio's Python constructor refuses a rotational inertia
    # with an eigenvalue of -1e-20 (round-off of a file's numbers, which its URDF
    # reader and check_inertia's tolerance accept).
    inertia = pin.Inertia.Zero()
    inertia.mass = mass
    inertia.lever = placement.translation
    inertia.inertia = rotation @ rotational @ rotation.T
    return inertia


def _joint_description(path: Path, joint) -> JointDescription:
    """Return a checked movable ``<joint>``'s description (limits as urdfdom reads them)."""
    kind = URDF_JOINT_KINDS[joint.get("type")]
    where = _where(path, joint)
    axis_element = joint.find("axis")
    axis = (
        np.array([1.0, 0.0, 0.0]) if axis_element is None else _unit_axis(path, axis_element, where)
    )
    bounds: dict[str, float] = {}
    limit = joint.find("limit")
    if limit is not None:
        bounds = {a: _number(where, limit, a) for a in LIMIT_ATTRIBUTES}
    friction = damping = 0.0
    dynamics = joint.find("dynamics")
    if dynamics is not None:
        friction = _number(where, dynamics, "friction") or 0.0
        damping = _number(where, dynamics, "damping") or 0.0
    one_dof = joint.get("type") in ONE_DOF_JOINT_TYPES
    return JointDescription(
        name=joint.get("name"),
        kind=kind,
        axis=axis,
        q0=NEUTRAL_Q0[kind],
        # urdfdom reads a missing lower or upper as 0.
        lower=(bounds.get("lower") or 0.0) if kind in LIMITED_KINDS else -np.inf,
        upper=(bounds.get("upper") or 0.0) if kind in LIMITED_KINDS else np.inf,
        effort=bounds["effort"] if one_dof and limit is not None else np.inf,
        velocity=bounds["velocity"] if one_dof and limit is not None else np.inf,
        friction=friction if one_dof else 0.0,
        damping=damping if one_dof else 0.0,
    )


#: Entries of a colour (r, g, b, a).
RGBA_SIZE = 4

#: Geometries of a ``<visual>`` that are drawn (others, such as a capsule, are not).
VISUAL_GEOMETRIES = ("box", "cylinder", "sphere", "mesh")


def _numbers(
    where: str, element, attribute: str, count: int, *, signed: bool = False
) -> tuple[float, ...]:
    """Return ``count`` finite numbers (>= 0 unless ``signed``) of an attribute, or raise
    naming it."""
    text = element.get(attribute)
    try:
        values = tuple(float(x) for x in (text or "").split())
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) and (signed or v >= 0.0) for v in values):
        valid = "finite number(s)" if signed else "finite number(s) >= 0"
        raise ModelFileError(
            f"{where} <{element.tag} {attribute}={quoted(text)}>: must be {count} {valid}"
        )
    return values


def _material_rgba(path: Path, material, named: dict[str, tuple[float, ...]]):
    """Return a ``<material>``'s colour (r, g, b, a) clipped to [0, 1], its named
    top-level material's, or None (none given)."""
    if material is None:
        return None
    color = material.find("color")
    if color is None:
        return named.get(material.get("name"))
    text = color.get("rgba")
    try:
        numbers = [float(x) for x in (text or "").split()]
    except ValueError:
        numbers = []
    if len(numbers) != RGBA_SIZE or not all(math.isfinite(x) for x in numbers):
        raise ModelFileError(
            f"{_where(path, material)} <color rgba={quoted(text)}>: must be "
            f"{RGBA_SIZE} finite numbers"
        )
    return tuple(float(np.clip(x, 0.0, 1.0)) for x in numbers)


def _materials(path: Path, root) -> dict[str, tuple[float, ...]]:
    """Return the colours of the top-level ``<material name>`` elements."""
    out = {}
    for material in root.findall("material"):
        rgba = _material_rgba(path, material, {})
        if rgba is not None:
            out[material.get("name")] = rgba
    return out


def _visuals(path: Path, link, named: dict[str, tuple[float, ...]]) -> tuple[Visual, ...]:
    """Return a ``<link>``'s drawn ``<visual>`` shapes (see :class:`Visual`); a mesh keeps
    its filename as written (``package://``, ``file://`` or relative), resolved when drawn
    beside the file that names the link."""
    out = []
    for visual in link.findall("visual"):
        where = _where(path, link) + " <visual>"
        origin = visual.find("origin")
        placement = pin.SE3.Identity() if origin is None else _origin(path, origin)
        geometry = visual.find("geometry")
        shape = None
        if geometry is not None:
            shape = next((g for g in geometry if g.tag in VISUAL_GEOMETRIES), None)
        if shape is None:
            continue
        rgba = _material_rgba(path, visual.find("material"), named)
        if shape.tag == "box":
            out.append(Visual("box", _numbers(where, shape, "size", 3), placement, rgba))
        elif shape.tag == "sphere":
            radius = _numbers(where, shape, "radius", 1)
            out.append(Visual("sphere", radius, placement, rgba))
        elif shape.tag == "cylinder":
            dims = (
                _numbers(where, shape, "radius", 1)[0],
                _numbers(where, shape, "length", 1)[0],
            )
            out.append(Visual("cylinder", dims, placement, rgba))
        else:
            filename = shape.get("filename")
            if not filename:
                raise ModelFileError(f"{where} <mesh>: missing filename=")
            scale = (
                (1.0, 1.0, 1.0)
                if shape.get("scale") is None
                else _numbers(where, shape, "scale", 3, signed=True)
            )
            out.append(Visual("mesh", scale, placement, rgba, filename))
    return tuple(out)


def _tree_edges(
    path: Path, joint_elements, links: tuple[str, ...], held: dict[str, str]
) -> dict[str, object]:
    """Return child link -> its ``<joint>``, refusing what urdfdom refuses: a joint without
    a known type, parent or child, a link it names that does not exist, a link with two
    parent joints, a revolute or prismatic joint without ``<limit>``, a ``<limit>`` without
    effort or velocity. ``held``: link -> the joint already holding it (a base's)."""
    known = set(links)
    held = dict(held)
    parent_joint: dict[str, object] = {}
    for joint in joint_elements:
        where = _where(path, joint)
        jtype = joint.get("type")
        if jtype not in URDF_JOINT_TYPES:
            raise ModelFileError(
                f"{where}: unknown joint type {quoted(jtype)}; valid: {', '.join(URDF_JOINT_TYPES)}"
            )
        ends = {}
        for tag in ("parent", "child"):
            end = joint.find(tag)
            name = None if end is None else end.get("link")
            if name is None:
                raise ModelFileError(f"{where}: missing <{tag} link=...>")
            if name not in known:
                raise ModelFileError(
                    f"{where}: <{tag} link={quoted(name)}> names no <link> of this file; "
                    f"links: {name_list(links)}"
                )
            ends[tag] = name
        if ends["parent"] == ends["child"]:
            raise ModelFileError(
                f"{where}: parent and child are the same link {quoted(ends['child'])}"
            )
        if ends["child"] in held:
            raise ModelFileError(
                f"{where}: link {quoted(ends['child'])} is already the child of joint "
                f"{quoted(held[ends['child']])}; a link has one parent joint (close a loop "
                "with a <loop> element)"
            )
        limit = joint.find("limit")
        if limit is None and jtype in LIMITED_JOINT_TYPES:
            raise ModelFileError(
                f"{where}: a {jtype} joint needs a <limit lower upper effort velocity> "
                "(URDF readers refuse it without)"
            )
        if limit is not None:
            for attribute in ("effort", "velocity"):
                if limit.get(attribute) is None:
                    raise ModelFileError(
                        f"{where} <limit>: missing {attribute}= (URDF readers refuse a "
                        "<limit> without it)"
                    )
        parent_joint[ends["child"]] = joint
        held[ends["child"]] = joint.get("name")
    return parent_joint


def _joint_key(body: BodyDescription) -> str:
    """Return the name of the joint that holds a body to its parent (its own name: none)."""
    return body.fixed_joint or (body.joints[0].name if body.joints else body.name)


def tree_order(
    bodies: Iterable[BodyDescription], *, tops: tuple[str | None, ...] = (None,)
) -> tuple[BodyDescription, ...]:
    """Return the bodies below the top (parent None, or another of ``tops``) depth first,
    each body's children in the order of their joints' names: the order in which
    Pinocchio's URDF reader numbers them (urdfdom keeps the joints in a map sorted by
    name). Bodies that no path from the top reaches (a cycle) are left out."""
    children: dict[str | None, list[BodyDescription]] = {}
    for body in bodies:
        children.setdefault(body.parent, []).append(body)
    out = []
    top = [b for t in tops for b in children.get(t, ())]
    stack = sorted(top, key=_joint_key, reverse=True)
    while stack:
        body = stack.pop()
        out.append(body)
        stack.extend(sorted(children.get(body.name, ()), key=_joint_key, reverse=True))
    return tuple(out)


def _describe(path: Path, root, name: str, base: TreeDescription | None) -> TreeDescription:
    """Return the description of a checked ``<robot>``'s tree, as Pinocchio's URDF reader
    builds it, merged into ``base`` (an overlay's) or whole (None).

    A whole tree and a tree merged into a URDF's are in :func:`tree_order`; a base with
    a world frame (another reader's) keeps its order, the overlay's bodies after it.
    """
    link_elements, joint_elements = root.findall("link"), root.findall("joint")
    bodies = {} if base is None else {b.name: b for b in base.bodies}
    held = {b.name: _joint_key(b) for b in bodies.values() if b.parent is not None}
    world_frame = base is not None and base.world_frame
    links = (*bodies, *(e.get("name") for e in link_elements))
    if world_frame:  # the world is a body the overlay's joints may hang from
        links = (*links, WORLD_LINK)
    parent_joint = _tree_edges(path, joint_elements, links, held)
    named = _materials(path, root)
    own = {e.get("name"): e for e in link_elements}
    for link, element in own.items():  # the overlay's links: on no joint yet
        bodies[link] = BodyDescription(
            link,
            None,
            pin.SE3.Identity(),
            inertia=_inertia(path, element),
            visuals=_visuals(path, element, named),
        )
    for child, joint in parent_joint.items():
        origin = joint.find("origin")
        fixed = joint.get("type") == "fixed"
        bodies[child] = replace(
            bodies[child],
            parent=joint.find("parent").get("link"),
            placement=pin.SE3.Identity() if origin is None else _origin(path, origin),
            joints=() if fixed else (_joint_description(path, joint),),
            fixed_joint=joint.get("name") if fixed else "",
        )
    roots = [b.name for b in bodies.values() if b.parent is None]
    if len(roots) != (0 if world_frame else 1):
        found = f"{len(roots)} root links ({name_list(roots)})" if roots else "no root link"
        raise ModelFileError(
            f"{path}: the links and joints make no tree: {found}; valid: one root link, "
            "every other link the child of one joint (close loops with <loop> elements)"
        )
    ordered = tree_order(bodies.values(), tops=(None, WORLD_LINK) if world_frame else (None,))
    if world_frame:  # the base's order, then the overlay's bodies
        ordered = (*base.bodies, *(b for b in ordered if b.name in own))
    if len(ordered) != len(bodies):
        reached = {b.name for b in ordered}
        raise ModelFileError(
            f"{path}: the links and joints make no tree: links "
            f"{name_list(n for n in bodies if n not in reached)} are on a cycle of joints, "
            f"not below the root link {quoted(roots[0] if roots else WORLD_LINK)} (close "
            "loops with <loop> elements)"
        )
    return TreeDescription(
        name=name,
        path=path,
        bodies=tuple(ordered),
        world_visuals=base.world_visuals if base else (),
        sites=base.sites if base else (),
        keyframes=base.keyframes if base else {},
        inactive=base.inactive if base else (),
        world_frame=world_frame,
    )


def _parse_transmissions(path: Path, root, joints: dict[str, str]) -> tuple[str, ...]:
    """Return the joints the ``<transmission>`` elements of ``root`` name, in file order
    (joints: name -> type of the tree's joints; a fixed one cannot be actuated)."""
    actuated: list[str] = []
    for trans in root.findall("transmission"):
        _check_name(path, trans, "transmission")
        _check_children(path, trans, TRANSMISSION_CHILDREN, strict=False)
        trans_joints = trans.findall("joint")
        if not trans_joints:
            raise ModelFileError(f"{_where(path, trans)}: has no <joint> child")
        for je in trans_joints:
            jname = je.get("name")
            if jname not in joints:
                raise ModelFileError(
                    f"{_where(path, trans)}: names joint {quoted(jname)}, which is not a <joint> "
                    f"of this file; joints: {', '.join(sorted(joints))}"
                )
            if joints[jname] == "fixed":
                raise ModelFileError(
                    f"{_where(path, trans)}: joint {quoted(jname)} is fixed and cannot be actuated"
                )
            if jname not in actuated:
                actuated.append(jname)
    return tuple(actuated)


def _parse_dynamics(
    path: Path, joint, joints: dict[str, str]
) -> tuple[JointDamping | None, JointArmature | None]:
    """Read a ``<joint>``'s ``<dynamics damping armature>`` (viscous damping [N m s/rad or
    N s/m], rotor inertia [kg m^2 or kg]); log a ``friction`` (Coulomb friction, not
    modelled), and a damping or armature on a fixed joint (no coordinate: left out)."""
    dynamics = joint.find("dynamics")
    if dynamics is None:
        return None, None
    where = _where(path, joint)
    name = joint.get("name")
    damping = _number(where, dynamics, "damping", minimum=0.0)
    armature = _number(where, dynamics, "armature", minimum=0.0)
    friction = _number(where, dynamics, "friction", minimum=0.0)
    if armature is not None and damping is None and friction is None:
        raise ModelFileError(
            f"{where} <dynamics>: URDF readers (urdfdom) refuse a <dynamics> without damping "
            'or friction; add damping="0"'
        )
    if friction:
        logger.info(
            "%s <dynamics friction=%g>: friction loss is not modelled (left out)", where, friction
        )
    if (damping or armature) and joints[name] == "fixed":
        logger.info("%s <dynamics>: a fixed joint has no coordinate: left out", where)
        return None, None
    line = dynamics.sourceline or 0
    return (
        JointDamping(name, damping, line) if damping else None,
        JointArmature(name, armature, line) if armature else None,
    )


def _parse_spring(path: Path, joint, joints: dict[str, str]) -> JointSpring | None:
    """Read the spring of a ``<joint>``'s ``<dynamics spring_stiffness spring_reference>``."""
    dynamics = joint.find("dynamics")
    if dynamics is None or not any(a in dynamics.attrib for a in SPRING_ATTRIBUTES):
        return None
    where = _where(path, joint)
    name = joint.get("name")
    if joints[name] not in SPRING_JOINT_TYPES:
        raise ModelFileError(
            f"{where} <dynamics>: a spring acts on one coordinate without wrap-around, and "
            f"this joint is {joints[name]}; valid joint types: {', '.join(SPRING_JOINT_TYPES)}"
        )
    stiffness = _number(where, dynamics, "spring_stiffness", minimum=0.0)
    if stiffness is None:
        raise ModelFileError(
            f"{where} <dynamics>: spring_reference without spring_stiffness [N m/rad or N/m]"
        )
    if dynamics.get("damping") is None and dynamics.get("friction") is None:
        raise ModelFileError(
            f"{where} <dynamics>: URDF readers (urdfdom) refuse a <dynamics> without damping "
            'or friction; add damping="0"'
        )
    reference = _number(where, dynamics, "spring_reference")
    return JointSpring(
        name, stiffness, 0.0 if reference is None else reference, dynamics.sourceline or 0
    )


def _parse_loop(path: Path, element, links: tuple[str, ...]) -> LoopSpec:
    where = _where(path, element)
    name = _check_name(path, element, "loop")
    _check_children(path, element, LOOP_CHILDREN, strict=True)
    ltype = element.get("type")
    if ltype not in LOOP_TYPES:
        raise ModelFileError(
            f"{where}: unknown loop type {quoted(ltype)}; valid choices: {', '.join(LOOP_TYPES)}"
        )

    def child(tag: str, required: bool = True):
        found = element.findall(tag)
        if len(found) > 1:
            raise ModelFileError(f"{where}: more than one <{tag}>")
        if not found and required:
            raise ModelFileError(f"{where}: missing <{tag}>")
        return found[0] if found else None

    ends, frames = {}, {}
    for tag in ("predecessor", "successor"):
        end = child(tag)
        link, frame = end.get("link"), end.get("frame")
        if (link is None) == (frame is None):
            raise ModelFileError(
                f"{where}: <{tag}> needs exactly one of link= (a link) or frame= (any frame "
                "of the tree: a link or a joint)"
            )
        if frame is not None:  # resolved against Pinocchio's frames by load()
            ends[tag] = frames[tag] = frame
            continue
        if link not in links:
            raise ModelFileError(
                f"{where}: <{tag} link={quoted(link)}> names an unknown link; links: "
                f"{name_list(links)} (or frame= for a joint's frame)"
            )
        ends[tag] = link
    if not frames and ends["predecessor"] == ends["successor"]:
        raise ModelFileError(f"{where}: predecessor and successor are the same link")

    origins = {}
    for tag in ("predecessor_origin", "successor_origin"):
        e = child(tag, required=False)
        origins[tag] = _origin(path, e) if e is not None else pin.SE3.Identity()

    axis_el = child("axis", required=ltype in ("revolute", "prismatic"))
    axis = np.array([1.0, 0.0, 0.0])
    if axis_el is not None:
        axis = _unit_axis(path, axis_el, where)

    return LoopSpec(
        name=name,
        type=ltype,
        predecessor=ends["predecessor"],
        successor=ends["successor"],
        predecessor_origin=origins["predecessor_origin"],
        successor_origin=origins["successor_origin"],
        axis=axis,
        line=element.sourceline or 0,
        predecessor_frame=frames.get("predecessor"),
        successor_frame=frames.get("successor"),
    )


def _coupling_spec(
    where: str, name: str, joint: str, mimics: str, element, joints, children, line: int
) -> LoopSpec:
    """Return the coupling loop ``q_joint = multiplier q_mimics + offset`` of ``element``
    (which holds ``multiplier`` and ``offset``), checking both joints."""
    for jname in (joint, mimics):
        if joints.get(jname) not in COUPLING_JOINT_TYPES:
            valid = sorted(j for j, t in joints.items() if t in COUPLING_JOINT_TYPES)
            found = "no joint of this file" if jname not in joints else f"a {joints[jname]} joint"
            raise ModelFileError(
                f"{where}: a coupling ties 1-dof joints without wrap-around, and "
                f"{quoted(jname)} is {found}; valid: revolute or prismatic joints "
                f"({name_list(valid)})"
            )
    if joint == mimics:
        raise ModelFileError(f"{where}: joint {quoted(joint)} cannot mimic itself")
    multiplier = _number(where, element, "multiplier", bound=COUPLING_MULTIPLIER_MAX)
    offset = _number(where, element, "offset", bound=COUPLING_OFFSET_MAX)
    return LoopSpec(
        name=name,
        type=COUPLING,
        predecessor=children.get(mimics, ""),
        successor=children.get(joint, ""),
        predecessor_origin=pin.SE3.Identity(),
        successor_origin=pin.SE3.Identity(),
        axis=np.array([1.0, 0.0, 0.0]),
        line=line,
        joint=joint,
        mimics=mimics,
        multiplier=1.0 if multiplier is None else multiplier,
        offset=0.0 if offset is None else offset,
    )


def _parse_coupling(path: Path, element, joints: dict[str, str], children) -> LoopSpec:
    """Read ``<loop type="coupling"><joint name/><mimics joint multiplier offset/></loop>``."""
    where = _where(path, element)
    name = _check_name(path, element, "loop")
    _check_children(path, element, COUPLING_CHILDREN, strict=True)
    found = {tag: element.findall(tag) for tag in COUPLING_CHILDREN}
    for tag, items in found.items():
        if len(items) != 1:
            raise ModelFileError(
                f"{where}: a coupling loop needs exactly one <{tag}>, found {len(items)}"
            )
    return _coupling_spec(
        where,
        name,
        found["joint"][0].get("name"),
        found["mimics"][0].get("joint"),
        found["mimics"][0],
        joints,
        children,
        element.sourceline or 0,
    )


def _parse_mimic(path: Path, joint, joints: dict[str, str], children) -> LoopSpec:
    """Read the URDF ``<mimic joint multiplier offset>`` of ``joint`` as a coupling loop."""
    mimics = joint.findall("mimic")
    where = _where(path, joint)
    if len(mimics) > 1:
        raise ModelFileError(f"{where}: more than one <mimic>")
    return _coupling_spec(
        where,
        joint.get("name") + MIMIC_SUFFIX,
        joint.get("name"),
        mimics[0].get("joint"),
        mimics[0],
        joints,
        children,
        mimics[0].sourceline or 0,
    )


#: Joint types a ``<scene>`` may set or track (one coordinate each).
SCENE_JOINT_TYPES = ("revolute", "prismatic")


def _scene_joint(path: Path, element, joints: dict[str, str]) -> str:
    name = element.get("joint")
    if joints.get(name) not in SCENE_JOINT_TYPES:
        valid = sorted(j for j, t in joints.items() if t in SCENE_JOINT_TYPES)
        raise ModelFileError(
            f"{_where(path, element)}: joint={quoted(name)} is not a revolute or prismatic joint "
            f"of this file; valid: {', '.join(valid)}"
        )
    return name


def _parse_scene(path: Path, element, joints: dict[str, str]) -> SceneSpec:
    """Read the ``<scene>`` element (see :class:`SceneSpec`)."""
    where = _where(path, element)
    _check_children(path, element, SCENE_CHILDREN, strict=True)
    initial: dict[str, float] = {}
    velocity: dict[str, float] = {}
    for e in element.findall("initial"):
        name = _scene_joint(path, e, joints)
        value = _number(_where(path, e), e, "value")
        if value is None:
            raise ModelFileError(f"{_where(path, e)}: missing value=")
        initial[name] = value
        rate = _number(_where(path, e), e, "velocity", bound=SCENE_RATE_BOUND)
        if rate is not None:
            velocity[name] = rate
    tracks = element.findall("track")
    if len(tracks) > 1:
        raise ModelFileError(f"{where}: more than one <track>")
    if not tracks:
        return SceneSpec(initial=initial, velocity=velocity, line=element.sourceline or 0)
    if velocity:
        raise ModelFileError(
            f"{where}: <initial velocity=...> is for passive scenes; a <track> starts "
            "from its references' velocity (leave out velocity= or the <track>)"
        )
    track = tracks[0]
    _check_children(path, track, TRACK_CHILDREN, strict=True)
    gains = {}
    for gain in ("kp", "kd"):
        value = _number(_where(path, track), track, gain, minimum=0.0)
        if value is None:
            raise ModelFileError(f"{_where(path, track)}: missing {gain}= (a gain >= 0)")
        gains[gain] = value
    refs = []
    for e in track.findall("sinusoid"):
        w = _where(path, e)
        refs.append(
            SinusoidSpec(
                joint=_scene_joint(path, e, joints),
                offset=_number(w, e, "offset") or 0.0,
                amplitude=_number(w, e, "amplitude") or 0.0,
                frequency=_number(w, e, "frequency", minimum=0.0) or 0.0,
            )
        )
    if not refs:
        raise ModelFileError(f"{_where(path, track)}: has no <sinusoid joint=...> child")
    return SceneSpec(initial=initial, track=tuple(refs), line=element.sourceline or 0, **gains)
