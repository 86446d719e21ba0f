"""Tests of closedchain.mechanism: row selection, coordinates, gravity, loading.

Expected row counts come from first principles (the number of relative
motions a closure forbids in the space the mechanism moves in), checked
against the numerical rank of the declared rows; the gravity test uses the
4-bar's closed-form centre-of-mass positions.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
import yourdfpy
from conftest import DATA_DIR as DATA
from conftest import MODELS, SHIPPED_MECHANISMS

import closedchain as cc

#: Rank threshold for the declared Jacobian (relative to its largest singular value).
RANK_RTOL = 1e-9
#: Generalized gravity against the closed form [N m].
TOL_GRAVITY = 1e-12

# name: (declared rows, independent rows, mobility, why)
ROW_COUNTS = {
    # Planar: a revolute cut leaves 2 in-plane translations to close; the
    # out-of-plane translation and both tilts vanish identically.
    "fourbar": (5, 2, 1),
    # Spherical wrist: every axis meets the centre, so the 3 translations of
    # each revolute cut vanish identically; each cut closes 2 tilts.
    "agile_eye": (15, 6, 3),
    # Spatial spherical cut: 3 translations.
    "spherical_chain": (3, 3, 1),
    # Spatial prismatic cut: 2 translations across the axis + 3 rotations.
    "slider_crank": (5, 5, 1),
    # Planar prismatic cut: the in-plane offset across the axis + the in-plane rotation.
    "slider_crank_planar": (5, 2, 1),
    # Spatial fixed cut: 3 translations + 3 rotations.
    "fixed_branches": (6, 6, 1),
    # The planar 4-bar on a turntable: the same 2 rows in every turntable angle.
    "turntable_fourbar": (5, 2, 2),
    # Bricard's 6R: Gruebler 0, but one of the 5 cut rows is dependent everywhere.
    "bricard": (5, 4, 1),
}

EXPECTED_INDEPENDENT = {
    "fourbar": ["crank_joint"],
    "agile_eye": ["actuator_1", "actuator_2", "actuator_3"],
    "spherical_chain": ["j1"],
    "slider_crank": ["crank_joint"],
    "slider_crank_planar": ["crank_joint"],
    "fixed_branches": ["a_j1"],
}


def declared_jacobian(mech, q):
    pin.computeJointJacobians(mech.model, mech.data, q)
    J = np.zeros((mech.declared.nc, mech.nv))
    mech.declared.evaluate(mech.model, mech.data, J=J)
    return J


def numerical_rank(J):
    s = np.linalg.svd(J, compute_uv=False)
    return int(np.sum(s > RANK_RTOL * max(s[0], 1.0)))


@pytest.mark.parametrize("name", list(ROW_COUNTS))
def test_row_selection_counts(load_mechanism, rng, name):
    mech = load_mechanism(name)
    declared, independent, mobility = ROW_COUNTS[name]
    assert mech.declared.nc == declared
    assert mech.nc == independent
    assert len(mech.rows) == independent
    assert len(mech.selected_rows) == independent
    assert mech.mobility == mobility == mech.nv - independent
    # The count is the rank of all declared rows at assembled states, and the
    # selected rows keep full rank there.
    for _ in range(3):
        q, _ = cc.random_consistent_state(mech, rng)
        assert numerical_rank(declared_jacobian(mech, q)) == independent
        s = np.linalg.svd(cc.compute_jacobian(mech, q), compute_uv=False)
        assert s[-1] > 1e-6


def test_fourbar_keeps_the_in_plane_translation_rows(fourbar):
    # In-plane translation in the coupler's cut frame (across the axis); the row along
    # the axis and the two tilt rows vanish identically in a planar linkage.
    assert [r.kind for r in fourbar.rows] == ["t1", "t2"]
    assert [r.label for r in fourbar.rows] == ["C.t1", "C.t2"]
    assert [r.kind for r in fourbar.declared.declared_rows] == ["t1", "t2", "ta", "r1", "r2"]


def test_agile_eye_keeps_two_tilt_rows_per_leg(agile_eye):
    per_loop = {}
    for r in agile_eye.rows:
        per_loop.setdefault(r.loop, []).append((r.kind, r.unit))
    assert per_loop == {f"leg{i}_platform": [("r1", "1"), ("r2", "1")] for i in (1, 2, 3)}


def test_planar_prismatic_keeps_one_translation_and_one_rotation(load_mechanism):
    mech = load_mechanism("slider_crank_planar")
    assert sorted(r.unit for r in mech.rows) == ["1", "m"]


@pytest.mark.parametrize("name", list(EXPECTED_INDEPENDENT))
def test_independent_coordinates_are_the_actuated_joints(load_mechanism, name):
    mech = load_mechanism(name)
    names = EXPECTED_INDEPENDENT[name]
    expected = np.concatenate([mech.joint_indices_v(j) for j in names])
    assert np.array_equal(mech.independent_idx_v, expected)
    assert np.array_equal(mech.actuated_idx_v, expected)
    assert mech.independent_source == "actuated"
    assert sorted(np.r_[mech.independent_idx_v, mech.dependent_idx_v]) == list(range(mech.nv))
    assert [mech.coordinate_names[i] for i in mech.independent_idx_v] == names


def _mark_independent(text: str, *joints: str) -> str:
    for joint in joints:
        old = f'<joint name="{joint}" type="revolute">'
        assert text.count(old) == 1
        text = text.replace(old, f'<joint name="{joint}" type="revolute" independent="true">')
    return text


def test_urdf_independent_attribute_overrides(fourbar, mechanism_files, tmp_path):
    path = tmp_path / "fourbar_rocker_independent.urdf"
    path.write_text(_mark_independent(mechanism_files["fourbar"].read_text(), "rocker_joint"))
    mech = cc.load(path)
    assert mech.independent_source == "urdf"
    assert [mech.coordinate_names[i] for i in mech.independent_idx_v] == ["rocker_joint"]
    assert [mech.coordinate_names[i] for i in mech.dependent_idx_v] == [
        "crank_joint",
        "coupler_joint",
    ]
    # The actuator is still the crank: independent and actuated are different notions.
    assert [mech.coordinate_names[i] for i in mech.actuated_idx_v] == ["crank_joint"]


def test_urdf_independent_attribute_overrides_spatial(mechanism_files, tmp_path):
    text = mechanism_files["fixed_branches"].read_text()
    path = tmp_path / "fixed_branches_b_independent.urdf"
    path.write_text(_mark_independent(text, "b_j1"))
    mech = cc.load(path)
    assert mech.independent_source == "urdf"
    assert [mech.coordinate_names[i] for i in mech.independent_idx_v] == ["b_j1"]
    assert [mech.coordinate_names[i] for i in mech.actuated_idx_v] == ["a_j1"]


def test_wrong_number_of_independent_joints_is_a_urdf_error(mechanism_files, tmp_path):
    path = tmp_path / "fourbar_two_independent.urdf"
    text = _mark_independent(mechanism_files["fourbar"].read_text(), "crank_joint", "rocker_joint")
    path.write_text(text)
    with pytest.raises(
        cc.ModelFileError,
        match=r"fourbar_two_independent\.urdf: 2 coordinates are marked "
        r'independent="true" \(crank_joint, rocker_joint\) but the mobility is 1',
    ):
        cc.load(path)


# -- gravity -------------------------------------------------------------------------------


def fourbar_generalized_gravity(cf, q, g):
    """Closed-form generalized gravity g(q) = -sum_i m_i (d p_i / d q)^T g [N m].

    Centres of mass of the unit-mass rods (models/fourbar.urdf header) in the
    the lesson's plane (x, y) = world (x, z): crank a/2 e(th2), coupler a e(th2) +
    b/2 e(th3), rocker D + c/2 e(th4).
    """
    th2, th3, th4 = cf.theta(q)
    a, b, c = cf.a, cf.b, cf.c

    def de(th):  # d e(th) / d th in world (x, y, z)
        return np.array([-math.sin(th), 0.0, math.cos(th)])

    dp_dtheta = [  # per body: columns d p / d theta_k, shape (3, 3)
        np.column_stack([a / 2 * de(th2), np.zeros(3), np.zeros(3)]),
        np.column_stack([a * de(th2), b / 2 * de(th3), np.zeros(3)]),
        np.column_stack([np.zeros(3), np.zeros(3), c / 2 * de(th4)]),
    ]
    masses = [1.0, 1.0, 1.0]
    return -sum(m * (Jp @ cf.T).T @ g for m, Jp in zip(masses, dp_dtheta, strict=True))


def test_gravity_default(fourbar, fourbar_closed_forms, rng):
    g = np.array([0.0, 0.0, -9.81])
    assert np.array_equal(fourbar.gravity, g)
    assert np.array_equal(fourbar.model.gravity.linear, g)
    for _ in range(20):
        q = rng.uniform(-np.pi, np.pi, 3)
        tau_g = pin.computeGeneralizedGravity(fourbar.model, fourbar.data, q)
        err = np.linalg.norm(tau_g - fourbar_generalized_gravity(fourbar_closed_forms, q, g))
        assert err <= TOL_GRAVITY


@pytest.mark.parametrize("g", [(0.0, 0.0, -1.62), (2.0, -3.0, 0.5), (0.0, 0.0, 0.0)])
def test_gravity_override(mechanism_files, fourbar_closed_forms, rng, g):
    mech = cc.load(mechanism_files["fourbar"], gravity=g)
    assert np.array_equal(mech.gravity, g)
    assert np.array_equal(mech.model.gravity.linear, g)
    for _ in range(20):
        q = rng.uniform(-np.pi, np.pi, 3)
        tau_g = pin.computeGeneralizedGravity(mech.model, mech.data, q)
        expected = fourbar_generalized_gravity(fourbar_closed_forms, q, np.array(g))
        assert np.linalg.norm(tau_g - expected) <= TOL_GRAVITY


@pytest.mark.parametrize("g", [(0.0, -9.81), (0.0, float("nan"), -9.81)])
def test_gravity_must_be_three_finite_numbers(mechanism_files, g):
    with pytest.raises(cc.ClosedChainError, match=r"gravity must be 3 finite numbers \[m/s\^2\]"):
        cc.load(mechanism_files["fourbar"], gravity=g)


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("g", [(1e308, 0.0, 0.0), (0.0, 6e5, 9e5)])
def test_gravity_norm_is_bounded(mechanism_files, g):
    """1e308 overflowed into numpy warnings and NaN torques; the norm is checked overflow-free."""
    from closedchain.mechanism import MAX_GRAVITY_NORM

    with pytest.raises(
        cc.ClosedChainError,
        match=r"is beyond the limit; valid: a norm of at most 1e\+06 m/s\^2",
    ):
        cc.load(mechanism_files["fourbar"], gravity=g)
    assert cc.load(mechanism_files["fourbar"], gravity=(0.0, 0.0, -MAX_GRAVITY_NORM)).nv == 3


# -- the files stay plain URDF for other tools ----------------------------------------------


@pytest.mark.parametrize("name", SHIPPED_MECHANISMS)
def test_model_files_load_in_other_urdf_readers(load_mechanism, mechanism_files, name):
    path = mechanism_files[name]
    mech = load_mechanism(name)
    robot = yourdfpy.URDF.load(str(path))
    assert robot.validate()
    # Fixed URDF joints become frames in Pinocchio, not joints.
    moving = [n for n, j in robot.joint_map.items() if j.type != "fixed"]
    assert sorted(moving) == sorted(mech.model.names[1:])
    assert sorted(robot.actuated_joint_names) == sorted(mech.model.names[1:])
    model = pin.buildModelFromUrdf(str(path))
    assert (model.nq, model.nv) == (mech.nq, mech.nv)
    assert list(model.names) == list(mech.model.names)


# -- coordinates, q_ref and sampling -------------------------------------------------------


@pytest.mark.parametrize("name", list(ROW_COUNTS))
def test_q_ref_is_assembled(load_mechanism, name):
    mech = load_mechanism(name)
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) <= cc.AssemblySettings().tol


@pytest.mark.parametrize("name", list(ROW_COUNTS))
def test_random_configuration_spans_one_turn_within_limits(load_mechanism, rng, name):
    """Revolute coordinates are drawn over [-pi, pi] clipped to their limits."""
    mech = load_mechanism(name)
    Q = np.array([mech.random_configuration(rng) for _ in range(400)])
    lo, hi = mech.model.lowerPositionLimit, mech.model.upperPositionLimit
    assert np.all(Q >= lo) and np.all(Q <= hi)
    margin = 0.1
    for j in range(1, mech.model.njoints):
        jm = mech.model.joints[j]
        if jm.nq != 1 or not jm.shortname().startswith("JointModelR"):
            continue
        i = jm.idx_q
        expected_lo, expected_hi = max(lo[i], -np.pi), min(hi[i], np.pi)
        name_j = mech.model.names[j]
        assert Q[:, i].min() < expected_lo + margin, (name_j, Q[:, i].min())
        assert Q[:, i].max() > expected_hi - margin, (name_j, Q[:, i].max())
        assert Q[:, i].min() >= expected_lo and Q[:, i].max() <= expected_hi


def test_coordinate_indices(fourbar):
    assert list(fourbar.coordinate_indices(["rocker_joint", 0])) == [0, 2]
    assert list(fourbar.coordinate_indices("actuated")) == [0]
    assert list(fourbar.coordinate_indices("dependent")) == [1, 2]
    assert list(fourbar.coordinate_indices("coupler_joint")) == [1]


def test_unknown_joint_lists_the_joints(fourbar):
    with pytest.raises(
        cc.ClosedChainError,
        match=r"unknown joint 'crank'; joints: crank_joint, coupler_joint, rocker_joint",
    ):
        fourbar.coordinate_indices(["crank"])


def test_velocity_index_out_of_range(fourbar):
    with pytest.raises(cc.ClosedChainError, match=r"velocity index 3 out of range 0\.\.2"):
        fourbar.coordinate_indices([3])


def test_continuous_joint_takes_two_configuration_entries(load_mechanism):
    mech = load_mechanism("slider_crank")
    assert (mech.nq, mech.nv) == (7, 6)
    assert list(mech.joint_indices_v("crank_joint")) == [0]
    assert mech.coordinate_names[0] == "crank_joint"


def test_summary_is_json_serialisable_and_consistent(agile_eye):
    import json

    s = json.loads(json.dumps(agile_eye.summary()))
    assert (s["declared_rows"], s["independent_rows"], s["mobility"]) == (15, 6, 3)
    assert s["independent"] == ["actuator_1", "actuator_2", "actuator_3"]
    assert s["pinocchio_reference"] is True
    assert [lp["name"] for lp in s["loops"]] == [f"leg{i}_platform" for i in (1, 2, 3)]
    assert all(len(lp["declared_rows"]) == 5 for lp in s["loops"])


def test_summary_reports_no_pinocchio_reference_for_prismatic_loops(load_mechanism):
    assert load_mechanism("slider_crank").summary()["pinocchio_reference"] is False


def test_configuration_off_the_unit_circle_is_refused(load_mechanism):
    """A continuous joint's (cos, sin) of norm 3 would give Pinocchio a scaled rotation."""
    mech = load_mechanism("slider_crank")
    q = mech.q_ref.copy()
    jm = mech.model.joints[mech.model.getJointId("crank_joint")]
    q[jm.idx_q : jm.idx_q + 2] *= 3.0
    with pytest.raises(cc.ClosedChainError, match=r"joint 'crank_joint'.*has norm 3"):
        cc.forward_dynamics(mech, q, np.zeros(mech.nv))


