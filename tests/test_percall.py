"""The public per-call functions on the compiled core: the same numbers as the numpy
reference, the backend argument, and results that do not change with later calls."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, MODELS

import closedchain as cc
from closedchain import compiled
from closedchain.benchmark.families import chain_urdf
from closedchain.closure import closure_error, max_declared_residual, solve_closure
from closedchain.dynamics.base import METHOD_CAPABILITIES, SolverSettings
from closedchain.exceptions import InvalidArgumentError, UnknownChoiceError
from closedchain.kinematics import random_consistent_state

needs_core = pytest.mark.skipif(not compiled.available(), reason="compiled core not built")

#: Compiled against numpy accelerations and multipliers, relative to 1 + max |a| (or
#: |lam|): the two factorize the same matrices in other orders (round-off of cond ~ 1e3).
BACKEND_PARITY_TOL = 1e-10
#: Crank offset from the 4-bar's change point (180 deg) where J has a weak direction
#: (sigma_min / sigma_max about 1e-4 < SolverSettings.weak_rcond) [rad].
WEAK_CRANK_OFFSET = 1e-4
#: Over-actuated torques, compiled against numpy: |diff| <= REDUNDANT_PARITY_ROUNDOFF eps
#: cond(J) (1 + max |tau|) (the weak-direction balance divides by J's small singular
#: values; both backends' SVDs are backward stable).
REDUNDANT_PARITY_ROUNDOFF = 100.0
#: phi, J and gamma: the same formulas evaluated in C++ and by numpy (round-off).
ROWS_TOL = 1e-13
#: Assembled configurations of the two backends [rad or m]: Gauss-Newton stops at
#: max |phi| <= AssemblySettings.tol = 1e-12 from iterates that differ by round-off, so
#: the two end points differ by about tol / sigma_min(J) along the rows.
ASSEMBLY_PARITY_TOL = 1e-9
#: Bricard's linkage with nothing held: where on its 1-dof motion Gauss-Newton ends is
#: itself sensitive to round-off (J's fifth singular value, of the order of the distance to
#: the motion, vanishes along the way): a 1e-15 change of the guess moves numpy's end point
#: by up to 7e-6 from starts 1e-3 off. The two backends agree to this [rad].
BRICARD_FREE_PARITY_TOL = 1e-4
#: Starts of the assembly parity tests: distance from an assembled state [rad or m].
ASSEMBLY_OFFSETS = (1e-3, 0.1)
#: Bound of the closure residual e at an aligned point with max |phi| <= tol (kinematics.py
#: _assemble_compiled): sqrt(3) tol, plus e's round-off [m or rad].
CLOSURE_PER_TOL = np.sqrt(3.0)
CLOSURE_ROUNDOFF = 1e-14
COMPILED_METHODS = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)


@pytest.fixture(scope="module")
def mechanisms(tmp_path_factory):
    chain = tmp_path_factory.mktemp("chain") / "chain10.urdf"
    chain.write_text(chain_urdf(10))
    paths = [MODELS / "fourbar.urdf", MODELS / "agile_eye.urdf", MODELS / "nfourbar_2.urdf"]
    out = {p.stem: cc.load(p) for p in [*paths, chain, DATA_DIR / "slider_crank.urdf"]}
    # a free-floating base: quaternion in q (nq = nv + 1)
    out["free_fourbar"] = cc.load(MODELS / "fourbar.urdf", root_joint="free")
    return out


#: Models of the inverse-dynamics and assembly parity tests: planar, a prismatic loop,
#: a long chain, a free-floating base, 3-D (spherical) loops.
PARITY_MODELS = ["fourbar", "slider_crank", "chain10", "free_fourbar", "agile_eye"]


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


def assert_rows_compiled_equal_numpy(mech, q, v):
    """phi, J and gamma of the public row functions at (q, v): compiled equals numpy."""
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
def test_rows_compiled_equal_numpy(mechanisms):
    for mech in mechanisms.values():
        q, v, _ = _state(mech, seed=1)
        assert_rows_compiled_equal_numpy(mech, q, v)


@needs_core
def test_result_keeps_the_rows_of_its_own_state(fourbar):
    """J and gamma of a compiled result are those of its own state: changing q
    afterwards, or later calls, do not change them."""
    q, v, tau = _state(fourbar)
    ref = cc.forward_dynamics(fourbar, q, v, tau, method="kkt", backend="numpy")
    res = cc.forward_dynamics(fourbar, q, v, tau, method="kkt", backend="compiled")
    q += 0.3
    cc.forward_dynamics(fourbar, *_state(fourbar, seed=5), method="kkt", backend="compiled")
    assert np.max(np.abs(res.J - ref.J)) <= ROWS_TOL
    assert np.max(np.abs(res.gamma - ref.gamma)) <= ROWS_TOL * (1 + np.max(np.abs(ref.gamma)))
    # Made without the dataclass __init__ (dynamics.base.new_frozen): every field, frozen,
    # equal to the numpy result's.
    fields = {f.name for f in dataclasses.fields(cc.ForwardDynamicsResult)}
    assert set(vars(res)) == set(vars(ref)) == fields
    assert res.method == ref.method == "kkt"
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.a = None


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


@needs_core
@pytest.mark.parametrize("name", PARITY_MODELS)
def test_inverse_dynamics_compiled_equals_numpy(mechanisms, name):
    mech = mechanisms[name]
    q, v, _ = _state(mech, seed=4)
    a_P = np.random.default_rng(5).standard_normal(mech.mobility)
    tau_passive = np.random.default_rng(6).standard_normal(mech.nv)
    for passive in (None, tau_passive):
        kw = dict(actuated="independent", tau_passive=passive)
        c = cc.inverse_dynamics(mech, q, v, a_P, backend="compiled", **kw)
        n = cc.inverse_dynamics(mech, q, v, a_P, backend="numpy", **kw)
        for field in ("tau", "a", "lam"):
            x, ref = getattr(c, field), getattr(n, field)
            assert np.max(np.abs(x - ref)) <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(ref)))
        assert np.max(np.abs(c.J - n.J)) <= ROWS_TOL
        assert np.max(np.abs(c.gamma - n.gamma)) <= ROWS_TOL * (1 + np.max(np.abs(n.gamma)))
        assert c.dynamics_residual <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(n.tau)))
        assert c.constraint_residual <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(n.a)))
        np.testing.assert_array_equal(c.actuated_idx_v, n.actuated_idx_v)
        # "auto" is the compiled core where it is built
        auto = cc.inverse_dynamics(mech, q, v, a_P, **kw)
        assert np.array_equal(auto.tau, c.tau)


@needs_core
@pytest.mark.parametrize(
    ("name", "actuated", "weak"),
    [
        ("fourbar", ["crank_joint", "rocker_joint"], False),
        ("fourbar", ["crank_joint", "coupler_joint", "rocker_joint"], False),
        ("fourbar", ["crank_joint", "rocker_joint"], True),
        ("fourbar", ["crank_joint", "coupler_joint", "rocker_joint"], True),
        ("agile_eye", ["actuator_1", "actuator_2", "actuator_3", "distal_joint_1"], False),
    ],
)
def test_inverse_dynamics_redundant_actuation_compiled_equals_numpy(
    mechanisms, name, actuated, weak
):
    """More actuators than degrees of freedom: the minimum-norm torques plus, where J has
    weak directions (the 4-bar near its change point), the spare torques that balance the
    load along them; the compiled core's equal numpy's."""
    mech = mechanisms[name]
    q, v, _ = _state(mech, seed=4)
    if weak:
        guess = [np.pi - WEAK_CRANK_OFFSET, -np.pi + WEAK_CRANK_OFFSET, np.pi]
        q, v = cc.assemble(mech, guess, fixed=["crank_joint"]), np.zeros(mech.nv)
    a_P = np.ones(mech.mobility)
    ref = cc.inverse_dynamics(mech, q, v, a_P, actuated=actuated, backend="numpy")
    res = cc.inverse_dynamics(mech, q, v, a_P, actuated=actuated, backend="compiled")
    s = np.linalg.svd(ref.J, compute_uv=False)
    assert (s[-1] < SolverSettings().weak_rcond * s[0]) == weak
    bound = REDUNDANT_PARITY_ROUNDOFF * np.finfo(float).eps * (s[0] / s[-1])
    scale = 1.0 + np.max(np.abs(ref.tau))
    assert np.max(np.abs(res.tau - ref.tau)) <= bound * scale
    assert np.max(np.abs(res.lam - ref.lam)) <= bound * (1.0 + np.max(np.abs(ref.lam)))
    assert np.max(np.abs(res.a - ref.a)) <= bound * (1.0 + np.max(np.abs(ref.a)))
    np.testing.assert_array_equal(res.actuated_idx_v, ref.actuated_idx_v)
    assert res.dynamics_residual <= bound * scale


@needs_core
@pytest.mark.parametrize("name", PARITY_MODELS)
def test_assemble_compiled_equals_numpy(mechanisms, name):
    mech = mechanisms[name]
    q, _, _ = _state(mech, seed=7)
    guess = pin.integrate(mech.model, q, 0.05 * np.random.default_rng(8).standard_normal(mech.nv))
    for fixed in ((), "independent"):
        c = cc.assemble(mech, guess, fixed=fixed, backend="compiled")
        n = cc.assemble(mech, guess, fixed=fixed, backend="numpy")
        assert np.max(np.abs(c - n)) <= ASSEMBLY_PARITY_TOL
        phi = cc.compute_phi(mech, c, backend="numpy")
        assert np.max(np.abs(phi)) <= cc.AssemblySettings().tol


@pytest.fixture(scope="module")
def assembly_mechanisms(mechanisms, load_mechanism, tmp_path_factory):
    """The shipped 3-D models, the 5-bar, one mechanism per loop type, chains of 10 and 100."""
    chain = tmp_path_factory.mktemp("chain") / "chain100.urdf"
    chain.write_text(chain_urdf(100))
    out = {n: mechanisms[n] for n in ("fourbar", "agile_eye", "chain10", "slider_crank")}
    for name in ("bricard", "spherical_chain", "fixed_branches"):
        out[name] = load_mechanism(name)
    out["five_bar"] = cc.load(DATA_DIR / "five_bar.urdf")
    out["chain100"] = cc.load(chain)
    return out


def _assemble_or_error(mech, guess, **kwargs):
    """cc.assemble's configuration, or its AssemblyError's (type, message)."""
    try:
        return cc.assemble(mech, guess, **kwargs)
    except cc.AssemblyError as exc:
        return type(exc), str(exc)


@needs_core
@pytest.mark.parametrize(
    "name",
    [
        "fourbar",
        "agile_eye",
        "five_bar",
        "bricard",
        "slider_crank",
        "spherical_chain",
        "fixed_branches",
        "chain10",
        "chain100",
    ],
)
def test_assemble_in_cxx_equals_numpy(assembly_mechanisms, name):
    """Gauss-Newton in C++ (Core.assemble_checked) and numpy's: the same configuration to
    round-off from starts near and far, holding nothing, the independent coordinates, a
    joint by name or a velocity index; every declared row closed; where C++ gives up, the
    same error."""
    mech = assembly_mechanisms[name]
    rng = np.random.default_rng(11)
    settings = cc.AssemblySettings()
    joint = mech.model.names[mech.model.njoints - 1]
    closed_in_cxx = 0
    for _ in range(3):
        q, _ = random_consistent_state(mech, rng)
        for offset in ASSEMBLY_OFFSETS:
            guess = pin.integrate(mech.model, q, offset * rng.standard_normal(mech.nv))
            for fixed in ((), "independent", [joint], [0]):
                c = _assemble_or_error(mech, guess, fixed=fixed, backend="compiled")
                n = _assemble_or_error(mech, guess, fixed=fixed, backend="numpy")
                if isinstance(n, tuple):
                    assert c == n
                    continue
                tol = BRICARD_FREE_PARITY_TOL if (name, fixed) == ("bricard", ()) else None
                assert np.max(np.abs(c - n)) <= (tol or ASSEMBLY_PARITY_TOL)
                assert max_declared_residual(mech, c[None]) <= settings.tol
                closed_in_cxx += _in_cxx(mech, guess, fixed, settings) is not None
    assert closed_in_cxx >= 12  # most starts close in C++: the path under test ran


def _in_cxx(mech, guess, fixed, settings):
    """Core.assemble_checked's result (None: Gauss-Newton failed or misaligned)."""
    held = mech.coordinate_indices(fixed)
    free = np.setdiff1d(np.arange(mech.nv), held).astype(np.int32)
    return compiled.declared_core(mech).assemble_checked(
        guess,
        free,
        settings.tol,
        settings.max_iter,
        settings.max_halvings,
        settings.fallback_rcond,
        settings.contraction,
    )


