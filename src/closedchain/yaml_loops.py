"""Loops in the YAML convention of example-parallel-robots (Gepetto, BSD-3).

Each robot of that collection is a URDF tree (``robot.urdf``) and a YAML
file (``robot.yaml``) that says how to close it::

    closed_loop: [["closedloop1_A", "closedloop1_B"], ["knee_A", "knee_B"]]
    type: ["6d", "3d"]            # per loop: 6d placements equal, 3d positions equal
    name_mot: ["mot1", "mot2"]    # the actuated joints
    joint_name: ["ankle", "foot"] # optional: joints to convert ...
    joint_type: ["SPHERICAL", "UJOINT_ZY"]  # ... into these

:func:`apply_loops_yaml` turns it into URDF+ in the tree's XML, so that the
rest of closedchain reads one format:

- each pair of ``closed_loop`` becomes a ``<loop>`` between the two frames
  (``<predecessor frame=...>``, any frame of the tree: links, joints, fixed
  joints), named ``A--B``: ``6d`` a ``fixed`` loop, ``3d`` a ``spherical`` one
  (:data:`LOOP_TYPE_OF`, case ignored);
- each joint of ``name_mot`` gets a ``<transmission>``;
- ``joint_type`` rewrites the joints of ``joint_name`` before Pinocchio reads
  the tree (:data:`JOINT_CONVERSIONS`, case ignored; a name of no joint is
  passed over with a logged warning, as the authors' loader passes over it
  silently): ``FIXED`` makes the
  joint fixed at its zero position (the URDF's origin); ``UJOINT_<A><B>``
  replaces it by two revolute joints ``<joint>_<A>`` and ``<joint>_<B>`` about
  the axes A then B of the joint's frame, at its origin, through a massless
  link ``<joint>_<A>_link``; ``SPHERICAL`` by Pinocchio's spherical joint
  ``<joint>`` (a unit quaternion in q, 3 entries of v), at the joint's origin;
- three revolute joints in a row through massless links at one point, the
  way the convention's URDFs write a ball joint, become one spherical joint
  named after the last (:func:`find_ball_chains`), as the authors' loader
  fuses them: left as Euler angles, massless links between, the mass
  matrix is singular at the middle angle +-pi/2 and ill-conditioned near it;
- a revolute or prismatic joint whose ``<limit>`` gives neither ``lower``
  nor ``upper`` gets no position limits. URDF reads such a limit as [0, 0],
  a locked joint; the convention's robots (exported by onshape-to-robot)
  write every joint so, and the authors' loader ignores limits.

URDF has no spherical joint type, so a ``SPHERICAL`` joint is written into
the XML as three revolute joints ``<joint>_X``, ``_Y``, ``_Z`` through massless
links (what URDF readers such as the drawing see), and :func:`closedchain.load`
fuses them into one ``JointModelSpherical`` (:func:`fuse_spherical_joints`),
as the authors' loader builds it. Left as three revolutes, the joint would be
Euler angles: singular where the middle angle reaches +-pi/2 (the X and Z axes
align and, the links between being massless, the mass matrix loses rank), and
random states near there made the validation against Pinocchio lose 7 digits.

The YAML is read with PyYAML's safe loader (no Python objects, no code).
"""

from __future__ import annotations

import difflib
import logging
import math
import re
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from lxml import etree

from ._io import read_input_bytes
from .exceptions import URDFError, quoted, shorten
from .urdf import NEAR_MISS_CUTOFF, URDFPlus, name_list

__all__ = [
    "LoopsYAML",
    "YAML_SUFFIXES",
    "apply_loops_yaml",
    "is_loops_yaml",
    "read_loops_yaml",
]

if TYPE_CHECKING:
    import pinocchio as pin

logger = logging.getLogger(__name__)

#: File suffixes that mark a ``loops=`` file as YAML (else it is a URDF+ overlay).
YAML_SUFFIXES = (".yaml", ".yml")

