"""Passive joint terms (closedchain.passive): springs, viscous damping and armature.

References, none of them closedchain's code:

* MuJoCo reads the test URDFs itself (``MjSpec.from_file``); the passive terms are set
  on its joints from this file's tables (:data:`CHAIN_TERMS`, :data:`FOURBAR_TERMS`):
  its mass matrix (``mj_fullM``, armature included), ``qfrc_bias``, ``qfrc_passive``
  (-K (q - q_ref) - D v) and, for the open chain, ``qacc``;
* Pinocchio's ``crba``, ``rnea``, ``aba`` and kinetic energy with ``model.armature``;
* with loops, a rigid KKT solve from MuJoCo's M and qfrc_bias - qfrc_passive with the
  loop rows' J and Jdot v (checked against the 4-bar's closed forms in test_constraints);
* the closed-form motion of a damped torsional oscillator with a spring and armature.
"""

from __future__ import annotations

import logging
import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR

import closedchain as cc
from closedchain import compiled
from closedchain.benchmark.families import chain_urdf
from closedchain.dynamics.base import compute_terms, mass_matrix
from closedchain.exceptions import ModelFileError
from closedchain.simulate import COMPILED_INTEGRATORS

CHAIN = DATA_DIR / "passive_chain.urdf"
FOURBAR = DATA_DIR / "passive_fourbar.urdf"

#: The passive terms the two files write, joint -> (stiffness [N m/rad or N/m],
#: spring reference [rad or m], damping [N m s/rad or N s/m], armature [kg m^2 or kg]).
CHAIN_TERMS = {
    "j1": (3.5, 0.4, 0.7, 0.05),
    "j2": (0.0, 0.0, 0.25, 0.12),
    "j3": (40.0, -0.05, 1.5, 0.8),
    "j4": (0.0, 0.0, 0.0, 0.0),
}
FOURBAR_TERMS = {
    "crank_joint": (6.0, 0.5, 0.35, 0.0),
    "coupler_joint": (0.0, 0.0, 0.15, 0.02),
    "rocker_joint": (2.5, -1.2, 0.0, 0.04),
}

#: M, h and forces against MuJoCo's and Pinocchio's: round-off of two double-precision
#: implementations, relative to the largest entry (measured 1.1e-15 at most).
TERMS_RTOL = 1e-12
#: Accelerations against MuJoCo's qacc or a rigid KKT solve from its arrays, relative to
#: max |a| (the issue's bound; measured 1e-14 at most, both backends).
ACCEL_RTOL = 1e-9
#: E - E0 - W of the open chain's 0.2 s rk4 run at 1 ms, relative (measured 1e-11).
CHAIN_BALANCE_TOL = 1e-9
#: E - E0 - W of the passive 4-bar's 1 s rk4 run at 1 ms, relative (measured 3.3e-10
#: numpy, 3.9e-10 compiled; its energy falls by twice its initial value).
LOOP_BALANCE_TOL = 3e-9
#: Random states per comparison.
N_STATES = 5
#: Velocity scale of the random states [rad/s or m/s].
VELOCITY_SCALE = 2.0

BACKENDS = ["numpy", "compiled"]
METHODS = ["kkt", "augmented-lagrangian", "schur", "nullspace", "reduced", "pinocchio"]


def _backends():
    return [b if b == "numpy" else pytest.param(b, marks=_needs_core) for b in BACKENDS]


_needs_core = pytest.mark.skipif(not compiled.available(), reason="compiled core not built")


def _mujoco(path, terms):
    """MuJoCo's model of the URDF at ``path`` with ``terms`` on its joints, contacts and
    limits off, and its data."""
    spec = mujoco.MjSpec.from_file(str(path))
    for joint in spec.joints:
        k, ref, d, r = terms[joint.name]
        joint.stiffness = [k, 0.0, 0.0]
        joint.springref = ref
        joint.damping = [d, 0.0, 0.0]
        joint.armature = r
    model = spec.compile()
    model.opt.disableflags |= (
        mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_LIMIT
    )
    return model, mujoco.MjData(model)


def _mujoco_terms(m, d, q, v, tau=None):
    """(M, qfrc_bias, qfrc_passive, qacc) of MuJoCo at (q, v) (1-dof joints: qpos = q)."""
    d.qpos[:], d.qvel[:] = q, v
    d.qfrc_applied[:] = 0.0 if tau is None else tau
    mujoco.mj_forward(m, d)
    M = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M)
    return M, d.qfrc_bias.copy(), d.qfrc_passive.copy(), d.qacc.copy()


