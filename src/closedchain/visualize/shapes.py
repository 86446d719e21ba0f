"""Shapes: the URDF ``<visual>`` primitives and meshes, joint markers, bodies."""

from __future__ import annotations

import io
import logging
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from .._io import MAX_MESH_BYTES, check_input_file
from ..constraints import axis_basis
from ..exceptions import ClosedChainError
from ..urdf import COUPLING

if TYPE_CHECKING:
    from ..mechanism import Mechanism

from .settings import (
    DEFAULT_SETTINGS,
    SCENE_ROOT,
    AnimationSettings,
    Body,
    JointMarker,
    VisualShape,
)

logger = logging.getLogger(__name__)


def _meshcat():
    import warnings

    with warnings.catch_warnings():
        # meshcat's server module (imported by meshcat, unused here) imports
        # zmq.eventloop.ioloop, deprecated in pyzmq >= 17.
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="meshcat")
        import meshcat  # lazy: it imports zmq and IPython

    return meshcat


def scene_path(*names: str) -> str:
    """Return the meshcat path of nested URDF names under :data:`SCENE_ROOT`.

    Each name is percent-encoded (``urllib.parse.quote`` with no safe
    characters), so a ``/`` cannot split it and markup characters cannot reach
    the page. Plain names (letters, digits, ``_.-~``) are unchanged.
    """
    return SCENE_ROOT + "".join("/" + urllib.parse.quote(n, safe="") for n in names)


def _mesh_candidates(filename: str, urdf_dir: Path) -> list[Path]:
    """Return the paths a URDF mesh ``filename`` may refer to, in lookup order.

    A plain name is relative to ``urdf_dir`` (or absolute); ``file://`` gives
    a path the same way; ``package://pkg/sub`` is looked up as ``sub`` in
    ``urdf_dir``, then in its parent directories (where ROS packages keep
    their meshes, so that :func:`_resolve_mesh` can name a file it refuses);
    other schemes give nothing.
    """
    scheme, sep, rest = filename.partition("://")
    if not sep:
        return [urdf_dir / filename]
    if scheme == "file":
        return [urdf_dir / urllib.parse.unquote(rest)]
    if scheme == "package":
        sub = rest.partition("/")[2]
        return [d / sub for d in (urdf_dir, *urdf_dir.parents)] if sub else []
    return []


def _resolve_mesh(filename: str, urdf_dir: Path) -> tuple[Path | None, Path | None]:
    """Return (the mesh file, None), or (None, a file found outside ``urdf_dir``).

    Only files under the URDF's directory (after resolving ``..`` and symbolic
    links) are drawn, so a URDF cannot embed arbitrary local files in the page.
    ``urdf_dir`` must be resolved. (None, None): no file found.
    """
    outside = None
    for candidate in _mesh_candidates(filename, urdf_dir):
        if not candidate.is_file():
            continue
        found = candidate.resolve()
        if found.is_relative_to(urdf_dir):
            return found, None
        outside = outside or found
    return None, outside


