"""Work-precision runs: jobs, execution (local processes or Dask), tidy rows.

A job is a plain dict (scenario, family, solver, backend, settings, repeat) so
it can be pickled to a local process or a Dask worker (there, one task per worker
thread runs a share of the jobs: :func:`run_jobs`); :func:`run_job` runs it
and returns the states on the comparison grid and the CPU seconds. The
parent then measures each run against the scenario's reference and writes one
tidy row per configuration (median CPU over repeats).
"""

from __future__ import annotations

import logging
import math
import random
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import numpy as np
import pinocchio as pin

from ..closure import max_declared_residual
from ..dynamics.base import METHOD_CAPABILITIES
from ..exceptions import ClosedChainError
from ..simulate import INTEGRATORS
from ..simulate.registry import COMPILED_INTEGRATORS
from .peers import RUNNERS
from .references import EXACT_REFERENCES
from .scenarios import (
    SCENARIOS,
    Scenario,
    fresh_compiled_core,
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

#: Largest number of local worker processes (``closedchain bench --workers``):
#: each holds the models and Pinocchio, some 100 MB.
MAX_WORKERS = 256

#: Largest number of runs per configuration (``closedchain bench --repeats``):
#: the full benchmark takes minutes per repeat.
MAX_REPEATS = 1000


@dataclass(frozen=True)
class BenchSettings:
    """Grids of one benchmark run.

    Attributes:
        quick: 4-bar passive only, short horizons, few settings, one repeat.
        repeats: runs per configuration near a front (CPU is their median); the
            others run once (see :func:`near_front`).
        tolerances: rtol = atol of DOP853 (closedchain's compiled one and scipy).
        other_tolerances: rtol = atol of the other adaptive integrators.
        numpy_tolerances: rtol = atol of closedchain's numpy adaptive integrators (the
            reference implementation, placed on the chart at a few points: the compiled
            one takes the same steps).
        steps: fixed steps [s] of closedchain's compiled fixed-step integrators and the lesson peer;
            on a scenario only the steps dividing its output spacing run (simulate would
            shorten any other step to one that does, a duplicate): the steps above 1e-2
            run where the comparison grid is coarser (the N-four-bar's 0.05 s), so that
            rk4 is not held to 1e-2 s where it reaches 1e-3 rad at 5e-2 s.
        numpy_steps: fixed steps [s] of the numpy (reference implementation) fixed-step
            integrators: their cost per step is 20-60x the compiled one's, so they are
            placed on the chart at the largest step only (unless the method has no
            compiled implementation).
        euler_steps: steps of Pinocchio's Euler loop [s].
        mujoco_steps: MuJoCo timesteps [s].
        reference_tol: tolerance of the reference and its confirmation.
        front_factor: a configuration whose CPU is within this factor of its family's
            Pareto front at its error is "near the front" and gets every repeat.
        seed: shuffling seed of the interleaved job order.
    """

    quick: bool = False
    repeats: int = 2
    tolerances: tuple[float, ...] = (1e-3, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
    other_tolerances: tuple[float, ...] = (1e-4, 1e-7)
    numpy_tolerances: tuple[float, ...] = (1e-4, 1e-8)
    steps: tuple[float, ...] = (5e-2, 2.5e-2, 1.25e-2, 1e-2, 5e-3, 2e-3, 1e-3)
    numpy_steps: tuple[float, ...] = (1e-2,)
    euler_steps: tuple[float, ...] = (1e-3, 5e-4, 2e-4, 1e-4)
    mujoco_steps: tuple[float, ...] = (2e-3, 1e-3, 5e-4, 2e-4, 1e-4)
    reference_tol: float = 1e-13
    front_factor: float = 2.0
    seed: int = 0


QUICK = BenchSettings(
    quick=True,
    repeats=1,
    tolerances=(1e-4, 1e-8),
    other_tolerances=(),
    numpy_tolerances=(1e-4, 1e-8),
    steps=(2e-3,),
    numpy_steps=(2e-3,),
    euler_steps=(1e-3, 1e-4),
    mujoco_steps=(1e-3, 1e-4),
)

#: Integrators the scipy peer runs.
SCIPY_INTEGRATORS = ("DOP853", "Radau")
#: Scenarios of ``--quick``.
QUICK_SCENARIOS = ("fourbar-passive",)
#: The only adaptive integrator of ``--quick`` and the fixed-step one.
QUICK_INTEGRATORS = ("DOP853", "rk4")


def _fmt(x: float) -> str:
    """``x`` in the shortest e-notation that reads back exactly (1e-02, 1.25e-02): the label is
    part of a configuration's key, so two settings must never share one."""
    for digits in range(16):
        s = f"{x:.{digits}e}"
        if float(s) == x:
            return s
    return repr(x)


def _closedchain_configs(settings: BenchSettings, method: str) -> list[dict]:
    """closedchain's configurations from both integrator registries (numpy and compiled),
    so a newly registered integrator or backend is benchmarked without edits here."""
    configs = []
    registries = [("numpy", INTEGRATORS)]
    if METHOD_CAPABILITIES[method].compiled:
        registries.append(("compiled", COMPILED_INTEGRATORS))
    for backend, registry in registries:
        for name, spec in registry.items():
            if settings.quick and name not in QUICK_INTEGRATORS:
                continue
            if spec.method_capabilities and not all(
                getattr(METHOD_CAPABILITIES[method], c) for c in spec.method_capabilities
            ):
                continue
            stab = spec.default_stabilization
            if stab not in spec.stabilizations:  # compiled fixed-step: no stage projection
                stab = "projection"
            if spec.kind == "adaptive":
                if backend == "numpy":
                    grid = settings.numpy_tolerances
                    if name != "DOP853" and METHOD_CAPABILITIES[method].compiled:
                        grid = grid[:1]  # one point per numpy integrator beside the compiled
                else:
                    grid = settings.tolerances if name == "DOP853" else settings.other_tolerances
                key, label = "tol", "tol"
            else:
                grid = settings.steps
                if backend == "numpy" and METHOD_CAPABILITIES[method].compiled:
                    grid = settings.numpy_steps
                key, label = "dt", "dt"
            for x in grid:
                configs.append(
                    dict(
                        family="closedchain",
                        solver=f"{method}/{name}/{stab}",
                        backend=backend,
                        settings=f"{label}={_fmt(x)}",
                        kwargs={
                            "method": method,
                            "integrator": name,
                            "stabilization": stab,
                            "backend": backend,
                            key: x,
                        },
                    )
                )
    return configs


def configurations(
    settings: BenchSettings, *, mujoco_available: bool, method: str = "kkt"
) -> list[dict]:
    """Return the configurations (without scenario and repeat): closedchain's (with the
    scenario's ``method``) and every peer's."""
    configs = _closedchain_configs(settings, method)
    for integ in SCIPY_INTEGRATORS:
        if settings.quick and integ != "DOP853":
            continue
        for tol in settings.tolerances if integ == "DOP853" else settings.other_tolerances:
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
    lesson_spec = COMPILED_INTEGRATORS.get("semi-implicit")
    lesson_backend = (
        "compiled"
        if lesson_spec is not None
        and "projection" in lesson_spec.stabilizations
        and METHOD_CAPABILITIES["kkt"].compiled
        else "numpy"
    )
    for dt in settings.steps:
        configs.append(
            dict(
                family="lesson",
                solver="euler/2 newton",
                backend=lesson_backend,
                settings=f"dt={_fmt(dt)}",
                kwargs=dict(dt=dt, backend=lesson_backend),
            )
        )
    return configs


def reference_configurations(
    settings: BenchSettings, scenario: Scenario | None = None, *, nq_equals_nv: bool = True
) -> list[dict]:
    """The reference and its confirmation of a scenario.

    * An exact reference (``scenario.exact``): the double-precision quadrature, confirmed
      by the mpmath one.
    * Otherwise: the scenario's method with DOP853 at the tightest tolerance (compiled
      when it can), confirmed by the numpy nullspace method with DOP853 and coordinate
      partitioning (another formulation, another drift control, another
      implementation); with nq != nv (continuous joints), where partitioning cannot
      run, projection after each step instead.
    """
    if scenario is not None and scenario.exact:
        return [
            dict(
                family=fam,
                solver=f"exact/{scenario.exact}" + ("" if fam == "reference" else "/mpmath"),
                backend="python",
                settings="quadrature",
                kwargs=dict(exact=scenario.exact),
            )
            for fam in ("reference", "confirmation")
        ]
    method = scenario.method if scenario is not None else "kkt"
    backend = "compiled" if METHOD_CAPABILITIES[method].compiled else "numpy"
    tol = settings.reference_tol
    confirm_stab = "partitioning" if nq_equals_nv else "projection"
    return [
        dict(
            family="reference",
            solver=f"{method}/DOP853/none",
            backend=backend,
            settings=f"tol={_fmt(tol)}",
            kwargs=dict(
                method=method, integrator="DOP853", stabilization="none", backend=backend, tol=tol
            ),
        ),
        dict(
            family="confirmation",
            solver=f"nullspace/DOP853/{confirm_stab}",
            backend="numpy",
            settings=f"tol={_fmt(tol)}",
            kwargs=dict(
                method="nullspace",
                integrator="DOP853",
                stabilization=confirm_stab,
                backend="numpy",
                tol=tol,
            ),
        ),
    ]


def scenario_grid(scenario: Scenario, quick: bool) -> np.ndarray:
    """Comparison times [s] of a scenario."""
    t_final = scenario.quick_t_final if quick else scenario.t_final
    n = round(t_final / scenario.output_dt)
    return np.linspace(0.0, n * scenario.output_dt, n + 1)


def divides(dt: float, spacing: float) -> bool:
    """True when the step ``dt`` [s] divides the output spacing ``spacing`` [s]."""
    n = round(spacing / dt)
    return n >= 1 and abs(n * dt - spacing) <= 1e-9 * spacing


def run_job(job: dict) -> dict:
    """Run one job (in any process); return its states on the grid and CPU seconds."""
    wall0 = time.perf_counter()
    scenario = SCENARIOS[job["scenario"]]
    mech = load_scenario_mechanism(job["models_dir"], scenario)
    fresh_compiled_core(mech)
    q0, v0 = initial_state(mech, scenario)
    tau_fn = torque_function(mech, scenario)
    t_grid = scenario_grid(scenario, job["quick"])
    out = dict(job)
    try:
        if "exact" in job["kwargs"]:
            reference, confirmation = EXACT_REFERENCES[job["kwargs"]["exact"]]
            fn = reference if job["family"] == "reference" else confirmation
            cpu0 = time.process_time()
            q = fn(mech, q0, v0, t_grid)
            out.update(
                q=q, v=np.empty((0,)), cpu_s=time.process_time() - cpu0, status="ok", message=""
            )
        else:
            runner = RUNNERS[
                "closedchain" if job["family"] in ("reference", "confirmation") else job["family"]
            ]
            with np.errstate(all="ignore"):
                res = runner(mech, q0, v0, t_grid, tau_fn, **job["kwargs"])
            out.update(q=res.q, v=res.v, cpu_s=res.cpu_s, status=res.status, message=res.message)
    except ClosedChainError as exc:
        out.update(q=None, v=None, cpu_s=math.nan, status="raised", message=_first_line(exc))
    except Exception as exc:  # a peer's own failure is a result, not a crash
        logger.debug("job failed: %s", traceback.format_exc())
        out.update(
            q=None,
            v=None,
            cpu_s=math.nan,
            status="raised",
            message=f"{type(exc).__name__}: {_first_line(exc)}",
        )
    out["wall_s"] = time.perf_counter() - wall0
    return out


#: Characters of an error message kept in the CSV.
MESSAGE_CHARS = 300


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return (text.splitlines()[0] if text else type(exc).__name__)[:MESSAGE_CHARS]


def worker_chunks(items: list, n_workers: int) -> list[list]:
    """Deal ``items`` round-robin into at most ``n_workers`` non-empty chunks (jobs come in
    an interleaved order: each chunk gets a share of every scenario and family, so the
    chunks cost about the same)."""
    n = max(1, min(n_workers, len(items)))
    return [items[k::n] for k in range(n)]


def run_jobs(jobs: list[dict], fn: Callable[[dict], dict] | None = None) -> list[dict]:
    """Run a batch of jobs one after another in one task (a Dask worker's share).

    Each job keeps its own clock (the CPU time is the measurement: the jobs never share
    the process's cores with each other); the scenario's mechanism is loaded once per
    process (:func:`.scenarios.load_scenario_mechanism`), not per job.
    """
    fn = fn or run_job
    return [fn(job) for job in jobs]


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
            or a ``distributed.Client``: one task per worker thread, each running its
            share of the jobs (:func:`run_jobs`).
        progress: called with the number of jobs finished (1 after each job; on Dask,
            a task's share when it ends).

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
            # One task per worker thread, each a batch of jobs (run_jobs): one round trip
            # and one model load per scenario and worker, not per job.
            chunks = worker_chunks(list(range(len(jobs))), sum(client.nthreads().values()))
            futures = client.map(
                run_jobs, [[jobs[i] for i in chunk] for chunk in chunks], fn=fn, pure=False
            )
            index = {f.key: chunk for f, chunk in zip(futures, chunks, strict=True)}
            results: list = [None] * len(jobs)
            for fut in as_completed(futures):
                chunk = index[fut.key]
                for i, res in zip(chunk, fut.result(), strict=True):
                    results[i] = res
                if progress:
                    progress(len(chunk))
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
            mech.passive.kinetic_energy(model, data, qk, vk)  # armature included
            + pin.computePotentialEnergy(model, data, qk)
            + mech.passive.spring_energy(qk)
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
    reference: str
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
        mech = load_scenario_mechanism(models_dir, scenario)
        ref = next(r for r in results if r["scenario"] == sc and r["family"] == "reference")
        conf = next(r for r in results if r["scenario"] == sc and r["family"] == "confirmation")
        label = (
            f"{ref['solver']} {ref['backend']} {ref['settings']} confirmed by "
            f"{conf['solver']} {conf['backend']} {conf['settings']}"
        )
        if ref["status"] != "ok" or conf["status"] != "ok":
            # No confirmed reference: the scenario's rows get no error (said in the output).
            logger.warning(
                "no confirmed reference for %s: %s %s", sc, ref["message"], conf["message"]
            )
            label += f" FAILED: {ref['message']} {conf['message']}".rstrip()
            refs[sc] = None
            checks.append(ReferenceCheck(sc, label, math.inf, ref["cpu_s"], conf["cpu_s"]))
            continue
        agreement = _coordinate_error(mech, conf["q"], ref["q"])
        refs[sc] = ref
        checks.append(ReferenceCheck(sc, label, agreement, ref["cpu_s"], conf["cpu_s"]))
    groups: dict[tuple, list[dict]] = {}
    for r in results:
        if r["family"] in ("reference", "confirmation"):
            continue
        key = (r["scenario"], r["family"], r["solver"], r["backend"], r["settings"])
        groups.setdefault(key, []).append(r)
    rows = []
    for (sc, family, solver, backend, setting), runs in groups.items():
        scenario = SCENARIOS[sc]
        mech = load_scenario_mechanism(models_dir, scenario)
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
                if ref is None:
                    row["message"] = "no confirmed reference: error not measured"
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
    settings: BenchSettings,
    scenarios: Iterable[str],
    models_dir: str,
    *,
    mujoco_available: bool,
    repeats: Iterable[int] | None = None,
    only: set[tuple] | None = None,
    references: bool = True,
) -> list[dict]:
    """Jobs: references first, then every configuration x scenario x repeat, interleaved
    (repeat by repeat, shuffled within a repeat) so machine noise hits all configurations
    alike.

    Args:
        repeats: repeat indices (default all of ``settings.repeats``).
        only: keep only these (scenario, family, solver, backend, settings) keys.
        references: include the reference and confirmation jobs.
    """
    scenarios = list(scenarios)
    per_scenario = {}
    jobs = []
    for sc in scenarios:
        scenario = SCENARIOS[sc]
        mech = load_scenario_mechanism(models_dir, scenario)
        t_final = scenario_grid(scenario, settings.quick)[-1]
        per_scenario[sc] = [
            cfg
            for cfg in configurations(
                settings, mujoco_available=mujoco_available, method=scenario.method
            )
            if "dt" not in cfg["kwargs"]
            or (
                divides(cfg["kwargs"]["dt"], scenario.output_dt)
                and (
                    scenario.max_steps is None
                    or t_final / cfg["kwargs"]["dt"] <= scenario.max_steps * (1 + 1e-9)
                )
            )
        ]
        if references:
            for cfg in reference_configurations(
                settings, scenario, nq_equals_nv=mech.nq == mech.nv
            ):
                jobs.append(
                    dict(cfg, scenario=sc, repeat=0, quick=settings.quick, models_dir=models_dir)
                )
    rng = random.Random(settings.seed)
    for rep in range(settings.repeats) if repeats is None else repeats:
        batch = [
            dict(cfg, scenario=sc, repeat=rep, quick=settings.quick, models_dir=models_dir)
            for sc in scenarios
            for cfg in per_scenario[sc]
            if only is None
            or (sc, cfg["family"], cfg["solver"], cfg["backend"], cfg["settings"]) in only
        ]
        rng.shuffle(batch)
        jobs += batch
    return jobs


def row_key(row: dict) -> tuple:
    """The configuration key of a row or job: (scenario, family, solver, backend, settings)."""
    return (row["scenario"], row["family"], row["solver"], row["backend"], row["settings"])


def near_front(rows: list[dict], factor: float) -> set[tuple]:
    """Keys of the rows that can matter to a front or the ratio table: a successful run whose
    CPU is within ``factor`` of the cheapest run of its family and scenario at least as
    accurate. Runs far off every front are measured once."""
    keep = set()
    for r in rows:
        if not (r["status"] == "ok" and math.isfinite(r["error"]) and math.isfinite(r["cpu_s"])):
            continue
        rivals = [
            x["cpu_s"]
            for x in rows
            if x["scenario"] == r["scenario"]
            and x["family"] == r["family"]
            and x["status"] == "ok"
            and math.isfinite(x["cpu_s"])
            and x["error"] <= r["error"]
        ]
        if r["cpu_s"] <= factor * min(rivals):
            keep.add(row_key(r))
    return keep


__all__ = [
    "BenchSettings",
    "near_front",
    "row_key",
    "COLUMNS",
    "QUICK",
    "ReferenceCheck",
    "asdict",
    "execute",
    "make_jobs",
    "measure",
    "run_job",
]