# -- digest: the model a trajectory depends on ----------------------------------------------


def test_digest_is_the_same_in_a_fresh_process(fourbar):
    code = f"import closedchain as cc; print(cc.load({str(fourbar.path)!r}).digest())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == fourbar.digest()


def test_digest_ignores_path_comments_visuals_actuation_and_gravity(fourbar, tmp_path):
    text = fourbar.path.read_text()
    text = text.replace("<robot ", "<!-- a copy -->\n<robot ").replace(
        '<box size="0.2 0.012 0.02"/>', '<box size="0.2 0.05 0.05"/>'
    )
    text = text.replace(' effort="50"', ' effort="10"')
    path = tmp_path / "elsewhere" / "copy.urdf"
    path.parent.mkdir()
    path.write_text(text)
    copy = cc.load(path, gravity=(0.0, 0.0, -1.62))
    assert copy.digest() == fourbar.digest()


@pytest.mark.parametrize(
    ("old", "new"),
    [
        ('<successor_origin xyz="0.3 0 0"', '<successor_origin xyz="0.32 0 0"'),  # loop
        ('<origin xyz="0.5 0 0" rpy="0 0 0"/>', '<origin xyz="0.51 0 0" rpy="0 0 0"/>'),  # joint
        ('<mass value="1.0"/>\n      <!-- m c^2', '<mass value="1.1"/>\n      <!-- m c^2'),
        ('ixx="0" ixy="0" ixz="0" iyy="0.0075"', 'ixx="0.001" ixy="0" ixz="0" iyy="0.0075"'),
        ('<loop name="C"', '<loop name="D"'),
    ],
)
def test_digest_changes_with_dimensions_masses_and_loops(fourbar, tmp_path, old, new):
    text = fourbar.path.read_text()
    assert text.count(old) == 1
    path = tmp_path / "changed.urdf"
    path.write_text(text.replace(old, new))
    assert cc.load(path).digest() != fourbar.digest()


