"""The public per-call functions on the compiled core: the same numbers as the numpy
reference, the backend argument, and results that do not change with later calls."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain import compiled
from closedchain.benchmark.families import chain_urdf
from closedchain.dynamics.base import METHOD_CAPABILITIES
from closedchain.exceptions import InvalidArgumentError, UnknownChoiceError
from closedchain.kinematics import random_consistent_state

needs_core = pytest.mark.skipif(not compiled.available(), reason="compiled core not built")

#: Compiled against numpy accelerations and multipliers, relative to 1 + max |a| (or
#: |lam|): the two factorize the same matrices in other orders (round-off of cond ~ 1e3).
BACKEND_PARITY_TOL = 1e-10
#: phi, J and gamma: the same formulas evaluated in C++ and by numpy (round-off).
ROWS_TOL = 1e-13
COMPILED_METHODS = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)


@pytest.fixture(scope="module")
def mechanisms(tmp_path_factory):
    chain = tmp_path_factory.mktemp("chain") / "chain10.urdf"
    chain.write_text(chain_urdf(10))
    paths = [MODELS / "fourbar.urdf", MODELS / "agile_eye.urdf", MODELS / "nfourbar_2.urdf"]
    return {p.stem: cc.load(p) for p in [*paths, chain]}


def _state(mech, seed=0):
    rng = np.random.default_rng(seed)
    q, v = random_consistent_state(mech, rng)
    return q, v, rng.standard_normal(mech.nv)


@needs_core
@pytest.mark.parametrize("method", COMPILED_METHODS)
@pytest.mark.parametrize("name", ["fourbar", "agile_eye", "nfourbar_2", "chain10"])
def test_forward_dynamics_compiled_equals_numpy(mechanisms, name, method):
    mech = mechanisms[name]
    q, v, tau = _state(mech)
    c = cc.forward_dynamics(mech, q, v, tau, method=method, backend="compiled")
    n = cc.forward_dynamics(mech, q, v, tau, method=method, backend="numpy")
    assert np.max(np.abs(c.a - n.a)) <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(n.a)))
    assert np.max(np.abs(c.lam - n.lam)) <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(n.lam)))
    assert np.max(np.abs(c.J - n.J)) <= ROWS_TOL
    assert np.max(np.abs(c.gamma - n.gamma)) <= ROWS_TOL * (1 + np.max(np.abs(n.gamma)))
    # "auto" is the compiled core where it is built
    a = cc.forward_dynamics(mech, q, v, tau, method=method)
    assert np.array_equal(a.a, c.a)


@needs_core
def test_rows_compiled_equal_numpy(mechanisms):
    for mech in mechanisms.values():
        q, v, _ = _state(mech, seed=1)
        for fn, args in (
            (cc.compute_phi, (q,)),
            (cc.compute_jacobian, (q,)),
            (cc.compute_gamma, (q, v)),
        ):
            c = fn(mech, *args, backend="compiled")
            n = fn(mech, *args, backend="numpy")
            assert c.shape == n.shape
            assert np.max(np.abs(c - n), initial=0.0) <= ROWS_TOL * (1 + np.max(np.abs(n)))


@needs_core
def test_result_keeps_the_rows_of_its_own_state(fourbar):
    """J and gamma of a compiled result are evaluated on first access from a copy of the
    state: changing q afterwards, or later calls, do not change them."""
    q, v, tau = _state(fourbar)
    ref = cc.forward_dynamics(fourbar, q, v, tau, method="kkt", backend="numpy")
    res = cc.forward_dynamics(fourbar, q, v, tau, method="kkt", backend="compiled")
    q += 0.3
    cc.forward_dynamics(fourbar, *_state(fourbar, seed=5), method="kkt", backend="compiled")
    assert np.max(np.abs(res.J - ref.J)) <= ROWS_TOL
    assert np.max(np.abs(res.gamma - ref.gamma)) <= ROWS_TOL * (1 + np.max(np.abs(ref.gamma)))


@needs_core
def test_compiled_backend_refuses_a_method_it_does_not_have(fourbar):
    q, v, tau = _state(fourbar)
    with pytest.raises(InvalidArgumentError, match="method 'pinocchio' has no compiled version"):
        cc.forward_dynamics(fourbar, q, v, tau, method="pinocchio", backend="compiled")
    # auto falls back to numpy for it
    res = cc.forward_dynamics(fourbar, q, v, tau, method="pinocchio")
    assert res.method == "pinocchio"


def test_unknown_backend_lists_the_valid_ones(fourbar):
    q, v, tau = _state(fourbar)
    with pytest.raises(UnknownChoiceError, match="auto.*compiled.*numpy"):
        cc.forward_dynamics(fourbar, q, v, tau, backend="gpu")
    with pytest.raises(UnknownChoiceError, match="auto.*compiled.*numpy"):
        cc.compute_phi(fourbar, q, backend="gpu")


@needs_core
def test_bad_state_is_refused_on_both_backends(fourbar):
    q, v, tau = _state(fourbar)
    for backend in ("compiled", "numpy"):
        with pytest.raises(cc.ClosedChainError, match="q has shape"):
            cc.forward_dynamics(fourbar, q[:-1], v, tau, backend=backend)
        bad = v.copy()
        bad[0] = np.nan
        with pytest.raises(cc.ClosedChainError, match="v contains non-finite values"):
            cc.forward_dynamics(fourbar, q, bad, tau, backend=backend)


@needs_core
def test_project_velocity_compiled_equals_numpy(mechanisms):
    """The same projection with J of the declared rows from C++ or numpy."""
    for mech in mechanisms.values():
        q, _, _ = _state(mech, seed=2)
        v = np.random.default_rng(3).standard_normal(mech.nv)
        for fixed in ((), "independent"):
            c = cc.project_velocity(mech, q, v, fixed=fixed, backend="compiled")
            n = cc.project_velocity(mech, q, v, fixed=fixed, backend="numpy")
            assert np.max(np.abs(c - n)) <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(n)))
