"""Tests of the constraint layer (closedchain.constraints): phi, J, gamma = Jdot v.

References, none of them computed by closedchain:

* the lesson's 4-bar closed forms (Section 2 phi and J_c, Problem 2 Jdot_c) and
  Freudenstein's equation (tests/conftest.py);
* central finite differences through ``pin.integrate`` for every loop type
  (revolute: 4-bar, Agile Eye; spherical, prismatic, fixed: tests/data/);
* the loop placements written in the URDF files, read here with the
  standard-library XML parser, for the "cut frames coincide" checks.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_MECHANISMS

import closedchain as cc
from closedchain.constraints import axis_basis
from closedchain.kinematics import AssemblySettings

#: Agreement of the layer with the lesson's closed forms [m, m/s^2] (round-off only).
TOL_CLOSED_FORM = 1e-12
#: Assembled 4-bar angles against Freudenstein's solution [rad].
TOL_FREUDENSTEIN = 1e-10
#: Central-difference step along pin.integrate [rad or m].
FD_STEP = 1e-6
#: Agreement of J and gamma with central differences (norm over a matrix/vector).
TOL_FD = 1e-7
#: Step of the second difference of phi (gamma = d^2 phi / dt^2 at a = 0).
FD2_STEP = 1e-4
#: Its tolerance: truncation O(h^2) plus round-off O(eps / h^2) ~ 1e-8.
TOL_FD2 = 1e-6
#: Cut frames of an assembled loop coincide to this [m or -].
TOL_CUT_FRAMES = 1e-10
#: A state sampled for the finite-difference tests: random (off the manifold) or assembled.
N_RANDOM_STATES = 8
N_ASSEMBLED_STATES = 3


# -- helpers -------------------------------------------------------------------------------


def read_loops(path: Path) -> list[dict]:
    """Read the ``<loop>`` elements of a URDF with the standard library (independent of lxml).

    Returns:
        One dict per loop: name, type, predecessor, successor, c1 and c2 (placements
        of the cut frames in their links, pin.SE3) and the unit axis, shape (3,).
    """
    root = ET.parse(path).getroot()

    def origin(el) -> pin.SE3:
        if el is None:
            return pin.SE3.Identity()
        xyz = np.array([float(x) for x in el.get("xyz", "0 0 0").split()])
        rpy = np.array([float(x) for x in el.get("rpy", "0 0 0").split()])
        return pin.SE3(pin.rpy.rpyToMatrix(rpy), xyz)

    loops = []
    for el in root.findall("loop"):
        axis_el = el.find("axis")
        axis = None
        if axis_el is not None:
            axis = np.array([float(x) for x in axis_el.get("xyz").split()])
        loops.append(
            {
                "name": el.get("name"),
                "type": el.get("type"),
                "predecessor": el.find("predecessor").get("link"),
                "successor": el.find("successor").get("link"),
                "c1": origin(el.find("predecessor_origin")),
                "c2": origin(el.find("successor_origin")),
                "axis": None if axis is None else axis / np.linalg.norm(axis),
            }
        )
    return loops


def layer_phi(mech, layer, q):
    pin.forwardKinematics(mech.model, mech.data, q)
    out = np.zeros(layer.nc)
    layer.evaluate(mech.model, mech.data, phi=out)
    return out


def layer_jacobian(mech, layer, q):
    pin.computeJointJacobians(mech.model, mech.data, q)
    out = np.zeros((layer.nc, mech.nv))
    layer.evaluate(mech.model, mech.data, J=out)
    return out


def layer_gamma(mech, layer, q, v):
    pin.forwardKinematics(mech.model, mech.data, q, v, np.zeros(mech.nv))
    out = np.zeros(layer.nc)
    layer.evaluate(mech.model, mech.data, gamma=out)
    return out


def fd_jacobian(mech, layer, q, h=FD_STEP):
    """Central differences of phi along pin.integrate, one velocity direction at a time."""
    cols = []
    for i in range(mech.nv):
        dv = np.zeros(mech.nv)
        dv[i] = h
        plus = layer_phi(mech, layer, pin.integrate(mech.model, q, dv))
        minus = layer_phi(mech, layer, pin.integrate(mech.model, q, -dv))
        cols.append((plus - minus) / (2.0 * h))
    return np.column_stack(cols)


def fd_gamma(mech, layer, q, v, h=FD_STEP):
    """d/dt (J(q(t)) v) at t = 0 along q(t) = q (+) t v (zero acceleration)."""
    plus = layer_jacobian(mech, layer, pin.integrate(mech.model, q, h * v)) @ v
    minus = layer_jacobian(mech, layer, pin.integrate(mech.model, q, -h * v)) @ v
    return (plus - minus) / (2.0 * h)


def second_difference_gamma(mech, layer, q, v, h=FD2_STEP):
    """d^2/dt^2 phi(q (+) t v) at t = 0: equals gamma because the acceleration is zero."""
    plus = layer_phi(mech, layer, pin.integrate(mech.model, q, h * v))
    minus = layer_phi(mech, layer, pin.integrate(mech.model, q, -h * v))
    return (plus - 2.0 * layer_phi(mech, layer, q) + minus) / h**2


def sample_states(mech, rng):
    """Random (off-manifold) and assembled configurations with random velocities."""
    states = []
    for _ in range(N_RANDOM_STATES):
        states.append((mech.random_configuration(rng), rng.standard_normal(mech.nv)))
    for _ in range(N_ASSEMBLED_STATES):
        q, _ = cc.random_consistent_state(mech, rng)
        states.append((q, rng.standard_normal(mech.nv)))
    return states


def layers(mech):
    """The independent rows (used by every method) and all declared rows."""
    return {"independent": mech.constraints, "declared": mech.declared}


# -- the lesson's 4-bar closed forms -------------------------------------------------------


def test_fourbar_rows_are_the_lesson_planar_rows_in_the_cut_frame(fourbar, fourbar_closed_forms):
    assert [(r.loop, r.kind, r.unit) for r in fourbar.rows] == [("C", "t1", "m"), ("C", "t2", "m")]
    # The reference's basis is the layer's: n1, n2 across the loop axis, right-handed.
    cf = fourbar_closed_forms
    n1, n2 = axis_basis(np.array([0.0, -1.0, 0.0]))
    assert np.linalg.norm(n1 - cf.N1) + np.linalg.norm(n2 - cf.N2) <= 1e-15
    assert np.linalg.norm(np.cross(cf.N1, cf.N2) - np.array([0.0, -1.0, 0.0])) <= 1e-15


def test_fourbar_phi_matches_lesson_section2(fourbar, fourbar_closed_forms, rng):
    cf = fourbar_closed_forms
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, 3)  # off the manifold: phi is defined everywhere
        err = np.linalg.norm(cc.compute_phi(fourbar, q) - cf.phi_cut(cf.theta(q)))
        assert err <= TOL_CLOSED_FORM, (q, err)
        # Same length as the lesson's world closure: a rotation of it.
        assert (
            abs(np.linalg.norm(cc.compute_phi(fourbar, q)) - np.linalg.norm(cf.phi(cf.theta(q))))
            <= TOL_CLOSED_FORM
        )


def test_fourbar_jacobian_matches_lesson_section2(fourbar, fourbar_closed_forms, rng):
    cf = fourbar_closed_forms
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, 3)
        expected = cf.jacobian_cut(cf.theta(q)) @ cf.T
        err = np.linalg.norm(cc.compute_jacobian(fourbar, q) - expected)
        assert err <= TOL_CLOSED_FORM, (q, err)


def test_fourbar_gamma_matches_lesson_problem2(fourbar, fourbar_closed_forms, rng):
    cf = fourbar_closed_forms
    for _ in range(200):
        q = rng.uniform(-np.pi, np.pi, 3)
        v = rng.normal(scale=3.0, size=3)
        theta_dot = cf.T @ v
        expected = cf.gamma_cut(cf.theta(q), theta_dot)
        err = np.linalg.norm(cc.compute_gamma(fourbar, q, v) - expected)
        assert err <= TOL_CLOSED_FORM * max(1.0, np.linalg.norm(expected)), (q, v, err)


def test_lesson_problem2_reference_is_the_derivative_of_the_jacobian(fourbar_closed_forms, rng):
    """The Jdot reference used above is d/dt J_c; the lesson's printed entry (2, 3) is not."""
    cf = fourbar_closed_forms
    h = FD_STEP
    for _ in range(20):
        theta = rng.uniform(-np.pi, np.pi, 3)
        theta_dot = rng.normal(size=3)
        fd = (cf.jacobian(theta + h * theta_dot) - cf.jacobian(theta - h * theta_dot)) / (2 * h)
        assert np.linalg.norm(cf.jacobian_dot(theta, theta_dot) - fd) <= TOL_FD
        # Lesson erratum: as printed, entry (2, 3) is the negative of the derivative;
        # every other printed entry is right.
        printed = cf.jacobian_dot_as_printed(theta, theta_dot)
        assert abs(printed[1, 2] + fd[1, 2]) <= TOL_FD
        others = np.ones((2, 3), dtype=bool)
        others[1, 2] = False
        assert np.linalg.norm(printed[others] - fd[others]) <= TOL_FD


