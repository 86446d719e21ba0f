"""The compiled core's tree path (src/cpp/tree_solve.hpp, core_tree.hpp): kkt, the
default method, null space and reduced coordinates (their range-space form) on a long tree
with few loop rows, M^-1 by the articulated-body recursion and M never formed, against the
dense path of the same core and the numpy reference -- one evaluation (and, near a singular
J, a 40-digit solve), and whole runs of the default integrator (rk43), of rk4 with the
stage projection's mass-orthogonal velocity step, and of ALI3-P."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import MODELS
from test_validation import mp_solve_kkt

import closedchain as cc
from closedchain import compiled
from closedchain.benchmark.families import chain_urdf, leg_pair_urdf
from closedchain.dynamics.augmented_lagrangian import PenalizedSolver
from closedchain.dynamics.base import MASS_HINT, RANK_LOSS_HINT, SolverSettings, compute_terms

pytestmark = pytest.mark.skipif(not compiled.available(), reason="compiled core not built")

#: One evaluation, tree path against the dense path or the numpy reference: a
#: round-off bound, ROUNDOFF_FACTOR eps kappa relative to the largest |a| or |W lam|
#: (|lam| for lam), kappa the larger condition number of the KKT matrix and of the
#: Delassus matrix J M^-1 J^T, and never below EVAL_RTOL.
EVAL_RTOL = 1e-12
ROUNDOFF_FACTOR = 10.0
#: A fixed-step run (rk4 or ALI3-P at 1 ms), tree path against the dense path: the same
#: steps, the round-off of the solves carried along; max |q - q_dense| [rad] (measured
#: 1.5e-12 on the 30-link chain) and max |v - v_dense| relative to max |v| (3.5e-11).
FIXED_STEP_TOL = 1e-10
FIXED_STEP_VTOL = 1e-9
#: A default run (rk43: adaptive step), tree path against the dense path and the numpy
#: reference, max |q - q_ref| at the outputs [rad], and the energies relative to max |E|:
#: measured 1.3e-11 and 7e-15 (the same steps), the bound allows for a step end that
#: round-off moves (the local errors are held to rtol 1e-9, atol 1e-10).
ADAPTIVE_TOL = 1e-8
#: The recorded energy of a fixed-step run, tree path (1/2 v^T M v by Newton-Euler)
#: against the dense path (the CRBA's M), relative to max |E| [1] (measured 4e-15).
ENERGY_RTOL = 1e-12
#: The test states: q_ref moved by about STATE_SPREAD / nv per independent joint [rad]
#: (larger moves do not assemble the 100-link chain).
STATE_SPREAD = 3.0
#: ALI3-P's relative penalty on the 30-link chain (the default, 1e11, is more than its
#: P = M + alpha J^T J takes: M's smallest eigenvalue is 2e-5).
ALI3P_PENALTY = 1e6
#: Simulated time of the runs [s].
RUN_T = 0.02
#: Chains (n links, one loop: 2 rows) and leg pairs (m links per leg, 4 loops: 8 rows).
FAMILIES = {
    "chain_30": (chain_urdf, 30),
    "chain_100": (chain_urdf, 100),
    "legs_30": (leg_pair_urdf, 30),
}
METHODS = ["kkt", "augmented-lagrangian"]
#: The methods solved in the range-space form on the tree path (tree_rows.hpp's tree_range).
RANGE_METHODS = ["nullspace", "reduced"]
#: Near a singular J (the chain pinned at REACH_SLACKS short of its full length): the
#: null-space method's error against a 40-digit KKT solve of the same double M, h, J,
#: gamma, relative to max(1, |reference|), stays below NEAR_SINGULAR_FACTOR eps cond_2(J)
#: (errors that may grow like cond(J); measured at most 1.7 eps cond(J), 2.5e-12 at
#: cond(J) 6.8e3, and 1e-12 to 2e-12 at the others).
NEAR_SINGULAR_FACTOR = 20.0
#: 1 - reach of the near-singular chains: cond_2(J) 6.8e3, 8.0e4, 3.0e5 (closer pins do
#: not load without a least-squares warning).
REACH_SLACKS = (1e-6, 1e-8, 1e-9)
#: Links of the near-singular chain (nv 16: the tree path's smallest size plus a margin).
NEAR_SINGULAR_LINKS = 16


@pytest.fixture(scope="module")
def family(tmp_path_factory):
    """``get(name)``: a mechanism of :data:`FAMILIES` (or ``chain_<n>``), loaded once."""
    cache: dict[str, cc.Mechanism] = {}

    def get(name: str) -> cc.Mechanism:
        if name not in cache:
            make, n = FAMILIES.get(name, (chain_urdf, int(name.rsplit("_", 1)[-1])))
            path = tmp_path_factory.mktemp("tree") / f"{name}.urdf"
            path.write_text(make(n))
            cache[name] = cc.load(path)
        return cache[name]

    return get


def _state(mech, rng):
    """A consistent state near the reference pose (random states of long chains are hard
    to assemble): q_ref moved along the independent coordinates, then assembled."""
    q = mech.q_ref.copy()
    step = STATE_SPREAD / mech.nv
    q[mech.independent_idx_v] += step * rng.standard_normal(len(mech.independent_idx_v))
    q = cc.assemble(mech, q, fixed="independent")
    v = rng.standard_normal(mech.nv)
    return q, cc.project_velocity(mech, q, v)


def _tolerances(mech, q, v, lam_ref):
    """(rtol, scale of a) of a comparison of one evaluation at (q, v)."""
    ws = compute_terms(mech, q, v)
    M, J = ws.M, ws.J
    K = np.block([[M, J.T], [J, np.zeros((mech.nc, mech.nc))]])
    W = np.linalg.solve(M, J.T)
    kappa = max(np.linalg.cond(K), np.linalg.cond(J @ W))
    rtol = max(EVAL_RTOL, ROUNDOFF_FACTOR * np.finfo(float).eps * kappa)
    return rtol, float(np.max(np.abs(W @ lam_ref), initial=1.0))


def _assert_close(mech, q, v, a, lam, a_ref, lam_ref):
    rtol, scale = _tolerances(mech, q, v, lam_ref)
    scale = max(1.0, scale, float(np.max(np.abs(a_ref))))
    assert np.max(np.abs(a - a_ref)) <= rtol * scale
    assert np.max(np.abs(lam - lam_ref)) <= rtol * max(1.0, float(np.max(np.abs(lam_ref))))


class dense_path:
    """Context: ``mech``'s shared compiled core (simulate's) without the tree path."""

    def __init__(self, mech):
        self.core = compiled.make_core(mech)

    def __enter__(self):
        self.core.set_tree_path(False)

    def __exit__(self, *exc):
        self.core.set_tree_path(True)


@pytest.mark.parametrize("method", METHODS + RANGE_METHODS)
@pytest.mark.parametrize("name", list(FAMILIES))
def test_tree_path_matches_the_dense_path_and_numpy(family, name, method, rng):
    mech = family(name)
    fd = compiled.compiled_dynamics(mech, method)
    assert fd.core.tree_solves()
    for _ in range(3):
        q, v = _state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a, lam = fd.forward(q, v, tau)
        fd.core.set_tree_path(False)
        assert not fd.core.tree_solves()
        a_dense, lam_dense = fd.forward(q, v, tau)
        fd.core.set_tree_path(True)
        ref = cc.forward_dynamics(mech, q, v, tau, method=method, backend="numpy")
        _assert_close(mech, q, v, a, lam, a_dense, lam_dense)
        _assert_close(mech, q, v, a, lam, ref.a, ref.lam)


def test_tree_path_is_chosen_by_size(family, fourbar):
    """More than TREE_SOLVE_MIN_NV velocities and at most nv / TREE_SOLVE_NV_PER_ROW rows;
    the methods without a tree path never take it."""
    assert compiled.TREE_SOLVE_MIN_NV == 12 and compiled.TREE_SOLVE_NV_PER_ROW == 4
    assert not compiled.compiled_dynamics(fourbar, "kkt").core.tree_solves()  # nv 3
    assert not compiled.compiled_dynamics(family("chain_12"), "kkt").core.tree_solves()
    assert compiled.compiled_dynamics(family("chain_13"), "kkt").core.tree_solves()
    assert not compiled.compiled_dynamics(family("chain_30"), "schur").core.tree_solves()
    for method in RANGE_METHODS:
        assert compiled.compiled_dynamics(family("chain_30"), method).core.tree_solves()
    nfourbar = cc.load(MODELS / "nfourbar_2.urdf")  # nv 5, nc 4
    assert not compiled.compiled_dynamics(nfourbar, "augmented-lagrangian").core.tree_solves()


@pytest.mark.parametrize("name", ["chain_30", "legs_30", "chain_10", "nfourbar"])
def test_band_exclusion_agrees_with_the_band_search(family, nfourbar, name):
    """compiled._band_excluded (a clique bound, no pattern formed) never excludes a band
    the numpy backend's search would choose, and excludes the chains' and leg pairs'."""
    mech = nfourbar(10) if name == "nfourbar" else family(name)
    solver = PenalizedSolver(mech)
    excluded = compiled._band_excluded(mech)
    if excluded:
        assert not solver.banded and not solver.normal.banded
    assert excluded == (name != "nfourbar")
    banded_p, banded_n, _, _ = compiled.make_core(mech, shared=False).band_info()
    assert (banded_p, banded_n) == (solver.banded, solver.normal.banded)