def _max_rel(x, ref) -> float:
    return float(np.max(np.abs(x - ref)) / max(1.0, float(np.max(np.abs(ref)))))


@pytest.fixture(scope="module")
def chain():
    return cc.load(CHAIN)


@pytest.fixture(scope="module")
def fourbar():
    return cc.load(FOURBAR)


def _joint_v(mech, name) -> int:
    return mech.model.joints[mech.model.getJointId(name)].idx_v


# -- reading ---------------------------------------------------------------------------


def test_urdf_dynamics_become_the_mechanisms_passive_terms(chain):
    urdf = chain.description
    assert {s.joint: (s.stiffness, s.reference) for s in urdf.springs} == {
        n: t[:2] for n, t in CHAIN_TERMS.items() if t[0]
    }
    assert {e.joint: e.damping for e in urdf.dampings} == {
        n: t[2] for n, t in CHAIN_TERMS.items() if t[2]
    }
    assert {e.joint: e.armature for e in urdf.armatures} == {
        n: t[3] for n, t in CHAIN_TERMS.items() if t[3]
    }
    damping = np.zeros(chain.nv)
    armature = np.zeros(chain.nv)
    for name, (_, _, d, r) in CHAIN_TERMS.items():
        damping[_joint_v(chain, name)], armature[_joint_v(chain, name)] = d, r
    np.testing.assert_array_equal(chain.passive.damping, damping)
    np.testing.assert_array_equal(chain.model.armature, armature)


@pytest.mark.parametrize(
    "dynamics, match",
    [
        ('damping="-1"', "damping='-1'>: must be a finite number >= 0"),
        ('damping="nan"', "damping='nan'>: must be a finite number >= 0"),
        ('damping="0" armature="-0.1"', "armature='-0.1'>: must be a finite number >= 0"),
        ('armature="0.1"', 'refuse a <dynamics> without damping or friction; add damping="0"'),
    ],
)
def test_bad_dynamics_are_refused(tmp_path, dynamics, match):
    text = CHAIN.read_text().replace(
        '<dynamics damping="0.25" armature="0.12"/>', f"<dynamics {dynamics}/>"
    )
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(ModelFileError, match=match):
        cc.load(path)


def test_friction_is_named_as_not_modelled(tmp_path, caplog):
    text = CHAIN.read_text().replace(
        '<dynamics damping="0.25" armature="0.12"/>',
        '<dynamics damping="0.25" friction="0.3" armature="0.12"/>',
    )
    path = tmp_path / "friction.urdf"
    path.write_text(text)
    with caplog.at_level(logging.INFO, logger="closedchain.urdf"):
        mech = cc.load(path)
    assert "friction loss is not modelled" in caplog.text
    assert {e.joint for e in mech.description.dampings} == {"j1", "j2", "j3"}


# -- Pinocchio with model.armature -------------------------------------------------------


def test_pinocchio_includes_the_armature(chain, rng):
    """Pinocchio 4.1's crba, rnea and aba add model.armature: M grows by diag(armature)
    and the other algorithms are consistent with that M; so is the kinetic energy."""
    model = chain.model
    bare = model.copy()
    bare.armature[:] = 0.0
    data, bare_data = model.createData(), bare.createData()
    for _ in range(N_STATES):
        q = pin.randomConfiguration(model)
        v, a = rng.standard_normal(chain.nv), rng.standard_normal(chain.nv)
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        M0 = pin.crba(bare, bare_data, q)
        M0 = np.triu(M0) + np.triu(M0, 1).T
        scale = float(np.max(np.abs(M)))
        assert np.max(np.abs(M - M0 - np.diag(chain.passive.armature))) <= TERMS_RTOL * scale
        nle = pin.nonLinearEffects(model, data, q, v)
        tau = pin.rnea(model, data, q, v, a)
        assert _max_rel(tau, M @ a + nle) <= TERMS_RTOL
        assert _max_rel(pin.aba(model, data, q, v, tau), a) <= TERMS_RTOL
        # Pinocchio's computeKineticEnergy misses the armature of the unaligned joint j2:
        # PassiveTerms.kinetic_energy (what simulate records) does not.
        T = chain.passive.kinetic_energy(model, data, q, v)
        assert abs(T - 0.5 * v @ M @ v) <= TERMS_RTOL * max(1.0, abs(T))


# -- against MuJoCo ------------------------------------------------------------------------


