"""Tests of closedchain.plotting (matplotlib, headless)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
from conftest import MODELS, kinematic_trajectory

import closedchain as cc
from closedchain.exceptions import ClosedChainError
from closedchain.plotting import RESIDUAL_FLOOR, coordinate_series, plot_trajectory

#: Plotted data are the trajectory's own numbers.
EXACT_TOL = 1e-12
#: Angles recovered from (cos, sin) pairs and quaternions [rad].
ANGLE_TOL = 1e-10
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def fourbar_run(fourbar_traj) -> cc.Trajectory:
    """The 4-bar sweep with made-up residuals and energy, as a simulation would give."""
    rng = np.random.default_rng(1)
    n = len(fourbar_traj.t)
    return dataclasses.replace(
        fourbar_traj,
        constraint_residual=10.0 ** rng.uniform(-15, -9, n),
        velocity_residual=np.zeros(n),  # exact zeros: drawn at the floor
        energy=1.5 + 1e-9 * np.cumsum(rng.standard_normal(n)),
        info={
            "mechanism": "fourbar",
            "method": "kkt",
            "integrator": "DOP853",
            "stabilization": "none",
            "coordinate_names": ["crank_joint", "coupler_joint", "rocker_joint"],
            "independent": ["crank_joint"],
        },
    )


def test_three_panels_against_time(fourbar, fourbar_run):
    fig = plot_trajectory(fourbar_run, mech=fourbar)
    ax_q, ax_res, ax_e = fig.axes
    t = fourbar_run.t
    # Independent coordinates: one line each, named, in [rad].
    (line,) = ax_q.get_lines()
    assert line.get_label() == "crank_joint [rad]"
    assert np.linalg.norm(line.get_xdata() - t) <= EXACT_TOL
    assert np.linalg.norm(line.get_ydata() - fourbar_run.q[:, 0]) <= EXACT_TOL
    # Residuals on a log scale, exact zeros at the floor.
    assert ax_res.get_yscale() == "log"
    res, vres = ax_res.get_lines()
    assert np.linalg.norm(res.get_ydata() - fourbar_run.constraint_residual) <= EXACT_TOL
    assert np.all(vres.get_ydata() == RESIDUAL_FLOOR)
    # Energy drift E(t) - E(0) [J].
    (drift,) = ax_e.get_lines()
    energy = fourbar_run.energy
    assert np.linalg.norm(drift.get_ydata() - (energy - energy[0])) <= EXACT_TOL
    assert ax_e.get_xlabel() == "time [s]"
    assert fig._suptitle.get_text() == "fourbar / kkt / DOP853 / none"


def test_a_driven_run_plots_its_energy_balance(fourbar, fourbar_run):
    """With the work W of tau recorded the energy panel is E - E(0) - W, labelled so;
    without it, E - E(0)."""
    rng = np.random.default_rng(2)
    work = 1e-3 * np.cumsum(rng.standard_normal(len(fourbar_run.t)))
    driven = dataclasses.replace(fourbar_run, work=work)
    ax_e = plot_trajectory(driven, mech=fourbar).axes[2]
    (balance,) = ax_e.get_lines()
    energy = driven.energy
    assert np.linalg.norm(balance.get_ydata() - (energy - energy[0] - work)) <= EXACT_TOL
    assert ax_e.get_ylabel().startswith("energy balance")
    assert r"\int_0^t \tau \cdot v" in ax_e.get_ylabel()
    assert (
        plot_trajectory(fourbar_run, mech=fourbar).axes[2].get_ylabel().startswith("energy drift")
    )


def test_agile_eye_plots_its_three_independent_coordinates(agile_eye, agile_eye_traj):
    fig = plot_trajectory(agile_eye_traj, mech=agile_eye)
    labels = [ln.get_label() for ln in fig.axes[0].get_lines()]
    expected = [agile_eye.coordinate_names[i] + " [rad]" for i in agile_eye.independent_idx_v]
    assert labels == expected


def test_without_mechanism_the_info_names_the_coordinates(fourbar_run, tmp_path):
    path = fourbar_run.save(tmp_path / "run.npz")
    fig = plot_trajectory(cc.Trajectory.load(path))
    (line,) = fig.axes[0].get_lines()
    assert line.get_label() == "crank_joint"
    assert np.linalg.norm(line.get_ydata() - fourbar_run.q[:, 0]) <= EXACT_TOL


def test_chosen_coordinates(fourbar, fourbar_run):
    fig = plot_trajectory(fourbar_run, mech=fourbar, coordinates=["coupler_joint", "rocker_joint"])
    labels = [ln.get_label() for ln in fig.axes[0].get_lines()]
    assert labels == ["coupler_joint [rad]", "rocker_joint [rad]"]
    with pytest.raises(ClosedChainError, match="unknown coordinate 'nope'; valid choices: crank"):
        plot_trajectory(fourbar_run, coordinates=["nope"])


def test_saves_png_headless(fourbar, fourbar_run, tmp_path):
    out = tmp_path / "run.png"
    plot_trajectory(fourbar_run, mech=fourbar).savefig(out)
    assert out.read_bytes()[:8] == PNG_MAGIC


def test_plotting_touches_no_global_matplotlib_state():
    """Building and saving a figure imports neither pyplot nor a GUI backend."""
    code = (
        "import sys, numpy as np, closedchain as cc\n"
        "n = 5\n"
        "tr = cc.Trajectory(t=np.arange(n) * 0.1, q=np.zeros((n, 2)), v=np.zeros((n, 2)),"
        " a=np.zeros((n, 2)), lam=np.zeros((n, 1)), constraint_residual=np.zeros(n),"
        " velocity_residual=np.zeros(n), energy=np.zeros(n))\n"
        "import io\n"
        "cc.plot_trajectory(tr).savefig(io.BytesIO(), format='png')\n"
        "print('matplotlib.pyplot' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


# -- command line ------------------------------------------------------------------------


def test_cli_plot_of_a_saved_trajectory(fourbar_run, tmp_path, capsys):
    from closedchain.cli import main

    npz = fourbar_run.save(tmp_path / "run.npz")
    out = tmp_path / "run.png"
    assert main(["plot", str(npz), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert str(out) in capsys.readouterr().out


def test_cli_plot_simulates_a_urdf(tmp_path):
    from closedchain.cli import main

    out = tmp_path / "sim.png"
    assert main(["plot", str(MODELS / "fourbar.urdf"), "--t-final", "0.5", "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG_MAGIC


def test_cli_plot_of_a_missing_file(tmp_path, capsys):
    from closedchain.cli import main

    assert main(["plot", str(tmp_path / "none.npz"), "-o", str(tmp_path / "x.png")]) == 2
    assert "none.npz" in capsys.readouterr().err


def test_cli_plot_refuses_a_trajectory_of_another_mechanism(
    short_traj, fourbar_lookalikes, tmp_path, capsys
):
    from closedchain.cli import main

    npz = short_traj.save(tmp_path / "run.npz")
    png = tmp_path / "x.png"
    other = fourbar_lookalikes["renamed"]
    assert main(["plot", str(npz), "--urdf", str(other.path), "-o", str(png)]) == 2
    err = capsys.readouterr().err
    assert f"does not fit mechanism 'fourbar' ({other.path}): its joint 2 is 'rocker_joint'" in err
    assert not png.exists()


@pytest.mark.parametrize(
    ("lookalike", "message"),
    [("renamed", r"its joint 2 is 'rocker_joint'"), ("longer_rocker", r"model digest")],
)
def test_plot_refuses_a_trajectory_of_another_mechanism(
    short_traj, fourbar_lookalikes, lookalike, message
):
    with pytest.raises(ClosedChainError, match=message):
        plot_trajectory(short_traj, mech=fourbar_lookalikes[lookalike])


# -- coordinates of joints with nq != nv ---------------------------------------------------


def test_coordinate_series_against_known_angles(rng):
    """Each joint type's scalar positions, against the angles the configurations are built from."""
    model = pin.Model()
    parent = 0
    for k, joint in enumerate(
        [
            pin.JointModelRUBZ(),
            pin.JointModelPlanar(),
            pin.JointModelSpherical(),
            pin.JointModelFreeFlyer(),
            pin.JointModelPX(),
        ]
    ):
        parent = model.addJoint(parent, joint, pin.SE3.Identity(), f"j{k}")
    n = 50
    theta = rng.uniform(-3.0, 3.0, n)  # continuous joint [rad]
    xy, phi = rng.uniform(-1.0, 1.0, (n, 2)), rng.uniform(-3.0, 3.0, n)  # planar [m], [rad]
    rotvec = rng.uniform(-1.5, 1.5, (n, 2, 3))  # spherical, free-flyer rotation vectors [rad]
    p, s = rng.uniform(-1.0, 1.0, (n, 3)), rng.uniform(-1.0, 1.0, n)  # [m]
    quat = [[pin.Quaternion(pin.exp3(rotvec[i, j])).coeffs() for j in range(2)] for i in range(n)]
    quat = np.array(quat)  # (x, y, z, w), Pinocchio's storage order
    q = np.column_stack(
        [np.cos(theta), np.sin(theta), xy, np.cos(phi), np.sin(phi), quat[:, 0], p, quat[:, 1], s]
    )
    assert q.shape == (n, model.nq) and model.nv == 1 + 3 + 3 + 6 + 1
    expected = np.column_stack([theta, xy, phi, rotvec[:, 0], p, rotvec[:, 1], s])
    got = np.column_stack([coordinate_series(model, q, i) for i in range(model.nv)])
    assert np.linalg.norm(got - expected) <= ANGLE_TOL
    # One configuration gives a scalar; the neutral one (identity quaternions) zeros.
    assert abs(float(coordinate_series(model, q[0], 0)) - theta[0]) <= ANGLE_TOL
    neutral = [coordinate_series(model, pin.neutral(model), i) for i in range(model.nv)]
    assert np.linalg.norm(neutral) == 0.0
    with pytest.raises(ClosedChainError, match="q has 3 columns, expected nq = 18"):
        coordinate_series(model, q[:, :3], 0)
    with pytest.raises(ClosedChainError, match=r"velocity index 14 out of range 0\.\.13"):
        coordinate_series(model, q, 14)