#: Keys of the YAML file (any other key is refused).
YAML_KEYS = ("closed_loop", "type", "name_mot", "joint_name", "joint_type")

#: Loop type of each YAML constraint type (keys case folded).
LOOP_TYPE_OF = {"6d": "fixed", "3d": "spherical"}

#: The ``joint_type`` conversions, as the message listing them says.
JOINT_CONVERSIONS = ("SPHERICAL", "FIXED", "UJOINT_<A><B> (A, B two different axes of X, Y, Z)")

#: A U-joint conversion: first and second axis.
_UJOINT = re.compile(r"UJOINT_([XYZ])([XYZ])")

#: Axes of the joint frame, as URDF ``<axis xyz=...>``.
AXIS_XYZ = {"X": "1 0 0", "Y": "0 1 0", "Z": "0 0 1"}

#: Axes of the three revolute joints of a ``SPHERICAL`` conversion, in order.
SPHERICAL_AXES = "XYZ"

#: Position limits [rad] of the revolute joints of a converted joint: +-CONVERTED_JOINT_LIMIT
#: (URDF's revolute joint needs limits; half a turn either way is every orientation).
CONVERTED_JOINT_LIMIT = math.pi

#: Joint types whose ``<limit>`` without lower and upper means no limits (see the module).
UNLIMITED_JOINT_TYPES = ("revolute", "prismatic")

#: Joint types a ``SPHERICAL`` or ``UJOINT`` conversion may replace (one degree of freedom).
CONVERTIBLE_JOINT_TYPES = ("revolute", "continuous", "prismatic")

#: Children of a ``<joint>`` that a conversion keeps (the others describe the old motion).
KEPT_JOINT_CHILDREN = ("origin", "parent", "child")

#: Separator of the two frame names in a loop's name.
LOOP_NAME_SEPARATOR = "--"


@dataclass(frozen=True)
class LoopsYAML:
    """The content of a loops YAML file, checked.

    Attributes:
        path: the file read.
        loops: per ``closed_loop`` pair: (predecessor frame, successor frame,
            loop type of :data:`LOOP_TYPE_OF`).
        motors: the joints of ``name_mot``, in file order.
        conversions: per ``joint_name`` entry: (joint, conversion in upper case).
    """

    path: Path
    loops: tuple[tuple[str, str, str], ...] = ()
    motors: tuple[str, ...] = ()
    conversions: tuple[tuple[str, str], ...] = ()


def is_loops_yaml(path: str | Path) -> bool:
    """Return whether a ``loops=`` file is YAML (:data:`YAML_SUFFIXES`, case ignored)."""
    return Path(path).suffix.lower() in YAML_SUFFIXES


#: Largest loops YAML file read [bytes]. The files of example-parallel-robots are below
#: 1 kB; PyYAML's reader parses about 1 MB/s, so a read stays within a second or two
#: (the XML files' cap, :data:`closedchain._io.MAX_XML_BYTES`, would take a minute).
MAX_YAML_BYTES = 2**20

#: Most aliases (``*name``) a loops YAML file may use: each is a reference to a node
#: already read, and nested ones multiply what a reader that expands them (a message,
#: a copy) would visit.
MAX_YAML_ALIASES = 100

#: Deepest nesting of lists and mappings in a loops YAML file (the convention uses 3:
#: the mapping, ``closed_loop``'s list, its pairs); deeper is refused before the
#: reader's recursion could exhaust Python's stack.
MAX_YAML_DEPTH = 16

#: Longest YAML reader's problem statement quoted in a message [characters].
YAML_PROBLEM_MAX = 200

#: Characters a name may not hold: C0 and C1 control characters (NUL included), lone
#: surrogates and the two non-characters XML refuses.
_BAD_NAME_CHARACTER = re.compile("[\x00-\x1f\x7f-\x9f\ud800-\udfff\ufffe\uffff]")


class _LimitError(Exception):
    """A bound of :func:`_check_events` exceeded, at ``line`` (1-based) of the file."""

    def __init__(self, message: str, line: int) -> None:
        super().__init__(message)
        self.line = line


