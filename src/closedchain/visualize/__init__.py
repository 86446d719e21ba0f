r"""Offline meshcat scenes and animations, written as one self-contained HTML file.

The scene is built with meshcat's own Python commands, recorded by a
window-like object instead of being sent to a meshcat server (no server
process, no network), and replayed in the page by meshcat's JavaScript viewer
(``main.min.js`` from the installed meshcat package, inlined):

- one meshcat node per URDF link that has something to draw, holding the
  link's ``<visual>`` primitives (box, cylinder, sphere) and meshes in their
  URDF colours (meshes embedded within ``AnimationSettings.mesh_budget_bytes``;
  a link over it, or whose mesh cannot be read, drawn as a stick figure), plus
  markers for the loop joints (on the predecessor link, at the cut-joint frame
  c1) and the actuated joints (on the joint's child link);
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

The package is split by concern: :mod:`.settings` (constants, settings and the
records a scene is made of), :mod:`.shapes` (URDF visuals, meshes, joint
markers, the stick figures' segments), :mod:`.framing` (resampling, placements,
swept volume, camera), :mod:`.scene` (recorded meshcat commands and tracks),
:mod:`.page` (the HTML page and :func:`write_html`).
"""

from __future__ import annotations

from .framing import (
    body_placements,
    frame_camera,
)
from .page import (
    scene_html,
    write_html,
)
from .scene import (
    build_scene,
)
from .settings import (
    CHROMIUM_PATH,
    DEFAULT_FPS,
    DEFAULT_SETTINGS,
    HEADLESS_CHROMIUM_ARGS,
    NATIVE_MESH_FORMATS,
    VISUAL_KINDS,
    AnimationSettings,
    Body,
    HTMLAnimation,
    JointMarker,
    MeshcatScene,
    MeshData,
    MeshSummary,
    StickSegment,
    VisualShape,
)
from .shapes import (
    joint_markers,
    posed_sticks,
    read_mesh,
    read_scene_visuals,
    read_visuals,
    stick_segments,
)

__all__ = [
    "AnimationSettings",
    "Body",
    "CHROMIUM_PATH",
    "DEFAULT_FPS",
    "DEFAULT_SETTINGS",
    "HEADLESS_CHROMIUM_ARGS",
    "HTMLAnimation",
    "JointMarker",
    "MeshData",
    "MeshSummary",
    "MeshcatScene",
    "NATIVE_MESH_FORMATS",
    "StickSegment",
    "VISUAL_KINDS",
    "VisualShape",
    "body_placements",
    "build_scene",
    "frame_camera",
    "joint_markers",
    "posed_sticks",
    "read_mesh",
    "read_scene_visuals",
    "read_visuals",
    "scene_html",
    "stick_segments",
    "write_html",
]
