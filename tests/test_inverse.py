"""Inverse dynamics and loop-joint reactions.

The 4-bar's static equilibrium is computed by hand here (free-body diagrams of
the rocker and the coupler, link data from the header of models/fourbar.urdf)
and compared with the crank torque from :func:`inverse_dynamics` and the pin
force at C from :func:`joint_reactions`; the reaction is also compared with
Pinocchio's own contact forces. Round trips forward(inverse(...)) recover the
motion on both models.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import closedchain as cc
from closedchain.dynamics import METHODS, SolverSettings, forward_dynamics
from closedchain.inverse import (
    InverseDynamicsResult,
    JointReaction,
    LoopReaction,
    inverse_dynamics,
    joint_reactions,
)
from closedchain.validation import pinocchio_forward_dynamics

MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
MODEL_NAMES = ("fourbar", "agile_eye")
#: The compiled core where it is built ("auto"), and the numpy reference.
BACKENDS = ("auto", "numpy")
SEED = 20251121
N_STATES = 30
#: Round trip: |a_forward - a_inverse|_2 <= TOL_ROUND_TRIP max(1, |a|) [rad/s^2].
TOL_ROUND_TRIP = 1e-9
#: Methods that form the Delassus matrix D = J M^-1 J^T and solve with it: their
#: round-off grows as eps cond(D) (cond(J) squared), so near a singular position
#: the round trip is judged against DELASSUS_ROUNDOFF eps cond(D) where that is
#: larger than TOL_ROUND_TRIP. Measured: 1.9 eps cond(D) (schur, agile_eye,
#: cond(D) 3.9e6, OpenBLAS Haswell kernel).
DELASSUS_METHODS = frozenset({"schur", "proximal", "pinocchio"})
DELASSUS_ROUNDOFF = 10.0
#: Hand computation vs code, statics of the 4-bar [N, N m].
TOL_STATICS = 1e-10
#: Our reaction vs Pinocchio's contact forces (its proximal solve, mu = 1e-8) [N].
TOL_PINOCCHIO_FORCE = 1e-8
#: Residuals reported by inverse_dynamics.
TOL_RESIDUAL = 1e-10
#: Agile Eye states for platform tracking must keep the legs' block of J
#: (the coordinates not prescribed) at most this ill-conditioned: random
#: assembly also lands on the branch where every leg is folded onto its
#: actuator axis (distal joints at +-90 deg), where the platform angles do not
#: determine the legs.
COND_JF_MAX = 1e6

PLATFORM = ("platform_yaw", "platform_pitch", "platform_roll")

# 4-bar data (models/fourbar.urdf header): lengths [m], 1 kg uniform rods, g [m/s^2].
A_LEN, B_LEN, C_LEN, D_LEN = 0.2, 0.4, 0.3, 0.5
MASS = 1.0
G = 9.81


@pytest.fixture(scope="module")
def mechs() -> dict[str, cc.Mechanism]:
    """The two models, loaded once for this module."""
    return {name: cc.load(MODELS_DIR / f"{name}.urdf") for name in MODEL_NAMES}


def rel_err(x: np.ndarray, ref: np.ndarray) -> float:
    """Return |x - ref|_2 / max(1, |ref|_2)."""
    return float(np.linalg.norm(x - ref) / max(1.0, np.linalg.norm(ref)))


# -- the 4-bar's statics by hand -----------------------------------------------------------


def cross2(r: np.ndarray, f: np.ndarray) -> float:
    """Moment [N m] of force f at lever r, both in the (x, z) plane, about the joints' axis.

    The joint axes are -y, so a positive angle turns x towards z and the
    moment about -y is r_x f_z - r_z f_x.
    """
    return float(r[0] * f[1] - r[1] * f[0])


def fourbar_statics_by_hand(q: np.ndarray) -> tuple[float, np.ndarray]:
    """Return (crank torque [N m], force of the coupler on the rocker at C [N], (x, z)).

    Free bodies, weights m g at the rod midpoints, pins frictionless:

    * rocker (pivot D): moment about D of the pin force f_C and its weight is zero;
    * coupler (pins B, C): the rocker pushes back with -f_C at C; moment about B zero;
      force balance gives the crank's pin force on it, f_B = f_C - m g;
    * crank (pivot A): tau - moment about A of f_B (the coupler pushes back with
      -f_B at B) plus its weight moment is zero.
    """
    th2, th3, th4 = q[0], q[0] + q[1], q[2]  # absolute angles (URDF header map)
    e = lambda th: np.array([np.cos(th), np.sin(th)])  # noqa: E731
    A = np.zeros(2)
    D = np.array([D_LEN, 0.0])
    B = A + A_LEN * e(th2)
    C = D + C_LEN * e(th4)
    np.testing.assert_allclose(B + B_LEN * e(th3), C, atol=1e-12)  # assembled
    w = np.array([0.0, -MASS * G])
    G_crank, G_coupler, G_rocker = (A + B) / 2, (B + C) / 2, (D + C) / 2
    # Unknown f_C = (fx, fz):  cross2(r, f) = r_x f_z - r_z f_x = [-r_z, r_x] . f
    row = lambda r: np.array([-r[1], r[0]])  # noqa: E731
    K = np.array([row(C - D), -row(C - B)])
    rhs = -np.array([cross2(G_rocker - D, w), cross2(G_coupler - B, w)])
    f_C = np.linalg.solve(K, rhs)
    f_B = f_C - w
    tau = cross2(B - A, f_B) - cross2(G_crank - A, w)
    return tau, f_C


CRANK_ANGLES = (0.3, 1.2, 2.0, 4.0, 5.5)


@pytest.mark.parametrize("theta2", CRANK_ANGLES)
def test_fourbar_static_equilibrium_by_hand(mechs, theta2):
    mech = mechs["fourbar"]
    q = cc.assemble(mech, np.array([theta2, 0.6, 1.6]), fixed=["crank_joint"])
    v = np.zeros(mech.nv)
    res = inverse_dynamics(mech, q, v, [0.0])
    tau_hand, f_C_hand = fourbar_statics_by_hand(q)
    assert res.tau[0] == pytest.approx(tau_hand, abs=TOL_STATICS)
    np.testing.assert_array_equal(res.tau[1:], 0.0)
    np.testing.assert_allclose(res.a, 0.0, atol=TOL_STATICS)
    # The torque holds the linkage still: forward dynamics gives a = 0.
    np.testing.assert_allclose(forward_dynamics(mech, q, v, res.tau).a, 0.0, atol=1e-9)

    (rx,) = joint_reactions(mech, q, v, res)
    assert isinstance(rx, LoopReaction)
    assert (rx.loop, rx.type, rx.frame) == ("C", "revolute", "C::predecessor")
    # force on the rocker (successor) in the world x-z plane
    assert np.linalg.norm(rx.force_world[[0, 2]] - f_C_hand) <= TOL_STATICS
    assert abs(rx.force_world[1]) <= TOL_STATICS
    # a revolute pin about the axis transmits no couple (and the planar loop none at all)
    assert np.linalg.norm(rx.torque) <= TOL_STATICS
    # components in c1 are the world ones rotated by the coupler's orientation
    oMc1 = pin.updateFramePlacement(mech.model, mech.data, mech.model.getFrameId("C::predecessor"))
    np.testing.assert_allclose(oMc1.rotation @ rx.force, rx.force_world, atol=1e-14)
    # in c1 (coupler frame, x along the coupler) the force is rotated by -theta3
    th3 = q[0] + q[1]
    c, s = np.cos(th3), np.sin(th3)
    fx, fz = f_C_hand
    np.testing.assert_allclose(
        rx.force[[0, 2]], [c * fx + s * fz, -s * fx + c * fz], atol=TOL_STATICS
    )


@pytest.mark.parametrize("theta2", CRANK_ANGLES)
def test_fourbar_tree_joint_reactions_by_hand(mechs, theta2):
    """The pin forces at A, B and D from the free bodies of the static 4-bar: the crank
    pushes the coupler at B with f_B = f_C - m g (coupler balance), the ground holds the
    crank at A with f_B - m g and the rocker at D with -f_C - m g; each pin carries the
    couple tau about its axis (-y) only."""
    mech = mechs["fourbar"]
    q = cc.assemble(mech, np.array([theta2, 0.6, 1.6]), fixed=["crank_joint"])
    v = np.zeros(mech.nv)
    res = inverse_dynamics(mech, q, v, [0.0])
    loop, *tree = joint_reactions(mech, q, v, res, tree=True)
    assert isinstance(loop, LoopReaction) and loop.loop == "C"
    assert all(isinstance(r, JointReaction) for r in tree)
    assert [r.joint for r in tree] == ["crank_joint", "coupler_joint", "rocker_joint"]
    _, f_C = fourbar_statics_by_hand(q)
    w = np.array([0.0, -MASS * G])
    f_B = f_C - w
    hand = {"crank_joint": f_B - w, "coupler_joint": f_B, "rocker_joint": -f_C - w}
    for r, tau in zip(tree, res.tau, strict=True):
        assert np.linalg.norm(r.force_world[[0, 2]] - hand[r.joint]) <= TOL_STATICS
        assert abs(r.force_world[1]) <= TOL_STATICS
        assert np.linalg.norm(r.torque_world - [0.0, -tau, 0.0]) <= TOL_STATICS
        assert r.tau == pytest.approx([tau], abs=TOL_STATICS)
        oMj = mech.data.oMi[mech.model.getJointId(r.joint)]
        np.testing.assert_allclose(oMj.rotation @ r.force, r.force_world, atol=1e-14)


#: tests/data/slider_crank_tree.urdf: crank and rod lengths [m], rod and slider masses [kg].
SLIDER_CRANK_R, SLIDER_CRANK_L = 0.1, 0.3
ROD_MASS, SLIDER_MASS = 0.7, 0.9


@pytest.mark.parametrize("theta", CRANK_ANGLES)
def test_slider_normal_force_by_hand(theta):
    """A slider on a tree prismatic joint, held still by the crank: its free body (passive
    guide along x: no force along it; the rod pinned at its origin) and the rod's moment
    balance about the crank tip B give the rod's push on the slider -m_rod g / 2 (z) and
    the guide's normal force N = (m_slider + m_rod / 2) g, whatever the crank angle."""
    mech = cc.load(Path(__file__).parent / "data" / "slider_crank_tree.urdf")
    r, l_ = SLIDER_CRANK_R, SLIDER_CRANK_L
    B = r * np.array([np.cos(theta), np.sin(theta)])
    s = B[0] + np.sqrt(l_**2 - B[1] ** 2)  # the slider on the x axis at distance l from B
    phi = np.arctan2(-B[1], s - B[0]) - theta
    q = cc.assemble(mech, np.array([theta, phi, s]), fixed=["crank_joint"])
    np.testing.assert_allclose(q, [theta, phi, s], atol=1e-12)  # the hand geometry
    v = np.zeros(mech.nv)
    res = inverse_dynamics(mech, q, v, [0.0])
    loop, *tree = joint_reactions(mech, q, v, res, tree=True)
    slider = next(r for r in tree if r.joint == "slider_joint")
    normal = (SLIDER_MASS + ROD_MASS / 2) * G
    assert np.linalg.norm(slider.force_world - [0.0, 0.0, normal]) <= TOL_STATICS
    assert np.linalg.norm(slider.torque_world) <= TOL_STATICS
    assert abs(slider.tau[0]) <= TOL_STATICS  # passive: nothing along the guide
    # the rod's push on the slider (the loop's successor)
    assert np.linalg.norm(loop.force_world - [0.0, 0.0, -ROD_MASS * G / 2]) <= TOL_STATICS


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_ground_reactions_move_the_centre_of_mass(mechs, states, name):
    """Newton's law for the whole mechanism (the loop forces are internal): the forces the
    ground transmits through its joints sum to m_total (a_com - g), a_com from Pinocchio's
    centre-of-mass kinematics; each joint's motion-subspace component is its tau."""
    mech = mechs[name]
    model = mech.model
    for q, v, a_ind in states[name][:5]:
        inv = inverse_dynamics(mech, q, v, a_ind)
        tree = [
            r for r in joint_reactions(mech, q, v, inv, tree=True) if isinstance(r, JointReaction)
        ]
        ground = sum(r.force_world for r in tree if model.parents[model.getJointId(r.joint)] == 0)
        data = model.createData()
        pin.centerOfMass(model, data, q, v, inv.a)
        newton = pin.computeTotalMass(model) * (data.acom[0] - model.gravity.linear)
        assert np.linalg.norm(ground - newton) <= TOL_ROUND_TRIP * max(1.0, np.linalg.norm(newton))
        np.testing.assert_allclose(
            np.concatenate([r.tau for r in tree]), inv.tau, rtol=0, atol=TOL_ROUND_TRIP
        )