def test_tree_path_kkt_checks_the_delassus_matrix(family, rng):
    """kkt on the tree path refuses a Delassus matrix above cond_max, naming it."""
    mech = family("chain_30")
    q, v = _state(mech, rng)
    fd = compiled.compiled_dynamics(mech, "kkt", SolverSettings(cond_max=1.0))
    with pytest.raises(
        cc.SingularConfigurationError,
        match=r"the Delassus matrix J M\^-1 J\^T .*; " + re.escape(RANK_LOSS_HINT),
    ):
        fd.forward(q, v, np.zeros(mech.nv))


def _singular_message(fd, q, v):
    """The message of fd.forward(q, v, 0)'s SingularConfigurationError."""
    with pytest.raises(cc.SingularConfigurationError) as info:
        fd.forward(q, v, np.zeros(len(v)))
    return str(info.value)


@pytest.mark.parametrize(
    ("method", "cond_max", "what"),
    [
        ("nullspace", 1.5, r"the constraint Jacobian J is singular .*it has lost rank"),
        ("reduced", 1.0, r"J_D .*is singular"),
        (
            "nullspace",
            5.0,
            r"the tree path's range-space matrix V_r\^T M\^-1 V_r is singular.*; "
            + re.escape(MASS_HINT),
        ),
        (
            "reduced",
            5.0,
            r"the tree path's range-space matrix V_r\^T M\^-1 V_r is singular.*; "
            + re.escape(MASS_HINT),
        ),
    ],
)
def test_range_methods_refuse_as_the_dense_path(family, rng, method, cond_max, what):
    """cond(J) above cond_max (null space) and cond(J_D) (reduced) raise the dense path's
    one-line message; G = V_r^T M^-1 V_r (the tree path's counterpart of the reduced mass
    matrix: cond 10.7 on the 30-link chain, cond(J) 2.6, cond(J_D) < 5) is named as the
    tree path's."""
    mech = family("chain_30")
    q, v = _state(mech, rng)
    fd = compiled.compiled_dynamics(mech, method, SolverSettings(cond_max=cond_max))
    assert fd.core.tree_solves()
    msg = _singular_message(fd, q, v)
    assert re.search(what, msg) and "\n" not in msg, msg
    if "range-space" in what:
        return
    with dense_path(mech):
        fd_dense = compiled.compiled_dynamics(mech, method, SolverSettings(cond_max=cond_max))
        assert _singular_message(fd_dense, q, v) == msg