@pytest.mark.parametrize("theta2_deg", [-170, -135, -90, -45, -10, 0, 10, 45, 90, 135, 170])
def test_fourbar_assembly_matches_freudenstein(
    fourbar, fourbar_closed_forms, angle_difference, rng, theta2_deg
):
    cf = fourbar_closed_forms
    theta2 = np.deg2rad(theta2_deg)
    branches = cf.freudenstein(theta2)
    assert np.linalg.norm(angle_difference(branches[0], branches[1])) > 0.1  # two branches
    for theta in branches:
        assert np.linalg.norm(cf.phi(theta)) <= TOL_CLOSED_FORM  # the reference closes
        q_exact = cf.q_from_theta(theta)
        q_guess = q_exact + np.r_[0.0, rng.uniform(-0.05, 0.05, 2)]
        q = cc.assemble(fourbar, q_guess, fixed=["crank_joint"])
        assert q[0] == q_guess[0]  # held exactly
        err = np.linalg.norm(angle_difference(q, q_exact))
        assert err <= TOL_FREUDENSTEIN, (theta2_deg, theta, q, err)


# -- finite differences through pin.integrate, every loop type ----------------------------


@pytest.mark.parametrize("name", ALL_MECHANISMS)
@pytest.mark.parametrize("rows", ["independent", "declared"])
def test_jacobian_matches_finite_differences(load_mechanism, rng, name, rows):
    mech = load_mechanism(name)
    layer = layers(mech)[rows]
    errors = []
    for q, _ in sample_states(mech, rng):
        J = layer_jacobian(mech, layer, q)
        errors.append(np.linalg.norm(J - fd_jacobian(mech, layer, q)))
    assert max(errors) <= TOL_FD, errors