def test_digest_ignores_the_last_bits(fourbar, tmp_path):
    """A different libm's last bit in sin/cos must not make another mechanism."""
    text = fourbar.path.read_text()
    path = tmp_path / "last_bit.urdf"
    path.write_text(text.replace('<mass value="1.0"/>', '<mass value="1.0000000000000002"/>'))
    assert cc.load(path).digest() == fourbar.digest()


# -- size limits (a tree too large is refused before any work) -----------------------------


@pytest.mark.parametrize("n", [5000, pytest.param(50_000, marks=pytest.mark.slow)])
def test_tree_beyond_the_supported_size_is_refused_before_work(tmp_path, n):
    from closedchain.benchmark.families import chain_urdf
    from closedchain.pindata import data_bytes, data_cost_formula, max_nv_for

    path = tmp_path / f"chain{n}.urdf"
    path.write_text(chain_urdf(n))
    with pytest.raises(cc.ModelTooLargeError) as exc:
        cc.load(path)
    msg = str(exc.value)
    limit = max_nv_for(2e9)
    assert msg.startswith(f"{path}: {n} joints with nv = {n} degrees of freedom are beyond")
    assert f"valid: nv <= {limit}" in msg
    assert f"one Pinocchio Data takes {data_cost_formula()}" in msg
    assert f"{data_bytes(n):.3g} here, over LoadSettings.max_data_bytes = 2e+09" in msg
    assert (exc.value.nv, exc.value.max_nv) == (n, limit)


