"""Coupling loops q_j = m q_i + c: URDF ``<mimic>`` and ``<loop type="coupling">``.

The references are independent of closedchain's constraint layer: the couplings'
numbers are written here from tests/data/mimic_gripper.urdf, the tree's M and h
come from a Pinocchio model built from the file, and the constrained accelerations
from a KKT system solved in the test; Pinocchio's own mimic joints (``mimic=True``,
reduced coordinates, RNEA) check the ``<mimic>`` couplings once more. The compiled
core's coupling rows are compared with the numpy reference (rows, every method, the
per-call functions, runs of every compiled integrator and stabilization, the tree path
of a long chain), and ``validate``'s reference for couplings, Pinocchio's mimic joints,
on a gripper, a four-bar finger with a <mimic> thumb and a coupling loop beside a loop.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR
from lxml import etree
from test_compiled import (
    ADAPTIVE_TOL,
    ATOL,
    FIXED_STEP_TOL,
    ROUNDOFF_FACTOR,
    RTOL,
    STEP_COUNT_SLACK,
)
from test_percall import (
    ASSEMBLY_PARITY_TOL,
    BACKEND_PARITY_TOL,
    assert_rows_compiled_equal_numpy,
)
from test_percall import ROWS_TOL as ROWS_PARITY_TOL

import closedchain as cc
from closedchain import compiled, validation
from closedchain.benchmark.families import chain_urdf
from closedchain.constraints import COUPLING_KIND
from closedchain.dynamics.base import METHOD_CAPABILITIES, compute_terms
from closedchain.exceptions import ModelFileError, ValidationUnavailableError

GRIPPER = DATA_DIR / "mimic_gripper.urdf"

#: The gripper's couplings as written in its file: joint -> (mimicked joint, m, c).
COUPLINGS = {
    "left_tip_joint": ("left_joint", 0.5, 0.1),
    "right_joint": ("left_joint", -1.0, 0.0),  # <mimic> without offset: URDF's default 0
    "right_tip_joint": ("right_joint", 0.5, -0.1),  # the URDF+ <loop type="coupling">
    "slide_joint": ("left_joint", 0.02, 0.01),
}

#: Relative tolerance of accelerations against the independent KKT solution (every
#: method: the iterative ones converge to ~1e-11 here).
ACCEL_RTOL = 1e-9

#: Largest |q_j - m q_i - c| [rad or m] along a simulation.
COUPLING_DRIFT_TOL = 1e-12

#: Tolerance of phi, J and gamma against their closed forms (round-off).
ROW_TOL = 1e-14

N_STATES = 5

#: Forward-dynamics methods that apply (Pinocchio has no coupling constraint model).
COUPLING_METHODS = ("kkt", "schur", "nullspace", "reduced", "proximal", "augmented-lagrangian")


@pytest.fixture(scope="module")
def gripper() -> cc.Mechanism:
    return cc.load(GRIPPER)


def _index(mech: cc.Mechanism, joint: str) -> int:
    return mech.coordinate_names.index(joint)


def _coupling_rows(mech: cc.Mechanism, q: np.ndarray):
    """phi, shape (nc,), and J, shape (nc, nv), of the couplings written from their
    numbers (:data:`COUPLINGS`), in the order of the mechanism's rows."""
    joint_of = {spec.name: spec.joint for spec in mech.description.loops}
    phi, J = [], np.zeros((mech.nc, mech.nv))
    for r, row in enumerate(mech.rows):
        joint = joint_of[row.loop]
        leader, m, c = COUPLINGS[joint]
        j, i = _index(mech, joint), _index(mech, leader)
        phi.append(q[j] - m * q[i] - c)
        J[r, j], J[r, i] = 1.0, -m
    return np.array(phi), J


