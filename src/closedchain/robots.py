"""Real robots: models found by name, loop overlays merged into any URDF.

Models of the installed ``example-robot-data`` package (the optional
``robots`` extra) are named ``erd:<name>``; :data:`ERD_MODELS` maps each name
to its URDF (or SDF, read by :mod:`closedchain.sdf`) and SRDF inside the
package (nothing is copied into closedchain).

An *overlay* is a file in URDF+ syntax whose ``<link>``, ``<joint>``,
``<material>``, ``<loop>`` and ``<transmission>`` elements are merged into the
base URDF's tree (so it can add the crank a robot turns, or weld a foot to
the ground)::

    <robot name="solo12_pinned">
      <loop name="FL_pin" type="spherical">
        <predecessor link="world"/>
        <successor link="FL_FOOT"/>
        <predecessor_origin xyz="0.19 0.15 0"/>
      </loop>
    </robot>

The link name ``world`` (:data:`closedchain.urdf.WORLD_LINK`) is reserved:
when the tree has no link of that name, a ``<loop>`` naming it is attached to
Pinocchio's universe, fixed whatever the root joint. An overlay ``<joint>``
may have ``world`` as parent only when the tree has such a link (as
ur5_robot.urdf does; Pinocchio's URDF reader needs one root link); if that
link is the tree's root and a root joint is added, it moves with the root.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from importlib import metadata
from pathlib import Path

import numpy as np

from .build import check_size
from .exceptions import ClosedChainError, ModelFileError, UnknownChoiceError
from .mjcf import MJCF_ROOT
from .sdf import is_sdf, read_sdf
from .urdf import WORLD_LINK, MechanismDescription, parse_urdf, read_overlay, read_xml
from .yaml_loops import apply_loops_yaml, is_loops_yaml, read_loops_yaml

__all__ = [
    "ERD_MODELS",
    "INSTALL_HINT",
    "RobotEntry",
    "resolve_model",
]

logger = logging.getLogger(__name__)

#: Prefix of a model name looked up in example-robot-data.
ERD_PREFIX = "erd:"

#: Distribution name of example-robot-data and where it keeps its robots.
ERD_DISTRIBUTION = "example-robot-data"
ERD_ROBOTS_DIR = "cmeel.prefix/share/example-robot-data/robots"

#: How to install the robots.
INSTALL_HINT = "pip install closedchain[robots]"

#: Overlay elements merged into the base tree.
OVERLAY_ELEMENTS = ("link", "joint", "material", "loop", "transmission")


@dataclass(frozen=True)
class RobotEntry:
    """One model of example-robot-data.

    Attributes:
        urdf: URDF (or SDF) path relative to the package's robots directory.
        srdf: SRDF path (reference configurations), or None.
        reference: name of the SRDF ``<group_state>`` used as the assembly
            start of ``q_ref``, or None (then Pinocchio's neutral configuration).
        cut_joints: for an SDF model, joints to cut in preference (see
            :mod:`closedchain.sdf`).
        fixed_joints: for an SDF model, joints read as ``fixed`` at their zero
            position (``fixed_joints`` of :func:`closedchain.sdf.read_sdf`).
        springs: whether the model's joint springs are kept (False: left out, with a
            logged note; for a file whose springs contradict its own geometry).
    """

    urdf: str
    srdf: str | None = None
    reference: str | None = None
    cut_joints: tuple[str, ...] = ()
    springs: bool = True
    fixed_joints: tuple[str, ...] = ()


#: Models found by ``erd:<name>``.
ERD_MODELS: dict[str, RobotEntry] = {
    "talos_reduced": RobotEntry(
        "talos_data/robots/talos_reduced.urdf", "talos_data/srdf/talos.srdf", "half_sitting"
    ),
    "solo12": RobotEntry(
        "solo_description/robots/solo12.urdf", "solo_description/srdf/solo.srdf", "standing"
    ),
    "ur5": RobotEntry("ur_description/urdf/ur5_robot.urdf", "ur_description/srdf/ur5.srdf"),
    # SDF: the achilles and plantar rods close with ball joints, the knee spring with a
    # revolute one; its gearbox joints tie each motor rotor to its output (closedchain.sdf).
    # The SRDF of cassie_v2 names the same joints with the same signs. The knee springs
    # (knee-shin joints) are held: the file's leaf-spring linkage (knee-spring link on a
    # revolute and a prismatic joint) locks the shin at a toggle (sigma_min(J) 9e-7) that
    # carries the shin's load with forces of 1e7 N; held, it closes with one clean row.
    # Its springs are left out: the achilles loops lock the heel springs, and at that
    # standing state hold them 0.63 rad from their spring_reference (790 N m)
    # (docs/guide/robots-and-moving-bases.md).
    "cassie": RobotEntry(
        "cassie_description/robots/cassie.sdf",
        "cassie_description/srdf/cassie_v2.srdf",
        "standing",
        springs=False,
        fixed_joints=("left-knee-shin-joint", "right-knee-shin-joint"),
    ),
}


def erd_robots_dir() -> Path:
    """Return the robots directory of the installed example-robot-data.

    Raises:
        ClosedChainError: the package is not installed (says how to install it).
    """
    try:
        dist = metadata.distribution(ERD_DISTRIBUTION)
    except metadata.PackageNotFoundError as exc:
        raise ClosedChainError(
            f"the {ERD_PREFIX} models need the {ERD_DISTRIBUTION} package, which is not "
            f"installed: {INSTALL_HINT}"
        ) from exc
    path = Path(str(dist.locate_file(ERD_ROBOTS_DIR)))
    if not path.is_dir():
        raise ClosedChainError(
            f"{ERD_DISTRIBUTION} {dist.version} has no robots directory {ERD_ROBOTS_DIR}; "
            f"reinstall it: {INSTALL_HINT}"
        )
    return path


def resolve_model(name: str | Path) -> tuple[Path, RobotEntry | None]:
    """Return the URDF file a model name stands for, and its registry entry.

    Args:
        name: a URDF path, or ``erd:<name>`` with a name of :data:`ERD_MODELS`.

    Raises:
        UnknownChoiceError: unknown ``erd:`` name (lists the valid ones).
        ClosedChainError: example-robot-data is not installed.
    """
    text = str(name)
    if not text.startswith(ERD_PREFIX):
        return Path(name), None
    key = text[len(ERD_PREFIX) :]
    if key not in ERD_MODELS:
        raise UnknownChoiceError(
            "example-robot-data model", text, [ERD_PREFIX + k for k in ERD_MODELS]
        )
    entry = ERD_MODELS[key]
    return erd_robots_dir() / entry.urdf, entry


def reference_configuration(model, entry: RobotEntry | None, *, robots_dir: Path | None = None):
    """Return the registry entry's SRDF reference configuration, or None.

    Args:
        model: the Pinocchio model (joints are matched by name; joints the
            SRDF does not mention keep their neutral value).
        entry: registry entry, or None.
        robots_dir: example-robot-data's robots directory (default: installed one).

    Returns:
        q, shape (nq,), or None when the entry names no reference.
    """
    import pinocchio as pin

    if entry is None or entry.srdf is None or entry.reference is None:
        return None
    robots_dir = robots_dir or erd_robots_dir()
    probe = model.copy()
    pin.loadReferenceConfigurations(probe, str(robots_dir / entry.srdf), False)
    if entry.reference not in probe.referenceConfigurations:
        raise ClosedChainError(
            f"{entry.srdf}: no <group_state name={entry.reference!r}>; states: "
            + ", ".join(sorted(probe.referenceConfigurations.keys()))
        )
    return np.array(probe.referenceConfigurations[entry.reference], dtype=float)


def read_base(base: Path, *, cut_joints: tuple[str, ...] = (), fixed_joints: tuple[str, ...] = ()):
    """Return the ``<robot>`` element of a base URDF.

    Args:
        base: the model file (an SDF file, ``.sdf``, and an MJCF file, root
            ``<mujoco>``, are refused: they are read into descriptions by
            :func:`closedchain.sdf.read_sdf` and :func:`closedchain.mjcf.read_mjcf`).
        cut_joints: SDF only: joints to cut in preference.
        fixed_joints: SDF only (a registry entry's): joints read as ``fixed``
            (:func:`closedchain.sdf.read_sdf`).

    Raises:
        ModelFileError: see :func:`closedchain.urdf.read_xml` and :func:`closedchain.sdf.read_sdf`;
            ``cut_joints`` given for a URDF; an SDF or MJCF file.
    """
    if is_sdf(base):
        raise ModelFileError(
            f"{base}: an SDF model is read into a description (closedchain.sdf.read_sdf), "
            "not a <robot> element"
        )
    if cut_joints:
        raise ModelFileError(
            f"{base}: cut_joints={list(cut_joints)} is for SDF models; a URDF names its "
            "loops with <loop> elements"
        )
    root = read_xml(base)
    if root.tag == MJCF_ROOT:
        raise ModelFileError(
            f"{base}: an MJCF model takes its loops from its <equality> elements; overlays "
            "(loops=, --loops) apply to URDF and SDF models"
        )
    return root


def merge_overlay(
    base: Path,
    overlay: str | Path | None,
    *,
    max_nv: int | None = None,
    cut_joints: tuple[str, ...] = (),
    fixed_joints: tuple[str, ...] = (),
    root=None,
) -> MechanismDescription:
    """Read a base model and merge an overlay into it.

    The base is read into a :class:`~closedchain.description.MechanismDescription` with its
    description (a URDF by :func:`~closedchain.urdf.parse_urdf`, once); the
    overlay's links, joints, loops and transmissions are read against it and
    merged into it (:func:`~closedchain.urdf.read_overlay`), a loops YAML's
    conversions applied to it (:func:`~closedchain.yaml_loops.apply_loops_yaml`):
    no text is merged or written, so any base with a description takes an overlay.

    An SDF base is read into a description by :func:`closedchain.sdf.read_sdf`; a loops
    YAML file, which converts a URDF's joints, is refused for it.

    Args:
        base: the base file (URDF or SDF).
        overlay: the overlay file (URDF+ syntax, root ``<robot>``), a loops
            YAML file of example-parallel-robots (a ``.yaml`` or ``.yml``
            suffix; see :mod:`closedchain.yaml_loops`), or None (an SDF base
            is still read).
        max_nv: largest supported tree size (see :func:`closedchain.urdf.parse_urdf`).
        cut_joints: SDF base only: joints to cut in preference (see :mod:`closedchain.sdf`).
        fixed_joints: SDF base only: joints read as ``fixed`` (see :mod:`closedchain.sdf`).
        root: the base's ``<robot>`` element, already read; None: :func:`read_base`
            reads it.

    Returns:
        The merged model. Its ``path`` is the overlay (messages about overlay
        elements give the overlay's line numbers); its ``robot_name`` is the
        overlay's ``<robot name>``, else the base's; its ``link_files`` send the
        base's links to the base file (their meshes are beside it).

    Raises:
        ModelFileError: unsafe or malformed XML, an element an overlay cannot hold
            (lists the valid ones), a link, joint or loop name the base already uses,
            or a tree larger than ``max_nv``.
    """
    if root is None and is_sdf(base):
        urdf, _ = read_sdf(base, cut_joints=cut_joints, fixed_joints=fixed_joints, max_nv=max_nv)
        if overlay is not None and is_loops_yaml(overlay):
            raise ModelFileError(
                f"{overlay}: a loops YAML file converts a URDF's joints; an SDF model takes a "
                "URDF+ overlay (root <robot>: links, joints, loops, transmissions)"
            )
    else:
        if root is None:
            root = read_base(base, cut_joints=cut_joints, fixed_joints=fixed_joints)
        urdf = parse_urdf(base, element=root, max_nv=max_nv)
    # The base's links keep their meshes beside the base, whatever file is merged in.
    base_links = {name: Path(base) for name in urdf.links}
    if overlay is None:
        return urdf
    if is_loops_yaml(overlay):
        converted = apply_loops_yaml(urdf, read_loops_yaml(overlay), root, base=base)
        check_size(converted.tree, max_nv)
        return replace(converted, link_files=base_links)
    merged = read_overlay(urdf, Path(overlay), _overlay_element(urdf, Path(overlay), base))
    check_size(merged.tree, max_nv)
    return replace(merged, link_files={**base_links, **urdf.link_files})


def _overlay_element(urdf: MechanismDescription, path: Path, base: Path):
    """Return an overlay file's ``<robot>`` element, checked: only :data:`OVERLAY_ELEMENTS`,
    no link, joint or loop name the base uses, no joint hanging from a missing world."""
    extra = read_xml(path, what="overlay file")
    if extra.tag != "robot":
        raise ModelFileError(f"{path}: root element is <{extra.tag}>, expected <robot>")
    taken = {
        "link": set(urdf.links),
        "joint": set(urdf.joints),
        "loop": {spec.name for spec in urdf.loops},
    }
    for element in extra:
        if not isinstance(element.tag, str):  # comments, processing instructions
            continue
        if element.tag not in OVERLAY_ELEMENTS:
            raise ModelFileError(
                f"{path}: line {element.sourceline}: <{element.tag}> cannot be merged; "
                f"valid overlay elements: {', '.join(OVERLAY_ELEMENTS)}"
            )
        name = element.get("name")
        if name in taken.get(element.tag, ()):
            raise ModelFileError(
                f"{path}: line {element.sourceline}: <{element.tag} name={name!r}> "
                f"already exists in {base}"
            )
    links = set(urdf.links) | {e.get("name") for e in extra.findall("link")}
    if urdf.tree.world_frame:
        links.add(WORLD_LINK)
    _check_world_joints(path, extra, links)
    return extra


def _check_world_joints(path: Path, root, links: set[str]) -> None:
    """Refuse overlay joints whose parent is ``world`` when the tree has no such link.

    Pinocchio's URDF reader needs a single root link, so a part can hang from
    the world through a ``<joint>`` only when the tree has a ``world`` link
    (e.g. ur5_robot.urdf); otherwise a ``<loop>`` to ``world`` fixes it.
    """
    if WORLD_LINK in links:
        return
    for joint in root.findall("joint"):
        parent = joint.find("parent")
        if parent is not None and parent.get("link") == WORLD_LINK:
            raise ModelFileError(
                f"{path}: line {joint.sourceline}: <joint name={joint.get('name')!r}> has "
                f"parent {WORLD_LINK!r}, but the tree has no {WORLD_LINK!r} link: attach the "
                f"part to the robot, or fix it to the world with a <loop> whose predecessor "
                f"is {WORLD_LINK!r}"
            )
