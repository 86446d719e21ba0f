"""Every public function refuses a settings object of the wrong class, naming the class
it takes (a wrong class used to end in an AttributeError far from the mistake)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain.export import export_mjcf
from closedchain.parallel import forward_kinematics, inverse_kinematics

#: A settings object of a class none of the functions below takes.
WRONG = cc.LoadSettings()


@pytest.fixture(scope="module")
def fourbar() -> cc.Mechanism:
    return cc.load(MODELS / "fourbar.urdf")


def _calls(mech, tmp_path):
    q, v = mech.q_ref, np.zeros(mech.nv)
    return {
        "simulate settings": (
            lambda: cc.simulate(mech, q, v, 0.01, settings=cc.SolverSettings()),
            "settings must be a SimulationSettings",
        ),
        "simulate solver_settings": (
            lambda: cc.simulate(mech, q, v, 0.01, solver_settings=cc.SimulationSettings()),
            "solver_settings must be a SolverSettings",
        ),
        "forward_dynamics": (
            lambda: cc.forward_dynamics(mech, q, v, settings=WRONG),
            "settings must be a SolverSettings",
        ),
        "inverse_dynamics": (
            lambda: cc.inverse_dynamics(mech, q, v, np.zeros(mech.mobility), settings=WRONG),
            "settings must be a SolverSettings",
        ),
        "load": (
            lambda: cc.load(MODELS / "fourbar.urdf", settings=cc.SolverSettings()),
            "settings must be a LoadSettings",
        ),
        "assemble": (
            lambda: cc.assemble(mech, q, settings=WRONG),
            "settings must be a AssemblySettings",
        ),
        "validate": (
            lambda: cc.validate(mech, n_samples=1, settings=WRONG),
            "settings must be a SolverSettings",
        ),
        "gravity_torque": (
            lambda: cc.gravity_torque(mech, q, settings=WRONG),
            "settings must be a SolverSettings",
        ),
        "forward_kinematics": (
            lambda: forward_kinematics(mech, q[:1], settings=WRONG),
            "settings must be a AssemblySettings",
        ),
        "inverse_kinematics": (
            lambda: inverse_kinematics(mech, "crank", np.zeros(3), mode="3d", settings=WRONG),
            "settings must be a AssemblySettings",
        ),
        "write_html": (
            lambda: cc.write_html(mech, None, tmp_path / "x.html", settings=WRONG),
            "settings must be a AnimationSettings",
        ),
        "export_mjcf": (
            lambda: export_mjcf(mech, tmp_path / "x.xml", settings=WRONG),
            "settings must be a MjcfSettings",
        ),
    }


NAMES = (
    "simulate settings",
    "simulate solver_settings",
    "forward_dynamics",
    "inverse_dynamics",
    "load",
    "assemble",
    "validate",
    "gravity_torque",
    "forward_kinematics",
    "inverse_kinematics",
    "write_html",
    "export_mjcf",
)


@pytest.mark.parametrize("name", NAMES)
def test_wrong_settings_class_is_refused_naming_the_class(fourbar, tmp_path, name):
    call, message = _calls(fourbar, tmp_path)[name]
    with pytest.raises(cc.InvalidArgumentError, match=message):
        call()
    assert not list(tmp_path.iterdir())  # refused before anything is written
