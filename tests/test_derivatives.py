"""Derivatives of the closed-chain dynamics and of the loop rows (closedchain.derivatives).

References, independent of the code under test:

* central finite differences of :func:`closedchain.forward_dynamics` (method ``kkt``)
  and of the rows (``compute_phi``, ``compute_jacobian``, ``compute_gamma``) in the
  tangent space (``pin.integrate``), one step per entry, for every loop kind, a
  coupling and the passive terms;
* ``pinocchio.computeConstraintDynamicsDerivatives`` after ``pinocchio.constraintDynamics``
  on Pinocchio's constraint models of the same frame pairs, where that function is
  right (see :func:`test_pinocchio_derivatives_are_wrong_for_points_between_moving_joints`),
  and central differences of ``pinocchio.constraintDynamics`` where it is not;
* the planar 4-bar written in closed form (its rods' Lagrangian, the lesson's closure in
  the coupler's cut frame) and solved and differentiated with mpmath at 60 digits.

Pinocchio writes a loop as points (CONTACT_3D) or a weld (CONTACT_6D) where closedchain
writes cut-frame rows: on the state manifold (phi = 0, J v = 0) the two define the same
motion, off it their rows differ by O(|phi|) and their gamma by O(|J v|). So da/d(q, v)
is compared on the tangent space of the state manifold, the directions (dq, dv) with
J dq = 0 and J dv + d(J v)/dq dq = 0, and in full where both write the loop as a weld.
"""

from __future__ import annotations

import os
from pathlib import Path

import mpmath
import numpy as np
import pinocchio as pin
import pytest
import scipy.linalg
from conftest import DATA_DIR, MECHANISM_FILES

import closedchain as cc
from closedchain.dynamics import SolverSettings

#: Mechanisms of every loop kind and the passive terms, for the finite-difference checks.
FD_MECHANISMS = {
    "fourbar": MECHANISM_FILES["fourbar"],  # revolute
    "agile_eye": MECHANISM_FILES["agile_eye"],  # revolute, spatial
    "turntable_fourbar": MECHANISM_FILES["turntable_fourbar"],  # moving base
    "spherical_chain": MECHANISM_FILES["spherical_chain"],  # spherical
    "fixed_branches": MECHANISM_FILES["fixed_branches"],  # fixed
    "slider_crank": MECHANISM_FILES["slider_crank"],  # prismatic
    "mimic_fourbar": DATA_DIR / "mimic_fourbar.urdf",  # coupling beside a revolute loop
    "mimic_gripper": DATA_DIR / "mimic_gripper.urdf",  # couplings only
    "passive_fourbar": DATA_DIR / "passive_fourbar.urdf",  # springs, damping, armature
}
#: Consistent states per mechanism.
N_STATES = 2
#: Central-difference step [rad, m, rad/s, m/s, N m or N] per unit of max(1, |x_k|) of
#: the fourth-order stencil: eps^(1/5), which balances its O(h^4) truncation against the
#: round-off eps |f| / h (a derivative small beside the function it differentiates, as
#: a gripper's lam beside its da/dv, keeps 1e-9 of the function's scale).
FD_STEP = np.finfo(float).eps ** (1.0 / 5.0)
#: Analytical against central differences: max |D - D_fd| / max |D_fd| (measured: up to
#: 2e-9 on these mechanisms).
TOL_FD = 1e-6
#: Against pinocchio.computeConstraintDynamicsDerivatives, same norm (measured: 1e-11).
TOL_PINOCCHIO = 1e-8
#: Pinocchio's proximal settings: accuracy, iterations and mu for rows of full rank, so
#: that its answer is the exact solution.
PIN_ACCURACY = 1e-14
PIN_MU = 1e-12
PIN_MAX_ITER = 200
#: Assembly tolerance of the states on the manifold that Pinocchio is differenced at [m].
PHI_TOL = 1e-14
#: The 40-digit 4-bar: working precision of the mpmath reference [digits] and its
#: central-difference step (truncation h^2 = 1e-40, round-off 1e-60 / h = 1e-40).
MP_DPS = 60
MP_STEP = mpmath.mpf("1e-20")
#: closedchain (double precision) against the 40-digit derivatives, same norm as TOL_FD
#: (measured: 3e-14).
TOL_HIGH_PRECISION = 1e-11
#: The default method's derivatives (at a, lam converged to al_tol) against kkt's.
TOL_METHODS = 1e-9


