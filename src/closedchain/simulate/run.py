"""Running a checked :func:`closedchain.simulate` request.

:func:`run_request` builds the :class:`~.problem.Problem` (the right-hand side)
and the :class:`~.problem.Recorder` (the samples), checks the start state
against the loops, runs the registered integrator and fills the run's
:class:`~closedchain.SimulationInfo`. A run that stops keeps the motion up to
the stop in ``exc.trajectory``.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import replace

import numpy as np
from threadpoolctl import threadpool_limits

from ..dynamics.base import METHOD_CAPABILITIES
from ..exceptions import SingularConfigurationError
from ..trajectory import SimulationInfo, Trajectory, energy_balance, energy_drift
from .problem import Problem, Recorder, report_limit_violations
from .request import Request, check_start_velocity
from .settings import SimulationError

logger = logging.getLogger(__name__)


def run_request(request: Request) -> Trajectory:
    """Integrate a checked request; return its trajectory.

    Raises:
        SingularConfigurationError: the method met a singular configuration
            (``exc.trajectory`` holds the motion up to the stop).
        SimulationError: non-finite state, integrator failure, drift beyond
            ``settings.drift_limit``, or an energy balance beyond
            ``settings.energy_tol`` (``exc.trajectory`` as above).
    """
    problem, recorder = _start(request)
    info = _run_info(request, problem)
    spec = request.spec
    cpu0 = time.process_time()
    # The numpy path makes many small solves; OpenBLAS's threads only spin on them (N-four-bar
    # N = 40 on the shared 2-core machine: 15 ms of CPU per step with one thread, 39 ms with
    # two). Entering the limit costs about 1 ms, nothing next to a numpy run.
    serial_blas = (
        threadpool_limits(limits=1, user_api="blas")
        if spec.backend == "numpy"
        else contextlib.nullcontext()
    )
    try:
        with serial_blas:
            steps = spec.run(
                problem,
                recorder,
                request.q0,
                request.v0,
                request.t_final,
                request.control,
                spec,
                request.stab,
                request.t_eval,
                request.progress,
                info,
            )
    except (SingularConfigurationError, SimulationError) as exc:
        _record_stop(exc, request, problem, recorder, info, cpu0)
        raise
    info["cpu_time"] = time.process_time() - cpu0
    return _finish(request, problem, recorder, info, steps)


def _start(request: Request) -> tuple[Problem, Recorder]:
    """Return the problem and the recorder of ``request``, its start state checked."""
    mech, spec, stab, settings = request.mech, request.spec, request.stab, request.settings
    solver_settings = request.solver_settings
    if stab.accel_terms:
        gains = (settings.baumgarte_alpha, settings.baumgarte_beta)
        solver_settings = replace(solver_settings, baumgarte=gains)
    problem = Problem(mech, request.method, request.tau, solver_settings, settings)
    # Passing singular positions takes a singular-robust method *and* accelerations
    # evaluated on the manifold only (stage projection) or an index-3 scheme; any
    # other configuration stops there with an error naming this one.
    problem.singular_robust = METHOD_CAPABILITIES[request.method].singular_robust and (
        stab.projects_stages or spec.singular_robust
    )
    recorder = Recorder(mech, settings.drift_limit, problem.jacobian, problem.meter)
    problem.check_start(request.q0, compiled_rows=spec.backend == "compiled")
    check_start_velocity(
        mech, request.q0, request.v0, settings.start_velocity_tol, problem.start_jacobian
    )
    return problem, recorder


def _run_info(request: Request, problem: Problem) -> dict:
    """Return the run configuration that :class:`~closedchain.SimulationInfo` records."""
    mech, control = request.mech, request.control
    info = {
        "mechanism": mech.name,
        "method": request.method,
        "integrator": request.spec.name,
        "backend": request.spec.backend,
        "stabilization": request.stab.name,
        "dt": control.dt,
        "rtol": control.rtol,
        "atol": control.atol,
        "t_final": request.t_final,
        "joint_names": list(mech.joint_names),
        "model_digest": mech.digest(),
        "coordinate_names": list(mech.coordinate_names) if mech.nq == mech.nv else None,
        "configuration_names": list(mech.configuration_names),
        "velocity_names": list(mech.coordinate_names),
        "independent": [mech.coordinate_names[i] for i in mech.independent_idx_v],
        "repartitions": [],
    }
    if request.stab.accel_terms:
        info["baumgarte"] = list(problem.solver_settings.baumgarte)
    return info


def _record_stop(
    exc: SingularConfigurationError | SimulationError,
    request: Request,
    problem: Problem,
    recorder: Recorder,
    info: dict,
    cpu0: float,
) -> None:
    """Give ``exc`` its time and the motion up to the stop (``exc.trajectory``)."""
    if request.spec.backend == "compiled" and not len(recorder):
        # The compiled loop hands its samples over at the end only: the
        # reference loop recovers the motion up to the stop (its error,
        # with exc.trajectory, is raised instead).
        logger.info("%s: compiled run stopped (%s); re-running with numpy", info["mechanism"], exc)
        run_request(request.on_numpy())
    # Nothing is lost: the caller gets the motion up to the stop (e.g. to animate it).
    if getattr(exc, "t", None) is None:  # raised outside a timed evaluation
        exc.t = float(recorder.series()["t"][-1]) if len(recorder) else 0.0
    info["stopped"] = {"t": exc.t, "reason": str(exc)}
    info["cpu_time"] = time.process_time() - cpu0
    info["evaluations"] = problem.n_evals
    exc.trajectory = recorder.trajectory(info) if len(recorder) else None


def _finish(
    request: Request, problem: Problem, recorder: Recorder, info: dict, steps: int
) -> Trajectory:
    """Return the trajectory of a completed run, its residuals and energy in ``info``."""
    info["row_reselections"] = problem.reselections
    info["steps"] = steps
    info["evaluations"] = problem.n_evals
    info["branch_changes"] = recorder.branch_changes
    series = recorder.series()
    info["max_constraint_residual"] = float(np.max(series["res"], initial=0.0))
    info["energy_drift"] = energy_drift(series["e"], series["ke"])
    work = None if recorder.meter is None else series["w"]
    info["energy_balance"] = energy_balance(series["e"], series["ke"], work)
    settings = request.settings
    report_limit_violations(request.mech, recorder, info, settings)  # warns; raises: stop_at_limits
    traj = recorder.trajectory(SimulationInfo.from_dict(info))
    # Mobility 0: nothing moves; E changes by the round-off of a zero velocity and has
    # no scale to be measured against (E(0) is zero where the potential's zero is).
    if settings.energy_tol is not None and request.mech.mobility > 0:
        check_energy(traj, settings.energy_tol)
    logger.info(
        "%s: %d steps, %d evaluations, %.3f s CPU",
        request.mech.name,
        steps,
        problem.n_evals,
        info["cpu_time"],
    )
    return traj


def check_energy(traj: Trajectory, energy_tol: float) -> None:
    """Raise SimulationError when the run's relative energy balance exceeds ``energy_tol``.

    ``Trajectory.energy_balance``: the energy drift E - E0 of an unforced, undamped run,
    and E - E0 - W of a run driven by tau or damped (W the work of tau and of the joint
    damping), which is zero for an exact solution whatever drives it. E holds the joint
    springs' potential.

    Raises:
        SimulationError: with ``trajectory`` the whole run.
    """
    balance = traj.energy_balance
    if not balance <= energy_tol:
        what = (
            "energy drift of this unforced run"
            if traj.work is None
            else "energy balance of this run (E - E0 - the work of tau and damping)"
        )
        exc = SimulationError(
            f"{traj.info.mechanism}: the relative {what} is {balance:.3g} > energy_tol "
            f"{energy_tol:.3g}: the integration is not accurate (use a smaller step or "
            "tolerance, or another integrator)",
            float(traj.t[-1]),
        )
        exc.trajectory = traj
        raise exc
