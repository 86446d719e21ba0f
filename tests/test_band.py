"""The compiled core's band path (many loops in a chain: the N-four-bar) against the
dense compiled path and the numpy backend.

For N >= 5 the N-four-bar's penalized mass matrix M + alpha J^T J has half bandwidth 2
and, from N = 10, its normal equations J J^T half bandwidth 3, whatever N; the numpy
backend detects it (closedchain.dynamics.augmented_lagrangian.PenalizedSolver,
NormalSolver) and so does the compiled core (Core.set_band). The band path must
compute what the dense one computes: per evaluation to round-off, and the same
trajectories (projections, regularity checks) over a few steps.
"""

from __future__ import annotations

import nfourbar_reference as ref
import numpy as np
import pytest

import closedchain as cc
from closedchain import compiled
from closedchain.dynamics.augmented_lagrangian import PenalizedSolver
from closedchain.dynamics.base import compute_terms

#: Per evaluation, |band - reference| <= EVAL_RTOL * scale, scale = max(1, max |a|,
#: max |M^-1 J^T lam|) (a = M^-1 (tau - h - J^T lam) cancels terms of that size), as
#: tests/test_compiled.py; lam against max(1, max |lam|).
EVAL_RTOL = 1e-12
#: lam's bar: max(EVAL_RTOL, LAM_ROUNDOFF eps cond(J M^-1 J^T)), the forward error of a
#: backward-stable solve with that condition number (a constant of 10 for the sizes here).
LAM_ROUNDOFF = 10.0
#: Fixed-step trajectories of the band and dense cores over FIXED_T (round-off
#: accumulates over the steps) [rad, rad/s].
FIXED_STEP_TOL = 1e-9
FIXED_T = 0.05
#: Through a flat position (J loses rank) round-off is amplified: the two paths agree to
#: the integration error (as SINGULAR_PASSAGE_TOL of tests/test_compiled.py).
SINGULAR_PASSAGE_TOL = 1e-6


def _dense_core(mech, method="augmented-lagrangian"):
    fd = compiled.compiled_dynamics(mech, method)
    fd.core.set_band(np.arange(mech.nv, dtype=np.int32), False, False)
    assert fd.core.band_info()[:2] == (False, False)
    return fd


def _parallelogram(mech, theta, rate):
    """Every crank at angle theta and rate ``rate``, couplers horizontal (consistent)."""
    is_crank = np.array([n.startswith("crank") for n in mech.coordinate_names])
    return np.where(is_crank, theta, -theta), np.where(is_crank, rate, -rate)


def _states(mech, rng, k):
    """k random consistent states (none at N = 40: no random assembly is found there),
    parallelogram states at 1.2 rad and near a flat position (cranks 1e-3 rad from
    horizontal), and the benchmark's start."""
    states = [cc.random_consistent_state(mech, rng) for _ in range(k)]
    states += [_parallelogram(mech, 1.2, -0.7), _parallelogram(mech, 1e-3, -1.0)]
    states.append(ref.initial_state(mech))
    return states


@pytest.mark.parametrize("n", [5, 10])
def test_band_structure_is_the_numpy_backends(nfourbar, n):
    """The core finds the bandwidths the numpy backend finds, and uses the band where
    the numpy backend does."""
    mech = nfourbar(n)
    solver = PenalizedSolver(mech)
    core = compiled.make_core(mech, shared=False)
    banded_p, banded_n, b_p, b_n = core.band_info()
    assert (b_p, b_n) == (solver.bandwidth, solver.normal.bandwidth)
    assert (banded_p, banded_n) == (solver.banded, solver.normal.banded)
    assert b_p == 2  # independent of N
    assert banded_p and banded_n == (n >= 10)


def _numpy(mech, q, v, tau):
    res = cc.forward_dynamics(mech, q, v, tau, method="augmented-lagrangian")
    return res.a, res.lam