def _rel(D: np.ndarray, ref: np.ndarray) -> float:
    """max |D - ref| / max(max |ref|, tiny): the norm-wise relative error."""
    return float(np.max(np.abs(D - ref), initial=0.0) / max(np.max(np.abs(ref)), 1e-300))


def _fd(f, n: int, shift, scale: np.ndarray) -> np.ndarray:
    """Central differences of f(shift(dx)) at dx = 0 along each unit vector e_k, step
    FD_STEP max(1, |scale_k|), fourth order (the five-point stencil); shape (len(f(0)), n)."""
    cols = []
    for k in range(n):
        h = FD_STEP * max(1.0, abs(scale[k]))
        e = np.zeros(n)
        e[k] = h
        f1, f2 = f(shift(e)) - f(shift(-e)), f(shift(2.0 * e)) - f(shift(-2.0 * e))
        cols.append((8.0 * f1 - f2) / (12.0 * h))
    return np.array(cols).T


@pytest.fixture(scope="module")
def mechs():
    cache: dict[str, cc.Mechanism] = {}

    def get(name: str) -> cc.Mechanism:
        if name not in cache:
            cache[name] = cc.load(FD_MECHANISMS[name])
        return cache[name]

    return get


def _states(mech: cc.Mechanism, rng: np.random.Generator, n: int = N_STATES):
    for _ in range(n):
        q, v = cc.random_consistent_state(mech, rng)
        tau = (mech.gravity_torque_scale() or 1.0) * rng.standard_normal(mech.nv)
        yield q, v, tau


# -- finite differences -------------------------------------------------------------------


@pytest.mark.parametrize("name", list(FD_MECHANISMS))
def test_forward_dynamics_derivatives_match_finite_differences(mechs, rng, name):
    mech = mechs(name)
    for q, v, tau in _states(mech, rng):
        d = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt")
        res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
        np.testing.assert_array_equal(d.a, res.a)
        np.testing.assert_array_equal(d.lam, res.lam)
        ours = {
            "q": np.vstack([d.da_dq, d.dlam_dq]),
            "v": np.vstack([d.da_dv, d.dlam_dv]),
            "tau": np.vstack([d.da_dtau, d.dlam_dtau]),
        }
        fd = _solution_differences(mech, q, v, tau)
        for x in ours:
            assert _rel(ours[x], fd[x]) <= TOL_FD, (name, x, _rel(ours[x], fd[x]))


def _solution_differences(mech, q, v, tau) -> dict[str, np.ndarray]:
    """Central differences of (a, lam) of method kkt in q (tangent), v and tau."""

    def solve(q, v, tau):
        r = cc.forward_dynamics(mech, q, v, tau, method="kkt")
        return np.concatenate([r.a, r.lam])

    nv, model = mech.nv, mech.model
    return {
        "q": _fd(lambda x: solve(x, v, tau), nv, lambda e: pin.integrate(model, q, e), q * 0),
        "v": _fd(lambda x: solve(q, x, tau), nv, lambda e: v + e, v),
        "tau": _fd(lambda x: solve(q, v, x), nv, lambda e: tau + e, tau),
    }


def _row_differences(mech, q, v) -> dict[str, np.ndarray]:
    """Central differences of phi, J v and gamma in q (tangent), and of gamma in v."""
    nv, model = mech.nv, mech.model

    def on_q(e):
        return pin.integrate(model, q, e)

    unit = np.ones(nv)
    return {
        "J": _fd(lambda x: cc.compute_phi(mech, x), nv, on_q, unit),
        "dJv_dq": _fd(lambda x: cc.compute_jacobian(mech, x) @ v, nv, on_q, unit),
        "dgamma_dq": _fd(lambda x: cc.compute_gamma(mech, x, v), nv, on_q, unit),
        "dgamma_dv": _fd(lambda x: cc.compute_gamma(mech, q, x), nv, lambda e: v + e, v),
    }


@pytest.mark.parametrize("name", list(FD_MECHANISMS))
def test_constraint_derivatives_match_finite_differences(mechs, rng, name):
    mech = mechs(name)
    for q, v, _ in _states(mech, rng):
        # Off the velocity manifold too: the rows' derivatives hold for every v.
        v = v + rng.standard_normal(mech.nv)
        d = cc.constraint_derivatives(mech, q, v)
        np.testing.assert_allclose(d.phi, cc.compute_phi(mech, q), rtol=0, atol=1e-15)
        np.testing.assert_allclose(d.J, cc.compute_jacobian(mech, q), rtol=0, atol=1e-14)
        np.testing.assert_allclose(d.gamma, cc.compute_gamma(mech, q, v), rtol=1e-13, atol=1e-13)
        for what, ref in _row_differences(mech, q, v).items():
            ours = getattr(d, what)
            if np.max(np.abs(ref), initial=0.0) == 0.0:  # couplings only: J is constant
                assert np.max(np.abs(ours), initial=0.0) == 0.0, (name, what)
                continue
            assert _rel(ours, ref) <= TOL_FD, (name, what, _rel(ours, ref))