def test_mass_matrix_and_passive_forces_match_mujoco(chain, rng):
    m, d = _mujoco(CHAIN, CHAIN_TERMS)
    assert [m.joint(i).name for i in range(m.njnt)] == list(chain.joint_names)
    for _ in range(N_STATES):
        q = pin.randomConfiguration(chain.model)
        v = VELOCITY_SCALE * rng.standard_normal(chain.nv)
        M_mj, bias, passive, _ = _mujoco_terms(m, d, q, v)
        assert np.max(np.abs(passive)) > 0.1  # the comparison is not 0 = 0
        assert _max_rel(mass_matrix(chain, q).M, M_mj) <= TERMS_RTOL
        assert _max_rel(chain.passive.force(q, v), passive) <= TERMS_RTOL
        springs = cc.spring_torque(chain, q)
        assert _max_rel(springs - chain.passive.damping * v, passive) <= TERMS_RTOL
        ws = compute_terms(chain, q, v)  # the methods' M and h - tau_p
        assert _max_rel(ws.M, M_mj) <= TERMS_RTOL
        assert _max_rel(ws.h, bias - passive) <= TERMS_RTOL


@pytest.mark.parametrize("backend", _backends())
def test_open_chain_accelerations_match_mujoco(chain, rng, backend):
    m, d = _mujoco(CHAIN, CHAIN_TERMS)
    for _ in range(N_STATES):
        q = pin.randomConfiguration(chain.model)
        v = VELOCITY_SCALE * rng.standard_normal(chain.nv)
        tau = rng.standard_normal(chain.nv)
        *_, qacc = _mujoco_terms(m, d, q, v, tau)
        a = cc.forward_dynamics(chain, q, v, tau, method="kkt", backend=backend).a
        assert _max_rel(a, qacc) <= ACCEL_RTOL


def _rigid_kkt(M, rhs, J, gamma):
    """a of [[M, J^T], [J, 0]] [a; lam] = [rhs; -gamma] (least squares: J may hold
    redundant rows)."""
    nv, nc = M.shape[0], J.shape[0]
    K = np.block([[M, J.T], [J, np.zeros((nc, nc))]])
    return np.linalg.lstsq(K, np.concatenate([rhs, -gamma]), rcond=None)[0][:nv]


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("method", METHODS)
def test_loop_accelerations_match_a_rigid_solve_from_mujoco(fourbar, rng, method, backend):
    if backend == "compiled" and not compiled.supports_method(method):
        pytest.skip(f"{method} runs on numpy only")
    m, d = _mujoco(FOURBAR, FOURBAR_TERMS)
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(fourbar, rng, velocity_scale=VELOCITY_SCALE)
        tau = rng.standard_normal(fourbar.nv)
        M_mj, bias, passive, _ = _mujoco_terms(m, d, q, v)
        ws = compute_terms(fourbar, q, v)
        a_ref = _rigid_kkt(M_mj, tau - bias + passive, ws.J.copy(), ws.gamma.copy())
        a = cc.forward_dynamics(fourbar, q, v, tau, method=method, backend=backend).a
        assert _max_rel(a, a_ref) <= ACCEL_RTOL


@pytest.mark.parametrize("backend", _backends())
def test_inverse_dynamics_with_passive_terms(fourbar, rng, backend):
    """The crank torque of inverse_dynamics, fed to forward_dynamics, gives back the
    prescribed acceleration: both solve with the same springs, damping and armature."""
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(fourbar, rng, velocity_scale=VELOCITY_SCALE)
        a_P = rng.standard_normal(fourbar.mobility)
        inv = cc.inverse_dynamics(fourbar, q, v, a_P, backend=backend)
        fwd = cc.forward_dynamics(fourbar, q, v, inv.tau, method="kkt", backend=backend)
        assert _max_rel(fwd.a, inv.a) <= ACCEL_RTOL


#: The tree path's chain: links (nv > the core's TREE_SOLVE_MIN_NV) and its passive terms
#: on every joint (stiffness [N m/rad], reference [rad], damping [N m s/rad], armature
#: [kg m^2]).
TREE_LINKS = 16
TREE_TERMS = (0.8, 0.1, 0.05, 0.002)


@pytest.fixture(scope="module")
def sprung_chain(tmp_path_factory):
    k, ref, d, r = TREE_TERMS
    dynamics = (
        f'<dynamics damping="{d}" armature="{r}" spring_stiffness="{k}" '
        f'spring_reference="{ref}"/></joint>'
    )
    path = tmp_path_factory.mktemp("passive") / "chain.urdf"
    path.write_text(chain_urdf(TREE_LINKS).replace("</joint>", dynamics))
    return cc.load(path)


