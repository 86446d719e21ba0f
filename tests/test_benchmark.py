"""Tests of closedchain.benchmark: the quick run's CSV schema and reference agreement, the
analysis helpers on hand-made rows, error paths, and the Dask path on a LocalCluster.

No timing assertions: CPU seconds are only checked to be positive numbers.
"""

from __future__ import annotations

import csv
import math

import pytest
from conftest import MODELS

from closedchain import cli
from closedchain import compiled as cc_compiled
from closedchain.benchmark import COLUMNS, QUICK, SCENARIOS, read_rows, run_work_precision
from closedchain.benchmark.analysis import cheapest_at, cpu_at, pareto_front, ratio_table
from closedchain.exceptions import ClosedChainError, UnknownChoiceError

#: The quick run's reference (kkt DOP853 1e-13) and its confirmation (nullspace, DOP853,
#: partitioning) agree to this on the 4-bar over 2 s [rad] (measured 1.3e-12).
REFERENCE_AGREEMENT_TOL = 1e-10
#: A closedchain DOP853 run at tol 1e-8 is within this of the reference [rad] (measured 2.5e-8).
DOP853_1E8_ERROR_TOL = 1e-6
#: The thirty-line scipy script computes the same dynamics: at equal tolerance its error
#: equals closedchain's to this factor (measured: equal to 3 digits).
SAME_DYNAMICS_FACTOR = 2.0
#: MuJoCo's soft loop closure keeps its error above this on the 4-bar [rad] (measured 4e-3).
MUJOCO_SOFT_ERROR_MIN = 1e-4
#: numpy and compiled DOP853 take the same steps: their errors agree to this (relative).
SAME_BACKEND_ERROR_RTOL = 1e-3
#: The exact N-four-bar reference against tests/nfourbar_reference.py [rad] (measured 1.6e-14),
#: and its mpmath confirmation against the double-precision one (measured 8.9e-15).
EXACT_REFERENCE_TOL = 1e-12
#: Every scenario's start is assembled to round-off [m or -].
ASSEMBLY_TOL = 1e-10

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    cache = tmp_path_factory.mktemp("bench-cache")
    args = ["bench", "--quick", "--out", str(out), "--models", str(MODELS), "--no-progress"]
    assert cli.main([*args, "--cache", str(cache)]) == 0
    assert len(list(cache.glob("*.npz"))) == 2  # the reference and its confirmation
    return out