def test_size_limit_is_a_setting(tmp_path):
    from closedchain.benchmark.families import chain_urdf
    from closedchain.pindata import data_bytes

    path = tmp_path / "chain12.urdf"
    path.write_text(chain_urdf(12))
    budget = (data_bytes(11) + data_bytes(12)) / 2
    with pytest.raises(cc.ModelTooLargeError, match=r"nv = 12 .*valid: nv <= 11"):
        cc.load(path, settings=cc.LoadSettings(max_data_bytes=budget))
    mech = cc.load(path)
    assert (mech.nv, mech.nc, mech.mobility) == (12, 2, 10)


#: Steps of the 1000-link chain in the CI run (each ~0.2 s CPU: four 1002 x 1002 KKT
#: solves); the whole second is a benchmark run (below).
CHAIN1000_CI_STEPS = 5


@pytest.fixture(scope="module")
def chain1000(tmp_path_factory):
    from closedchain.benchmark.families import chain_urdf

    path = tmp_path_factory.mktemp("chain1000") / "chain1000.urdf"
    path.write_text(chain_urdf(1000, length=1000.0))
    return cc.load(path)


@pytest.mark.slow
def test_a_1000_link_chain_with_one_loop_loads_and_takes_its_first_steps(chain1000):
    """The 1000-link chain loads (lean Data: no nv^3 tensors) and its first steps keep the
    loop closed and the energy; the full second is test_..._simulates_one_second."""
    mech = chain1000
    assert (mech.nv, mech.nc, mech.mobility) == (1000, 2, 998)
    dt = 1e-3
    traj = cc.simulate(
        mech,
        mech.q_ref,
        np.zeros(mech.nv),
        CHAIN1000_CI_STEPS * dt,
        method="kkt",
        integrator="rk4",
        dt=dt,
        solver_settings=cc.SolverSettings(cond_max=1e15),
    )
    assert traj.info.steps == CHAIN1000_CI_STEPS
    assert traj.max_constraint_residual <= 1e-9
    assert traj.energy_drift <= 1e-8
    assert np.all(np.isfinite(traj.q))


