"""Mechanisms without loops (open chains) simulate, plot, animate and benchmark.

The reference is independent of closedchain: Pinocchio's articulated-body
algorithm (``pin.aba``) integrated by scipy's DOP853 at tight tolerances.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from conftest import MODELS
from scipy.integrate import solve_ivp

import closedchain as cc
from closedchain import cli

#: Tolerance of the reference integration (scipy DOP853, rtol = atol).
REFERENCE_TOL = 1e-12
#: Largest |q - q_ref| [rad] at the end of 0.5 s for DOP853 at rtol 1e-10 (measured 2e-10).
ADAPTIVE_TOL = 1e-8
#: Fixed-step integrators, their order, and the largest |q - q_ref| [rad] at 0.5 s with
#: dt = 0.5 ms (measured: rk4 9.9e-9, ali3p 3.9e-5).
FIXED_STEP = {"rk4": (4, 1e-7), "ali3p": (2, 1e-4)}
#: Share of the theoretical error ratio 2^p between dt and dt / 2 that must be observed.
ORDER_SHARE = 0.7
T_FINAL = 0.5


@pytest.fixture(scope="module")
def pendulum3() -> cc.Mechanism:
    return cc.load(MODELS / "pendulum3.urdf")


def _aba_reference(mech: cc.Mechanism, q0, v0, t_final: float) -> np.ndarray:
    model = mech.model
    data = model.createData()
    nq = model.nq

    def rhs(_t, x):
        q, v = x[:nq], x[nq:]
        return np.concatenate([v, pin.aba(model, data, q, v, np.zeros(model.nv))])

    sol = solve_ivp(
        rhs,
        (0.0, t_final),
        np.concatenate([q0, v0]),
        method="DOP853",
        rtol=REFERENCE_TOL,
        atol=REFERENCE_TOL,
    )
    return sol.y[:nq, -1]


@pytest.mark.parametrize("backend", ("numpy", "compiled"))
def test_open_chain_adaptive_run_is_pinocchio_aba(pendulum3, backend):
    q0, v0 = np.array([0.3, 0.2, 0.1]), np.array([1.0, 0.0, 0.0])
    traj = cc.simulate(
        pendulum3, q0, v0, T_FINAL, integrator="DOP853", backend=backend, rtol=1e-10, atol=1e-12
    )
    assert traj.lam.shape == (len(traj.t), 0)
    assert traj.max_constraint_residual == 0.0
    q_ref = _aba_reference(pendulum3, q0, v0, T_FINAL)
    assert np.linalg.norm(traj.q[-1] - q_ref, np.inf) < ADAPTIVE_TOL


@pytest.mark.parametrize("backend", ("numpy", "compiled"))
@pytest.mark.parametrize("integrator", sorted(FIXED_STEP))
def test_open_chain_fixed_steps_converge_to_pinocchio_aba(pendulum3, backend, integrator):
    """The error at 0.5 ms is within the bound and falls by about 2^p from 1 ms."""
    order, bound = FIXED_STEP[integrator]
    q0, v0 = np.array([0.3, 0.2, 0.1]), np.array([1.0, 0.0, 0.0])
    q_ref = _aba_reference(pendulum3, q0, v0, T_FINAL)
    errors = []
    for dt in (1e-3, 5e-4):
        traj = cc.simulate(
            pendulum3, q0, v0, T_FINAL, integrator=integrator, dt=dt, backend=backend
        )
        errors.append(np.linalg.norm(traj.q[-1] - q_ref, np.inf))
    assert errors[1] < bound
    assert errors[0] / errors[1] > ORDER_SHARE * 2**order


@pytest.mark.parametrize("stabilization", ("partitioning", "projection", "baumgarte"))
def test_open_chain_takes_every_stabilization(pendulum3, stabilization):
    q0, v0 = np.array([0.3, 0.2, 0.1]), np.zeros(3)
    traj = cc.simulate(
        pendulum3, q0, v0, T_FINAL, integrator="DOP853", stabilization=stabilization,
        backend="numpy", rtol=1e-10, atol=1e-12,
    )  # fmt: skip
    q_ref = _aba_reference(pendulum3, q0, v0, T_FINAL)
    assert np.linalg.norm(traj.q[-1] - q_ref, np.inf) < ADAPTIVE_TOL


def test_open_chain_every_method_is_aba(pendulum3, rng):
    q, v, tau = rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3), rng.uniform(-1, 1, 3)
    a_ref = pin.aba(pendulum3.model, pendulum3.model.createData(), q, v, tau)
    for method in cc.METHODS:
        res = cc.forward_dynamics(pendulum3, q, v, tau, method=method)
        assert res.lam.shape == (0,)
        np.testing.assert_allclose(res.a, a_ref, rtol=0, atol=1e-11, err_msg=method)


def test_ur5_simulates_animates_and_plots_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "ur5.npz"
    status = cli.main(["simulate", "erd:ur5", "--t-final", "0.1", "--out", str(out)])
    assert status == 0, capsys.readouterr().err
    traj = cc.Trajectory.load(out)
    assert traj.q.shape[1] == 6 and traj.lam.shape[1] == 0
    assert cli.main(["plot", str(out), "-o", str(tmp_path / "ur5.png")]) == 0
    html = tmp_path / "ur5.html"
    assert cli.main(["animate", "erd:ur5", "--t-final", "0.1", "-o", str(html)]) == 0
    assert html.stat().st_size > 100_000


def test_open_chain_benchmark_scenario_runs(tmp_path):
    from closedchain.benchmark import QUICK, read_rows, run_work_precision

    run_work_precision(tmp_path, settings=QUICK, scenarios=["pendulum3-passive"], models_dir=MODELS)
    rows = read_rows(tmp_path / "work_precision.csv")
    ours = [r for r in rows if r["family"] == "closedchain"]
    assert ours and all(r["status"] == "ok" for r in ours)
    # The tightest closedchain run agrees with the reference (itself checked by a second
    # method) to better than 1e-6 rad over the quick horizon.
    assert min(r["error"] for r in ours) < 1e-6
