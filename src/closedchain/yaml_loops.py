"""Loops in the YAML convention of example-parallel-robots (Gepetto, BSD-3).

Each robot of that collection is a URDF tree (``robot.urdf``) and a YAML
file (``robot.yaml``) that says how to close it::

    closed_loop: [["closedloop1_A", "closedloop1_B"], ["knee_A", "knee_B"]]
    type: ["6d", "3d"]            # per loop: 6d placements equal, 3d positions equal
    name_mot: ["mot1", "mot2"]    # the actuated joints
    joint_name: ["ankle", "foot"] # optional: joints to convert ...
    joint_type: ["SPHERICAL", "UJOINT_ZY"]  # ... into these

:func:`apply_loops_yaml` applies it to the base URDF's description (the tree
:func:`closedchain.urdf.parse_urdf` read once; no URDF text is written):

- each pair of ``closed_loop`` becomes a loop between the two frames
  (a ``frame=`` side: any frame of the tree, links, joints, fixed joints),
  named ``A--B``: ``6d`` a ``fixed`` loop, ``3d`` a ``spherical`` one
  (:data:`LOOP_TYPE_OF`, case ignored);
- each joint of ``name_mot`` is actuated (as a ``<transmission>`` would make it);
- ``joint_type`` converts the joints of ``joint_name`` (:data:`JOINT_CONVERSIONS`,
  case ignored; a name of no joint is passed over with a logged warning, as the
  authors' loader passes over it silently): ``FIXED`` welds the joint's body at its
  zero position (the URDF's origin); ``UJOINT_<A><B>`` replaces it by two revolute
  joints ``<joint>_<A>`` and ``<joint>_<B>`` about the axes A then B of the joint's
  frame, at its origin, through a massless body ``<joint>_<A>_link``; ``SPHERICAL``
  by a spherical joint ``<joint>`` (Pinocchio's ``JointModelSpherical``: a unit
  quaternion in q, 3 entries of v), at the joint's origin, as the authors' loader
  builds it;
- three revolute joints in a row through massless links at one point, the
  way the convention's URDFs write a ball joint, become one spherical joint
  named after the last (:func:`fuse_ball_chains`), as the authors' loader
  fuses them: left as Euler angles, massless links between, the mass
  matrix is singular at the middle angle +-pi/2 and ill-conditioned near it;
- a revolute or prismatic joint whose ``<limit>`` gives neither ``lower``
  nor ``upper`` gets no position limits. URDF reads such a limit as [0, 0],
  a locked joint; the convention's robots (exported by onshape-to-robot)
  write every joint so, and the authors' loader ignores limits.

The YAML is read with PyYAML's safe loader (no Python objects, no code).
"""

from __future__ import annotations

import difflib
import logging
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pinocchio as pin
import yaml

from ._io import read_input_bytes
from .description import NEUTRAL_Q0, BodyDescription, JointDescription, TreeDescription
from .exceptions import ModelFileError, quoted, shorten
from .urdf import NEAR_MISS_CUTOFF, LoopSpec, MechanismDescription, name_list, tree_order

__all__ = [
    "LoopsYAML",
    "YAML_SUFFIXES",
    "apply_loops_yaml",
    "is_loops_yaml",
    "read_loops_yaml",
]

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

#: Axes of the joint frame (unit vectors).
AXES = {
    "X": np.array([1.0, 0.0, 0.0]),
    "Y": np.array([0.0, 1.0, 0.0]),
    "Z": np.array([0.0, 0.0, 1.0]),
}

#: Position limits [rad] of the revolute joints of a converted joint: +-CONVERTED_JOINT_LIMIT
#: (URDF's revolute joint needs limits; half a turn either way is every orientation).
CONVERTED_JOINT_LIMIT = math.pi

#: Joint types whose ``<limit>`` without lower and upper means no limits (see the module).
UNLIMITED_JOINT_TYPES = ("revolute", "prismatic")

#: Joint types a ``SPHERICAL`` or ``UJOINT`` conversion may replace (one degree of freedom).
CONVERTIBLE_JOINT_TYPES = ("revolute", "continuous", "prismatic")

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
        raise ModelFileError(
            f"{path}: {where} = {quoted(name)} holds the character {bad[0]!r}; valid: names "
            "without control characters or lone surrogates"
        )