def _kkt_reference(path, mech: cc.Mechanism, q, v, tau) -> np.ndarray:
    """Accelerations of the tree of ``path`` under the coupling rows (gamma = 0), by KKT."""
    model = pin.buildModelFromUrdf(str(path))
    model.gravity.linear = mech.gravity
    data = model.createData()
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    h = pin.nonLinearEffects(model, data, q, v)
    _, J = _coupling_rows(mech, q)
    k = len(J)
    K = np.block([[M, J.T], [J, np.zeros((k, k))]])
    return np.linalg.solve(K, np.concatenate([tau - h, np.zeros(k)]))[: mech.nv]


def test_mimic_and_coupling_elements_become_loops(gripper):
    loops = {spec.joint: spec for spec in gripper.description.loops}
    assert set(loops) == set(COUPLINGS)
    for joint, (leader, m, c) in COUPLINGS.items():
        spec = loops[joint]
        assert (spec.type, spec.mimics, spec.multiplier, spec.offset) == ("coupling", leader, m, c)
    assert loops["right_joint"].name == "right_joint_mimic"
    assert loops["right_tip_joint"].name == "right_tip"
    # Pinocchio builds the mimicking joints as ordinary ones: the constraint is the loop.
    assert (gripper.nv, gripper.nc, gripper.mobility) == (5, 4, 1)
    assert [gripper.coordinate_names[i] for i in gripper.independent_idx_v] == ["left_joint"]


def test_rows_match_their_closed_form(gripper, rng):
    for _ in range(N_STATES):
        q = gripper.random_configuration(rng)  # not assembled: phi != 0
        v = rng.standard_normal(gripper.nv)
        phi_ref, J_ref = _coupling_rows(gripper, q)
        np.testing.assert_allclose(cc.compute_phi(gripper, q), phi_ref, rtol=0, atol=ROW_TOL)
        np.testing.assert_allclose(cc.compute_jacobian(gripper, q), J_ref, rtol=0, atol=ROW_TOL)
        assert np.linalg.norm(cc.compute_gamma(gripper, q, v)) == 0.0


@pytest.mark.parametrize("method", COUPLING_METHODS)
def test_forward_dynamics_matches_independent_kkt(gripper, rng, method):
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(gripper, rng)
        tau = rng.standard_normal(gripper.nv)
        a = cc.forward_dynamics(gripper, q, v, tau, method=method).a
        a_ref = _kkt_reference(GRIPPER, gripper, q, v, tau)
        assert np.linalg.norm(a - a_ref) <= ACCEL_RTOL * np.linalg.norm(a_ref)


def test_mimic_joints_agree_with_pinocchio_mimic_model(rng, tmp_path):
    """Without the URDF+ loop the <mimic> couplings are exactly Pinocchio's mimic joints:
    its RNEA in reduced coordinates (left_joint, right_tip_joint) at closedchain's
    accelerations gives the reduced generalized force G^T tau."""
    root = etree.parse(str(GRIPPER)).getroot()
    root.remove(root.find("loop"))
    path = tmp_path / "mimic_only.urdf"
    path.write_bytes(etree.tostring(root))
    mech = cc.load(path)
    reduced = pin.buildModelFromUrdf(str(path), mimic=True)
    reduced.gravity.linear = mech.gravity
    rdata = reduced.createData()
    free = [_index(mech, "left_joint"), _index(mech, "right_tip_joint")]
    G = np.zeros((mech.nv, 2))  # full velocity from the reduced one
    G[free, [0, 1]] = 1.0
    for joint, (_, m, _) in COUPLINGS.items():
        if joint != "right_tip_joint":
            G[_index(mech, joint), 0] = m
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
        tau_reduced = pin.rnea(reduced, rdata, q[free], v[free], a[free])
        assert np.linalg.norm(tau_reduced - G.T @ tau) <= ACCEL_RTOL * np.linalg.norm(G.T @ tau)


def test_simulation_keeps_the_couplings(gripper):
    traj = cc.simulate(gripper, gripper.q_ref, np.zeros(gripper.nv), 0.5)
    for joint, (leader, m, c) in COUPLINGS.items():
        qj = traj.q[:, _index(gripper, joint)]
        qi = traj.q[:, _index(gripper, leader)]
        assert np.max(np.abs(qj - m * qi - c)) <= COUPLING_DRIFT_TOL
    # It moved: gravity opens the fingers.
    assert np.ptp(traj.q[:, _index(gripper, "left_joint")]) > 1e-3


