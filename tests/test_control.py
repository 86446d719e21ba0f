"""Tests of closedchain.control: computed-torque tracking and the default scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest

import closedchain as cc
from closedchain.control import computed_torque_controller, default_scene, sinusoid_reference
from closedchain.simulate import simulate
from closedchain.urdf import SinusoidSpec

#: The lesson's crank angle [rad].
THETA2_START = math.radians(10.0)
#: Max |phi| of accurate runs (DOP853 at 1e-10).
RESIDUAL_TOL = 1e-10
#: Max tracking error of computed-torque control with an exact model [rad].
TRACKING_TOL = 1e-6
#: Crossed-branch guess of the 4-bar at theta2 = 10 deg [deg] (theta4 = -103.8 deg).
CROSSED_GUESS_DEG = (10.0, -65.0, -104.0)


@pytest.fixture(scope="module")
def q_crossed(fourbar) -> np.ndarray:
    q = cc.assemble(fourbar, np.radians(CROSSED_GUESS_DEG), fixed=["crank_joint"])
    assert q[2] < 0.0
    return q


# -- computed-torque tracking (moved from test_simulate.py) ------------------------------

#: Reference of the 4-bar crank: theta2 = 10 deg + A sin(2 pi f t).
CRANK_AMPLITUDE = 0.3
CRANK_FREQUENCY = 0.5
#: Small sinusoids of the Agile Eye platform's yaw, pitch, roll around home [rad], [Hz].
PLATFORM_AMPLITUDES = (0.1, 0.08, 0.06)
PLATFORM_FREQUENCIES = (0.5, 0.7, 0.9)
PLATFORM_COORDINATES = ["platform_yaw", "platform_pitch", "platform_roll"]
KP, KD = 100.0, 20.0
T_TRACK = 3.0
TRACK_CONFIG = dict(integrator="DOP853", rtol=1e-10, atol=1e-10)


def _sinusoids(offsets, amplitudes, frequencies):
    offsets, amp = np.asarray(offsets, float), np.asarray(amplitudes, float)
    w = 2 * np.pi * np.asarray(frequencies, float)

    def reference(t):
        return offsets + amp * np.sin(w * t), amp * w * np.cos(w * t), -amp * w**2 * np.sin(w * t)

    return reference


def _start_on_reference(mech, reference, names, q_guess):
    q_idx = [mech.model.joints[mech.model.getJointId(n)].idx_q for n in names]
    v_idx = [mech.model.joints[mech.model.getJointId(n)].idx_v for n in names]
    q_ref0, v_ref0, _ = reference(0.0)
    q = np.array(q_guess, dtype=float)
    q[q_idx] = q_ref0
    q = cc.assemble(mech, q, fixed=names)
    v = np.zeros(mech.nv)
    v[v_idx] = v_ref0
    return q, cc.project_velocity(mech, q, v, fixed=names), q_idx


def _tracking_error(mech, names, offsets, amplitudes, frequencies, q_guess):
    reference = _sinusoids(offsets, amplitudes, frequencies)
    coordinates = names if names else "independent"
    ctrl = computed_torque_controller(mech, reference, kp=KP, kd=KD, coordinates=coordinates)
    names = names or [mech.coordinate_names[i] for i in mech.independent_idx_v]
    q0, v0, q_idx = _start_on_reference(mech, reference, names, q_guess)
    t_eval = np.linspace(0.0, T_TRACK, 301)
    traj = simulate(mech, q0, v0, T_TRACK, tau=ctrl, t_eval=t_eval, **TRACK_CONFIG)
    want = np.array([reference(t)[0] for t in traj.t])
    return np.max(np.linalg.norm(traj.q[:, q_idx] - want, axis=1)), traj


def test_fourbar_crank_tracking(fourbar, q_crossed):
    err, traj = _tracking_error(
        fourbar, None, [THETA2_START], [CRANK_AMPLITUDE], [CRANK_FREQUENCY], q_crossed
    )
    assert err <= TRACKING_TOL
    assert np.max(np.abs(traj.q[:, 0] - THETA2_START)) > 0.9 * CRANK_AMPLITUDE


def test_agile_eye_platform_tracking(agile_eye):
    err, traj = _tracking_error(
        agile_eye,
        PLATFORM_COORDINATES,
        np.zeros(3),
        PLATFORM_AMPLITUDES,
        PLATFORM_FREQUENCIES,
        agile_eye.q_ref,
    )
    assert err <= TRACKING_TOL
    assert traj.max_constraint_residual <= RESIDUAL_TOL


def test_controller_rejects_wrong_coordinates(agile_eye):
    ref = _sinusoids(np.zeros(2), [0.1, 0.1], [1.0, 1.0])
    with pytest.raises(cc.ClosedChainError, match="exactly 3 coordinates"):
        computed_torque_controller(
            agile_eye, ref, kp=KP, kd=KD, coordinates=["platform_yaw", "platform_pitch"]
        )


def test_sinusoid_reference_is_consistent():
    """v and a of the reference are the derivatives of q (central differences)."""
    ref = sinusoid_reference([SinusoidSpec("j", 0.2, 0.5, 0.3), SinusoidSpec("k", -1.0, 0.1, 2.0)])
    t, h = 0.37, 1e-5
    q, v, a = ref(t)
    np.testing.assert_allclose(
        q, [0.2 + 0.5 * math.sin(0.6 * math.pi * t), -1.0 + 0.1 * math.sin(4 * math.pi * t)]
    )
    np.testing.assert_allclose(v, (ref(t + h)[0] - ref(t - h)[0]) / (2 * h), rtol=1e-8)
    np.testing.assert_allclose(a, (ref(t + h)[1] - ref(t - h)[1]) / (2 * h), rtol=1e-7)


# -- default scenes (the <scene> element) --------------------------------------------------

#: The wrist's default scene must stay this far from a leg singularity over 10 s: max
#: cond(J) along the path (measured 2.30; a leg singularity is cond -> inf, and the
#: simulator stops at SimulationSettings.singular_cond = 1e3).
SCENE_COND_MAX = 10.0


@pytest.mark.slow
def test_agile_eye_default_scene_runs_10_s_tracking_its_path(agile_eye):
    scene = default_scene(agile_eye)
    assert scene.tau is not None and "platform_yaw" in scene.description
    t_eval = np.linspace(0.0, 10.0, 101)
    traj = simulate(agile_eye, scene.q0, scene.v0, 10.0, tau=scene.tau, t_eval=t_eval)
    spec = agile_eye.description.scene
    ref = sinusoid_reference(spec.track)
    idx = [agile_eye.model.joints[agile_eye.model.getJointId(s.joint)].idx_q for s in spec.track]
    want = np.array([ref(t)[0] for t in traj.t])
    assert traj.t[-1] == 10.0
    assert np.max(np.abs(traj.q[:, idx] - want)) <= TRACKING_TOL
    assert np.max(np.abs(want[:, 0])) > 0.79  # it really moves: yaw amplitude 0.8 rad
    cond = max(np.linalg.cond(cc.compute_jacobian(agile_eye, q)) for q in traj.q)
    assert cond <= SCENE_COND_MAX


def test_agile_eye_scene_is_read_from_the_urdf(agile_eye):
    spec = agile_eye.description.scene
    assert (spec.kp, spec.kd) == (100.0, 20.0)
    assert [(s.joint, s.amplitude, s.frequency) for s in spec.track] == [
        ("platform_yaw", 0.8, 0.1),
        ("platform_pitch", 0.5, 0.15),
        ("platform_roll", 0.5, 0.2),
    ]
    scene = default_scene(agile_eye)
    assert np.max(np.abs(cc.compute_phi(agile_eye, scene.q0))) <= 1e-12
    assert np.max(np.abs(cc.compute_jacobian(agile_eye, scene.q0) @ scene.v0)) <= 1e-12


def test_fourbar_default_scene_is_the_crossed_branch_at_rest(fourbar, q_crossed):
    scene = default_scene(fourbar)
    assert scene.tau is None
    np.testing.assert_allclose(scene.q0, q_crossed, atol=1e-10)
    np.testing.assert_array_equal(scene.v0, np.zeros(3))


def test_no_scene_element_is_rest_at_q_ref(load_mechanism):
    mech = load_mechanism("slider_crank")
    assert mech.description.scene is None
    scene = default_scene(mech)
    np.testing.assert_array_equal(scene.q0, mech.q_ref)
    assert scene.tau is None


def test_scene_tracking_the_wrong_number_of_joints(mechanism_files, tmp_path):
    text = mechanism_files["agile_eye"].read_text()
    line = '      <sinusoid joint="platform_roll" offset="0" amplitude="0.5" frequency="0.2"/>\n'
    assert text.count(line) == 1
    path = tmp_path / "eye.urdf"
    path.write_text(text.replace(line, ""))
    mech = cc.load(path)
    with pytest.raises(
        cc.ClosedChainError,
        match=r"eye.urdf: line \d+: <scene> <track> drives 2 joints .*it needs the mobility, 3",
    ):
        default_scene(mech)


def test_nfourbar_scene_is_the_benchmark_start(load_mechanism):
    """<initial velocity=...> on crank 0: the N-four-bar's scene is the IFToMM A02 start
    (tests/nfourbar_reference.py: cranks vertical at -1 rad/s, couplers horizontal)."""
    import nfourbar_reference as ref
    from conftest import MODELS

    mech = cc.load(MODELS / "nfourbar_2.urdf")
    assert mech.description.scene.velocity == {"crank_0_joint": ref.OMEGA0}
    scene = default_scene(mech)
    q0, v0 = ref.initial_state(mech)
    assert scene.tau is None
    assert np.linalg.norm(scene.q0 - q0) <= 1e-12
    assert np.linalg.norm(scene.v0 - v0) <= 1e-12


def test_scene_velocity_with_a_track_is_refused(mechanism_files, tmp_path):
    text = mechanism_files["agile_eye"].read_text()
    path = tmp_path / "eye.urdf"
    initial = '<scene>\n    <initial joint="platform_yaw" value="0" velocity="1"/>'
    path.write_text(text.replace("<scene>", initial, 1))
    with pytest.raises(cc.ClosedChainError, match=r"velocity=.*is for passive scenes"):
        cc.load(path)