def test_quick_csv_schema(quick_run):
    with open(quick_run / "work_precision.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == COLUMNS
        rows = list(reader)
    families = {r["family"] for r in rows}
    assert {"closedchain", "scipy", "pinocchio-euler", "mujoco", "lesson"} <= families
    assert {r["status"] for r in rows} <= {"ok", "drift", "diverged", "raised"}
    for r in read_rows(quick_run / "work_precision.csv"):
        if r["status"] == "ok":
            assert r["cpu_s"] > 0
            assert math.isfinite(r["error"]) and math.isfinite(r["residual"])
    assert (quick_run / "wp_fourbar-passive.png").stat().st_size > 0
    assert "closedchain / peer CPU" in (quick_run / "ratios.md").read_text()


def test_quick_reference_agreement(quick_run):
    ref = list(csv.DictReader(open(quick_run / "reference.csv", newline="")))
    assert [r["scenario"] for r in ref] == ["fourbar-passive"]
    assert float(ref[0]["agreement"]) <= REFERENCE_AGREEMENT_TOL
    assert "confirmed by nullspace/DOP853/partitioning" in ref[0]["reference"]


def test_quick_runs_both_backends(quick_run):
    rows = read_rows(quick_run / "work_precision.csv")
    backends = {r["backend"] for r in rows if r["family"] == "closedchain"}
    assert "numpy" in backends
    if cc_compiled.available():
        assert "compiled" in backends


def test_quick_errors_against_reference(quick_run):
    rows = read_rows(quick_run / "work_precision.csv")

    def row(family, solver, settings, backend):
        return next(
            r
            for r in rows
            if (r["family"], r["solver"], r["settings"], r["backend"])
            == (family, solver, settings, backend)
        )

    mine = row("closedchain", "kkt/DOP853/none", "tol=1e-08", "numpy")
    theirs = row("scipy", "constraintDynamics/DOP853", "tol=1e-08", "python")
    assert mine["error"] <= DOP853_1E8_ERROR_TOL
    assert theirs["error"] <= SAME_DYNAMICS_FACTOR * mine["error"]
    assert mine["error"] <= SAME_DYNAMICS_FACTOR * theirs["error"]
    if cc_compiled.available():
        # The compiled DOP853 computes the same steps as the numpy one.
        compiled = row("closedchain", "kkt/DOP853/none", "tol=1e-08", "compiled")
        assert abs(compiled["error"] - mine["error"]) <= SAME_BACKEND_ERROR_RTOL * mine["error"]
    for r in rows:
        if r["family"] == "mujoco" and r["status"] == "ok":
            assert r["error"] >= MUJOCO_SOFT_ERROR_MIN


def _row(family, cpu, err, status="ok"):
    return dict(
        family=family, scenario="s", solver=family, settings="", cpu_s=cpu, error=err, status=status
    )


def test_pareto_front_and_ratios():
    rows = [
        _row("closedchain", 1.0, 1e-4),
        _row("closedchain", 2.0, 1e-8),
        _row("closedchain", 3.0, 1e-6),  # dominated
        _row("peer", 0.5, 1e-4),
        _row("peer", 10.0, 1e-7),
        _row("peer", 0.1, 1e-9, "raised"),
    ]
    front = pareto_front([r for r in rows if r["family"] == "closedchain"])
    assert [(r["cpu_s"], r["error"]) for r in front] == [(1.0, 1e-4), (2.0, 1e-8)]
    assert cheapest_at(rows, 1e-9) is None  # the raised run does not count
    table = {e["target"]: e for e in ratio_table(rows, {"s": 1e-12})}
    assert table[1e-3]["ratio"] == pytest.approx(1.0 / 0.5)
    assert table[1e-6]["ratio"] == pytest.approx(2.0 / 10.0)
    assert "cannot reach" in table[1e-9]["note"]
    table = {e["target"]: e for e in ratio_table(rows, {"s": 1e-7})}
    assert "reference confirmed only to 1.0e-07" in table[1e-9]["note"]


def test_cpu_at_interpolates_the_front_log_log():
    # A front on the power law cpu = error^-1/4 (a fourth-order method): log-log
    # interpolation between two of its runs is exact.
    rows = [_row("closedchain", e**-0.25, e) for e in (1e-2, 1e-4, 1e-8)]
    rows.append(_row("closedchain", 50.0, 1e-3))  # dominated: not on the front
    assert cpu_at(rows, 1e-6) == pytest.approx((1e-6) ** -0.25, rel=1e-12)
    assert cpu_at(rows, 1e-1) == pytest.approx((1e-2) ** -0.25)  # no extrapolation
    assert math.isnan(cpu_at(rows, 1e-9))
    table = {e["target"]: e for e in ratio_table(rows + [_row("peer", 1.0, 1e-7)], {"s": 0.0})}
    assert table[1e-3]["interpolated"] == pytest.approx((1e-3) ** -0.25)
    assert table[1e-3]["ratio"] == pytest.approx((1e-4) ** -0.25)  # the grid's cheapest run


def test_steps_run_only_where_they_divide_the_output_spacing():
    from closedchain.benchmark.runner import BenchSettings, make_jobs

    settings = BenchSettings(repeats=1)
    jobs = make_jobs(
        settings,
        ["fourbar-passive", "nfourbar2-singular"],
        str(MODELS),
        mujoco_available=False,
        references=False,
    )

    def steps(scenario, family, solver=None):
        return {
            j["kwargs"]["dt"]
            for j in jobs
            if j["scenario"] == scenario
            and j["family"] == family
            and (solver is None or j["solver"] == solver)
            and "dt" in j["kwargs"]
        }

    rk4 = "augmented-lagrangian/rk4/stage-projection"
    assert max(steps("nfourbar2-singular", "closedchain", rk4)) == 5e-2
    assert {5e-2, 2.5e-2, 1.25e-2} <= steps("nfourbar2-singular", "lesson")
    assert max(steps("fourbar-passive", "closedchain", "kkt/rk4/stage-projection")) == 1e-2
    assert max(steps("fourbar-passive", "lesson")) == 1e-2
    # The settings label is part of a row's key: 1.25e-2 and 1e-2 must not share one.
    keys = [(j["scenario"], j["family"], j["solver"], j["backend"], j["settings"]) for j in jobs]
    assert len(keys) == len(set(keys))


def test_unknown_scenario_raises(tmp_path):
    with pytest.raises(UnknownChoiceError, match="scenario.*fourbar-passive"):
        run_work_precision(tmp_path, settings=QUICK, scenarios=["nope"], models_dir=MODELS)


def test_cli_bad_workers(tmp_path, capsys):
    assert cli.main(["bench", "--quick", "--out", str(tmp_path), "--workers", "0"]) == 2
    assert "--workers must be at least 1" in capsys.readouterr().err


def test_dask_local_cluster_runs_jobs(tmp_path):
    distributed = pytest.importorskip("distributed")
    from closedchain.benchmark.runner import execute, make_jobs

    jobs = make_jobs(QUICK, ["fourbar-passive"], str(MODELS), mujoco_available=False)
    jobs = [j for j in jobs if j["family"] in ("reference", "scipy")][:3]
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = execute(jobs, scheduler=client)
    local = execute(jobs)
    assert [r["status"] for r in remote] == ["ok"] * len(jobs)
    for a, b in zip(remote, local, strict=True):
        assert abs(a["q"] - b["q"]).max() == 0.0  # same deterministic computation


def test_dask_threaded_workers_run_one_batch_of_jobs_each():
    """On an in-process cluster of 2 threads: 2 tasks (one batch of jobs per thread), the
    scenario's model loaded once, the results those of the local run."""
    distributed = pytest.importorskip("distributed")
    from closedchain.benchmark import scenarios
    from closedchain.benchmark.runner import execute, make_jobs, worker_chunks

    jobs = make_jobs(QUICK, ["fourbar-passive"], str(MODELS), mujoco_available=False)
    jobs = [j for j in jobs if j["family"] in ("closedchain", "scipy")][:5]
    assert worker_chunks(list(range(5)), 2) == [[0, 2, 4], [1, 3]]
    assert worker_chunks(list(range(1)), 4) == [[0]]
    scenarios._load.cache_clear()
    ticks = []
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = execute(jobs, scheduler=client, progress=ticks.append)
    assert sorted(ticks) == [2, 3]  # one report per task, its share of the jobs
    assert scenarios._load.cache_info().misses == 1
    local = execute(jobs)
    assert [r["status"] for r in remote] == ["ok"] * len(jobs)
    for a, b in zip(remote, local, strict=True):
        assert (a["solver"], a["settings"]) == (b["solver"], b["settings"])
        assert abs(a["q"] - b["q"]).max() == 0.0  # same deterministic computation


def test_scheduler_without_dask_message(monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "distributed":
            raise ImportError(name)
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    from closedchain.benchmark.runner import execute

    with pytest.raises(ClosedChainError, match=r"pip install 'closedchain\[dask\]'"):
        execute([{}], scheduler="tcp://127.0.0.1:1")


# -- stability map, per-evaluation cost and scaling helpers ---------------------------

#: closedchain's stabilized rk4 keeps every declared row at round-off [m] (measured 2e-14).
STABLE_RESIDUAL_TOL = 1e-12
#: On the change-point case at dt = 1e-2 Pinocchio's Euler loop with Baumgarte drifts
#: (measured max declared row 2.9e-2), far above the "drift" threshold.
EULER_PEER_DRIFT_MIN = 1e-3
CHANGE_POINT_CASE = "fourbar change point (open branch) 1 s"


def test_stability_job_classifies_runs():
    from closedchain.benchmark.stability import DRIFT_ROW_TOL, PEER, run_stability_job

    def job(config, step):
        return run_stability_job(
            dict(case=CHANGE_POINT_CASE, config=config, step=step, models_dir=str(MODELS))
        )

    ok = job("kkt/rk4/projection", 1e-2)  # compiled when the core is built
    assert ok["status"] == "ok" and ok["residual"] <= STABLE_RESIDUAL_TOL
    peer = job(PEER, 1e-2)
    assert peer["status"] == "drift" and peer["residual"] >= EULER_PEER_DRIFT_MIN > DRIFT_ROW_TOL
    raised = job("kkt/rk4/projection", 1e-3)  # a fine step sees the change point
    assert raised["status"] == "raised"
    assert "losing rank" in raised["message"]


#: Largest declared row of closedchain's singular-robust configuration on the N-four-bar
#: over 20 s at 0.1 s steps [-] (measured 6e-14).
NFOURBAR_STAGE_RESIDUAL_TOL = 1e-12


def test_nfourbar_map_case_separates_the_peer():
    # Over 20 s (a dozen flat positions) Pinocchio's Euler loop reaches a non-finite state
    # at 0.1 s steps; the augmented Lagrangian with rk4 and stage projection stays closed.
    from closedchain.benchmark.stability import CASES, PEER, run_stability_job

    case = next(c for c in CASES if c.startswith("nfourbar"))
    assert CASES[case].t_final == 20.0

    def job(config):
        return run_stability_job(dict(case=case, config=config, step=0.1, models_dir=str(MODELS)))

    peer = job(PEER)
    assert peer["status"] == "diverged" and "non-finite" in peer["message"]
    mine = job("augmented-lagrangian/rk4/stage-projection")
    assert mine["status"] == "ok" and mine["residual"] <= NFOURBAR_STAGE_RESIDUAL_TOL


def test_stability_jobs_are_independent():
    # A partitioning run that stops on the N-four-bar left state in the mechanism's shared
    # compiled core that let a later kkt + rk4 + stage-projection run pass the flat position
    # it stops at on a new core: each job starts from a new core.
    from closedchain.benchmark.stability import CASES, run_stability_job

    case = next(c for c in CASES if c.startswith("nfourbar"))

    def job(config, step):
        return run_stability_job(dict(case=case, config=config, step=step, models_dir=str(MODELS)))

    first = job("kkt/rk4/stage-projection", 1e-2)
    job("kkt/euler/partitioning", 2e-3)
    again = job("kkt/rk4/stage-projection", 1e-2)
    assert (again["status"], again["message"]) == (first["status"], first["message"])


def test_largest_ok_step_needs_every_smaller_step_ok():
    from closedchain.benchmark.stability import best_fixed, largest_ok_step, stability_summary

    rows = [
        dict(case="c", config="a", step=s, status=st)
        for s, st in ((1e-3, "ok"), (1e-2, "ok"), (1e-1, "diverged"))
    ]
    rows += [
        dict(case="c", config="b", step=s, status=st)
        for s, st in ((1e-3, "ok"), (1e-2, "drift"), (1e-1, "ok"))
    ]
    assert largest_ok_step(rows, "c", "a") == 1e-2
    assert largest_ok_step(rows, "c", "b") == 1e-3
    assert largest_ok_step(rows, "c", "missing") == 0.0
    assert best_fixed(rows, "c") == ("a", 1e-2)
    assert "| c | a | 0.01 |" in stability_summary(rows)


def test_growth_exponent_of_a_power_law():
    from closedchain.benchmark.scaling import growth_exponents

    rows = [dict(n=n, method="m", us=3.0 * n**2) for n in (1, 2, 5, 10)]
    assert growth_exponents(rows)["m"] == pytest.approx(2.0, rel=1e-12)


#: Closure of the generated families at their neutral configuration [m] (round-off).
FAMILY_CLOSURE_TOL = 1e-12
#: Parallelogram: the closed form (opposite bars parallel) against the assembly [rad].
PARALLELOGRAM_TOL = 1e-9


def _loop_gap(mech, q) -> float:
    """Largest distance between the two frames of a loop at q (Pinocchio placements)."""
    import numpy as np
    import pinocchio as pin

    data = mech.model.createData()
    pin.framesForwardKinematics(mech.model, data, q)
    gaps = [0.0]
    for blk, _sl in mech.constraints.per_loop():
        gaps.append(
            float(np.linalg.norm(data.oMf[blk.fid_p].translation - data.oMf[blk.fid_s].translation))
        )
    return max(gaps)


@pytest.mark.parametrize("m", (3, 7))
def test_leg_pair_is_closed_with_the_mobility_of_its_parallelograms(tmp_path, m):
    """Grubler count: per leg 1 roll + m pitch + 2 bars, minus 2 planar conditions per
    parallelogram: mobility 2 (m - 1); closed at q = 0 (every link hanging)."""
    import numpy as np

    import closedchain as cc
    from closedchain.benchmark.families import leg_pair_urdf

    path = tmp_path / "legs.urdf"
    path.write_text(leg_pair_urdf(m))
    mech = cc.load(path)
    assert mech.nv == 2 * (1 + m + 2)
    assert mech.nv - mech.nc == 2 * (m - 1)
    assert _loop_gap(mech, np.zeros(mech.nq)) <= FAMILY_CLOSURE_TOL


def test_leg_pair_parallelogram_keeps_the_shank_parallel(tmp_path):
    """Turning the thigh by theta, the parallelogram turns link 2 by -theta relative to
    it (link 2 keeps the hip's orientation): the closed form of a parallelogram."""
    import numpy as np

    import closedchain as cc
    from closedchain.benchmark.families import leg_pair_urdf

    path = tmp_path / "legs.urdf"
    path.write_text(leg_pair_urdf(4))
    mech = cc.load(path)
    names = list(mech.coordinate_names)
    theta = 0.4
    guess = np.zeros(mech.nq)
    guess[names.index("left_001_pitch")] = theta
    q = cc.assemble(mech, guess, fixed=["left_001_pitch"])
    assert q[names.index("left_002_pitch")] == pytest.approx(-theta, abs=PARALLELOGRAM_TOL)
    assert _loop_gap(mech, q) <= FAMILY_CLOSURE_TOL


@pytest.mark.parametrize(
    ("factory", "bad", "match"),
    [("chain_urdf", 2, "n must be >= 3"), ("leg_pair_urdf", 2, "m must be >= 3")],
)
def test_families_refuse_sizes_too_small(factory, bad, match):
    from closedchain.benchmark import families

    with pytest.raises(ValueError, match=match):
        getattr(families, factory)(bad)


@pytest.mark.parametrize("reach", [0.0, 1.5])
def test_families_chain_refuses_a_reach_out_of_range(reach):
    from closedchain.benchmark.families import chain_urdf

    with pytest.raises(ValueError, match=r"reach must be in \(0, 1\] .*got"):
        chain_urdf(5, reach=reach)


def test_scaling_run_writes_every_series(tmp_path):
    """A small scaling run: one row per size and call, a table per family, the chart."""
    import numpy as np

    from closedchain.benchmark.scaling import IN_SIMULATE, SCALING_METHODS, run_scaling

    rows = run_scaling(tmp_path, ["chain"], repeats=1, sizes={"chain": (5, 8)})
    labels = {(r["method"], r["backend"]) for r in rows}
    assert {(m, "numpy") for m in SCALING_METHODS} <= labels
    assert ("pin.constraintDynamics", "C++") in labels
    if cc_compiled.available():
        assert {(m, b) for m in SCALING_METHODS for b in ("compiled", IN_SIMULATE)} <= labels
    assert len(rows) == 2 * len(labels)
    kkt = [r for r in rows if r["method"] == "kkt"]
    assert all(np.isfinite(r["us"]) and r["us"] > 0 for r in kkt)
    text = (tmp_path / "scaling.md").read_text()
    assert "### chain" in text and "n = 5 (nv 5, nc 2)" in text and "n = 8 (nv 8" in text
    assert (tmp_path / "scaling.png").stat().st_size > 0
    assert (tmp_path / "scaling.csv").read_text().startswith("family,n,nv,nc,method")


@pytest.mark.skipif(not cc_compiled.available(), reason="compiled core not built")
@pytest.mark.parametrize(
    ("family", "n", "method"),
    [("chain", 300, None), ("chain", 1000, None), ("leg-pair", 30, "kkt")],
)
def test_scaling_start_runs_the_timed_span(tmp_path, family, n, method):
    """The scaling page's timed state runs the longest in-simulate span (rk4 at
    SIMULATE_DT): with unit independent rates the 300-link chain left its manifold at
    t = 2 ms and the 30-link leg pair reached a flat (singular) position at 0.15 s; at
    1 ms the 1000-link chain left it at 0.017 s. Each was reported refused."""
    from closedchain import load, simulate
    from closedchain.benchmark.families import FAMILIES
    from closedchain.benchmark.scaling import EXTRA_STEPS, SIMULATE_DT, SIMULATE_STEPS, _start
    from closedchain.dynamics.base import DEFAULT_METHOD

    path = tmp_path / f"{family}{n}.urdf"
    path.write_text(FAMILIES[family].urdf(n))
    mech = load(path)
    q, v = _start(mech, FAMILIES[family].start)
    steps = SIMULATE_STEPS + EXTRA_STEPS[1]
    traj = simulate(
        mech,
        q,
        v,
        steps * SIMULATE_DT,
        method=method or DEFAULT_METHOD,
        integrator="rk4",
        dt=SIMULATE_DT,
        backend="compiled",
    )
    assert traj.info.steps == steps
    assert traj.max_constraint_residual <= 1e-9


def test_bench_scaling_refuses_an_unknown_family(capsys):
    with pytest.raises(SystemExit):
        cli.main(["bench", "--scaling", "tripod"])
    assert "invalid choice: 'tripod'" in capsys.readouterr().err


def test_evaluation_calls_cover_every_method_and_exact_pinocchio(fourbar):
    import closedchain as cc
    from closedchain.benchmark.evaluation import evaluation_calls
    from closedchain.dynamics.base import METHOD_CAPABILITIES

    calls = evaluation_calls(fourbar)
    labels = [c[0] for c in calls]
    assert {f"method {m}" for m in cc.METHODS} <= set(labels)
    assert "pin.constraintDynamics (cheapest exact)" in labels
    if cc_compiled.available():
        compiled = {c[0] for c in calls if c[1] == "compiled"}
        assert compiled == {f"method {m}" for m, c in METHOD_CAPABILITIES.items() if c.compiled}
        for _label, _backend, fn, _note in calls:
            fn()  # every timed call runs


# -- scenarios, references and the reference cache -----------------------------------


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_starts_assembled(name):
    import numpy as np

    import closedchain as cc
    from closedchain.benchmark.scenarios import (
        initial_state,
        load_scenario_mechanism,
        torque_function,
    )

    sc = SCENARIOS[name]
    mech = load_scenario_mechanism(str(MODELS), sc)
    q0, v0 = initial_state(mech, sc)
    assert np.max(np.abs(cc.compute_phi(mech, q0)), initial=0.0) <= ASSEMBLY_TOL
    assert np.max(np.abs(cc.compute_jacobian(mech, q0) @ v0), initial=0.0) <= ASSEMBLY_TOL
    tau = torque_function(mech, sc)
    assert (tau is None) == sc.passive
    if tau is not None:
        assert tau(0.0, q0, v0).shape == (mech.nv,)


def test_exact_nfourbar_reference():
    import nfourbar_reference as ref
    import numpy as np

    from closedchain.benchmark.references import EXACT_REFERENCES
    from closedchain.benchmark.scenarios import initial_state, load_scenario_mechanism

    sc = SCENARIOS["nfourbar2-singular"]
    mech = load_scenario_mechanism(str(MODELS), sc)
    q0, v0 = initial_state(mech, sc)
    t_grid = np.linspace(0.0, 1.0, 11)  # through the first flat position (t ~ 0.3 s)
    double, mp = EXACT_REFERENCES[sc.exact]
    q = double(mech, q0, v0, t_grid)
    expected = np.array([ref.crank_angle(2, t) for t in t_grid])
    assert np.max(np.abs(q[:, 0] - expected)) <= EXACT_REFERENCE_TOL
    assert np.max(np.abs(q + q[:, [0]] * np.where(q0 > 0, -1.0, 1.0))) == 0.0
    assert np.max(np.abs(mp(mech, q0, v0, t_grid[:4]) - q[:4])) <= EXACT_REFERENCE_TOL


def test_exact_reference_refuses_another_model(fourbar):
    import numpy as np

    from closedchain.benchmark.references import nfourbar_parallelogram

    with pytest.raises(ClosedChainError, match="does not describe this model"):
        nfourbar_parallelogram(fourbar, fourbar.q_ref, np.zeros(3), np.linspace(0, 1, 3))


def test_reference_cache_round_trip(tmp_path):
    import numpy as np

    from closedchain.benchmark.references import cache_key, cache_load, cache_store
    from closedchain.benchmark.runner import make_jobs

    jobs = make_jobs(QUICK, ["fourbar-passive"], str(MODELS), mujoco_available=False, repeats=())
    assert [j["family"] for j in jobs] == ["reference", "confirmation"]
    sc = SCENARIOS["fourbar-passive"]
    keys = {cache_key(j, sc) for j in jobs}
    assert len(keys) == 2
    key = cache_key(jobs[0], sc)
    assert cache_load(tmp_path, key) is None
    res = dict(q=np.arange(6.0).reshape(2, 3), v=np.ones((2, 3)), cpu_s=1.5, status="ok")
    cache_store(tmp_path, key, res)
    hit = cache_load(tmp_path, key)
    assert hit["cpu_s"] == 1.5 and np.array_equal(hit["q"], res["q"])
    cache_store(tmp_path, "failed", dict(res, status="raised"))
    assert cache_load(tmp_path, "failed") is None
    assert cache_load(None, key) is None


def test_near_front_keeps_cheap_accurate_runs():
    from closedchain.benchmark.runner import near_front

    rows = [
        dict(_row("closedchain", 1.0, 1e-4), backend="b"),
        dict(_row("closedchain", 1.5, 1e-6), backend="b", settings="x"),
        dict(_row("closedchain", 10.0, 1e-5), backend="b", settings="far"),
        dict(_row("closedchain", 0.1, 1e-9, "raised"), backend="b", settings="bad"),
    ]
    keys = near_front(rows, 2.0)
    assert ("s", "closedchain", "closedchain", "b", "") in keys
    assert ("s", "closedchain", "closedchain", "b", "x") in keys
    assert ("s", "closedchain", "closedchain", "b", "far") not in keys
    assert ("s", "closedchain", "closedchain", "b", "bad") not in keys


def test_mujoco_configuration_round_trip():
    import numpy as np

    pytest.importorskip("mujoco")
    import closedchain as cc
    from closedchain.benchmark.peers import pinocchio_configuration
    from closedchain.export.mjcf import mujoco_state

    mech = cc.load("erd:ur5", loops=MODELS / "ur5_crank.urdf")
    assert mech.nq != mech.nv  # the crank is a continuous joint: (cos, sin)
    q = mech.q_ref
    qpos, _ = mujoco_state(mech, q, np.zeros(mech.nv))
    assert np.max(np.abs(pinocchio_configuration(mech, qpos) - q)) <= 1e-15


def test_bench_extras_rejects_bad_arguments(tmp_path):
    import subprocess
    import sys

    from conftest import ROOT

    for args, message in (
        (["--workers", "0"], "--workers must be at least 1, got 0"),
        (["--number", "0"], "--number must be at least 1, got 0"),
        (["--parts", "nope"], "invalid choice: 'nope'"),
    ):
        res = subprocess.run(
            [sys.executable, str(ROOT / "scripts" / "bench_extras.py"), "--out", str(tmp_path)]
            + args,
            capture_output=True,
            text=True,
        )
        assert res.returncode == 2
        assert message in res.stderr


def test_the_whole_bench_runs_in_quick_mode(tmp_path, capsys):
    """Every scenario under the quick settings (issue 32: the driven scenarios lost their
    confirmed reference, and their charts raised): exit 0, every reference confirmed,
    every chart written."""
    out = tmp_path / "bench"
    args = ["bench", "--quick", "--scenarios", *SCENARIOS, "--out", str(out)]
    args += ["--models", str(MODELS), "--no-progress", "--no-cache"]
    assert cli.main(args) == 0, capsys.readouterr().err
    ref = {r["scenario"]: r for r in csv.DictReader(open(out / "reference.csv", newline=""))}
    assert set(ref) == set(SCENARIOS)
    for sc, r in ref.items():
        assert float(r["agreement"]) <= REFERENCE_AGREEMENT_TOL, sc
        assert (out / f"wp_{sc}.png").stat().st_size > 0
    rows = read_rows(out / "work_precision.csv")
    assert {r["scenario"] for r in rows} == set(SCENARIOS)
    assert all(math.isfinite(r["error"]) for r in rows if r["status"] == "ok")


def test_a_scenario_without_a_confirmed_reference_is_reported(tmp_path, monkeypatch):
    """A failed confirmation leaves the scenario's rows without an error, says so in the
    CSVs and on the chart, and the rest of the run completes."""
    from closedchain.benchmark import runner

    configurations = runner.reference_configurations

    def failing(settings, scenario=None, **kw):
        out = configurations(settings, scenario, **kw)
        out[1] = dict(out[1], kwargs=dict(out[1]["kwargs"], tol=-1.0))  # refused: exit 2
        return out

    monkeypatch.setattr(runner, "reference_configurations", failing)
    rows, checks = run_work_precision(
        tmp_path, settings=QUICK, scenarios=["pendulum3-passive"], models_dir=MODELS
    )
    (check,) = checks
    assert check.agreement == math.inf and "FAILED" in check.reference
    ours = [r for r in rows if r["family"] == "closedchain"]
    assert ours and all(r["status"] == "ok" for r in ours)
    assert all(r["message"] == "no confirmed reference: error not measured" for r in rows)
    assert all(math.isnan(r["error"]) for r in rows)
    assert (tmp_path / "wp_pendulum3-passive.png").stat().st_size > 0
    assert "FAILED" in (tmp_path / "reference.csv").read_text()