@pytest.mark.parametrize("name", ALL_MECHANISMS)
@pytest.mark.parametrize("rows", ["independent", "declared"])
def test_gamma_matches_finite_differences(load_mechanism, rng, name, rows):
    mech = load_mechanism(name)
    layer = layers(mech)[rows]
    errors = []
    for q, v in sample_states(mech, rng):
        gamma = layer_gamma(mech, layer, q, v)
        errors.append(np.linalg.norm(gamma - fd_gamma(mech, layer, q, v)))
    assert max(errors) <= TOL_FD, errors


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_gamma_is_second_derivative_of_phi(load_mechanism, rng, name):
    """gamma = d^2/dt^2 phi(q(t)) at zero acceleration: a check that never uses J."""
    mech = load_mechanism(name)
    errors = []
    for q, v in sample_states(mech, rng):
        v = v / np.linalg.norm(v)
        gamma = cc.compute_gamma(mech, q, v)
        errors.append(np.linalg.norm(gamma - second_difference_gamma(mech, mech.constraints, q, v)))
    assert max(errors) <= TOL_FD2, errors


#: The compiled core's rows against numpy's (the same formulas, round-off).
TOL_BACKENDS = 1e-13


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_public_functions_evaluate_the_independent_rows(load_mechanism, rng, name):
    """The numpy backend is the layer's own evaluation, bit for bit; the default backend
    (compiled where it is built) the same rows to round-off."""
    mech = load_mechanism(name)
    q = mech.random_configuration(rng)
    v = rng.standard_normal(mech.nv)
    layer = mech.constraints
    assert cc.compute_phi(mech, q).shape == (mech.nc,)
    assert cc.compute_jacobian(mech, q).shape == (mech.nc, mech.nv)
    want = (layer_phi(mech, layer, q), layer_jacobian(mech, layer, q))
    want += (layer_gamma(mech, layer, q, v),)
    for backend in ("numpy", "auto"):
        got = (
            cc.compute_phi(mech, q, backend=backend),
            cc.compute_jacobian(mech, q, backend=backend),
            cc.compute_gamma(mech, q, v, backend=backend),
        )
        for g, w in zip(got, want, strict=True):
            if backend == "numpy":
                assert np.array_equal(g, w)
            else:
                assert np.max(np.abs(g - w), initial=0.0) <= TOL_BACKENDS * (1 + np.max(np.abs(w)))


