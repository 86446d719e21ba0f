"""Whole-trajectory integration in the compiled core (``backend="compiled"`` entries).

The loops of :mod:`.fixed`, :mod:`.adaptive` and :mod:`.ali3p` (same output grid, projection,
stage projection, coordinate partitioning with re-partitioning, regularity
check, drift limit, error control of scipy's RK45/DOP853 with the same dense
output) run in C++ with the GIL released (other Python threads run
meanwhile: :func:`~.batch.simulate_batch`); the right-hand side never enters
Python unless ``tau`` is a callable (then it is called from C++, the GIL taken
back for the call), and a progress callback is called after each step. Ctrl-C
interrupts a run (in the main thread).

Each step checks every declared row (the dropped ones too): beyond
``drift_limit`` the run stops with SimulationError naming the row and time;
when a dropped row opens or the kept rows degenerate, the rows must be
re-selected, which the numpy backend does: the loop raises
:class:`closedchain.exceptions.RowCheckRequired` and the request runs there from
the start (logged; ``info.backend_fallback`` says why).
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .. import compiled
from ..exceptions import RowCheckRequired
from .fixed import output_grid
from .problem import Problem
from .registry import INTEGRATORS
from .rk43 import record_outputs

logger = logging.getLogger(__name__)


def _start_work(problem: Problem, q0: np.ndarray, v0: np.ndarray) -> None:
    """Start the work of tau at (q0, v0) (the core records samples only; W is integrated
    on them by :meth:`~.problem.Recorder.sample_work`, from this point)."""
    if problem.meter is not None:
        problem.step_end(0.0, q0, v0, problem.accel(0.0, q0, v0))


def _prepare(problem: Problem, info: dict, stab):
    core = compiled.make_core(problem.mech)
    compiled.configure(
        core,
        info["method"],
        problem.solver_settings,
        # The dropped-row threshold of the numpy checks (floored by a rounded model's
        # accepted disagreement: LoopClosure.dropped_row_tol).
        replace(problem.settings, dropped_row_tol=problem.row_check.dropped_tol),
        stage_projects=stab.projects_stages,
        singular_robust=problem.singular_robust,
        partitions=stab.partitions,
        independent=problem.ind,
    )
    core.set_tau(problem.tau_input)
    # The branch series (sign of det J_D at every sample, Recorder._add_branch) in C++.
    mech = problem.mech
    dep = np.asarray(mech.dependent_idx_v, dtype=np.int32)
    core.set_branch_columns(dep if mech.nc and len(dep) == mech.nc else dep[:0])
    return core


def _finish(problem: Problem, core, recorder, out: dict, info: dict, keep: bool = True) -> int:
    """Account for a compiled run ``out``; append its samples to ``recorder`` unless not
    ``keep``; return its steps."""
    problem.n_evals += int(out["evaluations"])
    names = problem.mech.coordinate_names
    for t, ind in out["repartitions"]:  # as Problem.repartition logs and fixed.py records
        logger.info(
            "%s: re-partitioned at t = %.9g s; independent: %s",
            problem.mech.name,
            t,
            ", ".join(names[i] for i in ind),
        )
        info["repartitions"].append([float(t), [names[i] for i in ind]])
    if out["repartitions"]:
        ind, dep = core.partition
        problem.ind, problem.dep = np.array(ind, dtype=int), np.array(dep, dtype=int)
    if "singular_splits" in out:  # rk4 with stage projection (fixed.py, rk43.py)
        info["singular_splits"] = int(out["singular_splits"])
    if "rejected_steps" in out:  # rk43.py
        info["rejected_steps"] = int(out["rejected_steps"])
        info["error_estimate_max"] = float(out["error_estimate_max"])
        info["error_estimate_sum"] = float(out["error_estimate_sum"])
    if keep:
        recorder.extend(out)
    return int(out["steps"])


def _numpy_fallback(exc, problem, recorder, args, spec, info) -> int:
    """Run the request with the numpy loop of the same name (it re-selects the rows);
    ``exc``: the reason, an exception or a sentence."""
    logger.info("%s: %s; the numpy backend re-selects the rows", problem.mech.name, exc)
    info["backend"] = "numpy"
    info["backend_fallback"] = str(exc)
    problem.n_evals = 0
    ref = INTEGRATORS[spec.name]
    q0, v0, t_final, control, stab, t_eval, progress = args
    return ref.run(problem, recorder, q0, v0, t_final, control, ref, stab, t_eval, progress, info)


def _output_steps(n_steps: int, out_steps) -> np.ndarray:
    """The steps a fixed-step loop records (``output_grid``'s; None: every step)."""
    if out_steps is None:
        return np.arange(n_steps + 1, dtype=np.int32)
    return np.asarray(out_steps, dtype=np.int32)


def _recorded_steps(problem: Problem, n_steps: int, out_steps):
    """Return (the steps the fixed-step loop records, the outputs among them or None).

    The work of tau (:class:`~.problem.WorkMeter`) needs the step ends, which the core
    returns as samples only: with tau and sparse outputs every step is recorded (while
    that fits ``max_outputs``), W computed on them, the outputs kept (:func:`_keep`).
    """
    if problem.meter is None or out_steps is None or n_steps + 1 > problem.settings.max_outputs:
        return _output_steps(n_steps, out_steps), None
    return _output_steps(n_steps, None), np.asarray(out_steps, dtype=np.intp)


def _keep(recorder, out: dict, keep: np.ndarray | None) -> dict:
    """Return the samples ``out`` of every step with W, cut to the output steps ``keep``."""
    if keep is None:
        return out
    work = recorder.sample_work(out)
    kept = {k: np.asarray(out[k])[keep] for k in (*recorder.SERIES, "branch") if k in out}
    return {**out, **kept, "w": work[keep]}


def run_fixed_compiled(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Fixed-step loop in C++ (euler, semi-implicit, rk4); return the number of steps."""
    _start_work(problem, q, v)
    core = _prepare(problem, info, stab)
    dt, n_steps, out_steps = output_grid(t_final, control.dt, t_eval)
    info["dt"] = dt
    recorded, keep = _recorded_steps(problem, n_steps, out_steps)
    try:
        out = core.run_fixed(
            compiled.INTEGRATOR_CODES[spec.name],
            np.asarray(q, dtype=float),
            np.asarray(v, dtype=float),
            float(dt),
            int(n_steps),
            recorded,
            bool(stab.projects),
            progress,
        )
    except RowCheckRequired as exc:
        args = (q, v, t_final, control, stab, t_eval, progress)
        return _numpy_fallback(exc, problem, recorder, args, spec, info)
    return _finish(problem, core, recorder, _keep(recorder, out, keep), info)


def run_adaptive_compiled(
    problem: Problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Adaptive Dormand-Prince loop in C++ (RK45, DOP853); return the number of steps.

    With tau and ``t_eval`` the work of tau needs the step ends, which the core returns
    only as samples: a first run finds them (t_eval None), the run proper records at
    them and at ``t_eval`` (dense output: the same steps), W is computed on all of them
    and the outputs kept (:func:`_keep`); twice the cost of the integration.
    """
    if stab.partitions and not len(problem.ind):
        # Mobility 0: no independent coordinate to integrate; the core's step control
        # needs a state (scipy's takes an empty one: the dependent solve does the rest).
        args = (q0, v0, t_final, control, stab, t_eval, progress)
        reason = "coordinate partitioning with no independent coordinate (mobility 0)"
        return _numpy_fallback(reason, problem, recorder, args, spec, info)
    _start_work(problem, q0, v0)

    def run(times, report):
        core = _prepare(problem, info, stab)  # configured anew: each run from the start
        out = core.run_adaptive(
            compiled.INTEGRATOR_CODES[spec.name],
            np.asarray(q0, dtype=float),
            np.asarray(v0, dtype=float),
            float(t_final),
            float(control.rtol),
            float(control.atol),
            None if times is None else np.asarray(times, dtype=float),
            bool(stab.projects),
            report,
        )
        return core, out

    keep = None
    times = t_eval
    try:
        if problem.meter is not None and t_eval is not None:
            _, steps = run(None, None)
            problem.n_evals += int(steps["evaluations"])
            grid = np.union1d(t_eval, np.asarray(steps["t"], dtype=float).ravel())
            if len(grid) <= problem.settings.max_outputs:
                times, keep = grid, np.searchsorted(grid, t_eval)
        core, out = run(times, progress)
    except RowCheckRequired as exc:
        args = (q0, v0, t_final, control, stab, t_eval, progress)
        return _numpy_fallback(exc, problem, recorder, args, spec, info)
    return _finish(problem, core, recorder, _keep(recorder, out, keep), info)


def run_rk43_compiled(
    problem: Problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """rk43 in C++ (:mod:`.rk43`, step for step); return the accepted steps.

    The core records every step end up to the last output time; the outputs before it
    are interpolated from them here (:func:`.rk43.record_outputs`, as the numpy loop
    does), the work of tau advanced over the step ends.
    """
    _start_work(problem, q0, v0)
    core = _prepare(problem, info, stab)
    try:
        out = core.run_rk43(
            np.asarray(q0, dtype=float),
            np.asarray(v0, dtype=float),
            float(t_final if t_eval is None else t_eval[-1]),
            float(control.rtol),
            float(control.atol),
            float(problem.settings.dt),
            None,
            False,
            progress,
        )
    except RowCheckRequired as exc:
        args = (q0, v0, t_final, control, stab, t_eval, progress)
        return _numpy_fallback(exc, problem, recorder, args, spec, info)
    if t_eval is None:
        return _finish(problem, core, recorder, out, info)
    steps = _finish(problem, core, recorder, out, info, keep=False)
    t = np.asarray(out["t"], dtype=float).ravel()
    q, v, a, lam = (recorder.sample_rows(out, k) for k in ("q", "v", "a", "lam"))
    pending = [float(s) for s in t_eval]
    if pending[0] <= 0.0:
        recorder.add(0.0, q[0], v[0], a[0], lam[0])
        pending.pop(0)
    for k in range(1, len(t)):
        problem.step_end(t[k], q[k], v[k], a[k])
        start, end = (t[k - 1], q[k - 1], v[k - 1], a[k - 1]), (t[k], q[k], v[k], a[k])
        record_outputs(problem, recorder, pending, start, end)
    return steps


def run_dop853_rk43_compiled(
    problem: Problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """dop853-rk43 in C++ (:mod:`.dop853_rk43`, step for step); return the accepted steps.

    The core records every step end and the outputs within the steps (their indices in
    ``out["outputs"]``): the work of tau is integrated over all of them, the outputs
    kept (:func:`_keep`).
    """
    _start_work(problem, q0, v0)
    core = _prepare(problem, info, stab)
    try:
        out = core.run_dop853_rk43(
            np.asarray(q0, dtype=float),
            np.asarray(v0, dtype=float),
            float(t_final if t_eval is None else t_eval[-1]),
            float(control.rtol),
            float(control.atol),
            float(problem.settings.dt),
            None if t_eval is None else np.asarray(t_eval, dtype=float),
            progress,
        )
    except RowCheckRequired as exc:
        args = (q0, v0, t_final, control, stab, t_eval, progress)
        return _numpy_fallback(exc, problem, recorder, args, spec, info)
    info["far_steps"] = int(out["far_steps"])
    info["zone_steps"] = int(out["zone_steps"])
    keep = None if t_eval is None else np.asarray(out["outputs"], dtype=np.intp)
    return _finish(problem, core, recorder, _keep(recorder, out, keep), info)


def run_ali3p_compiled(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """ALI3-P in C++ (src/cpp/ali3p.hpp, the algorithm of :mod:`.ali3p` step for step,
    with the band Cholesky of M + alpha J^T J where the numpy backend uses one);
    return the number of steps."""
    _start_work(problem, q, v)
    core = _prepare(problem, info, stab)
    s = problem.settings
    dt, n_steps, out_steps = output_grid(t_final, control.dt, t_eval)
    info["dt"] = dt
    recorded, keep = _recorded_steps(problem, n_steps, out_steps)
    out = core.run_ali3p(
        np.asarray(q, dtype=float),
        np.asarray(v, dtype=float),
        float(dt),
        int(n_steps),
        recorded,
        compiled.ali3p_settings(s),
        progress,
    )
    info["ali3p_alpha"] = float(out["ali3p_alpha"])
    info["newton_iterations"] = int(out["newton_iterations"])
    return _finish(problem, core, recorder, _keep(recorder, out, keep), info)
