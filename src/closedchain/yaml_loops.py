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
  the tree (:data:`JOINT_CONVERSIONS`, case ignored): ``FIXED`` makes the
  joint fixed at its zero position (the URDF's origin); ``UJOINT_<A><B>``
  replaces it by two revolute joints ``<joint>_<A>`` and ``<joint>_<B>`` about
  the axes A then B of the joint's frame, at its origin, through a massless
  link ``<joint>_<A>_link``; ``SPHERICAL`` by Pinocchio's spherical joint
  ``<joint>`` (a unit quaternion in q, 3 entries of v), at the joint's origin;
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
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from lxml import etree

from .exceptions import URDFError
from .urdf import NEAR_MISS_CUTOFF, URDFPlus, name_list

if TYPE_CHECKING:
    import pinocchio as pin

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


def _names(path: Path, data: dict, key: str) -> list[str]:
    """Return ``data[key]`` (default empty) as a list of strings, or raise naming the key."""
    value = data.get(key)
    if value is None:
        return []
    if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
        raise URDFError(f"{path}: {key} must be a list of names, got {_brief(value)}")
    return value


def _brief(value: object, limit: int = 60) -> str:
    """Return ``repr(value)`` cut to ``limit`` characters (one line)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def read_loops_yaml(path: str | Path) -> LoopsYAML:
    """Read and check a loops YAML file (see the module docstring).

    Args:
        path: the YAML file.

    Returns:
        Its loops, motors and joint conversions.

    Raises:
        URDFError: the file cannot be read or is not YAML; an unknown key
            (lists the valid ones); a value of the wrong shape; ``closed_loop``
            and ``type`` (or ``joint_name`` and ``joint_type``) of different
            lengths; an unknown constraint type or conversion (lists the valid
            ones); a name given twice.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise URDFError(f"{path}: cannot read loops file: {exc.strerror}") from exc
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise URDFError(f"{path}: not a YAML file: {' '.join(str(exc).split())}") from exc
    if not isinstance(data, dict):
        raise URDFError(f"{path}: expected a mapping of keys {', '.join(YAML_KEYS)}")
    for key in data:
        if key not in YAML_KEYS:
            raise URDFError(f"{path}: unknown key {key!r}; valid keys: {', '.join(YAML_KEYS)}")

    pairs = data.get("closed_loop") or []
    if not isinstance(pairs, list) or not all(
        isinstance(p, list) and len(p) == 2 and all(isinstance(x, str) for x in p) for p in pairs
    ):
        raise URDFError(
            f"{path}: closed_loop must be a list of pairs of frame names, got {_brief(pairs)}"
        )
    types = _names(path, data, "type")
    if len(types) != len(pairs):
        raise URDFError(
            f"{path}: closed_loop has {len(pairs)} pairs but type has {len(types)} entries; "
            "valid: one type per pair"
        )
    loops = []
    for i, ((a, b), kind) in enumerate(zip(pairs, types, strict=True)):
        if kind.casefold() not in LOOP_TYPE_OF:
            raise URDFError(f"{path}: type[{i}] = {kind!r} is not a constraint type; valid: 6d, 3d")
        if a == b:
            raise URDFError(f"{path}: closed_loop[{i}] pairs frame {a!r} with itself")
        loops.append((a, b, LOOP_TYPE_OF[kind.casefold()]))
    seen: dict[tuple[str, str], int] = {}
    for i, (a, b, _) in enumerate(loops):
        if (a, b) in seen or (b, a) in seen:
            j = seen.get((a, b), seen.get((b, a)))
            raise URDFError(f"{path}: closed_loop[{i}] repeats closed_loop[{j}] ({a!r}, {b!r})")
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
        for i, name in enumerate(names):
            if name in names[:i]:
                raise URDFError(f"{path}: {key} lists {name!r} twice")
    conversions = []
    for i, (joint, kind) in enumerate(zip(joints, kinds, strict=True)):
        upper = kind.upper()
        m = _UJOINT.fullmatch(upper)
        if upper not in ("SPHERICAL", "FIXED") and (m is None or m[1] == m[2]):
            raise URDFError(
                f"{path}: joint_type[{i}] = {kind!r} (joint {joint!r}) is not a conversion; "
                f"valid: {', '.join(JOINT_CONVERSIONS)}"
            )
        conversions.append((joint, upper))
    return LoopsYAML(
        path=path, loops=tuple(loops), motors=tuple(motors), conversions=tuple(conversions)
    )


def apply_loops_yaml(root, loops: LoopsYAML, *, base: Path) -> dict[str, tuple[str, ...]]:
    """Write a loops YAML file's conversions, loops and motors into a URDF tree, in place.

    Args:
        root: the ``<robot>`` element of the base URDF (modified).
        loops: the checked YAML content (:func:`read_loops_yaml`).
        base: the base URDF file, for messages.

    Returns:
        What :func:`edit_model` does once Pinocchio has read the tree, as
        fields of :class:`~closedchain.urdf.URDFPlus`: ``spherical``, the
        joints converted to ``SPHERICAL`` (written as three revolute joints),
        and ``unlimited``, the joints whose limits give no range.

    Raises:
        URDFError: ``joint_name`` names no ``<joint>`` (lists them), a joint
            that cannot be converted so, or one whose conversion would reuse a
            name; ``name_mot`` names no movable joint of the converted tree (lists
            them). Loop frames are checked when the tree is built
            (:func:`closedchain.load`).
    """
    path = loops.path
    joints = {e.get("name"): e for e in root.findall("joint")}
    taken = set(joints) | {e.get("name") for e in root.findall("link")}
    converted = {}
    for i, (name, kind) in enumerate(loops.conversions):
        where = f"{path}: joint_name[{i}] = {name!r}"
        joint = joints.get(name)
        if joint is None:
            raise URDFError(
                f"{where} is not a <joint> of {base}{_did_you_mean(name, joints)}; joints: "
                f"{name_list(joints)}"
            )
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

    movable = [e.get("name") for e in root.findall("joint") if e.get("type") != "fixed"]
    for i, name in enumerate(loops.motors):
        if name in converted:
            raise URDFError(
                f"{path}: name_mot[{i}] = {name!r} is converted to {converted[name]} by "
                "joint_type, so it cannot be a motor"
            )
        if name not in movable:
            raise URDFError(
                f"{path}: name_mot[{i}] = {name!r} is not a movable <joint> of {base}"
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
    }


def edit_model(model: pin.Model, urdf: URDFPlus) -> pin.Model:
    """Return the Pinocchio model with a loops YAML's edits: spherical joints fused, limits removed.

    Args:
        model: the model Pinocchio built from ``urdf.xml``.
        urdf: the parsed tree, with its ``spherical`` and ``unlimited`` joints.
    """
    if urdf.spherical:
        model = fuse_spherical_joints(model, urdf.spherical)
    lower, upper = model.lowerPositionLimit.copy(), model.upperPositionLimit.copy()
    for name in urdf.unlimited:
        jm = model.joints[model.getJointId(name)]
        lower[jm.idx_q : jm.idx_q + jm.nq] = -np.inf
        upper[jm.idx_q : jm.idx_q + jm.nq] = np.inf
    model.lowerPositionLimit, model.upperPositionLimit = lower, upper
    return model


def _did_you_mean(name: str, names) -> str:
    """Return ``" (did you mean 'x'?)"`` for the closest of ``names`` (NEAR_MISS_CUTOFF), or ""."""
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=NEAR_MISS_CUTOFF)
    return f" (did you mean {close[0]!r}?)" if close else ""


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


