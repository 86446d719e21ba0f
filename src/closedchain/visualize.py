r"""Offline meshcat scenes and animations, written as one self-contained HTML file.

The scene is built with meshcat's own Python commands, recorded by a
window-like object instead of being sent to a meshcat server (no server
process, no network), and replayed in the page by meshcat's JavaScript viewer
(``main.min.js`` from the installed meshcat package, inlined):

- one meshcat node per URDF link that has something to draw, holding the
  link's ``<visual>`` primitives (box, cylinder, sphere, and meshes whose file
  is found) in their URDF colours, plus markers for the loop joints (on the
  predecessor link, at the cut-joint frame c1) and the actuated joints (on the
  joint's child link);
- one transform track (position + quaternion) per moving link node, with
  keyframes resampled to the display rate ``fps`` whatever the simulation
  step, interpolated on the configuration Lie group (``pin.interpolate``);
- a camera that frames the volume the mechanism sweeps over the whole motion.

Object UUIDs are derived from the scene paths (``uuid5``), not from the clock,
so the same trajectory gives a byte-identical file. Names from the URDF are
percent-encoded in scene paths and JSON-escaped in the page; a
Content-Security-Policy admits only the page's own scripts (by hash) and no
network access.

meshcat (which imports zmq and IPython) is imported lazily, on first use.
"""

from __future__ import annotations

import base64
import functools
import hashlib
import html
import io
import json
import logging
import math
import urllib.parse
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from .constraints import axis_basis
from .exceptions import ClosedChainError
from .trajectory import Trajectory

if TYPE_CHECKING:
    from .mechanism import Mechanism

logger = logging.getLogger(__name__)

#: Namespace of the deterministic object UUIDs (uuid5 of the object's scene path).
UUID_NAMESPACE = uuid.UUID("6c0b6f1e-3f55-5a43-9a53-636c6f736564")

#: Default display rate of the animation [frames/s].
DEFAULT_FPS = 30.0

#: Shapes of the URDF ``<visual>`` geometries that are drawn.
VISUAL_KINDS = ("box", "cylinder", "sphere", "mesh")

#: Mesh formats meshcat's viewer reads directly; others are converted to STL by trimesh.
NATIVE_MESH_FORMATS = ("stl", "obj", "dae")

#: A trajectory time step below this [s] counts as a repeated sample.
TIME_EPS = 1e-12

#: Relative tolerance on t * fps when counting whole frames, and absolute
#: tolerance [frames] for a keyframe to count as a whole frame number.
FRAME_EPS = 1e-9

#: Smallest radius [m] given to the swept volume (a point-like scene).
MIN_SCENE_RADIUS = 1e-3

#: Cell size [m] of meshcat's grid (THREE.GridHelper(20, 40)); the grid is
#: scaled to cells of {1, 2, 5} x 10^k m near a quarter of the scene radius.
MESHCAT_GRID_CELL = 0.5
GRID_CELLS_PER_RADIUS = 4.0
#: The grid lies this fraction of the scene radius below the lowest point [-].
GRID_CLEARANCE = 0.05

#: Camera near and far planes: camera distance divided and multiplied by this [-].
CLIP_RATIO = 100.0

#: Segments of the ring markers (three.js TorusGeometry) around the tube and the ring.
TORUS_SEGMENTS = (12, 48)

#: Scene root of the mechanism in the meshcat tree.
SCENE_ROOT = "/meshcat"

#: Debian's Chromium, which renders these pages headless (tests, scripts/screenshot.py).
CHROMIUM_PATH = "/usr/bin/chromium"

#: Chromium flags for headless rendering: software WebGL (SwiftShader), no
#: sandbox (containers), no background traffic of the browser itself.
HEADLESS_CHROMIUM_ARGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
)

#: Rotation taking meshcat's cylinder axis (y) onto URDF's cylinder axis (z).
_Y_TO_Z = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