#: PyYAML's safe loader, its libyaml build when there is one (ten times faster).
_SAFE_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _check_events(text: str) -> None:
    """Refuse more than :data:`MAX_YAML_ALIASES` aliases or nesting deeper than
    :data:`MAX_YAML_DEPTH`, from the parser's events, before anything is built."""
    aliases = depth = 0
    for event in yaml.parse(text, Loader=_SAFE_LOADER):
        if isinstance(event, yaml.AliasEvent):
            aliases += 1
            if aliases > MAX_YAML_ALIASES:
                raise _LimitError(
                    f"more than {MAX_YAML_ALIASES} aliases", event.start_mark.line + 1
                )
        elif isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise _LimitError(
                    f"lists or mappings nested deeper than {MAX_YAML_DEPTH}",
                    event.start_mark.line + 1,
                )
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def _check_name(path: Path, where: str, name: str) -> None:
    """Refuse a name with a control character or a lone surrogate (no XML can hold it)."""
    bad = _BAD_NAME_CHARACTER.search(name)
    if bad is not None:
        raise URDFError(
            f"{path}: {where} = {quoted(name)} holds the character {bad[0]!r}; valid: names "
            "without control characters or lone surrogates"
        )


def _names(path: Path, data: dict, key: str) -> list[str]:
    """Return ``data[key]`` (default empty) as a list of strings, or raise naming the key."""
    value = data.get(key)
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
        raise URDFError(f"{path}: {key} must be a list of names, got {shorten(value)}")
    for i, name in enumerate(value):
        _check_name(path, f"{key}[{i}]", name)
    return value


def _first_repeat(names: list) -> tuple[int, int] | None:
    """Return (first index, repeating index) of the first name given twice, or None."""
    first: dict = {}
    for i, name in enumerate(names):
        j = first.setdefault(name, i)
        if j != i:
            return j, i
    return None


def _load_yaml(path: Path):
    """Return the YAML content of a loops file, read within the bounds of this module."""
    raw = read_input_bytes(path, limit=MAX_YAML_BYTES, what="loops file", error=URDFError)
    try:
        text = raw.decode("utf-8")
        _check_events(text)
        return yaml.load(text, Loader=_SAFE_LOADER)  # noqa: S506 (a safe loader)
    except _LimitError as exc:
        raise URDFError(f"{path}: line {exc.line}: {exc}; valid: a loops file") from None
    except UnicodeDecodeError as exc:
        raise URDFError(f"{path}: not a YAML file: not UTF-8 at byte {exc.start}") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f"line {mark.line + 1}: " if mark is not None else ""
        raise URDFError(
            f"{path}: not a YAML file: {line}{shorten(str(exc.problem), YAML_PROBLEM_MAX)}"
        ) from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an int beyond 4300 digits
        raise URDFError(f"{path}: not a YAML file: {shorten(str(exc), YAML_PROBLEM_MAX)}") from None


