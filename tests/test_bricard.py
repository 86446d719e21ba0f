"""Bricard's overconstrained 6R linkage (models/bricard.urdf, IFToMM benchmark A04).

Grübler-Kutzbach counts 6 (6 - 1) - 6 x 5 = 0 degrees of freedom; the linkage moves
with one. References: the numerical rank of the declared Jacobian computed here by
SVD along a simulated motion; the benchmark's geometry, rod centres and gravity as
two independent implementations of A04 write them (the OpenSim model of
RehabEngGroup/MBSbenchmarksInOpenSim and S. Acuna's simEngine3D driver, both in the
benchmark's frame B with gravity along -y_B); energy conservation.
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
#: The joints at q = 0 in the benchmark's frame B [m]: P0 ... P5 (createModel.cpp of
#: MBSbenchmarksInOpenSim / simEngine3D_BricardMechanism.m).
BENCHMARK_POINTS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, -1, 0], [1, -1, 1], [0, -1, 1], [0, 0, 1]], dtype=float
)
#: Joint axes at P0 ... P5 in B (up to sign).
BENCHMARK_AXES = np.array(
    [[0, 1, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=float
)
#: Rod centres of mass in B [m], rods 1 ... 5 (simEngine3D's r_link of links 1 ... 5).
BENCHMARK_CENTRES = np.array(
    [[0.5, 0, 0], [1, -0.5, 0], [1, -1, 0.5], [0.5, -1, 1], [0, -0.5, 1]], dtype=float
)
#: Benchmark gravity in B [m/s^2].
BENCHMARK_GRAVITY = np.array([0.0, -9.81, 0.0])
#: World from B: Rx(+90 deg) (URDF header), so that -y_B is the world's -z.
R_WORLD_B = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
#: Round-off of the placements built from the URDF's rpy = pi/2 [m or -].
TOL_GEOMETRY = 1e-15
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


def test_geometry_is_the_benchmark_loop(bricard):
    """At q = 0 the joints sit on the benchmark's points with its axes, the rods' centres
    of mass where A04 puts them, rods of 1 m and 1 kg, the loop closed (all in B)."""
    model, data = bricard.model, bricard.data
    q0 = pin.neutral(model)
    pin.framesForwardKinematics(model, data, q0)
    frames = [data.oMi[model.getJointId(j)] for j in ("j0", "j1", "j2")]
    frames.append(data.oMf[model.getFrameId("j3::predecessor")])
    frames += [data.oMi[model.getJointId(j)] for j in ("j4", "j5")]
    points_b = np.array([R_WORLD_B.T @ f.translation for f in frames])
    assert np.max(np.abs(points_b - BENCHMARK_POINTS)) <= TOL_GEOMETRY
    axes = [model.joints[model.getJointId(j)].shortname()[-1] for j in ("j0", "j1", "j2")]
    axes.append("Y")  # the loop's axis, <axis xyz="0 1 0"> in rod3's frame
    axes += [model.joints[model.getJointId(j)].shortname()[-1] for j in ("j4", "j5")]
    for f, letter, expected in zip(frames, axes, BENCHMARK_AXES, strict=True):
        axis_b = R_WORLD_B.T @ f.rotation[:, "XYZ".index(letter)]
        assert np.max(np.abs(np.abs(axis_b) - expected)) <= TOL_GEOMETRY
    centres_b = [
        R_WORLD_B.T @ data.oMi[model.getJointId(j)].act(model.inertias[model.getJointId(j)].lever)
        for j in ("j0", "j1", "j2", "j4", "j5")
    ]
    # j0 .. j2 carry rods 1 .. 3, j4 rod 4 and j5 rod 5.
    assert np.max(np.abs(np.array(centres_b) - BENCHMARK_CENTRES)) <= TOL_GEOMETRY
    assert [model.inertias[i].mass for i in range(1, model.njoints)] == [1.0] * 5
    lengths = np.linalg.norm(
        np.diff(np.vstack([BENCHMARK_POINTS, BENCHMARK_POINTS[:1]]), axis=0), axis=1
    )
    assert np.allclose(lengths, ROD_LENGTH, rtol=0, atol=TOL_GEOMETRY)
    assert np.max(np.abs(cc.compute_phi(bricard, q0))) <= TOL_GEOMETRY


def test_gravity_is_the_benchmarks_minus_y(bricard):
    """closedchain's world gravity seen in B is A04's (0, -9.81, 0)."""
    assert np.max(np.abs(R_WORLD_B.T @ bricard.gravity - BENCHMARK_GRAVITY)) <= TOL_GEOMETRY


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


#: Starts drawn around q = 0 for the assembly test: count and spread [rad].
N_ASSEMBLY_STARTS = 50
ASSEMBLY_SPREAD = 0.1


def test_assembles_from_starts_near_the_motion(bricard):
    """Off the motion J has 5 independent rows, one with a singular value of the order
    of the distance to it: the full Gauss-Newton step along it used to overshoot (18 of
    100 starts 0.1 rad away failed). Every start converges onto phi = 0, every row."""
    rng = np.random.default_rng(8)
    for _ in range(N_ASSEMBLY_STARTS):
        guess = bricard.q_ref + ASSEMBLY_SPREAD * rng.standard_normal(bricard.nv)
        q = cc.assemble(bricard, guess)
        declared = np.zeros(bricard.declared.nc)
        pin.forwardKinematics(bricard.model, bricard.data, q)
        bricard.declared.evaluate(bricard.model, bricard.data, phi=declared)
        assert np.max(np.abs(declared)) <= cc.AssemblySettings().tol
