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
from closedchain.benchmark import COLUMNS, QUICK, read_rows, run_work_precision
from closedchain.benchmark.analysis import cheapest_at, pareto_front, ratio_table
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

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    assert (
        cli.main(["bench", "--quick", "--out", str(out), "--models", str(MODELS), "--no-progress"])
        == 0
    )
    return out


def test_quick_csv_schema(quick_run):
    with open(quick_run / "work_precision.csv", newline="") as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == COLUMNS
        rows = list(reader)
    families = {r["family"] for r in rows}
    assert {"closedchain", "scipy", "pinocchio-euler", "mujoco", "seed"} <= families
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


def test_quick_errors_against_reference(quick_run):
    rows = read_rows(quick_run / "work_precision.csv")

    def row(family, solver, settings):
        return next(
            r
            for r in rows
            if (r["family"], r["solver"], r["settings"]) == (family, solver, settings)
        )

    mine = row("closedchain", "kkt/DOP853/none", "tol=1e-08")
    theirs = row("scipy", "constraintDynamics/DOP853", "tol=1e-08")
    assert mine["error"] <= DOP853_1E8_ERROR_TOL
    assert theirs["error"] <= SAME_DYNAMICS_FACTOR * mine["error"]
    assert mine["error"] <= SAME_DYNAMICS_FACTOR * theirs["error"]
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
