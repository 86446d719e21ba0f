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
#: 1.5e-8, the gripper's da/dv, small beside its lam; 6e-10 elsewhere).
TOL_FD = 1e-6
#: Against pinocchio.computeConstraintDynamicsDerivatives, same norm (measured: up to 7e-13).
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
#: (measured: 1.1e-15; the KKT matrix's condition number is about 10).
TOL_HIGH_PRECISION = 1e-12
#: The default method's derivatives (at a, lam converged to al_tol) against kkt's.
TOL_METHODS = 1e-9
#: Central-difference step of the inverse dynamics [rad, m, rad/s, m/s, rad/s^2 or m/s^2]:
#: smaller than FD_STEP, since its fifth derivatives are large where J_F is far from
#: orthogonal (the Agile Eye: truncation 3e-3 of 743 at 1e-3, 3e-7 at 1e-4).
INVERSE_FD_STEP = 1e-4
#: One integration step [s] of the step-derivative checks.
STEP_H = 1e-2
#: Step derivatives against central differences of the library's own step, same norm as
#: TOL_FD (measured: at most 2e-8, the fixed branches' dq/dq of the DOP853 step, where
#: the projection's iteration count differs between the differenced points).
TOL_STEP = 1e-6
#: The step's end state against the library's own step [rad, m, rad/s or m/s] (measured:
#: 3e-14, the slider-crank's v after the DOP853 step).
TOL_STEP_VALUE = 1e-12
#: The step [s] and the central-difference step in q [rad] of the step checks 1e-2 rad
#: short of the 4-bar's change point (FD_STEP, 7e-4, is not small beside that distance:
#: relative error 3e-3; at 1e-5, 2e-9).
NEAR_SINGULAR_STEP_H = 1e-3
NEAR_SINGULAR_FD_STEP = 1e-5


def _rel(D: np.ndarray, ref: np.ndarray) -> float:
    """max |D - ref| / max(max |ref|, tiny): the norm-wise relative error."""
    return float(np.max(np.abs(D - ref), initial=0.0) / max(np.max(np.abs(ref)), 1e-300))


def _fd(f, n: int, shift, scale: np.ndarray, step: float = FD_STEP) -> np.ndarray:
    """Central differences of f(shift(dx)) at dx = 0 along each unit vector e_k, step
    ``step`` max(1, |scale_k|), fourth order (the five-point stencil); shape (len(f(0)), n)."""
    cols = []
    for k in range(n):
        h = step * max(1.0, abs(scale[k]))
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


# -- the 4-bar at 40 digits ---------------------------------------------------------------