@pytest.mark.slow
@pytest.mark.benchmark
def test_a_1000_link_chain_with_one_loop_loads_and_simulates_one_second(tmp_path):
    """The size the issue asks for: 1000 one-metre links, the tip pinned (one loop).

    Measured (README, "Input checks and size limits"): load 9.5 s CPU, 1 s of
    rk4 at dt = 1 ms with the KKT method 1000 steps / 4001 evaluations / 209 s
    CPU, 0.7 GB peak. A uniform chain's mass matrix has a condition number
    near 1e12 at n = 1000, so the numpy KKT's default cond_max refuses it by name
    and the run raises the bound (the compiled core's tree path checks J M^-1 J^T).
    """
    from closedchain.benchmark.families import chain_urdf

    path = tmp_path / "chain1000.urdf"
    path.write_text(chain_urdf(1000, length=1000.0))
    mech = cc.load(path)
    assert (mech.nv, mech.nc, mech.mobility) == (1000, 2, 998)
    v0 = np.zeros(mech.nv)
    with pytest.raises(cc.SingularConfigurationError, match=r"> cond_max 1\.0e\+12"):
        cc.simulate(mech, mech.q_ref, v0, 1e-3, method="kkt", integrator="rk4", backend="numpy")
    traj = cc.simulate(
        mech,
        mech.q_ref,
        v0,
        1.0,
        method="kkt",
        integrator="rk4",
        t_eval=np.linspace(0.0, 1.0, 11),
        solver_settings=cc.SolverSettings(cond_max=1e15),
    )
    assert traj.t[-1] == 1.0 and traj.info.steps == 1000
    assert traj.max_constraint_residual <= 1e-9
    assert traj.energy_drift <= 1e-8
    assert np.all(np.isfinite(traj.q))