def test_tree_nullspace_near_a_singular_J(tmp_path, rng):
    """The chain pinned nearly at full stretch (cond_2(J) up to 3e5): the tree path's
    null-space method agrees with a 40-digit KKT solve within eps cond(J) (times
    NEAR_SINGULAR_FACTOR) in a and J^T lam."""
    eps = np.finfo(float).eps
    for slack in REACH_SLACKS:
        path = tmp_path / f"chain_{slack:g}.urdf"
        path.write_text(chain_urdf(NEAR_SINGULAR_LINKS, reach=1.0 - slack))
        mech = cc.load(path)
        q0 = np.zeros(mech.nq)
        q0[0], q0[1:] = 0.3, -0.01  # straightens the chain's built-in bend
        q = cc.assemble(mech, q0 + 0.01 * np.sin(np.arange(mech.nq)))
        v = cc.project_velocity(mech, q, rng.standard_normal(mech.nv))
        tau = rng.standard_normal(mech.nv)
        fd = compiled.compiled_dynamics(mech, "nullspace")
        assert fd.core.tree_solves()
        a, lam = fd.forward(q, v, tau)
        ws = compute_terms(mech, q, v)
        sigma = np.linalg.svd(ws.J, compute_uv=False)
        cond_j = sigma[0] / sigma[-1]
        a_ref, lam_ref = mp_solve_kkt(ws.M, ws.h, ws.J, ws.gamma, tau)
        f_ref = ws.J.T @ lam_ref
        err_a = np.linalg.norm(a - a_ref) / max(1.0, np.linalg.norm(a_ref))
        err_f = np.linalg.norm(ws.J.T @ lam - f_ref) / max(1.0, np.linalg.norm(f_ref))
        assert max(err_a, err_f) <= NEAR_SINGULAR_FACTOR * eps * cond_j, (slack, err_a, err_f)