def read_visuals(mech: Mechanism, *, settings: AnimationSettings = DEFAULT_SETTINGS):
    """Read the ``<visual>`` elements of the mechanism's URDF.

    Materials are resolved by name against the robot's top-level
    ``<material>`` elements. Mesh files are looked up relative to the URDF
    (``file://`` URLs as paths, ``package://pkg/sub`` as ``sub``); only files
    under the URDF's directory are drawn (the page embeds them, so a URDF must
    not reach other local files): a mesh outside it, whose file is not found,
    or larger than :data:`closedchain._io.MAX_MESH_BYTES`, is skipped with a
    warning naming the file and the link.

    Args:
        mech: the mechanism.
        settings: gives the colour of visuals without a material.

    Returns:
        tuple of :class:`VisualShape`, in URDF order.
    """
    import yourdfpy

    robot = yourdfpy.URDF.load(
        io.BytesIO(mech.urdf.xml.encode("utf-8")),
        build_scene_graph=False,
        load_meshes=False,
        build_collision_scene_graph=False,
        load_collision_meshes=False,
    ).robot
    named = {m.name: m for m in robot.materials if m.name}
    urdf_dir = Path(mech.path).resolve().parent
    out: list[VisualShape] = []
    for link in robot.links:
        for i, vis in enumerate(link.visuals):
            origin = np.eye(4) if vis.origin is None else np.array(vis.origin, dtype=float)
            rgba = _rgba(vis.material, named, settings.default_rgba)
            g = vis.geometry
            if g is None:
                continue
            if g.box is not None:
                out.append(VisualShape(link.name, "box", _floats(g.box.size), origin, rgba))
            elif g.cylinder is not None:
                dims = (float(g.cylinder.radius), float(g.cylinder.length))
                out.append(VisualShape(link.name, "cylinder", dims, origin, rgba))
            elif g.sphere is not None:
                out.append(
                    VisualShape(link.name, "sphere", (float(g.sphere.radius),), origin, rgba)
                )
            elif g.mesh is not None:
                found, outside = _resolve_mesh(g.mesh.filename, urdf_dir)
                if outside is not None:
                    logger.warning(
                        "%s: link %r visual %d: mesh file %r (%s) is outside the URDF's"
                        " directory %s; not drawn",
                        mech.path,
                        link.name,
                        i,
                        g.mesh.filename,
                        outside,
                        urdf_dir,
                    )
                    continue
                if found is None:
                    logger.warning(
                        "%s: link %r visual %d: mesh file %r not found; not drawn",
                        mech.path,
                        link.name,
                        i,
                        g.mesh.filename,
                    )
                    continue
                try:  # the page embeds the mesh: bound it (a FIFO is not is_file())
                    check_input_file(found, limit=MAX_MESH_BYTES, what="mesh file")
                except ClosedChainError as exc:
                    logger.warning(
                        "%s: link %r visual %d: %s; not drawn", mech.path, link.name, i, exc
                    )
                    continue
                scale = g.mesh.scale
                dims = (1.0, 1.0, 1.0) if scale is None else _floats(np.broadcast_to(scale, 3))
                out.append(VisualShape(link.name, "mesh", dims, origin, rgba, found))
    return tuple(out)


def _floats(x) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(x, dtype=float).ravel())


def _rgba(material, named: dict, default) -> tuple[float, float, float, float]:
    if material is None:
        return tuple(default)
    color = material.color
    if color is None and material.name in named:
        color = named[material.name].color
    if color is None or color.rgba is None:
        return tuple(default)
    rgba = np.clip(np.asarray(color.rgba, dtype=float), 0.0, 1.0)
    return tuple(float(c) for c in rgba)


