"""Singular positions: the augmented-Lagrangian and proximal methods, ALI3-P, the default
configuration of simulate on the N-four-bar (IFToMM A02) and the change-point 4-bar.

References: ``pinocchio``-independent KKT solves (``kkt`` where J has full rank, a
minimum-norm least-squares KKT solve where it has not), the quadrature reference of the
N-four-bar (``tests/nfourbar_reference.py``) and energy conservation.
"""

from __future__ import annotations

import math

import nfourbar_reference as ref
import numpy as np
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain import compiled
from closedchain.dynamics.base import METHOD_CAPABILITIES, compute_terms
from closedchain.simulate import SimulationSettings, fixed, simulate

#: Backends the default configuration runs on here.
BACKENDS = ("compiled", "numpy") if compiled.available() else ("numpy",)
#: Agreement of the new methods with kkt at regular states [rad/s^2] (measured <= 1e-12).
METHOD_AGREEMENT_TOL = 1e-9
#: B0 position at t = 20 s against the quadrature reference [m] (issue 11).
B0_TOL = 1e-6
#: Energy drift over the run, relative (issue 11).
ENERGY_DRIFT_TOL = 1e-6
#: Closure kept by projection [m].
RESIDUAL_TOL = 1e-10
#: Benchmark horizon [s].
T_BENCHMARK = 20.0
#: Open-branch 4-bar (tests/test_simulate.py): crank angle [deg] and Newton guess [deg].
OPEN_GUESS_DEG = (10.0, 50.0, 30.0)
T_CHANGE_POINT = 10.0


def _with_all_declared_rows(path) -> cc.Mechanism:
    """A mechanism whose layer keeps every declared row (redundant ones included)."""
    mech = cc.load(path)
    mech.closure.active = mech.declared  # LoopClosure owns the kept rows
    return mech


@pytest.mark.parametrize("name", ["fourbar", "agile_eye"])
@pytest.mark.parametrize("method", ["augmented-lagrangian", "proximal"])
def test_methods_agree_with_kkt(load_mechanism, rng, name, method):
    mech = load_mechanism(name)
    for _ in range(20):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.normal(size=mech.nv) * mech.gravity_torque_scale()
        ref_res = cc.forward_dynamics(mech, q, v, tau, method="kkt")
        res = cc.forward_dynamics(mech, q, v, tau, method=method)
        assert np.linalg.norm(res.a - ref_res.a) <= METHOD_AGREEMENT_TOL
        assert (
            np.linalg.norm(
                res.generalized_constraint_force() - ref_res.generalized_constraint_force()
            )
            <= METHOD_AGREEMENT_TOL
        )


@pytest.mark.slow
@pytest.mark.parametrize("name", ["fourbar", "agile_eye"])
@pytest.mark.parametrize("method", ["augmented-lagrangian", "proximal"])
def test_redundant_rows_without_row_selection(load_mechanism, rng, name, method):
    """All declared rows (4-bar: 5 of rank 2; Agile Eye: 15 of rank 6): same accelerations
    and generalized constraint force as kkt on the selected rows; kkt itself refuses them."""
    selected = load_mechanism(name)
    redundant = _with_all_declared_rows(selected.path)
    assert redundant.nc > selected.nc
    for _ in range(10):
        q, v = cc.random_consistent_state(selected, rng)
        tau = rng.normal(size=selected.nv) * selected.gravity_torque_scale()
        ref_res = cc.forward_dynamics(selected, q, v, tau, method="kkt")
        res = cc.forward_dynamics(redundant, q, v, tau, method=method)
        assert np.linalg.norm(res.a - ref_res.a) <= METHOD_AGREEMENT_TOL
        assert (
            np.linalg.norm(
                res.generalized_constraint_force() - ref_res.generalized_constraint_force()
            )
            <= METHOD_AGREEMENT_TOL
        )
    with pytest.raises(cc.SingularConfigurationError, match="condition number"):
        cc.forward_dynamics(redundant, q, v, tau, method="kkt")


def test_capabilities_are_declared():
    assert METHOD_CAPABILITIES["augmented-lagrangian"].singular_robust
    assert METHOD_CAPABILITIES["augmented-lagrangian"].redundant_rows
    assert METHOD_CAPABILITIES["proximal"].redundant_rows
    assert not METHOD_CAPABILITIES["kkt"].singular_robust


def _flat_state(mech):
    """The N-four-bar with every rod horizontal (theta = 0), cranks turning at 3 rad/s."""
    is_crank = np.array([n.startswith("crank") for n in mech.coordinate_names])
    return np.zeros(mech.nq), np.where(is_crank, -3.0, 3.0)