@_needs_core
@pytest.mark.parametrize("method", ["kkt", "augmented-lagrangian", "nullspace", "reduced"])
def test_tree_path_includes_the_passive_terms(sprung_chain, rng, method):
    """The compiled tree path (M^-1 by the articulated-body recursion) against a KKT
    solve from Pinocchio's crba and rnea with the passive forces written here."""
    mech = sprung_chain
    k, ref, d, r = TREE_TERMS
    fd = compiled.compiled_dynamics(mech, method)
    assert fd.core.tree_solves()
    model, data = mech.model, mech.model.createData()
    for _ in range(N_STATES):
        # Near the reference pose (random states of long chains are hard to assemble).
        q = mech.q_ref.copy()
        q[mech.independent_idx_v] += rng.standard_normal(mech.mobility) / mech.nv
        q = cc.assemble(mech, q, fixed="independent")
        v = cc.project_velocity(mech, q, VELOCITY_SCALE * rng.standard_normal(mech.nv))
        tau = rng.standard_normal(mech.nv)
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        passive = -k * (q - ref) - d * v
        rhs = tau + passive - pin.rnea(model, data, q, v, np.zeros(mech.nv))
        ws = compute_terms(mech, q, v)
        a_ref = _rigid_kkt(M, rhs, ws.J.copy(), ws.gamma.copy())
        a = cc.forward_dynamics(mech, q, v, tau, method=method, backend="compiled").a
        assert _max_rel(a, a_ref) <= ACCEL_RTOL


# -- simulation and energy -----------------------------------------------------------------

#: The torsional oscillator: a disc about the vertical axis (gravity does no work),
#: inertia [kg m^2], armature [kg m^2], stiffness [N m/rad], reference [rad], damping
#: [N m s/rad]; its start (q0 [rad], v0 [rad/s]) and the simulated time [s].
DISC_INERTIA = 0.02
DISC_TERMS = (1.5, 0.3, 0.04, 0.03)  # stiffness, reference, damping, armature
DISC_START = (1.1, -2.0)
DISC_T = 2.0
#: Integrators, their step [s] (fixed-step; None: the adaptive defaults), the largest
#: error of q [rad] and of E [J, relative to E(0)] against the closed form, and the
#: largest relative E - E0 - W (measured, q / balance: rk4 at 1 ms 3e-11 / 3e-11, DOP853
#: 8e-9 / 1.4e-7, RK45 6e-9 / 1.5e-8, rk43 8e-10 / 6e-10, semi-implicit at 0.1 ms 2e-4 /
#: 4e-4, euler at 0.1 ms 1.1e-3 / 2.8e-3, ALI3-P at 1 ms 1e-5 / 6e-6; both backends).
DISC_RUNS = {
    "rk4": (1e-3, 1e-9, 1e-9),
    "DOP853": (None, 1e-7, 1e-6),
    "RK45": (None, 1e-7, 1e-7),
    "rk43": (None, 1e-8, 1e-8),
    "semi-implicit": (1e-4, 1e-3, 2e-3),
    "euler": (1e-4, 5e-3, 1e-2),
    "ali3p": (1e-3, 5e-5, 3e-5),
}


@pytest.fixture(scope="module")
def disc(tmp_path_factory):
    k, ref, d, r = DISC_TERMS
    text = f"""<robot name="disc"><link name="base"/>
      <link name="disc"><inertial><origin xyz="0 0 0"/><mass value="1"/>
        <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="{DISC_INERTIA}"/>
      </inertial></link>
      <joint name="turn" type="revolute"><parent link="base"/><child link="disc"/>
        <axis xyz="0 0 1"/><limit lower="-10" upper="10" effort="1" velocity="100"/>
        <dynamics damping="{d}" armature="{r}" spring_stiffness="{k}" spring_reference="{ref}"/>
      </joint></robot>"""
    path = tmp_path_factory.mktemp("disc") / "disc.urdf"
    path.write_text(text)
    return cc.load(path)


def _disc_closed_form(t):
    """q(t), v(t) and the energy E(t) = T + V_spring of the damped torsional oscillator
    (I + r) q'' + d q' + k (q - ref) = 0 (underdamped)."""
    k, ref, d, r = DISC_TERMS
    inertia = DISC_INERTIA + r
    sigma = d / (2.0 * inertia)
    omega = math.sqrt(k / inertia - sigma * sigma)
    A = DISC_START[0] - ref
    B = (DISC_START[1] + sigma * A) / omega
    decay = np.exp(-sigma * t)
    c, s = np.cos(omega * t), np.sin(omega * t)
    q = ref + decay * (A * c + B * s)
    v = decay * ((B * omega - sigma * A) * c - (A * omega + sigma * B) * s)
    return q, v, 0.5 * inertia * v**2 + 0.5 * k * (q - ref) ** 2