def test_tree_reactions_need_the_accelerations(mechs):
    mech = mechs["fourbar"]
    with pytest.raises(cc.ClosedChainError, match=r"tree=True\) needs the accelerations"):
        joint_reactions(mech, mech.q_ref, np.zeros(3), np.zeros(mech.nc), tree=True)


@pytest.mark.parametrize("theta2", CRANK_ANGLES)
def test_fourbar_reaction_matches_pinocchio(mechs, theta2):
    """Pinocchio's contact forces at C (two CONTACT_3D points on the axis) sum to our pin force."""
    mech = mechs["fourbar"]
    q = cc.assemble(mech, np.array([theta2, 0.6, 1.6]), fixed=["crank_joint"])
    v = np.zeros(mech.nv)
    res = inverse_dynamics(mech, q, v, [0.0])
    (rx,) = joint_reactions(mech, q, v, res)

    # (1) Pinocchio's lambda_c: the force on the predecessor (joint1 side), in c1.
    cms, cds, owners, data = mech.pinocchio_constraints()
    prox = pin.ProximalSettings(1e-13, 0.0, SolverSettings().pinocchio_mu, 50)
    a_pin = pin.constraintDynamics(mech.model, data, q, v, res.tau, cms, cds, prox)
    np.testing.assert_allclose(a_pin, 0.0, atol=1e-9)
    assert owners == ["C", "C"]
    f_pred = data.lambda_c.reshape(-1, 3).sum(axis=0)
    assert np.linalg.norm(rx.force + f_pred) <= TOL_PINOCCHIO_FORCE

    # (2) Pinocchio's generalized constraint force J^T lam -> our multipliers -> wrench.
    _, f_gen = pinocchio_forward_dynamics(mech, q, v, res.tau, SolverSettings())
    lam = np.linalg.lstsq(res.J.T, f_gen, rcond=None)[0]
    (rx_pin,) = joint_reactions(mech, q, v, lam)
    assert np.linalg.norm(rx_pin.force - rx.force) <= TOL_PINOCCHIO_FORCE
    assert np.linalg.norm(rx_pin.torque - rx.torque) <= TOL_PINOCCHIO_FORCE