def read_loops_yaml(path: str | Path) -> LoopsYAML:
    """Read and check a loops YAML file (see the module docstring).

    Args:
        path: the YAML file.

    Returns:
        Its loops, motors and joint conversions.

    Raises:
        URDFError: the file cannot be read, is not a regular file, is larger than
            :data:`MAX_YAML_BYTES`, is not UTF-8 YAML, uses more than
            :data:`MAX_YAML_ALIASES` aliases or nests deeper than
            :data:`MAX_YAML_DEPTH`; an unknown key (lists the valid ones); a value
            of the wrong shape; a name with a control character; ``closed_loop``
            and ``type`` (or ``joint_name`` and ``joint_type``) of different
            lengths; an unknown constraint type or conversion (lists the valid
            ones); a name given twice.
    """
    path = Path(path)
    data = _load_yaml(path)
    if not isinstance(data, dict):
        raise URDFError(f"{path}: expected a mapping of keys {', '.join(YAML_KEYS)}")
    for key in data:
        if key not in YAML_KEYS:
            raise URDFError(
                f"{path}: unknown key {quoted(key) if isinstance(key, str) else shorten(key)}; "
                f"valid keys: {', '.join(YAML_KEYS)}"
            )

    pairs = data.get("closed_loop") or []
    if not isinstance(pairs, list) or not all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p) for p in pairs
    ):
        raise URDFError(
            f"{path}: closed_loop must be a list of pairs of frame names, got {shorten(pairs)}"
        )
    for i, pair in enumerate(pairs):
        for k, name in enumerate(pair):
            _check_name(path, f"closed_loop[{i}][{k}]", name)
    types = _names(path, data, "type")
    if len(types) != len(pairs):
        raise URDFError(
            f"{path}: closed_loop has {len(pairs)} pairs but type has {len(types)} entries; "
            "valid: one type per pair"
        )
    loops = []
    for i, ((a, b), kind) in enumerate(zip(pairs, types, strict=True)):
        if kind.casefold() not in LOOP_TYPE_OF:
            raise URDFError(
                f"{path}: type[{i}] = {quoted(kind)} is not a constraint type; valid: 6d, 3d"
            )
        if a == b:
            raise URDFError(f"{path}: closed_loop[{i}] pairs frame {quoted(a)} with itself")
        loops.append((a, b, LOOP_TYPE_OF[kind.casefold()]))
    seen: dict[tuple[str, str], int] = {}
    for i, (a, b, _) in enumerate(loops):
        if (a, b) in seen or (b, a) in seen:
            j = seen.get((a, b), seen.get((b, a)))
            raise URDFError(
                f"{path}: closed_loop[{i}] repeats closed_loop[{j}] ({quoted(a)}, {quoted(b)})"
            )
        seen[a, b] = i

    motors = _names(path, data, "name_mot")
    joints = _names(path, data, "joint_name")
    kinds = _names(path, data, "joint_type")
    if len(joints) != len(kinds):
        raise URDFError(
            f"{path}: joint_name has {len(joints)} entries but joint_type has {len(kinds)}; "
            "valid: one type per joint"
        )
    for key, names in (("name_mot", motors), ("joint_name", joints)):
        repeat = _first_repeat(names)
        if repeat is not None:
            j, i = repeat
            raise URDFError(f"{path}: {key}[{i}] repeats {key}[{j}] ({quoted(names[i])})")
    conversions = []
    for i, (joint, kind) in enumerate(zip(joints, kinds, strict=True)):
        upper = kind.upper()
        m = _UJOINT.fullmatch(upper)
        if upper not in ("SPHERICAL", "FIXED") and (m is None or m[1] == m[2]):
            raise URDFError(
                f"{path}: joint_type[{i}] = {quoted(kind)} (joint {quoted(joint)}) is not a "
                f"conversion; valid: {', '.join(JOINT_CONVERSIONS)}"
            )
        conversions.append((joint, upper))
    return LoopsYAML(
        path=path, loops=tuple(loops), motors=tuple(motors), conversions=tuple(conversions)
    )