def _min_norm_kkt(mech, q, v):
    """Gauss's principle by a minimum-norm least-squares KKT solve (any rank of J)."""
    ws = compute_terms(mech, q, v)
    M, J, h, gamma = ws.M.copy(), ws.J.copy(), ws.h.copy(), ws.gamma.copy()
    nv, nc = mech.nv, mech.nc
    K = np.block([[M, J.T], [J, np.zeros((nc, nc))]])
    x = np.linalg.lstsq(K, np.concatenate([-h, -gamma]), rcond=1e-12)[0]
    return x[:nv], J, gamma


def test_flat_position_kkt_refuses_augmented_lagrangian_solves():
    """At the N-four-bar's flat position J loses rank: kkt raises, the augmented Lagrangian
    returns Gauss's accelerations (minimum-norm KKT solve) with J a + gamma = 0."""
    mech = cc.load(MODELS / "nfourbar_2.urdf")
    q, v = _flat_state(mech)
    with pytest.raises(cc.SingularConfigurationError, match="condition number"):
        cc.forward_dynamics(mech, q, v, method="kkt")
    res = cc.forward_dynamics(mech, q, v, method="augmented-lagrangian")
    a_ref, J, gamma = _min_norm_kkt(mech, q, v)
    assert np.linalg.matrix_rank(J, tol=1e-10) < mech.nc
    assert np.all(np.isfinite(res.a))
    assert np.linalg.norm(res.a - a_ref) <= 1e-6
    assert res.constraint_residual() <= 1e-9


#: The proximal method's bias near the flat position (defaults mu_r = 1e-8, 50
#: iterations; measured at 1e-4 rad: |J a + gamma| 1.9e-12, |a - a_kkt| 3.8e-8).
PROXIMAL_NEAR_FLAT = 1e-4
PROXIMAL_BIAS_A_MAX = 1e-6
PROXIMAL_BIAS_RESIDUAL_MAX = 1e-10


def test_proximal_bias_at_and_near_the_flat_position():
    """At the flat position proximal converges to Gauss's accelerations; 1e-4 rad away
    (J nearly rank-deficient) it stops at its iteration cap with a small, bounded bias."""
    mech = cc.load(MODELS / "nfourbar_2.urdf")
    q, v = _flat_state(mech)
    res = cc.forward_dynamics(mech, q, v, method="proximal")
    a_ref, _, _ = _min_norm_kkt(mech, q, v)
    assert np.linalg.norm(res.a - a_ref) <= 1e-6
    is_crank = np.array([n.startswith("crank") for n in mech.coordinate_names])
    q_near = np.where(is_crank, PROXIMAL_NEAR_FLAT, -PROXIMAL_NEAR_FLAT)
    res = cc.forward_dynamics(mech, q_near, v, method="proximal")
    exact = cc.forward_dynamics(mech, q_near, v, method="kkt")
    bias = np.linalg.norm(res.a - exact.a)
    assert bias <= PROXIMAL_BIAS_A_MAX
    assert res.constraint_residual() <= PROXIMAL_BIAS_RESIDUAL_MAX


# -- the N-four-bar -----------------------------------------------------------------------


def _b0_error_and_drift(mech, traj, n):
    theta = ref.crank_angle(n, T_BENCHMARK)
    # B0 is the tip of crank 0 (pivot at the origin): its position from the crank angle.
    b0 = ref.point_b0(traj.q[-1, 0])
    err = float(np.linalg.norm(b0 - ref.point_b0(theta)))
    drift = float(np.max(np.abs(traj.energy - traj.energy[0]))) / ref.characteristic_energy(n)
    return err, drift


#: The benchmark's N; the default configuration (compiled core) of N = 1, 2, 10 runs in
#: the slow set (seconds each), the others with ``pytest --run-benchmark`` (N = 40: 9 to
#: 11 s CPU on the compiled band path, 43 s before it; measured figures: README, "Singular
#: positions"; ``scripts/nfourbar_cost.py --full`` prints the same numbers).
NFOURBAR_N = (1, 2, 5, 10, 20, 40)
NFOURBAR_IN_CI = (1, 2, 10)
#: ALI3-P's step for the 20 s runs [s]: second order, its B0 error at 20 s is 1.3e-5 m at
#: 1 ms and 8.2e-7 m at 0.25 ms (N = 1), so 1e-6 m takes 0.2 ms: 100,000 steps, on the
#: compiled core 0.9, 1.5, 3.0, 5.1, 10.6 and 27 s of CPU for N = 1, 2, 5, 10, 20, 40
#: (``scripts/nfourbar_cost.py --full --integrator ali3p --dt 2e-4``; 80 to 160 s on numpy
#: for N = 1 to 5). N = 1 and 2 run in the slow set, the others with --run-benchmark.
ALI3P_DT = 2e-4
ALI3P_IN_CI = (1, 2)


