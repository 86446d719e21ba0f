"""The HTML page: meshcat's viewer inlined, CSP, legend, :func:`write_html`."""

from __future__ import annotations

import base64
import functools
import hashlib
import html
import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from .._io import atomic_write
from .._locking import exclusive
from ..exceptions import ClosedChainError, check_settings
from ..trajectory import Trajectory

if TYPE_CHECKING:
    from ..mechanism import Mechanism

from .scene import (
    _three,
    build_scene,
)
from .settings import (
    DEFAULT_FPS,
    DEFAULT_SETTINGS,
    AnimationSettings,
    HTMLAnimation,
    MeshcatScene,
)
from .shapes import (
    _meshcat,
)

logger = logging.getLogger(__name__)


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
        "meshes": {
            "embedded": scene.meshes.n_embedded,
            "embedded_bytes": scene.meshes.embedded_bytes,
            "budget_bytes": scene.meshes.budget_bytes,
            "primitive_links": list(scene.meshes.primitive_links),
        },
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
    commands (meshes embedded in them); when the URDF has meshes, its legend
    says what of them is embedded
    (:meth:`~closedchain.visualize.settings.MeshSummary.describe`). Nothing
    is loaded from the network (the Content-Security-Policy
    forbids it, and admits only the page's own two scripts, by hash).
    """
    from .. import __version__

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
    if scene.meshes.has_meshes:
        legend += f"<br>{html.escape(scene.meshes.describe())}"
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


@exclusive
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
    panel. The same inputs give a byte-identical file. Meshes are embedded
    within ``settings.mesh_budget_bytes``, links over it drawn as stick
    figures (:func:`~closedchain.visualize.shapes.read_scene_visuals`); the
    page's legend and the result's ``meshes`` say how many.

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
        What was written: path, size [bytes], duration [s], keyframes, tracks, meshes.

    Raises:
        ClosedChainError: the trajectory does not fit the mechanism (its shape,
            or it was simulated on another:
            :meth:`~closedchain.trajectory.Trajectory.check_mechanism`), its
            times do not increase, or fps is not positive.
    """
    check_settings("settings", settings, AnimationSettings)
    scene = build_scene(mech, trajectory, fps=fps, settings=settings)
    text = scene_html(scene, settings, stop=stop)
    path = Path(path)
    with atomic_write(path) as f:
        f.write(text.encode("utf-8"))
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
        meshes=scene.meshes,
    )
