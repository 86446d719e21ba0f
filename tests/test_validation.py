"""Tests of closedchain.validation and of the KKT forward dynamics it validates.

References:

* ``pinocchio.constraintDynamics``, through :func:`closedchain.validate` and,
  independently, through constraint models built here from the URDF text;
* the same KKT system (M, h from Pinocchio; J, gamma from the layer) solved
  with mpmath at 40 significant digits.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import mpmath
import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, SHIPPED_MECHANISMS, VALIDATABLE_MECHANISMS

import closedchain as cc
from closedchain import validation
from closedchain.dynamics import base as dynamics_base
from closedchain.validation import MAX_VALIDATION_SAMPLES

#: Mechanisms with a Pinocchio reference (no prismatic loops).
VALIDATABLE = list(VALIDATABLE_MECHANISMS)

#: Random consistent states compared with pinocchio.constraintDynamics per model.
N_VALIDATION_STATES = 100
VALIDATION_SEED = 7
#: max |a - a_pin| [rad/s^2 or m/s^2].
TOL_ACCELERATION = 1e-9
#: Generalized constraint force J^T lam: absolute below 1 N m, relative above.
TOL_FORCE = 1e-8
#: |J a + gamma| of the KKT accelerations [m/s^2 or 1/s^2].
TOL_ACCELERATION_CONSTRAINT = 1e-10

#: Significant digits of the mpmath reference solve.
MP_DIGITS = 40
#: KKT accelerations against the 40-digit solve, relative to max(1, |a|).
TOL_HIGH_PRECISION = 1e-11
N_HIGH_PRECISION_STATES = 15

#: Pinocchio proximal settings of the independent reference (mu > 0
#: copes with redundant rows; the iterations converge to the exact solution).
PIN_MU = 1e-8
PIN_ACCURACY = 1e-13
PIN_MAX_ITER = 100
#: Distance [m] between the two contact points standing for a revolute loop.
REVOLUTE_POINT_OFFSET = 0.05
N_INDEPENDENT_STATES = 30
#: Their tolerance on |a - a_pin| / max(1, |a_pin|): the reference's own accuracy.
#: With tau ~ N(0, 1) N m the light Agile Eye accelerates at ~2e3 rad/s^2, where the
#: proximal solver (mu = PIN_MU, redundant point-contact rows) stops short of the exact
#: solution: at one state of this seed it is 3.6e-11 relative from a 40-digit KKT solve
#: whatever its iteration limit (100 to 1000) while closedchain's KKT solve is 1.2e-14
#: from it (measured on an AMD EPYC, OpenBLAS Haswell kernel). closedchain's own accuracy
#: is held to TOL_HIGH_PRECISION by test_kkt_agrees_with_a_40_digit_solve.
TOL_ACCELERATION_RELATIVE = 1e-10


# -- closedchain.validate -------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED_MECHANISMS)
def test_validate_agrees_with_pinocchio_on_the_models(load_mechanism, name):
    rep = cc.validate(load_mechanism(name), n_samples=N_VALIDATION_STATES, seed=VALIDATION_SEED)
    assert rep.n_samples == N_VALIDATION_STATES
    assert rep.n_singular == 0
    assert rep.max_da <= TOL_ACCELERATION
    assert rep.max_dforce <= TOL_FORCE
    assert rep.max_constraint_residual <= TOL_ACCELERATION_CONSTRAINT
    assert rep.passed
    assert rep.as_dict()["passed"] is True


@pytest.mark.parametrize("name", ["spherical_chain", "fixed_branches"])
def test_validate_agrees_with_pinocchio_on_spherical_and_fixed_loops(load_mechanism, name):
    rep = cc.validate(load_mechanism(name), n_samples=30, seed=VALIDATION_SEED)
    assert rep.n_singular == 0
    assert rep.max_da <= TOL_ACCELERATION
    assert rep.max_dforce <= TOL_FORCE
    assert rep.passed


def _biased_method(da: float = 0.0, dlam_rel: float = 0.0):
    kkt = dynamics_base.METHODS["kkt"]

    def method(mech, q, v, tau, settings):
        a, lam = kkt(mech, q, v, tau, settings)
        return a + da, lam * (1.0 + dlam_rel)

    return method


def test_validate_fails_a_wrong_acceleration(fourbar, monkeypatch):
    monkeypatch.setitem(dynamics_base.METHODS, "kkt_biased", _biased_method(da=1e-6))
    rep = cc.validate(fourbar, n_samples=10, seed=VALIDATION_SEED, method="kkt_biased")
    assert rep.max_da == pytest.approx(1e-6, rel=1e-3)
    assert not rep.passed


def test_validate_fails_a_wrong_constraint_force(fourbar, monkeypatch):
    monkeypatch.setitem(dynamics_base.METHODS, "kkt_biased", _biased_method(dlam_rel=1e-5))
    rep = cc.validate(fourbar, n_samples=10, seed=VALIDATION_SEED, method="kkt_biased")
    assert rep.max_da <= TOL_ACCELERATION
    assert rep.max_dforce > TOL_FORCE
    assert not rep.passed


def test_validate_does_not_pass_when_every_state_is_refused(fourbar, monkeypatch):
    def always_singular(mech, q, v, tau, settings):
        raise cc.SingularConfigurationError("refused", q=q)

    monkeypatch.setitem(dynamics_base.METHODS, "refuses", always_singular)
    rep = cc.validate(fourbar, n_samples=5, seed=VALIDATION_SEED, method="refuses")
    assert rep.n_singular == 5
    assert not rep.passed


def test_validate_refuses_prismatic_loops(load_mechanism):
    with pytest.raises(
        cc.ValidationUnavailableError,
        match=r"loop 'P' is prismatic: Pinocchio has no prismatic rigid constraint model.*"
        r"valid loop types for validation: revolute, spherical, fixed",
    ):
        cc.validate(load_mechanism("slider_crank"), n_samples=1)


def test_unknown_method_lists_the_registered_ones(fourbar):
    with pytest.raises(
        cc.UnknownChoiceError, match=r"unknown forward-dynamics method 'nope'; valid choices: .*kkt"
    ):
        cc.forward_dynamics(fourbar, fourbar.q_ref, np.zeros(3), method="nope")


# -- an independent Pinocchio reference, built from the URDF text --------------------------


def pinocchio_reference_constraints(mech, path):
    """Rigid constraint models for the loops of ``path``, from the URDF text alone.

    revolute: two CONTACT_3D points on the axis; spherical: one CONTACT_3D;
    fixed: CONTACT_6D (all LOCAL).
    """
    model = mech.model
    cms = pin.StdVec_RigidConstraintModel()
    for el in ET.parse(path).getroot().findall("loop"):
        placements = []
        for side in ("predecessor", "successor"):
            link = el.find(side).get("link")
            frame = model.frames[model.getFrameId(link, pin.FrameType.BODY)]
            origin = el.find(f"{side}_origin")
            xyz = np.array([float(x) for x in origin.get("xyz").split()])
            rpy = np.array([float(x) for x in origin.get("rpy").split()])
            placements.append(
                (frame.parentJoint, frame.placement * pin.SE3(pin.rpy.rpyToMatrix(rpy), xyz))
            )
        (j1, M1), (j2, M2) = placements
        kind = el.get("type")
        local = pin.ReferenceFrame.LOCAL
        if kind == "fixed":
            cms.append(
                pin.RigidConstraintModel(pin.ContactType.CONTACT_6D, model, j1, M1, j2, M2, local)
            )
            continue
        cms.append(
            pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, model, j1, M1, j2, M2, local)
        )
        if kind == "revolute":
            axis = np.array([float(x) for x in el.find("axis").get("xyz").split()])
            shift = pin.SE3(np.eye(3), REVOLUTE_POINT_OFFSET * axis / np.linalg.norm(axis))
            cms.append(
                pin.RigidConstraintModel(
                    pin.ContactType.CONTACT_3D, model, j1, M1 * shift, j2, M2 * shift, local
                )
            )
    return cms


@pytest.mark.parametrize("name", VALIDATABLE)
def test_kkt_agrees_with_an_independent_pinocchio_reference(
    load_mechanism, mechanism_files, rng, name
):
    mech = load_mechanism(name)
    model = mech.model
    data = model.createData()
    cms = pinocchio_reference_constraints(mech, mechanism_files[name])
    cds = pin.StdVec_RigidConstraintData()
    for cm in cms:
        cds.append(cm.createData())
    pin.initConstraintDynamics(model, data, cms, cds)
    prox = pin.ProximalSettings(PIN_ACCURACY, 0.0, PIN_MU, PIN_MAX_ITER)
    da, dforce = [], []
    for _ in range(N_INDEPENDENT_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a_pin = pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox).copy()
        Jc = pin.getConstraintsJacobian(model, data, cms, cds)
        force_pin = -Jc.T @ data.lambda_c  # Pinocchio: M a + h = tau + Jc^T lambda_c
        res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
        da.append(np.linalg.norm(res.a - a_pin) / max(1.0, np.linalg.norm(a_pin)))
        scale = max(1.0, np.linalg.norm(force_pin))
        dforce.append(np.linalg.norm(res.generalized_constraint_force() - force_pin) / scale)
        assert res.constraint_residual() <= TOL_ACCELERATION_CONSTRAINT
    assert max(da) <= TOL_ACCELERATION_RELATIVE, max(da)
    assert max(dforce) <= TOL_FORCE, max(dforce)


# -- the KKT solve against a 40-digit solve of the same system -------------------------------


def mp_solve_kkt(M, h, J, gamma, tau):
    """Solve [[M, J^T], [J, 0]] [a; lam] = [tau - h; -gamma] with mpmath at MP_DIGITS digits."""
    nv, nc = M.shape[0], J.shape[0]
    with mpmath.workdps(MP_DIGITS):
        K = mpmath.zeros(nv + nc, nv + nc)
        rhs = mpmath.zeros(nv + nc, 1)
        for i in range(nv):
            rhs[i] = mpmath.mpf(float(tau[i])) - mpmath.mpf(float(h[i]))
            for j in range(nv):
                K[i, j] = mpmath.mpf(float(M[i, j]))
        for r in range(nc):
            rhs[nv + r] = -mpmath.mpf(float(gamma[r]))
            for j in range(nv):
                K[nv + r, j] = K[j, nv + r] = mpmath.mpf(float(J[r, j]))
        x = mpmath.lu_solve(K, rhs)
        return (
            np.array([float(x[i]) for i in range(nv)]),
            np.array([float(x[nv + r]) for r in range(nc)]),
        )


@pytest.mark.parametrize("name", SHIPPED_MECHANISMS)
def test_kkt_agrees_with_a_40_digit_solve(load_mechanism, rng, name):
    mech = load_mechanism(name)
    model = mech.model
    data = model.createData()
    errors = []
    for _ in range(N_HIGH_PRECISION_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T  # crba fills the upper triangle
        h = pin.nonLinearEffects(model, data, q, v)
        J = cc.compute_jacobian(mech, q)
        gamma = cc.compute_gamma(mech, q, v)
        a_ref, lam_ref = mp_solve_kkt(M, h, J, gamma, tau)
        res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
        # The method evaluated the same J and gamma (through computeAllTerms).
        assert np.linalg.norm(res.J - J) <= 1e-14 * max(1.0, np.linalg.norm(J))
        assert np.linalg.norm(res.gamma - gamma) <= 1e-13 * max(1.0, np.linalg.norm(gamma))
        err_a = np.linalg.norm(res.a - a_ref) / max(1.0, np.linalg.norm(a_ref))
        f_ref = J.T @ lam_ref
        err_f = np.linalg.norm(res.generalized_constraint_force() - f_ref) / max(
            1.0, np.linalg.norm(f_ref)
        )
        errors.append((err_a, err_f))
    worst = np.max(np.array(errors), axis=0)
    assert worst[0] <= TOL_HIGH_PRECISION, worst
    assert worst[1] <= TOL_HIGH_PRECISION, worst


#: validate's own states (VALIDATION_SEED, N_VALIDATION_STATES) compared with the 40-digit
#: solve per mechanism: the ones nearest a singular J (smallest sigma_min(J) / sigma_max(J)).
N_NEAR_SINGULAR_STATES = 3
#: The Agile Eye's nearest of them lies below this sigma_min(J) / sigma_max(J) [-] (9.2e-4
#: at state 97, where solving the equilibrated KKT matrix was off by 3e-11 to 8e-11
#: relative and pivoted LU of K as it stands by 1.3e-14 to 2e-14).
NEAR_SINGULAR_SIGMA_RATIO = 1e-2


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
@pytest.mark.parametrize("name", SHIPPED_MECHANISMS)
def test_kkt_agrees_with_a_40_digit_solve_near_a_singular_J(load_mechanism, name, backend):
    """Where J nearly loses rank, kkt's solve keeps its digits (both backends): the states
    of validate nearest a singular J agree with the 40-digit solve to TOL_HIGH_PRECISION."""
    if backend == "compiled":
        from closedchain import compiled

        if not compiled.available():
            pytest.skip("the compiled core is not built")
    mech = load_mechanism(name)
    states = []
    for q, v, tau in validation._validation_states(
        mech, N_VALIDATION_STATES, VALIDATION_SEED, 1.0, None
    ):
        ws = dynamics_base.compute_terms(mech, q, v)
        sigma = np.linalg.svd(ws.J, compute_uv=False)
        states.append((sigma[-1] / sigma[0], q, v, tau, ws.M.copy(), ws.h.copy()))
    states.sort(key=lambda s: s[0])
    if name == "agile_eye":
        assert states[0][0] <= NEAR_SINGULAR_SIGMA_RATIO
    for _, q, v, tau, M, h in states[:N_NEAR_SINGULAR_STATES]:
        res = cc.forward_dynamics(mech, q, v, tau, method="kkt", backend=backend)
        a_ref, lam_ref = mp_solve_kkt(M, h, res.J, res.gamma, tau)
        err_a = np.linalg.norm(res.a - a_ref) / max(1.0, np.linalg.norm(a_ref))
        assert err_a <= TOL_HIGH_PRECISION, err_a
        f_ref = res.J.T @ lam_ref
        err_f = np.linalg.norm(res.generalized_constraint_force() - f_ref)
        assert err_f <= TOL_HIGH_PRECISION * max(1.0, np.linalg.norm(f_ref)), err_f


def test_validate_fails_when_the_reference_returns_nan(fourbar, monkeypatch):
    """A NaN from Pinocchio is a failed comparison, not a skipped one."""
    from closedchain import validation

    def nan_reference(mech, q, v, tau, settings):
        nan = np.full(mech.nv, np.nan)
        return nan, nan, nan

    monkeypatch.setattr(validation, "pinocchio_reference_dynamics", nan_reference)
    report = cc.validate(fourbar, n_samples=3, seed=0)
    assert not report.passed
    assert report.max_da == np.inf


def test_validate_refuses_to_compare_pinocchio_with_itself(fourbar):
    with pytest.raises(cc.UnknownChoiceError, match=r"'pinocchio'.*valid choices: .*kkt"):
        cc.validate(fourbar, n_samples=1, method="pinocchio")


@pytest.mark.parametrize("n_samples", [0, -5, 2.5, True, "10", MAX_VALIDATION_SAMPLES + 1, 10**30])
def test_validate_refuses_no_samples_and_too_many(fourbar, n_samples):
    """A check on no states would report PASSED having compared nothing; too many never ends."""
    with pytest.raises(
        cc.InvalidArgumentError,
        match=rf"n_samples must be an integer in \[1, {MAX_VALIDATION_SAMPLES}\] .*got",
    ):
        cc.validate(fourbar, n_samples=n_samples)


@pytest.mark.parametrize("seed", [-1, 1.5, True, "3"])
def test_validate_refuses_a_negative_or_non_integer_seed(fourbar, seed):
    with pytest.raises(cc.InvalidArgumentError, match=r"seed must be an integer >= 0 .*got"):
        cc.validate(fourbar, n_samples=1, seed=seed)


def test_validate_method_in_any_case(fourbar):
    assert cc.validate(fourbar, n_samples=2, method="Schur").method == "schur"


# -- near-massless links: the accelerations judged in the mass-matrix norm -------------------

#: Condition number of M at least this on the light-rod delta (the corpus's robots: 1e6 to 1e8).
MIN_LIGHT_COND_M = 1e6
#: Accelerations of the light-rod delta's validation states reach at least this [rad/s^2].
MIN_LIGHT_ACCELERATION = 1e3


@pytest.fixture(scope="module")
def light_delta():
    """The delta of tests/data with rods of 2e-5 kg (make_yaml_mechanisms.py), like the corpus."""
    return cc.load(DATA_DIR / "yaml_delta_light.urdf", loops=DATA_DIR / "yaml_delta.yaml")


def _mass_norm(M, x):
    return float(np.sqrt(x @ M @ x))


def test_light_links_are_judged_in_the_mass_matrix_norm(light_delta, rng):
    """Both sides agree with a 40-digit solve in the mass-matrix norm; validate passes.

    max |a - a_pin| is left unjudged: along the rods' spins (M eigenvalue 5e-8 kg m^2)
    the accelerations reach 1e4 rad/s^2 or more, where the double-precision problem
    does not determine them to 1e-9 (validation module docstring).
    """
    mech = light_delta
    model, data = mech.model, mech.model.createData()
    M0 = pin.crba(model, data, mech.q_ref)
    assert np.linalg.cond(np.triu(M0) + np.triu(M0, 1).T) >= MIN_LIGHT_COND_M
    scale = mech.gravity_torque_scale()
    worst_ours = worst_pin = largest_a = 0.0
    for _ in range(5):
        q, v = cc.random_consistent_state(mech, rng)
        tau = scale * rng.standard_normal(mech.nv)
        M = pin.crba(model, data, q)
        M = np.triu(M) + np.triu(M, 1).T
        h = pin.nonLinearEffects(model, data, q, v)
        a_ref, _ = mp_solve_kkt(
            M, h, cc.compute_jacobian(mech, q), cc.compute_gamma(mech, q, v), tau
        )
        ours = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
        a_pin = validation.pinocchio_reference_dynamics(mech, q, v, tau)[0]
        norm = max(1.0, _mass_norm(M, a_ref))
        worst_ours = max(worst_ours, _mass_norm(M, ours - a_ref) / norm)
        worst_pin = max(worst_pin, _mass_norm(M, a_pin - a_ref) / norm)
        largest_a = max(largest_a, float(np.max(np.abs(a_ref))))
    assert largest_a >= MIN_LIGHT_ACCELERATION
    # Rounding M, h, J and gamma to double alone moves the 40-digit solution by
    # 3e-11 to 1e-10 of ||a||_M here (measured), so TOL_HIGH_PRECISION cannot hold.
    assert worst_ours <= TOL_ACCELERATION
    assert worst_pin <= TOL_ACCELERATION
    rep = cc.validate(mech, n_samples=10, seed=VALIDATION_SEED)
    assert rep.max_da_mass_norm <= TOL_ACCELERATION
    assert rep.max_dforce <= TOL_FORCE
    assert rep.passed


def test_validate_fails_a_wrong_acceleration_in_the_mass_matrix_norm(fourbar, monkeypatch):
    """A bias of 1e-6 rad/s^2 on every coordinate fails the judged mass-matrix norm."""
    monkeypatch.setitem(dynamics_base.METHODS, "kkt_biased", _biased_method(da=1e-6))
    rep = cc.validate(fourbar, n_samples=10, seed=VALIDATION_SEED, method="kkt_biased")
    assert rep.max_da_mass_norm > TOL_ACCELERATION
    assert not rep.passed