class _FourBarMP:
    """The lesson's 4-bar (models/fourbar.urdf: rods of 1 kg, lengths in
    FourBarClosedForms) in closed form at mpmath precision: M and h from the rods'
    Lagrangian, the closure in the coupler's cut frame (conftest's phi_cut,
    jacobian_cut, gamma_cut) and the KKT solve, all in the joint coordinates q."""

    G = mpmath.mpf("9.81")  # gravity along -z [m/s^2], the lesson's -y

    def __init__(self, cf) -> None:
        self.a, self.b, self.c, self.d = (mpmath.mpf(str(x)) for x in (cf.a, cf.b, cf.c, cf.d))
        self.T = mpmath.matrix([[1, 0, 0], [1, 1, 0], [0, 0, 1]])

    @staticmethod
    def _e(t):
        return mpmath.matrix([mpmath.cos(t), mpmath.sin(t)])

    @staticmethod
    def _eperp(t):
        return mpmath.matrix([-mpmath.sin(t), mpmath.cos(t)])

    def _rods(self, th, thd):
        """Per rod: (mass, inertia about the centre, J_theta (2 x 3) of the centre,
        its bias acceleration (2,), angular-velocity row (1 x 3) in theta)."""
        a, b, c = self.a, self.b, self.c
        z = mpmath.matrix(2, 1)
        ep = [self._eperp(t) for t in th]
        e = [self._e(t) for t in th]
        cols = [
            [a / 2 * ep[0], z, z],
            [a * ep[0], b / 2 * ep[1], z],
            [z, z, c / 2 * ep[2]],
        ]
        bias = [
            -a / 2 * thd[0] ** 2 * e[0],
            -a * thd[0] ** 2 * e[0] - b / 2 * thd[1] ** 2 * e[1],
            -c / 2 * thd[2] ** 2 * e[2],
        ]
        out = []
        for k, length in enumerate((a, b, c)):
            Jc = mpmath.matrix(2, 3)
            for j in range(3):
                Jc[0, j], Jc[1, j] = cols[k][j][0], cols[k][j][1]
            w = mpmath.matrix(1, 3)
            w[0, k] = 1
            out.append((1, length**2 / 12, Jc, bias[k], w))
        return out

    def solve(self, q, v, tau):
        """(a, lam) of the KKT system at (q, v, tau), mpmath vectors."""
        q, v, tau = (mpmath.matrix(list(x)) for x in (q, v, tau))
        th, thd = self.T * q, self.T * v
        M, h = mpmath.matrix(3, 3), mpmath.matrix(3, 1)
        for m, inertia, Jc, bias, w in self._rods(th, thd):
            Jq, wq = Jc * self.T, w * self.T
            M += m * Jq.T * Jq + inertia * wq.T * wq
            h += m * Jq.T * bias
            h += m * self.G * Jq[1, :].T
        J, gamma = self._rows(th, thd)
        K = mpmath.matrix(5, 5)
        rhs = mpmath.matrix(5, 1)
        for i in range(3):
            rhs[i] = tau[i] - h[i]
            for j in range(3):
                K[i, j] = M[i, j]
        for r in range(2):
            rhs[3 + r] = -gamma[r]
            for j in range(3):
                K[3 + r, j] = K[j, 3 + r] = J[r, j]
        x = mpmath.lu_solve(K, rhs)
        return x

    def _rows(self, th, thd):
        """J (2 x 3, in q) and gamma (2,) of phi_cut = Q(theta3)^T phi (conftest)."""
        a, b, c, d = self.a, self.b, self.c, self.d
        c3, s3 = mpmath.cos(th[1]), mpmath.sin(th[1])
        Q = mpmath.matrix([[-s3, -c3], [c3, -s3]])
        dQ = mpmath.matrix([[-c3, s3], [-s3, -c3]])
        phi = a * self._e(th[0]) + b * self._e(th[1]) - c * self._e(th[2])
        phi[0] -= d
        Jc = mpmath.matrix(2, 3)
        for j, (length, sign) in enumerate(((a, 1), (b, 1), (c, -1))):
            col = sign * length * self._eperp(th[j])
            Jc[0, j], Jc[1, j] = col[0], col[1]
        Jcut = Q.T * Jc
        col = dQ.T * phi
        Jcut[0, 1] += col[0]
        Jcut[1, 1] += col[1]
        Jdot_thd = -(
            a * thd[0] ** 2 * self._e(th[0])
            + b * thd[1] ** 2 * self._e(th[1])
            - c * thd[2] ** 2 * self._e(th[2])
        )
        w3 = thd[1]
        gamma = -Q.T * phi * w3**2 + 2 * w3 * dQ.T * (Jc * thd) + Q.T * Jdot_thd
        return Jcut * self.T, gamma


def test_fourbar_derivatives_agree_with_a_40_digit_reference(fourbar, fourbar_closed_forms, rng):
    """(a, lam) and their derivatives in q, v and tau against the closed-form 4-bar solved
    and differenced with mpmath at MP_DPS digits (central differences of step MP_STEP)."""
    ref = _FourBarMP(fourbar_closed_forms)
    with mpmath.workdps(MP_DPS):
        for q, v, tau in _states(fourbar, rng, 3):
            d = cc.forward_dynamics_derivatives(fourbar, q, v, tau, method="kkt")
            x0 = ref.solve(q, v, tau)
            np.testing.assert_allclose(
                np.array(x0.tolist(), dtype=float).ravel(),
                np.concatenate([d.a, d.lam]),
                rtol=TOL_HIGH_PRECISION,
                atol=TOL_HIGH_PRECISION,
            )
            args = [mpmath.matrix(list(x)) for x in (q, v, tau)]
            for i, (da, dlam) in enumerate(
                ((d.da_dq, d.dlam_dq), (d.da_dv, d.dlam_dv), (d.da_dtau, d.dlam_dtau))
            ):
                cols = []
                for k in range(3):
                    plus, minus = list(args), list(args)
                    plus[i], minus[i] = args[i].copy(), args[i].copy()
                    plus[i][k] += MP_STEP
                    minus[i][k] -= MP_STEP
                    cols.append((ref.solve(*plus) - ref.solve(*minus)) / (2 * MP_STEP))
                exact = np.array([[float(c[r]) for c in cols] for r in range(5)])
                assert _rel(np.vstack([da, dlam]), exact) <= TOL_HIGH_PRECISION, i