def apply_loops_yaml(root, loops: LoopsYAML, *, base: Path) -> dict[str, object]:
    """Write a loops YAML file's conversions, loops and motors into a URDF tree, in place.

    Args:
        root: the ``<robot>`` element of the base URDF (modified).
        loops: the checked YAML content (:func:`read_loops_yaml`).
        base: the base URDF file, for messages.

    Returns:
        What :func:`edit_model` does once Pinocchio has read the tree, as
        fields of :class:`~closedchain.urdf.URDFPlus`: ``spherical``, the
        joints converted to ``SPHERICAL`` (written as three revolute joints),
        ``unlimited``, the joints whose limits give no range, and
        ``fuse_ball_chains`` (True: the convention's ball joints, see
        :func:`find_ball_chains`).

    A ``joint_name`` entry that names no ``<joint>`` is passed over with a
    logged warning (suggesting the nearest name), as the authors' loader passes
    over it silently.

    Raises:
        URDFError: ``joint_name`` names a joint that cannot be converted so, or
            one whose conversion would reuse a name; ``name_mot`` names no
            movable joint of the converted tree (lists them). Loop frames are
            checked when the tree is built (:func:`closedchain.load`).
    """
    path = loops.path
    joints = {e.get("name"): e for e in root.findall("joint")}
    taken = set(joints) | {e.get("name") for e in root.findall("link")}
    converted = {}
    missing = []
    for i, (name, kind) in enumerate(loops.conversions):
        where = f"{path}: joint_name[{i}] = {quoted(name)}"
        joint = joints.get(name)
        if joint is None:
            missing.append(i)
            continue
        if kind == "FIXED":
            _make_fixed(joint)
        else:
            jtype = joint.get("type")
            if jtype not in CONVERTIBLE_JOINT_TYPES:
                raise URDFError(
                    f"{where} is a {jtype} joint, which {kind} cannot replace; valid: a "
                    f"{', '.join(CONVERTIBLE_JOINT_TYPES)} joint"
                )
            axes = SPHERICAL_AXES if kind == "SPHERICAL" else kind[-2:]
            _replace_by_revolute_chain(root, joint, axes, taken, where)
        converted[name] = kind

    if missing:
        # The authors' loader converts the joints it finds by name and passes over the
        # others: so does this one, saying so once.
        i = missing[0]
        name, kind = loops.conversions[i]
        logger.warning(
            "%s: joint_name[%d] = %s is not a <joint> of %s%s: ignored (%s not applied), as "
            "the authors' loader does%s",
            path,
            i,
            quoted(name),
            base,
            _did_you_mean(name, joints),
            kind,
            f"; so are {len(missing) - 1} more joint_name entries" if len(missing) > 1 else "",
        )

    movable = [e.get("name") for e in root.findall("joint") if e.get("type") != "fixed"]
    movable_set = set(movable)
    for i, name in enumerate(loops.motors):
        if name in converted:
            raise URDFError(
                f"{path}: name_mot[{i}] = {quoted(name)} is converted to {converted[name]} by "
                "joint_type, so it cannot be a motor"
            )
        if name not in movable_set:
            raise URDFError(
                f"{path}: name_mot[{i}] = {quoted(name)} is not a movable <joint> of {base}"
                f"{_did_you_mean(name, movable)}; movable joints: {name_list(movable)}"
            )
        transmission = etree.SubElement(root, "transmission", name=f"{name}_transmission")
        etree.SubElement(transmission, "type").text = "transmission_interface/SimpleTransmission"
        etree.SubElement(transmission, "joint", name=name)

    for a, b, loop_type in loops.loops:
        loop = etree.SubElement(root, "loop", name=f"{a}{LOOP_NAME_SEPARATOR}{b}", type=loop_type)
        etree.SubElement(loop, "predecessor", frame=a)
        etree.SubElement(loop, "successor", frame=b)
    unlimited = [
        e.get("name")
        for e in root.findall("joint")
        if e.get("type") in UNLIMITED_JOINT_TYPES
        and (limit := e.find("limit")) is not None
        and limit.get("lower") is None
        and limit.get("upper") is None
    ]
    return {
        "spherical": tuple(name for name, kind in converted.items() if kind == "SPHERICAL"),
        "unlimited": tuple(unlimited),
        "fuse_ball_chains": True,
    }


def edit_model(model: pin.Model, urdf: URDFPlus) -> pin.Model:
    """Return the Pinocchio model with a loops YAML's edits: ball joints fused, limits removed.

    Args:
        model: the model Pinocchio built from ``urdf.xml``.
        urdf: the parsed tree: its ``spherical`` joints, whether to fuse other
            ball chains (``fuse_ball_chains``, see :func:`find_ball_chains`), and
            its ``unlimited`` joints.
    """
    chains = [_named_chain(model, name) for name in urdf.spherical]
    if urdf.fuse_ball_chains:
        chains += find_ball_chains(model, exclude={j for _, ids in chains for j in ids})
    if chains:
        model = fuse_spherical_joints(model, chains)
    lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    for name in urdf.unlimited:
        if not model.existJointName(name):  # fused into a spherical joint: no limits
            continue
        jm = model.joints[model.getJointId(name)]
        lower[jm.idx_q : jm.idx_q + jm.nq] = -np.inf
        upper[jm.idx_q : jm.idx_q + jm.nq] = np.inf
    model.lowerPositionLimit, model.upperPositionLimit = lower, upper
    return model


