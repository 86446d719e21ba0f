"""The compiled core against the numpy backend (the reference implementation).

Per evaluation the two must agree to round-off (:data:`EVAL_RTOL`); whole
trajectories run the same algorithm (same steps, same error control), so they
agree far below the integration tolerance (:data:`FIXED_STEP_TOL`,
:data:`ADAPTIVE_TOL`).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import scipy.integrate

import closedchain as cc
from closedchain import compiled
from closedchain.dynamics.base import METHOD_CAPABILITIES, compute_terms
from closedchain.simulate import COMPILED_INTEGRATORS, INTEGRATORS, SimulationError
from closedchain.simulate.problem import passing_hint

#: Per evaluation: |compiled - numpy| <= EVAL_RTOL * max(1, max |reference|) ...
EVAL_RTOL = 1e-12
#: ... or, for the solution of an ill-conditioned system, ROUNDOFF_FACTOR * eps * kappa
#: times that scale, kappa the larger 2-norm condition number of the KKT matrix and of
#: the Delassus matrix J M^-1 J^T (the Schur method's lam on the Agile Eye: kappa ~ 1e5,
#: both backends within eps * kappa of the exact solution, 2.4e-12 apart).
ROUNDOFF_FACTOR = 10.0
#: Fixed-step trajectories (same arithmetic, round-off grows over the steps) [rad, rad/s].
FIXED_STEP_TOL = 1e-9
#: Adaptive trajectories at RTOL/ATOL below: agreement within the integration tolerance.
RTOL, ATOL = 1e-9, 1e-11
ADAPTIVE_TOL = 1e-7
#: The compiled DOP853 and scipy's on the same right-hand side: steps may differ by this many.
STEP_COUNT_SLACK = 3
#: Duration of the adaptive and fixed-step comparisons [s] (euler without
#: stabilization leaves the Agile Eye's manifold beyond drift_limit at 0.147 s) and step [s].
T_CMP, T_FIXED, DT = 0.3, 0.1, 1e-3

ROOT = Path(__file__).resolve().parent.parent
#: The shipped models the trajectories are compared on (nfourbar_2: two four-bars in
#: series, dropped rows in both loops).
MECHS = ["fourbar", "agile_eye", "nfourbar_2"]
ALL_MECHS = ["fourbar", "agile_eye", "spherical_chain", "slider_crank", "fixed_branches"]
COMPILED_METHODS = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)
#: Stabilizations of the compiled adaptive loops; the fixed-step ones add stage projection.
STABS = ["none", "baumgarte", "projection", "partitioning"]
FIXED_STABS = [*STABS, "stage-projection"]


@pytest.fixture(scope="module")
def mech_by_name(load_mechanism):
    """``get(name)``: the test mechanisms and the shipped models of models/."""
    cache: dict[str, cc.Mechanism] = {}

    def get(name: str) -> cc.Mechanism:
        if name not in cache:
            path = ROOT / "models" / f"{name}.urdf"
            cache[name] = cc.load(path) if path.exists() else load_mechanism(name)
        return cache[name]

    return get


def _kappa(mech, q, v):
    ws = compute_terms(mech, q, v)
    M, J = ws.M, ws.J
    K = np.block([[M, J.T], [J, np.zeros((mech.nc, mech.nc))]])
    D = J @ np.linalg.solve(M, J.T)
    return max(np.linalg.cond(K), np.linalg.cond(D))


def _close(x, ref, rtol=EVAL_RTOL):
    scale = max(1.0, float(np.max(np.abs(ref), initial=0.0)))
    return float(np.max(np.abs(np.asarray(x) - ref), initial=0.0)) <= rtol * scale


def test_core_is_built():
    assert compiled.available(), compiled.IMPORT_ERROR
    assert set(COMPILED_METHODS) >= {"kkt", "schur", "nullspace", "augmented-lagrangian", "reduced"}
    assert set(COMPILED_INTEGRATORS) == {
        "euler",
        "semi-implicit",
        "rk4",
        "rk43",
        "dop853-rk43",
        "RK45",
        "DOP853",
        "ali3p",
    }
    for name, spec in COMPILED_INTEGRATORS.items():
        assert spec.backend == "compiled"
        assert spec.kind == INTEGRATORS[name].kind


@pytest.mark.parametrize("baumgarte", [None, (10.0, 7.0)], ids=["exact", "baumgarte"])
@pytest.mark.parametrize("name", ALL_MECHS)
def test_rows_match_numpy(load_mechanism, name, baumgarte, rng):
    """phi, J and gamma (with Baumgarte terms) of every loop type, at random states."""
    mech = load_mechanism(name)
    fd = compiled.compiled_dynamics(mech, "kkt", cc.SolverSettings(baumgarte=baumgarte))
    for _ in range(5):
        q, v = cc.random_consistent_state(mech, rng)
        v = v + 0.1 * rng.standard_normal(mech.nv)  # off J v = 0: exercises every term
        q = pin.integrate(mech.model, q, 1e-2 * rng.standard_normal(mech.nv))  # phi != 0
        phi, J, gamma = fd.rows(q, v)
        ws = compute_terms(mech, q, v, baumgarte)
        phi_ref = np.zeros(mech.nc)
        mech.constraints.evaluate(mech.model, mech.data, phi=phi_ref)
        assert _close(phi, phi_ref)
        assert _close(J, ws.J)
        assert _close(gamma, ws.gamma)


#: Joint sequences of the random trees below: (joint, parent index in the list or -1).
#: "unaligned": the shipped models' joint; "mixed": every revolute kind beside joints
#: that keep Pinocchio's visitor (prismatic, unbounded revolute, spherical, free
#: flyer), with branches so that subtrees are not suffixes of the chain. Depth-first
#: order, as every Pinocchio model the loader makes (the tree passes assume it).
_MIXED_JOINTS = ["free", "RX", "unaligned", "PZ", "PX", "RY", "spherical", "RZ", "RUBZ"]
_MIXED_PARENTS = [-1, 0, 1, 2, 3, 1, 5, 0, 7, 8, -1]
TREES = {
    "unaligned": [("unaligned", -1), *[("unaligned", k) for k in range(5)]],
    "mixed": list(zip([*_MIXED_JOINTS, "unaligned", "unaligned"], _MIXED_PARENTS, strict=True)),
}
REVOLUTE_KINDS = {"unaligned", "RX", "RY", "RZ"}


def _random_tree(kinds, rng):
    """A pinocchio.Model of the given joints with random placements, inertias, armature."""
    model = pin.Model()
    ids = []
    for kind, parent in kinds:
        if kind == "unaligned":
            axis = rng.normal(size=3)
            joint = pin.JointModelRevoluteUnaligned(axis / np.linalg.norm(axis))
        else:
            joint = {"RX": pin.JointModelRX, "RY": pin.JointModelRY, "RZ": pin.JointModelRZ,
                     "PX": pin.JointModelPX, "PZ": pin.JointModelPZ,
                     "RUBZ": pin.JointModelRUBZ, "spherical": pin.JointModelSpherical,
                     "free": pin.JointModelFreeFlyer}[kind]()  # fmt: skip
        placement = pin.SE3(pin.exp3(rng.normal(size=3)), rng.normal(size=3))
        jid = model.addJoint(0 if parent < 0 else ids[parent], joint, placement, f"j{len(ids)}")
        ids.append(jid)
        a = rng.normal(size=(3, 3))
        inertia = pin.Inertia(rng.uniform(0.5, 2.0), rng.normal(size=3), a @ a.T + np.eye(3))
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
    model.armature = rng.uniform(0.0, 0.1, model.nv)
    return model


@pytest.mark.parametrize("tree", sorted(TREES))
def test_tree_pass_matches_pinocchio(tree, rng, core_testing):
    """tree_terms.hpp (revolute path + Pinocchio's visitor for the other joints) against
    pinocchio.crba, nonLinearEffects, computeJointJacobians and forwardKinematics."""
    model = _random_tree(TREES[tree], rng)
    expected = [False] + [k in REVOLUTE_KINDS for k, _ in TREES[tree]]
    assert list(core_testing._revolute_joints(model)) == expected
    data = model.createData()
    for _ in range(5):
        q = pin.randomConfiguration(model, -np.pi * np.ones(model.nq), np.pi * np.ones(model.nq))
        v = rng.normal(size=model.nv)
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        h = pin.nonLinearEffects(model, data, q, v)
        J = pin.computeJointJacobians(model, data, q).copy()
        oMi = [data.oMi[i].homogeneous.copy() for i in range(model.njoints)]
        pin.forwardKinematics(model, data, q, v, np.zeros(model.nv))
        ov = np.column_stack([data.oMi[i].act(data.v[i]).vector for i in range(model.njoints)])
        oa = np.column_stack([data.oMi[i].act(data.a[i]).vector for i in range(model.njoints)])
        for at_kinematics in (False, True):
            got = core_testing._tree_terms(model, q, v, at_kinematics)
            assert _close(got["M"], M) and _close(got["h"], h)
            assert _close(got["J"], J)
            assert all(_close(g, r) for g, r in zip(got["oMi"], oMi, strict=True))
            assert _close(got["ov"], ov) and _close(got["oa"], oa)
        kin = core_testing._joint_kinematics(model, q)
        assert _close(kin["J"], J)
        assert all(_close(g, r) for g, r in zip(kin["oMi"], oMi, strict=True))


def test_the_production_module_has_no_test_helpers(core_testing):
    """The tree-pass and lean_data helpers live in closedchain._core_testing only."""
    from closedchain import _core

    helpers = ("_tree_terms", "_joint_kinematics", "_revolute_joints", "_lean_data_matches_full")
    assert all(hasattr(core_testing, h) and not hasattr(_core, h) for h in helpers)


def test_errors_are_declared_in_one_module():
    """The exceptions the compiled core raises are classes of closedchain.exceptions; the
    modules that declared two of them before re-export the same classes."""
    from closedchain import exceptions
    from closedchain.simulate import settings

    assert compiled.RowCheckRequired is exceptions.RowCheckRequired
    assert settings.SimulationError is exceptions.SimulationError is SimulationError


def test_core_settings_are_the_dataclasses_fields_with_their_defaults():
    """Each typed settings class of the core binds fields of its Python settings dataclass
    (same names; Ali3pSettings those after ``ali3p_``), with the dataclass's defaults."""
    from closedchain import _core

    for cls, source, prefix in (
        (_core.SolverSettings, cc.SolverSettings(), ""),
        (_core.SimulationSettings, cc.SimulationSettings(), ""),
        (_core.Ali3pSettings, cc.SimulationSettings(), "ali3p_"),
    ):
        core = cls()
        got = {name: getattr(core, name) for name in cls.fields}
        assert got == {name: getattr(source, prefix + name) for name in cls.fields}


def test_core_settings_take_the_dataclass_values_and_check_types():
    """compiled.core_settings copies every field; a value of the wrong type is refused by
    the binding, a Baumgarte pair of the wrong length by the core."""
    from closedchain import _core

    solver = cc.SolverSettings(cond_max=1e9, baumgarte=(3.0, 4.0), al_max_iter=7)
    core = compiled.core_settings(_core.SolverSettings, solver)
    assert (core.cond_max, core.baumgarte, core.al_max_iter) == (1e9, (3.0, 4.0), 7)
    sim = cc.SimulationSettings(drift_limit=0.5, projection_iters=3, project_velocities=False)
    core = compiled.core_settings(_core.SimulationSettings, sim)
    assert (core.drift_limit, core.projection_iters, core.project_velocities) == (0.5, 3, False)
    assert compiled.ali3p_settings(cc.SimulationSettings(ali3p_max_iter=9)).max_iter == 9
    with pytest.raises(TypeError, match=r"did not match C\+\+ signature"):
        core.drift_limit = "large"
    with pytest.raises(cc.ClosedChainError, match="baumgarte: None or the gains"):
        _core.SolverSettings().baumgarte = (1.0, 2.0, 3.0)


def test_generated_constants_header_is_up_to_date():
    """src/cpp/constants.hpp is what scripts/gen_constants.py writes from the Python
    constants it shares (run it after changing one of them)."""
    import importlib.util

    path = Path(__file__).resolve().parent.parent / "scripts" / "gen_constants.py"
    spec = importlib.util.spec_from_file_location("gen_constants", path)
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert gen.OUT.read_text() == gen.render(), "run python scripts/gen_constants.py"


@pytest.mark.parametrize("name", [*ALL_MECHS, "nfourbar_2"])
def test_declared_rows_match_numpy(mech_by_name, name, rng):
    """compiled.declared_rows (simulate's start checks): phi and J of every declared row,
    the dropped ones included, against the numpy layer at random states off phi = 0."""
    from closedchain.closure import layer_jacobian, layer_phi

    mech = mech_by_name(name)
    for _ in range(5):
        q, _ = cc.random_consistent_state(mech, rng)
        q = pin.integrate(mech.model, q, 1e-2 * rng.standard_normal(mech.nv))  # phi != 0
        phi, J = compiled.declared_rows(mech, q)
        phi_ref = layer_phi(mech.model, mech.data, mech.declared, q)
        assert np.max(np.abs(phi_ref)) > 1e-6  # an independent check that phi is exercised
        assert _close(phi, phi_ref)
        assert _close(J, layer_jacobian(mech.model, mech.data, mech.declared, q))
        # the kept rows are the selected rows of the declared ones
        assert _close(J[list(mech.selected_rows)], cc.compute_jacobian(mech, q))


def test_compiled_start_check_reselects_rows_as_numpy(mechanism_files):
    """The start check on compiled rows (Problem.check_start(compiled_rows=True)) finds an
    open dropped row and re-selects the rows as the numpy check does (test_closure's case:
    kept rows C.t1, C.ta, the dropped C.t2 open by more than 1e-2)."""
    from closedchain.kinematics import solve_closure
    from closedchain.simulate.problem import Problem

    outcomes = []
    for compiled_rows in (True, False):
        mech = cc.load(mechanism_files["fourbar"])
        labels = [r.label for r in mech.declared.declared_rows]
        mech.closure.active = mech.declared.restricted([labels.index("C.t1"), labels.index("C.ta")])
        q = solve_closure(
            mech.model,
            mech.data,
            mech.declared.restricted([labels.index("C.t1")]),
            np.radians([10.0, -65.0, -80.0]),
            np.array([1]),
            cc.AssemblySettings(),
        )
        problem = Problem(mech, "kkt", None, cc.SolverSettings(), cc.SimulationSettings())
        problem.check_start(q, compiled_rows=compiled_rows)
        J = problem.start_jacobian(q)
        outcomes.append((mech.row_selection.kept, mech.row_selection.reason, J))
    assert outcomes[0][0] == outcomes[1][0] == ("C.t1", "C.t2")
    # the same reason, to the kept rows' residual (round-off: 1.1e-17 and 1.4e-17)
    opened = [o[1].split(" (kept rows")[0] for o in outcomes]
    assert opened[0] == opened[1] and opened[0].startswith("dropped row C.t2 open by ")
    # after the re-selection, the start Jacobian is that of the new rows (not the compiled
    # one of the old rows): the numpy layer's J of C.t1, C.t2
    assert outcomes[0][2].shape == (2, 3) and np.array_equal(outcomes[0][2], outcomes[1][2])


@pytest.mark.parametrize("baumgarte", [None, (10.0, 7.0)], ids=["exact", "baumgarte"])
@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("name", ALL_MECHS)
def test_forward_matches_numpy(load_mechanism, name, method, baumgarte, rng):
    mech = load_mechanism(name)
    settings = cc.SolverSettings(baumgarte=baumgarte)
    fd = compiled.compiled_dynamics(mech, method, settings)
    for _ in range(5):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a, lam = fd.forward(q, v, tau)
        ref = cc.forward_dynamics(mech, q, v, tau, method=method, settings=settings)
        rtol = max(EVAL_RTOL, ROUNDOFF_FACTOR * np.finfo(float).eps * _kappa(mech, q, v))
        # a = M^-1 (tau - h - J^T lam) cancels terms larger than a itself: round-off
        # scales with the largest of them (slider_crank: |M^-1 J^T lam| ~ 10 |a|).
        ws = compute_terms(mech, q, v)
        constraint_term = np.linalg.solve(ws.M, ws.J.T @ ref.lam)
        scale = max(1.0, float(np.max(np.abs(ref.a))), float(np.max(np.abs(constraint_term))))
        assert np.max(np.abs(a - ref.a)) <= rtol * scale
        assert _close(lam, ref.lam, rtol)


def test_forward_singular_raises(fourbar):
    """Exactly singular KKT matrix (J = 0 rows impossible, so a zero mass matrix row is
    simulated by an absurd cond_max): the library's exception with q and condition."""
    fd = compiled.compiled_dynamics(fourbar, "kkt", cc.SolverSettings(cond_max=1.0))
    q = fourbar.q_ref
    with pytest.raises(cc.SingularConfigurationError, match="condition number") as exc:
        fd.forward(q, np.zeros(3), np.zeros(3))
    assert exc.value.condition_number > 1.0
    assert np.array_equal(exc.value.q, q)
    assert exc.value.t is None


#: cond_max just above / below the numpy estimate of cond_1(D K D) (relative).
COND_EDGE = 1e-6


@pytest.mark.parametrize("name", ALL_MECHS)
def test_kkt_condition_decision_at_the_bound(load_mechanism, name, rng):
    """The compiled kkt's condition decision (a cheap bound of cond_1(D K D) from K's LU
    factors, else the dlacn2-style estimate) is numpy's: at a cond_max just above the
    numpy backend's estimate (solve_kkt) it solves as numpy does, just below it raises
    with that estimate, as numpy does."""
    from closedchain.dynamics.kkt import solve_kkt

    mech = load_mechanism(name)
    for _ in range(3):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        ws = compute_terms(mech, q, v)
        _, _, rcond, info = solve_kkt(ws.M, ws.J, tau - ws.h, ws.gamma)
        assert info == 0 and rcond > 0
        cond = 1.0 / rcond
        above = cc.SolverSettings(cond_max=cond * (1 + COND_EDGE))
        a, lam = compiled.compiled_dynamics(mech, "kkt", above).forward(q, v, tau)
        ref = cc.forward_dynamics(mech, q, v, tau, method="kkt", settings=above)
        rtol = max(EVAL_RTOL, ROUNDOFF_FACTOR * np.finfo(float).eps * _kappa(mech, q, v))
        constraint_term = np.linalg.solve(ws.M, ws.J.T @ ref.lam)
        scale = max(1.0, float(np.max(np.abs(ref.a))), float(np.max(np.abs(constraint_term))))
        assert np.max(np.abs(a - ref.a)) <= rtol * scale
        assert _close(lam, ref.lam, rtol)
        below = cc.SolverSettings(cond_max=cond * (1 - COND_EDGE))
        with pytest.raises(cc.SingularConfigurationError) as exc:
            compiled.compiled_dynamics(mech, "kkt", below).forward(q, v, tau)
        assert exc.value.condition_number == pytest.approx(cond, rel=COND_EDGE / 10)


def test_bad_arguments_raise_library_errors(fourbar):
    fd = compiled.compiled_dynamics(fourbar, "kkt")
    with pytest.raises(cc.ClosedChainError, match="shape"):
        fd.forward(np.zeros(2), np.zeros(3), np.zeros(3))
    with pytest.raises(cc.ClosedChainError, match="no compiled implementation"):
        compiled.compiled_dynamics(fourbar, "proximal")


# -- trajectories -------------------------------------------------------------------------


def _state(mech, name):
    if name == "fourbar":
        q = cc.assemble(mech, np.radians((10.0, -65.0, -104.0)), fixed=["crank_joint"])
        return q, np.zeros(3)
    q = mech.q_ref.copy()
    if name == "nfourbar_2":  # q_ref (theta = 0) is a flat, singular position
        q = np.where(np.arange(mech.nq) % 2 == 0, 0.5, -0.5)
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = (0.3, -0.2, 0.1)[: len(mech.independent_idx_v)]
    return q, cc.project_velocity(mech, q, v, fixed="independent")


def _pair(mech, q0, v0, t_final=T_CMP, **kw):
    a = cc.simulate(mech, q0, v0, t_final, backend="compiled", **kw)
    b = cc.simulate(mech, q0, v0, t_final, backend="numpy", **kw)
    assert a.info.backend == "compiled" and b.info.backend == "numpy"
    return a, b


@pytest.mark.parametrize("stab", FIXED_STABS)
@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("integrator", ["euler", "semi-implicit", "rk4"])
@pytest.mark.parametrize("name", MECHS)
def test_fixed_step_trajectories_match(mech_by_name, name, integrator, method, stab):
    mech = mech_by_name(name)
    q0, v0 = _state(mech, name)
    a, b = _pair(
        mech, q0, v0, T_FIXED, integrator=integrator, method=method, stabilization=stab, dt=DT
    )
    assert a.info.steps == b.info.steps
    assert a.info.evaluations == b.info.evaluations
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-12)
    for key in ("q", "v"):
        assert np.max(np.abs(getattr(a, key) - getattr(b, key))) <= FIXED_STEP_TOL
    assert np.max(np.abs(a.energy - b.energy)) <= FIXED_STEP_TOL
    assert np.max(np.abs(a.constraint_residual - b.constraint_residual)) <= FIXED_STEP_TOL
    # the assembly-branch series (sign of det(J_D)) is recorded from compiled samples too
    assert (a.branch is None) == (b.branch is None)
    if b.branch is not None:
        assert np.array_equal(a.branch, b.branch)