@pytest.fixture(scope="module")
def slider_crank_turns(load_mechanism) -> tuple[cc.Mechanism, cc.Trajectory, np.ndarray]:
    """A slider-crank trajectory whose continuous crank turns past pi (the other joints fixed)."""
    mech = load_mechanism("slider_crank")
    n = 41
    theta = np.linspace(0.0, 5.0, n)  # crank angle [rad], beyond atan2's range
    q = np.tile(mech.q_ref, (n, 1))
    q[:, 0], q[:, 1] = np.cos(theta), np.sin(theta)  # the crank is the first joint
    traj = kinematic_trajectory(
        mech,
        np.linspace(0.0, 1.0, n),
        q,
        info={
            "mechanism": mech.name,
            "coordinate_names": None,  # as simulate() writes when nq != nv
            "velocity_names": list(mech.coordinate_names),
            "independent": ["crank_joint"],
        },
    )
    return mech, traj, theta


def test_continuous_crank_is_plotted_as_its_angle(slider_crank_turns):
    mech, traj, theta = slider_crank_turns
    (line,) = plot_trajectory(traj, mech=mech).axes[0].get_lines()
    assert line.get_label() == "crank_joint [rad]"
    assert np.linalg.norm(line.get_ydata() - theta) <= ANGLE_TOL  # unwrapped