# -- where the derivative is not defined, and bad input ------------------------------------

#: The 4-bar's change point (a + d = b + c): theta2 = 180 deg with every link on the
#: ground line, q = [theta2, theta3 - theta2, theta4]; J has rank 1 there.
FOURBAR_CHANGE_POINT = np.array([np.pi, -np.pi, np.pi])


#: Crank angles short of the change point [rad] of the growth test.
NEAR_SINGULAR_OFFSETS = (1e-2, 1e-3)
#: Fraction of the 1 / sigma^2 growth of max |dlam/dq| the test asks for (measured: 1.0).
NEAR_SINGULAR_GROWTH = 0.5


@pytest.mark.parametrize("method", ["kkt", "augmented-lagrangian"])
def test_singular_position_is_refused(fourbar, method):
    q = FOURBAR_CHANGE_POINT
    assert np.max(np.abs(cc.compute_phi(fourbar, q))) < 1e-15
    zero = np.zeros(fourbar.nv)
    with pytest.raises(cc.SingularConfigurationError, match=r"KKT matrix.*(not defined|rank)"):
        cc.forward_dynamics_derivatives(fourbar, q, zero, zero, method=method)


def test_derivatives_grow_near_a_singular_position_and_stay_exact(fourbar, rng):
    """Approaching the change point (sigma_min(J) ~ 0.2 times the crank's distance to it)
    the multipliers' derivatives grow like 1 / sigma_min^2 and the derivatives still
    match central differences (tau: a and lam are linear in it)."""
    peaks = []
    for offset in NEAR_SINGULAR_OFFSETS:
        guess = FOURBAR_CHANGE_POINT - np.array([offset, 0.0, 0.0])
        q = cc.assemble(fourbar, guess, fixed=["crank_joint"])
        v = cc.project_velocity(fourbar, q, rng.standard_normal(fourbar.nv))
        tau = rng.standard_normal(fourbar.nv)
        d = cc.forward_dynamics_derivatives(fourbar, q, v, tau, method="kkt")
        fd = _solution_differences(fourbar, q, v, tau)["tau"]
        assert _rel(np.vstack([d.da_dtau, d.dlam_dtau]), fd) <= TOL_FD
        peaks.append(np.max(np.abs(d.dlam_dq)))
    ratio = NEAR_SINGULAR_OFFSETS[0] / NEAR_SINGULAR_OFFSETS[1]
    assert peaks[1] >= NEAR_SINGULAR_GROWTH * ratio**2 * peaks[0]


def test_bad_input_is_refused_in_one_line(fourbar):
    zero = np.zeros(fourbar.nv)
    with pytest.raises(cc.ClosedChainError, match=r"^q has shape \(2,\), expected \(3,\)$"):
        cc.forward_dynamics_derivatives(fourbar, np.zeros(2), zero)
    with pytest.raises(cc.ClosedChainError, match=r"^v contains non-finite values"):
        cc.constraint_derivatives(fourbar, fourbar.q_ref, np.full(fourbar.nv, np.nan))
    with pytest.raises(cc.ClosedChainError, match="settings"):
        cc.forward_dynamics_derivatives(fourbar, fourbar.q_ref, zero, settings={"cond_max": 1})
    with pytest.raises(cc.UnknownChoiceError, match="kkt"):
        cc.forward_dynamics_derivatives(fourbar, fourbar.q_ref, zero, method="newton")


# -- inverse dynamics ---------------------------------------------------------------------


def _inverse_differences(mech, q, v, a_P, **kwargs) -> dict[str, np.ndarray]:
    """Central differences of (tau, a, lam) of inverse_dynamics (numpy) in q (tangent), v
    and a_P."""

    def solve(q, v, a_P):
        r = cc.inverse_dynamics(mech, q, v, a_P, backend="numpy", **kwargs)
        return np.concatenate([r.tau, r.a, r.lam])

    nv, mob, model = mech.nv, mech.mobility, mech.model
    step = INVERSE_FD_STEP
    return {
        "q": _fd(lambda x: solve(x, v, a_P), nv, lambda e: pin.integrate(model, q, e), q * 0, step),
        "v": _fd(lambda x: solve(q, x, a_P), nv, lambda e: v + e, v, step),
        "a": _fd(lambda x: solve(q, v, x), mob, lambda e: a_P + e, a_P, step),
    }


