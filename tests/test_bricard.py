"""Bricard's overconstrained 6R linkage (models/bricard.urdf, IFToMM benchmark A04).

Grübler-Kutzbach counts 6 (6 - 1) - 6 x 5 = 0 degrees of freedom; the linkage moves
with one. References: the numerical rank of the declared Jacobian computed here by
SVD along a simulated motion, the cube-edge geometry stated in the URDF header (the
rods' end points), and energy conservation.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import closedchain as cc

#: Relative threshold of the numerical rank.
RANK_RTOL = 1e-8
#: 10 s from rest under gravity, DOP853 at tight tolerances, no stabilization.
T_FINAL = 10.0
CONFIG = dict(integrator="DOP853", rtol=1e-12, atol=1e-12)
TOL_ENERGY = 1e-9
TOL_ROWS = 1e-9
#: The joints on the unit cube's edges at q = 0 [m] (URDF header): P0 ... P5.
CUBE_POINTS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1], [0, 1, 1], [0, 0, 1]], dtype=float
)
#: Rod lengths [m].
ROD_LENGTH = 1.0


@pytest.fixture(scope="module")
def bricard(load_mechanism) -> cc.Mechanism:
    return load_mechanism("bricard")


@pytest.fixture(scope="module")
def fall(bricard) -> cc.Trajectory:
    q0 = pin.neutral(bricard.model)
    return cc.simulate(bricard, q0, np.zeros(bricard.nv), T_FINAL, **CONFIG)


def declared_jacobian(mech, q):
    pin.computeJointJacobians(mech.model, mech.data, q)
    J = np.zeros((mech.declared.nc, mech.nv))
    mech.declared.evaluate(mech.model, mech.data, J=J)
    return J


def rank(J):
    s = np.linalg.svd(J, compute_uv=False)
    return int(np.sum(s > RANK_RTOL * max(1.0, s[0])))


def test_geometry_is_the_cube_edge_loop(bricard):
    """At q = 0 the joint frames sit on the cube's vertices, rods of 1 m, the loop closed."""
    model, data = bricard.model, bricard.data
    q0 = pin.neutral(model)
    pin.framesForwardKinematics(model, data, q0)
    points = [data.oMi[model.getJointId(j)].translation for j in ("j0", "j1", "j2")]
    points.append(data.oMf[model.getFrameId("j3::predecessor")].translation)
    points += [data.oMi[model.getJointId(j)].translation for j in ("j4", "j5")]
    assert np.linalg.norm(np.array(points) - CUBE_POINTS) <= 1e-15
    lengths = np.linalg.norm(np.diff(np.vstack([CUBE_POINTS, CUBE_POINTS[:1]]), axis=0), axis=1)
    assert np.allclose(lengths, ROD_LENGTH, rtol=0, atol=1e-15)
    assert np.max(np.abs(cc.compute_phi(bricard, q0))) <= 1e-15


def test_four_of_five_rows_independent(bricard):
    """The layer finds the redundancy itself: 5 declared rows, generic rank 4, mobility 1."""
    assert bricard.declared.nc == 5
    assert bricard.nc == 4 and bricard.row_selection.rank == 4
    assert bricard.mobility == 1
    assert len(bricard.row_selection.dropped) == 1


def test_rank_stays_four_along_the_motion(bricard, fall):
    for q in fall.q[:: max(1, len(fall.t) // 50)]:
        J = declared_jacobian(bricard, q)
        assert rank(J) == 4
        assert rank(J[list(bricard.selected_rows)]) == 4


def test_falls_for_ten_seconds_conserving_energy(bricard, fall):
    assert fall.t[-1] == pytest.approx(T_FINAL)
    assert np.ptp(fall.q[:, 0]) > 1.0  # a large motion [rad], not a rest state
    assert fall.energy_drift <= TOL_ENERGY
    assert fall.max_constraint_residual <= TOL_ROWS  # every declared row
    assert fall.info.row_reselections == ()