def _check_forward(mech, rng, k):
    band = compiled.compiled_dynamics(mech, "augmented-lagrangian")
    assert band.core.band_info()[0]
    dense = _dense_core(mech)
    for q, v in _states(mech, rng, k):
        tau = rng.standard_normal(mech.nv)
        a, lam = band.forward(q, v, tau)
        ws = compute_terms(mech, q, v)
        for ref_a, ref_lam in (
            dense.forward(q, v, tau),
            _numpy(mech, q, v, tau),
        ):
            term = np.linalg.solve(ws.M, ws.J.T @ ref_lam)
            scale = max(1.0, float(np.max(np.abs(ref_a))), float(np.max(np.abs(term))))
            assert np.max(np.abs(a - ref_a)) <= EVAL_RTOL * scale
            lam_scale = max(1.0, float(np.max(np.abs(ref_lam))))
            # lam solves (J M^-1 J^T) lam = ...: two correct factorizations differ by
            # up to about eps cond(J M^-1 J^T) relative (N = 40: cond ~1e5 at random states).
            schur = ws.J @ np.linalg.solve(ws.M, ws.J.T)
            lam_rtol = max(EVAL_RTOL, LAM_ROUNDOFF * np.finfo(float).eps * np.linalg.cond(schur))
            assert np.max(np.abs(lam - ref_lam)) <= lam_rtol * lam_scale


def test_band_forward_matches_dense_and_numpy(nfourbar, rng):
    """augmented-lagrangian per evaluation, N = 10: band core = dense core = numpy."""
    _check_forward(nfourbar(10), rng, 4)


@pytest.mark.slow
def test_band_forward_matches_dense_and_numpy_n40(nfourbar, rng):
    """The same at N = 40 (81 coordinates, 80 kept rows)."""
    _check_forward(nfourbar(40), rng, 0)


def _run(mech, monkeypatch, band: bool, **kw):
    """simulate on the band core (band) or on a dense core."""
    mech.__dict__.pop("_compiled_cores", None)
    try:
        with monkeypatch.context() as m:
            if not band:
                m.setattr(
                    compiled,
                    "set_band",
                    lambda core, mech: core.set_band(
                        np.arange(mech.nv, dtype=np.int32), False, False
                    ),
                )
            return cc.simulate(mech, backend="compiled", **kw)
    finally:
        mech.__dict__.pop("_compiled_cores", None)


def _runs(mech, monkeypatch, **kw):
    return [_run(mech, monkeypatch, band, **kw) for band in (True, False)]


@pytest.mark.parametrize(
    "method, stabilization",
    [("augmented-lagrangian", "stage-projection"), ("kkt", "projection")],
)
def test_band_trajectory_matches_dense(nfourbar, monkeypatch, method, stabilization):
    """rk4 steps with projections (band normal equations) and, for kkt, the regularity
    check (cond(J) certified below singular_cond on the band): the same steps."""
    mech = nfourbar(10)
    q0, v0 = ref.initial_state(mech)
    a, b = _runs(
        mech,
        monkeypatch,
        q0=q0,
        v0=v0,
        t_final=FIXED_T,
        method=method,
        integrator="rk4",
        stabilization=stabilization,
    )
    for key in ("q", "v", "a"):
        assert np.max(np.abs(getattr(a, key) - getattr(b, key))) <= FIXED_STEP_TOL
    assert np.max(np.abs(a.energy - b.energy)) <= FIXED_STEP_TOL


def test_band_passes_a_flat_position_as_the_dense_path(nfourbar, monkeypatch):
    """The default configuration through the flat position at t = 0.73 s, band and dense;
    kkt stops there with the same error (the band's certified condition check hands
    over to the exact cond(J) near the rank loss)."""
    mech = nfourbar(10)
    q0, v0 = ref.initial_state(mech)
    t_eval = np.linspace(0.0, 0.9, 10)
    a, b = _runs(mech, monkeypatch, q0=q0, v0=v0, t_final=0.9, t_eval=t_eval)
    assert a.info.method == "augmented-lagrangian"
    assert np.min(a.q[:, 0]) < 0.0  # through theta = 0
    assert np.max(np.abs(a.q - b.q)) <= SINGULAR_PASSAGE_TOL
    assert np.max(a.constraint_residual) <= 1e-12
    errors = []
    for band in (True, False):
        with pytest.raises(cc.SingularConfigurationError, match="condition number") as info:
            _run(mech, monkeypatch, band, q0=q0, v0=v0, t_final=0.9, method="kkt")
        errors.append(info.value)
    assert errors[0].t == errors[1].t