def test_baumgarte_terms_are_differentiated(mechs, rng):
    """With Baumgarte gains the rows are J a + gamma + 2 alpha J v + beta^2 phi; off the
    manifold (q perturbed) all their terms count."""
    mech = mechs("fourbar")
    settings = SolverSettings(baumgarte=(3.0, 5.0))
    model, nv = mech.model, mech.nv
    q, v, tau = next(_states(mech, rng, 1))
    q = pin.integrate(model, q, 1e-2 * rng.standard_normal(nv))

    def solve(x):
        r = cc.forward_dynamics(mech, x, v, tau, method="kkt", settings=settings)
        return np.concatenate([r.a, r.lam])

    d = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt", settings=settings)
    fd = _fd(solve, nv, lambda e: pin.integrate(model, q, e), np.ones(nv))
    assert _rel(np.vstack([d.da_dq, d.dlam_dq]), fd) <= TOL_FD


@pytest.mark.parametrize("name", ["fourbar", "agile_eye", "mimic_fourbar"])
def test_default_method_gives_the_kkt_derivatives(mechs, rng, name):
    """The default method's (a, lam) are the KKT solution to al_tol: the derivatives
    evaluated there are the KKT ones."""
    mech = mechs(name)
    for q, v, tau in _states(mech, rng, 1):
        ref = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt")
        d = cc.forward_dynamics_derivatives(mech, q, v, tau)
        assert d.method == "augmented-lagrangian"
        for f in ("da_dq", "da_dv", "da_dtau", "dlam_dq", "dlam_dv", "dlam_dtau"):
            assert _rel(getattr(d, f), getattr(ref, f)) <= TOL_METHODS, f


# -- Pinocchio ----------------------------------------------------------------------------


def _pinocchio_derivatives(mech, q, v, tau):
    """Pinocchio's (ddq_dq, ddq_dv, ddq_dtau) on the loops' constraint models, and a
    function (q, v, tau) -> its constrained accelerations."""
    cms, cds, _, data = mech.pinocchio_constraints()
    prox = pin.ProximalSettings(PIN_ACCURACY, 0.0, PIN_MU, PIN_MAX_ITER)
    model = mech.model

    def accelerations(q, v, tau=tau):
        return pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox).copy()

    accelerations(q, v)
    pin.computeConstraintDynamicsDerivatives(model, data, cms, cds, prox)
    return (data.ddq_dq.copy(), data.ddq_dv.copy(), data.ddq_dtau.copy()), accelerations


def _state_tangent(mech, q, v) -> tuple[np.ndarray, np.ndarray]:
    """A basis (Tq, Tv), shapes (nv, 2 k), of the tangent space of the state manifold
    {phi = 0, J v = 0} at (q, v): J dq = 0 and J dv + d(J v)/dq dq = 0."""
    cd = cc.constraint_derivatives(mech, q, v)
    N = scipy.linalg.null_space(cd.J)
    Tq = np.hstack([N, np.zeros_like(N)])
    Tv = np.hstack([-np.linalg.pinv(cd.J) @ cd.dJv_dq @ N, N])
    return Tq, Tv


def _tangent_differences(accelerations, mech, q, v, Tq, Tv) -> np.ndarray:
    """Central differences of accelerations(q, v) along curves on the state manifold
    with tangents the columns of (Tq, Tv): q + h Tq assembled onto phi = 0, v + h Tv
    projected onto J v = 0 (each correction O(h^2)). Off the manifold Pinocchio's point
    rows are not those of closedchain (and a revolute loop's six rows gain rank)."""
    settings = cc.AssemblySettings(tol=PHI_TOL)

    def on_manifold(e):
        qe = cc.assemble(mech, pin.integrate(mech.model, q, Tq @ e), settings=settings)
        return qe, cc.project_velocity(mech, qe, v + Tv @ e)

    k = Tq.shape[1]
    return _fd(lambda qv: accelerations(*qv), k, on_manifold, np.ones(k))