#: Measured failures of the issue's bar, kept as strict expected failures (the bar is not
#: lowered; a fix turns them into errors to remove from here): N -> what was measured.
#: (N = 1 and 5 missed it, 6.9e-5 and 6.2e-6 m, until the stage projection became
#: mass-orthogonal and its evaluation points kept 0.3 steps from the crossings.)
DEFAULT_MISSES: dict[int, str] = {}


#: (N = 5 stopped at t = 6.59 s, Newton stalling at a step that ended 0.002 step before a
#: flat position, until ALI3-P's steps were kept away from the crossings; N = 40 at t =
#: 0.7216 s, a step ending 0.095 step past one, until the zone also covered a rank
#: indicator below sqrt(10 / ali3p_penalty).)
ALI3P_MISSES: dict[int, str] = {}


def _nfourbar_params(in_ci: tuple[int, ...], misses: dict[int, str]):
    params = []
    for n in NFOURBAR_N:
        marks = [pytest.mark.slow] + ([] if n in in_ci else [pytest.mark.benchmark])
        if n in misses:
            marks.append(pytest.mark.xfail(reason=misses[n], strict=True))
        params.append(pytest.param(n, marks=marks))
    return params


def _check_benchmark(mech, traj, n):
    """The issue's bar at t = 20 s, against the quadrature reference (tests/nfourbar_reference.py).

    B0 is the benchmark's output point: the tip of crank 0, i.e. the left end of the first
    coupler, at (L cos theta, 0, L sin theta) for crank angle theta (crank 0 pivots at the
    world origin; frame ``crank_0_tip`` of the model). Its error is the distance between
    B0 at the simulated crank angle and at the reference's, <= B0_TOL = 1e-6 m. The energy
    drift is max_t |E(t) - E(0)| over the output samples divided by the largest kinetic
    energy of the motion (``characteristic_energy``), <= ENERGY_DRIFT_TOL = 1e-6.
    """
    err, drift = _b0_error_and_drift(mech, traj, n)
    assert err <= B0_TOL, err
    assert drift <= ENERGY_DRIFT_TOL, drift
    assert traj.max_constraint_residual <= RESIDUAL_TOL
    # Every crank at the same angle: the motion stayed on the parallelogram branch.
    cranks = [i for i, nm in enumerate(mech.coordinate_names) if nm.startswith("crank")]
    assert np.max(np.ptp(traj.q[:, cranks], axis=1)) <= B0_TOL
    assert np.min(traj.q[:, 0]) < -2 * math.pi * 9  # about 10 turns, 20 flat positions


@pytest.mark.parametrize("n", _nfourbar_params(NFOURBAR_IN_CI, DEFAULT_MISSES))
def test_nfourbar_default_configuration(nfourbar, n):
    """20 s of the benchmark with simulate's default method, integrator, tolerances and
    stabilization (augmented-lagrangian, dop853-rk43, rtol 1e-11, stage-projection): see
    :func:`_check_benchmark`."""
    mech = nfourbar(n)
    q0, v0 = ref.initial_state(mech)
    traj = simulate(mech, q0, v0, T_BENCHMARK, t_eval=np.linspace(0, T_BENCHMARK, 201))
    info = traj.info
    assert (info["method"], info["integrator"], info["stabilization"], info["dt"]) == (
        "augmented-lagrangian",
        "dop853-rk43",
        "stage-projection",
        None,
    )
    assert (info.rtol, info.atol) == cc.INTEGRATORS["dop853-rk43"].tolerances
    _check_benchmark(mech, traj, n)


#: Relative perturbations of v0 (multiples of 1e-15) under which N = 1 meets the bar too.
#: Before the mass-orthogonal stage projection and the rule that keeps evaluation points
#: 0.3 steps from a crossing, they moved the B0 error between 1.4e-10 and 2.7e-5 m (the
#: flat passages amplified round-off about 1e10-fold). The exact B0 moves by about 1e-12 m.
V0_PERTURBATIONS = (-2, -1, 1, 2, 10)