@pytest.mark.parametrize("stab", STABS)
@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("integrator", ["RK45", "DOP853"])
@pytest.mark.parametrize("name", MECHS)
def test_adaptive_trajectories_match(mech_by_name, name, integrator, method, stab):
    mech = mech_by_name(name)
    q0, v0 = _state(mech, name)
    t_eval = np.linspace(0.0, T_CMP, 7)
    for te in (None, t_eval):
        a, b = _pair(
            mech,
            q0,
            v0,
            integrator=integrator,
            method=method,
            stabilization=stab,
            rtol=RTOL,
            atol=ATOL,
            t_eval=te,
        )
        assert abs(a.info.steps - b.info.steps) <= STEP_COUNT_SLACK
        if te is not None:
            np.testing.assert_array_equal(a.t, t_eval)
            np.testing.assert_array_equal(b.t, t_eval)
        assert a.t[-1] == b.t[-1] == pytest.approx(T_CMP)
        assert np.max(np.abs(a.q[-1] - b.q[-1])) <= ADAPTIVE_TOL
        assert np.max(np.abs(a.v[-1] - b.v[-1])) <= ADAPTIVE_TOL
        if te is not None:
            assert np.max(np.abs(a.q - b.q)) <= ADAPTIVE_TOL


@pytest.mark.parametrize("integrator", ["RK45", "DOP853"])
def test_dormand_prince_matches_scipy(fourbar, integrator):
    """The compiled loop and scipy's solver on the same right-hand side: same steps."""
    q0, v0 = _state(fourbar, "fourbar")
    fd = compiled.compiled_dynamics(fourbar, "kkt")
    nv = fourbar.nv

    def fun(t, y):
        return np.concatenate([y[nv:], fd.forward(y[:nv], y[nv:], np.zeros(nv))[0]])

    t_final = 2.0
    ref = scipy.integrate.solve_ivp(
        fun, (0.0, t_final), np.concatenate([q0, v0]), method=integrator, rtol=RTOL, atol=ATOL
    )
    traj = cc.simulate(
        fourbar,
        q0,
        v0,
        t_final,
        integrator=integrator,
        method="kkt",
        stabilization="none",
        rtol=RTOL,
        atol=ATOL,
        backend="compiled",
        settings=cc.SimulationSettings(singular_cond=np.inf),
    )
    assert abs(traj.info.steps - (len(ref.t) - 1)) <= STEP_COUNT_SLACK
    assert np.max(np.abs(traj.q[-1] - ref.y[:nv, -1])) <= ADAPTIVE_TOL


