"""Cost per forward-dynamics evaluation against the size of a mechanism family.

For each family of :data:`~closedchain.benchmark.families.FAMILIES` (a chain closed
by one loop, a pair of legs with four loops, the N-four-bar) and each size, times one
evaluation (the work of one explicit step) of closedchain's default method and of
``kkt`` -- numpy reference, compiled core called from Python, compiled core inside
``simulate`` -- beside ``pinocchio.constraintDynamics`` (the cheapest exact proximal
settings) and MuJoCo's ``mj_forward`` on the exported model, interleaved size by size,
and fits the growth exponent p of cost ~ nv^p by least squares on log-log axes.

``closedchain bench --scaling`` runs it (:func:`run_scaling`).
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
from threadpoolctl import threadpool_limits

from .._io import atomic_write
from ..dynamics.base import DEFAULT_METHOD, DEFAULT_SETTINGS, get_method
from ..simulate.request import DEFAULT_INTEGRATOR
from ..exceptions import SingularConfigurationError
from ..kinematics import assemble, project_velocity
from ..mechanism import Mechanism, load
from . import write_rows
from .evaluation import cheapest_exact_settings, compiled_methods, mujoco_forward
from .families import FAMILIES

logger = logging.getLogger(__name__)

SCALING_COLUMNS = ("family", "n", "nv", "nc", "method", "backend", "us")
#: Label of Pinocchio's solver in the rows.
PINOCCHIO_CALL = "pin.constraintDynamics"
#: Label of MuJoCo's forward dynamics in the rows.
MUJOCO_CALL = "mujoco.mj_forward"
#: The methods of the study: the default and the lesson's block system.
SCALING_METHODS = (DEFAULT_METHOD, "kkt")
#: CPU time each timing repeat aims at [s] (the number of calls is chosen from it).
REPEAT_BUDGET = 0.05
#: Steps of the shorter of the two ``simulate`` runs whose difference is timed (rk4 at
#: :data:`SIMULATE_DT`, 4 evaluations a step; the difference leaves out the run's setup),
#: and the bounds of the extra steps of the longer one (chosen to take about
#: :data:`REPEAT_BUDGET` of CPU, at most 20 ms of motion). The step is short enough for every
#: size: rk4 at 1 ms left the 1000-link chain's manifold at t = 0.017 s (the run raised), and
#: the cost of an evaluation does not depend on the step.
SIMULATE_STEPS = 2
EXTRA_STEPS = (20, 200)
SIMULATE_DT = 1e-4  # [s]
#: Motion per "step" of the default run [s]: the default integrator chooses its own
#: steps; the two runs last SIMULATE_STEPS and SIMULATE_STEPS + extra times this.
DEFAULT_RUN_DT = SIMULATE_DT  # [s]
#: Label of ``simulate``'s default settings (method and integrator) in the rows.
DEFAULT_CALL = f"default, {DEFAULT_INTEGRATOR}"
#: Backend label of the compiled core timed inside ``simulate``.
IN_SIMULATE = "compiled, in simulate"
#: Sum of the independent coordinates' rates at the timed state [rad/s]: each moves at
#: START_RATE / n_I. A unit rate each turned the 300-link chain's dependent joints at
#: 168 rad/s (|a| 4.5e5 rad/s^2: rk4 at 1 ms left its manifold in two steps) and brought
#: the 30-link leg pair's parallelograms to a flat position at t = 0.15 s (kkt stops).
START_RATE = 1.0  # [rad/s]


def cpu_us(fn: Callable[[], object], budget: float = REPEAT_BUDGET) -> float:
    """CPU time of one call of ``fn`` [us], averaged over as many calls as fit in
    ``budget`` seconds of CPU (at least one; ``time.process_time``)."""
    t0 = time.process_time()
    fn()
    once = max(time.process_time() - t0, 1e-7)
    number = max(1, min(100_000, int(budget / once)))
    t0 = time.process_time()
    for _ in range(number):
        fn()
    return (time.process_time() - t0) / number * 1e6


def _start(mech: Mechanism, guess: Callable[[Mechanism], np.ndarray] | None):
    """The timed state: the assembled start, its independent coordinates moving at
    :data:`START_RATE` / n_I each (random consistent states are hard to find for long
    chains)."""
    q = mech.q_ref.copy()
    if guess is not None:
        q = assemble(mech, guess(mech), fixed="independent")
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = START_RATE / len(mech.independent_idx_v)
    return q, project_velocity(mech, q, v, fixed="independent")


def _in_simulate(mech: Mechanism, method: str | None, q, v) -> Callable[[], float]:
    """A call returning the CPU per evaluation [us] of the compiled loop: the
    difference of two runs, so that the setup of a run (checks, the core's
    configuration) is not counted. ``method`` runs under rk4 at :data:`SIMULATE_DT`
    (a run of ``steps`` steps); None runs ``simulate``'s default settings over
    ``steps`` x :data:`DEFAULT_RUN_DT` of motion (its own steps, error estimates and
    projections counted in the cost of its evaluations)."""
    from ..simulate import simulate

    def run(steps: int) -> tuple[float, int]:
        t0 = time.process_time()
        if method is None:
            traj = simulate(mech, q, v, steps * DEFAULT_RUN_DT, backend="compiled")
        else:
            traj = simulate(
                mech,
                q,
                v,
                steps * SIMULATE_DT,
                method=method,
                integrator="rk4",
                dt=SIMULATE_DT,
                backend="compiled",
            )
        return time.process_time() - t0, traj.info.evaluations

    longer = []

    def per_evaluation() -> float:
        if not longer:  # caches made on first use, then the length of the longer run
            run(SIMULATE_STEPS)
            cpu1, _ = run(SIMULATE_STEPS)
            cpu2, _ = run(SIMULATE_STEPS + EXTRA_STEPS[0])
            per_step = max(cpu2 - cpu1, 1e-9) / EXTRA_STEPS[0]
            extra = int(np.clip(REPEAT_BUDGET / per_step, *EXTRA_STEPS))
            longer.append(SIMULATE_STEPS + extra)
        (cpu1, ev1), (cpu2, ev2) = run(SIMULATE_STEPS), run(longer[0])
        return (cpu2 - cpu1) / (ev2 - ev1) * 1e6

    return per_evaluation


def scaling_calls(mech: Mechanism, q, v, methods=SCALING_METHODS) -> list[tuple]:
    """The timed calls ``(method, backend, fn, per_evaluation)`` at (q, v); ``fn()``
    returns the CPU per evaluation [us] itself when ``per_evaluation`` is True."""
    tau = np.zeros(mech.nv)
    calls = []
    for name in methods:
        f = get_method(name)
        calls.append((name, "numpy", lambda f=f: f(mech, q, v, tau, DEFAULT_SETTINGS), False))
    compiled = dict(compiled_methods(mech))
    for name in methods:
        if name in compiled:
            fd = compiled[name]
            calls.append((name, "compiled", lambda fd=fd: fd.forward(q, v, tau), False))
            calls.append((name, IN_SIMULATE, _in_simulate(mech, name, q, v), True))
    if compiled:
        calls.append((DEFAULT_CALL, IN_SIMULATE, _in_simulate(mech, None, q, v), True))
    cms, cds, _, data = mech.pinocchio_constraints()
    prox = None
    try:  # the reference of the cheapest exact settings: the default method
        a_ref = get_method(DEFAULT_METHOD)(mech, q, v, tau, DEFAULT_SETTINGS)[0]
        prox, _note = cheapest_exact_settings(mech, q, v, tau, a_ref, cms, cds, data)
    except SingularConfigurationError as exc:
        logger.warning("scaling: no reference for Pinocchio's exact settings: %s", exc)
    prox = prox or DEFAULT_SETTINGS.pinocchio_proximal()
    calls.append(
        (
            PINOCCHIO_CALL,
            "C++",
            lambda: pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, prox),
            False,
        )
    )
    mj_forward = mujoco_forward(mech, q, v)
    if mj_forward is not None:
        calls.append((MUJOCO_CALL, "C", mj_forward, False))
    return calls


def time_scaling(
    files: dict[int, str | Path],
    *,
    family: str = "",
    methods: tuple[str, ...] = SCALING_METHODS,
    repeats: int = 3,
    guess: Callable[[Mechanism], np.ndarray] | None = None,
) -> list[dict]:
    """Microseconds per evaluation for each size n -> URDF file (tidy rows).

    Args:
        files: n -> URDF file.
        family: the family's name in the rows.
        methods: closedchain methods timed (numpy, compiled, inside simulate).
        repeats: timing repeats, interleaved over every call of every size (median).
        guess: ``guess(mech) -> q`` near a regular configuration, assembled with the
            independent coordinates held (default: the model's ``q_ref``).
    """
    entries = []
    for n, path in sorted(files.items()):
        mech = load(path)
        q, v = _start(mech, guess)
        for name, backend, fn, per_evaluation in scaling_calls(mech, q, v, methods):
            entries.append((n, mech, name, backend, fn, per_evaluation, []))
    # BLAS on one thread: idle OpenBLAS workers spin and charge their CPU time to the
    # next timed call.
    with threadpool_limits(limits=1, user_api="blas"):
        _time_entries(entries, repeats)
    return [
        dict(
            family=family,
            n=n,
            nv=mech.nv,
            nc=mech.nc,
            method=name,
            backend=backend,
            us=float(np.median(runs)),
        )
        for n, mech, name, backend, _fn, _per, runs in entries
    ]


def _time_entries(entries: list[tuple], repeats: int) -> None:
    """Time every entry once per repeat, interleaved; a failure is timed as NaN."""
    for _ in range(repeats):
        for *_, fn, per_evaluation, runs in entries:
            try:
                runs.append(fn() if per_evaluation else cpu_us(fn))
            except Exception as exc:  # a method that cannot handle a size is reported
                logger.warning("scaling: %s", exc)
                runs.append(math.nan)


def series_label(row: dict) -> str:
    """``method (backend)`` of a scaling row (the method alone when no backend is given)."""
    backend = row.get("backend")
    return f"{row['method']} ({backend})" if backend else row["method"]


def growth_exponents(rows: list[dict], size: str = "n") -> dict[str, float]:
    """Least-squares slope p of log(us) against log(size) per method and backend
    (``size``: the row key of the size, ``"n"`` or ``"nv"``)."""
    out = {}
    for method in sorted({series_label(r) for r in rows}):
        mine = [r for r in rows if series_label(r) == method and np.isfinite(r["us"])]
        if len(mine) >= 2:
            x = np.log([r[size] for r in mine])
            y = np.log([r["us"] for r in mine])
            out[method] = float(np.polyfit(x, y, 1)[0])
    return out


def scaling_markdown(rows: list[dict]) -> str:
    """One table per family: us per evaluation at each size, and the exponent in nv."""
    parts = []
    for family in dict.fromkeys(r["family"] for r in rows):
        mine = [r for r in rows if r["family"] == family]
        sizes = sorted({(r["n"], r["nv"], r["nc"]) for r in mine})
        exps = growth_exponents(mine, size="nv")
        us = {(series_label(r), r["n"]): r["us"] for r in mine}
        head = " | ".join(f"n = {n} (nv {nv}, nc {nc})" for n, nv, nc in sizes)
        lines = [
            f"### {family}",
            "",
            f"{FAMILIES[family].about}" if family in FAMILIES else "",
            "",
            f"| method (backend) | p (cost ~ nv^p) | {head} |",
            "| --- | --- |" + " --- |" * len(sizes),
        ]
        for label in sorted({series_label(r) for r in mine}):
            p = exps.get(label, math.nan)
            cells = " | ".join(_us(us.get((label, n), math.nan)) for n, _, _ in sizes)
            lines.append(f"| {label} | {p:.2f} | {cells} |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


def _us(x: float) -> str:
    return "refused" if not np.isfinite(x) else (f"{x:.1f}" if x < 1000 else f"{x:.0f}")


def run_scaling(
    out_dir: str | Path,
    families: list[str] | None = None,
    *,
    repeats: int = 3,
    sizes: dict[str, tuple[int, ...]] | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """Time the families and write ``scaling.csv``, ``scaling.md`` and ``scaling.png``.

    Args:
        out_dir: output directory (created).
        families: names in :data:`~closedchain.benchmark.families.FAMILIES` (default all).
        repeats: timing repeats (median).
        sizes: family -> sizes, replacing the family's own.
        progress: called with each family's name before it is timed.

    Returns:
        The rows written to ``scaling.csv``.
    """
    from .plots import plot_scaling

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in families or list(FAMILIES):
        fam = FAMILIES[name]
        if progress is not None:
            progress(name)
        with tempfile.TemporaryDirectory() as tmp:
            files = {}
            for n in (sizes or {}).get(name, fam.sizes):
                path = Path(tmp) / f"{name}_{n}.urdf"
                path.write_text(fam.urdf(n))
                files[n] = path
            rows += time_scaling(files, family=name, repeats=repeats, guess=fam.start)
    write_rows(rows, out / "scaling.csv", SCALING_COLUMNS)
    with atomic_write(out / "scaling.md", "w") as f:
        f.write(scaling_markdown(rows))
    plot_scaling(rows, out / "scaling.png")
    return rows
