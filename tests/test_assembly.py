"""Tests of the assembly: closure residuals, the globalized solve, q_ref within the limits.

References: finite differences of the closure residual through ``pin.integrate`` (its
Jacobian), Gauss-Newton on the rows (the solve the global one must beat), the cut
frames' geometry (a 180-degree flip), the joint limits written in the URDF, and
``pinocchio.constraintDynamics`` (the Stewart platform's accelerations).
"""

from __future__ import annotations

import logging

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, MECHANISM_FILES

import closedchain as cc
from closedchain.closure import AssemblySettings, assemble_closure, closure_error, solve_closure

#: One mechanism per loop type.
LOOP_TYPES = {
    "revolute": "fourbar",
    "spherical": "spherical_chain",
    "prismatic": "slider_crank",
    "fixed": "fixed_branches",
}
#: Step [rad or m] and agreement of central differences with the closure Jacobian.
FD_STEP = 1e-6
TOL_FD = 1e-7
#: Distance [rad] of the far starts from an assembled configuration.
FAR = 2.5
#: Far starts per mechanism.
N_FAR = 8
#: The 6-UPS Stewart platform in URDF+ and its leg limits [m].
STEWART = DATA_DIR / "stewart.urdf"
LEG_LIMITS = (0.3, 1.0)
#: Rounding of the rounded-CAD model's weld across the plane of motion [m].
ROUNDING = 1e-7


def closure(mech, q, jacobian=False):
    if jacobian:
        pin.computeJointJacobians(mech.model, mech.data, q)
    else:
        pin.forwardKinematics(mech.model, mech.data, q)
    return mech.declared.closure_residuals(mech.model, mech.data, jacobian=jacobian)


@pytest.mark.parametrize("loop_type", list(LOOP_TYPES))
def test_closure_jacobian_matches_finite_differences(load_mechanism, rng, loop_type):
    mech = load_mechanism(LOOP_TYPES[loop_type])
    assert {spec.type for spec in mech.description.loops} == {loop_type}
    for _ in range(5):
        q = mech.random_configuration(rng)
        _, E = closure(mech, q, jacobian=True)
        E_fd = np.zeros_like(E)
        for k in range(mech.nv):
            dv = np.zeros(mech.nv)
            dv[k] = FD_STEP
            plus, _ = closure(mech, pin.integrate(mech.model, q, dv))
            minus, _ = closure(mech, pin.integrate(mech.model, q, -dv))
            E_fd[:, k] = (plus - minus) / (2.0 * FD_STEP)
        assert np.linalg.norm(E - E_fd) <= TOL_FD * max(1.0, np.linalg.norm(E))


@pytest.mark.parametrize("name", list(MECHANISM_FILES))
def test_closure_residual_vanishes_at_q_ref(load_mechanism, name):
    mech = load_mechanism(name)
    pin.forwardKinematics(mech.model, mech.data, mech.q_ref)
    per_loop = mech.declared.loop_residuals(mech.model, mech.data)
    assert set(per_loop) == {spec.name for spec in mech.description.loops}
    assert max(per_loop.values()) <= AssemblySettings().closure_tol


def test_flipped_closure_is_not_closed(rng):
    """Turning distal joint 1 of the off-centre wrist by pi: the rows phi of leg 1 vanish,
    its closure residual holds the axis chord R a - a of length 2."""
    wrist = cc.load(DATA_DIR / "off_centre_wrist.urdf")
    q, _ = cc.random_consistent_state(wrist, rng)
    q[wrist.model.joints[wrist.model.getJointId("distal_joint_1")].idx_q] += np.pi
    assert np.max(np.abs(cc.compute_phi(wrist, q))) <= 1e-14
    e, _ = closure(wrist, q)
    (sl,) = [sl for name, sl in wrist.declared.closure_slices() if name == "leg1_platform"]
    assert np.linalg.norm(e[sl][3:]) == pytest.approx(2.0, abs=1e-12)
    assert closure_error(wrist.model, wrist.data, wrist.declared, q) > 1.0


@pytest.mark.parametrize("name", ["fourbar_fixed_loop", "agile_eye"])
def test_far_starts_that_gauss_newton_cannot_close(name, rng):
    """The 4-bar welded by a 6d fixed loop, and the Agile Eye (spherical), started 2.5 rad
    from q_ref: Gauss-Newton on the rows fails from half or more, the global solve closes
    all."""
    path = DATA_DIR / f"{name}.urdf" if name != "agile_eye" else MECHANISM_FILES[name]
    mech = cc.load(path)
    free = np.arange(mech.nv)
    settings = AssemblySettings()
    n_old = 0
    for _ in range(8):
        step = rng.standard_normal(mech.nv)
        q0 = pin.integrate(mech.model, mech.q_ref, FAR * step / np.linalg.norm(step))
        try:
            solve_closure(mech.model, mech.data, mech.declared, q0, free, settings)
            n_old += 1
        except cc.AssemblyError:
            pass
        q = cc.assemble(mech, q0)
        assert closure_error(mech.model, mech.data, mech.declared, q) <= settings.closure_tol
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= settings.tol
    assert n_old <= N_FAR // 2


