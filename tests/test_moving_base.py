"""Loops on a moving base: the lesson's 4-bar on a turntable (models/turntable_fourbar.urdf).

References, none computed by closedchain's turntable model:

* the 4-bar alone (models/fourbar.urdf, itself checked against the lesson's closed
  forms in tests/test_constraints.py): rows written in frames that move with the
  loop do not depend on the turntable angle, so phi, J and gamma of the turntable
  model are those of the 4-bar, with a zero turntable column;
* conservation laws of the passive turntable: energy, and the angular momentum
  about the turntable axis (gravity is parallel to it and the bearing transmits no
  moment about it);
* pinocchio.constraintDynamics (tests/test_validation.py runs validate on it).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import closedchain as cc

#: 4-bar coordinates in the turntable model's velocity order.
FOURBAR_V = slice(1, 4)
#: Agreement of the turntable rows with the 4-bar's [m, m/s^2] (round-off).
TOL_ROWS = 1e-12
#: Crossed-branch start of the 4-bar [deg] (crank, coupler, rocker guesses): regular.
CROSSED_GUESS_DEG = (10.0, -65.0, -104.0)
#: Turntable spin [rad/s] of the issue's report (its kept world rows degenerated at 0.73 s).
SPIN = 2.0
#: Gain of the turntable's velocity servo [N m s/rad].
SERVO_GAIN = 50.0
#: Driven run [s]: past the old stop at 0.73 s, more than a full turn.
T_DRIVEN = 4.0
#: Passive run [s] and its integrator (DOP853 at tight tolerances, no stabilization).
T_PASSIVE = 10.0
PASSIVE_CONFIG = dict(integrator="DOP853", rtol=1e-12, atol=1e-12)
DRIVEN_CONFIG = dict(integrator="DOP853", rtol=1e-10, atol=1e-10)
#: Energy drift (relative) and declared-row residual [m] of the runs.
TOL_ENERGY = 1e-9
TOL_ROWS_RUN = 1e-9
#: Relative drift of the angular momentum about the turntable axis.
TOL_MOMENTUM = 1e-9
#: A point of the turntable axis in the world [m] (scripts/make_turntable_fourbar.py).
AXIS_POINT = np.array([0.25, 0.0, 0.0])


@pytest.fixture(scope="module")
def turntable(load_mechanism) -> cc.Mechanism:
    return load_mechanism("turntable_fourbar")


@pytest.fixture(scope="module")
def spinning_start(turntable):
    """Crossed branch at 10 deg crank, turntable at 0 turning at SPIN, 4-bar at rest."""
    guess = np.r_[0.0, np.radians(CROSSED_GUESS_DEG)]
    held = ["turntable_joint", "crank_joint"]
    q0 = cc.assemble(turntable, guess, fixed=held)
    v0 = cc.project_velocity(turntable, q0, np.array([SPIN, 0.0, 0.0, 0.0]), fixed=held)
    return q0, v0


def _declared(mech, q, v=None):
    model, data, layer = mech.model, mech.data, mech.declared
    pin.computeJointJacobians(model, data, q)
    J = np.zeros((layer.nc, mech.nv))
    phi = np.zeros(layer.nc)
    layer.evaluate(model, data, phi=phi, J=J)
    gamma = np.zeros(layer.nc)
    if v is not None:
        pin.forwardKinematics(model, data, q, v, np.zeros(mech.nv))
        layer.evaluate(model, data, gamma=gamma)
    return phi, J, gamma


def test_turntable_keeps_the_fourbar_rows(turntable, fourbar):
    assert [r.label for r in turntable.rows] == [r.label for r in fourbar.rows]
    assert turntable.row_selection.rank == 2
    assert turntable.mobility == 2
    assert turntable.summary()["row_selection"]["dropped"] == ["C.ta", "C.r1", "C.r2"]


def test_rows_do_not_depend_on_the_turntable(turntable, fourbar, rng):
    """phi, J, gamma of every declared row equal the 4-bar's at any turntable angle and
    speed (the turntable column of J is zero)."""
    errors = []
    for _ in range(50):
        q4 = rng.uniform(-np.pi, np.pi, 3)  # off the manifold too
        v4 = rng.normal(scale=3.0, size=3)
        q = np.r_[rng.uniform(-np.pi, np.pi), q4]
        v = np.r_[rng.normal(scale=5.0), v4]
        phi, J, gamma = _declared(turntable, q, v)
        phi4, J4, gamma4 = _declared(fourbar, q4, v4)
        errors.append(
            np.linalg.norm(phi - phi4)
            + np.linalg.norm(J[:, FOURBAR_V] - J4)
            + np.linalg.norm(J[:, 0])
            + np.linalg.norm(gamma - gamma4) / max(1.0, np.linalg.norm(gamma4))
        )
    assert max(errors) <= TOL_ROWS, max(errors)


def test_driven_spin_passes_where_world_rows_stopped(turntable, spinning_start):
    """The issue's report: spun at 2 rad/s the world-row 4-bar stopped at t = 0.73 s."""
    q0, v0 = spinning_start

    def servo(t, q, v):
        return np.array([SERVO_GAIN * (SPIN - v[0]), 0.0, 0.0, 0.0])

    traj = cc.simulate(turntable, q0, v0, T_DRIVEN, tau=servo, **DRIVEN_CONFIG)
    assert traj.t[-1] == pytest.approx(T_DRIVEN)
    assert traj.q[-1, 0] - traj.q[0, 0] > 2.0 * np.pi  # more than a full turn
    assert traj.max_constraint_residual <= TOL_ROWS_RUN  # every declared row
    assert traj.info.row_reselections == ()


def test_passive_spin_conserves_energy_and_axial_momentum(turntable, spinning_start):
    q0, v0 = spinning_start
    traj = cc.simulate(turntable, q0, v0, T_PASSIVE, **PASSIVE_CONFIG)
    assert traj.t[-1] == pytest.approx(T_PASSIVE)
    assert traj.q[-1, 0] > 2.0 * np.pi  # it turned (passively: no torque at all)
    assert np.ptp(traj.q[:, 1]) > 0.05  # and the 4-bar swung [rad]
    assert traj.energy_drift <= TOL_ENERGY
    assert traj.max_constraint_residual <= TOL_ROWS_RUN
    model, data = turntable.model, turntable.model.createData()
    mass = sum(model.inertias[j].mass for j in range(1, model.njoints))

    def axial_momentum(q, v):
        pin.computeCentroidalMomentum(model, data, q, v)  # at the centre of mass, world axes
        c, h = data.com[0], data.hg
        return float((h.angular + np.cross(c - AXIS_POINT, mass * data.vcom[0]))[2])

    L = np.array([axial_momentum(q, v) for q, v in zip(traj.q, traj.v, strict=True)])
    assert abs(L[0]) > 0.1  # [kg m^2/s]: a real spin
    assert np.max(np.abs(L - L[0])) / abs(L[0]) <= TOL_MOMENTUM


def test_assembly_at_random_turntable_poses_closes_every_row(turntable, rng):
    """Random turntable angles, 4-bar near the crossed branch: every declared row closes."""
    for _ in range(50):
        q = np.r_[rng.uniform(-np.pi, np.pi), np.radians(CROSSED_GUESS_DEG)]
        q[1:] += rng.uniform(-0.05, 0.05, 3)
        q = cc.assemble(turntable, q, fixed=["turntable_joint", "crank_joint"])
        phi, _, _ = _declared(turntable, q)
        assert np.max(np.abs(phi)) <= cc.AssemblySettings().tol