@pytest.mark.slow
@pytest.mark.skipif(not compiled.available(), reason="the compiled core is not built")
@pytest.mark.parametrize("k", V0_PERTURBATIONS)
def test_nfourbar_default_is_insensitive_to_round_off(nfourbar, k):
    """N = 1, 20 s, default configuration (compiled core: 0.3 s each) with v0 scaled by
    1 + k 1e-15: every run meets the bar of :func:`_check_benchmark`."""
    mech = nfourbar(1)
    q0, v0 = ref.initial_state(mech)
    traj = simulate(
        mech,
        q0,
        v0 * (1.0 + k * 1e-15),
        T_BENCHMARK,
        t_eval=np.linspace(0, T_BENCHMARK, 201),
        backend="compiled",
    )
    _check_benchmark(mech, traj, 1)


@pytest.mark.parametrize("n", _nfourbar_params(ALI3P_IN_CI, ALI3P_MISSES))
def test_nfourbar_ali3p(nfourbar, n):
    """20 s of the benchmark with ALI3-P (augmented-lagrangian, mass-orthogonal) at
    ALI3P_DT: see :func:`_check_benchmark`."""
    mech = nfourbar(n)
    q0, v0 = ref.initial_state(mech)
    traj = simulate(
        mech,
        q0,
        v0,
        T_BENCHMARK,
        integrator="ali3p",
        dt=ALI3P_DT,
        t_eval=np.linspace(0, T_BENCHMARK, 201),
    )
    assert traj.info["stabilization"] == "mass-orthogonal"
    _check_benchmark(mech, traj, n)


#: The largest step of the 0.1 s output grid at which the default configuration meets
#: the bar for every N (compiled core, ``scripts/nfourbar_cost.py --full --dt X``: at
#: 6.25 ms N = 1, 2 and 10 miss it with 3.6e-6, 1.8e-6 and 1.1e-6 m; at 5 ms the largest
#: B0 error is 8.8e-7 m, N = 1). The numpy path at this step is the issue's cost figure.
LARGE_DT = 5e-3


def _large_step_params():
    params = []
    for n in NFOURBAR_N:
        for backend in ("compiled", "numpy"):
            marks = [pytest.mark.slow]
            if backend == "numpy" or n not in NFOURBAR_IN_CI:
                marks.append(pytest.mark.benchmark)
            params.append(pytest.param(n, backend, marks=marks, id=f"{n}-{backend}"))
    return params


@pytest.mark.parametrize(("n", "backend"), _large_step_params())
def test_nfourbar_default_at_large_step(nfourbar, n, backend):
    """20 s of the benchmark with the default configuration at LARGE_DT on each backend
    (numpy: the reference path whose cost the issue bounds): see :func:`_check_benchmark`."""
    if backend == "compiled" and not compiled.available():
        pytest.skip("the compiled core is not built")
    mech = nfourbar(n)
    q0, v0 = ref.initial_state(mech)
    traj = simulate(
        mech,
        q0,
        v0,
        T_BENCHMARK,
        dt=LARGE_DT,
        t_eval=np.linspace(0, T_BENCHMARK, 201),
        backend=backend,
    )
    assert traj.info["backend"] == backend
    assert traj.info["dt"] == pytest.approx(LARGE_DT, rel=1e-12)  # no shortening
    _check_benchmark(mech, traj, n)


#: Crossing times [steps from a step's start] ahead of the step, and behind it.
CROSSINGS_AHEAD = (0.05, 0.3, 0.431, 0.6, 0.97, 1.2, 2.5)
CROSSINGS_BEHIND = (-0.05, -0.5, -2.0)


def _indicator_samples(tau, slope_after=1.0):
    """A rank indicator proportional to the distance to a crossing at tau (slope 2e-3
    per step before it, 2e-3 slope_after after it) at a step's start, midpoint and end."""
    return [2e-3 * abs(t - tau) * (slope_after if t > tau else 1.0) for t in (0.0, 0.5, 1.0)]


@pytest.mark.parametrize("tau", CROSSINGS_AHEAD)
def test_crossing_estimate_from_start_midpoint_and_end(tau):
    """The V-shaped fit recovers the crossing wherever it is, also once the midpoint is
    past it (the former line through the start and midpoint put 0.431 at 0.595)."""
    assert fixed.crossing_estimate(*_indicator_samples(tau)) == pytest.approx(tau, abs=1e-12)
    # Slopes 1 : 1.5 on the two sides (three samples cannot tell that from a shifted
    # crossing with equal slopes): within 0.15 step.
    assert abs(fixed.crossing_estimate(*_indicator_samples(tau, 1.5)) - tau) <= 0.15


@pytest.mark.parametrize("tau", CROSSINGS_BEHIND)
def test_no_retake_for_a_crossing_behind_the_step(tau):
    zone = SimulationSettings().stage_singular_zone
    assert fixed.retake_plan(fixed.crossing_estimate(*_indicator_samples(tau)), zone) is None