# -- backend selection, errors, callbacks -------------------------------------------------

#: A request the compiled loops run (not the default, to exercise another method).
COMPILED_REQUEST = dict(method="kkt", stabilization="projection")


def test_auto_backend_uses_compiled_where_supported(fourbar):
    q0, v0 = _state(fourbar, "fourbar")
    traj = cc.simulate(fourbar, q0, v0, 0.05, integrator="rk4", **COMPILED_REQUEST)
    assert traj.info.backend == "compiled"
    # the default: augmented-lagrangian, rk4, stage projection
    assert cc.simulate(fourbar, q0, v0, 0.05).info.backend == "compiled"
    # partitioning and the reduced method are compiled too
    for kw in (
        dict(COMPILED_REQUEST, stabilization="partitioning"),
        dict(COMPILED_REQUEST, method="reduced"),
    ):
        assert cc.simulate(fourbar, q0, v0, 0.05, integrator="rk4", **kw).info.backend == "compiled"
    # a method without a compiled implementation: numpy, silently, or an error saying why
    kw = dict(COMPILED_REQUEST, method="proximal")
    assert cc.simulate(fourbar, q0, v0, 0.05, integrator="rk4", **kw).info.backend == "numpy"
    with pytest.raises(cc.ClosedChainError, match="backend='compiled' cannot"):
        cc.simulate(fourbar, q0, v0, 0.05, integrator="rk4", backend="compiled", **kw)
    with pytest.raises(cc.UnknownChoiceError, match="backend"):
        cc.simulate(fourbar, q0, v0, 0.05, backend="fortran")