def _named_chain(model: pin.Model, name: str) -> tuple[str, list[int]]:
    """Return ``(name, ids)`` of the joints ``name_X, _Y, _Z`` a SPHERICAL conversion wrote.

    Raises:
        URDFError: they are not three revolute joints about X, Y, Z in a row at
            one place (the XML was changed after the conversion).
    """
    parts = [f"{name}_{axis}" for axis in SPHERICAL_AXES]
    ids = [model.getJointId(p) if model.existJointName(p) else 0 for p in parts]
    if (
        0 in ids
        or [model.joints[j].shortname() for j in ids] != [f"JointModelR{a}" for a in SPHERICAL_AXES]
        or any(model.parents[b] != a for a, b in zip(ids, ids[1:], strict=False))
        or not all(model.jointPlacements[j].isIdentity() for j in ids[1:])
    ):
        raise URDFError(
            f"joint {name!r}: expected revolute joints {', '.join(parts)} about X, Y, Z in a row "
            "at one place, to fuse into a spherical joint"
        )
    return name, ids


#: A chain of three revolute joints is a ball joint when the second and third sit
#: within this distance [m] of the first (the corpus writes them at exactly one point) ...
BALL_POINT_TOL = 1e-9

#: ... and their unit axes are independent: |det(a1, a2, a3)| at least this.
BALL_AXES_MIN_DET = 1e-6


def _is_revolute(joint) -> bool:
    """Whether a Pinocchio joint model is revolute (RX/RY/RZ, unaligned, unbounded)."""
    return joint.shortname().startswith("JointModelR") and joint.nv == 1


def find_ball_chains(
    model: pin.Model, *, exclude: Collection[int] = ()
) -> list[tuple[str, list[int]]]:
    """Return the chains of three revolute joints that make a ball joint, as the corpus writes one.

    example-parallel-robots writes a ball joint as three revolute joints in a
    row through two massless links, and the authors' loader fuses them
    (``simplifyModel``). A chain (j1, j2, j3) is fused when j2 is the only
    joint child of j1 and j3 of j2, the bodies of j1 and j2 are massless
    (mass and rotational inertia exactly 0: a link with mass is a real body),
    j2 and j3 sit within :data:`BALL_POINT_TOL` of j1, and the three axes are
    independent (:data:`BALL_AXES_MIN_DET`, at the neutral configuration).

    Args:
        model: the Pinocchio model.
        exclude: joint ids already fused otherwise.

    Returns:
        ``[(name of j3, [j1, j2, j3]), ...]``: the spherical joint takes j3's name.
    """
    import pinocchio as pin

    children: dict[int, list[int]] = {}
    for j in range(1, model.njoints):
        children.setdefault(model.parents[j], []).append(j)
    data = model.createData()
    q0 = pin.neutral(model)
    pin.forwardKinematics(model, data, q0)
    used, chains = set(exclude), []
    for first in range(1, model.njoints):
        ids = [first]
        while len(ids) < 3 and len(children.get(ids[-1], [])) == 1:
            ids.append(children[ids[-1]][0])
        if len(ids) < 3 or used.intersection(ids):
            continue
        if not all(_is_revolute(model.joints[j]) for j in ids):
            continue
        if any(model.inertias[j].mass != 0.0 or model.inertias[j].inertia.any() for j in ids[:2]):
            continue
        if any(
            np.linalg.norm(model.jointPlacements[j].translation) > BALL_POINT_TOL for j in ids[1:]
        ):
            continue
        axes = []
        for j in ids:
            jdata = model.joints[j].createData()
            model.joints[j].calc(jdata, q0)
            axes.append(data.oMi[j].rotation @ np.asarray(jdata.S, dtype=float).ravel()[3:6])
        if abs(np.linalg.det(np.array(axes))) < BALL_AXES_MIN_DET:
            continue
        chains.append((model.names[ids[2]], ids))
        used.update(ids)
    return chains