#: Chains that the default method refused at t = 0 while its penalty was rho tr(M) /
#: tr(J^T J) alone (issue #24): M's smallest eigenvalue is 2e-5 (n = 30), 2e-6 (n = 100).
PENALTY_CHAINS = (30, 100)
#: Their simulated time [s] (the default integrator: rk4 at 1 ms, stage projection).
PENALTY_CHAIN_T = 0.02
#: Agreement of the default method with "kkt" at q_ref, |a - a_kkt| / max |a_kkt| (both
#: carry round-off of order eps cond(M), cond(M) = 2e8 at n = 100; measured 1.4e-9).
TOL_CHAIN_A = 1e-8
#: Agreement of the trajectories of the default method and of "kkt" (rk4 at 1 ms, stage
#: projection: mass-orthogonal for the one, minimum-norm for the other), max |q - q_kkt|
#: [rad]; measured 2.4e-8 (n = 30) and 2.0e-7 (n = 100), where rk4's own error against
#: DOP853 at rtol 1e-12 is 1e-7 and 3e-5.
TOL_CHAIN_Q = 1e-6


@pytest.fixture(scope="module")
def penalty_chain(tmp_path_factory):
    from closedchain.benchmark.families import chain_urdf

    cache: dict = {}

    def get(n: int) -> cc.Mechanism:
        if n not in cache:
            path = tmp_path_factory.mktemp("chains") / f"chain{n}.urdf"
            path.write_text(chain_urdf(n))
            cache[n] = cc.load(path)
        return cache[n]

    return get


