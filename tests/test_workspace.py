"""Tests of closedchain.workspace: the 4-bar's link lengths and Grashof class measured on
the model against the lesson's lengths (conftest closed forms), the crank-range sweep against
the closed form, the Agile Eye's platform outputs and singularity map, error paths, CLI."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA_DIR

import closedchain as cc
from closedchain import cli
from closedchain.exceptions import ClosedChainError
from closedchain.workspace import analyze_fourbar, default_outputs, singularity_map

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