def test_far_start_on_one_joint_of_the_welded_fourbar():
    mech = cc.load(DATA_DIR / "fourbar_fixed_loop.urdf")
    q0 = mech.q_ref.copy()
    q0[0] += FAR
    free = np.arange(mech.nv)
    # Gauss-Newton on the rows ends on the 180-degree flip, where they vanish too.
    with pytest.raises(cc.AssemblyError, match="spurious closure of loop.s. C"):
        solve_closure(mech.model, mech.data, mech.declared, q0, free, AssemblySettings())
    q = assemble_closure(mech.model, mech.data, mech.declared, q0, free, AssemblySettings())
    assert closure_error(mech.model, mech.data, mech.declared, q) <= AssemblySettings().tol


@pytest.fixture(scope="module")
def stewart():
    return cc.load(STEWART)


def test_stewart_platform_loads_within_its_limits(stewart):
    """Neutral has every leg at length 0 (outside [0.3, 1.0] m): q_ref comes from the middle
    of the limits, every leg within them and the platform above the base."""
    neutral = pin.neutral(stewart.model)
    assert not stewart.within_limits(neutral)
    assert (stewart.nc, stewart.mobility) == (15, 6)
    assert stewart.within_limits(stewart.q_ref)
    legs = [stewart.q_ref[stewart.joint_indices_v(f"leg_{i}")[0]] for i in range(1, 7)]
    assert all(LEG_LIMITS[0] <= x <= LEG_LIMITS[1] for x in legs)
    pin.framesForwardKinematics(stewart.model, stewart.data, stewart.q_ref)
    platform = stewart.data.oMf[stewart.model.getFrameId("platform")]
    assert platform.translation[2] > 0.0
    assert (
        closure_error(stewart.model, stewart.data, stewart.declared, stewart.q_ref)
        <= AssemblySettings().closure_tol
    )


def test_stewart_platform_matches_pinocchio(stewart):
    rep = cc.validate(stewart, n_samples=10, seed=0)
    assert rep.max_da <= rep.tol_a
    assert rep.max_dforce <= rep.tol_force


def test_stewart_platform_outside_any_limits_warns_naming_the_legs(tmp_path, caplog):
    """Legs limited to [0.3, 0.31] m cannot reach the platform: q_ref is a closure outside
    the limits, and the warning names the legs outside."""
    text = STEWART.read_text().replace('lower="0.3" upper="1.0"', 'lower="0.3" upper="0.31"')
    path = tmp_path / "short_stewart.urdf"
    path.write_text(text)
    with caplog.at_level(logging.WARNING, logger="closedchain.mechanism"):
        mech = cc.load(path)
    assert not mech.within_limits(mech.q_ref)
    (record,) = [r for r in caplog.records if "within the joint limits" in r.getMessage()]
    assert "no closed configuration within the joint limits" in record.getMessage()
    assert "leg_" in record.getMessage() and "outside [0.3, 0.31]" in record.getMessage()


def test_loading_needs_one_closed_configuration():
    """No random start at all: the walk from q_ref fills in the samples."""
    settings = cc.LoadSettings(max_attempts=0)
    mech = cc.load(STEWART, settings=settings)
    assert mech.row_selection.n_samples >= settings.n_samples * (1 + settings.walk_steps)
    assert mech.row_selection.rank == 15


def test_rounded_cad_weld_loads_with_a_warning(tmp_path, caplog):
    """The 4-bar welded by a fixed loop whose successor origin is off the plane of motion
    by 1e-7 m: no configuration closes the weld, the least-squares minimum is 1e-7; the
    model loads with a warning naming loop C, q_ref closes the kept rows."""
    text = (DATA_DIR / "fourbar_fixed_loop.urdf").read_text()
    rounded = text.replace(
        '<successor_origin xyz="0.3 0 0"', f'<successor_origin xyz="0.3 {ROUNDING!r} 0"'
    )
    assert rounded != text
    path = tmp_path / "rounded.urdf"
    path.write_text(rounded)
    with caplog.at_level(logging.WARNING, logger="closedchain.mechanism"):
        mech = cc.load(path)
    (record,) = [r for r in caplog.records if "least-squares" in r.getMessage()]
    assert "loop(s) C close only to a least-squares residual of 1e-07" in record.getMessage()
    assert mech.nc == 3
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) <= AssemblySettings().tol
    residual = closure_error(mech.model, mech.data, mech.declared, mech.q_ref)
    assert residual == pytest.approx(ROUNDING, rel=1e-6)
    # Usable after load: assembly closes the kept rows, a run keeps the rounding.
    guess = pin.integrate(mech.model, mech.q_ref, np.full(mech.nv, 0.3))
    q = cc.assemble(mech, guess, fixed=["crank_joint"])
    assert q[0] == guess[0]
    assert np.max(np.abs(cc.compute_phi(mech, q))) <= AssemblySettings().tol
    for backend in ("compiled", "numpy"):
        traj = cc.simulate(mech, q, np.zeros(mech.nv), 0.5, backend=backend)
        assert traj.max_constraint_residual == pytest.approx(ROUNDING, rel=1e-3)


def test_rounding_beyond_the_mismatch_tolerance_is_refused(tmp_path):
    text = (DATA_DIR / "fourbar_fixed_loop.urdf").read_text()
    path = tmp_path / "off_plane.urdf"
    path.write_text(
        text.replace('<successor_origin xyz="0.3 0 0"', '<successor_origin xyz="0.3 0.01 0"')
    )
    # Off the plane of every joint axis: proven open before any assembly is tried.
    with pytest.raises(
        cc.LoopClosureError,
        match=r"loop 'C' \(fixed\) cannot close in any configuration: .* differ by 0\.01 m",
    ):
        cc.load(path, settings=cc.LoadSettings(max_attempts=2))