def fuse_spherical_joints(model: pin.Model, names: tuple[str, ...]) -> pin.Model:
    """Return a copy of ``model`` with each chain ``J_X, J_Y, J_Z`` fused into a spherical ``J``.

    The spherical joint takes the place of ``J_X`` (its placement in the
    parent joint's frame) and the bodies of the three joints (the massless
    links and the child link: ``J_Y`` and ``J_Z`` sit at identity, so their
    inertias are already expressed in the same frame at q = 0). Frames keep
    their names and placements; the JOINT frames ``J_X, J_Y, J_Z`` give way to
    one JOINT frame ``J``. Limits, friction, damping and armature of the other
    joints are copied.

    Args:
        model: the model Pinocchio built from the XML of :func:`apply_loops_yaml`.
        names: the joints converted to ``SPHERICAL``.

    Raises:
        URDFError: a chain is not three revolute joints about X, Y, Z in a row
            at one place (the XML was changed after the conversion).
    """
    import pinocchio as pin

    chains: dict[int, tuple[str, list[int]]] = {}
    for name in names:
        parts = [f"{name}_{axis}" for axis in SPHERICAL_AXES]
        ids = [model.getJointId(p) if model.existJointName(p) else 0 for p in parts]
        if (
            0 in ids
            or [model.joints[j].shortname() for j in ids]
            != ["JointModelRX", "JointModelRY", "JointModelRZ"]
            or any(model.parents[b] != a for a, b in zip(ids, ids[1:], strict=False))
            or not all(model.jointPlacements[j].isIdentity() for j in ids[1:])
        ):
            raise URDFError(
                f"joint {name!r}: expected revolute joints {', '.join(parts)} about X, Y, Z in a "
                "row at one place, to fuse into a spherical joint"
            )
        chains[ids[0]] = (name, ids)

    new = pin.Model()
    new.name = model.name
    joint_of = {0: 0}
    copied: list[tuple[int, int]] = []  # (old joint, new joint) of unchanged joints
    for j in range(1, model.njoints):
        if j in joint_of:  # J_Y, J_Z: fused already
            continue
        parent = joint_of[model.parents[j]]
        if j in chains:
            name, ids = chains[j]
            jid = new.addJoint(parent, pin.JointModelSpherical(), model.jointPlacements[j], name)
            inertia = model.inertias[ids[0]] + model.inertias[ids[1]] + model.inertias[ids[2]]
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

    fused_joint_frames = {
        f"{name}_{axis}": name for name, _ in chains.values() for axis in SPHERICAL_AXES
    }
    frame_of = {0: 0}
    for i in range(1, len(model.frames)):
        f = model.frames[i]
        if f.type == pin.FrameType.JOINT and f.name in fused_joint_frames:
            name = fused_joint_frames[f.name]
            if not new.existFrame(name, pin.FrameType.JOINT):
                new.addFrame(
                    pin.Frame(
                        name,
                        joint_of[f.parentJoint],
                        frame_of[f.parentFrame],
                        pin.SE3.Identity(),
                        pin.FrameType.JOINT,
                    ),
                    False,
                )
            frame_of[i] = new.getFrameId(name, pin.FrameType.JOINT)
            continue
        frame = pin.Frame(
            f.name, joint_of[f.parentJoint], frame_of[f.parentFrame], f.placement, f.type, f.inertia
        )
        frame_of[i] = new.addFrame(frame, False)
    return new