#: Mechanisms whose Pinocchio constraint models computeConstraintDynamicsDerivatives
#: differentiates correctly (a point on the ground, welds of full rank), and whether
#: both sides write every loop as a weld (then the full matrices agree).
PINOCCHIO_MECHANISMS = {"spherical_chain": False, "fixed_branches": True}


@pytest.mark.parametrize("name", list(PINOCCHIO_MECHANISMS))
def test_forward_dynamics_derivatives_match_pinocchio(mechs, rng, name):
    mech = mechs(name)
    for q, v, tau in _states(mech, rng):
        d = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt")
        (dq, dv, dtau), _ = _pinocchio_derivatives(mech, q, v, tau)
        Tq, Tv = _state_tangent(mech, q, v)
        assert _rel(d.da_dq @ Tq + d.da_dv @ Tv, dq @ Tq + dv @ Tv) <= TOL_PINOCCHIO
        assert _rel(d.da_dtau, dtau) <= TOL_PINOCCHIO
        if PINOCCHIO_MECHANISMS[name]:
            assert _rel(d.da_dq, dq) <= TOL_PINOCCHIO
            assert _rel(d.da_dv, dv) <= TOL_PINOCCHIO


@pytest.mark.parametrize("name", ["agile_eye", "fourbar"])
def test_revolute_loops_match_pinocchio_constrained_dynamics(mechs, rng, name):
    """Revolute loops are two points between moving links for Pinocchio (6 rows of rank
    5, or 2 in the plane), where its derivatives are wrong (ddq_dq: next test; ddq_dtau
    of the redundant rows moves with mu, 3e-4 off at mu = 1e-12 on the 4-bar): da/dtau
    and da/d(q, v) on the state manifold are compared with central differences of
    pinocchio.constraintDynamics."""
    mech = mechs(name)
    for q, v, tau in _states(mech, rng):
        d = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt")
        _, accelerations = _pinocchio_derivatives(mech, q, v, tau)
        fd = _fd(lambda x: accelerations(q, v, x), mech.nv, lambda e: tau + e, tau)  # noqa: B023
        assert _rel(d.da_dtau, fd) <= TOL_FD
        Tq, Tv = _state_tangent(mech, q, v)
        fd = _tangent_differences(accelerations, mech, q, v, Tq, Tv)
        assert _rel(d.da_dq @ Tq + d.da_dv @ Tv, fd) <= TOL_FD


def test_pinocchio_derivatives_are_wrong_for_points_between_moving_joints(mechs, rng):
    """Pinocchio 4.1's ddq_dq disagrees with its own constraintDynamics by O(1) when a
    CONTACT_3D joins two moving joints (../shared/PINOCCHIO.md): the reason the test
    above does not use it. When this fails, Pinocchio is fixed: compare with it there."""
    mech = mechs("agile_eye")
    q, v, tau = next(_states(mech, rng, 1))
    (dq, dv, _), accelerations = _pinocchio_derivatives(mech, q, v, tau)
    Tq, Tv = _state_tangent(mech, q, v)
    fd = _tangent_differences(accelerations, mech, q, v, Tq, Tv)
    assert _rel(dq @ Tq + dv @ Tv, fd) > 0.1


#: A local copy of example-parallel-robots' robots/ folder (git clone
#: https://github.com/Gepetto/example-parallel-robots): the corpus test runs when set.
CORPUS_ENV = "CLOSEDCHAIN_PARALLEL_ROBOTS"
#: Robots of the corpus whose loops are welds of full rank (Pinocchio's derivatives hold).
CORPUS_ROBOTS = ("5bar_linkage", "5bar_linkage_iso6d", "cassie_like", "talos_like")


@pytest.mark.parametrize("robot", CORPUS_ROBOTS)
@pytest.mark.skipif(CORPUS_ENV not in os.environ, reason=f"set {CORPUS_ENV} to the corpus")
def test_corpus_robots_match_pinocchio(rng, robot):
    folder = Path(os.environ[CORPUS_ENV]) / robot
    mech = cc.load(folder / "robot.urdf", loops=folder / "robot.yaml")
    for q, v, tau in _states(mech, rng):
        d = cc.forward_dynamics_derivatives(mech, q, v, tau, method="kkt")
        (dq, dv, dtau), _ = _pinocchio_derivatives(mech, q, v, tau)
        for ours, ref in ((d.da_dq, dq), (d.da_dv, dv), (d.da_dtau, dtau)):
            assert _rel(ours, ref) <= TOL_PINOCCHIO, robot
