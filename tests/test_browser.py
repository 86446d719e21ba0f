"""The HTML animations in a real browser: Debian's headless Chromium driven by Playwright.

Every network request is routed and aborted unless it is the page's own file.
The test fails (it does not skip) when the browser cannot start: install
Debian's ``chromium`` and the ``playwright`` Python package (never run
``playwright install``: the system Chromium is used).
"""

from __future__ import annotations

import urllib.parse
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin
import pytest
from conftest import MODELS, fourbar_sweep
from lxml import etree

import closedchain as cc
from closedchain.visualize import CHROMIUM_PATH, HEADLESS_CHROMIUM_ARGS

pytestmark = pytest.mark.browser

#: Viewport of the pages [px].
VIEWPORT = {"width": 960, "height": 640}
#: Time for a page to load and render its first frames [ms] (software WebGL).
LOAD_TIMEOUT_MS = 60_000
#: Display rate of the animations [frames/s].
FPS = 30.0
#: The frame the test seeks to: 45 / 30 fps = 1.5 s, sample 150 of the 100 Hz trajectory.
SEEK_FRAME = 45
#: World positions in the page vs Pinocchio forward kinematics [m] (keyframes
#: are single precision in three.js).
POSITION_TOL = 1e-6
#: Orientations in the page vs Pinocchio, Frobenius norm of R_page - R_pin [-].
ROTATION_TOL = 1e-5
#: The mechanism spans at least this fraction of the viewport in x or y on open.
MIN_SCREEN_EXTENT = 0.4

EVIL_LINK = "</script><script>alert(1)</script>"
EVIL_ROBOT = "<img src=x onerror=alert(2)>"