@pytest.mark.parametrize("name", list(FD_MECHANISMS))
def test_inverse_dynamics_derivatives_match_finite_differences(mechs, rng, name):
    mech = mechs(name)
    for q, v, _ in _states(mech, rng):
        a_P = rng.standard_normal(mech.mobility)
        d = cc.inverse_dynamics_derivatives(mech, q, v, a_P)
        res = cc.inverse_dynamics(mech, q, v, a_P)
        np.testing.assert_allclose(d.tau, res.tau, rtol=0, atol=0)
        np.testing.assert_array_equal(d.prescribed_idx_v, mech.independent_idx_v)
        fd = _inverse_differences(mech, q, v, a_P)
        for x, ref in fd.items():
            ours = np.vstack(
                [getattr(d, f"dtau_d{x}"), getattr(d, f"da_d{x}"), getattr(d, f"dlam_d{x}")]
            )
            assert _rel(ours, ref) <= TOL_FD, (name, x, _rel(ours, ref))


def test_over_actuated_inverse_derivatives_are_the_minimum_norm_torques(mechs, rng):
    """The 4-bar driven at its crank and its rocker (two actuators, one degree of
    freedom): the minimum-norm torques' derivatives."""
    mech = mechs("fourbar")
    q, v, _ = next(_states(mech, rng, 1))
    a_P = rng.standard_normal(mech.mobility)
    actuated = [0, 2]
    d = cc.inverse_dynamics_derivatives(mech, q, v, a_P, actuated=actuated)
    assert np.all(d.tau[actuated] != 0.0)
    fd = _inverse_differences(mech, q, v, a_P, actuated=actuated)
    for x, ref in fd.items():
        ours = np.vstack(
            [getattr(d, f"dtau_d{x}"), getattr(d, f"da_d{x}"), getattr(d, f"dlam_d{x}")]
        )
        assert _rel(ours, ref) <= TOL_FD, x


# -- one integration step -----------------------------------------------------------------


def _library_step(mech, q, v, tau, h, integrator: str, method: str = "augmented-lagrangian"):
    """(q+, v+) of the library's own step: ``rk4_projected``, or one trial of
    ``Dop853Far`` (tolerances so loose that it is accepted) for ``"dop853"``, with the
    Problem that ``simulate`` builds for the default method and stage projection."""
    from closedchain.dynamics.base import METHOD_CAPABILITIES
    from closedchain.simulate.dop853_rk43 import Dop853Far
    from closedchain.simulate.fixed import rk4_projected
    from closedchain.simulate.problem import Problem

    problem = Problem(mech, method, tau, SolverSettings(), cc.SimulationSettings())
    problem.singular_robust = METHOD_CAPABILITIES[method].singular_robust
    if integrator == "rk4-projected":
        a = problem.accel(0.0, q, v)
        return rk4_projected(problem, 0.0, q, v, a, h)[:2]
    far = Dop853Far(problem, 1.0, 1.0, method)
    far.h = h
    out = far.trial(0.0, q, v, problem.accel(0.0, q, v, method=far.method), h)
    assert isinstance(out, tuple), out  # None: handed over to rk43
    return out[1], out[2]


def _step_differences(mech, q, v, tau, h, scheme, method) -> dict[str, np.ndarray]:
    """Central differences of the library's step in q (tangent), v and tau; the end
    configuration as pin.difference from the undisturbed one."""
    model, nv = mech.model, mech.nv
    q1, _ = _library_step(mech, q, v, tau, h, scheme, method)

    def end(q, v, tau):
        qe, ve = _library_step(mech, q, v, tau, h, scheme, method)
        return np.concatenate([pin.difference(model, q1, qe), ve])

    return {
        "q": _fd(lambda x: end(x, v, tau), nv, lambda e: pin.integrate(model, q, e), q * 0),
        "v": _fd(lambda x: end(q, x, tau), nv, lambda e: v + e, v),
        "tau": _fd(lambda x: end(q, v, x), nv, lambda e: tau + e, tau),
    }