@needs_core
@pytest.mark.parametrize("name", ["fourbar", "spherical_chain", "slider_crank", "fixed_branches"])
def test_assembly_in_cxx_bounds_the_closure_residual(assembly_mechanisms, name):
    """Revolute, spherical, prismatic and fixed loops: where C++ closes max |phi| <= tol on
    an aligned point, the closure residual e is at most sqrt(3) tol (the argument in
    kinematics._assemble_compiled), so assemble need not evaluate e."""
    mech = assembly_mechanisms[name]
    rng = np.random.default_rng(12)
    settings = cc.AssemblySettings()
    closed = 0
    for _ in range(10):
        q, _ = random_consistent_state(mech, rng)
        guess = pin.integrate(mech.model, q, 0.1 * rng.standard_normal(mech.nv))
        c = _in_cxx(mech, guess, (), settings)
        if c is None:
            continue
        closed += 1
        e = closure_error(mech.model, mech.data, mech.declared, c)
        assert e <= CLOSURE_PER_TOL * settings.tol + CLOSURE_ROUNDOFF
    assert closed >= 8


@needs_core
def test_assembly_in_cxx_checks_e_under_a_tight_closure_tol(assembly_mechanisms):
    """closure_tol below kinematics.CLOSURE_PER_PHI tol: e is evaluated on the C++ result,
    which is returned where it passes (the numpy path's result to round-off)."""
    mech = assembly_mechanisms["fixed_branches"]
    q, _ = random_consistent_state(mech, np.random.default_rng(13))
    guess = pin.integrate(mech.model, q, np.full(mech.nv, 1e-3))
    settings = cc.AssemblySettings(tol=1e-10, closure_tol=2e-10)
    c = cc.assemble(mech, guess, settings=settings, backend="compiled")
    n = cc.assemble(mech, guess, settings=settings, backend="numpy")
    assert np.max(np.abs(c - n)) <= ASSEMBLY_PARITY_TOL
    assert closure_error(mech.model, mech.data, mech.declared, c) <= settings.closure_tol


