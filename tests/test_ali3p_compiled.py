"""ALI3-P in the compiled core (src/cpp/ali3p.hpp) against the numpy reference
(closedchain/simulate/ali3p.py).

Both run the same algorithm step for step (predictor, Newton on the trapezoidal
index-3 augmented-Lagrangian equations with the multiplier update, the stopping rules,
the mass-orthogonal projections, the singular-zone splits), so they differ by what the
Newton iterations leave: they stop once a correction of the step's displacement is
below ``ali3p_tol`` (1e-10) *and* 1e-4 of it or no longer halving, i.e. at the round-off
floor, and the two backends round differently (band or dense Cholesky of
M + alpha J^T J, Pinocchio's passes or the Core's tree pass).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess

import nfourbar_reference as ref
import numpy as np
import pytest

import closedchain as cc
from closedchain import compiled
from closedchain.simulate import COMPILED_INTEGRATORS, INTEGRATORS, SimulationError

pytestmark = pytest.mark.skipif(not compiled.available(), reason="compiled core not built")

#: Compiled against numpy, max abs difference of q [rad] at the end of a run: the
#: Newton tolerance ali3p_tol (a correction left in the displacement is left in q).
ALI3P_Q_TOL = 1e-10
#: ... and of v [rad/s]: a displacement error e is a velocity error 2 e / h.
ALI3P_V_TOL_PER_DT = 2e-10
#: Step [s] and horizon [s] of the comparisons; the N-four-bar's first flat position
#: (all rods horizontal) is at t = 0.73 s.
DT, T_SHORT, T_FLAT = 1e-3, 0.2, 0.8


def _fourbar_state(mech):
    q = cc.assemble(mech, np.radians((10.0, -65.0, -104.0)), fixed=["crank_joint"])
    return q, np.zeros(mech.nv)


def _agile_eye_state(mech):
    q = mech.q_ref.copy()
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = (0.3, -0.2, 0.1)
    return q, cc.project_velocity(mech, q, v, fixed="independent")


def _both(mech, q0, v0, t_final, **kw):
    a = cc.simulate(mech, q0, v0, t_final, integrator="ali3p", **kw)
    b = cc.simulate(mech, q0, v0, t_final, integrator="ali3p", backend="numpy", **kw)
    assert a.info.backend == "compiled" and b.info.backend == "numpy"
    return a, b


def _agree(a, b, dt):
    assert a.t.shape == b.t.shape and np.array_equal(a.t, b.t)
    assert np.max(np.abs(a.q - b.q)) <= ALI3P_Q_TOL
    assert np.max(np.abs(a.v - b.v)) <= ALI3P_V_TOL_PER_DT / dt
    assert a.info.extra["singular_splits"] == b.info.extra["singular_splits"]
    assert a.info.extra["ali3p_alpha"] == pytest.approx(b.info.extra["ali3p_alpha"], rel=1e-12)


def test_registered_as_compiled():
    spec = COMPILED_INTEGRATORS["ali3p"]
    assert spec.backend == "compiled" and spec.kind == "fixed"
    assert spec.stabilizations == INTEGRATORS["ali3p"].stabilizations == ("mass-orthogonal",)
    assert spec.singular_robust and spec.method_capabilities == ("singular_robust",)


def test_fourbar_matches_numpy(fourbar):
    q0, v0 = _fourbar_state(fourbar)
    a, b = _both(fourbar, q0, v0, T_SHORT, dt=DT)
    _agree(a, b, DT)
    assert a.info.steps == b.info.steps == round(T_SHORT / DT)
    assert a.max_constraint_residual <= 1e-12


def test_agile_eye_matches_numpy(agile_eye):
    q0, v0 = _agile_eye_state(agile_eye)
    a, b = _both(agile_eye, q0, v0, T_SHORT, dt=DT)
    # (The multipliers are not compared: lam = 4 / h^2 (mu + alpha phi) carries the
    # round-off of phi times 4 alpha / h^2, 3.6e14 here; measured 0.47 apart of 0.95.)
    _agree(a, b, DT)


@pytest.mark.parametrize("n", [2, 5], ids=["dense", "band"])
def test_nfourbar_across_a_flat_position_matches_numpy(nfourbar, n):
    """N = 2 (dense P) and N = 5 (band Cholesky of P) through the first flat position
    (t = 0.73 s), against the numpy loop and the quadrature reference."""
    mech = nfourbar(n)
    if n == 5:
        assert compiled.make_core(mech).band_info()[0], "N = 5 must take the band path"
    q0, v0 = ref.initial_state(mech)
    t_eval = np.linspace(0.0, T_FLAT, 81)
    a, b = _both(mech, q0, v0, T_FLAT, dt=DT, t_eval=t_eval)
    _agree(a, b, DT)
    assert np.min(a.q[:, 0]) < 0.0 < np.max(a.q[:, 0])  # through theta = 0
    # second order at 1 ms: the crank angle within 1e-5 rad of the reduced motion
    assert abs(a.q[-1, 0] - ref.crank_angle(n, T_FLAT)) <= 1e-5


def test_callable_tau_and_progress(fourbar):
    q0, v0 = _fourbar_state(fourbar)
    seen: list[float] = []

    def tau(t, q, v):
        return np.array([0.5 * np.sin(3 * t) - 0.1 * v[0], 0.0, 0.0])

    a = cc.simulate(
        fourbar, q0, v0, T_SHORT, integrator="ali3p", dt=DT, tau=tau, progress=seen.append
    )
    b = cc.simulate(fourbar, q0, v0, T_SHORT, integrator="ali3p", dt=DT, tau=tau, backend="numpy")
    assert a.info.backend == "compiled"
    assert len(seen) == a.info.steps and seen[-1] == pytest.approx(T_SHORT)
    _agree(a, b, DT)


def test_non_convergence_names_the_time(fourbar):
    """One Newton iteration cannot meet ali3p_tol: SimulationError at the first step."""
    q0, v0 = _fourbar_state(fourbar)
    settings = cc.SimulationSettings(ali3p_max_iter=1)
    with pytest.raises(SimulationError, match=r"did not converge at t = 0.001 s") as exc:
        cc.simulate(fourbar, q0, v0, 0.1, integrator="ali3p", dt=DT, settings=settings)
    assert exc.value.t == pytest.approx(DT)
    assert exc.value.trajectory is not None  # the motion up to the stop (numpy re-run)


def test_errors_cross_the_boundary(fourbar):
    q0, v0 = _fourbar_state(fourbar)

    def bad(t, q, v):
        return np.array([np.nan if t > 0.01 else 0.0, 0.0, 0.0])

    with pytest.raises(SimulationError, match=r"tau\(t, q, v\) returned .* at t = ") as exc:
        cc.simulate(fourbar, q0, v0, 0.1, integrator="ali3p", dt=DT, tau=bad, backend="compiled")
    assert exc.value.t > 0.01

    def raising(t, q, v):
        raise RuntimeError("controller failed")

    with pytest.raises(RuntimeError, match="controller failed"):
        cc.simulate(
            fourbar, q0, v0, 0.1, integrator="ali3p", dt=DT, tau=raising, backend="compiled"
        )

    def stop(t):
        if t > 0.02:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cc.simulate(fourbar, q0, v0, 0.1, integrator="ali3p", dt=DT, progress=stop)


def test_ctrl_c_interrupts_a_long_run(fourbar):
    """SIGINT from another process stops a long compiled ALI3-P run (checked every 64
    steps, as the other compiled loops; see test_compiled.test_ctrl_c_interrupts_a_long_run)."""
    q0, v0 = _fourbar_state(fourbar)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    killer = subprocess.Popen(["sh", "-c", f"sleep 0.5; kill -INT {os.getpid()}"])
    reached = [0.0]

    def progress(t):
        reached[0] = t

    try:
        with pytest.raises(KeyboardInterrupt):
            # 2e7 steps: hours if not interrupted
            cc.simulate(
                fourbar,
                q0,
                v0,
                2e4,
                integrator="ali3p",
                dt=1e-3,
                t_eval=np.array([2e4]),
                progress=progress,
            )
            killer.wait()
            import time

            time.sleep(1.0)
    finally:
        killer.wait()
        signal.signal(signal.SIGINT, previous)
    assert 0.0 < reached[0] < 2e4
    assert not math.isnan(reached[0])