@pytest.mark.parametrize("n", PENALTY_CHAINS)
def test_long_chain_runs_under_the_default_method(penalty_chain, n):
    """The default method lowers its penalty to what P = M + alpha J^T J can take and
    agrees with the KKT solve."""
    mech = penalty_chain(n)
    v = np.zeros(mech.nv)
    res = cc.forward_dynamics(mech, mech.q_ref, v)
    ref = cc.forward_dynamics(mech, mech.q_ref, v, method="kkt")
    assert res.method == "augmented-lagrangian"
    assert np.max(np.abs(res.a - ref.a)) <= TOL_CHAIN_A * np.max(np.abs(ref.a))


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
@pytest.mark.parametrize("n", PENALTY_CHAINS)
def test_long_chain_simulates_under_the_default_method(penalty_chain, n, backend):
    """simulate's defaults (augmented-lagrangian, rk4, stage projection) follow the KKT
    method's trajectory on either backend."""
    from closedchain import compiled

    if backend == "compiled" and not compiled.available():
        pytest.skip("the compiled core is not built")
    mech = penalty_chain(n)
    v0 = np.zeros(mech.nv)
    t_eval = np.linspace(0.0, PENALTY_CHAIN_T, 3)
    traj = cc.simulate(mech, mech.q_ref, v0, PENALTY_CHAIN_T, t_eval=t_eval, backend=backend)
    ref = cc.simulate(mech, mech.q_ref, v0, PENALTY_CHAIN_T, t_eval=t_eval, method="kkt")
    assert traj.info.method == "augmented-lagrangian"
    assert np.max(np.abs(traj.q - ref.q)) <= TOL_CHAIN_Q
    assert traj.max_constraint_residual <= 1e-9


# -- Mechanism.q_from: named joint values to q ---------------------------------------------

#: Round-off bound of a configuration built two ways (cos/sin, quaternions) [-].
Q_FROM_TOL = 1e-12
#: Closure residual an assembled slider-crank reaches [m or rad].
Q_FROM_CLOSURE_TOL = 1e-9


def test_q_from_writes_a_continuous_joint_as_pinocchio_integrates_it():
    mech = cc.load(DATA / "slider_crank.urdf")
    angle = 2.5  # rad, past pi / 2 so that cos < 0
    zero = mech.q_from({"crank_joint": 0.0})
    dv = np.zeros(mech.nv)
    dv[mech.joint_indices_v("crank_joint")] = angle
    expected = pin.integrate(mech.model, zero, dv)
    assert np.linalg.norm(mech.q_from({"crank_joint": angle}) - expected) < Q_FROM_TOL


def test_q_from_then_assemble_holds_the_crank_and_closes_the_loop():
    mech = cc.load(DATA / "slider_crank.urdf")
    angle = 2.0
    q = cc.assemble(mech, mech.q_from({"crank_joint": angle}), fixed=["crank_joint"])
    jm = mech.model.joints[mech.model.getJointId("crank_joint")]
    cos, sin = q[jm.idx_q : jm.idx_q + 2]
    assert abs(math.atan2(sin, cos) - angle) < Q_FROM_TOL
    assert np.max(np.abs(cc.compute_phi(mech, q))) < Q_FROM_CLOSURE_TOL