@needs_core
def test_spurious_closure_in_cxx_falls_back_to_least_squares():
    """The welded 4-bar 2.5 rad off on the crank: Gauss-Newton ends on the 180-degree flip;
    C++ reports it (None) as numpy's solve_closure does (its message), and assemble closes
    by the least-squares solve on both backends, to the same configuration."""
    mech = cc.load(DATA_DIR / "fourbar_fixed_loop.urdf")
    q0 = mech.q_ref.copy()
    q0[0] += 2.5
    settings = cc.AssemblySettings()
    with pytest.raises(cc.AssemblyError, match="spurious closure of loop.s. C"):
        solve_closure(mech.model, mech.data, mech.declared, q0, np.arange(mech.nv), settings)
    assert _in_cxx(mech, q0, (), settings) is None
    c = cc.assemble(mech, q0, backend="compiled")
    n = cc.assemble(mech, q0, backend="numpy")
    assert np.max(np.abs(c - n)) <= ASSEMBLY_PARITY_TOL
    assert closure_error(mech.model, mech.data, mech.declared, c) <= settings.closure_tol


@needs_core
def test_assembly_errors_are_the_same_on_both_backends(mechanisms):
    """Arguments, an impossible closure, too few iterations: the numpy path's messages."""
    fourbar, free = mechanisms["fourbar"], mechanisms["free_fourbar"]
    off_sphere = free.q_ref.copy()
    off_sphere[3:7] *= 1.01  # the base's quaternion
    cases = [
        (fourbar, (np.zeros(2),), {}, "q_guess has shape"),
        (fourbar, (np.array([0.0, np.nan, 0.0]),), {}, "q_guess contains non-finite"),
        (fourbar, (fourbar.q_ref,), dict(fixed=["crank"]), "unknown joint 'crank'"),
        (fourbar, (fourbar.q_ref,), dict(fixed=[7]), "velocity index 7 out of range"),
        (fourbar, (np.zeros(2),), dict(fixed=["crank"]), "q_guess has shape"),
        (free, (off_sphere,), {}, "has norm 1.01"),
        (fourbar, (np.zeros(3),), dict(fixed=["rocker_joint"]), "did not converge.*holding 1"),
        (
            fourbar,
            (np.array([1.0, 2.0, -1.0]),),
            dict(settings=cc.AssemblySettings(max_iter=1)),
            "did not converge",
        ),
    ]
    for mech, args, kwargs, match in cases:
        c = _message(cc.assemble, mech, *args, backend="compiled", **kwargs)
        n = _message(cc.assemble, mech, *args, backend="numpy", **kwargs)
        assert c == n
        assert re.search(match, c[1])