def test_retakes_keep_every_evaluation_point_out_of_the_zone():
    """For a crossing anywhere from zone to 1 + zone steps ahead (the previous step kept
    its end zone away), the plain step or the retake chosen keeps all its evaluation
    points (substep midpoints and ends) at least zone steps from it."""
    zone = SimulationSettings().stage_singular_zone
    for tau in np.linspace(zone, 1 + zone, 241):
        plan = fixed.retake_plan(tau, zone)
        if plan is None:
            points = [0.5, 1.0]
        else:
            double, h1 = plan
            end = 2.0 if double else 1.0
            points = [end / 2, end] if h1 >= end else [h1 / 2, h1, (h1 + end) / 2, end]
        assert min(abs(p - tau) for p in points) >= zone - 1e-12, (tau, plan)


#: Where a step of the default configuration ends relative to a flat position [rad of
#: crank angle]: far, near, within the augmented Lagrangian's unenforced zone (below
#: about 3e-6 rad), exactly on it, and just past it.
LANDINGS = (1e-3, 1e-4, 4.7e-5, 1e-5, 1e-6, 1e-7, 0.0, -1e-6, -1e-4)
#: Error of the crank rate after three default steps through a flat position, against
#: the one-degree-of-freedom motion integrated by scipy [rad/s] (measured <= 7.6e-11 on
#: both backends, the retakes' truncation; before the steps were kept away from the
#: crossing: 1e-6 at 1e-6 rad, the whole rate, 4.9 rad/s, at 0 rad).
LANDING_RATE_TOL = 1e-10
#: Error of the crank angle after those three steps [rad]: the rk4 truncation of the
#: retaken steps, whose substeps reach 1.65 steps to keep every stage 0.3 steps from the
#: crossing (measured 1.1e-11 on both backends alike for every landing within 0.3
#: steps; 7.6e-15 without the retakes, stage_singular_zone = 0; 1e-13 with the former
#: 0.04-step rule).
LANDING_ANGLE_TOL = 3e-11
#: Compiled against numpy through a flat position (same splits): round-off only.
LANDING_BACKEND_TOL = 1e-11


def _landing_case(mech, n, x, dt):
    """A parallelogram state whose first default step of dt ends x rad before the flat
    position theta = 0, and the exact crank angle and rate three steps later."""
    import scipy.integrate

    inertia, c, _ = ref.constants(n)
    e0 = ref.energy(n, math.pi / 2, ref.OMEGA0)
    is_crank = np.array([nm.startswith("crank") for nm in mech.coordinate_names])

    def rate(theta):
        return -math.sqrt(2 * (e0 - ref.GRAVITY * c * math.sin(theta)) / inertia)

    def exact(theta0, t):
        sol = scipy.integrate.solve_ivp(
            lambda _, y: [y[1], -ref.GRAVITY * c * math.cos(y[0]) / inertia],
            (0.0, t),
            [theta0, rate(theta0)],
            method="DOP853",
            rtol=1e-13,
            atol=1e-15,
        )
        return sol.y[0, -1], sol.y[1, -1]

    theta0 = x - rate(0.0) * dt
    for _ in range(5):  # Newton on the start angle: exact(theta0, dt) lands at x
        theta0 -= exact(theta0, dt)[0] - x
    q0 = np.where(is_crank, theta0, -theta0)
    v0 = np.where(is_crank, rate(theta0), -rate(theta0))
    return q0, v0, exact(theta0, 3 * dt)


@pytest.mark.parametrize("x", LANDINGS)
def test_default_steps_through_a_flat_position_wherever_they_land(nfourbar, x):
    """N = 5, three fixed rk4 steps whose first ends x rad before a flat position: the
    crank rate agrees with the reduced motion (scipy DOP853 at 1e-13) on both backends,
    and the two backends take the same substeps around the crossing."""
    n, dt = 5, SimulationSettings().dt
    mech = nfourbar(n)
    q0, v0, (theta, rate) = _landing_case(mech, n, x, dt)
    grid = np.linspace(0.0, 3 * dt, 4)
    runs = {b: simulate(mech, q0, v0, 3 * dt, dt=dt, t_eval=grid, backend=b) for b in BACKENDS}
    for traj in runs.values():
        assert abs(traj.v[-1, 0] - rate) <= LANDING_RATE_TOL
        assert abs(traj.q[-1, 0] - theta) <= LANDING_ANGLE_TOL
        assert traj.max_constraint_residual <= RESIDUAL_TOL
    if len(runs) == 2:
        a, b = runs["compiled"], runs["numpy"]
        assert a.info["singular_splits"] == b.info["singular_splits"]
        assert np.max(np.abs(a.q - b.q)) <= LANDING_BACKEND_TOL
        assert np.max(np.abs(a.v - b.v)) <= LANDING_BACKEND_TOL