# -- round trips -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def states(mechs):
    """Per model: N_STATES (q, v, a_independent), regular consistent states."""
    out = {}
    for name, mech in mechs.items():
        rng = np.random.default_rng(SEED)
        out[name] = []
        for _ in range(N_STATES):
            q, v = cc.random_consistent_state(mech, rng)
            out[name].append((q, v, 5.0 * rng.standard_normal(mech.mobility)))
    return out


def round_trip_bound(mech, q: np.ndarray, method: str) -> float:
    """Return the round trip's error bound at q for method (see DELASSUS_ROUNDOFF)."""
    if method not in DELASSUS_METHODS:
        return TOL_ROUND_TRIP
    data = mech.model.createData()
    M = pin.crba(mech.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T  # crba fills the upper triangle
    J = cc.compute_jacobian(mech, q, backend="numpy")
    D = J @ np.linalg.solve(M, J.T)
    return max(TOL_ROUND_TRIP, DELASSUS_ROUNDOFF * np.finfo(float).eps * np.linalg.cond(D))


@pytest.mark.parametrize("method", sorted(METHODS))
@pytest.mark.parametrize("model", MODEL_NAMES)
def test_round_trip(mechs, states, model, method):
    mech = mechs[model]
    worst_a = worst_lam = 0.0  # errors divided by their bound
    for q, v, a_ind in states[model]:
        inv = inverse_dynamics(mech, q, v, a_ind)
        bound = round_trip_bound(mech, q, method)
        assert isinstance(inv, InverseDynamicsResult)
        assert inv.dynamics_residual <= TOL_RESIDUAL * max(1.0, np.abs(inv.tau).max())
        assert inv.constraint_residual <= TOL_RESIDUAL * max(1.0, np.abs(inv.gamma).max())
        off = np.setdiff1d(np.arange(mech.nv), mech.actuated_idx_v)
        np.testing.assert_array_equal(inv.tau[off], 0.0)
        np.testing.assert_array_equal(inv.a[mech.independent_idx_v], a_ind)
        fwd = forward_dynamics(mech, q, v, inv.tau, method=method)
        worst_a = max(worst_a, rel_err(fwd.a, inv.a) / bound)
        worst_lam = max(
            worst_lam,
            rel_err(fwd.generalized_constraint_force(), inv.generalized_constraint_force()) / bound,
        )
    assert worst_a <= 1.0, f"{method}: round trip a error {worst_a:.2f} x its bound"
    assert worst_lam <= 1.0, f"{method}: round trip J^T lam error {worst_lam:.2f} x its bound"


def well_posed_platform_states(mech, rng, n):
    """Draw n consistent states where the platform angles determine the legs."""
    P = mech.coordinate_indices(list(PLATFORM))
    F = np.setdiff1d(np.arange(mech.nv), P)
    out = []
    while len(out) < n:
        q, v = cc.random_consistent_state(mech, rng)
        if np.linalg.cond(cc.compute_jacobian(mech, q)[:, F]) < COND_JF_MAX:
            out.append((q, v))
    return out


def test_agile_eye_platform_tracking_round_trip(mechs):
    """Prescribe the platform's Euler-angle accelerations; forward dynamics reproduces them."""
    mech = mechs["agile_eye"]
    rng = np.random.default_rng(SEED)
    P = mech.coordinate_indices(list(PLATFORM))
    for q, v in well_posed_platform_states(mech, rng, 20):
        a_P = 5.0 * rng.standard_normal(3)
        inv = inverse_dynamics(mech, q, v, a_P, coordinates=list(PLATFORM))
        np.testing.assert_array_equal(inv.prescribed_idx_v, P)
        np.testing.assert_array_equal(inv.a[P], a_P)
        assert inv.constraint_residual <= TOL_RESIDUAL * max(1.0, np.abs(inv.gamma).max())
        fwd = forward_dynamics(mech, q, v, inv.tau)
        assert rel_err(fwd.a, inv.a) <= TOL_ROUND_TRIP
        assert rel_err(fwd.a[P], a_P) <= TOL_ROUND_TRIP
        # the actuators alone do it
        assert set(np.flatnonzero(inv.tau)) <= set(mech.actuated_idx_v)


def test_coordinates_keep_the_callers_order(mechs):
    mech = mechs["agile_eye"]
    ((q, v),) = well_posed_platform_states(mech, np.random.default_rng(SEED), 1)
    a_P = np.array([1.0, -2.0, 3.0])
    fwd_order = inverse_dynamics(mech, q, v, a_P, coordinates=list(PLATFORM))
    rev_order = inverse_dynamics(mech, q, v, a_P[::-1], coordinates=list(PLATFORM[::-1]))
    np.testing.assert_allclose(rev_order.tau, fwd_order.tau, rtol=0, atol=1e-12)
    # velocity indices work too
    by_index = inverse_dynamics(
        mech, q, v, a_P, coordinates=[int(i) for i in fwd_order.prescribed_idx_v]
    )
    np.testing.assert_allclose(by_index.tau, fwd_order.tau, rtol=0, atol=1e-12)


def test_over_actuated_fourbar_minimum_norm_torques(mechs, states):
    """Two actuators on a 1-dof linkage: the torques are the minimum-norm ones."""
    mech = mechs["fourbar"]
    for q, v, a_ind in states["fourbar"][:10]:
        inv = inverse_dynamics(mech, q, v, a_ind, actuated=["crank_joint", "rocker_joint"])
        assert inv.tau[1] == 0.0
        fwd = forward_dynamics(mech, q, v, inv.tau)
        assert rel_err(fwd.a, inv.a) <= TOL_ROUND_TRIP
        # minimum norm: tau_A is parallel to N^T B (the 1-dof motion direction at A)
        J = inv.J
        n = np.linalg.svd(J)[2][-1]  # null-space direction of J
        t = inv.tau[[0, 2]]
        assert abs(t[0] * n[2] - t[1] * n[0]) <= 1e-12 * max(1.0, np.linalg.norm(t))
        single = inverse_dynamics(mech, q, v, a_ind)
        assert np.linalg.norm(t) <= abs(single.tau[0]) * (1 + 1e-12)


def test_joint_reactions_from_forward_result_and_array(mechs, states):
    mech = mechs["agile_eye"]
    q, v, a_ind = states["agile_eye"][0]
    inv = inverse_dynamics(mech, q, v, a_ind)
    fwd = forward_dynamics(mech, q, v, inv.tau)
    r_inv = joint_reactions(mech, q, v, inv)
    r_fwd = joint_reactions(mech, q, v, fwd)
    r_arr = joint_reactions(mech, q, v, inv.lam)
    assert [r.loop for r in r_inv] == ["leg1_platform", "leg2_platform", "leg3_platform"]
    for x, y, z in zip(r_inv, r_fwd, r_arr, strict=True):
        np.testing.assert_allclose(x.torque, y.torque, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(x.torque, z.torque)
        # the spherical wrist's legs carry couples only in the independent rows kept
        # (rotation rows): their forces along the legs are statically indeterminate
        np.testing.assert_array_equal(x.force, 0.0)
        # a revolute loop transmits no couple about its own axis (in c1)
        oMc1 = pin.updateFramePlacement(mech.model, mech.data, mech.model.getFrameId(x.frame))
        axis = next(lp.axis for lp in mech.description.loops if lp.name == x.loop)
        assert abs(x.torque @ axis) <= 1e-12 * max(1.0, np.linalg.norm(x.torque))
        np.testing.assert_allclose(oMc1.rotation @ x.torque, x.torque_world, atol=1e-14)


def test_reactions_balance_the_generalized_constraint_force(mechs, states):
    """Virtual work: the loop wrenches, mapped through the frame Jacobians, give -J^T lam."""
    for name, mech in mechs.items():
        q, v, a_ind = states[name][0]
        inv = inverse_dynamics(mech, q, v, a_ind)
        model, data = mech.model, mech.data
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        gen = np.zeros(mech.nv)
        for rx in joint_reactions(mech, q, v, inv):
            w = np.concatenate([rx.force_world, rx.torque_world])
            lwa = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
            Js = pin.getFrameJacobian(model, data, model.getFrameId(f"{rx.loop}::successor"), lwa)
            Jp = pin.getFrameJacobian(model, data, model.getFrameId(rx.frame), lwa)
            # the predecessor gets -w applied at the successor frame's origin
            oMp = data.oMf[model.getFrameId(rx.frame)]
            oMs = data.oMf[model.getFrameId(f"{rx.loop}::successor")]
            r = oMs.translation - oMp.translation
            w_p = -np.concatenate([rx.force_world, rx.torque_world + np.cross(r, rx.force_world)])
            gen += Js.T @ w + Jp.T @ w_p
        # constraint forces enter as M a + h = tau - J^T lam
        np.testing.assert_allclose(gen, -inv.generalized_constraint_force(), atol=1e-10)


# -- error paths ------------------------------------------------------------------------------


def test_wrong_number_of_coordinates(mechs):
    mech = mechs["agile_eye"]
    with pytest.raises(
        cc.ClosedChainError, match=r"coordinates names 2 coordinates .* mobility is 3"
    ):
        inverse_dynamics(
            mech, mech.q_ref, np.zeros(mech.nv), [0.0, 0.0], coordinates=list(PLATFORM[:2])
        )


@pytest.mark.parametrize("backend", BACKENDS)
def test_result_has_every_field(mechs, states, backend):
    """The result (made without the dataclass __init__ on the hot path) sets every field."""
    mech = mechs["fourbar"]
    q, v, a_P = states["fourbar"][0]
    res = inverse_dynamics(mech, q, v, a_P, backend=backend)
    assert set(vars(res)) == {f.name for f in dataclasses.fields(InverseDynamicsResult)}
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.tau = None


@pytest.mark.parametrize("backend", BACKENDS)
def test_repeated_calls_follow_their_arguments(mechs, states, backend):
    """A call reuses the checks of the last call with the same specs (a controller's loop),
    never its settings, coordinates or rows: each call answers to its own arguments."""
    mech = mechs["agile_eye"]
    q, v, a_P = states["agile_eye"][0]
    first = inverse_dynamics(mech, q, v, a_P, backend=backend).tau
    with pytest.raises(cc.SingularConfigurationError, match=r"cond_max 1\.0e\+00"):
        inverse_dynamics(mech, q, v, a_P, settings=SolverSettings(cond_max=1.01), backend=backend)
    platform = inverse_dynamics(mech, q, v, a_P, coordinates=list(PLATFORM), backend=backend)
    assert list(platform.prescribed_idx_v) == list(mech.coordinate_indices(list(PLATFORM)))
    with pytest.raises(cc.ClosedChainError, match=r"coordinates names 2 coordinates"):
        inverse_dynamics(mech, q, v, a_P[:2], coordinates=list(PLATFORM[:2]), backend=backend)
    np.testing.assert_array_equal(inverse_dynamics(mech, q, v, a_P, backend=backend).tau, first)


@pytest.mark.parametrize("backend", BACKENDS)
def test_wrong_number_of_accelerations(mechs, backend):
    mech = mechs["agile_eye"]
    for a_P in ([0.0, 0.0], [0.0, np.nan, 0.0], [np.inf, 0.0, 0.0]):
        with pytest.raises(cc.ClosedChainError, match=r"a_independent must be 3 finite numbers"):
            inverse_dynamics(mech, mech.q_ref, np.zeros(mech.nv), a_P, backend=backend)
    # Checked before q (here of a wrong shape), as on numpy.
    with pytest.raises(cc.ClosedChainError, match=r"a_independent must be 3 finite numbers"):
        inverse_dynamics(
            mech, np.zeros(mech.nq + 1), np.zeros(mech.nv), [np.nan] * 3, backend=backend
        )
    # Checked before the singular J_F that the compiled core meets first.
    with pytest.raises(cc.ClosedChainError, match=r"a_independent must be 1 finite numbers"):
        inverse_dynamics(
            mechs["fourbar"],
            fourbar_rocker_dead_centre(),
            np.zeros(3),
            [np.nan],
            coordinates=["rocker_joint"],
            backend=backend,
        )


def test_duplicate_coordinate(mechs):
    mech = mechs["agile_eye"]
    with pytest.raises(cc.ClosedChainError, match=r"names a coordinate twice"):
        inverse_dynamics(
            mech,
            mech.q_ref,
            np.zeros(mech.nv),
            [0.0] * 3,
            coordinates=["platform_yaw", "platform_yaw", "platform_roll"],
        )


def test_unknown_joint_name(mechs):
    mech = mechs["fourbar"]
    with pytest.raises(cc.ClosedChainError, match=r"unknown joint 'elbow'; joints: crank_joint"):
        inverse_dynamics(mech, mech.q_ref, np.zeros(3), [0.0], actuated=["elbow"])


def test_under_actuated(mechs):
    mech = mechs["agile_eye"]
    with pytest.raises(cc.ClosedChainError, match=r"under-actuated: 2 actuated coordinates"):
        inverse_dynamics(
            mech, mech.q_ref, np.zeros(mech.nv), [0.0] * 3, actuated=["actuator_1", "actuator_2"]
        )


def fourbar_rocker_dead_centre() -> np.ndarray:
    """Return q with crank and coupler aligned (|AC| = a + b): the rocker is at its extreme."""
    theta4 = np.arccos(((A_LEN + B_LEN) ** 2 - D_LEN**2 - C_LEN**2) / (2 * D_LEN * C_LEN))
    theta2 = np.arctan2(C_LEN * np.sin(theta4), D_LEN + C_LEN * np.cos(theta4))
    return np.array([theta2, 0.0, theta4])


@pytest.mark.parametrize("backend", BACKENDS)
def test_actuation_singularity(mechs, backend):
    """At the rocker's extreme, a rocker motor cannot move the linkage."""
    mech = mechs["fourbar"]
    q = fourbar_rocker_dead_centre()
    with pytest.raises(
        cc.SingularConfigurationError,
        match=r"(?s)N\^T B .* is singular at q = \[.*condition number .*actuated coordinates "
        r"rocker_joint cannot produce every motion",
    ):
        inverse_dynamics(mech, q, np.zeros(3), [0.0], actuated=["rocker_joint"], backend=backend)
    # the crank motor can
    inverse_dynamics(mech, q, np.zeros(3), [0.0], backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_prescribed_coordinates_do_not_determine_motion(mechs, backend):
    """At the rocker's extreme, the rocker's acceleration does not determine the others."""
    mech = mechs["fourbar"]
    q = fourbar_rocker_dead_centre()
    with pytest.raises(
        cc.SingularConfigurationError,
        match=r"(?s)J_F .*crank_joint, coupler_joint.* is singular at q = \[.*condition number"
        r".*rocker_joint do not determine the motion",
    ) as info:
        inverse_dynamics(mech, q, np.zeros(3), [0.0], coordinates=["rocker_joint"], backend=backend)
    np.testing.assert_array_equal(info.value.q, q)


def test_joint_reactions_rejects_wrong_lam(mechs):
    mech = mechs["fourbar"]
    with pytest.raises(cc.ClosedChainError, match=r"lam has shape \(3,\), expected \(2,\)"):
        joint_reactions(mech, mech.q_ref, np.zeros(3), np.zeros(3))


def test_exported_from_package():
    for name in ("inverse_dynamics", "joint_reactions", "InverseDynamicsResult", "LoopReaction"):
        assert hasattr(cc, name), name
