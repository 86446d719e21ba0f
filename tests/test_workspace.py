"""Tests of closedchain.workspace: the 4-bar's link lengths and Grashof class measured on
the model against the lesson's lengths (conftest closed forms), the crank-range sweep against
the closed form, the Agile Eye's platform outputs and singularity map, error paths, CLI;
the pictures' stick figures against the 4-bar's closed-form joint positions and the Agile
Eye's sphere."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
from conftest import DATA_DIR

import closedchain as cc
from closedchain import cli
from closedchain.exceptions import ClosedChainError
from closedchain.visualize import posed_sticks, stick_segments
from closedchain.visualize.settings import STICK_MIN_LENGTH
from closedchain.workspace import (
    FIGURE_POSES,
    analyze_fourbar,
    default_outputs,
    plot_workspace,
    singularity_map,
    view_plane,
    workspace_figure,
)

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

#: Link lengths are measured from joint origins at q_ref [m] (round-off of assembly).
LENGTH_TOL = 1e-9
#: Sweep points of the tests.
SWEEP = 73
#: Grid of the Agile Eye map in the test.
GRID = 5


def test_fourbar_lengths_and_class(fourbar, fourbar_closed_forms):
    a = analyze_fourbar(fourbar, points=SWEEP)
    ref = fourbar_closed_forms
    got = (a.crank, a.coupler, a.rocker, a.ground)
    np.testing.assert_allclose(got, (ref.a, ref.b, ref.c, ref.d), atol=LENGTH_TOL)
    assert a.grashof == "change point"  # a + d = b + c
    assert a.agreement == 1.0
    assert a.closed_form.all()  # the crank turns fully (change-point linkage)


def test_not_a_fourbar_raises(agile_eye):
    with pytest.raises(ClosedChainError, match="not a planar 4-bar"):
        analyze_fourbar(agile_eye)


def test_agile_eye_outputs_are_the_platform_joints(agile_eye):
    assert default_outputs(agile_eye) == ("platform_yaw", "platform_pitch", "platform_roll")


def test_agile_eye_map_is_regular_at_home(agile_eye):
    m = singularity_map(agile_eye, points=GRID, span=0.3)
    centre = GRID // 2
    # Home is far from both singularity types (the isotropic Agile Eye pose).
    assert m.parallel[centre, centre] > 0.1
    assert m.serial[centre, centre] > 0.1
    with pytest.raises(ClosedChainError, match="two output coordinates"):
        singularity_map(agile_eye, outputs=("platform_yaw",))
    with pytest.raises(ClosedChainError, match="outputs names platform_yaw more than once"):
        singularity_map(agile_eye, outputs=("platform_yaw", "platform_yaw"))


#: The map's smallest singular values are those of J at the assembled grid points.
SIGMA_TOL = 1e-12


def test_five_bar_maps_its_independent_coordinates():
    """A five-bar's loop joins two distal links (no platform link): the map's outputs are
    its independent coordinates, the actuated cranks (before: the passive distal joints),
    and its values are sigma_min of J_D at the assembled configurations."""
    mech = cc.load(DATA_DIR / "five_bar.urdf")
    cranks = ("left_crank_joint", "right_crank_joint")
    assert tuple(mech.coordinate_names[i] for i in mech.independent_idx_v) == cranks
    assert default_outputs(mech) == cranks
    m = singularity_map(mech, points=GRID, span=0.2)
    assert m.outputs == cranks
    centre = GRID // 2
    q = cc.assemble(mech, mech.q_ref, fixed=list(cranks))
    J = cc.compute_jacobian(mech, q)
    sigma = np.linalg.svd(J[:, mech.dependent_idx_v], compute_uv=False)[-1]
    assert abs(m.parallel[centre, centre] - sigma) <= SIGMA_TOL
    np.testing.assert_array_equal(m.serial, m.parallel)  # outputs = actuators


def test_cli_workspace_five_bar(tmp_path, capsys):
    out = tmp_path / "w.png"
    argv = ["workspace", str(DATA_DIR / "five_bar.urdf"), "-o", str(out), "--points", "5"]
    assert cli.main(argv) == 0
    text = capsys.readouterr().out
    assert "singularity map over left_crank_joint, right_crank_joint" in text
    assert "serial = parallel" in text


def test_cli_workspace(tmp_path, mechanism_files, capsys):
    out = tmp_path / "w.png"
    argv = ["workspace", str(mechanism_files["fourbar"]), "-o", str(out), "--points", "37"]
    assert cli.main(argv) == 0
    assert "change point" in capsys.readouterr().out
    assert out.stat().st_size > 0


# -- the stick figures ---------------------------------------------------------------

#: Stick end points are placed by forward kinematics: round-off of a few products [m].
STICK_TOL = 1e-12
#: Crank angles [rad] where the 4-bar's sticks are checked (both assembly branches).
STICK_ANGLES = (0.3, 1.7, -2.4)


def _by_name(mech, q):
    sticks = stick_segments(mech)
    return {(s.link, s.to): p for s, p in zip(sticks, posed_sticks(mech, q, sticks), strict=True)}


def test_fourbar_sticks_are_the_closed_form_joint_positions(fourbar, fourbar_closed_forms):
    """The lesson's 4-bar (models/fourbar.urdf header: a, b, c, d, plane world x-z): at a
    crank angle each stick runs between the closed-form pivots A, D, crank tip B and loop
    point C, for both assembly branches (Freudenstein)."""
    ref = fourbar_closed_forms

    def world(x, y):  # the lesson's plane (x, y) is world (x, z)
        return np.array([x, 0.0, y])

    for theta2 in STICK_ANGLES:
        for theta in ref.freudenstein(theta2):
            th2, th3, th4 = theta
            A, D = world(0.0, 0.0), world(ref.d, 0.0)
            B = world(ref.a * np.cos(th2), ref.a * np.sin(th2))
            C = D + world(ref.c * np.cos(th4), ref.c * np.sin(th4))
            expected = {
                ("ground", "crank_joint"): (A, A),
                ("ground", "rocker_joint"): (A, D),
                ("crank", "coupler_joint"): (A, B),
                ("coupler", "C"): (B, C),
                ("rocker", "C"): (D, C),
            }
            got = _by_name(fourbar, ref.q_from_theta(theta))
            assert got.keys() == expected.keys()
            for key, ends in expected.items():
                assert np.linalg.norm(got[key] - np.array(ends)) <= STICK_TOL, (theta, key)


def test_agile_eye_sticks_lie_on_the_sphere_of_its_axes_centre(agile_eye):
    """models/agile_eye.urdf: every joint axis passes through O = 0 and the actuator axes
    are world x, y, z (its header). All joint origins are O, so each link is a chord between
    points at one distance R along its axes: on a sphere about O, the proximal links
    starting on the actuator axes, each loop's two sides ending at one point."""
    rng = np.random.default_rng(3)
    outputs = list(default_outputs(agile_eye))
    for _ in range(3):
        guess = agile_eye.q_ref.copy()
        guess[agile_eye.coordinate_indices(outputs)] += rng.uniform(-0.4, 0.4, 3)
        q = cc.assemble(agile_eye, guess, fixed=outputs)
        got = _by_name(agile_eye, q)
        chords = np.array([p for p in got.values() if np.linalg.norm(p[1] - p[0]) > 0])
        radii = np.linalg.norm(chords, axis=2).ravel()
        # 3 proximal, 3 distal, the platform's 2 (its roll axis is v_2: one stick is a point)
        assert len(chords) == 8
        assert np.max(np.abs(radii - radii[0])) <= STICK_TOL
        for i, axis in enumerate(np.eye(3), start=1):
            start = got[(f"proximal_{i}", f"distal_joint_{i}")][0]
            assert np.linalg.norm(start - radii[0] * axis) <= STICK_TOL
            sides = [p[1] for (_, to), p in got.items() if to == f"leg{i}_platform"]
            assert len(sides) == 2 and np.linalg.norm(sides[0] - sides[1]) <= LOOP_TOL