@pytest.fixture(scope="module")
def browser():
    """Debian's Chromium, headless, or why it could not start (the tests then fail)."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as exc:  # pragma: no cover (a missing test dependency)
        yield f"the playwright Python package is needed: {exc}"
        return
    with sync_playwright() as p:
        try:
            b = p.chromium.launch(
                executable_path=CHROMIUM_PATH, args=list(HEADLESS_CHROMIUM_ARGS), headless=True
            )
        except Exception as exc:
            yield f"headless Chromium ({CHROMIUM_PATH}) did not start: {exc}"
            return
        yield b
        b.close()


def running(browser):
    """Return the browser, or fail the test (never skip it) when it did not start."""
    if isinstance(browser, str):
        pytest.fail(f"{browser}\ninstall it with: apt-get install chromium", pytrace=False)
    return browser


class Page:
    """A loaded page and what it tried to do: requests, errors, dialogs."""

    def __init__(self, browser, html: Path) -> None:
        self.url = html.resolve().as_uri()
        self.requests: list[str] = []
        self.errors: list[str] = []
        self.dialogs: list[str] = []
        context = browser.new_context(viewport=VIEWPORT)
        self.page = page = context.new_page()
        page.on("pageerror", lambda exc: self.errors.append(str(exc)))
        page.on(
            "console",
            lambda msg: self.errors.append(msg.text) if msg.type == "error" else None,
        )
        page.on("dialog", self._dialog)
        page.route("**/*", self._route)
        page.goto(self.url)
        # Loaded: meshcat's viewer replayed every command and rendered two frames.
        page.wait_for_function(
            "() => window.closedchain && window.closedchain.ready", timeout=LOAD_TIMEOUT_MS
        )

    def _route(self, route) -> None:
        self.requests.append(route.request.url)
        if route.request.url == self.url:
            route.continue_()
        else:
            route.abort()

    def _dialog(self, dialog) -> None:
        self.dialogs.append(dialog.message)
        dialog.dismiss()

    def evaluate(self, js: str, arg=None):
        return self.page.evaluate(js, arg)

    def close(self) -> None:
        self.page.context.close()


def drawn_links(urdf: Path) -> list[str]:
    """Links with a <visual> in the URDF: the bodies the scene must hold."""
    root = etree.parse(str(urdf)).getroot()
    return [ln.get("name") for ln in root.findall("link") if ln.find("visual") is not None]


#: Body names (scene node names) under the mechanism's node.
JS_BODIES = """(root) => {
  const v = window.closedchain.viewer;
  return Object.keys(v.scene_tree.children.meshcat.children[root].children);
}"""

#: Pause, seek with meshcat's time scrubber, return world placements of the
#: bodies in meshcat's world frame (z up), column-major 4x4.
JS_SEEK = """([t, paths]) => {
  const v = window.closedchain.viewer, THREE = MeshCat.THREE;
  v.animator.pause();
  v.animator.time_scrubber.setValue(t);
  v.scene.updateMatrixWorld(true);
  const worldToScene = new THREE.Matrix4().copy(v.scene.matrixWorld).invert();
  const out = {};
  for (const [link, path] of Object.entries(paths)) {
    let node = v.scene_tree;
    for (const name of path.split("/").filter((s) => s.length)) { node = node.children[name]; }
    const M = new THREE.Matrix4().multiplyMatrices(worldToScene, node.object.matrixWorld);
    out[link] = M.toArray();
  }
  return { placements: out, shown: v.animator.time };
}"""

#: Normalized device coordinates of the corners of the mechanism's bounding box.
JS_SCREEN_BOX = """(root) => {
  const v = window.closedchain.viewer, THREE = MeshCat.THREE;
  v.scene.updateMatrixWorld(true);
  v.camera.updateMatrixWorld(true);
  v.camera.updateProjectionMatrix();
  const box = new THREE.Box3().setFromObject(v.scene_tree.children.meshcat.children[root].object);
  const out = [];
  for (const x of [box.min.x, box.max.x]) for (const y of [box.min.y, box.max.y])
    for (const z of [box.min.z, box.max.z]) {
      const p = new THREE.Vector3(x, y, z).project(v.camera);
      out.push([p.x, p.y, p.z]);
    }
  return out;
}"""


@pytest.fixture(params=["fourbar", "agile_eye"])
def model(request):
    """(name, mechanism, trajectory at 100 Hz over 4 s)."""
    name = request.param
    return (
        name,
        request.getfixturevalue(name),
        request.getfixturevalue(f"{name}_traj"),
    )


def test_animation_in_headless_chromium(browser, model, tmp_path, artifacts_dir):
    name, mech, traj = model
    html = cc.write_html(mech, traj, tmp_path / f"{name}.html", fps=FPS)
    page = Page(running(browser), html.path)
    try:
        # Offline: the page asked for nothing but itself.
        assert page.requests == [page.url]
        assert page.errors == [] and page.dialogs == []

        # The bodies of the URDF, one node each, and nothing else.
        root = urllib.parse.quote(mech.name, safe="")
        expected = [urllib.parse.quote(ln, safe="") for ln in drawn_links(mech.path)]
        assert sorted(page.evaluate(JS_BODIES, root)) == sorted(expected)

        # The animation lasts as long as the trajectory and has one action per moving body.
        duration = traj.t[-1] - traj.t[0]
        anim = page.evaluate(
            "() => { const a = window.closedchain.viewer.animator;"
            " return [a.duration, a.actions.length, a.actions.map((x) => x._clip.duration),"
            " a.playing, a.actions.map((x) => x.repetitions)]; }"
        )
        assert anim[0] == pytest.approx(duration, abs=1e-6)
        assert anim[1] == html.n_tracks
        assert np.linalg.norm(np.array(anim[2]) - duration) <= 1e-5
        assert anim[3] is True  # playing on open
        assert all(r is None or r > 1e300 for r in anim[4])  # loops forever (Infinity)

        # Seek to a fixed frame; compare every moving body with Pinocchio at that sample.
        t_seek = SEEK_FRAME / FPS
        k = int(np.argmin(np.abs(traj.t - traj.t[0] - t_seek)))
        assert abs(traj.t[k] - traj.t[0] - t_seek) <= 1e-12
        meta = page.evaluate("() => window.closedchain.meta")
        moving = {ln: meta["bodies"][ln] for ln in meta["moving"]}
        got = page.evaluate(JS_SEEK, [t_seek, moving])
        assert got["shown"] == pytest.approx(t_seek)  # the scrubber shows the time
        data = mech.model.createData()
        pin.framesForwardKinematics(mech.model, data, traj.q[k])
        for link, flat in got["placements"].items():
            M = np.array(flat).reshape(4, 4).T  # three.js arrays are column-major
            oMf = data.oMf[mech.model.getFrameId(link, pin.FrameType.BODY)]
            assert np.linalg.norm(M[:3, 3] - oMf.translation) <= POSITION_TOL, link
            assert np.linalg.norm(M[:3, :3] - oMf.rotation) <= ROTATION_TOL, link

        # The camera frames the mechanism: all of it in view, and not a speck.
        ndc = np.array(page.evaluate(JS_SCREEN_BOX, root))
        assert np.all(np.abs(ndc[:, :2]) <= 1.0) and np.all(np.abs(ndc[:, 2]) < 1.0)
        extent = ndc[:, :2].max(axis=0) - ndc[:, :2].min(axis=0)
        assert np.max(extent) / 2 >= MIN_SCREEN_EXTENT

        page.page.wait_for_timeout(200)  # let the paused frame render
        page.page.screenshot(path=str(artifacts_dir / f"browser_{name}.png"))
        assert page.errors == [] and page.dialogs == []
    finally:
        page.close()


def test_urdf_names_stay_text_in_the_browser(browser, tmp_path, artifacts_dir):
    """A link named </script><script>alert(1)</script> runs nothing and is a body name."""
    urdf = (MODELS / "fourbar.urdf").read_text()
    urdf = urdf.replace('"rocker"', quoteattr(EVIL_LINK))
    urdf = urdf.replace('<robot name="fourbar">', f"<robot name={quoteattr(EVIL_ROBOT)}>")
    path = tmp_path / "evil.urdf"
    path.write_text(urdf)
    mech = cc.load(path)
    html = cc.write_html(mech, fourbar_sweep(mech, np.linspace(0.0, 1.0, 31)), tmp_path / "e.html")
    page = Page(running(browser), html.path)
    try:
        assert page.dialogs == [] and page.errors == []
        assert page.requests == [page.url]
        assert page.evaluate("() => document.scripts.length") == 3
        assert page.evaluate("() => document.images.length") == 0
        assert page.evaluate("() => document.title") == f"{EVIL_ROBOT} - closedchain"
        root = urllib.parse.quote(EVIL_ROBOT, safe="")
        assert urllib.parse.quote(EVIL_LINK, safe="") in page.evaluate(JS_BODIES, root)
        page.page.screenshot(path=str(artifacts_dir / "browser_escaped_names.png"))
    finally:
        page.close()


#: World-free bounding boxes of each link's visual geometries, by "link/visual_i".
JS_GEOMETRY_BOXES = """(root) => {
  const links = window.closedchain.viewer.scene_tree.children.meshcat.children[root].children;
  const out = {};
  for (const [link, node] of Object.entries(links)) {
    for (const [name, child] of Object.entries(node.children)) {
      const obj = child.children["<object>"] ? child.children["<object>"].object : child.object;
      const g = obj && obj.geometry;
      if (!name.startsWith("visual_") || !g) { continue; }
      g.computeBoundingBox();
      out[link + "/" + name] = [g.boundingBox.min.toArray(), g.boundingBox.max.toArray()];
    }
  }
  return out;
}"""

#: Mesh bounds in the browser vs trimesh's [m] (three.js keeps single precision).
MESH_BOUNDS_TOL = 1e-6


def test_meshes_of_every_format_are_drawn_in_the_browser(browser, tmp_path, artifacts_dir):
    """STL (binary, ASCII), OBJ and DAE meshes load in meshcat's viewer with trimesh's bounds."""
    import trimesh

    from closedchain import visualize as vz

    tetra = trimesh.Trimesh(
        vertices=[[0, 0, 0], [0.2, 0, 0], [0, 0.03, 0], [0, 0, 0.03]],
        faces=[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    )
    formats = {"crank": "stl", "coupler": "obj", "rocker": "dae"}
    for link, fmt in formats.items():
        tetra.apply_scale(1.5)  # a size per link
        (tmp_path / f"{link}.{fmt}").write_bytes(_as_bytes(tetra.export(file_type=fmt)))
    (tmp_path / "ground.stl").write_bytes(_as_bytes(tetra.export(file_type="stl_ascii")))
    urdf = (MODELS / "fourbar.urdf").read_text()
    for box, link in (
        ("0.2 0.012 0.02", "crank"),
        ("0.4 0.012 0.02", "coupler"),
        ("0.3 0.012 0.02", "rocker"),
        ("0.5 0.01 0.012", "ground"),
    ):
        name = f"{link}.{formats.get(link, 'stl')}"
        urdf = urdf.replace(f'<box size="{box}"/>', f'<mesh filename="{name}"/>')
    (tmp_path / "meshes.urdf").write_text(urdf)
    mech = cc.load(tmp_path / "meshes.urdf")
    html = cc.write_html(mech, fourbar_sweep(mech, np.linspace(0.0, 1.0, 31)), tmp_path / "m.html")
    assert html.meshes.n_embedded == 4 and html.meshes.primitive_links == ()
    expected, counters = {}, {}
    for v in vz.read_visuals(mech):
        i = counters[v.link] = counters.get(v.link, -1) + 1
        if v.kind == "mesh":
            expected[f"{v.link}/visual_{i}"] = (v.mesh_data.lower, v.mesh_data.upper)
    page = Page(running(browser), html.path)
    try:
        assert page.errors == [] and page.dialogs == [] and page.requests == [page.url]
        boxes = page.evaluate(JS_GEOMETRY_BOXES, "fourbar")
        assert len(expected) == 4 and set(expected) <= set(boxes)
        for key, (lower, upper) in expected.items():
            got = np.array(boxes[key])
            assert np.linalg.norm(got[0] - lower) <= MESH_BOUNDS_TOL, key
            assert np.linalg.norm(got[1] - upper) <= MESH_BOUNDS_TOL, key
        page.page.screenshot(path=str(artifacts_dir / "browser_meshes.png"))
    finally:
        page.close()


def _as_bytes(data: bytes | str) -> bytes:
    return data.encode() if isinstance(data, str) else data