@pytest.mark.parametrize("integrator", ["rk4", "DOP853"])
def test_callable_tau_and_progress(fourbar, integrator):
    """A Python tau(t, q, v) is called from C++; progress sees every step; results match."""
    q0, v0 = _state(fourbar, "fourbar")
    seen: list[float] = []

    def tau(t, q, v):
        return np.array([0.5 * np.sin(3 * t) - 0.1 * v[0], 0.0, 0.0])

    step = dict(dt=DT) if integrator == "rk4" else dict(rtol=RTOL, atol=ATOL)
    kw = dict(integrator=integrator, tau=tau, **step, **COMPILED_REQUEST)
    a = cc.simulate(fourbar, q0, v0, T_CMP, backend="compiled", progress=seen.append, **kw)
    b = cc.simulate(fourbar, q0, v0, T_CMP, backend="numpy", **kw)
    assert len(seen) == a.info.steps and seen[-1] == pytest.approx(T_CMP)
    assert np.all(np.diff(seen) > 0)
    assert np.max(np.abs(a.q[-1] - b.q[-1])) <= ADAPTIVE_TOL
    const = cc.simulate(
        fourbar,
        q0,
        v0,
        T_CMP,
        backend="compiled",
        integrator=integrator,
        tau=np.array([0.2, 0.0, 0.0]),
        **step,
        **COMPILED_REQUEST,
    )
    ref = cc.simulate(
        fourbar,
        q0,
        v0,
        T_CMP,
        backend="numpy",
        integrator=integrator,
        tau=np.array([0.2, 0.0, 0.0]),
        **step,
        **COMPILED_REQUEST,
    )
    assert np.max(np.abs(const.q[-1] - ref.q[-1])) <= ADAPTIVE_TOL