#: The loop's two sides meet within the assembly's residual [m].
LOOP_TOL = 1e-9


def test_view_planes(fourbar, agile_eye):
    """The 4-bar's joint axes are all (0, -1, 0): drawn in world x, z; the Agile Eye is
    not planar: drawn in the principal plane of its joint points, an orthonormal pair."""
    plane = view_plane(fourbar, posed_sticks(fourbar, fourbar.q_ref).reshape(-1, 3))
    assert plane.labels == ("world x [m]", "world z [m]")
    np.testing.assert_array_equal(plane.basis, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert "normal to the joint axes (0.00, -1.00, 0.00)" in plane.how
    plane = view_plane(agile_eye, posed_sticks(agile_eye, agile_eye.q_ref).reshape(-1, 3))
    assert "principal directions" in plane.how
    assert np.linalg.norm(plane.basis @ plane.basis.T - np.eye(2)) <= STICK_TOL


def _stick_lines(fig):
    return [line for ax in fig.axes for line in ax.get_lines() if line.get_gid() == "stick"]


def _long_sticks(mech):
    return sum(1 for s in stick_segments(mech) if s.length >= STICK_MIN_LENGTH)


def test_fourbar_picture_draws_the_linkage_at_its_telling_angles(fourbar, tmp_path):
    fig, summary = workspace_figure(fourbar, points=SWEEP)
    try:
        panels = [ax for ax in fig.axes if any(ln.get_gid() == "stick" for ln in ax.get_lines())]
        assert len(panels) == FIGURE_POSES
        assert _long_sticks(fourbar) == 4  # ground, crank, coupler, rocker
        assert len(_stick_lines(fig)) == 4 * FIGURE_POSES
        # The change point (crank at 180 deg, the sweep's largest cond(J)) is drawn.
        assert any("largest cond(J)" in ax.get_title() for ax in panels)
        assert all(ax.get_xlabel() == "world x [m]" for ax in panels)
    finally:
        plt.close(fig)
    assert "drawn at -180 deg" in summary and "10 deg" in summary  # q_ref: 10 deg
    out = tmp_path / "w.png"
    plot_workspace(fourbar, out, points=SWEEP)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["w.png"]  # written atomically


def test_map_picture_draws_q_ref_and_the_most_singular_point():
    """The five-bar's map: its serial map is its parallel one, so one panel at q_ref and
    one at the smallest sigma_min; each the five-bar's sticks."""
    mech = cc.load(DATA_DIR / "five_bar.urdf")
    fig, summary = workspace_figure(mech, points=GRID, span=0.2)
    try:
        assert len(_stick_lines(fig)) == 2 * _long_sticks(mech)
        titles = [ax.get_title() for ax in fig.axes]
        assert any(t.startswith("q_ref") for t in titles)
        assert any(t.startswith("smallest sigma: parallel") and "serial" in t for t in titles)
    finally:
        plt.close(fig)
    assert "drawn at q_ref and the most singular grid points" in summary
