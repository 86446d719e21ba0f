"""Work-precision runs: jobs, execution (local processes or Dask), tidy rows.

A job is a plain dict (scenario, family, solver, backend, settings, repeat) so
it can be pickled to a local process or a Dask worker; :func:`run_job` runs it
and returns the states on the comparison grid and the CPU seconds. The
parent then measures each run against the scenario's reference and writes one
tidy row per configuration (median CPU over repeats).
"""

from __future__ import annotations

import logging
import math
import random
import traceback
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import numpy as np
import pinocchio as pin

from ..closure import max_declared_residual
from ..exceptions import ClosedChainError
from ..simulate import INTEGRATORS
from .peers import RUNNERS
from .scenarios import (
    SCENARIOS,
    Scenario,
    initial_state,
    load_scenario_mechanism,
    torque_function,
)

logger = logging.getLogger(__name__)

#: Columns of the work-precision CSV, in order.
COLUMNS = (
    "family",
    "mechanism",
    "scenario",
    "solver",
    "backend",
    "settings",
    "cpu_s",
    "error",
    "residual",
    "energy_drift",
    "status",
    "message",
)


@dataclass(frozen=True)
class BenchSettings:
    """Grids of one benchmark run.

    Attributes:
        quick: 4-bar passive only, short horizons, few settings, one repeat.
        repeats: runs per configuration (CPU is their median).
        tolerances: rtol = atol of adaptive integrators (closedchain and scipy).
        steps: fixed steps [s] of closedchain's fixed-step integrators and the seed.
        euler_steps: steps of Pinocchio's Euler loop [s].
        mujoco_steps: MuJoCo timesteps [s].
        method: closedchain's forward-dynamics method of the work-precision runs.
        reference_tol: tolerance of the reference and its confirmation.
        drift_row_tol: a declared row above this is "drift" (stability map) [m or -].
        seed: shuffling seed of the interleaved job order.
    """

    quick: bool = False
    repeats: int = 2
    tolerances: tuple[float, ...] = (1e-3, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
    steps: tuple[float, ...] = (1e-2, 5e-3, 2e-3, 1e-3)
    euler_steps: tuple[float, ...] = (1e-3, 5e-4, 2e-4, 1e-4, 5e-5)
    mujoco_steps: tuple[float, ...] = (2e-3, 1e-3, 5e-4, 2e-4, 1e-4, 5e-5)
    method: str = "kkt"
    reference_tol: float = 1e-13
    seed: int = 0


QUICK = BenchSettings(
    quick=True,
    repeats=1,
    tolerances=(1e-4, 1e-8),
    steps=(2e-3,),
    euler_steps=(1e-3, 1e-4),
    mujoco_steps=(1e-3, 1e-4),
)

#: Adaptive integrators below this order stop at LOW_ORDER_MIN_TOL.
HIGH_ORDER = 8
LOW_ORDER_MIN_TOL = 1e-9
#: Integrators the scipy peer runs.
SCIPY_INTEGRATORS = ("DOP853", "Radau")
#: Scenarios of ``--quick``.
QUICK_SCENARIOS = ("fourbar-passive",)


def _fmt(x: float) -> str:
    return f"{x:.0e}"


def configurations(settings: BenchSettings, *, mujoco_available: bool) -> list[dict]:
    """Return the configurations (without scenario and repeat): closedchain's come from the
    integrator registry, so a newly registered backend is benchmarked without edits here."""
    configs: list[dict] = []
    for name, spec in INTEGRATORS.items():
        if spec.kind == "adaptive":
            if settings.quick and name != "DOP853":
                continue
            for tol in settings.tolerances:
                if spec.order < HIGH_ORDER and tol < LOW_ORDER_MIN_TOL:
                    continue  # thousands of steps per second for no new information
                configs.append(
                    dict(
                        family="closedchain",
                        solver=f"{settings.method}/{name}/{spec.default_stabilization}",
                        backend=spec.backend,
                        settings=f"tol={_fmt(tol)}",
                        kwargs=dict(
                            method=settings.method,
                            integrator=name,
                            stabilization=spec.default_stabilization,
                            tol=tol,
                        ),
                    )
                )
        else:
            if settings.quick and name != "rk4":
                continue
            for dt in settings.steps:
                configs.append(
                    dict(
                        family="closedchain",
                        solver=f"{settings.method}/{name}/{spec.default_stabilization}",
                        backend=spec.backend,
                        settings=f"dt={_fmt(dt)}",
                        kwargs=dict(
                            method=settings.method,
                            integrator=name,
                            stabilization=spec.default_stabilization,
                            dt=dt,
                        ),
                    )
                )
    for integ in SCIPY_INTEGRATORS:
        if settings.quick and integ != "DOP853":
            continue
        for tol in settings.tolerances:
            if integ != "DOP853" and tol < LOW_ORDER_MIN_TOL:
                continue
            configs.append(
                dict(
                    family="scipy",
                    solver=f"constraintDynamics/{integ}",
                    backend="python",
                    settings=f"tol={_fmt(tol)}",
                    kwargs=dict(integrator=integ, tol=tol),
                )
            )
    for dt in settings.euler_steps:
        configs.append(
            dict(
                family="pinocchio-euler",
                solver="constraintDynamics/semi-implicit/baumgarte",
                backend="python",
                settings=f"dt={_fmt(dt)}",
                kwargs=dict(dt=dt),
            )
        )
    if mujoco_available:
        for stiff in (False, True):
            for dt in settings.mujoco_steps:
                configs.append(
                    dict(
                        family="mujoco",
                        solver="mj_step/" + ("stiff" if stiff else "default"),
                        backend="C",
                        settings=f"dt={_fmt(dt)}",
                        kwargs=dict(dt=dt, stiff=stiff),
                    )
                )
    for dt in settings.steps:
        configs.append(
            dict(
                family="seed",
                solver="euler/2 newton",
                backend="numpy",
                settings=f"dt={_fmt(dt)}",
                kwargs=dict(dt=dt),
            )
        )
    return configs


def reference_configurations(settings: BenchSettings) -> list[dict]:
    """The reference (kkt, DOP853, tightest tolerance) and its confirmation (nullspace,
    DOP853 with coordinate partitioning: another formulation and another drift control)."""
    tol = settings.reference_tol
    return [
        dict(
            family="reference",
            solver="kkt/DOP853/none",
            backend="numpy",
            settings=f"tol={_fmt(tol)}",
            kwargs=dict(method="kkt", integrator="DOP853", stabilization="none", tol=tol),
        ),
        dict(
            family="confirmation",
            solver="nullspace/DOP853/partitioning",
            backend="numpy",
            settings=f"tol={_fmt(tol)}",
            kwargs=dict(
                method="nullspace", integrator="DOP853", stabilization="partitioning", tol=tol
            ),
        ),
    ]


def scenario_grid(scenario: Scenario, quick: bool) -> np.ndarray:
    """Comparison times [s] of a scenario."""
    t_final = scenario.quick_t_final if quick else scenario.t_final
    n = round(t_final / scenario.output_dt)
    return np.linspace(0.0, n * scenario.output_dt, n + 1)


def run_job(job: dict) -> dict:
    """Run one job (in any process); return its states on the grid and CPU seconds."""
    scenario = SCENARIOS[job["scenario"]]
    mech = load_scenario_mechanism(job["models_dir"], scenario.urdf, scenario.gravity)
    q0, v0 = initial_state(mech, scenario)
    tau_fn = torque_function(mech, scenario)
    t_grid = scenario_grid(scenario, job["quick"])
    runner = RUNNERS[
        "closedchain" if job["family"] in ("reference", "confirmation") else job["family"]
    ]
    out = dict(job)
    try:
        res = runner(mech, q0, v0, t_grid, tau_fn, **job["kwargs"])
        out.update(q=res.q, v=res.v, cpu_s=res.cpu_s, status=res.status, message=res.message)
    except ClosedChainError as exc:
        out.update(q=None, v=None, cpu_s=math.nan, status="raised", message=str(exc))
    except Exception as exc:  # a peer's own failure is a result, not a crash
        logger.debug("job failed: %s", traceback.format_exc())
        out.update(
            q=None, v=None, cpu_s=math.nan, status="raised", message=f"{type(exc).__name__}: {exc}"
        )
    return out


def execute(
    jobs: list[dict],
    *,
    fn: Callable[[dict], dict] | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    progress: Callable[[int], None] | None = None,
) -> list[dict]:
    """Run ``jobs`` in this process (workers = 1), local processes, or on a Dask cluster.

    Args:
        jobs: the jobs.
        fn: the function run on each job (default :func:`run_job`); module-level, so
            it pickles.
        workers: local worker processes (ignored with ``scheduler``).
        scheduler: address of a Dask distributed scheduler (``tcp://host:port``),
            or a ``distributed.Client``.
        progress: called with 1 after each finished job.

    Returns:
        The results, in the order of ``jobs``.
    """
    fn = fn or run_job
    if scheduler is not None:
        try:
            from distributed import Client, as_completed
        except ImportError as exc:
            raise ClosedChainError(
                "--scheduler needs Dask distributed: pip install 'closedchain[dask]'"
            ) from exc
        client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
        try:
            futures = client.map(fn, jobs, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            results: list = [None] * len(jobs)
            for fut in as_completed(futures):
                results[index[fut.key]] = fut.result()
                if progress:
                    progress(1)
            return results
        finally:
            if client is not scheduler:
                client.close()
    if workers <= 1:
        results = []
        for job in jobs:
            results.append(fn(job))
            if progress:
                progress(1)
        return results
    from concurrent.futures import ProcessPoolExecutor

    results = []
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for res in pool.map(fn, jobs):
            results.append(res)
            if progress:
                progress(1)
    return results


def _energy(mech, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    model, data = mech.model, mech.model.createData()
    return np.array(
        [
            pin.computeKineticEnergy(model, data, qk, vk)
            + pin.computePotentialEnergy(model, data, qk)
            for qk, vk in zip(q, v, strict=True)
        ]
    )


def _coordinate_error(mech, q: np.ndarray, q_ref: np.ndarray) -> float:
    model = mech.model
    pairs = zip(q, q_ref, strict=True)
    return float(max(np.max(np.abs(pin.difference(model, a, b))) for a, b in pairs))


@dataclass
class ReferenceCheck:
    """A scenario's reference and the agreement of its confirmation [rad or m]."""

    scenario: str
    agreement: float
    reference_cpu_s: float
    confirmation_cpu_s: float


def measure(
    results: Iterable[dict], models_dir: str, quick: bool
) -> tuple[list[dict], list[ReferenceCheck]]:
    """Turn job results into tidy rows: error against the reference, residual, energy drift,
    median CPU per simulated second over repeats."""
    results = list(results)
    refs: dict[str, dict] = {}
    checks = []
    for sc in sorted({r["scenario"] for r in results}):
        scenario = SCENARIOS[sc]
        mech = load_scenario_mechanism(models_dir, scenario.urdf, scenario.gravity)
        ref = next(r for r in results if r["scenario"] == sc and r["family"] == "reference")
        conf = next(r for r in results if r["scenario"] == sc and r["family"] == "confirmation")
        if ref["status"] != "ok" or conf["status"] != "ok":
            raise ClosedChainError(f"reference of {sc} failed: {ref['message']} {conf['message']}")
        agreement = _coordinate_error(mech, conf["q"], ref["q"])
        refs[sc] = ref
        checks.append(ReferenceCheck(sc, agreement, ref["cpu_s"], conf["cpu_s"]))
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        if r["family"] in ("reference", "confirmation"):
            continue
        key = (r["scenario"], r["family"], r["solver"], r["backend"], r["settings"])
        groups.setdefault(key, []).append(r)
    rows = []
    for (sc, family, solver, backend, setting), runs in groups.items():
        scenario = SCENARIOS[sc]
        mech = load_scenario_mechanism(models_dir, scenario.urdf, scenario.gravity)
        t_final = scenario_grid(scenario, quick)[-1]
        ref = refs[sc]
        first = runs[0]
        row = dict(
            family=family,
            mechanism=mech.name,
            scenario=sc,
            solver=solver,
            backend=backend,
            settings=setting,
            cpu_s=math.nan,
            error=math.nan,
            residual=math.nan,
            energy_drift=math.nan,
            status=first["status"],
            message=first["message"],
        )
        cpus = [r["cpu_s"] for r in runs if r["status"] == "ok"]
        if first["q"] is not None and len(first["q"]):
            q, v = np.asarray(first["q"]), np.asarray(first["v"])
            n = len(q)
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
                row.update(status="diverged", message="non-finite state")
            else:
                row["error"] = _coordinate_error(mech, q, ref["q"][:n])
                row["residual"] = max_declared_residual(mech, q)
                if scenario.passive:
                    e = _energy(mech, q, v)
                    row["energy_drift"] = float(np.max(np.abs(e - e[0])))
        if row["status"] == "ok" and cpus:
            row["cpu_s"] = float(np.median(cpus)) / t_final
        elif row["status"] != "ok":
            row["cpu_s"] = float(np.median([r["cpu_s"] for r in runs])) / t_final
        rows.append(row)
    return rows, checks


def make_jobs(
    settings: BenchSettings, scenarios: Iterable[str], models_dir: str, *, mujoco_available: bool
) -> list[dict]:
    """All jobs: references first, then every configuration x scenario x repeat,
    interleaved (repeat by repeat, shuffled within a repeat) so machine noise hits all
    configurations alike."""
    base = configurations(settings, mujoco_available=mujoco_available)
    jobs = []
    for sc in scenarios:
        for cfg in reference_configurations(settings):
            jobs.append(
                dict(cfg, scenario=sc, repeat=0, quick=settings.quick, models_dir=models_dir)
            )
    rng = random.Random(settings.seed)
    for rep in range(settings.repeats):
        batch = [
            dict(cfg, scenario=sc, repeat=rep, quick=settings.quick, models_dir=models_dir)
            for sc in scenarios
            for cfg in base
        ]
        rng.shuffle(batch)
        jobs += batch
    return jobs


__all__ = [
    "BenchSettings",
    "COLUMNS",
    "QUICK",
    "ReferenceCheck",
    "asdict",
    "execute",
    "make_jobs",
    "measure",
    "run_job",
]