@dataclass(frozen=True)
class AnimationSettings:
    """Settings of the scene, camera and animation that :func:`write_html` writes.

    Attributes:
        default_rgba: colour of a visual without a URDF material, (r, g, b, a) in [0, 1].
        loop_color: colour of the loop-joint markers, 0xRRGGBB.
        actuated_color: colour of the actuated-joint markers, 0xRRGGBB.
        marker_radius: smallest ring radius of a joint marker, as a fraction
            of the radius of the swept volume [-] (also the size of a marker
            that finds no pin).
        marker_pin_ratio: a marker around a pin (a cylinder visual coaxial
            with the joint) has this times the pin's radius [-].
        marker_tube: tube radius of a ring as a fraction of its radius [-].
        coaxial_tol: a cylinder is a joint's pin when its axis is within this
            angle [rad] of the joint axis and its centre within this fraction of
            its length of the axis line.
        camera_fov: vertical field of view of the camera [deg].
        camera_margin: the camera stands this factor farther than the distance
            at which the swept volume's bounding sphere fills the field of view [-].
        axis_ratio: the camera looks along the principal axis of least extent
            of the swept volume (the normal of a planar motion, the symmetry
            axis of a spherical wrist) when its extent is below this fraction
            of the middle one; otherwise along ``view_direction`` [-].
        camera_tilt: how far the view direction leans from that axis towards
            ``view_direction`` (for depth) [-].
        view_direction: direction from the target to the camera in the world
            frame when the swept volume has no clear axis of least extent; it
            also chooses the side the camera looks from.
        max_bound_samples: keyframes sampled to bound the swept volume.
        show_axes: keep meshcat's world axes (0.5 m arrows at the origin).
        open_controls: open meshcat's control panel (with the animation
            controls: play, pause, reset, time scrubber) when the page opens.
    """

    default_rgba: tuple[float, float, float, float] = (0.6, 0.6, 0.6, 1.0)
    loop_color: int = 0xE0218A
    actuated_color: int = 0x00A5CF
    marker_radius: float = 0.04
    marker_pin_ratio: float = 1.8
    marker_tube: float = 0.18
    coaxial_tol: float = 1e-3
    camera_fov: float = 40.0
    camera_margin: float = 1.05
    axis_ratio: float = 0.8
    camera_tilt: float = 0.15
    view_direction: tuple[float, float, float] = (1.0, -1.0, 0.8)
    max_bound_samples: int = 60
    show_axes: bool = False
    open_controls: bool = True


DEFAULT_SETTINGS = AnimationSettings()


@dataclass(frozen=True)
class VisualShape:
    """One URDF ``<visual>`` element to draw.

    Attributes:
        link: name of its link.
        kind: one of :data:`VISUAL_KINDS`.
        dims: box (x, y, z) sizes [m]; cylinder (radius, length) [m]; sphere
            (radius,) [m]; mesh scale (sx, sy, sz) [-].
        origin: placement of the visual in the link frame, shape (4, 4) [m].
        rgba: colour, (r, g, b, a) in [0, 1].
        mesh: the mesh file (kind ``"mesh"`` only).
    """

    link: str
    kind: str
    dims: tuple[float, ...]
    origin: np.ndarray
    rgba: tuple[float, float, float, float]
    mesh: Path | None = None


@dataclass(frozen=True)
class JointMarker:
    """A marker drawn at a loop joint or an actuated joint.

    Attributes:
        kind: ``"loop"`` or ``"actuated"``.
        name: the loop's or the joint's name.
        link: the link that carries it.
        origin: marker frame in the link frame, shape (4, 4) [m]; its z axis is
            the joint axis.
        shape: ``"ring"`` (around the axis: revolute, prismatic) or ``"ball"``.
        pin_radius: radius [m] of the joint's pin (a cylinder visual of either
            link coaxial with the joint; the marker rings it), 0 if none.
    """

    kind: str
    name: str
    link: str
    origin: np.ndarray
    shape: str
    pin_radius: float = 0.0


@dataclass(frozen=True)
class Body:
    """A link drawn as one meshcat node.

    Attributes:
        link: link name from the URDF.
        frame_id: its Pinocchio BODY frame.
        path: its meshcat path (names percent-encoded).
        moving: whether it moves (then it has a transform track).
    """

    link: str
    frame_id: int
    path: str
    moving: bool


@dataclass(frozen=True)
class MeshcatScene:
    """A recorded meshcat scene and animation, ready to be written as HTML.

    Attributes:
        name: the mechanism's name.
        bodies: the drawn links.
        visuals: the URDF visuals drawn.
        markers: the joint markers drawn.
        commands: meshcat commands, msgpack-encoded, in replay order.
        times: keyframe times [s], shape (K,), starting at 0.
        placements: world placements of the bodies at the keyframes, shape (K, nb, 4, 4) [m].
        fps: display rate [frames/s].
        center: centre of the swept volume in the world frame, shape (3,) [m].
        radius: radius of its bounding sphere [m].
        camera_position: camera position in the world frame, shape (3,) [m].
        camera_target: point the camera looks at, world frame, shape (3,) [m].
    """

    name: str
    bodies: tuple[Body, ...]
    visuals: tuple[VisualShape, ...]
    markers: tuple[JointMarker, ...]
    commands: tuple[bytes, ...]
    times: np.ndarray
    placements: np.ndarray
    fps: float
    center: np.ndarray
    radius: float
    camera_position: np.ndarray
    camera_target: np.ndarray

    @property
    def duration(self) -> float:
        """Length of the animation [s]."""
        return float(self.times[-1])

    @property
    def n_tracks(self) -> int:
        """Number of transform tracks (one per moving body)."""
        return sum(b.moving for b in self.bodies) if len(self.times) > 1 else 0