@pytest.mark.parametrize("backend", _backends())
@pytest.mark.parametrize("integrator", list(DISC_RUNS))
def test_damped_oscillator_follows_its_closed_form(disc, integrator, backend):
    dt, q_tol, balance_tol = DISC_RUNS[integrator]
    if backend == "compiled" and integrator not in COMPILED_INTEGRATORS:
        pytest.skip(f"{integrator} has no compiled loop")
    traj = cc.simulate(
        disc,
        np.array([DISC_START[0]]),
        np.array([DISC_START[1]]),
        DISC_T,
        integrator=integrator,
        dt=dt,
        t_eval=np.linspace(0.0, DISC_T, 41),
        backend=backend,
    )
    q, v, E = _disc_closed_form(traj.t)
    assert np.max(np.abs(traj.q[:, 0] - q)) <= q_tol
    # E holds the spring's potential and the armature's kinetic energy, W the damping's
    # work: E - E0 = W along the closed form, and the run's balance stays at its error.
    assert np.max(np.abs(traj.energy - E)) <= q_tol * E[0]
    assert np.max(np.abs(traj.work - (E - E[0]))) <= balance_tol * E[0]
    assert traj.energy_balance <= balance_tol
    assert traj.energy_drift > 0.5  # the damping takes most of the energy: not a 0 = 0 check


@pytest.mark.parametrize("backend", _backends())
def test_damped_loop_energy_balance(fourbar, backend):
    """The passive 4-bar released from rest: E (springs' potential included) falls by the
    damping's work, E - E0 - W within the integration error."""
    q0 = cc.assemble(fourbar, fourbar.q_ref)
    traj = cc.simulate(
        fourbar, q0, np.zeros(fourbar.nv), 1.0, integrator="rk4", dt=1e-3, backend=backend
    )
    assert traj.work is not None and traj.work[-1] < 0.0
    assert traj.energy_balance <= LOOP_BALANCE_TOL
    assert traj.energy_drift > 1.0  # the damping takes more than E(0): not a 0 = 0 check


def test_export_writes_the_passive_terms(chain, rng):
    """MuJoCo's model of the exported MJCF carries the same springs, damping and armature:
    its M and qfrc_passive are closedchain's."""
    from closedchain.export.mjcf import load_mujoco, mujoco_state

    m, d = load_mujoco(chain)
    for _ in range(N_STATES):
        q = pin.randomConfiguration(chain.model)
        v = VELOCITY_SCALE * rng.standard_normal(chain.nv)
        d.qpos[:], d.qvel[:] = mujoco_state(chain, q, v)
        mujoco.mj_forward(m, d)
        M = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, M)
        assert _max_rel(M, mass_matrix(chain, q).M) <= TERMS_RTOL
        assert _max_rel(d.qfrc_passive, chain.passive.force(q, v)) <= TERMS_RTOL


@pytest.mark.parametrize("backend", _backends())
def test_recorded_energy_holds_armature_and_springs(chain, backend):
    """The open chain's run: the recorded kinetic energy is 1/2 v^T M v with the armature
    (M from Pinocchio's crba; its computeKineticEnergy leaves out the unaligned joint's
    armature), E adds the springs' potential, and E - E0 - W stays at the step's error."""
    k = {n: t[0] for n, t in CHAIN_TERMS.items()}
    ref = {n: t[1] for n, t in CHAIN_TERMS.items()}
    traj = cc.simulate(
        chain, chain.q_ref, 0.5 * np.ones(chain.nv), 0.2, integrator="rk4", dt=1e-3, backend=backend
    )
    model, data = chain.model, chain.model.createData()
    for q, v, T, E in zip(traj.q, traj.v, traj.kinetic_energy, traj.energy, strict=True):
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        springs = sum(0.5 * k[n] * (q[_joint_v(chain, n)] - ref[n]) ** 2 for n in k)
        V = pin.computePotentialEnergy(model, data, q) + springs
        assert abs(T - 0.5 * v @ M @ v) <= TERMS_RTOL * max(1.0, T)
        assert abs(E - T - V) <= TERMS_RTOL * max(1.0, abs(E))
    assert traj.energy_balance <= CHAIN_BALANCE_TOL