def test_errors_cross_the_boundary(fourbar):
    q0, v0 = _state(fourbar, "fourbar")

    def bad(t, q, v):
        return np.array([np.nan if t > 0.01 else 0.0, 0.0, 0.0])

    with pytest.raises(SimulationError, match=r"tau\(t, q, v\) returned .* at t = ") as exc:
        cc.simulate(
            fourbar, q0, v0, 0.1, integrator="rk4", tau=bad, backend="compiled", **COMPILED_REQUEST
        )
    assert exc.value.t > 0.01

    def raising(t, q, v):
        raise RuntimeError("controller failed")

    with pytest.raises(RuntimeError, match="controller failed"):
        cc.simulate(
            fourbar,
            q0,
            v0,
            0.1,
            integrator="DOP853",
            tau=raising,
            backend="compiled",
            **COMPILED_REQUEST,
        )

    def stop(t):
        if t > 0.02:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cc.simulate(
            fourbar,
            q0,
            v0,
            0.1,
            integrator="rk4",
            progress=stop,
            backend="compiled",
            **COMPILED_REQUEST,
        )

    # drift beyond the limit: euler without stabilization at a coarse step
    with pytest.raises(SimulationError, match="left the constraint manifold at t = "):
        cc.simulate(
            fourbar,
            q0,
            v0,
            2.0,
            integrator="euler",
            dt=5e-2,
            method="kkt",
            stabilization="none",
            backend="compiled",
            settings=cc.SimulationSettings(drift_limit=1e-3),
        )


