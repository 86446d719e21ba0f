"""Accuracy against speed: closedchain beside its peers, in the same run, as tidy rows.

``run_work_precision`` runs every configuration of closedchain (from the
integrator registry: a newly registered backend is benchmarked without edits)
and of the peers (:mod:`.peers`) on each scenario (:mod:`.scenarios`), measures
the error against a reference confirmed by a second configuration, and writes

* ``work_precision.csv``: one tidy row per configuration (:data:`COLUMNS`);
* ``reference.csv``: per scenario, the agreement of reference and confirmation;
* ``ratios.md``: closedchain CPU / peer CPU at error 1e-3, 1e-6, 1e-9;
* ``wp_<scenario>.png``: the work-precision charts.

Plots are drawn from the rows by :mod:`.plots`; nothing there measures.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable
from pathlib import Path

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
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def read_rows(path: str | Path) -> list[dict]:
    """Read a CSV written by :func:`write_rows` (numbers back to float)."""
    out = []
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            for k in ("cpu_s", "error", "residual", "energy_drift"):
                if k in r:
                    r[k] = float(r[k]) if r[k] not in ("", "nan") else math.nan
            out.append(r)
    return out


def run_work_precision(
    out_dir: str | Path,
    *,
    settings: BenchSettings | None = None,
    scenarios: list[str] | None = None,
    models_dir: str | Path = "models",
    workers: int = 1,
    scheduler=None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[list[dict], list[ReferenceCheck]]:
    """Run the work-precision benchmark and write its CSVs, ratio table and charts.

    Args:
        out_dir: output directory (created).
        settings: grids and repeats; default :class:`BenchSettings`.
        scenarios: scenario names; default all (``QUICK_SCENARIOS`` when quick).
        models_dir: directory holding the scenarios' URDF files.
        workers: local processes.
        scheduler: Dask scheduler address (or Client): jobs go to that cluster.
        progress: ``progress(done, total)`` after each job.

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
    jobs = make_jobs(settings, scenarios, models_dir, mujoco_available=_mujoco_available())
    done = [0]

    def tick(n: int) -> None:
        done[0] += n
        if progress:
            progress(done[0], len(jobs))

    results = execute(jobs, workers=workers, scheduler=scheduler, progress=tick)
    rows, checks = measure(results, models_dir, settings.quick)
    rows.sort(key=lambda r: (r["scenario"], r["family"], r["solver"], r["settings"]))
    write_rows(rows, out / "work_precision.csv")
    write_rows(
        [c.__dict__ for c in checks],
        out / "reference.csv",
        ("scenario", "agreement", "reference_cpu_s", "confirmation_cpu_s"),
    )
    agreements = {c.scenario: c.agreement for c in checks}
    table = ratio_table(rows, agreements)
    (out / "ratios.md").write_text(ratio_markdown(table))
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