def test_nq_neq_nv_needs_the_mechanism(slider_crank_turns, fourbar_run):
    mech, traj, _ = slider_crank_turns
    with pytest.raises(ClosedChainError, match=r"nq = 7 != nv = 6: plotting it needs the mech"):
        plot_trajectory(traj)
    with pytest.raises(ClosedChainError, match="trajectory has nq = 3, nv = 3 but mechanism"):
        plot_trajectory(fourbar_run, mech=mech)


def test_integer_coordinates_are_velocity_indices(fourbar, fourbar_run):
    (line,) = plot_trajectory(fourbar_run, coordinates=[2]).axes[0].get_lines()
    assert line.get_label() == "rocker_joint"
    assert np.linalg.norm(line.get_ydata() - fourbar_run.q[:, 2]) <= EXACT_TOL
    (line,) = plot_trajectory(fourbar_run, mech=fourbar, coordinates=[2]).axes[0].get_lines()
    assert line.get_label() == "rocker_joint [rad]"
    with pytest.raises(ClosedChainError, match=r"velocity index 3 out of range 0\.\.2"):
        plot_trajectory(fourbar_run, coordinates=[3])


def test_cli_plot_of_a_continuous_joint_needs_the_urdf(slider_crank_turns, tmp_path, capsys):
    from closedchain.cli import build_parser, main

    mech, traj, _ = slider_crank_turns
    npz = traj.save(tmp_path / "run.npz")
    out = tmp_path / "run.png"
    assert main(["plot", str(npz), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("closedchain: error: the trajectory of 'slider_crank' has nq = 7")
    assert "--urdf" in err and not out.exists()
    assert main(["plot", str(npz), "--urdf", str(mech.path), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == PNG_MAGIC
    args = build_parser().parse_args(["plot", "t.npz", "-o", "x.png", "--coordinates", "2", "j"])
    assert args.coordinates == [2, "j"]
