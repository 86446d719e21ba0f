"""Tests of closedchain.visualize: scene, keyframes, HTML file (no browser; see test_browser)."""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import json
import logging
import re
import uuid
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin
import pytest
import umsgpack
from conftest import DATA_DIR, MODELS, fourbar_sweep, kinematic_trajectory

import closedchain as cc
from closedchain import visualize as vz
from closedchain.exceptions import ClosedChainError
from closedchain.visualize import framing, shapes

#: Keyframes are stored in single precision (three.js keeps Float32Array):
#: absolute error on positions of ~1 m [m] and on unit quaternions [-].
FLOAT32_TOL = 1e-6
#: Geometry computed in double precision [m].
EXACT_TOL = 1e-12
#: Size budget of a 10 s 4-bar animation at 30 fps [bytes].
SIZE_BUDGET = 2_000_000
#: A link name that tries to close the script element.
EVIL_LINK = "</script><script>alert(1)</script>"
EVIL_ROBOT = "<img src=x onerror=alert(2)>"


def decode(scene: vz.MeshcatScene) -> list[dict]:
    return [umsgpack.unpackb(c) for c in scene.commands]


def animation_of(scene: vz.MeshcatScene) -> list[dict]:
    anims = [c for c in decode(scene) if c["type"] == "set_animation"]
    assert len(anims) == 1
    return anims[0]["animations"]