@pytest.mark.parametrize("name", ["chain_30", "legs_30"])
def test_default_run_on_the_tree_path(family, name, rng):
    """The default integrator (dop853-rk43: kkt's solves far from singular positions,
    stage projection with the mass-orthogonal velocity step near them) follows the dense
    path's and the numpy reference's trajectory; the recorded energy (Newton-Euler's
    1/2 v^T M v) is the CRBA's."""
    mech = family(name)
    q, v = _state(mech, rng)
    t_eval = np.linspace(0.0, RUN_T, 5)
    traj = cc.simulate(mech, q, v, RUN_T, t_eval=t_eval, backend="compiled")
    with dense_path(mech):
        dense = cc.simulate(mech, q, v, RUN_T, t_eval=t_eval, backend="compiled")
    ref = cc.simulate(mech, q, v, RUN_T, t_eval=t_eval, backend="numpy")
    assert traj.info.method == "augmented-lagrangian" and traj.info.integrator == "dop853-rk43"
    assert np.max(np.abs(traj.q - dense.q)) <= ADAPTIVE_TOL
    assert np.max(np.abs(traj.q - ref.q)) <= ADAPTIVE_TOL
    assert traj.max_constraint_residual <= 1e-9
    e_scale = max(1.0, float(np.max(np.abs(dense.energy))))
    assert np.max(np.abs(traj.energy - dense.energy)) <= ADAPTIVE_TOL * e_scale


@pytest.mark.parametrize("method", METHODS + RANGE_METHODS)
def test_fixed_step_run_on_the_tree_path(family, method, rng):
    """rk4 at a fixed step (the default method: stage projection with the mass-orthogonal
    velocity step; kkt: end-of-step projection; null space and reduced: their range-space
    solve inside the run) takes the dense path's steps."""
    mech = family("chain_30")
    q, v = _state(mech, rng)
    kw = dict(method=method, integrator="rk4", dt=1e-3, backend="compiled")
    traj = cc.simulate(mech, q, v, RUN_T, **kw)
    with dense_path(mech):
        dense = cc.simulate(mech, q, v, RUN_T, **kw)
    assert traj.info.steps == dense.info.steps
    assert np.max(np.abs(traj.q - dense.q)) <= FIXED_STEP_TOL
    assert np.max(np.abs(traj.v - dense.v)) <= FIXED_STEP_VTOL * max(1.0, np.max(np.abs(dense.v)))
    e_scale = max(1.0, float(np.max(np.abs(dense.energy))))
    assert np.max(np.abs(traj.energy - dense.energy)) <= ENERGY_RTOL * e_scale


def test_ali3p_on_the_tree_path(family, rng):
    """ALI3-P forms M where it needs it (Core::mass_matrix on the tree path). Its own
    P = M + alpha J^T J keeps a fixed penalty: ALI3P_PENALTY, which the chain's P takes."""
    mech = family("chain_30")
    q, v = _state(mech, rng)
    settings = cc.SimulationSettings(ali3p_penalty=ALI3P_PENALTY)
    kw = dict(integrator="ali3p", dt=1e-3, backend="compiled", settings=settings)
    traj = cc.simulate(mech, q, v, RUN_T, **kw)
    with dense_path(mech):
        dense = cc.simulate(mech, q, v, RUN_T, **kw)
    assert np.max(np.abs(traj.q - dense.q)) <= FIXED_STEP_TOL