# -- assembled configurations: phi = 0 and the cut frames coincide ----------------------


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_cut_frames_coincide_after_assembly(load_mechanism, mechanism_files, rng, name):
    mech = load_mechanism(name)
    model, data = mech.model, mech.data
    loops = read_loops(mechanism_files[name])
    assert [lp["name"] for lp in loops] == [spec.name for spec in mech.description.loops]
    for _ in range(5):
        q, _ = cc.random_consistent_state(mech, rng)
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= AssemblySettings().tol
        # The declared (redundant) rows vanish too: row selection dropped no constraint.
        assert np.linalg.norm(layer_phi(mech, mech.declared, q)) <= TOL_CUT_FRAMES
        pin.framesForwardKinematics(model, data, q)
        for lp in loops:
            # Cut frames from the URDF text: link placement times the loop origin.
            link_p = model.getFrameId(lp["predecessor"], pin.FrameType.BODY)
            link_s = model.getFrameId(lp["successor"], pin.FrameType.BODY)
            oMc1 = data.oMf[link_p] * lp["c1"]
            oMc2 = data.oMf[link_s] * lp["c2"]
            # ... and they are the model frames the layer added for the loop.
            f1 = data.oMf[model.getFrameId(f"{lp['name']}::predecessor")]
            f2 = data.oMf[model.getFrameId(f"{lp['name']}::successor")]
            assert np.linalg.norm((oMc1.inverse() * f1).homogeneous - np.eye(4)) <= 1e-12
            assert np.linalg.norm((oMc2.inverse() * f2).homogeneous - np.eye(4)) <= 1e-12
            d = oMc1.translation - oMc2.translation
            R1, R2 = oMc1.rotation, oMc2.rotation
            if lp["type"] in ("revolute", "spherical", "fixed"):
                assert np.linalg.norm(d) <= TOL_CUT_FRAMES, (lp["name"], d)
            if lp["type"] == "revolute":
                # Equal axes; free rotation about them.
                assert np.linalg.norm(R1 @ lp["axis"] - R2 @ lp["axis"]) <= TOL_CUT_FRAMES
            if lp["type"] in ("fixed", "prismatic"):
                assert np.linalg.norm(pin.log3(R1.T @ R2)) <= TOL_CUT_FRAMES
            if lp["type"] == "prismatic":
                # Free translation along the axis only.
                assert np.linalg.norm(np.cross(d, R1 @ lp["axis"])) <= TOL_CUT_FRAMES


@pytest.mark.parametrize("name", ALL_MECHANISMS[4:])
def test_test_mechanisms_close_at_their_stated_configuration(mechanism_files, load_mechanism, name):
    """Each tests/data/ file states a configuration q_star at which its loop is closed."""
    mech = load_mechanism(name)
    text = Path(mechanism_files[name]).read_text()
    line = next(ln for ln in text.splitlines() if "q_star_v = [" in ln)
    q_star_v = np.array([float(x) for x in line.split("[")[1].split("]")[0].split(",")])
    q_star = pin.integrate(mech.model, pin.neutral(mech.model), q_star_v)
    assert np.linalg.norm(layer_phi(mech, mech.declared, q_star)) <= 1e-13


def test_agile_eye_translation_rows_vanish_identically(agile_eye, rng):
    """Agile Eye: its translation rows vanish identically (every axis meets the centre)."""
    for _ in range(5):
        q = agile_eye.random_configuration(rng)
        phi = layer_phi(agile_eye, agile_eye.declared, q)
        J = layer_jacobian(agile_eye, agile_eye.declared, q)
        translation = [i for i, r in enumerate(agile_eye.declared.rows) if r.unit == "m"]
        assert len(translation) == 9
        assert np.linalg.norm(phi[translation]) <= 1e-15
        assert np.linalg.norm(J[translation]) <= 1e-15


# -- many loops ----------------------------------------------------------------------------


def test_many_loops_match_finite_differences(tmp_path, rng):
    """The N-four-bar with 5 loops: J and gamma against central differences, every
    declared row."""
    from closedchain.benchmark.families import nfourbar_urdf

    path = tmp_path / "nfourbar_5.urdf"
    path.write_text(nfourbar_urdf(5))
    mech = cc.load(path)
    for layer in layers(mech).values():
        for q, v in sample_states(mech, rng):
            J = layer_jacobian(mech, layer, q)
            assert np.linalg.norm(J - fd_jacobian(mech, layer, q)) <= TOL_FD
            gamma = layer_gamma(mech, layer, q, v)
            assert np.linalg.norm(gamma - fd_gamma(mech, layer, q, v)) <= TOL_FD