def test_q_from_takes_a_rotation_or_a_quaternion_for_a_spherical_joint():
    mech = cc.load(DATA / "yaml_offset_rod.urdf", loops=DATA / "yaml_offset_rod_ball.yaml")
    rotvec = np.array([0.3, -0.2, 0.5])
    rotation = pin.exp3(rotvec)
    identity = mech.q_from({"spherical_rod": np.eye(3)})
    dv = np.zeros(mech.nv)
    dv[mech.joint_indices_v("spherical_rod")] = rotvec
    expected = pin.integrate(mech.model, identity, dv)
    for value in (rotation, pin.Quaternion(rotation), pin.Quaternion(rotation).coeffs()):
        q = mech.q_from({"spherical_rod": value})
        assert np.linalg.norm(q - expected) < Q_FROM_TOL, type(value)


def test_q_from_places_a_free_flyer_at_an_se3():
    mech = cc.load(MODELS / "fourbar.urdf", root_joint="free")
    placement = pin.SE3(pin.exp3(np.array([0.1, 0.2, -0.3])), np.array([1.0, -2.0, 0.5]))
    q = mech.q_from({"root_joint": placement})
    data = mech.model.createData()
    pin.forwardKinematics(mech.model, data, q)
    root = mech.model.getJointId("root_joint")
    assert np.linalg.norm(pin.log6(data.oMi[root].inverse() * placement).vector) < Q_FROM_TOL


@pytest.mark.parametrize(
    ("values", "match"),
    [
        ({"crank": 0.1}, r"unknown joint 'crank'; joints: crank_joint, s1"),
        ({"crank_joint": [0.1, 0.2]}, r"joint 'crank_joint' takes an angle \[rad\]"),
        ({"crank_joint": math.nan}, r"joint 'crank_joint': nan is not finite"),
        ({"s1": "a"}, r"joint 's1' takes an angle \[rad\] or a displacement \[m\]"),
    ],
)
def test_q_from_names_the_bad_joint(values, match):
    mech = cc.load(DATA / "slider_crank.urdf")
    with pytest.raises(cc.InvalidArgumentError, match=match):
        mech.q_from(values)


@pytest.mark.parametrize(
    ("value", "match"),
    [
        (2.0 * np.eye(3), "not a rotation"),
        (np.array([0.0, 0.0, 0.0, 2.0]), "has norm 2, expected 1"),
        (np.zeros(2), "spherical: give a rotation matrix"),
    ],
)
def test_q_from_refuses_what_is_not_a_rotation(value, match):
    mech = cc.load(DATA / "yaml_offset_rod.urdf", loops=DATA / "yaml_offset_rod_ball.yaml")
    with pytest.raises(cc.InvalidArgumentError, match=match):
        mech.q_from({"spherical_rod": value})


def test_q_from_places_a_planar_root_at_x_y_angle():
    mech = cc.load(MODELS / "fourbar.urdf", root_joint="planar")
    x, y, angle = 0.3, -0.2, 2.0
    q = mech.q_from({"root_joint": (x, y, angle)})
    data = mech.model.createData()
    pin.forwardKinematics(mech.model, data, q)
    expected = pin.SE3(pin.exp3(np.array([0.0, 0.0, angle])), np.array([x, y, 0.0]))
    placement = data.oMi[mech.model.getJointId("root_joint")]
    assert np.linalg.norm(pin.log6(placement.inverse() * expected).vector) < Q_FROM_TOL


def test_the_former_names_still_reach_the_description(fourbar):
    # Formerly Mechanism.urdf, URDFPlus and URDFError: the same objects, the first
    # with a DeprecationWarning naming its successor.
    from closedchain.description import MechanismDescription
    from closedchain.urdf import URDFPlus

    with pytest.warns(DeprecationWarning, match=r"use Mechanism\.description"):
        old = fourbar.urdf
    assert old is fourbar.description
    assert isinstance(fourbar.description, MechanismDescription)
    assert URDFPlus is MechanismDescription
    assert cc.URDFError is cc.ModelFileError
    assert [spec.name for spec in fourbar.description.loops] == ["C"]