@pytest.mark.parametrize(
    ("integrator", "scheme", "method"),
    [
        ("rk4", "rk4-projected", "augmented-lagrangian"),  # mass-orthogonal projections
        ("rk4", "rk4-projected", "kkt"),  # minimum-norm projections
        ("default", "dop853", "augmented-lagrangian"),
    ],
)
@pytest.mark.parametrize("name", list(FD_MECHANISMS))
def test_step_derivatives_match_finite_differences(mechs, rng, name, integrator, scheme, method):
    mech = mechs(name)
    q, v, tau = next(_states(mech, rng, 1))
    d = cc.step_derivatives(mech, q, v, tau, STEP_H, integrator=integrator, method=method)
    assert d.scheme == scheme
    q1, v1 = _library_step(mech, q, v, tau, STEP_H, scheme, method)
    assert np.max(np.abs(pin.difference(mech.model, q1, d.q))) <= TOL_STEP_VALUE
    assert np.max(np.abs(v1 - d.v)) <= TOL_STEP_VALUE
    fd = _step_differences(mech, q, v, tau, STEP_H, scheme, method)
    for x, ref in fd.items():
        ours = np.vstack([getattr(d, f"dq_d{x}"), getattr(d, f"dv_d{x}")])
        assert _rel(ours, ref) <= TOL_STEP, (x, _rel(ours, ref))


def test_default_step_is_rk4_near_a_singular_position(fourbar, rng):
    """Within the rank indicator's cap (the 4-bar 1e-2 rad short of its change point) the
    default integrator's step is rk43's: rk4 with stage projection. The differences in q
    take a step far below the distance to the change point (NEAR_SINGULAR_FD_STEP)."""
    guess = FOURBAR_CHANGE_POINT - np.array([NEAR_SINGULAR_OFFSETS[0], 0.0, 0.0])
    q = cc.assemble(fourbar, guess, fixed=["crank_joint"])
    v = cc.project_velocity(fourbar, q, rng.standard_normal(fourbar.nv))
    tau = rng.standard_normal(fourbar.nv)
    h, model = NEAR_SINGULAR_STEP_H, fourbar.model
    d = cc.step_derivatives(fourbar, q, v, tau, h)
    assert d.scheme == "rk4-projected"
    ref = cc.step_derivatives(fourbar, q, v, tau, h, integrator="rk4")
    np.testing.assert_array_equal(d.dv_dq, ref.dv_dq)
    q1, _ = _library_step(fourbar, q, v, tau, h, "rk4-projected")

    def end(q, tau):
        qe, ve = _library_step(fourbar, q, v, tau, h, "rk4-projected")
        return np.concatenate([pin.difference(model, q1, qe), ve])

    fd_q = _fd(
        lambda x: end(x, tau),
        fourbar.nv,
        lambda e: pin.integrate(model, q, e),
        q * 0,
        NEAR_SINGULAR_FD_STEP,
    )
    fd_tau = _fd(lambda x: end(q, x), fourbar.nv, lambda e: tau + e, tau)
    assert _rel(np.vstack([d.dq_dq, d.dv_dq]), fd_q) <= TOL_STEP
    assert _rel(np.vstack([d.dq_dtau, d.dv_dtau]), fd_tau) <= TOL_STEP


@pytest.mark.parametrize("offset", NEAR_SINGULAR_OFFSETS)
def test_default_method_derivatives_near_a_singular_position(fourbar, rng, offset):
    """Short of the change point the augmented Lagrangian still converges to the KKT
    solution (its penalty does not move the fixed point): its derivatives are kkt's."""
    guess = FOURBAR_CHANGE_POINT - np.array([offset, 0.0, 0.0])
    q = cc.assemble(fourbar, guess, fixed=["crank_joint"])
    v = cc.project_velocity(fourbar, q, rng.standard_normal(fourbar.nv))
    tau = rng.standard_normal(fourbar.nv)
    ref = cc.forward_dynamics_derivatives(fourbar, q, v, tau, method="kkt")
    d = cc.forward_dynamics_derivatives(fourbar, q, v, tau)
    for f in ("da_dq", "da_dv", "da_dtau", "dlam_dq", "dlam_dv", "dlam_dtau"):
        assert _rel(getattr(d, f), getattr(ref, f)) <= TOL_METHODS, f


def test_step_derivatives_refuse_bad_input(fourbar):
    q, zero = fourbar.q_ref, np.zeros(fourbar.nv)
    with pytest.raises(cc.UnknownChoiceError, match="rk4"):
        cc.step_derivatives(fourbar, q, zero, zero, 1e-2, integrator="euler")
    with pytest.raises(cc.ClosedChainError, match="positive"):
        cc.step_derivatives(fourbar, q, zero, zero, 0.0)
    free = cc.load(MECHANISM_FILES["fourbar"], root_joint="free")
    with pytest.raises(cc.ClosedChainError, match="free-flyer"):
        cc.step_derivatives(free, free.q_ref, np.zeros(free.nv), None, 1e-2)
