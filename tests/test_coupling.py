"""Coupling loops q_j = m q_i + c: URDF ``<mimic>`` and ``<loop type="coupling">``.

The references are independent of closedchain's constraint layer: the couplings'
numbers are written here from tests/data/mimic_gripper.urdf, the tree's M and h
come from a Pinocchio model built from the file, and the constrained accelerations
from a KKT system solved in the test; Pinocchio's own mimic joints (``mimic=True``,
reduced coordinates, RNEA) check the ``<mimic>`` couplings once more.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR
from lxml import etree

import closedchain as cc
from closedchain.exceptions import InvalidArgumentError, URDFError, ValidationUnavailableError

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
    joint_of = {spec.name: spec.joint for spec in mech.urdf.loops}
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
    loops = {spec.joint: spec for spec in gripper.urdf.loops}
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


def test_auto_backend_falls_back_and_says_why(gripper):
    traj = cc.simulate(gripper, gripper.q_ref, np.zeros(gripper.nv), 0.05)
    assert traj.info.backend == "numpy"
    assert "no joint-coupling rows" in traj.info.backend_fallback


def test_compiled_backend_refuses_couplings(gripper):
    with pytest.raises(InvalidArgumentError, match=r"no joint-coupling rows .*'right_tip'"):
        cc.simulate(gripper, gripper.q_ref, np.zeros(gripper.nv), 0.05, backend="compiled")


def test_validate_has_no_pinocchio_reference_for_couplings(gripper):
    with pytest.raises(ValidationUnavailableError, match="no Pinocchio reference for coupling"):
        cc.validate(gripper, n_samples=1)


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
    with pytest.raises(URDFError, match=match):
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
    with pytest.raises(URDFError, match=match):
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