@dataclass(frozen=True)
class HTMLAnimation:
    """What :func:`write_html` wrote.

    Attributes:
        path: the HTML file.
        size: its size [bytes].
        duration: length of the animation [s].
        fps: display rate [frames/s].
        n_keyframes: keyframes per track.
        n_tracks: transform tracks (one per moving body).
        bodies: names of the links drawn.
    """

    path: Path
    size: int
    duration: float
    fps: float
    n_keyframes: int
    n_tracks: int
    bodies: tuple[str, ...] = field(default_factory=tuple)


# -- reading the URDF ----------------------------------------------------------


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
    not reach other local files): a mesh outside it, or whose file is not
    found, is skipped with a warning naming the file and the link.

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


def check_trajectory(mech: Mechanism, trajectory: Trajectory) -> None:
    """Raise ClosedChainError unless the trajectory fits the mechanism and its times increase."""
    t = np.asarray(trajectory.t, dtype=float)
    q = np.asarray(trajectory.q, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ClosedChainError(f"trajectory.t has shape {t.shape}, expected (N,) with N >= 1")
    if q.shape != (t.size, mech.nq):
        raise ClosedChainError(
            f"trajectory.q has shape {q.shape}, expected ({t.size}, {mech.nq}) for {mech.name}"
        )
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ClosedChainError("trajectory.t or trajectory.q contains non-finite values")
    if np.any(np.diff(t) <= TIME_EPS):
        k = int(np.argmax(np.diff(t) <= TIME_EPS))
        raise ClosedChainError(
            f"trajectory times must increase: t[{k}] = {t[k]!r}, t[{k + 1}] = {t[k + 1]!r}"
        )


def resample(mech: Mechanism, trajectory: Trajectory, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Resample a trajectory at the display rate.

    Keyframes fall at k / fps for k = 0, 1, ... from the first sample, plus one
    at the last sample if it lies between two frames, so the animation lasts
    exactly as long as the trajectory. Configurations between samples are
    interpolated on the configuration Lie group (``pin.interpolate``); a
    keyframe that falls on a sample takes that sample exactly.

    Args:
        mech: the mechanism.
        trajectory: times shape (N,) [s] and configurations shape (N, nq).
        fps: display rate [frames/s].

    Returns:
        (times [s] from 0, shape (K,); configurations, shape (K, nq)).
    """
    check_trajectory(mech, trajectory)
    if not (math.isfinite(fps) and fps > 0):
        raise ClosedChainError(f"fps must be a positive number of frames per second, got {fps}")
    t = np.asarray(trajectory.t, dtype=float) - float(trajectory.t[0])
    q = np.asarray(trajectory.q, dtype=float)
    T = float(t[-1])
    n = int(math.floor(T * fps * (1.0 + FRAME_EPS))) + 1
    times = np.arange(n, dtype=float) / fps
    if T - times[-1] > TIME_EPS:
        times = np.append(times, T)
    if t.size == 1:
        return times[:1], q[:1].copy()
    idx = np.clip(np.searchsorted(t, times, side="right") - 1, 0, t.size - 2)
    alpha = np.clip((times - t[idx]) / (t[idx + 1] - t[idx]), 0.0, 1.0)
    out = np.empty((times.size, mech.nq))
    for k, (i, a) in enumerate(zip(idx, alpha, strict=True)):
        if a == 0.0:
            out[k] = q[i]
        elif a == 1.0:
            out[k] = q[i + 1]
        else:
            out[k] = pin.interpolate(mech.model, q[i], q[i + 1], float(a))
    return times, out


def body_placements(mech: Mechanism, bodies, qs: np.ndarray) -> np.ndarray:
    """Return the world placements of bodies at configurations.

    Args:
        mech: the mechanism.
        bodies: sequence of :class:`Body`.
        qs: configurations, shape (K, nq).

    Returns:
        Homogeneous placements oMf, shape (K, nb, 4, 4) [m].
    """
    data = mech.model.createData()
    out = np.empty((len(qs), len(bodies), 4, 4))
    for k, q in enumerate(qs):
        pin.framesForwardKinematics(mech.model, data, q)
        for b, body in enumerate(bodies):
            out[k, b] = data.oMf[body.frame_id].homogeneous
    return out


def _local_points(kind: str, dims: tuple[float, ...], mesh: Path | None) -> np.ndarray:
    """Return corners of a shape's bounding box in its own frame, shape (8, 3) [m]."""
    if kind == "box":
        h = 0.5 * np.array(dims)
    elif kind == "cylinder":
        h = np.array([dims[0], dims[0], 0.5 * dims[1]])
    elif kind == "sphere":
        h = np.full(3, dims[0])
    else:
        lo, hi = _mesh_bounds(mesh)
        lo, hi = lo * np.array(dims), hi * np.array(dims)
        return np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return signs * h


def _mesh_bounds(mesh: Path | None) -> tuple[np.ndarray, np.ndarray]:
    try:
        import trimesh

        bounds = trimesh.load(str(mesh), force="mesh").bounds
        return np.asarray(bounds[0], dtype=float), np.asarray(bounds[1], dtype=float)
    except Exception as exc:  # any failure of a third-party reader: fall back
        logger.warning("cannot read the bounds of mesh %s (%s); framing ignores it", mesh, exc)
        return np.zeros(3), np.zeros(3)


def _swept_points(bodies, visuals, markers, placements, sizes, settings) -> np.ndarray:
    """World points bounding the visuals over sampled keyframes, shape (P, 3) [m]."""
    index = {b.link: i for i, b in enumerate(bodies)}
    K = placements.shape[0]
    ks = np.unique(np.linspace(0, K - 1, min(K, settings.max_bound_samples)).astype(int))
    local: list[tuple[int, np.ndarray]] = []
    for v in visuals:
        if v.link in index:
            pts = _local_points(v.kind, v.dims, v.mesh)
            pts = (v.origin[:3, :3] @ pts.T).T + v.origin[:3, 3]
            local.append((index[v.link], pts))
    for m in markers:
        if m.link in index:
            pts = _local_points("sphere", (sizes[(m.kind, m.name)],), None)
            local.append((index[m.link], pts + m.origin[:3, 3]))
    if not local:
        return placements[ks][:, :, :3, 3].reshape(-1, 3)
    out = []
    for b, pts in local:
        M = placements[ks, b]  # (k, 4, 4)
        out.append(np.einsum("kij,pj->kpi", M[:, :3, :3], pts) + M[:, None, :3, 3])
    return np.concatenate([o.reshape(-1, 3) for o in out])


def _bounds(points: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = points.min(axis=0), points.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.max(np.linalg.norm(points - center, axis=1)))
    return center, max(radius, MIN_SCENE_RADIUS)


def frame_camera(points: np.ndarray, settings: AnimationSettings = DEFAULT_SETTINGS):
    """Place the camera so that it frames the given world points.

    The target is the centre of the points' bounding box. The camera looks
    along the principal axis of least extent of the points, which shows the
    most of them (a planar linkage face-on), leaning by ``settings.camera_tilt``
    towards ``settings.view_direction``; when no axis is clearly least
    (smallest extent above ``settings.axis_ratio`` times the middle one) it
    looks along ``view_direction``. The distance makes the bounding sphere fill
    the vertical field of view, times ``settings.camera_margin``.

    Args:
        points: world points [m], shape (P, 3).
        settings: camera settings.

    Returns:
        (camera position, target, bounding-sphere radius): shapes (3,), (3,) [m], float [m].
    """
    center, radius = _bounds(points)
    d0 = np.asarray(settings.view_direction, dtype=float)
    d0 = d0 / np.linalg.norm(d0)
    _, s, Vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    direction = d0
    if s.size == 3 and s[1] > 0 and s[2] < settings.axis_ratio * s[1]:
        n = Vt[2] if Vt[2] @ d0 >= 0 else -Vt[2]
        lean = d0 - (d0 @ n) * n
        direction = n + settings.camera_tilt * lean
        direction = direction / np.linalg.norm(direction)
    distance = settings.camera_margin * radius / math.sin(math.radians(settings.camera_fov) / 2)
    return center + distance * direction, center, radius


def _nice_step(x: float) -> float:
    """Return the number of the form {1, 2, 5} x 10^k closest (in log) to x > 0."""
    k = math.floor(math.log10(x))
    candidates = [m * 10.0**e for e in (k, k + 1) for m in (1.0, 2.0, 5.0)]
    return min(candidates, key=lambda c: abs(math.log(c / x)))


# -- recording meshcat commands ------------------------------------------------


class CommandRecorder:
    """A window-like object for ``meshcat.Visualizer(window=...)`` that records commands.

    ``meshcat.Visualizer()`` would start a server process; this records each
    command as meshcat's server would receive it (msgpack of ``command.lower()``).
    Animations are packed in single precision: three.js stores keyframes as
    Float32Array anyway, so nothing the viewer shows is lost.
    """

    def __init__(self) -> None:
        self.commands: list[bytes] = []

    def send(self, command) -> None:
        """Record one meshcat command."""
        import umsgpack

        lowered = command.lower()
        if lowered["type"] == "set_animation":
            self.commands.append(umsgpack.packb(lowered, force_float_precision="single"))
        else:
            self.commands.append(umsgpack.packb(lowered))


class _TorusGeometry:
    """three.js TorusGeometry (a ring about the z axis), duck-typed as a meshcat Geometry."""

    field = "geometries"

    def __init__(self, radius: float, tube: float, uid: str) -> None:
        self.radius = radius
        self.tube = tube
        self.uuid = uid

    def intrinsic_transform(self) -> np.ndarray:
        return np.eye(4)

    def lower(self, object_data) -> dict:
        return {
            "uuid": self.uuid,
            "type": "TorusGeometry",
            "radius": self.radius,
            "tube": self.tube,
            "radialSegments": TORUS_SEGMENTS[0],
            "tubularSegments": TORUS_SEGMENTS[1],
        }

    def lower_in_object(self, object_data) -> str:
        object_data.setdefault(self.field, []).append(self.lower(object_data))
        return self.uuid


def _uid(*parts: str) -> str:
    return str(uuid.uuid5(UUID_NAMESPACE, "\x00".join(parts)))


def _hex(rgba) -> int:
    r, g, b = (int(round(255 * c)) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


def _mesh_geometry(mg, path: Path):
    """Return a meshcat geometry for a mesh file (None if it cannot be read)."""
    fmt = path.suffix.lower().lstrip(".")
    try:
        if fmt in NATIVE_MESH_FORMATS:
            reader = {
                "stl": mg.StlMeshGeometry,
                "obj": mg.ObjMeshGeometry,
                "dae": mg.DaeMeshGeometry,
            }[fmt]
            return reader.from_file(str(path))
        import trimesh

        stl = trimesh.load(str(path), force="mesh").export(file_type="stl")
        return mg.StlMeshGeometry.from_stream(io.BytesIO(stl))
    except Exception as exc:  # an unreadable mesh is skipped, not fatal
        logger.warning("cannot read mesh %s (%s); not drawn", path, exc)
        return None


def _set_mesh(vis, mg, geometry, rgba, key: str) -> None:
    """``vis.set_object`` of a Mesh with deterministic UUIDs derived from ``key``."""
    geometry.uuid = _uid(key, "geometry")
    material = mg.MeshPhongMaterial(color=_hex(rgba), opacity=float(rgba[3]))
    material.uuid = _uid(key, "material")
    obj = mg.Mesh(geometry, material)
    obj.uuid = _uid(key, "object")
    vis.set_object(obj)


def build_scene(
    mech: Mechanism,
    trajectory: Trajectory,
    *,
    fps: float = DEFAULT_FPS,
    settings: AnimationSettings = DEFAULT_SETTINGS,
) -> MeshcatScene:
    """Record the meshcat scene and animation of a trajectory.

    Args:
        mech: the mechanism.
        trajectory: its motion: times shape (N,) [s], configurations shape (N, nq).
        fps: display rate [frames/s]; keyframes are resampled to it.
        settings: scene, camera and marker settings.

    Returns:
        The recorded scene.

    Raises:
        ClosedChainError: the trajectory does not fit the mechanism, its times
            do not increase, or fps is not positive.
    """
    mc = _meshcat()
    mg = mc.geometry
    times, qs = resample(mech, trajectory, fps)
    visuals = read_visuals(mech, settings=settings)
    markers = joint_markers(mech, visuals, settings=settings)
    if not visuals:
        logger.warning(
            "%s: the URDF has no drawable <visual>: only joint markers are drawn", mech.path
        )
    drawn = {v.link for v in visuals} | {m.link for m in markers}
    root = mech.name
    bodies = _bodies(mech, [ln for ln in mech.urdf.links if ln in drawn], root)
    placements = body_placements(mech, bodies, qs)

    # Markers are sized from their pin, at least a fraction of the swept volume.
    _, radius0 = _bounds(_swept_points(bodies, visuals, (), placements, {}, settings))
    sizes = {
        (m.kind, m.name): max(
            settings.marker_pin_ratio * m.pin_radius, settings.marker_radius * radius0
        )
        for m in markers
    }
    points = _swept_points(bodies, visuals, markers, placements, sizes, settings)
    cam_pos, target, radius = frame_camera(points, settings)

    recorder = CommandRecorder()
    vis = mc.Visualizer(window=recorder)
    index = {b.link: b for b in bodies}
    counters: dict[str, int] = {}
    for v in visuals:
        body = index.get(v.link)
        if body is None:
            continue
        i = counters.get(v.link, 0)
        counters[v.link] = i + 1
        path = f"{body.path}/visual_{i}"
        T = v.origin
        if v.kind == "box":
            geometry = mg.Box(list(v.dims))
        elif v.kind == "cylinder":
            geometry = mg.Cylinder(v.dims[1], v.dims[0])
            T = T @ _Y_TO_Z
        elif v.kind == "sphere":
            geometry = mg.Sphere(v.dims[0])
        else:
            geometry = _mesh_geometry(mg, v.mesh)
            if geometry is None:
                continue
            T = T @ np.diag([*v.dims, 1.0])
        _set_mesh(vis[path], mg, geometry, v.rgba, path)
        vis[path].set_transform(T)
    for m in markers:
        body = index.get(m.link)
        if body is None:
            continue
        path = f"{body.path}/{m.kind}_{urllib.parse.quote(m.name, safe='')}"
        color = settings.loop_color if m.kind == "loop" else settings.actuated_color
        rgba = ((color >> 16 & 255) / 255, (color >> 8 & 255) / 255, (color & 255) / 255, 1.0)
        size = sizes[(m.kind, m.name)]
        if m.shape == "ring":
            geometry = _TorusGeometry(size, settings.marker_tube * size, _uid(path, "geometry"))
        else:
            geometry = mg.Sphere(size)
        _set_mesh(vis[path], mg, geometry, rgba, path)
        vis[path].set_transform(m.origin)
    for b, body in enumerate(bodies):
        vis[body.path].set_transform(placements[0, b])

    # World helpers: a grid under the swept volume with {1, 2, 5} x 10^k cells,
    # meshcat's 0.5 m axes hidden (they would dwarf a small mechanism).
    cell = _nice_step(radius / GRID_CELLS_PER_RADIUS)
    G = np.diag([cell / MESHCAT_GRID_CELL] * 3 + [1.0])
    G[:3, 3] = [target[0], target[1], float(points[:, 2].min()) - GRID_CLEARANCE * radius]
    vis["/Grid"].set_transform(G)
    if not settings.show_axes:
        vis["/Axes"].set_property("visible", False)
    distance = float(np.linalg.norm(cam_pos - target))
    camera = vis["/Cameras/default/rotated/<object>"]
    camera.set_property("fov", float(settings.camera_fov))
    camera.set_property("near", distance / CLIP_RATIO)
    camera.set_property("far", distance * CLIP_RATIO)
    camera.set_property("position", _three(cam_pos).tolist())

    if len(times) > 1:
        anim = mc.animation.Animation(default_framerate=fps)
        moving = [b for b, body in enumerate(bodies) if body.moving]
        quats = _continuous_quaternions(placements[:, moving, :3, :3])
        for k, frame in enumerate(times * fps):
            key = int(round(frame)) if abs(frame - round(frame)) < FRAME_EPS else float(frame)
            with anim.at_frame(vis, key) as f:
                for j, b in enumerate(moving):
                    node = f[bodies[b].path]
                    node.set_property("position", "vector3", placements[k, b, :3, 3].tolist())
                    node.set_property("quaternion", "quaternion", quats[k, j].tolist())
        vis.set_animation(anim, play=True, repetitions=math.inf)

    logger.info(
        "%s: %d bodies (%d moving), %d visuals, %d markers, %d keyframes at %g fps",
        mech.name,
        len(bodies),
        sum(b.moving for b in bodies),
        len(visuals),
        len(markers),
        len(times),
        fps,
    )
    return MeshcatScene(
        name=mech.name,
        bodies=bodies,
        visuals=visuals,
        markers=markers,
        commands=tuple(recorder.commands),
        times=times,
        placements=placements,
        fps=float(fps),
        center=target,
        radius=radius,
        camera_position=cam_pos,
        camera_target=target,
    )


def _continuous_quaternions(R: np.ndarray) -> np.ndarray:
    """Return (x, y, z, w) quaternions of rotations, signs chosen continuous in time.

    Args:
        R: rotation matrices, shape (K, nb, 3, 3).

    Returns:
        Unit quaternions in three.js order, shape (K, nb, 4); consecutive ones
        in the same hemisphere, so that interpolation takes the short way.
    """
    K, nb = R.shape[:2]
    out = np.empty((K, nb, 4))
    for k in range(K):
        for b in range(nb):
            out[k, b] = pin.Quaternion(R[k, b]).coeffs()
            if k and out[k, b] @ out[k - 1, b] < 0:
                out[k, b] *= -1.0
    return out


def _three(p: np.ndarray) -> np.ndarray:
    """Map a point from meshcat's world frame (z up) to three.js's (y up).

    meshcat's scene root is rotated by -90 deg about x: (x, y, z) -> (x, z, -y).
    The default camera's parent cancels that rotation, so camera positions and
    the orbit target are given in three.js's frame.
    """
    return np.array([p[0], p[2], -p[1]], dtype=float)


# -- the HTML page -------------------------------------------------------------


@functools.lru_cache(maxsize=1)
def _viewer_js() -> str:
    js_path = Path(_meshcat().viewer_assets_path()) / "dist" / "main.min.js"
    text = js_path.read_text(encoding="utf-8")
    if "</script" in text.lower():  # pragma: no cover (not in meshcat 0.3.2)
        raise ClosedChainError(f"{js_path} contains '</script' and cannot be inlined")
    return text


_BOOTSTRAP = """
(function () {
  "use strict";
  var scene = JSON.parse(document.getElementById("closedchain-scene").textContent);
  var viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
  scene.commands.forEach(function (b64) {
    var bin = atob(b64);
    var bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) { bytes[i] = bin.charCodeAt(i); }
    viewer.handle_command_bytearray(bytes);
  });
  var t = scene.meta.camera_target;
  viewer.controls.target.set(t[0], t[1], t[2]);
  viewer.controls.update();
  if (scene.meta.open_controls) {
    viewer.gui.open();
    var folders = viewer.gui.__folders;
    if (folders && folders.Scene) { folders.Scene.close(); }
  }
  viewer.set_dirty();
  var state = { viewer: viewer, meta: scene.meta, ready: false };
  window.closedchain = state;
  requestAnimationFrame(function () {
    requestAnimationFrame(function () {
      state.ready = true;
      document.body.setAttribute("data-ready", "true");
    });
  });
})();
"""

_STYLE = """
body { margin: 0; font-family: sans-serif; }
#meshcat-pane { width: 100vw; height: 100vh; overflow: hidden; }
#closedchain-legend {
  position: absolute; left: 8px; bottom: 8px; padding: 4px 8px; font-size: 12px;
  color: #fff; background: rgba(0, 0, 0, 0.45); border-radius: 4px; pointer-events: none;
}
#closedchain-stop {
  position: absolute; left: 8px; top: 8px; max-width: 60vw; padding: 6px 10px;
  font-size: 13px; color: #fff; background: rgba(180, 20, 20, 0.85); border-radius: 4px;
}
#closedchain-legend .swatch {
  display: inline-block; width: 10px; height: 10px; border-radius: 50%; margin: 0 3px 0 8px;
}
"""


def _json_for_script(obj) -> str:
    """JSON text safe inside a ``<script>`` element (no ``<``, ``>``, ``&``)."""
    text = json.dumps(obj, ensure_ascii=True, separators=(",", ":"), allow_nan=False)
    return text.replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026")


def _csp_hash(script: str) -> str:
    digest = hashlib.sha256(script.encode("utf-8")).digest()
    return "'sha256-" + base64.b64encode(digest).decode("ascii") + "'"


def scene_meta(scene: MeshcatScene, settings: AnimationSettings = DEFAULT_SETTINGS) -> dict:
    """Return the JSON-serialisable description the page exposes as ``window.closedchain.meta``.

    Positions are in meshcat's world frame (z up) except ``camera_target``,
    which is in three.js's frame (y up), as the orbit controls use it.
    """
    return {
        "name": scene.name,
        "bodies": {b.link: b.path for b in scene.bodies},
        "moving": [b.link for b in scene.bodies if b.moving],
        "duration": scene.duration,
        "fps": scene.fps,
        "n_keyframes": int(len(scene.times)),
        "center": scene.center.tolist(),
        "radius": scene.radius,
        "camera_position": scene.camera_position.tolist(),
        "camera_target": _three(scene.camera_target).tolist(),
        "open_controls": bool(settings.open_controls),
        "loop_color": f"#{settings.loop_color:06x}",
        "actuated_color": f"#{settings.actuated_color:06x}",
    }


def scene_html(
    scene: MeshcatScene,
    settings: AnimationSettings = DEFAULT_SETTINGS,
    *,
    stop: str | None = None,
) -> str:
    """Return the self-contained HTML page of a recorded scene.

    ``stop``, when given, is shown (escaped) in a banner at the top of the page
    and in ``meta["stop"]``: the simulation stopped there (e.g. a singularity).

    The page inlines meshcat's ``main.min.js`` and replays the recorded
    commands; nothing is loaded from the network (the Content-Security-Policy
    forbids it, and admits only the page's own two scripts, by hash).
    """
    from . import __version__

    meta = scene_meta(scene, settings)
    meta["stop"] = stop
    data = {
        "meta": meta,
        "commands": [base64.b64encode(c).decode("ascii") for c in scene.commands],
    }
    js = _viewer_js()
    csp = (
        "default-src 'none'; "
        f"script-src {_csp_hash(js)} {_csp_hash(_BOOTSTRAP)}; "
        "style-src 'unsafe-inline'; img-src data: blob:; "
        "base-uri 'none'; form-action 'none'"
    )
    name = html.escape(scene.name)
    banner = (
        ""
        if stop is None
        else f'<div id="closedchain-stop" role="alert">{html.escape(stop)}</div>\n'
    )
    legend = (
        f"<b>{name}</b> &middot; {scene.duration:.3g} s"
        f'<span class="swatch" style="background:{meta["actuated_color"]}"></span>actuated joint'
        f'<span class="swatch" style="background:{meta["loop_color"]}"></span>loop joint'
    )
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f'<meta http-equiv="Content-Security-Policy" content="{csp}">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f'<meta name="generator" content="closedchain {html.escape(__version__)}">\n'
        f"<title>{name} - closedchain</title>\n"
        f"<style>{_STYLE}</style>\n</head>\n<body>\n"
        '<div id="meshcat-pane"></div>\n'
        + banner
        + f'<div id="closedchain-legend">{legend}</div>\n'
        f'<script type="application/json" id="closedchain-scene">{_json_for_script(data)}'
        "</script>\n"
        f"<script>{js}</script>\n"
        f"<script>{_BOOTSTRAP}</script>\n"
        "</body>\n</html>\n"
    )


def write_html(
    mech: Mechanism,
    trajectory: Trajectory,
    path: str | Path,
    *,
    fps: float = DEFAULT_FPS,
    settings: AnimationSettings = DEFAULT_SETTINGS,
    stop: str | None = None,
) -> HTMLAnimation:
    """Write the motion as one self-contained HTML file that plays it in meshcat's viewer.

    The page opens offline (meshcat's JavaScript is inlined; no server, no
    network), frames the mechanism, loops the animation, and has meshcat's
    animation controls (play, pause, reset, time scrubber) in its control
    panel. The same inputs give a byte-identical file.

    Args:
        mech: the mechanism.
        trajectory: its motion: times shape (N,) [s], configurations shape (N, nq).
        path: the HTML file to write.
        fps: display rate [frames/s]; keyframes are resampled to it whatever
            the simulation step.
        settings: scene, camera and marker settings.
        stop: why the motion ends early (e.g. the singularity message of a
            stopped simulation), shown in a red banner; None: no banner.

    Returns:
        What was written: path, size [bytes], duration [s], keyframes, tracks.

    Raises:
        ClosedChainError: the trajectory does not fit the mechanism, its times
            do not increase, or fps is not positive.
    """
    scene = build_scene(mech, trajectory, fps=fps, settings=settings)
    text = scene_html(scene, settings, stop=stop)
    path = Path(path)
    path.write_bytes(text.encode("utf-8"))
    size = path.stat().st_size
    logger.info("wrote %s (%d bytes, %.3g s at %g fps)", path, size, scene.duration, fps)
    return HTMLAnimation(
        path=path,
        size=size,
        duration=scene.duration,
        fps=scene.fps,
        n_keyframes=int(len(scene.times)),
        n_tracks=scene.n_tracks,
        bodies=tuple(b.link for b in scene.bodies),
    )