#: Seconds after which the test's SIGINT arrives.
SIGINT_AFTER = 0.5


def test_ctrl_c_interrupts_a_long_run(fourbar):
    """SIGINT stops a long compiled run (checked every 64 steps).

    The signal comes from another process, as Ctrl-C does: a Python thread
    (threading.Timer + _thread.interrupt_main) would need the GIL, which the
    compiled loop holds, so it would only run once the loop ends. Python's own
    SIGINT handler is installed for the test: a process started in the background
    by a non-interactive shell (CI) inherits SIGINT ignored.
    """
    q0, v0 = _state(fourbar, "fourbar")
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    killer = subprocess.Popen(["sh", "-c", f"sleep {SIGINT_AFTER}; kill -INT {os.getpid()}"])
    reached = [0.0]

    def progress(t):
        reached[0] = t

    try:
        with pytest.raises(KeyboardInterrupt):
            # 20 million steps (each calling progress): many minutes if not interrupted
            cc.simulate(
                fourbar,
                q0,
                v0,
                2e4,
                integrator="semi-implicit",
                dt=1e-3,
                t_eval=np.array([2e4]),
                backend="compiled",
                progress=progress,
                **COMPILED_REQUEST,
            )
            killer.wait()  # the run ended first: let the signal arrive inside pytest.raises
            time.sleep(1.0)
    finally:
        killer.wait()
        signal.signal(signal.SIGINT, previous)
    assert 0.0 < reached[0] < 2e4  # stopped inside the run, not after it


