"""Constants, :class:`AnimationSettings` and the records the scene is made of."""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    pass

logger = logging.getLogger(__name__)

#: Namespace of the deterministic object UUIDs (uuid5 of the object's scene path).
UUID_NAMESPACE = uuid.UUID("6c0b6f1e-3f55-5a43-9a53-636c6f736564")

#: Default display rate of the animation [frames/s].
DEFAULT_FPS = 30.0

#: Shapes of the URDF ``<visual>`` geometries that are drawn.
VISUAL_KINDS = ("box", "cylinder", "sphere", "mesh")

#: Mesh formats meshcat's viewer reads directly (three.js's STLLoader: binary and
#: ASCII STL; OBJLoader2 and ColladaLoader: UTF-8 text); others are converted to
#: binary STL by trimesh.
NATIVE_MESH_FORMATS = ("stl", "obj", "dae")

#: Bytes in the megabyte of the page's messages (SI, as the CLI's page sizes).
MEGABYTE = 1_000_000

#: Radius [m] of the cylinders of the stick figure that stands for a link whose
#: meshes are not drawn (see :func:`closedchain.visualize.shapes.stick_figure`).
STICK_RADIUS = 0.02

#: Radius of the stick figure's ball at the link origin, in stick radii [-].
STICK_BALL_RATIO = 1.5

#: Stick segments shorter than this [m] get no cylinder.
STICK_MIN_LENGTH = 1e-3

#: Length [m] of the stick figure's axis points when the model gives no length to scale
#: them by (see :func:`closedchain.visualize.shapes.stick_segments`).
STICK_AXIS_LENGTH = 0.1

#: Radius of the sticks of a link without any visual (a URDF with inertials only), as a
#: fraction of the model's typical link length (the median length of its sticks) [-]:
#: the figure is sized from the model, a 10 cm linkage as a 2 m robot.
STICK_RADIUS_RATIO = 0.04

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
        max_keyframes: largest number of keyframes (duration x fps + 1) an
            animation may hold, refused before any is computed: each takes
            about 94 bytes per track in the page (4-bar, 3 tracks: 100,000
            keyframes make a 28 MB page, an hour at 30 fps).
        show_axes: keep meshcat's world axes (0.5 m arrows at the origin).
        open_controls: open meshcat's control panel (with the animation
            controls: play, pause, reset, time scrubber) when the page opens.
        mesh_budget_bytes: mesh data the page may embed [bytes] (base64 adds a
            third in the page): in URDF order, the meshes of a link are
            embedded when they fit in what the links before them left; a link
            whose meshes do not fit, or cannot be read, is drawn as a stick
            figure (:func:`~closedchain.visualize.shapes.stick_figure`). The
            default, 20 MB, holds the visual meshes of every robot of
            :data:`closedchain.robots.ERD_MODELS` and keeps a page loadable in
            a browser; 0 draws every mesh link as a stick figure.
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
    max_keyframes: int = 100_000
    show_axes: bool = False
    open_controls: bool = True
    mesh_budget_bytes: int = 20 * MEGABYTE


DEFAULT_SETTINGS = AnimationSettings()


@dataclass(frozen=True)
class MeshData:
    """A mesh read, checked and ready to embed in the page.

    Attributes:
        format: the format meshcat's viewer reads it in: ``"stl"``, ``"obj"`` or ``"dae"``.
        data: the bytes embedded (a converted STL for formats meshcat does not read).
        lower: lower corner of its bounding box in the mesh frame, before scaling, shape (3,).
        upper: upper corner, shape (3,).
    """

    format: str
    data: bytes = field(repr=False)
    lower: np.ndarray
    upper: np.ndarray


@dataclass(frozen=True)
class MeshSummary:
    """What the page embeds of the URDF's meshes.

    Attributes:
        n_embedded: mesh visuals embedded.
        embedded_bytes: their data [bytes].
        budget_bytes: :attr:`AnimationSettings.mesh_budget_bytes` [bytes].
        primitive_links: links with mesh visuals drawn as stick figures instead
            (over the budget, or a mesh that cannot be read), in URDF order.
    """

    n_embedded: int = 0
    embedded_bytes: int = 0
    budget_bytes: int = 0
    primitive_links: tuple[str, ...] = ()

    @property
    def has_meshes(self) -> bool:
        """Whether the URDF has mesh visuals (embedded or not)."""
        return self.n_embedded > 0 or bool(self.primitive_links)

    def describe(self) -> str:
        """Return the page's line, e.g. ``meshes: 7 embedded (6.66 MB of a 20 MB budget), 0
        links drawn as primitives``."""
        m = len(self.primitive_links)
        return (
            f"meshes: {self.n_embedded} embedded ({self.embedded_bytes / MEGABYTE:.3g} MB of a "
            f"{self.budget_bytes / MEGABYTE:.3g} MB budget), {m} link{'' if m == 1 else 's'} "
            "drawn as primitives"
        )


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
        mesh_data: what the page embeds of it (kind ``"mesh"`` only).
    """

    link: str
    kind: str
    dims: tuple[float, ...]
    origin: np.ndarray
    rgba: tuple[float, float, float, float]
    mesh: Path | None = None
    mesh_data: MeshData | None = None


@dataclass(frozen=True)
class StickSegment:
    """One stick of a link's stick figure.

    The sticks of a mechanism are :func:`closedchain.visualize.shapes.stick_segments`.

    Attributes:
        link: name of its link (its BODY frame).
        start: the link's own joint point in the link frame, shape (3,) [m].
        end: the point of the child joint or loop frame in the link frame, shape (3,) [m].
        to: the child joint's name, or the loop's.
        loop: whether ``end`` is a loop frame (a cut joint's side).
    """

    link: str
    start: np.ndarray
    end: np.ndarray
    to: str
    loop: bool = False

    @property
    def length(self) -> float:
        """Return the stick's length [m]."""
        return float(np.linalg.norm(self.end - self.start))


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
        meshes: what the page embeds of the URDF's meshes.
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
    meshes: MeshSummary = field(default_factory=MeshSummary)

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
        meshes: what the page embeds of the URDF's meshes.
    """

    path: Path
    size: int
    duration: float
    fps: float
    n_keyframes: int
    n_tracks: int
    bodies: tuple[str, ...] = field(default_factory=tuple)
    meshes: MeshSummary = field(default_factory=MeshSummary)


# -- reading the URDF ----------------------------------------------------------