def _names(path: Path, data: dict, key: str) -> list[str]:
    """Return ``data[key]`` (default empty) as a list of strings, or raise naming the key."""
    value = data.get(key)
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
        raise ModelFileError(f"{path}: {key} must be a list of names, got {shorten(value)}")
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
    raw = read_input_bytes(path, limit=MAX_YAML_BYTES, what="loops file", error=ModelFileError)
    try:
        text = raw.decode("utf-8")
        _check_events(text)
        return yaml.load(text, Loader=_SAFE_LOADER)  # noqa: S506 (a safe loader)
    except _LimitError as exc:
        raise ModelFileError(f"{path}: line {exc.line}: {exc}; valid: a loops file") from None
    except UnicodeDecodeError as exc:
        raise ModelFileError(f"{path}: not a YAML file: not UTF-8 at byte {exc.start}") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f"line {mark.line + 1}: " if mark is not None else ""
        raise ModelFileError(
            f"{path}: not a YAML file: {line}{shorten(str(exc.problem), YAML_PROBLEM_MAX)}"
        ) from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an int beyond 4300 digits
        raise ModelFileError(
            f"{path}: not a YAML file: {shorten(str(exc), YAML_PROBLEM_MAX)}"
        ) from None


def read_loops_yaml(path: str | Path) -> LoopsYAML:
    """Read and check a loops YAML file (see the module docstring).

    Args:
        path: the YAML file.

    Returns:
        Its loops, motors and joint conversions.

    Raises:
        ModelFileError: the file cannot be read, is not a regular file, is larger than
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
        raise ModelFileError(f"{path}: expected a mapping of keys {', '.join(YAML_KEYS)}")
    for key in data:
        if key not in YAML_KEYS:
            raise ModelFileError(
                f"{path}: unknown key {quoted(key) if isinstance(key, str) else shorten(key)}; "
                f"valid keys: {', '.join(YAML_KEYS)}"
            )

    pairs = data.get("closed_loop") or []
    if not isinstance(pairs, list) or not all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p) for p in pairs
    ):
        raise ModelFileError(
            f"{path}: closed_loop must be a list of pairs of frame names, got {shorten(pairs)}"
        )
    for i, pair in enumerate(pairs):
        for k, name in enumerate(pair):
            _check_name(path, f"closed_loop[{i}][{k}]", name)
    types = _names(path, data, "type")
    if len(types) != len(pairs):
        raise ModelFileError(
            f"{path}: closed_loop has {len(pairs)} pairs but type has {len(types)} entries; "
            "valid: one type per pair"
        )
    loops = []
    for i, ((a, b), kind) in enumerate(zip(pairs, types, strict=True)):
        if kind.casefold() not in LOOP_TYPE_OF:
            raise ModelFileError(
                f"{path}: type[{i}] = {quoted(kind)} is not a constraint type; valid: 6d, 3d"
            )
        if a == b:
            raise ModelFileError(f"{path}: closed_loop[{i}] pairs frame {quoted(a)} with itself")
        loops.append((a, b, LOOP_TYPE_OF[kind.casefold()]))
    seen: dict[tuple[str, str], int] = {}
    for i, (a, b, _) in enumerate(loops):
        if (a, b) in seen or (b, a) in seen:
            j = seen.get((a, b), seen.get((b, a)))
            raise ModelFileError(
                f"{path}: closed_loop[{i}] repeats closed_loop[{j}] ({quoted(a)}, {quoted(b)})"
            )
        seen[a, b] = i

    motors = _names(path, data, "name_mot")
    joints = _names(path, data, "joint_name")
    kinds = _names(path, data, "joint_type")
    if len(joints) != len(kinds):
        raise ModelFileError(
            f"{path}: joint_name has {len(joints)} entries but joint_type has {len(kinds)}; "
            "valid: one type per joint"
        )
    for key, names in (("name_mot", motors), ("joint_name", joints)):
        repeat = _first_repeat(names)
        if repeat is not None:
            j, i = repeat
            raise ModelFileError(f"{path}: {key}[{i}] repeats {key}[{j}] ({quoted(names[i])})")
    conversions = []
    for i, (joint, kind) in enumerate(zip(joints, kinds, strict=True)):
        upper = kind.upper()
        m = _UJOINT.fullmatch(upper)
        if upper not in ("SPHERICAL", "FIXED") and (m is None or m[1] == m[2]):
            raise ModelFileError(
                f"{path}: joint_type[{i}] = {quoted(kind)} (joint {quoted(joint)}) is not a "
                f"conversion; valid: {', '.join(JOINT_CONVERSIONS)}"
            )
        conversions.append((joint, upper))
    return LoopsYAML(
        path=path, loops=tuple(loops), motors=tuple(motors), conversions=tuple(conversions)
    )


def apply_loops_yaml(
    urdf: MechanismDescription, loops: LoopsYAML, root, *, base: Path
) -> MechanismDescription:
    """Return a base URDF's tree with a loops YAML's conversions, loops and motors.

    Args:
        urdf: the base URDF, parsed (:func:`closedchain.urdf.parse_urdf`): its
            description is edited, nothing is written as text.
        loops: the checked YAML content (:func:`read_loops_yaml`).
        root: the base's ``<robot>`` element (read only: which ``<limit>`` elements
            give no range, see the module docstring).
        base: the base URDF file, for messages.

    Returns:
        The converted tree, named after the YAML file (``path``), with the YAML's
        loops (``frame=`` sides) and motors (``actuated``) after the base's.

    A ``joint_name`` entry that names no ``<joint>`` is passed over with a
    logged warning (suggesting the nearest name), as the authors' loader passes
    over it silently.

    Raises:
        ModelFileError: ``joint_name`` names a joint that cannot be converted so, one
            whose conversion would reuse a name, or one that the base's loops,
            scene, transmissions, springs or ``independent`` flags name;
            ``name_mot`` names no movable joint of the converted tree (lists
            them). Loop frames are checked when the tree is built
            (:func:`closedchain.load`).
    """
    path = loops.path
    bodies = list(urdf.tree.bodies)
    index = {j.name: k for k, b in enumerate(bodies) for j in b.joints}
    joints, links = dict(urdf.joints), list(urdf.links)
    taken = set(joints) | set(links)
    converted: dict[str, str] = {}
    missing = []
    for i, (name, kind) in enumerate(loops.conversions):
        where = f"{path}: joint_name[{i}] = {quoted(name)}"
        if name not in joints:
            missing.append(i)
            continue
        _refuse_referenced(urdf, name, where, base)
        jtype = joints[name]
        if kind == "FIXED":
            if jtype != "fixed":  # fixed at its zero position: the body where the file puts it
                bodies[index[name]] = replace(bodies[index[name]], joints=(), fixed_joint=name)
                joints[name] = "fixed"
        elif jtype not in CONVERTIBLE_JOINT_TYPES:
            raise ModelFileError(
                f"{where} is a {jtype} joint, which {kind} cannot replace; valid: a "
                f"{', '.join(CONVERTIBLE_JOINT_TYPES)} joint"
            )
        elif kind == "SPHERICAL":
            body = bodies[index[name]]
            ball = JointDescription(name, "spherical", q0=NEUTRAL_Q0["spherical"])
            bodies[index[name]] = replace(body, joints=(ball,))
            joints[name] = "spherical"
        else:
            added = _replace_by_revolute_pair(bodies, index[name], kind[-2:], taken, where)
            bodies.append(added)
            del joints[name]
            joints.update(dict.fromkeys((f"{name}_{a}" for a in kind[-2:]), "revolute"))
            links.append(added.name)
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

    movable = [name for name, jtype in joints.items() if jtype != "fixed"]
    movable_set = set(movable)
    actuated = list(urdf.actuated)
    for i, name in enumerate(loops.motors):
        if name in converted:
            raise ModelFileError(
                f"{path}: name_mot[{i}] = {quoted(name)} is converted to {converted[name]} by "
                "joint_type, so it cannot be a motor"
            )
        if name not in movable_set:
            raise ModelFileError(
                f"{path}: name_mot[{i}] = {quoted(name)} is not a movable <joint> of {base}"
                f"{_did_you_mean(name, movable)}; movable joints: {name_list(movable)}"
            )
        if name not in actuated:
            actuated.append(name)

    unlimited = {
        e.get("name")
        for e in root.findall("joint")
        if e.get("type") in UNLIMITED_JOINT_TYPES
        and (limit := e.find("limit")) is not None
        and limit.get("lower") is None
        and limit.get("upper") is None
    }
    bodies = [
        replace(
            b,
            joints=tuple(
                replace(j, lower=-np.inf, upper=np.inf) if j.name in unlimited else j
                for j in b.joints
            ),
        )
        for b in bodies
    ]
    description = fuse_ball_chains(replace(urdf.tree, bodies=tree_order(bodies)))
    new_loops = tuple(
        LoopSpec(
            name=f"{a}{LOOP_NAME_SEPARATOR}{b}",
            type=loop_type,
            predecessor=a,
            successor=b,
            predecessor_origin=pin.SE3.Identity(),
            successor_origin=pin.SE3.Identity(),
            axis=np.array([1.0, 0.0, 0.0]),
            predecessor_frame=a,
            successor_frame=b,
        )
        for a, b, loop_type in loops.loops
    )
    names = [spec.name for spec in (*urdf.loops, *new_loops)]
    for name in set(names):
        if names.count(name) > 1:
            raise ModelFileError(f"{path}: loop name {quoted(name)} is used more than once")
    return replace(
        urdf,
        path=path,
        tree=description,
        joints=joints,
        links=tuple(links),
        loops=urdf.loops + new_loops,
        actuated=tuple(actuated),
    )


def _refuse_referenced(urdf: MechanismDescription, name: str, where: str, base: Path) -> None:
    """Refuse to convert a joint that the base's couplings, scene, transmissions, springs
    or ``independent`` flags name (they would name a joint that is no longer there)."""
    users = [
        *(f"<loop name={quoted(s.name)}>" for s in urdf.loops if name in (s.joint, s.mimics)),
        *(["its <scene>"] if urdf.scene is not None and _scene_names(urdf.scene, name) else []),
        *(["a <transmission>"] if name in urdf.actuated else []),
        *(["independent="] if name in urdf.independent else []),
        *(
            "its <dynamics>"
            for terms in (urdf.springs, urdf.dampings, urdf.armatures)
            for t in terms
            if t.joint == name
        ),
    ]
    if users:
        raise ModelFileError(
            f"{where}: {base} names the joint in {', '.join(dict.fromkeys(users))}, so it "
            "cannot be converted"
        )


def _scene_names(scene, name: str) -> bool:
    """Whether a scene sets, starts or tracks the joint ``name``."""
    return (
        name in scene.initial or name in scene.velocity or any(s.joint == name for s in scene.track)
    )


#: A chain of three revolute joints is a ball joint when the second and third sit
#: within this distance [m] of the first (the corpus writes them at exactly one point) ...
BALL_POINT_TOL = 1e-9

#: ... and their unit axes are independent: |det(a1, a2, a3)| at least this.
BALL_AXES_MIN_DET = 1e-6

#: Joint kinds a ball chain is made of (one angle each).
BALL_CHAIN_KINDS = ("revolute", "continuous")


def find_ball_chains(description: TreeDescription) -> list[tuple[str, str, str]]:
    """Return the chains of three revolute joints that make a ball joint, as the corpus writes one.

    example-parallel-robots writes a ball joint as three revolute joints in a
    row through two massless links, and the authors' loader fuses them
    (``simplifyModel``). A chain of bodies (b1, b2, b3), each on one revolute
    joint (:data:`BALL_CHAIN_KINDS`, anchored at its origin), is fused when b2
    is the only moving body on b1 (with the bodies welded to it) and b3 on b2,
    b1 and b2 and their welded bodies are massless (inertia exactly 0: a link with
    mass is a real body), the joints of b2 and b3 sit within
    :data:`BALL_POINT_TOL` of b1's, and the three axes are independent
    (:data:`BALL_AXES_MIN_DET`, with every joint at 0).

    Args:
        description: the tree (every joint at its ``q0`` = 0, as a URDF's).

    Returns:
        ``[(b1, b2, b3), ...]`` (body names), in tree order.
    """
    bodies = description.bodies
    #: each body's moving body (itself, or the one it is welded to), None: the universe
    segment: dict[str, str | None] = {}
    #: each body's frame in its moving body's frame, and in the world
    in_segment: dict[str, pin.SE3] = {}
    world: dict[str, pin.SE3] = {}
    moving_children: dict[str | None, list[str]] = {}
    massless: dict[str | None, bool] = {None: False}
    for b in bodies:
        up = pin.SE3.Identity() if b.parent is None else world[b.parent]
        world[b.name] = up * b.placement
        if b.joints:
            segment[b.name], in_segment[b.name] = b.name, pin.SE3.Identity()
            moving_children.setdefault(segment.get(b.parent), []).append(b.name)
            massless[b.name] = True
        else:
            segment[b.name] = segment.get(b.parent)
            in_segment[b.name] = in_segment.get(b.parent, pin.SE3.Identity()) * b.placement
        zero = b.inertia.mass == 0.0 and not b.inertia.inertia.any()
        massless[segment[b.name]] = massless.get(segment[b.name], True) and zero
    by_name = {b.name: b for b in bodies}

    def ball_joint(name: str) -> bool:
        joints = by_name[name].joints
        return (
            len(joints) == 1
            and joints[0].kind in BALL_CHAIN_KINDS
            and not np.any(joints[0].position)
        )

    used: set[str] = set()
    chains = []
    for b in bodies:
        chain = [b.name]
        while len(chain) < 3 and len(moving_children.get(chain[-1], [])) == 1:
            chain.append(moving_children[chain[-1]][0])
        if len(chain) < 3 or used.intersection(chain) or not all(map(ball_joint, chain)):
            continue
        if not (massless[chain[0]] and massless[chain[1]]):
            continue
        offsets = [in_segment[by_name[n].parent] * by_name[n].placement for n in chain[1:]]
        if any(np.linalg.norm(m.translation) > BALL_POINT_TOL for m in offsets):
            continue
        axes = [world[n].rotation @ by_name[n].joints[0].axis for n in chain]
        if abs(np.linalg.det(np.array(axes))) < BALL_AXES_MIN_DET:
            continue
        chains.append(tuple(chain))
        used.update(chain)
    return chains


def fuse_ball_chains(description: TreeDescription) -> TreeDescription:
    """Return the description with each ball chain (:func:`find_ball_chains`) one spherical joint.

    The spherical joint takes the last joint's name and stands where its frame
    is at q = 0 (``P1 P2 P3`` in the first's parent); the two massless bodies
    before it are welded to it (FIXED_JOINT frames named after their joints, so
    loops may still name them), with their welded bodies.
    """
    chains = find_ball_chains(description)
    if not chains:
        return description
    bodies = {b.name: b for b in description.bodies}
    for first, second, last in chains:
        b1, b2, b3 = bodies[first], bodies[second], bodies[last]
        # Where each joint's frame is in the previous one's (through welded bodies).
        m12 = _in_moving_body(bodies, b2)
        m23 = _in_moving_body(bodies, b3)
        ball = JointDescription(b3.joints[0].name, "spherical", q0=NEUTRAL_Q0["spherical"])
        bodies[last] = replace(
            b3, parent=b1.parent, placement=b1.placement * m12 * m23, joints=(ball,)
        )
        for body, placement in ((b1, (m12 * m23).inverse()), (b2, m23.inverse())):
            bodies[body.name] = replace(
                body,
                parent=last,
                placement=placement,
                joints=(),
                fixed_joint=body.joints[0].name,
            )
    return replace(description, bodies=tree_order(bodies.values()))


def _in_moving_body(bodies: dict, body) -> pin.SE3:
    """Return a body's placement in the frame of the moving body its parent is welded to."""
    placement = body.placement
    parent = bodies[body.parent]
    while not parent.joints:
        placement = parent.placement * placement
        parent = bodies[parent.parent]
    return placement


def _did_you_mean(name: str, names) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest of ``names`` (NEAR_MISS_CUTOFF), or ""."""
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=NEAR_MISS_CUTOFF)
    return f" (did you mean {quoted(close[0])}?)" if close else ""


def _replace_by_revolute_pair(bodies: list, k: int, axes: str, taken: set[str], where: str):
    """Replace the joint of ``bodies[k]`` by revolute joints about ``axes`` of its frame.

    Joint ``<name>_<A>`` turns a new massless body ``<name>_<A>_link`` about axis
    A, at the old joint's place (its parent and placement); joint ``<name>_<B>``
    turns the old body about B, at the new body's origin. Both take the old
    joint's effort and velocity and +-:data:`CONVERTED_JOINT_LIMIT`.

    Args:
        bodies: the bodies (``bodies[k]`` is replaced).
        k: the index of the body whose joint is converted.
        axes: the two axes in order, letters of :data:`AXES`.
        taken: names of every link and joint so far (updated).
        where: the YAML entry, for messages.

    Returns:
        The new massless body (for the caller to add).
    """
    body = bodies[k]
    old = body.joints[0]
    names = [f"{old.name}_{axis}" for axis in axes]
    link = f"{names[0]}_link"
    for new in (*names, link):
        if new in taken:
            raise ModelFileError(
                f"{where}: converting it needs the name {new!r}, which the tree already uses"
            )
        taken.add(new)
    joints = [
        JointDescription(
            name,
            "revolute",
            axis=AXES[axis],
            lower=-CONVERTED_JOINT_LIMIT,
            upper=CONVERTED_JOINT_LIMIT,
            effort=old.effort if math.isfinite(old.effort) else 0.0,
            velocity=old.velocity if math.isfinite(old.velocity) else 0.0,
        )
        for name, axis in zip(names, axes, strict=True)
    ]
    bodies[k] = replace(body, parent=link, placement=pin.SE3.Identity(), joints=(joints[1],))
    return BodyDescription(link, body.parent, body.placement, joints=(joints[0],))