def _frame_with_z(axis: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Return a (4, 4) frame at ``origin`` [m] whose z axis is the unit ``axis``."""
    n1, n2 = axis_basis(axis)
    T = np.eye(4)
    T[:3, :3] = np.column_stack((n1, n2, axis))
    T[:3, 3] = origin
    return T


def _find_pin(cylinders, axis: np.ndarray, tol: float) -> tuple[float, float] | None:
    """Return (offset along the axis [m], radius [m]) of the largest coaxial cylinder.

    Args:
        cylinders: (placement in the joint frame (4, 4), radius [m], length [m]).
        axis: joint axis in the joint frame, unit, shape (3,).
        tol: angle tolerance [rad] and relative offset tolerance [-].
    """
    best = None
    for T, radius, length in cylinders:
        c, z = T[:3, 3], T[:3, 2]
        off_axis = np.linalg.norm(c - (c @ axis) * axis)
        if np.linalg.norm(np.cross(z, axis)) <= tol and off_axis <= tol * max(length, radius):
            if best is None or radius > best[1]:
                best = (float(c @ axis), float(radius))
    return best


def _cylinders(visuals, link: str, jMl: np.ndarray):
    return [
        (jMl @ v.origin, v.dims[0], v.dims[1])
        for v in visuals
        if v.link == link and v.kind == "cylinder"
    ]


def joint_markers(
    mech: Mechanism, visuals=(), *, settings: AnimationSettings = DEFAULT_SETTINGS
) -> tuple[JointMarker, ...]:
    """Return the markers of the actuated joints and the loop joints.

    A loop marker is carried by the predecessor link, an actuated-joint marker
    by the joint's child link. Its z axis is the joint axis. It sits on the
    joint's pin when one of the two links has a cylinder visual coaxial with
    the joint (the largest such), otherwise at the joint origin (which for a
    spherical mechanism is the common centre).

    Args:
        mech: the mechanism.
        visuals: the URDF visuals (see :func:`read_visuals`), searched for pins.
        settings: gives the coaxiality tolerance.
    """
    model = mech.model
    q_neutral = pin.neutral(model)
    tol = settings.coaxial_tol
    out: list[JointMarker] = []
    for name in mech.actuated_joints:
        jid = model.getJointId(name)
        # URDF: the child link's frame is the joint frame; Pinocchio links the
        # JOINT frame to its parent link's BODY frame and the child's to it.
        fj = model.getFrameId(name, pin.FrameType.JOINT)
        child = next(
            (f for f in model.frames if f.parentFrame == fj and f.type == pin.FrameType.BODY),
            None,
        )
        if child is None:
            continue
        axis, shape = _joint_axis(model.joints[jid], q_neutral)
        jMc = child.placement.homogeneous
        cylinders = _cylinders(visuals, child.name, jMc)
        parent = model.frames[model.frames[fj].parentFrame]
        if parent.type == pin.FrameType.BODY:
            # Parent link in the joint frame at q = 0 (a revolute joint only turns
            # about the axis, which keeps coaxial cylinders coaxial).
            jMp = model.jointPlacements[jid].inverse() * parent.placement
            cylinders += _cylinders(visuals, parent.name, jMp.homogeneous)
        pin_ = _find_pin(cylinders, axis, tol) if shape == "ring" else None
        offset, pin_radius = pin_ if pin_ else (0.0, 0.0)
        cMj = np.linalg.inv(jMc)
        origin = cMj @ _frame_with_z(axis, offset * axis)
        out.append(JointMarker("actuated", name, child.name, origin, shape, pin_radius))
    for spec in mech.urdf.loops:
        if spec.type == COUPLING:  # it joins two coordinates, no two frames: no marker
            continue
        shape = "ring" if spec.type in ("revolute", "prismatic") else "ball"
        # In the cut-joint frames c1 and c2 the axis has the same coordinates
        # (closed, they differ by a motion along or about the axis).
        cylinders = []
        for link, M in (
            (spec.predecessor, spec.predecessor_origin),
            (spec.successor, spec.successor_origin),
        ):
            cylinders += _cylinders(visuals, link, M.inverse().homogeneous)
        pin_ = _find_pin(cylinders, spec.axis, tol) if shape == "ring" else None
        offset, pin_radius = pin_ if pin_ else (0.0, 0.0)
        origin = spec.predecessor_origin.homogeneous @ _frame_with_z(spec.axis, offset * spec.axis)
        out.append(JointMarker("loop", spec.name, spec.predecessor, origin, shape, pin_radius))
    return tuple(out)


def _joint_axis(joint, q_neutral: np.ndarray) -> tuple[np.ndarray, str]:
    """Return (unit axis in the joint frame, marker shape) of a Pinocchio joint model.

    The axis of a 1-dof joint is read from its motion subspace S (shape (6, 1):
    linear, angular): the angular part for a revolute joint (aligned,
    unaligned, unbounded), the linear part for a prismatic one. Other joints
    get a ball marker.
    """
    if joint.nv != 1:
        return np.array([0.0, 0.0, 1.0]), "ball"
    jdata = joint.createData()
    joint.calc(jdata, q_neutral)
    S = np.asarray(jdata.S, dtype=float).ravel()
    axis = S[3:] if np.linalg.norm(S[3:]) > 0 else S[:3]
    return axis / np.linalg.norm(axis), "ring"


def _bodies(mech: Mechanism, links: list[str], root: str) -> tuple[Body, ...]:
    model = mech.model
    bodies = []
    for link in links:
        if not model.existFrame(link, pin.FrameType.BODY):
            logger.warning("%s: link %r is not in the Pinocchio model; not drawn", mech.path, link)
            continue
        fid = model.getFrameId(link, pin.FrameType.BODY)
        moving = model.frames[fid].parentJoint != 0
        bodies.append(Body(link, fid, scene_path(root, link), moving))
    return tuple(bodies)


# -- the motion ----------------------------------------------------------------
