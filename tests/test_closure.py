"""Tests of closedchain.closure: row selection over the motion and every-declared-row checks.

References: the rank of the declared Jacobian computed here by SVD at fresh random
states (not the load-time samples), the cut frames' geometry (a flipped closure is
built by turning one distal joint by pi), and the declared rows evaluated directly.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR

import closedchain as cc
from closedchain.constraints import ROW_ROTATION, ROW_TRANSLATION
from closedchain.kinematics import solve_closure

OFF_CENTRE_WRIST = DATA_DIR / "off_centre_wrist.urdf"
#: Random orientations of the issue's report and the distance of the guesses [rad].
N_ORIENTATIONS = 200
GUESS_DISTANCE = 0.05
#: Relative threshold of the numerical rank.
RANK_RTOL = 1e-8
#: Cut-frame offset of tests/data/off_centre_wrist.urdf along the loop axes [m].
WRIST_CUT_OFFSET = 0.1


@pytest.fixture(scope="module")
def wrist() -> cc.Mechanism:
    return cc.load(OFF_CENTRE_WRIST)


def declared_phi(mech, q):
    pin.forwardKinematics(mech.model, mech.data, q)
    phi = np.zeros(mech.declared.nc)
    mech.declared.evaluate(mech.model, mech.data, phi=phi)
    return phi


def declared_jacobian(mech, q):
    pin.computeJointJacobians(mech.model, mech.data, q)
    J = np.zeros((mech.declared.nc, mech.nv))
    mech.declared.evaluate(mech.model, mech.data, J=J)
    return J


def rank(J):
    s = np.linalg.svd(J, compute_uv=False)
    return int(np.sum(s > RANK_RTOL * max(1.0, s[0])))


def test_off_centre_wrist_assembles_with_every_declared_row_closed(wrist, rng):
    """Issue 8: 200 random orientations, guesses 0.05 rad away; with world rows kept at one
    pose 6 of them assembled with declared rows open by up to 5e-2."""
    tol = cc.AssemblySettings().tol
    worst = 0.0
    for _ in range(N_ORIENTATIONS):
        q_true, _ = cc.random_consistent_state(wrist, rng)
        step = rng.standard_normal(wrist.nv)
        guess = pin.integrate(wrist.model, q_true, GUESS_DISTANCE * step / np.linalg.norm(step))
        q = cc.assemble(wrist, guess)  # raises rather than return an open loop
        worst = max(worst, float(np.max(np.abs(declared_phi(wrist, q)))))
        pin.forwardKinematics(wrist.model, wrist.data, q)
        assert wrist.declared.misaligned_loops(wrist.model, wrist.data) == []
    assert worst <= tol


def test_off_centre_wrist_rank_is_two_per_leg_everywhere(wrist, rng):
    assert wrist.row_selection.rank == 6
    assert wrist.nc == 6 and wrist.declared.nc == 15
    for _ in range(20):
        q, _ = cc.random_consistent_state(wrist, rng)
        J = declared_jacobian(wrist, q)
        assert rank(J) == 6
        assert rank(J[list(wrist.selected_rows)]) == 6


def test_flipped_closure_is_caught_by_the_dropped_rows(wrist, rng):
    """Turning distal joint 1 by pi flips leg 1's axis: the kept rotation rows vanish,
    the dropped translation row along the axis is open by twice the offset."""
    q, _ = cc.random_consistent_state(wrist, rng)
    jm = wrist.model.joints[wrist.model.getJointId("distal_joint_1")]
    q_flip = q.copy()
    q_flip[jm.idx_q] += np.pi
    assert np.max(np.abs(cc.compute_phi(wrist, q_flip))) <= 1e-14  # kept rows: "closed"
    phi = declared_phi(wrist, q_flip)
    labels = [r.label for r in wrist.declared.declared_rows]
    assert abs(phi[labels.index("leg1_platform.ta")]) == pytest.approx(2 * WRIST_CUT_OFFSET)
    with pytest.raises(
        cc.LoopClosureError,
        match=r"off_centre_wrist at t = 1\.5 s: loop row leg1_platform\.ta is open by 2\.000e-01",
    ):
        wrist.closure.check_rows(wrist.model, wrist.data, q_flip, t=1.5)
    # The selection is unchanged by the failed check.
    assert all(lb.endswith(("r1", "r2")) for lb in wrist.row_selection.kept)


def test_assembly_from_a_flipped_guess_never_returns_a_flipped_closure(wrist, rng):
    for _ in range(5):
        q, _ = cc.random_consistent_state(wrist, rng)
        jm = wrist.model.joints[wrist.model.getJointId("distal_joint_1")]
        q[jm.idx_q] += np.pi
        try:
            q_new = cc.assemble(wrist, q)
        except cc.AssemblyError:
            continue
        assert np.max(np.abs(declared_phi(wrist, q_new))) <= cc.AssemblySettings().tol
        pin.forwardKinematics(wrist.model, wrist.data, q_new)
        assert wrist.declared.misaligned_loops(wrist.model, wrist.data) == []


def test_simulation_reselects_a_degenerate_kept_set(mechanism_files):
    """Force a kept set of rank 1 (t1 and the identically zero ta): the run re-selects."""
    mech = cc.load(mechanism_files["fourbar"])
    labels = [r.label for r in mech.declared.declared_rows]
    mech.closure.active = mech.declared.restricted([labels.index("C.t1"), labels.index("C.ta")])
    q0 = cc.assemble(mech, np.radians((10.0, -65.0, -104.0)), fixed=["crank_joint"])
    # kkt + DOP853: a configuration that checks the kept rows' rank (the default,
    # singular-robust, passes rank loss through and catches the open t2 a step later).
    traj = cc.simulate(mech, q0, np.zeros(3), 0.5, method="kkt", integrator="DOP853")
    (event,) = traj.info.row_reselections
    assert event[0] == 0.0 and event[1] == ("C.t1", "C.t2")
    assert "kept rows degenerate" in event[2]
    assert traj.max_constraint_residual <= 1e-9


def test_open_dropped_row_triggers_reselection(mechanism_files):
    """Kept (t1, ta) and a configuration with t1 = 0 but t2 open: re-selected to (t1, t2)."""
    mech = cc.load(mechanism_files["fourbar"])
    labels = [r.label for r in mech.declared.declared_rows]
    mech.closure.active = mech.declared.restricted([labels.index("C.t1"), labels.index("C.ta")])
    q = np.radians([10.0, -65.0, -80.0])  # rocker 24 deg off the crossed assembly
    # Close t1 alone by moving the coupler (the row's own Newton), leaving t2 open.
    q = solve_closure(
        mech.model,
        mech.data,
        mech.declared.restricted([labels.index("C.t1")]),
        q,
        np.array([1]),
        cc.AssemblySettings(),
    )
    phi = declared_phi(mech, q)
    assert abs(phi[labels.index("C.t1")]) <= 1e-12 and abs(phi[labels.index("C.t2")]) > 1e-2
    assert mech.closure.check_rows(mech.model, mech.data, q, t=0.25) is True
    assert mech.row_selection.kept == ("C.t1", "C.t2")
    assert "dropped row C.t2 open" in mech.row_selection.reason


@pytest.mark.parametrize("name", ["fourbar", "agile_eye", "turntable_fourbar", "fixed_branches"])
def test_row_table_describes_the_kept_rows(load_mechanism, rng, name):
    """The per-row table (what a compiled evaluator reads) reproduces phi row by row."""
    mech = load_mechanism(name)
    table = mech.constraints.row_table()
    assert table.labels == tuple(r.label for r in mech.rows)
    for _ in range(5):
        q = mech.random_configuration(rng)
        pin.framesForwardKinematics(mech.model, mech.data, q)
        phi = np.empty(mech.nc)
        for i in range(mech.nc):
            oMp = mech.data.oMf[int(table.frame_p[i])]
            oMs = mech.data.oMf[int(table.frame_s[i])]
            U = oMp.rotation @ table.u[i]
            if table.function[i] == ROW_TRANSLATION:
                phi[i] = U @ (oMp.translation - oMs.translation)
            else:
                assert table.function[i] == ROW_ROTATION
                phi[i] = U @ (oMs.rotation @ table.w[i])
        assert np.linalg.norm(phi - cc.compute_phi(mech, q)) <= 1e-14


#: The 4-bar with pin C in the tree and a fixed loop (tests/data/fourbar_fixed_loop.urdf).
FIXED_LOOP_FOURBAR = DATA_DIR / "fourbar_fixed_loop.urdf"
#: Agreement of the two 4-bar formulations' joint angles over the run [rad].
TOL_SAME_MOTION = 1e-9
SAME_MOTION_CONFIG = dict(integrator="DOP853", rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("method", ["kkt", "nullspace", "reduced"])
def test_fixed_loop_gives_the_motion_of_the_revolute_loop(fourbar, method):
    """Pin C in the tree (massless pin link) welded to the rocker by a fixed loop: 6 declared
    rows, 3 independent (planar), the same motion as the revolute loop C. (Methods that
    invert M, schur and pinocchio, refuse the massless pin link.)"""
    welded = cc.load(FIXED_LOOP_FOURBAR)
    assert (welded.declared.nc, welded.nc, welded.mobility) == (6, 3, 1)
    q = cc.assemble(fourbar, np.radians((10.0, -65.0, -104.0)), fixed=["crank_joint"])
    # The pin's angle is the rocker's absolute angle minus the coupler's.
    guess = np.r_[q[0], q[1], q[2] - (q[0] + q[1]), q[2]]
    q_welded = cc.assemble(welded, guess, fixed=["crank_joint"])
    t_eval = np.linspace(0.0, 2.0, 41)
    a = cc.simulate(
        fourbar, q, np.zeros(3), 2.0, t_eval=t_eval, method=method, **SAME_MOTION_CONFIG
    )
    b = cc.simulate(
        welded, q_welded, np.zeros(4), 2.0, t_eval=t_eval, method=method, **SAME_MOTION_CONFIG
    )
    same = [welded.coordinate_names.index(n) for n in fourbar.coordinate_names]
    assert np.ptp(a.q[:, 0]) > 0.5  # it swings [rad]
    assert np.max(np.abs(a.q - b.q[:, same])) <= TOL_SAME_MOTION
    assert b.max_constraint_residual <= 1e-9  # all six welded rows


#: The greedy row choice's smallest singular values against one SVD per candidate set,
#: relative to the largest singular value of the stacked rows (round-off of two SVDs).
SIGMA_MIN_TOL = 1e-13


@pytest.mark.parametrize("case", ["generic", "near-dependent", "dependent", "tiny", "ill"])
def test_sigma_min_with_each_row_matches_an_svd_per_candidate(rng, case):
    """closure._sigma_min_with_each_row (secular equation of the arrowhead matrix) gives
    the smallest singular value of [B; a] for every candidate row a, as scipy's SVD of
    each stacked matrix does, also where a row is (nearly) dependent on B."""
    import scipy.linalg

    from closedchain.closure import _sigma_min_with_each_row

    for _ in range(40):
        n = int(rng.integers(3, 12))
        k = int(rng.integers(1, n))
        m = int(rng.integers(1, 6))
        samples = int(rng.integers(1, 4))
        B = rng.standard_normal((samples, k, n))
        A = rng.standard_normal((samples, m, n))
        if case == "near-dependent":
            A[:, 0] = 2.0 * B[:, 0] + 1e-9 * rng.standard_normal(n)
        elif case == "dependent":
            A[:, 0] = B[:, -1]
        elif case == "tiny":
            A *= 1e-6
        elif case == "ill" and k > 1:
            B[:, 1] = B[:, 0] * (1.0 + 1e-7)
        got = _sigma_min_with_each_row(B, A)
        for s in range(samples):
            for i in range(m):
                stacked = np.vstack([B[s], A[s, i]])
                ref = scipy.linalg.svdvals(stacked)[-1]
                scale = scipy.linalg.svdvals(stacked)[0]
                assert abs(got[s, i] - ref) <= SIGMA_MIN_TOL * scale