def _message(fn, *args, **kwargs) -> tuple[type, str]:
    with pytest.raises(cc.ClosedChainError) as info:
        fn(*args, **kwargs)
    return type(info.value), str(info.value)


@needs_core
def test_argument_errors_are_the_same_on_both_backends(mechanisms):
    """The compiled entry points check shapes, finiteness and normalization in C++ with
    the numpy path's exception classes and messages."""
    free = mechanisms["free_fourbar"]
    q, v, tau = _state(free)
    nan = v.copy()
    nan[1] = np.nan
    off_sphere = q.copy()
    off_sphere[3:7] *= 1.01  # the base's quaternion
    cases = [
        ("q has shape", (q[:-1], v, tau)),
        ("q has shape", (q[:, None], v, tau)),
        ("v contains non-finite values", (q, nan, tau)),
        ("tau contains non-finite values", (q, v, nan)),
        ("tau has shape", (q, v, tau[:3])),
        ("has norm 1.01", (off_sphere, v, tau)),
        ("overflowed to non-finite", (q, 1e200 * np.ones(free.nv), tau)),
    ]
    for match, args in cases:
        c = _message(cc.forward_dynamics, free, *args, method="kkt", backend="compiled")
        n = _message(cc.forward_dynamics, free, *args, method="kkt", backend="numpy")
        assert c == n
        assert match in c[1]
    for fn, args in ((cc.compute_phi, (off_sphere,)), (cc.compute_gamma, (q, nan))):
        assert _message(fn, free, *args, backend="compiled") == _message(
            fn, free, *args, backend="numpy"
        )


@needs_core
def test_compiled_calls_take_what_numpy_takes(mechanisms):
    """Lists, integer and strided arrays: converted as numpy.asarray(x, dtype=float)."""
    mech = mechanisms["chain10"]
    q, v, tau = _state(mech)
    ref = cc.forward_dynamics(mech, q, v, tau, method="kkt", backend="compiled")
    strided = np.zeros((mech.nv, 2))
    strided[:, 0] = v
    for args in ((list(q), list(v), list(tau)), (q, strided[:, 0], np.zeros(mech.nv, int))):
        res = cc.forward_dynamics(mech, *args, method="kkt", backend="compiled")
        exp = cc.forward_dynamics(mech, *args, method="kkt", backend="numpy")
        assert np.max(np.abs(res.a - exp.a)) <= BACKEND_PARITY_TOL * (1 + np.max(np.abs(exp.a)))
    backwards = v[::-1].copy()[::-1]  # a negative stride
    res = cc.forward_dynamics(mech, q, backwards, None, method="kkt", backend="compiled")
    assert np.array_equal(res.a, cc.forward_dynamics(mech, q, v, method="kkt").a)
    assert not np.array_equal(ref.a, res.a)  # tau mattered