def test_couplings_run_on_the_compiled_core_by_default(gripper):
    traj = cc.simulate(gripper, gripper.q_ref, np.zeros(gripper.nv), 0.05)
    assert traj.info.backend == "compiled"
    assert traj.info.backend_fallback is None


def test_pinocchio_method_names_the_coupling_it_cannot_hold(gripper):
    q, v = gripper.q_ref, np.zeros(gripper.nv)
    with pytest.raises(ValidationUnavailableError, match=r"'right_tip' is a joint coupling"):
        cc.forward_dynamics(gripper, q, v, method="pinocchio")


def _variant(tmp_path, old: str, new: str):
    text = GRIPPER.read_text()
    assert old in text
    path = tmp_path / "variant.urdf"
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            '<joint name="left_joint" type="revolute">',
            '<joint name="left_joint" type="continuous">',
            r"'left_joint' is a continuous joint; valid: revolute or prismatic",
        ),
        (
            '<mimic joint="left_joint" multiplier="-1"/>',
            '<mimic joint="thumb" multiplier="-1"/>',
            r"<joint name='right_joint'>: .*'thumb' is no joint of this file",
        ),
        (
            '<mimic joint="left_joint" multiplier="-1"/>',
            '<mimic joint="right_joint"/>',
            r"joint 'right_joint' cannot mimic itself",
        ),
        (
            'multiplier="0.02" offset="0.01"',
            'multiplier="two" offset="0.01"',
            r"<mimic multiplier='two'>: must be a finite number",
        ),
        (
            '<mimics joint="right_joint" multiplier="0.5" offset="-0.1"/>',
            "",
            r"<loop name='right_tip'>: a coupling loop needs exactly one <mimics>, found 0",
        ),
        (
            '<joint name="right_tip_joint"/>',
            '<joint name="right_tip_joint"/><axis xyz="0 0 1"/>',
            r"<axis>: unknown element in <loop>; valid: <joint>, <mimics>",
        ),
    ],
)
def test_bad_couplings_are_refused(tmp_path, old, new, match):
    with pytest.raises(ModelFileError, match=match):
        cc.load(_variant(tmp_path, old, new))


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            'multiplier="0.02" offset="0.01"',
            'multiplier="1e300" offset="0.01"',
            r"<mimic multiplier='1e300'>: must be within \+-1e\+06$",
        ),
        (
            'multiplier="-1"/>',
            'multiplier="-1.5e6"/>',
            r"<mimic multiplier='-1.5e6'>: must be within \+-1e\+06$",
        ),
        (
            'multiplier="0.5" offset="-0.1"/>',
            'multiplier="0.5" offset="-1e200"/>',
            r"<mimics offset='-1e200'>: must be within \+-1e\+06$",
        ),
    ],
)
def test_huge_coupling_numbers_are_refused_at_load(tmp_path, capsys, old, new, match):
    """A multiplier of 1e300 printed numpy's overflow warnings (then stopped); 1e150 its
    division warnings before a result. They are refused at load, in one line."""
    from closedchain import cli

    path = _variant(tmp_path, old, new)
    with pytest.raises(ModelFileError, match=match):
        cc.load(path)
    assert cli.main(["simulate", str(path), "--t-final", "0.05"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Warning" not in err


def test_the_largest_coupling_multiplier_simulates_without_warnings(tmp_path, recwarn):
    """A gear of 1e6 (the bound): the run completes and the coupling holds, with no
    RuntimeWarning (numpy's error state inside every public function raises instead)."""
    import warnings

    path = _variant(tmp_path, 'multiplier="0.02" offset="0.01"', 'multiplier="1e6" offset="0"')
    mech = cc.load(path)
    warnings.simplefilter("error", RuntimeWarning)
    q0 = cc.assemble(mech, mech.q_ref)
    traj = cc.simulate(mech, q0, np.zeros(mech.nv), 0.01)
    slide, left = _index(mech, "slide_joint"), _index(mech, "left_joint")
    assert np.max(np.abs(traj.q[:, slide] - 1e6 * traj.q[:, left])) <= COUPLING_TOL * 1e6
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


#: |q_slide - m q_left| of a run, relative to m [m/rad]: the assembly's tolerance (1e-10)
#: times the gear (measured 0 at rest).
COUPLING_TOL = 1e-9


def test_joint_reactions_leave_couplings_out(gripper, rng):
    """A coupling transmits no wrench between two links: its generalized force acts on
    the coupled joints as a motor's would, so each tree joint transmits
    tau - J^T lam along its axis (J written from the file's numbers)."""
    q, v = cc.random_consistent_state(gripper, rng)
    tau = rng.standard_normal(gripper.nv)
    res = cc.forward_dynamics(gripper, q, v, tau, method="kkt")
    assert cc.joint_reactions(gripper, q, v, res) == []
    tree = cc.joint_reactions(gripper, q, v, res, tree=True)
    _, J = _coupling_rows(gripper, q)
    transmitted = np.array([float(r.tau[0]) for r in tree])
    assert np.linalg.norm(transmitted - (tau - J.T @ res.lam)) <= ACCEL_RTOL * np.linalg.norm(tau)


# -- the compiled core's coupling rows against the numpy reference ---------------------

#: The four-bar finger with a <mimic> thumb (frame rows and coupling rows together).
MIMIC_FOURBAR = DATA_DIR / "mimic_fourbar.urdf"
#: Links of the chain whose coupling row takes the compiled core's tree path (nv > 12,
#: nc <= nv / 4).
TREE_CHAIN_LINKS = 30
#: Its coupling: joint j20 follows j5 (a gear between two links of one chain).
TREE_CHAIN_COUPLING = (
    '<loop name="gear" type="coupling"><joint name="j20"/>'
    '<mimics joint="j5" multiplier="0.5" offset="0.01"/></loop>'
)
# Compiled against numpy, the bounds of tests/test_percall.py (rows: the same formulas;
# accelerations, multipliers and velocities relative to 1 + max |x|; assembled
# configurations) and tests/test_compiled.py (runs: the same steps or the same error
# control; ill-conditioned solves: ROUNDOFF_FACTOR eps kappa, kappa the larger condition
# number of the KKT matrix and of J M^-1 J^T: the 30-link chain's accelerations reach 1e4
# rad/s^2 under unit torques, its v 23 rad/s, compared relative to 1 + max |v|).
#: ALI3-P's relative penalty on the 30-link chain (test_tree_solve.py's: the default, 1e11,
#: is more than its P = M + alpha J^T J takes).
CHAIN_ALI3P_PENALTY = 1e6
#: Duration [s] and step [s] of the run comparisons.
T_RUN, DT = 0.1, 1e-3
COMPILED_METHODS = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)
FIXED_STABS = ("none", "baumgarte", "projection", "partitioning", "stage-projection")
ADAPTIVE_STABS = ("none", "baumgarte", "projection", "partitioning")


@pytest.fixture(scope="module")
def coupled(gripper, tmp_path_factory):
    """``{name: mechanism}``: couplings alone (the gripper), with a loop (the four-bar
    finger), and on a long chain (the tree path)."""
    chain = tmp_path_factory.mktemp("coupled") / "chain_gear.urdf"
    chain.write_text(
        chain_urdf(TREE_CHAIN_LINKS).replace("</robot>", TREE_CHAIN_COUPLING + "</robot>")
    )
    return {
        "gripper": gripper,
        "mimic_fourbar": cc.load(MIMIC_FOURBAR),
        "chain_gear": cc.load(chain),
    }


def _scaled(x, ref, tol):
    return float(np.max(np.abs(x - ref), initial=0.0)) <= tol * (
        1.0 + float(np.max(np.abs(ref), initial=0.0))
    )


def _kappa(mech, q, v) -> float:
    """The larger condition number of the KKT matrix and of J M^-1 J^T at (q, v)."""
    ws = compute_terms(mech, q, v)
    M, J = ws.M, ws.J
    K = np.block([[M, J.T], [J, np.zeros((len(J), len(J)))]])
    return max(np.linalg.cond(K), np.linalg.cond(J @ np.linalg.solve(M, J.T)))


def test_the_chain_takes_the_tree_path(coupled):
    """The chain's rows (one coupling among them) are solved without forming M."""
    mech = coupled["chain_gear"]
    assert [r.kind for r in mech.rows].count(COUPLING_KIND) == 1
    assert compiled.compiled_dynamics(mech, "kkt").core.tree_solves()
    assert not compiled.compiled_dynamics(coupled["mimic_fourbar"], "kkt").core.tree_solves()


@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar", "chain_gear"])
def test_compiled_rows_equal_numpy(coupled, name, rng):
    """phi, J and gamma of the kept and of the declared rows, off the manifold too."""
    mech = coupled[name]
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        q = pin.integrate(mech.model, q, 1e-2 * rng.standard_normal(mech.nv))  # phi != 0
        v = v + 0.1 * rng.standard_normal(mech.nv)
        assert_rows_compiled_equal_numpy(mech, q, v)
        phi_d, J_d = compiled.declared_rows(mech, q)
        phi_ref = np.zeros(mech.declared.nc)
        J_ref = np.zeros((mech.declared.nc, mech.nv))
        pin.computeJointJacobians(mech.model, mech.data, q)
        mech.declared.evaluate(mech.model, mech.data, phi=phi_ref, J=J_ref)
        assert _scaled(phi_d, phi_ref, ROWS_PARITY_TOL)
        assert _scaled(J_d, J_ref, ROWS_PARITY_TOL)
    if name == "gripper":  # the coupling rows as written in the file
        phi_ref, J_ref = _coupling_rows(mech, q)
        np.testing.assert_allclose(
            cc.compute_phi(mech, q, backend="compiled"), phi_ref, atol=ROW_TOL
        )
        np.testing.assert_allclose(cc.compute_jacobian(mech, q, backend="compiled"), J_ref, atol=0)
        assert not np.any(cc.compute_gamma(mech, q, v, backend="compiled"))


@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar", "chain_gear"])
def test_compiled_forward_dynamics_equals_numpy(coupled, name, method, rng):
    mech = coupled[name]
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        c = cc.forward_dynamics(mech, q, v, tau, method=method, backend="compiled")
        n = cc.forward_dynamics(mech, q, v, tau, method=method, backend="numpy")
        rtol = max(BACKEND_PARITY_TOL, ROUNDOFF_FACTOR * np.finfo(float).eps * _kappa(mech, q, v))
        assert _scaled(c.a, n.a, rtol)
        assert _scaled(c.lam, n.lam, rtol)
        if name == "gripper":  # and the independent KKT solution
            a_ref = _kkt_reference(GRIPPER, mech, q, v, tau)
            assert np.linalg.norm(c.a - a_ref) <= ACCEL_RTOL * np.linalg.norm(a_ref)


@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar", "chain_gear"])
def test_compiled_per_call_functions_equal_numpy(coupled, name, rng):
    """project_velocity, assemble and inverse_dynamics on both backends."""
    mech = coupled[name]
    q, v = cc.random_consistent_state(mech, rng)
    w = rng.standard_normal(mech.nv)
    for fixed in ((), "independent"):
        c = cc.project_velocity(mech, q, w, fixed=fixed, backend="compiled")
        n = cc.project_velocity(mech, q, w, fixed=fixed, backend="numpy")
        assert _scaled(c, n, BACKEND_PARITY_TOL)
        guess = pin.integrate(mech.model, q, 0.05 * rng.standard_normal(mech.nv))
        c = cc.assemble(mech, guess, fixed=fixed, backend="compiled")
        n = cc.assemble(mech, guess, fixed=fixed, backend="numpy")
        assert np.max(np.abs(c - n)) <= ASSEMBLY_PARITY_TOL
    a_P = rng.standard_normal(mech.mobility)
    c = cc.inverse_dynamics(mech, q, v, a_P, actuated="independent", backend="compiled")
    n = cc.inverse_dynamics(mech, q, v, a_P, actuated="independent", backend="numpy")
    for field in ("tau", "a", "lam"):
        assert _scaled(getattr(c, field), getattr(n, field), BACKEND_PARITY_TOL)


def _state(mech):
    q = mech.q_ref.copy()
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = 0.3
    return q, cc.project_velocity(mech, q, v, fixed="independent")


def _pair(mech, t_final, **kw):
    q0, v0 = _state(mech)
    a = cc.simulate(mech, q0, v0, t_final, backend="compiled", **kw)
    b = cc.simulate(mech, q0, v0, t_final, backend="numpy", **kw)
    assert (a.info.backend, b.info.backend) == ("compiled", "numpy")
    return a, b


@pytest.mark.parametrize("stab", FIXED_STABS)
@pytest.mark.parametrize("integrator", ["euler", "semi-implicit", "rk4"])
@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar"])
def test_compiled_fixed_step_runs_equal_numpy(coupled, name, integrator, stab):
    mech = coupled[name]
    a, b = _pair(mech, T_RUN, integrator=integrator, stabilization=stab, dt=DT)
    assert a.info.steps == b.info.steps
    assert np.max(np.abs(a.q - b.q)) <= FIXED_STEP_TOL
    assert _scaled(a.v, b.v, FIXED_STEP_TOL)
    assert np.max(np.abs(a.constraint_residual - b.constraint_residual)) <= FIXED_STEP_TOL


def test_random_states_keep_the_couplings(coupled, rng):
    """Random consistent states satisfy every coupling: a coupled joint is never wrapped
    by a turn (q_j = m q_i + c ties coordinates, not poses)."""
    mech = coupled["mimic_fourbar"]
    for _ in range(4 * N_STATES):
        q, _ = cc.random_consistent_state(mech, rng)
        assert np.max(np.abs(cc.compute_phi(mech, q, backend="numpy"))) <= cc.AssemblySettings().tol


@pytest.mark.parametrize("stab", ADAPTIVE_STABS)
@pytest.mark.parametrize("integrator", ["RK45", "DOP853"])
@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar"])
def test_compiled_adaptive_runs_equal_numpy(coupled, name, integrator, stab):
    mech = coupled[name]
    a, b = _pair(mech, T_RUN, integrator=integrator, stabilization=stab, rtol=RTOL, atol=ATOL)
    assert abs(a.info.steps - b.info.steps) <= STEP_COUNT_SLACK
    assert np.max(np.abs(a.q[-1] - b.q[-1])) <= ADAPTIVE_TOL
    assert np.max(np.abs(a.v[-1] - b.v[-1])) <= ADAPTIVE_TOL


@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar", "chain_gear"])
def test_compiled_methods_run_equal_numpy(coupled, name, method):
    """Every method in a run of rk4 with the stage projection, and the default
    integrator (rk43) and ALI3-P, with the couplings held."""
    mech = coupled[name]
    a, b = _pair(
        mech, T_RUN, integrator="rk4", stabilization="stage-projection", dt=DT, method=method
    )
    assert np.max(np.abs(a.q - b.q)) <= FIXED_STEP_TOL
    assert _scaled(a.v, b.v, FIXED_STEP_TOL)


@pytest.mark.parametrize("integrator", ["rk43", "ali3p"])
@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar", "chain_gear"])
def test_compiled_default_and_ali3p_runs_equal_numpy(coupled, name, integrator):
    mech = coupled[name]
    kw = {"dt": DT} if integrator == "ali3p" else {}
    if integrator == "ali3p" and name == "chain_gear":
        kw["settings"] = cc.SimulationSettings(ali3p_penalty=CHAIN_ALI3P_PENALTY)
    a, b = _pair(mech, T_RUN, integrator=integrator, **kw)
    assert np.max(np.abs(a.q[-1] - b.q[-1])) <= ADAPTIVE_TOL
    assert np.max(np.abs(a.v[-1] - b.v[-1])) <= ADAPTIVE_TOL
    assert np.max(np.abs(a.constraint_residual)) <= COUPLING_DRIFT_TOL


# -- validation against Pinocchio's mimic joints -----------------------------------------

#: States per validation.
N_VALIDATION = 10


@pytest.mark.parametrize("name", ["gripper", "mimic_fourbar"])
def test_validate_checks_couplings_on_pinocchio_mimic_joints(coupled, name):
    rep = cc.validate(coupled[name], n_samples=N_VALIDATION)
    assert rep.reference == "pinocchio mimic joints"
    assert rep.passed, rep


def test_validate_checks_a_coupling_loop_beside_a_loop(tmp_path):
    """The thumb tip's <mimic> written as a coupling loop: the reference takes its
    numbers from the loop (Pinocchio's reader knows no coupling loop)."""
    path = tmp_path / "coupling_fourbar.urdf"
    text = MIMIC_FOURBAR.read_text()
    mimic = '<mimic joint="rocker_joint" multiplier="0.5" offset="-0.1"/>'
    loop = (
        '<loop name="tip" type="coupling"><joint name="thumb_tip_joint"/>'
        '<mimics joint="rocker_joint" multiplier="0.5" offset="-0.1"/></loop>'
    )
    path.write_text(text.replace(mimic, "").replace("</robot>", loop + "</robot>"))
    mech = cc.load(path)
    assert "tip" in [spec.name for spec in mech.declared.couplings]
    rep = cc.validate(mech, n_samples=N_VALIDATION)
    assert rep.passed, rep


def test_mimic_reference_is_pinocchios_own_urdf_mimic_model(coupled, rng):
    """The reference's reduced M and h are those of ``buildModelFromUrdf(path, mimic=True)``."""
    mech = coupled["mimic_fourbar"]
    ref = validation.mimic_reference(mech)
    own = pin.buildModelFromUrdf(str(MIMIC_FOURBAR), mimic=True)
    own.gravity = mech.model.gravity
    data = own.createData()
    assert [own.names[j] for j in range(1, own.njoints) if own.joints[j].nv] == [
        mech.model.names[j] for j in range(1, ref.model.njoints) if ref.model.joints[j].nv
    ]
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        q_r, v_r = q[ref.q_index], v[ref.v_index]
        M_ref = pin.crba(ref.model, ref.data, q_r).copy()
        np.testing.assert_allclose(M_ref, pin.crba(own, data, q_r), rtol=0, atol=ROW_TOL)
        np.testing.assert_allclose(
            pin.nonLinearEffects(ref.model, ref.data, q_r, v_r),
            pin.nonLinearEffects(own, data, q_r, v_r),
            rtol=0,
            atol=ROW_TOL,
        )


def test_validate_fails_on_a_wrong_multiplier(tmp_path):
    """closedchain's rows with multiplier 0.5 where the file, read again by the
    validation, says 0.6: the reference follows the file, and validation fails."""
    mech = cc.load(MIMIC_FOURBAR)
    good = 'multiplier="0.5" offset="-0.1"'
    text = MIMIC_FOURBAR.read_text()
    assert good in text
    changed = tmp_path / MIMIC_FOURBAR.name
    changed.write_text(text.replace(good, 'multiplier="0.6" offset="-0.1"'))
    mech.description = dataclasses.replace(mech.description, path=changed)
    rep = cc.validate(mech, n_samples=N_VALIDATION)
    assert not rep.passed
    assert rep.max_da_mass_norm > rep.tol_a
