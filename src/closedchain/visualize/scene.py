"""The meshcat scene: recorded commands, geometries, transform tracks."""

from __future__ import annotations

import io
import logging
import math
import urllib.parse
import uuid
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from ..exceptions import ClosedChainError
from ..trajectory import Trajectory

if TYPE_CHECKING:
    from ..mechanism import Mechanism

from .framing import (
    _bounds,
    _nice_step,
    _swept_points,
    body_placements,
    frame_camera,
    resample,
)
from .settings import (
    _Y_TO_Z,
    CLIP_RATIO,
    DEFAULT_FPS,
    DEFAULT_SETTINGS,
    FRAME_EPS,
    GRID_CELLS_PER_RADIUS,
    GRID_CLEARANCE,
    MESHCAT_GRID_CELL,
    TORUS_SEGMENTS,
    UUID_NAMESPACE,
    AnimationSettings,
    MeshcatScene,
    MeshData,
)
from .shapes import (
    _bodies,
    _meshcat,
    joint_markers,
    read_scene_visuals,
)

logger = logging.getLogger(__name__)


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


def _mesh_geometry(mg, mesh: MeshData):
    """Return the meshcat geometry of a mesh checked by ``read_mesh``.

    As meshcat's own readers send them: STL as a typed array (three.js's
    STLLoader parses its buffer), OBJ and DAE as text.
    """
    if mesh.format == "stl":
        return mg.StlMeshGeometry.from_stream(io.BytesIO(mesh.data))
    return mg.MeshGeometry(mesh.data.decode("utf-8"), mesh.format)


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
            do not increase, fps is not positive, or the keyframes would be more
            than ``settings.max_keyframes``.
    """
    mc = _meshcat()
    mg = mc.geometry
    times, qs = resample(mech, trajectory, fps, max_keyframes=settings.max_keyframes)
    visuals, meshes = read_scene_visuals(mech, settings=settings)
    markers = joint_markers(mech, visuals, settings=settings)
    if not visuals and not markers:
        raise ClosedChainError(
            f"{mech.path}: nothing to draw: the model has no drawable <visual>, no actuated "
            "joint (<transmission>) and no loop joint to mark; add a <visual> to a link"
        )
    if not visuals:
        logger.warning(
            "%s: the URDF has no drawable <visual>: only joint markers are drawn", mech.path
        )
    drawn = {v.link for v in visuals} | {m.link for m in markers}
    root = mech.name
    bodies = _bodies(mech, [ln for ln in mech.description.links if ln in drawn], root)
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
            geometry = _mesh_geometry(mg, v.mesh_data)
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

    if meshes.has_meshes:
        logger.info("%s: %s", mech.name, meshes.describe())
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
        meshes=meshes,
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