def track(entry: dict, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(frames, values) of one track of an animation entry."""
    (tr,) = [t for t in entry["clip"]["tracks"] if t["name"] == "." + name]
    frames = np.array([k["time"] for k in tr["keys"]], dtype=float)
    values = np.array([k["value"] for k in tr["keys"]], dtype=float)
    return frames, values


def fk(mech: cc.Mechanism, q: np.ndarray, link: str) -> pin.SE3:
    data = mech.model.createData()
    pin.framesForwardKinematics(mech.model, data, q)
    return data.oMf[mech.model.getFrameId(link, pin.FrameType.BODY)]


@pytest.fixture(scope="module")
def fourbar_scene(fourbar, fourbar_traj) -> vz.MeshcatScene:
    return vz.build_scene(fourbar, fourbar_traj, fps=30.0)


@pytest.fixture(scope="module")
def agile_eye_scene(agile_eye, agile_eye_traj) -> vz.MeshcatScene:
    return vz.build_scene(agile_eye, agile_eye_traj, fps=30.0)


@pytest.fixture(params=["fourbar", "agile_eye"])
def case(request):
    """(mechanism, trajectory, scene) for each model."""
    name = request.param
    return (
        request.getfixturevalue(name),
        request.getfixturevalue(f"{name}_traj"),
        request.getfixturevalue(f"{name}_scene"),
    )


# -- URDF visuals and joint markers ----------------------------------------------


def test_read_visuals_fourbar(fourbar):
    visuals = vz.read_visuals(fourbar)
    assert [v.link for v in visuals] == ["ground"] * 3 + ["crank", "coupler", "coupler"] + [
        "rocker"
    ] * 2
    assert [v.kind for v in visuals] == ["box", "cylinder", "cylinder", "box"] + [
        "box",
        "cylinder",
        "box",
        "cylinder",
    ]
    crank = visuals[3]
    assert crank.dims == pytest.approx((0.2, 0.012, 0.02))
    assert crank.rgba == pytest.approx((0.85, 0.33, 0.10, 1.0))  # material named, defined on top
    assert np.linalg.norm(crank.origin[:3, 3] - [0.1, 0.0, 0.0]) <= EXACT_TOL


def test_read_visuals_agile_eye(agile_eye):
    visuals = vz.read_visuals(agile_eye)
    links = {v.link for v in visuals}
    assert links == {"base", "platform"} | {
        f"{p}_{i}" for p in ("proximal", "distal") for i in (1, 2, 3)
    }
    assert {v.kind for v in visuals} == {"box", "cylinder", "sphere"}


@pytest.mark.parametrize("name", ["fourbar", "agile_eye"])
def test_markers_sit_on_the_joint_axes(request, name):
    """Every marker's z axis is its joint's axis, and its origin lies on the axis line."""
    mech = request.getfixturevalue(name)
    markers = vz.joint_markers(mech, vz.read_visuals(mech))
    assert {m.name for m in markers if m.kind == "actuated"} == set(mech.actuated_joints)
    assert {m.name for m in markers if m.kind == "loop"} == {
        lp.name for lp in mech.description.loops
    }
    model, data = mech.model, mech.model.createData()
    q = mech.q_ref
    pin.framesForwardKinematics(model, data, q)
    for m in markers:
        oMm = fk(mech, q, m.link).homogeneous @ m.origin
        if m.kind == "loop":
            oMc = data.oMf[model.getFrameId(f"{m.name}::predecessor")]
            spec = next(lp for lp in mech.description.loops if lp.name == m.name)
            axis, point = oMc.rotation @ spec.axis, oMc.translation
        else:
            jid = model.getJointId(m.name)
            axis_j, _ = shapes._joint_axis(model.joints[jid], pin.neutral(model))
            axis, point = data.oMi[jid].rotation @ axis_j, data.oMi[jid].translation
        assert np.linalg.norm(np.cross(oMm[:3, 2], axis)) <= EXACT_TOL
        d = oMm[:3, 3] - point
        assert np.linalg.norm(d - (d @ axis) * axis) <= EXACT_TOL
        assert m.pin_radius > 0.0  # both models draw a pin at every marked joint


def test_fourbar_markers_ring_the_pins(fourbar):
    markers = {m.kind: m for m in vz.joint_markers(fourbar, vz.read_visuals(fourbar))}
    assert markers["actuated"].pin_radius == pytest.approx(0.014)  # ground pin at A
    assert markers["loop"].pin_radius == pytest.approx(0.016)  # loop pin at C, on the rocker
    assert markers["loop"].link == "coupler"  # carried by the predecessor


# -- scene structure ---------------------------------------------------------------


def test_one_node_and_one_track_per_body(case):
    mech, _, scene = case
    moving = [b for b in scene.bodies if b.moving]
    root = mech.model.frames[1].name  # the URDF root link, fixed to the world
    assert {b.link for b in moving} == {b.link for b in scene.bodies} - {root}
    entries = animation_of(scene)
    assert sorted(e["path"] for e in entries) == sorted(b.path for b in moving)
    for e in entries:
        assert sorted(t["name"] for t in e["clip"]["tracks"]) == [".position", ".quaternion"]
    # Visuals and markers hang under their link's node and are never animated.
    objects = [c["path"] for c in decode(scene) if c["type"] == "set_object"]
    for path in objects:
        assert any(path.startswith(b.path + "/") for b in scene.bodies), path
    assert scene.n_tracks == len(moving)


def test_links_without_visuals_get_no_node(agile_eye, agile_eye_scene):
    drawn = {b.link for b in agile_eye_scene.bodies}
    assert "euler_link_z" not in drawn and "euler_link_y" not in drawn
    assert {"base", "platform"} <= drawn


def test_keyframes_at_display_rate_match_forward_kinematics(case):
    """Trajectory at 100 Hz, display at 30 fps: keys at k/30 s; on samples, equal to FK."""
    mech, traj, scene = case
    fps = scene.fps
    n_keys = int(round(traj.t[-1] * fps)) + 1
    assert len(scene.times) == n_keys
    assert np.linalg.norm(scene.times - np.arange(n_keys) / fps) <= EXACT_TOL
    index = {b.path: b for b in scene.bodies}
    for entry in animation_of(scene):
        body = index[entry["path"]]
        frames, pos = track(entry, "position")
        _, quat = track(entry, "quaternion")
        assert entry["clip"]["fps"] == pytest.approx(fps)
        assert np.array_equal(frames, np.arange(n_keys))
        for k in range(0, n_keys, 3):  # k / 30 s = sample 10 k / 3 of the 100 Hz trajectory
            oMf = fk(mech, traj.q[10 * k // 3], body.link)
            assert np.linalg.norm(pos[k] - oMf.translation) <= FLOAT32_TOL
            q_ref = pin.Quaternion(oMf.rotation).coeffs()
            assert min(np.linalg.norm(quat[k] - q_ref), np.linalg.norm(quat[k] + q_ref)) <= (
                FLOAT32_TOL
            )
        # Consecutive quaternions in one hemisphere: interpolation takes the short way.
        assert np.all(np.sum(quat[1:] * quat[:-1], axis=1) > 0)


def test_keyframes_do_not_depend_on_the_simulation_step(fourbar):
    """The same motion sampled at 100 Hz, 250 Hz and on an uneven grid gives the same keys.

    Keys fall at k / fps whatever the samples, and match the motion evaluated
    exactly at those times up to the interpolation error between samples.
    """
    fps = 24.0
    rng = np.random.default_rng(0)
    uneven = np.linspace(0.0, 2.0, 201)
    uneven[1:-1] += rng.uniform(-3e-3, 3e-3, 199)  # steps of 4 to 16 ms
    grids = [np.linspace(0.0, 2.0, 201), np.linspace(0.0, 2.0, 501), uneven]
    exact = vz.build_scene(fourbar, fourbar_sweep(fourbar, np.arange(49) / fps), fps=fps)
    #: Interpolation error between samples at most 16 ms apart (crank swing
    #: 0.8 rad at 0.5 Hz: |q''| h^2 / 8 < 3e-4 rad, times a lever < 1 m) [m].
    interp_tol = 3e-4
    for t in grids:
        scene = vz.build_scene(fourbar, fourbar_sweep(fourbar, t), fps=fps)
        assert len(scene.times) == 49 and scene.duration == pytest.approx(2.0)
        assert np.linalg.norm(scene.times - exact.times) <= EXACT_TOL
        err = np.linalg.norm(scene.placements - exact.placements, axis=(2, 3))  # (K, nb)
        assert np.max(err) <= interp_tol


def test_duration_is_the_trajectory_duration(fourbar):
    """A trajectory whose length is not a whole number of frames ends on an extra key."""
    traj = fourbar_sweep(fourbar, np.linspace(0.5, 1.51, 102))  # starts at 0.5 s, lasts 1.01 s
    scene = vz.build_scene(fourbar, traj, fps=30.0)
    assert scene.duration == pytest.approx(1.01)
    assert len(scene.times) == 32  # 0 .. 30/30 s, then 1.01 s
    frames, pos = track(animation_of(scene)[0], "position")
    assert frames[-1] == pytest.approx(1.01 * 30.0)
    body = next(b for b in scene.bodies if b.path == animation_of(scene)[0]["path"])
    assert np.linalg.norm(pos[-1] - fk(fourbar, traj.q[-1], body.link).translation) <= (FLOAT32_TOL)


def test_single_configuration_is_a_still_scene(fourbar, fourbar_traj):
    arrays = {
        f.name: getattr(fourbar_traj, f.name)[:1]
        for f in dataclasses.fields(cc.Trajectory)
        if f.name != "info" and getattr(fourbar_traj, f.name) is not None
    }
    traj = cc.Trajectory(**{**arrays, "info": {}})
    scene = vz.build_scene(fourbar, traj)
    assert scene.duration == 0.0
    assert scene.n_tracks == 0
    assert not [c for c in decode(scene) if c["type"] == "set_animation"]


def test_animation_loops_and_plays(fourbar_scene):
    (anim,) = [c for c in decode(fourbar_scene) if c["type"] == "set_animation"]
    assert anim["options"]["play"] is True
    assert anim["options"]["repetitions"] == float("inf")


def test_uuids_are_deterministic(fourbar_scene):
    """No time-based (version 1) UUID: every object UUID is a uuid5 of its scene path."""
    found = []
    for c in decode(fourbar_scene):
        if c["type"] == "set_object":
            obj = c["object"]
            found += [obj["object"]["uuid"]] + [g["uuid"] for g in obj["geometries"]]
            found += [m["uuid"] for m in obj["materials"]]
    assert found and all(uuid.UUID(u).version == 5 for u in found)
    assert len(set(found)) == len(found)


@pytest.mark.parametrize(
    "name",
    [
        "fourbar",
        "agile_eye",
        "spherical_chain",
        "slider_crank",
        "slider_crank_planar",
        "fixed_branches",
    ],
)
def test_every_test_mechanism_animates(load_mechanism, name, tmp_path):
    """Every loop type (revolute, prismatic, spherical, fixed) gets its markers and tracks."""
    mech = load_mechanism(name)
    rng = np.random.default_rng(0)
    qs = np.array([cc.random_consistent_state(mech, rng)[0] for _ in range(3)])
    traj = kinematic_trajectory(mech, np.array([0.0, 0.5, 1.0]), qs)
    out = cc.write_html(mech, traj, tmp_path / f"{name}.html", fps=10.0)
    scene = vz.build_scene(mech, traj, fps=10.0)
    kinds = sorted(m.kind for m in scene.markers)
    assert kinds == sorted(
        ["actuated"] * len(mech.actuated_joints) + ["loop"] * len(mech.description.loops)
    )
    assert out.n_tracks == sum(b.moving for b in scene.bodies) > 0
    assert out.n_keyframes == 11 and out.size < SIZE_BUDGET


# -- camera ------------------------------------------------------------------------


def test_camera_frames_the_swept_volume(case):
    mech, _, scene = case
    settings = vz.DEFAULT_SETTINGS
    points = framing._swept_points(
        scene.bodies,
        scene.visuals,
        (),
        scene.placements,
        {},
        settings,
    )
    view = scene.camera_target - scene.camera_position
    distance = np.linalg.norm(view)
    rel = points - scene.camera_position
    cos = rel @ view / (np.linalg.norm(rel, axis=1) * distance)
    half_fov = np.radians(settings.camera_fov) / 2
    assert np.all(cos >= np.cos(half_fov))  # every visual corner inside the view cone
    assert np.linalg.norm(scene.center - scene.camera_target) <= EXACT_TOL
    assert scene.radius < distance < 10 * scene.radius  # close enough to fill the view


def test_planar_linkage_is_seen_face_on(fourbar_scene):
    view = fourbar_scene.camera_target - fourbar_scene.camera_position
    view /= np.linalg.norm(view)
    assert abs(view[1]) > 0.95  # the 4-bar moves in the world x-z plane


def test_camera_and_grid_commands(fourbar_scene):
    cmds = decode(fourbar_scene)
    cam = {
        c["property"]: c["value"]
        for c in cmds
        if c["type"] == "set_property" and c["path"] == "/Cameras/default/rotated/<object>"
    }
    # meshcat's scene is z-up, three.js's camera frame y-up: (x, y, z) -> (x, z, -y).
    x, y, z = fourbar_scene.camera_position
    assert np.linalg.norm(np.array(cam["position"]) - [x, z, -y]) <= EXACT_TOL
    assert cam["fov"] == vz.DEFAULT_SETTINGS.camera_fov
    axes = [c for c in cmds if c["type"] == "set_property" and c["path"] == "/Axes"]
    assert axes and axes[0]["value"] is False


# -- the HTML file -------------------------------------------------------------------


def test_fourbar_10s_at_30fps_stays_under_2MB(fourbar, tmp_path):
    traj = fourbar_sweep(fourbar, np.linspace(0.0, 10.0, 1001))
    out = cc.write_html(fourbar, traj, tmp_path / "fourbar.html", fps=30.0)
    assert out.size == (tmp_path / "fourbar.html").stat().st_size
    assert out.size < SIZE_BUDGET
    assert out.n_keyframes == 301 and out.n_tracks == 3 and out.duration == pytest.approx(10.0)
    logging.getLogger(__name__).info("10 s 4-bar at 30 fps: %d bytes", out.size)


def test_same_trajectory_gives_identical_bytes(agile_eye, agile_eye_traj, tmp_path):
    a = cc.write_html(agile_eye, agile_eye_traj, tmp_path / "a.html")
    b = cc.write_html(agile_eye, agile_eye_traj, tmp_path / "b.html")
    assert a.path.read_bytes() == b.path.read_bytes()


def scripts_of(text: str) -> list[tuple[str, str]]:
    """(attributes, body) of every <script> element."""
    return re.findall(r"<script([^>]*)>(.*?)</script>", text, flags=re.DOTALL)


def test_page_is_self_contained_and_offline(fourbar, fourbar_traj, tmp_path):
    text = cc.write_html(fourbar, fourbar_traj, tmp_path / "f.html").path.read_text()
    meshcat_js = (Path(shapes._meshcat().viewer_assets_path()) / "dist" / "main.min.js").read_text()
    scripts = scripts_of(text)
    assert [attrs for attrs, _ in scripts] == [
        ' type="application/json" id="closedchain-scene"',
        "",
        "",
    ]
    assert scripts[1][1] == meshcat_js  # meshcat's viewer, inlined verbatim
    # No external resource: no src/href attributes, no stylesheet links.
    outside_js = text.replace(meshcat_js, "")
    assert not re.search(r"\b(src|href)\s*=", outside_js)
    assert not re.search(r"<link\b|https?://|\bimport\(|\bfetch\(", outside_js)
    # The Content-Security-Policy forbids the network and admits exactly these two scripts.
    csp = re.search(r'http-equiv="Content-Security-Policy" content="([^"]*)"', text).group(1)
    assert "default-src 'none'" in csp
    for _, body in scripts[1:]:
        digest = base64.b64encode(hashlib.sha256(body.encode()).digest()).decode()
        assert f"'sha256-{digest}'" in csp
    assert (
        csp.count("'sha256-") == 2
        and "unsafe-inline" not in csp.split("script-src")[1].split(";")[0]
    )


def test_urdf_names_cannot_inject_markup(fourbar, tmp_path):
    """A link named </script><script>... and a robot named <img ...> stay inert text."""
    urdf = (MODELS / "fourbar.urdf").read_text()
    urdf = urdf.replace('"rocker"', quoteattr(EVIL_LINK))
    urdf = urdf.replace('<robot name="fourbar">', f"<robot name={quoteattr(EVIL_ROBOT)}>")
    path = tmp_path / "evil.urdf"
    path.write_text(urdf)
    mech = cc.load(path)
    assert EVIL_LINK in mech.description.links
    traj = fourbar_sweep(mech, np.linspace(0.0, 1.0, 31))
    text = cc.write_html(mech, traj, tmp_path / "evil.html").path.read_text()
    assert EVIL_LINK not in text and EVIL_ROBOT not in text
    assert "<script>alert" not in text and "<img" not in text
    assert len(scripts_of(text)) == 3 and text.count("<script") == 3
    data = json.loads(scripts_of(text)[0][1])
    assert data["meta"]["name"] == EVIL_ROBOT
    path = data["meta"]["bodies"][EVIL_LINK]
    assert path == shapes.scene_path(EVIL_ROBOT, EVIL_LINK)
    assert len(path.split("/")) == 4  # "", meshcat, robot, link: the "/" in names is encoded


def test_scene_path_escapes_names():
    assert shapes.scene_path("fourbar", "crank") == "/meshcat/fourbar/crank"
    assert shapes.scene_path("a/b", "<c>") == "/meshcat/a%2Fb/%3Cc%3E"


# -- meshes --------------------------------------------------------------------------


#: Binary STL: an 80-byte header, a uint32 triangle count, then 50 bytes per triangle.
STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
#: A tetrahedron [m] and its four triangles.
TETRA = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], dtype=float)
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
#: What the page carries besides a mesh's base64 when the mesh replaces its link's
#: stick figure (the mesh's object and material, the legend's digits) [bytes].
MESH_PAGE_SLACK = 2_000


def write_binary_stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> int:
    """Write a binary STL (normals zero); return its size [bytes]."""
    triangles = np.zeros(len(faces), dtype=STL_TRIANGLE)
    triangles["vertices"] = vertices[faces]
    data = b"\0" * 80 + np.uint32(len(faces)).tobytes() + triangles.tobytes()
    path.write_bytes(data)
    return len(data)


def tetrahedra(n: int, length: float) -> tuple[np.ndarray, np.ndarray]:
    """n tetrahedra side by side along x over ``length`` [m]: (vertices, faces)."""
    offsets = np.linspace(0.0, length, n)[:, None, None] * np.array([1.0, 0.0, 0.0])
    vertices = (TETRA[None] * (length / n) + offsets).reshape(-1, 3)
    faces = (TETRA_FACES[None] + 4 * np.arange(n)[:, None, None]).reshape(-1, 3)
    return vertices, faces


def mesh_fourbar(directory: Path, crank: str, coupler: str) -> cc.Mechanism:
    """The 4-bar with its crank's and its coupler's box visuals replaced by meshes."""
    urdf = (MODELS / "fourbar.urdf").read_text()
    urdf = urdf.replace(
        '<geometry><box size="0.2 0.012 0.02"/></geometry>',
        f'<geometry><mesh filename="{crank}"/></geometry>',
    ).replace(
        '<geometry><box size="0.4 0.012 0.02"/></geometry>',
        f'<geometry><mesh filename="{coupler}"/></geometry>',
    )
    (directory / "mesh.urdf").write_text(urdf)
    return cc.load(directory / "mesh.urdf")


def mesh_objects(scene: vz.MeshcatScene) -> dict[str, dict]:
    """Scene path -> geometry of the meshes the scene embeds."""
    return {
        c["path"]: c["object"]["geometries"][0]
        for c in decode(scene)
        if c["type"] == "set_object" and c["object"]["geometries"][0]["type"] == "_meshfile"
    }


def test_mesh_visuals_are_embedded_or_skipped(tmp_path, caplog):
    mesh_dir = tmp_path / "meshes"
    mesh_dir.mkdir()
    write_binary_stl(mesh_dir / "tetra.stl", TETRA, TETRA_FACES)
    urdf = (MODELS / "fourbar.urdf").read_text()
    urdf = urdf.replace(
        '<geometry><box size="0.4 0.012 0.02"/></geometry>',
        '<geometry><mesh filename="meshes/tetra.stl" scale="2 1 1"/></geometry>',
    ).replace(
        '<geometry><box size="0.3 0.012 0.02"/></geometry>',
        '<geometry><mesh filename="package://missing/rocker.stl"/></geometry>',
    )
    (tmp_path / "mesh.urdf").write_text(urdf)
    mech = cc.load(tmp_path / "mesh.urdf")
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        visuals = vz.read_visuals(mech)
    assert "package://missing/rocker.stl" in caplog.text and "not found" in caplog.text
    (mesh,) = [v for v in visuals if v.kind == "mesh"]
    assert mesh.link == "coupler" and mesh.dims == (2.0, 1.0, 1.0)
    assert mesh.mesh == (mesh_dir / "tetra.stl").resolve()
    scene = vz.build_scene(mech, fourbar_sweep(mech, np.linspace(0.0, 1.0, 11)))
    meshes = [
        (c["path"], c["object"]["geometries"][0])
        for c in decode(scene)
        if c["type"] == "set_object" and c["object"]["geometries"][0]["type"] == "_meshfile"
    ]
    assert len(meshes) == 1 and meshes[0][1]["format"] == "stl"
    assert meshes[0][0].startswith(shapes.scene_path("fourbar", "coupler") + "/")
    assert bytes(meshes[0][1]["data"].data) == (mesh_dir / "tetra.stl").read_bytes()
    # The scale is in the visual's node transform.
    transforms = {c["path"]: c["matrix"] for c in decode(scene) if c["type"] == "set_transform"}
    M = np.array(transforms[meshes[0][0]]).reshape(4, 4).T
    assert np.linalg.norm(np.linalg.norm(M[:3, :3], axis=0) - [2.0, 1.0, 1.0]) <= EXACT_TOL


@pytest.mark.parametrize(
    "filename",
    [
        "{outside}",
        "file://{outside}",
        "../outside/secret.stl",
        "meshes/../../outside/secret.stl",
        "package://robot/../outside/secret.stl",
        "package://robot/outside/secret.stl",  # found in a parent directory
        "meshes/link.stl",  # a symbolic link inside pointing outside
    ],
)
def test_mesh_files_outside_the_urdf_directory_are_refused(tmp_path, caplog, filename):
    """A URDF cannot embed local files from outside its own directory in the page."""
    (tmp_path / "outside").mkdir()
    secret = tmp_path / "outside" / "secret.stl"
    write_binary_stl(secret, TETRA, TETRA_FACES)
    robot = tmp_path / "robot"
    (robot / "meshes").mkdir(parents=True)
    (robot / "meshes" / "link.stl").symlink_to(secret)
    filename = filename.format(outside=secret)
    urdf = (
        (MODELS / "fourbar.urdf")
        .read_text()
        .replace(
            '<geometry><box size="0.4 0.012 0.02"/></geometry>',
            f'<geometry><mesh filename="{filename}"/></geometry>',
        )
    )
    (robot / "mesh.urdf").write_text(urdf)
    mech = cc.load(robot / "mesh.urdf")
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        visuals = vz.read_visuals(mech)
        scene = vz.build_scene(mech, fourbar_sweep(mech, np.linspace(0.0, 1.0, 3)))
    assert [v for v in visuals if v.kind == "mesh"] == []
    assert f"link 'coupler' visual 0: mesh file {filename!r} ({secret}) is outside" in caplog.text
    geometries = [
        c["object"]["geometries"][0]["type"] for c in decode(scene) if c["type"] == "set_object"
    ]
    assert "_meshfile" not in geometries


# -- errors --------------------------------------------------------------------------


def test_trajectory_of_another_mechanism_is_refused(fourbar, agile_eye_traj):
    with pytest.raises(ClosedChainError, match=r"trajectory.q has shape \(401, 9\), expected"):
        vz.build_scene(fourbar, agile_eye_traj)


@pytest.mark.parametrize(
    ("lookalike", "message"),
    [
        ("renamed", r"its joint 2 is 'rocker_joint', the mechanism's is 'rocker_pivot'"),
        ("longer_rocker", r"same joints, model digest [0-9a-f]{12} != [0-9a-f]{12}"),
    ],
)
def test_trajectory_of_a_mechanism_of_the_same_nq_is_refused(
    short_traj, fourbar_lookalikes, tmp_path, lookalike, message
):
    path = tmp_path / "x.html"
    with pytest.raises(ClosedChainError, match=message):
        vz.write_html(fourbar_lookalikes[lookalike], short_traj, path)
    assert not path.exists()


def test_trajectory_of_its_own_mechanism_is_drawn(fourbar, short_traj, tmp_path):
    assert vz.write_html(fourbar, short_traj, tmp_path / "x.html").n_keyframes >= 2


def test_times_must_increase(fourbar, fourbar_traj):
    t = fourbar_traj.t.copy()
    t[5] = t[4]
    bad = dataclasses.replace(fourbar_traj, t=t)
    with pytest.raises(ClosedChainError, match=r"times must increase: t\[4\]"):
        vz.build_scene(fourbar, bad)


@pytest.mark.parametrize("fps", [0.0, -30.0, float("nan")])
def test_fps_must_be_positive(fourbar, fourbar_traj, fps):
    with pytest.raises(ClosedChainError, match="fps must be a positive number"):
        vz.build_scene(fourbar, fourbar_traj, fps=fps)


# -- command line ----------------------------------------------------------------------


def test_cli_animate_writes_html_and_reports_size(tmp_path, capsys):
    from closedchain.cli import main

    out = tmp_path / "fourbar.html"
    rc = main(
        ["animate", str(MODELS / "fourbar.urdf"), "--t-final", "1", "--fps", "20", "-o", str(out)]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert str(out) in text and "MB" in text
    assert out.stat().st_size < SIZE_BUDGET
    data = json.loads(scripts_of(out.read_text())[0][1])
    assert data["meta"]["duration"] == pytest.approx(1.0) and data["meta"]["fps"] == 20.0


def test_cli_needs_an_output(capsys):
    from closedchain.cli import main

    with pytest.raises(SystemExit):
        main(["animate", str(MODELS / "fourbar.urdf")])
    assert "-o/--output" in capsys.readouterr().err


def test_mesh_files_over_the_size_limit_are_skipped(tmp_path, caplog, monkeypatch):
    """The page embeds each mesh: one over MAX_MESH_BYTES is left out, unread, with a warning."""
    from closedchain.visualize import shapes

    write_binary_stl(tmp_path / "tetra.stl", TETRA, TETRA_FACES)
    size = (tmp_path / "tetra.stl").stat().st_size  # 84 + 4 x 50 bytes
    urdf = (MODELS / "fourbar.urdf").read_text()
    urdf = urdf.replace(
        '<geometry><box size="0.4 0.012 0.02"/></geometry>',
        '<geometry><mesh filename="tetra.stl"/></geometry>',
    )
    (tmp_path / "mesh.urdf").write_text(urdf)
    mech = cc.load(tmp_path / "mesh.urdf")
    monkeypatch.setattr(shapes, "MAX_MESH_BYTES", size - 1)
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        visuals = vz.read_visuals(mech)
    assert [v for v in visuals if v.kind == "mesh"] == []
    assert (
        f"link 'coupler' visual 0: {(tmp_path / 'tetra.stl').resolve()}: mesh file of {size} "
        f"bytes is larger than the limit of {size - 1} bytes; not drawn" in caplog.text
    )
    monkeypatch.setattr(shapes, "MAX_MESH_BYTES", size)
    assert [v.link for v in vz.read_visuals(mech) if v.kind == "mesh"] == ["coupler"]


# -- mesh budget -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def two_meshes(tmp_path_factory):
    """(4-bar whose crank is a 100 kB STL and coupler a 284-byte one, their sizes [bytes])."""
    directory = tmp_path_factory.mktemp("two_meshes")
    (directory / "meshes").mkdir()
    big = write_binary_stl(directory / "meshes" / "crank.stl", *tetrahedra(500, 0.2))
    small = write_binary_stl(directory / "meshes" / "coupler.stl", TETRA, TETRA_FACES)
    return mesh_fourbar(directory, "meshes/crank.stl", "meshes/coupler.stl"), big, small


def test_meshes_within_the_budget_are_embedded_the_others_drawn_as_sticks(two_meshes, caplog):
    mech, big, small = two_meshes
    settings = vz.AnimationSettings(mesh_budget_bytes=big)  # the crank's mesh fits exactly
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        visuals, meshes = vz.read_scene_visuals(mech, settings=settings)
    assert meshes == vz.MeshSummary(1, big, big, ("coupler",))
    assert (
        "meshes over what is left of the budget of 0.1 MB (AnimationSettings.mesh_budget_bytes), "
        "drawn as primitives: coupler (0.000284 MB)" in caplog.text
    )
    assert [v.link for v in visuals if v.kind == "mesh"] == ["crank"]
    # The coupler's stick figure: a ball at its origin and a stick to its loop frame (it
    # has no child joint in the tree); its pin cylinder stays.
    (loop,) = [lp for lp in mech.description.loops if "coupler" in (lp.predecessor, lp.successor)]
    side = loop.predecessor_origin if loop.predecessor == "coupler" else loop.successor_origin
    coupler = [(v.kind, v.dims) for v in visuals if v.link == "coupler"]
    assert coupler == [
        ("sphere", (0.03,)),
        ("cylinder", (0.02, pytest.approx(np.linalg.norm(side.translation), abs=EXACT_TOL))),
        ("cylinder", (0.012, 0.05)),
    ]

    # A budget of 0: the crank is a stick from its origin to the coupler joint.
    visuals, meshes = vz.read_scene_visuals(
        mech, settings=vz.AnimationSettings(mesh_budget_bytes=0)
    )
    assert meshes == vz.MeshSummary(0, 0, 0, ("crank", "coupler"))
    ball, stick = [v for v in visuals if v.link == "crank"]
    joint = mech.model.jointPlacements[mech.model.getJointId("coupler_joint")].translation
    assert ball.kind == "sphere" and np.linalg.norm(ball.origin[:3, 3]) <= EXACT_TOL
    assert stick.kind == "cylinder" and stick.dims[1] == pytest.approx(np.linalg.norm(joint))
    assert np.linalg.norm(stick.origin[:3, 3] - joint / 2) <= EXACT_TOL
    assert np.linalg.norm(stick.origin[:3, 2] - joint / np.linalg.norm(joint)) <= EXACT_TOL


def test_page_states_its_meshes_and_grows_by_the_embedded_mesh_only(two_meshes, tmp_path):
    mech, big, small = two_meshes
    traj = fourbar_sweep(mech, np.linspace(0.0, 1.0, 11))
    sizes, legends = {}, {}
    for budget in (0, big, big + small):
        out = vz.write_html(
            mech,
            traj,
            tmp_path / f"{budget}.html",
            settings=vz.AnimationSettings(mesh_budget_bytes=budget),
        )
        text = out.path.read_text()
        sizes[budget] = out.size
        legends[budget] = re.search(r'<div id="closedchain-legend">(.*?)</div>', text).group(1)
        meta = json.loads(scripts_of(text)[0][1])["meta"]["meshes"]
        assert meta["embedded_bytes"] == out.meshes.embedded_bytes
        assert meta["primitive_links"] == list(out.meshes.primitive_links)
    assert legends[0].endswith(
        "<br>meshes: 0 embedded (0 MB of a 0 MB budget), 2 links drawn as primitives"
    )
    assert legends[big].endswith(
        f"<br>meshes: 1 embedded ({big / 1e6:.3g} MB of a {big / 1e6:.3g} MB budget), "
        "1 link drawn as primitives"
    )
    assert "2 embedded" in legends[big + small] and "0 links drawn" in legends[big + small]
    # base64 carries 4 bytes per 3 of the mesh.
    assert abs(sizes[big] - sizes[0] - 4 * big / 3) <= MESH_PAGE_SLACK
    assert abs(sizes[big + small] - sizes[big] - 4 * small / 3) <= MESH_PAGE_SLACK


def test_pages_without_meshes_say_nothing_of_them(fourbar_scene):
    assert fourbar_scene.meshes == vz.MeshSummary(0, 0, vz.DEFAULT_SETTINGS.mesh_budget_bytes)
    assert "meshes:" not in vz.scene_html(fourbar_scene)


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (lambda: b"not a mesh\n" * 20, "STL mesh has no triangles"),
        (lambda: tetra_stl()[:-60], "STL mesh has no triangles"),  # truncated
        (lambda: tetra_stl() + b"\0\0", "STL mesh has no triangles"),  # a count that lies
    ],
    ids=["text", "truncated", "trailing"],
)
def test_a_corrupt_stl_is_drawn_as_a_stick_with_a_warning(tmp_path, caplog, content, reason):
    (tmp_path / "bad.stl").write_bytes(content())
    write_binary_stl(tmp_path / "good.stl", TETRA, TETRA_FACES)
    mech = mesh_fourbar(tmp_path, "bad.stl", "good.stl")
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        scene = vz.build_scene(mech, fourbar_sweep(mech, np.linspace(0.0, 1.0, 3)))
    assert f"link 'crank' visual 0: {(tmp_path / 'bad.stl').resolve()}: {reason}; not drawn" in (
        caplog.text
    )
    assert scene.meshes.primitive_links == ("crank",) and scene.meshes.n_embedded == 1
    assert [p.rsplit("/", 2)[1] for p in mesh_objects(scene)] == ["coupler"]


def tetra_stl() -> bytes:
    triangles = np.zeros(len(TETRA_FACES), dtype=STL_TRIANGLE)
    triangles["vertices"] = TETRA[TETRA_FACES]
    return b"\0" * 80 + np.uint32(len(TETRA_FACES)).tobytes() + triangles.tobytes()


OBJ_TETRA = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_obj_meshes_are_embedded_as_text(tmp_path):
    (tmp_path / "tetra.obj").write_text(OBJ_TETRA)
    mesh = vz.read_mesh(tmp_path / "tetra.obj")
    assert mesh.format == "obj" and mesh.data == OBJ_TETRA.encode()
    assert np.linalg.norm(mesh.lower) <= EXACT_TOL
    assert np.linalg.norm(mesh.upper - 0.1) <= EXACT_TOL


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        (
            "t.obj",
            OBJ_TETRA.encode().replace(b"v 0 0 0", b"v 0 0 0 \xff"),
            r"OBJ file is not UTF-8",
        ),
        (
            "t.dae",
            b'<?xml version="1.0"?><!DOCTYPE x [<!ENTITY a "b">]><COLLADA/>',
            r"t.dae: DAE file declares a DOCTYPE; valid: COLLADA without one",
        ),
        ("t.stl", b"", r"t.stl: STL mesh has no triangles"),
        ("t.ply", b"ply\n", r"t.ply: cannot read mesh: "),
    ],
)
def test_meshes_meshcat_cannot_take_are_refused(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(ClosedChainError, match=match):
        vz.read_mesh(tmp_path / name)


def test_a_negative_mesh_budget_is_refused(fourbar):
    with pytest.raises(
        ClosedChainError, match=r"mesh_budget_bytes = -1; valid: a number of bytes >= 0"
    ):
        vz.read_visuals(fourbar, settings=vz.AnimationSettings(mesh_budget_bytes=-1))


@pytest.fixture(scope="module")
def ur5_crank():
    """erd:ur5 with an overlay from models/: its meshes lie in example-robot-data."""
    return cc.load("erd:ur5", loops=MODELS / "ur5_crank.urdf")


def test_an_erd_robot_embeds_its_meshes_within_the_budget(ur5_crank):

    from closedchain.robots import erd_robots_dir

    bodies = ur5_crank.description.tree.bodies
    files = [v.mesh_file for b in bodies for v in b.visuals if v.kind == "mesh"]
    assert len(files) == 7 and all(f.startswith("package://example-robot-data/") for f in files)
    share = erd_robots_dir().parent
    total = sum((share / f.partition("example-robot-data/")[2]).stat().st_size for f in files)
    visuals, meshes = vz.read_scene_visuals(ur5_crank)
    assert meshes == vz.MeshSummary(7, total, vz.DEFAULT_SETTINGS.mesh_budget_bytes, ())
    assert {v.mesh.parent.name for v in visuals if v.kind == "mesh"} == {"visual"}

    tiny = vz.AnimationSettings(mesh_budget_bytes=1)
    visuals, meshes = vz.read_scene_visuals(ur5_crank, settings=tiny)
    assert (meshes.n_embedded, meshes.embedded_bytes, len(meshes.primitive_links)) == (0, 0, 7)
    assert {v.kind for v in visuals} == {"sphere", "cylinder"}


def test_cli_states_the_meshes_and_takes_a_budget(two_meshes, tmp_path, capsys):
    from closedchain.cli import main

    mech, big, _ = two_meshes
    out = tmp_path / "m.html"
    argv = ["animate", str(mech.path), "--t-final", "0.1", "-o", str(out)]
    assert main([*argv, "--mesh-budget", f"{big / 1e6}"]) == 0
    assert (
        capsys.readouterr()
        .out.rstrip()
        .endswith(
            f"; meshes: 1 embedded ({big / 1e6:.3g} MB of a {big / 1e6:.3g} MB budget), "
            "1 link drawn as primitives)"
        )
    )


def test_links_without_visuals_are_drawn_as_sticks_sized_from_the_model():
    """tests/data/slider_crank_driven.urdf has inertials only: the crank is a stick from
    its pivot to the rod joint (0.1 m), the rod one to its loop frame on the slider side
    (0.35 m), the slider a ball (it carries nothing); the radius is STICK_RADIUS_RATIO
    times the median of those lengths."""
    mech = cc.load(Path(__file__).parent / "data" / "slider_crank_driven.urdf")
    visuals = vz.read_visuals(mech)
    radius = vz.settings.STICK_RADIUS_RATIO * np.median([0.1, 0.35])
    by_link = {link: [v for v in visuals if v.link == link] for link in ("crank", "rod", "slider")}
    for link, length in (("crank", 0.1), ("rod", 0.35)):
        ball, stick = by_link[link]
        assert ball.kind == "sphere" and stick.kind == "cylinder"
        assert stick.dims == pytest.approx((radius, length), abs=EXACT_TOL)
        # Along the link's x axis, centred halfway (a URDF cylinder runs along its z).
        assert np.linalg.norm(stick.origin[:3, 2] - [1.0, 0.0, 0.0]) <= EXACT_TOL
        assert np.linalg.norm(stick.origin[:3, 3] - [length / 2, 0.0, 0.0]) <= EXACT_TOL
    (slider,) = by_link["slider"]
    assert slider.kind == "sphere"
    assert not [v for v in visuals if v.link == "ground"]  # no mass, nothing to join


def test_stick_figures_are_drawn_from_the_shared_stick_segments():
    """The animation's sticks and the workspace pictures' are one list
    (shapes.stick_segments): each cylinder of tests/data/slider_crank_driven.urdf's
    stick figures runs along one segment of at least STICK_MIN_LENGTH, in order, and
    the segments end at the URDF's joint origins (crank -> rod joint at 0.1 m along x)
    and loop frames (rod -> loop Q at 0.35 m)."""
    mech = cc.load(Path(__file__).parent / "data" / "slider_crank_driven.urdf")
    sticks = [s for s in vz.stick_segments(mech) if s.length >= vz.settings.STICK_MIN_LENGTH]
    ends = {(s.link, s.to, s.loop): (s.start, s.end) for s in sticks}
    assert ends.keys() == {("crank", "rod_joint", False), ("rod", "Q", True)}
    for key, end in ((("crank", "rod_joint", False), 0.1), (("rod", "Q", True), 0.35)):
        start, stop = ends[key]
        assert np.linalg.norm(start) <= EXACT_TOL
        assert np.linalg.norm(stop - [end, 0.0, 0.0]) <= EXACT_TOL
    cylinders = [v for v in vz.read_visuals(mech) if v.kind == "cylinder"]
    assert [v.link for v in cylinders] == [s.link for s in sticks]
    for v, s in zip(cylinders, sticks, strict=True):
        half = v.origin[:3, 2] * v.dims[1] / 2.0  # a cylinder runs along its z axis
        assert np.linalg.norm(v.origin[:3, 3] - half - s.start) <= EXACT_TOL
        assert np.linalg.norm(v.origin[:3, 3] + half - s.end) <= EXACT_TOL


def test_meshes_resolve_against_the_file_that_names_them(tmp_path, caplog):
    """Under --loops (an overlay or a loops YAML file elsewhere) the base's meshes were
    looked up beside the overlay: reported missing, or a file of the same name there
    embedded instead. Each link's meshes are now looked up beside its own file."""
    base_dir, other_dir = tmp_path / "base", tmp_path / "overlay"
    for d in (base_dir / "meshes", other_dir / "meshes"):
        d.mkdir(parents=True)
    write_binary_stl(base_dir / "meshes" / "tetra.stl", TETRA, TETRA_FACES)
    write_binary_stl(other_dir / "meshes" / "tetra.stl", *tetrahedra(2, 0.2))  # a decoy
    write_binary_stl(other_dir / "meshes" / "own.stl", *tetrahedra(3, 0.3))
    urdf = (
        (MODELS / "fourbar.urdf")
        .read_text()
        .replace(
            '<geometry><box size="0.4 0.012 0.02"/></geometry>',
            '<geometry><mesh filename="meshes/tetra.stl"/></geometry>',
        )
    )
    (base_dir / "mesh.urdf").write_text(urdf)
    overlay = other_dir / "overlay.urdf"
    overlay.write_text(
        '<robot name="with_marker"><link name="marker"><visual><geometry>'
        '<mesh filename="meshes/own.stl"/></geometry></visual></link>'
        '<joint name="marker_joint" type="fixed"><parent link="crank"/><child link="marker"/>'
        "</joint></robot>"
    )
    mech = cc.load(base_dir / "mesh.urdf", loops=overlay)
    with caplog.at_level(logging.WARNING, logger="closedchain.visualize"):
        meshes = {v.link: v.mesh for v in vz.read_visuals(mech) if v.kind == "mesh"}
    assert "not found" not in caplog.text
    assert meshes == {
        "coupler": (base_dir / "meshes" / "tetra.stl").resolve(),
        "marker": (other_dir / "meshes" / "own.stl").resolve(),
    }
    # A loops YAML file beside a decoy: the base's meshes still come from the base.
    yaml_urdf = (DATA_DIR / "yaml_fivebar.urdf").read_text()
    first_link = yaml_urdf.index(">", yaml_urdf.index('<link name="prox1"')) + 1
    yaml_urdf = (
        yaml_urdf[:first_link]
        + '<visual><geometry><mesh filename="meshes/tetra.stl"/></geometry></visual>'
        + yaml_urdf[first_link:]
    )
    (base_dir / "fivebar.urdf").write_text(yaml_urdf)
    loops = other_dir / "fivebar.yaml"
    loops.write_text((DATA_DIR / "yaml_fivebar_6d.yaml").read_text())
    mech = cc.load(base_dir / "fivebar.urdf", loops=loops)
    (visual,) = [v for v in vz.read_visuals(mech) if v.kind == "mesh"]
    assert visual.link == "prox1"
    assert visual.mesh == (base_dir / "meshes" / "tetra.stl").resolve()


def test_an_sdf_model_animates_with_its_visuals(tmp_path):
    """An SDF model is drawn from its description: the crank's <visual> (a cylinder 0.05 m
    along the crank's x, turned pi/2 about y, red in tests/data/fourbar.sdf) sits in
    the crank's frame and moves with it."""
    mech = cc.load(DATA_DIR / "fourbar.sdf")
    visuals, meshes = vz.read_scene_visuals(mech)
    (crank,) = [v for v in visuals if v.link == "crank"]
    origin = pin.SE3(pin.rpy.rpyToMatrix(0.0, np.pi / 2, 0.0), np.array([0.05, 0.0, 0.0]))
    assert (crank.kind, crank.dims, crank.rgba) == ("cylinder", (0.01, 0.1), (0.8, 0.2, 0.2, 1.0))
    assert np.max(np.abs(crank.origin - origin.homogeneous)) < EXACT_TOL
    assert meshes.n_embedded == 0
    rng = np.random.default_rng(0)
    qs = np.array([cc.random_consistent_state(mech, rng)[0] for _ in range(3)])
    traj = kinematic_trajectory(mech, np.array([0.0, 0.5, 1.0]), qs)
    out = cc.write_html(mech, traj, tmp_path / "fourbar_sdf.html", fps=10.0)
    scene = vz.build_scene(mech, traj, fps=10.0)
    moving = {b.link for b in scene.bodies if b.moving}
    assert {"crank", "coupler", "rocker", "motor"} <= moving
    assert out.n_tracks == len(moving) and out.size < SIZE_BUDGET