#: ALI3-P's step in the landing test [s] (the 20 s runs' step).
ALI3P_LANDING_DT = ALI3P_DT
#: Error of the crank rate after three ALI3-P steps of 0.2 ms through a flat position,
#: against the reduced motion [rad/s]: its second-order truncation (measured <= 1.3e-9
#: with the steps kept away from the crossing; before, 7.9e-4 at 1e-6 rad, 2.6e-3 at 0,
#: 1.3e-2 and the other branch (crank angle off by 5.1 rad) at -1e-6 rad, Newton stalled
#: at 1e-5 and 1e-7 rad).
ALI3P_LANDING_RATE_TOL = 1e-8
#: Compiled against numpy ALI3-P through a flat position (same splits) [rad; rad/s times
#: dt]: the Newton tolerance ali3p_tol (a correction e left in the displacement is e in q
#: and 2 e / h in v).
ALI3P_LANDING_BACKEND_TOL = 1e-10


@pytest.mark.parametrize("x", LANDINGS)
def test_ali3p_steps_through_a_flat_position_wherever_they_land(nfourbar, x):
    """N = 5, three ALI3-P steps whose first would end x rad before a flat position: the
    crank rate and angle agree with the reduced motion (scipy DOP853 at 1e-13)."""
    n, dt = 5, ALI3P_LANDING_DT
    mech = nfourbar(n)
    q0, v0, (theta, rate) = _landing_case(mech, n, x, dt)
    grid = np.linspace(0.0, 3 * dt, 4)
    runs = {
        b: simulate(mech, q0, v0, 3 * dt, integrator="ali3p", dt=dt, t_eval=grid, backend=b)
        for b in BACKENDS
    }
    for traj in runs.values():
        assert abs(traj.v[-1, 0] - rate) <= ALI3P_LANDING_RATE_TOL
        assert abs(traj.q[-1, 0] - theta) <= ALI3P_LANDING_RATE_TOL * dt
        assert traj.max_constraint_residual <= RESIDUAL_TOL
    if len(runs) == 2:
        a, b = runs["compiled"], runs["numpy"]
        assert a.info["singular_splits"] == b.info["singular_splits"]
        assert np.max(np.abs(a.q - b.q)) <= ALI3P_LANDING_BACKEND_TOL
        assert np.max(np.abs(a.v - b.v)) <= ALI3P_LANDING_BACKEND_TOL / dt


#: ALI3-P (second order) at 1 ms over 2 s on N = 2: B0 error measured 2.4e-7 m.
ALI3P_T = 2.0
ALI3P_B0_TOL = 1e-6


@pytest.mark.slow
def test_ali3p_passes_the_flat_positions(nfourbar):
    mech = nfourbar(2)
    q0, v0 = ref.initial_state(mech)
    traj = simulate(mech, q0, v0, ALI3P_T, integrator="ali3p", dt=1e-3)
    assert traj.info.stabilization == "mass-orthogonal"
    theta = ref.crank_angle(2, ALI3P_T)
    assert np.linalg.norm(ref.point_b0(traj.q[-1, 0]) - ref.point_b0(theta)) <= ALI3P_B0_TOL
    assert np.min(traj.q[:, 0]) < -math.pi  # through theta = 0 and -pi (flat)
    assert traj.max_constraint_residual <= RESIDUAL_TOL


def test_ali3p_needs_a_singular_robust_method(nfourbar):
    mech = nfourbar(2)
    q0, v0 = ref.initial_state(mech)
    with pytest.raises(cc.ClosedChainError, match="needs a method with singular_robust"):
        simulate(mech, q0, v0, 0.1, integrator="ali3p", method="kkt")


# -- the change-point 4-bar ---------------------------------------------------------------


@pytest.fixture(scope="module")
def q_open(load_mechanism):
    mech = load_mechanism("fourbar")
    return cc.assemble(mech, np.radians(OPEN_GUESS_DEG), fixed=["crank_joint"])


@pytest.mark.slow
def test_change_point_fourbar_default_passes(load_mechanism, q_open):
    """Open branch from rest at 10 deg, 10 s, default configuration: energy kept to 1e-6
    (measured 9.3e-8) through every passage of the change point."""
    mech = load_mechanism("fourbar")
    traj = simulate(mech, q_open, np.zeros(mech.nv), T_CHANGE_POINT)
    assert np.min(traj.q[:, 0]) < -math.pi
    assert traj.energy_drift <= ENERGY_DRIFT_TOL
    assert traj.max_constraint_residual <= RESIDUAL_TOL


