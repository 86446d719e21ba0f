"""Accuracy against speed: closedchain beside its peers, in the same run, as tidy rows.

``run_work_precision`` runs every configuration of closedchain (from the
integrator registry: a newly registered backend is benchmarked without edits)
and of the peers (:mod:`.peers`) on each scenario (:mod:`.scenarios`), measures
the error against a reference confirmed by a second configuration, and writes

* ``work_precision.csv``: one tidy row per configuration (:data:`COLUMNS`);
* ``reference.csv``: per scenario, the agreement of reference and confirmation;
* ``ratios.md``: closedchain CPU / peer CPU at error 1e-3, 1e-6, 1e-9;
* ``jobs.csv``: the wall seconds of every job (where the run's time went);
* ``wp_<scenario>.png``: the work-precision charts.

Plots are drawn from the rows by :mod:`.plots`; nothing there measures.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable
from pathlib import Path

from .._io import MAX_CSV_BYTES, atomic_write, check_input_file
from .analysis import TARGET_ERRORS, pareto_front, ratio_markdown, ratio_table
from .runner import (
    COLUMNS,
    QUICK,
    QUICK_SCENARIOS,
    BenchSettings,
    ReferenceCheck,
    execute,
    make_jobs,
    measure,
    near_front,
)
from .scenarios import SCENARIOS, Scenario, get_scenario

logger = logging.getLogger(__name__)

__all__ = [
    "COLUMNS",
    "QUICK",
    "SCENARIOS",
    "TARGET_ERRORS",
    "BenchSettings",
    "ReferenceCheck",
    "Scenario",
    "pareto_front",
    "ratio_table",
    "read_rows",
    "run_work_precision",
    "write_rows",
]


def _mujoco_available() -> bool:
    try:
        import mujoco  # noqa: F401
    except ImportError:
        logger.warning(
            "MuJoCo is not installed: the mujoco peer is left out "
            "(pip install 'closedchain[bench]')"
        )
        return False
    return True


def write_rows(rows: list[dict], path: str | Path, columns: tuple[str, ...] = COLUMNS) -> None:
    """Write tidy rows as CSV with ``columns`` in order."""
    with atomic_write(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def read_rows(path: str | Path) -> list[dict]:
    """Read a CSV written by :func:`write_rows` (numbers back to float)."""
    check_input_file(path, limit=MAX_CSV_BYTES, what="benchmark table")
    out = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            for k in ("cpu_s", "error", "residual", "energy_drift"):
                if k in r:
                    r[k] = float(r[k]) if r[k] not in ("", "nan") else math.nan
            out.append(r)
    return out


def _run_references(jobs: list[dict], cache_dir, execute_kw: dict) -> list[dict]:
    """Reference jobs, from the on-disk cache where a result of the same configuration,
    scenario, models and code is stored; the others are run and stored."""
    from .references import cache_key, cache_load, cache_store

    results: list = [None] * len(jobs)
    keys = [cache_key(j, SCENARIOS[j["scenario"]]) for j in jobs]
    todo = []
    for i, (job, key) in enumerate(zip(jobs, keys, strict=True)):
        hit = cache_load(cache_dir, key)
        if hit is not None:
            logger.info("reference %s %s: from the cache", job["scenario"], job["family"])
            results[i] = dict(job, **hit, wall_s=0.0)
            execute_kw["progress"](1)
        else:
            todo.append(i)
    for i, res in zip(todo, execute([jobs[i] for i in todo], **execute_kw), strict=True):
        results[i] = res
        cache_store(cache_dir, keys[i], res)
    return results


def run_work_precision(
    out_dir: str | Path,
    *,
    settings: BenchSettings | None = None,
    scenarios: list[str] | None = None,
    models_dir: str | Path = "models",
    workers: int = 1,
    scheduler=None,
    progress: Callable[[int, int], None] | None = None,
    cache_dir: str | Path | None = None,
) -> tuple[list[dict], list[ReferenceCheck]]:
    """Run the work-precision benchmark and write its CSVs, ratio table and charts.

    Three passes, each a batch of independent jobs: the references (from ``cache_dir``
    when computed before by the same code), every configuration once, then the
    remaining repeats of the configurations near a front (:func:`.runner.near_front`).

    Args:
        out_dir: output directory (created).
        settings: grids and repeats; default :class:`BenchSettings`.
        scenarios: scenario names; default all (``QUICK_SCENARIOS`` when quick).
        models_dir: directory holding the scenarios' URDF files.
        workers: local processes.
        scheduler: Dask scheduler address (or Client): jobs go to that cluster.
        progress: ``progress(done, total)`` after each job.
        cache_dir: directory of cached references (None: no cache).

    Returns:
        The tidy rows and the reference checks.
    """
    settings = settings or BenchSettings()
    if scenarios is None:
        scenarios = list(QUICK_SCENARIOS if settings.quick else SCENARIOS)
    for sc in scenarios:
        get_scenario(sc)
    models_dir = str(Path(models_dir).resolve())
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mujoco = _mujoco_available()
    ref_jobs = [
        j for j in make_jobs(settings, scenarios, models_dir, mujoco_available=mujoco, repeats=())
    ]
    first = make_jobs(
        settings, scenarios, models_dir, mujoco_available=mujoco, repeats=(0,), references=False
    )
    # Estimated total: every configuration repeated (the last pass usually runs fewer).
    total = [len(ref_jobs) + len(first) * settings.repeats]
    done = [0]

    def tick(n: int) -> None:
        done[0] += n
        if progress:
            progress(done[0], max(total[0], done[0]))

    kw = dict(workers=workers, scheduler=scheduler, progress=tick)
    results = _run_references(ref_jobs, cache_dir, kw)
    results += execute(first, **kw)
    if settings.repeats > 1:
        rows, _ = measure(results, models_dir, settings.quick)
        keep = near_front(rows, settings.front_factor)
        more = make_jobs(
            settings,
            scenarios,
            models_dir,
            mujoco_available=mujoco,
            repeats=range(1, settings.repeats),
            only=keep,
            references=False,
        )
        total[0] = done[0] + len(more)
        results += execute(more, **kw)
    # Where the wall time went, job by job (the slowest first).
    write_rows(
        sorted(results, key=lambda r: -r.get("wall_s", 0.0)),
        out / "jobs.csv",
        ("wall_s", "scenario", "family", "solver", "backend", "settings", "repeat", "status"),
    )
    rows, checks = measure(results, models_dir, settings.quick)
    rows.sort(key=lambda r: (r["scenario"], r["family"], r["solver"], r["backend"], r["settings"]))
    write_rows(rows, out / "work_precision.csv")
    write_rows(
        [c.__dict__ for c in checks],
        out / "reference.csv",
        ("scenario", "reference", "agreement", "reference_cpu_s", "confirmation_cpu_s"),
    )
    agreements = {c.scenario: c.agreement for c in checks}
    table = ratio_table(rows, agreements)
    with atomic_write(out / "ratios.md", "w", encoding="utf-8") as f:
        f.write(ratio_markdown(table))
    from .plots import plot_work_precision

    for sc in scenarios:
        plot_work_precision(
            rows,
            sc,
            out / f"wp_{sc}.png",
            agreement=agreements[sc],
            title=SCENARIOS[sc].description,
        )
    return rows, checks
