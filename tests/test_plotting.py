"""Tests of closedchain.plotting (matplotlib, headless)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain.exceptions import ClosedChainError
from closedchain.plotting import RESIDUAL_FLOOR, plot_trajectory

#: Plotted data are the trajectory's own numbers.
EXACT_TOL = 1e-12
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