#: Which configurations pass the change point (1 s, through it at t = 0.393 s) and which
#: stop with the documented error naming the configuration that passes (the default,
#: which passes, is test_change_point_fourbar_default_passes).
CHANGE_POINT_TABLE = {
    "kkt-rk4-stage": (dict(method="kkt", dt=1e-3), "singular"),
    "kkt-dop853": (dict(method="kkt", integrator="DOP853", rtol=1e-10, atol=1e-10), "singular"),
    # rk43's step ends straddle the change point; its stages are checked too.
    "kkt-rk43": (dict(method="kkt", integrator="rk43"), "singular"),
    "kkt-rk43-numpy": (dict(method="kkt", integrator="rk43", backend="numpy"), "singular"),
    "al-dop853-none": (
        dict(integrator="DOP853", rtol=1e-10, atol=1e-10, stabilization="none"),
        "singular",
    ),
    "al-rk4-projection": (dict(stabilization="projection"), "singular"),
    "al-rk4-projection-unguarded": (
        dict(stabilization="projection", settings=SimulationSettings(singular_cond=math.inf)),
        "inaccurate",
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("config", sorted(CHANGE_POINT_TABLE))
def test_change_point_configurations(load_mechanism, q_open, config):
    mech = load_mechanism("fourbar")
    kwargs, outcome = CHANGE_POINT_TABLE[config]
    v0 = np.zeros(mech.nv)
    if outcome == "singular":
        with pytest.raises(
            cc.SingularConfigurationError,
            match=r"t = .*condition number.*use method='augmented-lagrangian' with "
            r"stabilization='stage-projection'",
        ) as exc:
            simulate(mech, q_open, v0, 1.0, **kwargs)
        assert exc.value.t == pytest.approx(0.393, abs=0.02)
        return
    traj = simulate(mech, q_open, v0, 1.0, **kwargs)
    assert np.min(traj.q[:, 0]) < -math.pi
    if outcome == "pass":
        assert traj.energy_drift <= ENERGY_DRIFT_TOL
    else:
        # Passes without stopping, but acceleration-level steps off the manifold near the
        # change point lose energy (measured 9e-5 for rk4 + projection over 2 s).
        assert traj.energy_drift > ENERGY_DRIFT_TOL


@pytest.mark.slow
def test_branch_series_says_which_branch_the_change_point_leaves_on(
    load_mechanism, fourbar_closed_forms, q_open
):
    """The open-branch 4-bar passes its change point at t = 0.393 s: the branch series
    (sign of det(J_D), J_D = coupler and rocker columns) starts +1 (open) and the
    trajectory reports each change, independently checked with the lesson's closed form
    det(J_D) = b c sin(theta3 - theta4) (theta3 = q0 + q1, theta4 = q2)."""
    mech = load_mechanism("fourbar")
    traj = simulate(mech, q_open, np.zeros(mech.nv), 0.6, t_eval=np.linspace(0, 0.6, 61))
    cf = fourbar_closed_forms
    closed_form = np.sign([cf.det_dependent(cf.theta(q)) for q in traj.q])
    assert traj.branch is not None
    assert np.array_equal(np.abs(traj.branch), np.ones(len(traj.t)))
    # Up to one global sign (the orientation of the URDF axes).
    assert np.array_equal(traj.branch, closed_form) or np.array_equal(traj.branch, -closed_form)
    changes = traj.info.branch_changes
    assert changes, "the motion left the change point on the other assembly branch"
    t_before, t_after, _, _ = changes[0]
    assert t_before <= 0.393 + 0.02 and t_after >= 0.393 - 0.02


# -- banded solves (many loops) -----------------------------------------------------------

#: Loops of the N-four-bar whose P = M + alpha J^T J and J J^T are banded (nv > 8).
BANDED_N = 10


#: Band against dense solve of M + alpha J^T J at rho = 1 (two backward-stable solves).
BAND_SOLVE_RTOL = 1e-12


@pytest.mark.parametrize("order", ["natural", "reversed"])
def test_band_holds_the_products_and_solves_like_dense(nfourbar, rng, order):
    """N = 10: J^T J (in a column order, here the natural one or reversed) and J J^T have
    nothing outside the structural half bandwidth the banded solvers use, the band of
    J J^T is its diagonals, and P = M + alpha J^T J factorized as a band solves like the
    dense P."""
    from closedchain.dynamics.augmented_lagrangian import PenalizedSolver, relative_penalty
    from closedchain.dynamics.base import mass_matrix, position_terms

    mech = nfourbar(BANDED_N)
    solver = PenalizedSolver(mech)
    assert solver.banded and solver.normal.banded
    perm = np.arange(mech.nv) if order == "natural" else np.arange(mech.nv)[::-1].copy()
    for _ in range(3):
        q = mech.random_configuration(rng)
        J = position_terms(mech, q).J.copy()
        JtJ = (J.T @ J)[np.ix_(perm, perm)]
        assert np.abs(np.triu(JtJ, solver.bandwidth + 1)).max() == 0.0
        band, dense = solver.normal.band(J), J @ J.T
        b = len(band) - 1
        assert np.abs(np.triu(dense, b + 1)).max() == 0.0  # nothing outside the band
        for k in range(b + 1):
            assert np.array_equal(band[b - k, k:], np.diagonal(dense, k))
        M = mass_matrix(mech, q).M.copy()
        alpha = relative_penalty(M, J, 1.0)  # a well-conditioned P for the solve check
        solver.factor(M, J, alpha, mech, q)
        rhs = rng.standard_normal(mech.nv)
        want = np.linalg.solve(M + alpha * J.T @ J, rhs)
        assert np.linalg.norm(solver.solve(rhs) - want) <= BAND_SOLVE_RTOL * np.linalg.norm(want)


#: Distances [rad of crank angle] from the N-four-bar's flat position of the rank checks.
FLAT_DISTANCES = (1e-2, 1e-3, 1e-4, 1e-6)
#: The banded and the dense rank indicator: round-off apart.
RANK_INDICATOR_RTOL = 1e-12
#: Spread of rank indicator / distance near a flat position (linear in the distance).
RANK_INDICATOR_LINEAR_RTOL = 1e-4


def test_banded_rank_indicator_is_the_dense_one(nfourbar):
    """N = 10 on its parallelogram branch at crank angles delta from the flat position:
    the rank indicator from the band of J J^T (dpbtrf, |J^T x|^2) equals the dense one,
    is at least sqrt(lambda_min / mean eigenvalue) of J J^T (a Rayleigh quotient; eigvalsh
    as the reference), and grows linearly with delta (what crossing_estimate fits)."""
    from closedchain.dynamics.augmented_lagrangian import NormalSolver

    mech = nfourbar(BANDED_N)
    normal = NormalSolver(mech)
    assert normal.banded
    q0, v0 = ref.initial_state(mech)
    direction = v0 / ref.OMEGA0  # the branch is a straight line in these coordinates
    ratios = []
    for delta in FLAT_DISTANCES:
        J = cc.compute_jacobian(mech, q0 + (delta - math.pi / 2) * direction)
        dense, banded = fixed.rank_indicator(J), fixed.rank_indicator(J, normal)
        assert abs(banded - dense) <= RANK_INDICATOR_RTOL * dense
        if delta >= 1e-4:  # eigvalsh resolves lambda_min ~ delta^2 to round-off
            ev = np.linalg.eigvalsh(J @ J.T)
            assert banded >= math.sqrt(ev[0] / ev.mean()) * (1.0 - RANK_INDICATOR_LINEAR_RTOL)
        ratios.append(banded / delta)
    assert np.ptp(ratios) <= RANK_INDICATOR_LINEAR_RTOL * np.mean(ratios)


@pytest.mark.slow
def test_banded_solves_agree_with_dense_ones(nfourbar, rng):
    """N = 10: the augmented Lagrangian on the banded factorization of M + alpha J^T J
    agrees with kkt (dense LU), and the banded normal equations give lstsq's minimum-norm
    correction (the projections' Gauss-Newton step)."""
    from closedchain.dynamics.augmented_lagrangian import NormalSolver, PenalizedSolver

    mech = nfourbar(BANDED_N)
    assert PenalizedSolver(mech).banded
    normal = NormalSolver(mech)
    assert normal.banded and normal.bandwidth < mech.nc // 4
    for _ in range(5):
        q, v = cc.random_consistent_state(mech, rng)
        ref_res = cc.forward_dynamics(mech, q, v, method="kkt")
        res = cc.forward_dynamics(mech, q, v, method="augmented-lagrangian")
        assert np.linalg.norm(res.a - ref_res.a) <= METHOD_AGREEMENT_TOL
        force = res.generalized_constraint_force() - ref_res.generalized_constraint_force()
        assert np.linalg.norm(force) <= METHOD_AGREEMENT_TOL
        J = cc.compute_jacobian(mech, q)
        r = rng.normal(size=mech.nc)
        step = J.T @ normal.solve(J, r)
        assert np.linalg.norm(step - np.linalg.lstsq(J, r, rcond=None)[0]) <= METHOD_AGREEMENT_TOL
