"""Tests of closedchain.kinematics: assembly, velocity projection, singularity measures.

References: the lesson's 4-bar closed forms and Freudenstein's equation
(tests/conftest.py), geometry (which rocker angles the 4-bar can reach), and
linear algebra done here with numpy (projectors, row spaces).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_MECHANISMS

import closedchain as cc

#: Default assembly tolerance on max |phi| [m or -].
TOL_ASSEMBLY = cc.AssemblySettings().tol
#: Projection identities (J P v = 0, P P v = P v, ...) relative to |v|.
TOL_PROJECTION = 1e-12
#: Singular values of J against the lesson's closed-form J (round-off) [m].
TOL_SIGMA = 1e-12
#: Random guesses are q_ref displaced by up to this [rad or m] per coordinate.
GUESS_SPREAD = 0.3


def q_slices_of(mech, idx_v):
    """Configuration entries of the joints owning the velocity indices idx_v."""
    out = []
    for j in range(1, mech.model.njoints):
        jm = mech.model.joints[j]
        if any(jm.idx_v <= i < jm.idx_v + jm.nv for i in idx_v):
            out += list(range(jm.idx_q, jm.idx_q + jm.nq))
    return np.array(out, dtype=int)


def guess_near_q_ref(mech, rng):
    return pin.integrate(mech.model, mech.q_ref, rng.uniform(-GUESS_SPREAD, GUESS_SPREAD, mech.nv))


# -- assemble ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_assemble_converges(load_mechanism, rng, name):
    mech = load_mechanism(name)
    for _ in range(5):
        guess = guess_near_q_ref(mech, rng)
        q = cc.assemble(mech, guess)
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= TOL_ASSEMBLY
        # A valid configuration (unit complex numbers for continuous joints).
        assert np.linalg.norm(pin.normalize(mech.model, q) - q) <= 1e-14


@pytest.mark.parametrize(
    ("name", "fixed"),
    [(n, "independent") for n in ALL_MECHANISMS]
    # Bricard's linkage has no actuators to hold.
    + [(n, "actuated") for n in ALL_MECHANISMS if n != "bricard"],
)
def test_assemble_holds_fixed_coordinates_exactly(load_mechanism, rng, name, fixed):
    mech = load_mechanism(name)
    held_v = mech.coordinate_indices(fixed)
    held_q = q_slices_of(mech, held_v)
    assert len(held_q) > 0
    for _ in range(5):
        # Start off the manifold, with the held coordinates at a reachable value (moving
        # them, even by 0.02 rad, can leave the range of motion near a turning point).
        q0, _ = cc.random_consistent_state(mech, rng)
        dv = rng.uniform(-0.1, 0.1, mech.nv)
        dv[held_v] = 0.0
        guess = pin.integrate(mech.model, q0, dv)
        q = cc.assemble(mech, guess, fixed=fixed)
        assert np.array_equal(q[held_q], guess[held_q])  # bit for bit
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= TOL_ASSEMBLY


def test_assemble_holds_named_joints(fourbar, rng):
    guess = fourbar.q_ref + rng.uniform(-0.2, 0.2, 3)
    q = cc.assemble(fourbar, guess, fixed=["coupler_joint"])
    assert q[1] == guess[1]
    assert np.max(np.abs(cc.compute_phi(fourbar, q))) <= TOL_ASSEMBLY


def test_assemble_raises_with_the_residual_when_impossible(fourbar):
    """The rocker at theta4 = 0 puts C 0.8 m from A; crank + coupler reach at most 0.6 m."""
    guess = np.array([0.0, 0.0, 0.0])
    with pytest.raises(
        cc.AssemblyError,
        match=r"fourbar: assembly did not converge: max \|phi\| = [0-9.e+-]+ > tol 1\.0e-12 "
        r"\(holding 1 coordinates: rocker_joint\)",
    ) as info:
        cc.assemble(fourbar, guess, fixed=["rocker_joint"])
    exc = info.value
    # The gap is at least 0.8 - 0.6 = 0.2 m, so max |phi| >= 0.2 / sqrt(2).
    assert exc.residual >= 0.2 / np.sqrt(2) - 1e-9
    assert exc.q[2] == 0.0
    assert exc.residual == pytest.approx(np.max(np.abs(cc.compute_phi(fourbar, exc.q))), rel=1e-12)


def test_assemble_raises_when_the_iterations_run_out(fourbar):
    settings = cc.AssemblySettings(max_iter=1)
    with pytest.raises(cc.AssemblyError, match=r"max \|phi\| = .* > tol") as info:
        cc.assemble(fourbar, np.array([1.0, 2.0, -1.0]), settings=settings)
    assert info.value.residual > settings.tol


def test_assemble_checks_its_arguments(fourbar):
    with pytest.raises(cc.ClosedChainError, match=r"q_guess has shape \(2,\), expected \(3,\)"):
        cc.assemble(fourbar, np.zeros(2))
    with pytest.raises(cc.ClosedChainError, match="q_guess contains non-finite values"):
        cc.assemble(fourbar, np.array([0.0, np.nan, 0.0]))
    with pytest.raises(cc.ClosedChainError, match="unknown joint 'crank'; joints: crank_joint"):
        cc.assemble(fourbar, fourbar.q_ref, fixed=["crank"])


# -- project_velocity ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_project_velocity_is_the_orthogonal_projection(load_mechanism, rng, name):
    mech = load_mechanism(name)
    for _ in range(5):
        q, _ = cc.random_consistent_state(mech, rng)
        J = cc.compute_jacobian(mech, q)
        v = rng.standard_normal(mech.nv)
        Pv = cc.project_velocity(mech, q, v)
        scale = np.linalg.norm(v)
        assert np.linalg.norm(J @ Pv) <= TOL_PROJECTION * scale
        assert np.linalg.norm(cc.project_velocity(mech, q, Pv) - Pv) <= TOL_PROJECTION * scale
        # v - Pv lies in the row space of J, so it is orthogonal to Pv.
        r = v - Pv
        y = np.linalg.lstsq(J.T, r, rcond=None)[0]
        assert np.linalg.norm(J.T @ y - r) <= TOL_PROJECTION * scale
        assert abs(r @ Pv) <= TOL_PROJECTION * scale**2
        # The same as the textbook projector I - J^+ J.
        P = np.eye(mech.nv) - np.linalg.pinv(J) @ J
        assert np.linalg.norm(P @ v - Pv) <= TOL_PROJECTION * scale


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_project_velocity_keeps_fixed_coordinates(load_mechanism, rng, name):
    mech = load_mechanism(name)
    ind = mech.independent_idx_v
    q, _ = cc.random_consistent_state(mech, rng)
    J = cc.compute_jacobian(mech, q)
    v = rng.standard_normal(mech.nv)
    Pv = cc.project_velocity(mech, q, v, fixed="independent")
    assert np.array_equal(Pv[ind], v[ind])
    assert np.linalg.norm(J @ Pv) <= TOL_PROJECTION * np.linalg.norm(v) * 1e2


# -- singularity measures --------------------------------------------------------------------


def _fourbar_at(fourbar, cf, theta2, branch=0):
    theta = cf.freudenstein(theta2)[branch]
    q = cc.assemble(fourbar, cf.q_from_theta(theta), fixed=["crank_joint"])
    return q, theta


def test_singularity_measures_match_the_lesson_jacobian(fourbar, fourbar_closed_forms):
    cf = fourbar_closed_forms
    for theta2 in np.deg2rad([-120, -30, 0, 45, 100, 160]):
        for branch in (0, 1):
            q, theta = _fourbar_at(fourbar, cf, theta2, branch)
            m = cc.singularity_measures(fourbar, q)
            Jc = cf.jacobian(cf.theta(q)) @ cf.T
            s = np.linalg.svd(Jc, compute_uv=False)
            assert abs(m.sigma_min - s[-1]) <= TOL_SIGMA
            assert m.cond_J == pytest.approx(s[0] / s[-1], rel=1e-9)
            sd = np.linalg.svd(Jc[:, 1:], compute_uv=False)  # dependent: coupler, rocker
            assert m.cond_JD == pytest.approx(sd[0] / sd[-1], rel=1e-9)


def test_singularity_measures_near_the_change_point(fourbar, fourbar_closed_forms):
    """theta2 -> 180 deg: a + d = b + c, coupler and rocker collinear, sigma_min(J) -> 0."""
    cf = fourbar_closed_forms
    sigmas, conds = [], []
    for delta in [1e-1, 1e-2, 1e-3, 1e-4]:
        q, _ = _fourbar_at(fourbar, cf, np.pi - delta)
        m = cc.singularity_measures(fourbar, q)
        s = np.linalg.svd(cf.jacobian(cf.theta(q)) @ cf.T, compute_uv=False)
        assert abs(m.sigma_min - s[-1]) <= 1e-9
        # The change point is a simple root of sigma_min(theta2): it vanishes like delta.
        assert m.sigma_min <= delta
        sigmas.append(m.sigma_min)
        conds.append(m.cond_JD)
    assert all(b < a for a, b in zip(sigmas, sigmas[1:], strict=False))
    assert all(b > a for a, b in zip(conds, conds[1:], strict=False))
    # Exactly at the change point: crank at 180 deg, coupler along +x, rocker at 180 deg.
    q_sing = cf.q_from_theta(np.array([np.pi, 0.0, np.pi]))
    assert np.linalg.norm(cc.compute_phi(fourbar, q_sing)) <= 1e-15
    m = cc.singularity_measures(fourbar, q_sing)
    assert m.sigma_min <= 1e-15
    assert m.cond_J > 1e14
    with pytest.raises(
        cc.SingularConfigurationError, match=r"fourbar: the KKT matrix .* is singular"
    ):
        cc.forward_dynamics(fourbar, q_sing, np.zeros(3), np.zeros(3), method="kkt")


# -- random_consistent_state -----------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_random_consistent_state(load_mechanism, rng, name):
    mech = load_mechanism(name)
    for _ in range(3):
        q, v = cc.random_consistent_state(mech, rng, min_sigma=1e-2)
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= TOL_ASSEMBLY
        assert mech.within_limits(q)
        assert np.linalg.norm(cc.compute_jacobian(mech, q) @ v) <= TOL_PROJECTION * max(
            1.0, np.linalg.norm(v)
        )
        assert cc.singularity_measures(mech, q).sigma_min >= 1e-2


def test_random_consistent_state_gives_up_loudly(fourbar, rng):
    with pytest.raises(cc.AssemblyError, match="fourbar: no random consistent state in 3 attempts"):
        cc.random_consistent_state(fourbar, rng, min_sigma=1e3, max_attempts=3)