def _did_you_mean(name: str, names) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest of ``names`` (NEAR_MISS_CUTOFF), or ""."""
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=NEAR_MISS_CUTOFF)
    return f" (did you mean {quoted(close[0])}?)" if close else ""


def _make_fixed(joint) -> None:
    """Turn ``joint`` into a fixed joint at its zero position (its origin)."""
    joint.set("type", "fixed")
    for child in list(joint):
        if isinstance(child.tag, str) and child.tag not in KEPT_JOINT_CHILDREN:
            joint.remove(child)


def _replace_by_revolute_chain(root, joint, axes: str, taken: set[str], where: str) -> None:
    """Replace ``joint`` by revolute joints about ``axes`` of its frame, all at its origin.

    Joint ``<name>_<axis>`` turns about ``axis``; massless links
    ``<name>_<axis>_link`` join consecutive ones; the first has the old
    joint's parent and origin, the last its child.

    Args:
        root: the ``<robot>`` element (modified).
        joint: the ``<joint>`` element to replace.
        axes: the axes in order, letters of :data:`AXIS_XYZ`.
        taken: names of every link and joint so far (updated).
        where: the YAML entry, for messages.
    """
    name = joint.get("name")
    parent, child = joint.find("parent"), joint.find("child")
    if parent is None or child is None:
        raise URDFError(f"{where}: the <joint> has no <parent> or <child>")
    limit = joint.find("limit")
    rates = {
        key: limit.get(key, "0") if limit is not None else "0" for key in ("effort", "velocity")
    }
    names = [f"{name}_{axis}" for axis in axes]
    links = [f"{n}_link" for n in names[:-1]]
    for new in names + links:
        if new in taken:
            raise URDFError(
                f"{where}: converting it needs the name {new!r}, which the tree already uses"
            )
        taken.add(new)
    origin = joint.find("origin")
    position = list(root).index(joint)
    root.remove(joint)
    elements = [etree.Element("link", name=link) for link in links]
    parents = [parent.get("link"), *links]
    children = [*links, child.get("link")]
    for k, (jname, axis) in enumerate(zip(names, axes, strict=True)):
        new = etree.Element("joint", name=jname, type="revolute")
        if k == 0 and origin is not None:
            new.append(origin)
        etree.SubElement(new, "parent", link=parents[k])
        etree.SubElement(new, "child", link=children[k])
        etree.SubElement(new, "axis", xyz=AXIS_XYZ[axis])
        etree.SubElement(
            new,
            "limit",
            lower=repr(-CONVERTED_JOINT_LIMIT),
            upper=repr(CONVERTED_JOINT_LIMIT),
            **rates,
        )
        elements.append(new)
    for offset, element in enumerate(elements):
        root.insert(position + offset, element)


#: Model vectors with one entry per configuration entry, and per velocity entry,
#: that :func:`fuse_spherical_joints` copies joint by joint.
Q_VECTORS = ("lowerPositionLimit", "upperPositionLimit", "positionLimitMargin")
V_VECTORS = (
    "armature",
    "damping",
    "effortLimit",
    "friction",
    "lowerDryFrictionLimit",
    "lowerEffortLimit",
    "lowerVelocityLimit",
    "rotorGearRatio",
    "rotorInertia",
    "upperDryFrictionLimit",
    "upperEffortLimit",
    "upperVelocityLimit",
    "velocityLimit",
)


def fuse_spherical_joints(model: pin.Model, chains: list[tuple[str, list[int]]]) -> pin.Model:
    """Return a copy of ``model`` with each chain of three revolute joints fused into a spherical.

    The spherical joint stands where the chain's last joint's frame is at its
    zero position (placement ``P1 P2 P3`` in the parent joint's frame) and
    carries the bodies and frames of the three joints, moved into that frame
    (the frames of j1 and j2 by ``(P2 P3)^-1`` and ``P3^-1``). The JOINT frames
    of the chain become OP_FRAMEs, except one JOINT frame with the spherical
    joint's name. Limits, friction, damping and armature of the other joints
    are copied.

    Args:
        model: the Pinocchio model.
        chains: ``[(name, [j1, j2, j3]), ...]`` (:func:`_named_chain`,
            :func:`find_ball_chains`).
    """
    import pinocchio as pin

    by_first = {ids[0]: (name, ids) for name, ids in chains}
    # Placement of each fused joint's frame in its chain's last joint frame, at q = 0.
    in_last: dict[int, pin.SE3] = {}
    for _, (j1, j2, j3) in chains:
        in_last[j3] = pin.SE3.Identity()
        in_last[j2] = model.jointPlacements[j3].inverse()
        in_last[j1] = (model.jointPlacements[j2] * model.jointPlacements[j3]).inverse()

    new = pin.Model()
    new.name = model.name
    new.appendBodyToJoint(0, model.inertias[0], pin.SE3.Identity())  # links fixed to the world
    joint_of = {0: 0}
    copied: list[tuple[int, int]] = []  # (old joint, new joint) of unchanged joints
    for j in range(1, model.njoints):
        if j in joint_of:  # the second and third joints of a chain: fused already
            continue
        parent = joint_of[model.parents[j]]
        if j in by_first:
            name, ids = by_first[j]
            placement = model.jointPlacements[ids[0]]
            for k in ids[1:]:
                placement = placement * model.jointPlacements[k]
            jid = new.addJoint(parent, pin.JointModelSpherical(), placement, name)
            inertia = pin.Inertia.Zero()
            for k in ids:
                inertia += in_last[k].act(model.inertias[k])
            joint_of.update(dict.fromkeys(ids, jid))
        else:
            jid = new.addJoint(parent, model.joints[j], model.jointPlacements[j], model.names[j])
            inertia = model.inertias[j]
            joint_of[j] = jid
            copied.append((j, jid))
        new.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
    for attribute in Q_VECTORS + V_VECTORS:
        per_q = attribute in Q_VECTORS
        old_values, values = getattr(model, attribute), getattr(new, attribute).copy()
        for j, jid in copied:
            a, b = model.joints[j], new.joints[jid]
            if per_q:
                values[b.idx_q : b.idx_q + b.nq] = old_values[a.idx_q : a.idx_q + a.nq]
            else:
                values[b.idx_v : b.idx_v + b.nv] = old_values[a.idx_v : a.idx_v + a.nv]
        setattr(new, attribute, values)

    names = {j: name for name, ids in chains for j in ids}
    frame_of = {0: 0}
    for i in range(1, len(model.frames)):
        f = model.frames[i]
        parent, parent_frame = joint_of[f.parentJoint], frame_of[f.parentFrame]
        if f.parentJoint not in in_last:
            frame = pin.Frame(f.name, parent, parent_frame, f.placement, f.type, f.inertia)
            frame_of[i] = new.addFrame(frame, False)
            continue
        name = names[f.parentJoint]
        if f.type == pin.FrameType.JOINT and not new.existFrame(name, pin.FrameType.JOINT):
            frame = pin.Frame(name, parent, parent_frame, pin.SE3.Identity(), pin.FrameType.JOINT)
            new.addFrame(frame, False)
        kind = f.type
        if kind == pin.FrameType.JOINT:
            if f.name == name:
                frame_of[i] = new.getFrameId(name, pin.FrameType.JOINT)
                continue
            kind = pin.FrameType.OP_FRAME
        placement = in_last[f.parentJoint] * f.placement
        frame = pin.Frame(f.name, parent, parent_frame, placement, kind, f.inertia)
        frame_of[i] = new.addFrame(frame, False)
    return new