def test_missing_compiler_message(tmp_path):
    """Without a C++ compiler the build stops with the package to install."""
    import cmake as cmake_pkg  # the test extra (the build's own cmake is in its isolated env)

    cmake = str(Path(cmake_pkg.CMAKE_BIN_DIR) / "cmake")
    out = subprocess.run(
        [cmake, "-S", str(ROOT), "-B", str(tmp_path), "-DCMAKE_CXX_COMPILER=/nonexistent/c++"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.returncode != 0
    assert "no C++17 compiler found" in out.stderr
    assert "apt-get install g++" in out.stderr


# -- the default configuration through singular positions; every declared row -------------

#: Trajectories through the N-four-bar's flat positions (J loses rank): both backends
#: pass them with the default configuration; round-off near the rank loss is
#: amplified, so the agreement is that of the integration error, not of round-off.
SINGULAR_PASSAGE_TOL = 1e-6


def test_default_configuration_passes_flat_positions(mech_by_name):
    """augmented-lagrangian + rk4 + stage projection (the default) compiled and numpy
    out of a flat position of the N-four-bar (cranks at 3 rad/s from theta = 0)."""
    mech = mech_by_name("nfourbar_2")
    is_crank = np.array([n.startswith("crank") for n in mech.coordinate_names])
    q0, v0 = np.zeros(mech.nq), np.where(is_crank, -3.0, 3.0)
    a, b = _pair(mech, q0, v0, 0.3, t_eval=np.linspace(0.0, 0.3, 7))
    assert a.info.method == "augmented-lagrangian"
    assert a.info.stabilization == "stage-projection"
    assert np.max(np.abs(a.q - b.q)) <= SINGULAR_PASSAGE_TOL
    assert np.max(a.constraint_residual) <= 1e-12
    with pytest.raises(cc.SingularConfigurationError, match="at t = .*condition number"):
        cc.simulate(mech, q0, v0, 0.3, method="kkt", backend="compiled")


def test_every_declared_row_is_checked_at_every_step(fourbar):
    """The drift limit holds at every step, not only at output samples, and the error
    names the row and the time."""
    q0, v0 = _state(fourbar, "fourbar")
    kw = dict(
        integrator="euler",
        dt=5e-2,
        method="kkt",
        stabilization="none",
        t_eval=np.array([2.0]),  # one output, at the end
        settings=cc.SimulationSettings(drift_limit=1e-3),
    )
    stops = []
    for backend in ("compiled", "numpy"):
        with pytest.raises(SimulationError, match=r"at t = .* row \w+\.t[12]\)") as exc:
            cc.simulate(fourbar, q0, v0, 2.0, backend=backend, **kw)
        stops.append(exc.value.t)
    assert stops[0] == stops[1] < 2.0


def test_an_open_dropped_row_hands_the_run_to_the_row_reselection(fourbar, monkeypatch):
    """A dropped row that opens (here: the kept rows are declared dropped to the check,
    so their drift without stabilization opens them) stops the compiled loop with
    RowCheckRequired; the request runs on the numpy backend, which re-selects rows."""
    from closedchain.simulate import compiled_loops

    real = compiled.make_core

    def make_core(mech, *, shared=True):
        core = real(mech, shared=False)
        # every row counts as dropped
        compiled.set_declared_rows(core, mech, np.zeros(mech.declared.nc, dtype=np.int32))
        return core

    monkeypatch.setattr(compiled_loops.compiled, "make_core", make_core)
    q0, v0 = _state(fourbar, "fourbar")
    traj = cc.simulate(
        fourbar, q0, v0, 0.2, integrator="euler", method="kkt", stabilization="none", dt=DT
    )
    assert traj.info.backend == "numpy"
    assert "dropped row" in traj.info.backend_fallback


# -- the reduced method and coordinate partitioning ----------------------------------------


@pytest.mark.parametrize("name", MECHS)
def test_reduced_matches_numpy_per_evaluation(mech_by_name, name, rng):
    """The compiled reduced method against dynamics/reduced.py at random consistent states
    (nfourbar_2 included: its partition spans two loops with dropped rows)."""
    mech = mech_by_name(name)
    fd = compiled.compiled_dynamics(mech, "reduced")
    states = [_state(mech, name)] + [cc.random_consistent_state(mech, rng) for _ in range(7)]
    compared = 0
    for q, v in states:
        tau = rng.standard_normal(mech.nv)
        try:
            ref = cc.forward_dynamics(mech, q, v, tau, method="reduced")
        except cc.SingularConfigurationError as exc:
            # the load-time partition's J_D is singular at this sample: the same error
            with pytest.raises(cc.SingularConfigurationError, match="J_D") as err:
                fd.forward(q, v, tau)
            assert err.value.condition_number > cc.SolverSettings().cond_max
            assert exc.condition_number > cc.SolverSettings().cond_max
            continue
        compared += 1
        a, lam = fd.forward(q, v, tau)
        assert _close(a, ref.a)
        assert _close(lam, ref.lam)
        # and both solve the constrained equations (an independent check of the pair)
        ws = compute_terms(mech, q, v)
        assert _close(ws.M @ a + ws.h + ws.J.T @ lam, tau, 1e-10)
        assert _close(ws.J @ a + ws.gamma, np.zeros(mech.nc), 1e-10)
    assert compared >= 4


def test_reduced_singular_partition_raises(fourbar):
    """J_D above cond_max: the library's error naming J_D's coordinates, with the same
    1-norm condition estimate as LAPACK's dgecon on the numpy side."""
    settings = cc.SolverSettings(cond_max=1.0)
    q, v = fourbar.q_ref, np.zeros(fourbar.nv)
    fd = compiled.compiled_dynamics(fourbar, "reduced", settings)
    with pytest.raises(cc.SingularConfigurationError, match=r"J_D \(constraint-Jacobian") as exc:
        fd.forward(q, v, np.zeros(fourbar.nv))
    with pytest.raises(cc.SingularConfigurationError) as ref:
        cc.forward_dynamics(
            fourbar, q, v, np.zeros(fourbar.nv), method="reduced", settings=settings
        )
    dep = ", ".join(fourbar.coordinate_names[i] for i in fourbar.dependent_idx_v)
    assert f"dependent coordinates {dep})" in str(exc.value)
    assert exc.value.condition_number == pytest.approx(ref.value.condition_number, rel=1e-12)
    assert exc.value.t is None


#: Adaptive partitioning: the two backends' step ends drift apart by about 1e-4 of a step
#: (the dependent solve leaves phi anywhere below dependent_tol, and that noise enters the
#: error estimate; measured 4e-5 s at the re-partition, steps of about 0.05 s there).
REPARTITION_T_TOL = 1e-3


def _agile_eye_near_repartition(mech):
    """The coasting Agile Eye (no gravity) at t = 9.25 s, from an accurate run: there the
    partition chosen at load has cond(J_D) = 41, above repartition_cond, so a partitioned
    run from it re-partitions at its first step."""
    q0 = mech.q_ref.copy()
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = (0.3, -0.2, 0.1)
    v0 = cc.project_velocity(mech, q0, v, fixed="independent")
    ref = cc.simulate(
        mech, q0, v0, 9.25, integrator="DOP853", rtol=1e-12, atol=1e-12, method="kkt",
        stabilization="none", t_eval=np.array([9.25]),
    )  # fmt: skip
    # The platform has turned past pi, outside its URDF limits [-pi, pi]: the same pose
    # within one turn starts the runs.
    q = mech.wrap_angles(ref.q[-1])
    return q, cc.project_velocity(mech, q, ref.v[-1])


@pytest.fixture(scope="module")
def agile_eye_coasting():
    mech = cc.load(ROOT / "models" / "agile_eye.urdf")
    mech.model.gravity.linear[:] = 0.0
    q0, v0 = _agile_eye_near_repartition(mech)
    return mech, q0, v0


@pytest.mark.parametrize("integrator", ["rk4", "DOP853"])
@pytest.mark.parametrize("method", ["kkt", "reduced"])
def test_repartitioning_sequence_matches_numpy(agile_eye_coasting, integrator, method):
    """Both backends re-partition at the same time to the same independent coordinates,
    and their trajectories agree to the integration tolerance across it."""
    mech, q0, v0 = agile_eye_coasting
    step = dict(dt=DT) if integrator == "rk4" else dict(rtol=RTOL, atol=ATOL)
    a, b = _pair(
        mech, q0, v0, 0.5, integrator=integrator, method=method, stabilization="partitioning",
        t_eval=np.linspace(0.0, 0.5, 11), **step,
    )  # fmt: skip
    assert len(b.info.repartitions) >= 1, "the reference re-partitions in this window"
    assert [r[1] for r in a.info.repartitions] == [r[1] for r in b.info.repartitions]
    # fixed step: the same grid point; adaptive: the end of the same accepted step, whose
    # time differs a little (REPARTITION_T_TOL)
    t_tol = 1e-12 if integrator == "rk4" else REPARTITION_T_TOL
    np.testing.assert_allclose(
        [r[0] for r in a.info.repartitions], [r[0] for r in b.info.repartitions], atol=t_tol
    )
    tol = FIXED_STEP_TOL if integrator == "rk4" else ADAPTIVE_TOL
    assert np.max(np.abs(a.q - b.q)) <= tol
    assert np.max(np.abs(a.v - b.v)) <= tol
    assert np.max(a.constraint_residual) <= cc.SimulationSettings().dependent_tol


def _core_run(mech, integrator, q0, v0, t_final, method="kkt", settings=None, dt=DT):
    """Run the compiled loop itself (simulate re-runs a failed compiled request on numpy
    to recover the motion, so its error would be numpy's)."""
    from closedchain.simulate.fixed import output_grid

    settings = settings or cc.SimulationSettings()
    core = compiled.make_core(mech, shared=False)
    compiled.configure(core, method, cc.SolverSettings(), settings, partitions=True)
    core.set_tau(None)
    code = compiled.INTEGRATOR_CODES[integrator]
    if integrator in ("RK45", "DOP853"):
        return core.run_adaptive(code, q0, v0, t_final, RTOL, ATOL, None, False, None)
    h, n, _ = output_grid(t_final, dt, None)
    return core.run_fixed(code, q0, v0, h, n, np.arange(n + 1, dtype=np.int32), False, None)


#: The open 4-bar from rest (test_singular's OPEN_GUESS_DEG) reaches its change point,
#: where every J_D is singular at once, at t = 0.393 s (measured: every 2 x 2 minor of J
#: changes sign between 0.3928 and 0.3929 s).
OPEN_GUESS_DEG = (10.0, 50.0, 30.0)
CHANGE_POINT_T = 0.393
#: DOP853 at RTOL near the change point takes steps of 0.022 to 0.025 s [s] (measured on
#: both backends under OpenBLAS's SkylakeX, Haswell, Sandybridge, Nehalem, Prescott kernels).
CHANGE_POINT_STEP = 0.03
#: With partition_singular_cond = 30 the best J_D passes it 4 ms before the change point
#: (measured: rk4 at 1 ms stops at t = 0.389 s on both backends).
APPROACH_T = 0.01


@pytest.mark.parametrize("integrator", ["rk4", "DOP853"])
def test_partitioning_singular_error(fourbar, fourbar_closed_forms, integrator):
    """At the 4-bar's change point no partition has a regular J_D: the compiled loop stops
    with SingularConfigurationError naming the time, the bound and the configuration that
    passes, as the numpy loop does (fixed step: partition_singular_cond; adaptive:
    det(J_D) changes sign within a step, singular_cond off to reach it)."""
    q0 = cc.assemble(fourbar, np.radians(OPEN_GUESS_DEG), fixed=["crank_joint"])
    v0 = np.zeros(fourbar.nv)
    if integrator == "rk4":
        settings = cc.SimulationSettings(repartition_cond=10.0, partition_singular_cond=30.0)
        match = r"best-conditioned J_D .* > partition_singular_cond 3.0e\+01"
    else:
        settings = cc.SimulationSettings(singular_cond=np.inf)
        match = r"det\(J_D\) changed sign within the last step"
    hint = r"use method='augmented-lagrangian' with stabilization='stage-projection'"
    with pytest.raises(cc.SingularConfigurationError, match=match + ".*" + hint) as exc:
        _core_run(fourbar, integrator, q0, v0, 1.0, settings=settings)
    assert str(exc.value).endswith(passing_hint())  # constants.hpp's, generated from it
    step = dict(dt=DT) if integrator == "rk4" else dict(rtol=RTOL, atol=ATOL)
    with pytest.raises(cc.SingularConfigurationError, match=match) as ref:
        cc.simulate(
            fourbar, q0, v0, 1.0, integrator=integrator, method="kkt",
            stabilization="partitioning", settings=settings, backend="numpy", **step,
        )  # fmt: skip
    if integrator == "rk4":  # the same steps: the same grid point and J_D, on the way in
        assert exc.value.t == pytest.approx(ref.value.t, abs=1e-12)
        assert exc.value.condition_number == pytest.approx(ref.value.condition_number, rel=1e-6)
        assert CHANGE_POINT_T - APPROACH_T <= exc.value.t < CHANGE_POINT_T
        return
    # Adaptive: det(J_D) is checked at step ends, so each run stops at the end of the step
    # in which its dependent solve left the start's assembly branch. The open and crossed
    # branches of q_D(q_I) meet at the change point, and the solve, started from a guess
    # extrapolated over the step, may land on the crossed one a little before it (numpy
    # under SkylakeX: 0.3902 s, the crank 2.5 deg short of -180 deg) or follow the motion
    # through it (compiled 0.4091 s, numpy under Haswell 0.4113 s). Which step that is
    # depends on round-off: the dependent solve leaves phi at up to dependent_tol, noise
    # that enters the error estimate (first step 1.8e-4 s on both, the next ones differ
    # by 5%), and OpenBLAS's kernel (chosen by the CPU) moves the numpy side's stop
    # between 0.3900 and 0.4113 s. So the assertion is the physics, not a step end: a stop
    # within one step of the change point on either side, at a configuration on the other
    # branch (the lesson's closed-form det(J_D) has changed sign).
    cf = fourbar_closed_forms
    start_branch = np.sign(cf.det_dependent(cf.theta(q0)))
    for err in (exc.value, ref.value):
        assert abs(err.t - CHANGE_POINT_T) <= CHANGE_POINT_STEP
        assert np.sign(cf.det_dependent(cf.theta(err.q))) == -start_branch


def test_a_partitioning_run_leaves_no_state_in_the_shared_core(mech_by_name):
    """The compiled core is shared by every run on a mechanism; each run starts from its
    own configuration. A fixed-step partitioning run (which checks the rows only) before
    a kkt + rk4 + stage-projection run must not switch off the latter's singularity check:
    it stops at the N-four-bar's first flat position as the numpy backend's run does
    (before the fix it ran through every flat position unchecked)."""
    import nfourbar_reference as ref

    mech = mech_by_name("nfourbar_2")
    q0, v0 = ref.initial_state(mech)
    stops = {}
    for backend in ("numpy", "compiled"):
        cc.simulate(
            mech,
            q0,
            v0,
            0.2,
            integrator="euler",
            stabilization="partitioning",
            method="kkt",
            backend=backend,
        )
        with pytest.raises(cc.SingularConfigurationError) as info:
            cc.simulate(
                mech,
                q0,
                v0,
                2.0,
                method="kkt",
                integrator="rk4",
                stabilization="stage-projection",
                backend=backend,
            )
        stops[backend] = info.value.t
    assert stops["compiled"] < 1.0  # the first flat position, t = 0.73 s
    assert abs(stops["compiled"] - stops["numpy"]) <= 2 * cc.SimulationSettings().dt
