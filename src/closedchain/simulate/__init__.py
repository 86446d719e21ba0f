r"""Time integration of closed-chain dynamics with drift control.

The index-1 DAE of the seed text (Problem 5),

.. math::

    \dot q = v, \qquad M a + h + J^\top \lambda = \tau, \qquad J a + \gamma = 0,

is integrated as an ODE in (q, v) by one of :data:`INTEGRATORS`, with one of
:data:`STABILIZATIONS` to keep phi(q) = 0 and J v = 0 from drifting:

``"none"``
    the acceleration-level constraint only: phi and J v drift with the
    integration error.
``"baumgarte"``
    J a + gamma + 2 alpha J v + beta^2 phi = 0 (Baumgarte 1972): drift is
    damped, not removed.
``"projection"``
    after each step, q is brought back onto phi = 0 by Gauss-Newton
    (minimum-norm, as in the seed's Python program) and v onto J v = 0.
``"partitioning"``
    coordinate partitioning (Wehage & Haug 1982, seed Sections 4 and 6): only
    the independent coordinates (q_I, v_I) are integrated; the dependent ones
    are solved exactly from phi(q) = 0 and J v = 0 at every evaluation, so there
    is no drift by construction. When J_D becomes ill-conditioned the
    partition is changed (re-partitioning) and integration restarts from the
    current state.

The seed's own algorithm is ``integrator="semi-implicit", stabilization=
"projection"`` with ``SimulationSettings(projection_iters=2,
project_velocities=False)`` (see :func:`seed_settings`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from .._locking import exclusive
from ..dynamics import DEFAULT_SETTINGS as DEFAULT_SOLVER_SETTINGS
from ..dynamics import SolverSettings
from ..dynamics.base import DEFAULT_METHOD, METHOD_CAPABILITIES, METHODS, method_name
from ..exceptions import (
    InvalidArgumentError,
    SingularConfigurationError,
    check_settings,
    resolve_choice,
)
from ..trajectory import SimulationInfo, Trajectory, energy_balance, energy_drift
from .problem import Problem, Recorder, report_limit_violations
from .registry import (
    COMPILED_INTEGRATORS,
    INTEGRATORS,
    STABILIZATIONS,
    IntegratorSpec,
    StabilizationSpec,
    StepControl,
    get_integrator,
    get_stabilization,
    register_integrator,
    register_stabilization,
)
from .settings import (
    DEFAULT_SIMULATION_SETTINGS,
    SimulationError,
    SimulationSettings,
    TorqueInput,
    seed_settings,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)

#: The integrator of ``simulate(integrator=None)``: rk4 with stage projection and an
#: adaptive step under rtol/atol (:mod:`closedchain.simulate.rk43`).
DEFAULT_INTEGRATOR = "rk43"
#: The integrator of ``simulate(integrator=None, dt=...)``, and of a stabilization that
#: the default does not support: fixed-step rk4.
DEFAULT_FIXED_INTEGRATOR = "rk4"
#: The integrator of ``simulate(integrator=None, rtol=..., stabilization=...)`` with a
#: stabilization that the default does not support.
DEFAULT_ADAPTIVE_INTEGRATOR = "DOP853"

#: Values of ``simulate(backend=...)``.
BACKENDS = ("auto", "compiled", "numpy")

__all__ = [
    "BACKENDS",
    "COMPILED_INTEGRATORS",
    "INTEGRATORS",
    "STABILIZATIONS",
    "IntegratorSpec",
    "SimulationError",
    "SimulationSettings",
    "StabilizationSpec",
    "StepControl",
    "TorqueInput",
    "get_integrator",
    "get_stabilization",
    "register_integrator",
    "register_stabilization",
    "seed_settings",
    "simulate",
]


#: Smallest relative tolerance accepted: 100 machine epsilons, the floor scipy's
#: solvers silently raise a smaller rtol to.
MIN_RTOL = 100 * float(np.finfo(float).eps)

#: Smallest absolute tolerance accepted: scipy's error norm squares
#: error / (atol + rtol |y|), and below 1e-150 the square of an O(1) error over
#: atol overflows double precision (1e300 against the largest double, 1.8e308).
MIN_ATOL = 1e-150


def check_start_velocity(
    mech: Mechanism,
    q0: np.ndarray,
    v0: np.ndarray,
    tol: float,
    jacobian: Callable[[np.ndarray], np.ndarray] | None = None,
) -> None:
    """Raise InvalidArgumentError when v0 violates the loops' velocity constraint J(q0) v0 = 0.

    The residual is compared with ``tol * max(1, max |v0|)`` [m/s or rad/s per row].

    Args:
        jacobian: J(q) of the kept rows (e.g. ``Problem.jacobian``, which reuses the J
            its start check computed at q0); default: :func:`closedchain.compute_jacobian`.
    """
    if jacobian is None:
        from ..kinematics import compute_jacobian

        def jacobian(q):
            return compute_jacobian(mech, q)

    residual = float(np.max(np.abs(jacobian(q0) @ v0), initial=0.0))
    bound = tol * max(1.0, float(np.max(np.abs(v0), initial=0.0)))
    if residual > bound:
        raise InvalidArgumentError(
            f"{mech.name}: v0 violates the loops' velocity constraint J(q0) v0 = 0: max |J v0| "
            f"= {residual:.3g} > {bound:.3g} (SimulationSettings.start_velocity_tol x "
            "max(1, max |v0|)); project it first: v0 = closedchain.project_velocity(mech, q0, v0)"
        )


def check_energy(traj: Trajectory, energy_tol: float) -> None:
    """Raise SimulationError when the run's relative energy balance exceeds ``energy_tol``.

    ``Trajectory.energy_balance``: the energy drift E - E0 of an unforced run, and
    E - E0 - W of a run driven by tau (W its work), which is zero for an exact solution
    whatever drives it.

    Raises:
        SimulationError: with ``trajectory`` the whole run.
    """
    balance = traj.energy_balance
    if not balance <= energy_tol:
        what = (
            "energy drift of this unforced run"
            if traj.work is None
            else "energy balance of this driven run (E - E0 - the work of tau)"
        )
        exc = SimulationError(
            f"{traj.info.mechanism}: the relative {what} is {balance:.3g} > energy_tol "
            f"{energy_tol:.3g}: the integration is not accurate (use a smaller step or "
            "tolerance, or another integrator)",
            float(traj.t[-1]),
        )
        exc.trajectory = traj
        raise exc


def check_positive(name: str, value, what: str) -> None:
    """Raise ClosedChainError (a ValueError) unless ``value`` is a finite number > 0.

    Args:
        name: argument name, for the message.
        value: the value given.
        what: what the argument is, for the message.
    """
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise InvalidArgumentError(
            f"{name} ({what}) must be a finite number > 0, got {value!r}; valid range: (0, inf)"
        )


def check_t_eval(
    t_eval, t_final: float, settings: SimulationSettings = DEFAULT_SIMULATION_SETTINGS
) -> np.ndarray | None:
    """Return ``t_eval`` as a float array, or raise naming what is wrong with it.

    Valid: None, or a 1-D array of 1 to ``settings.max_outputs`` finite,
    strictly increasing times within [0, t_final].
    """
    if t_eval is None:
        return None
    t_eval = np.asarray(t_eval, dtype=float)
    valid = (
        f"valid: 1 to {settings.max_outputs} finite, strictly increasing times within "
        f"[0, t_final = {t_final:g}] s"
    )
    if t_eval.ndim != 1 or t_eval.size == 0:
        raise InvalidArgumentError(f"t_eval has shape {t_eval.shape}; {valid}")
    if t_eval.size > settings.max_outputs:
        raise InvalidArgumentError(
            f"t_eval has {t_eval.size} times, more than SimulationSettings.max_outputs; {valid}"
        )
    if not np.all(np.isfinite(t_eval)):
        raise InvalidArgumentError(f"t_eval contains non-finite times; {valid}")
    if np.any(np.diff(t_eval) <= 0):
        k = int(np.argmax(np.diff(t_eval) <= 0))
        raise InvalidArgumentError(
            f"t_eval is not strictly increasing (t_eval[{k}] = {t_eval[k]:g}, "
            f"t_eval[{k + 1}] = {t_eval[k + 1]:g}); {valid}"
        )
    if t_eval[0] < 0 or t_eval[-1] > t_final * (1 + 1e-12):
        raise InvalidArgumentError(
            f"t_eval spans [{t_eval[0]:g}, {t_eval[-1]:g}] s, outside [0, t_final]; {valid}"
        )
    return t_eval


def default_integrator(
    dt: float | None, rtol: float | None, atol: float | None, stabilization: str | None
) -> str:
    """Return the integrator of ``simulate(integrator=None, ...)``: :data:`DEFAULT_INTEGRATOR`
    unless the request needs another kind (``dt``: :data:`DEFAULT_FIXED_INTEGRATOR`) or a
    stabilization it does not support (then the fixed or, with ``rtol`` or ``atol``, the
    adaptive :data:`DEFAULT_ADAPTIVE_INTEGRATOR`)."""
    if dt is not None:
        return DEFAULT_FIXED_INTEGRATOR
    default = get_integrator(DEFAULT_INTEGRATOR)
    if stabilization is None or get_stabilization(stabilization).name in default.stabilizations:
        return default.name
    if rtol is not None or atol is not None:
        return DEFAULT_ADAPTIVE_INTEGRATOR
    return DEFAULT_FIXED_INTEGRATOR


def _select_backend(
    spec: IntegratorSpec, backend: str, stabilization: str, method: str, mech: Mechanism
) -> tuple[IntegratorSpec, str | None]:
    """Return the integrator entry that runs the request (see ``simulate``'s ``backend``)
    and, when ``"auto"`` falls back to numpy because of the mechanism's rows, why."""
    from .. import compiled

    backend = resolve_choice("backend", backend, BACKENDS)
    if backend == "numpy":
        return spec, None
    rows = compiled.unsupported_rows(mech)
    if rows is not None:
        if backend == "compiled":
            raise InvalidArgumentError("backend='compiled' cannot run this request: " + rows)
        return spec, rows
    method = method_name(method)
    cspec = COMPILED_INTEGRATORS.get(spec.name)
    reasons = []
    if cspec is None:
        reasons.append(f"integrator {spec.name!r} has no compiled loop")
    elif stabilization not in cspec.stabilizations:
        reasons.append(
            f"the compiled {spec.name!r} supports stabilizations "
            f"{', '.join(cspec.stabilizations)}, not {stabilization!r}"
        )
    if not METHOD_CAPABILITIES[method].compiled:
        reasons.append(f"method {method!r} has no compiled implementation")
    if not reasons:
        return cspec, None
    if backend == "compiled":
        raise InvalidArgumentError(
            "backend='compiled' cannot run this request: " + "; ".join(reasons)
        )
    return spec, None


@exclusive
def simulate(
    mech: Mechanism,
    q0: np.ndarray,
    v0: np.ndarray,
    t_final: float,
    *,
    method: str = DEFAULT_METHOD,
    integrator: str | None = None,
    dt: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    stabilization: str | None = None,
    tau: TorqueInput = None,
    t_eval: np.ndarray | None = None,
    settings: SimulationSettings = DEFAULT_SIMULATION_SETTINGS,
    solver_settings: SolverSettings = DEFAULT_SOLVER_SETTINGS,
    progress: Callable[[float], None] | None = None,
    backend: str = "auto",
) -> Trajectory:
    """Integrate the constrained dynamics from (q0, v0) over [0, t_final].

    Args:
        mech: the mechanism.
        q0: initial configuration, shape (nq,), on phi = 0 (see :func:`assemble`).
        v0: initial velocity, shape (nv,), with J v0 = 0 (see :func:`project_velocity`).
        t_final: duration [s].
        method: forward-dynamics method (a name in ``closedchain.METHODS``).
            Default ``DEFAULT_METHOD`` (``"augmented-lagrangian"``, as
            :func:`~closedchain.forward_dynamics`): well posed where J loses rank.
        integrator: a name in :data:`INTEGRATORS`. Default (None): ``"rk43"``, rk4
            with stage projection whose step is chosen by an embedded error estimate
            under ``rtol``/``atol`` (first trial step ``settings.dt``), which passes
            singular positions (see the guide, "Singular positions"); with ``dt``,
            ``"rk4"`` at that fixed step; with a stabilization rk43 does not
            support, ``"rk4"`` (``"DOP853"`` when ``rtol`` or ``atol`` is given):
            :func:`default_integrator`.
        dt: fixed step [s] (fixed-step integrators; default ``settings.dt``).
        rtol: relative tolerance (adaptive integrators; default: the integrator's
            ``IntegratorSpec.tolerances``, 1e-9 for rk43, else ``settings.rtol``).
        atol: absolute tolerance (adaptive integrators; default: the integrator's
            ``IntegratorSpec.tolerances``, 1e-10 for rk43, else ``settings.atol``).
        stabilization: a name in :data:`STABILIZATIONS`; default: the
            integrator's ``default_stabilization`` (``"stage-projection"`` for
            the explicit fixed-step integrators, ``"mass-orthogonal"`` for
            ``"ali3p"``, ``"none"`` for adaptive ones).
        tau: generalized forces [N m or N]: None (zero), a constant array of
            shape (nv,), or a callable ``tau(t, q, v) -> (nv,)`` (actuators,
            springs, dampers, a controller).
        t_eval: output times [s], increasing, within [0, t_final]; default:
            every step (fixed-step) or every accepted step (adaptive). Adaptive
            integrators use dense output; fixed-step outputs fall on the step
            grid (``dt`` is shortened so that each output time is a step).
        settings: simulation settings.
        solver_settings: settings of the dynamics method.
        progress: called with the current time [s] after each step.
        backend: ``"auto"`` (default): the compiled integrator of the same
            name (:data:`COMPILED_INTEGRATORS`) when it supports the
            stabilization and the method is compiled
            (``MethodCapabilities.compiled``), else the numpy one;
            ``"compiled"``: the compiled one or an error saying why not;
            ``"numpy"``: the Python reference implementation.

    Returns:
        The trajectory; ``info`` holds the steps, evaluations, CPU time,
        re-partitions and the run configuration.

    Raises:
        UnknownChoiceError: unknown integrator, stabilization or method.
        SingularConfigurationError: the method met a singular configuration
            (message and attributes give the time and condition number;
            ``exc.trajectory`` holds the motion up to the stop).
        SimulationError: non-finite state, integrator failure, or drift
            beyond ``settings.drift_limit`` (``exc.trajectory`` as above).
    """
    check_settings("settings", settings, SimulationSettings)
    check_settings("solver_settings", solver_settings, SolverSettings)
    if integrator is None:
        integrator = default_integrator(dt, rtol, atol, stabilization)
    spec = get_integrator(integrator)
    integrator = spec.name
    fixed = spec.kind == "fixed"
    if stabilization is None:
        stabilization = spec.default_stabilization
    spec, fallback = _select_backend(spec, backend, stabilization, method, mech)
    stab = get_stabilization(stabilization)
    stabilization = stab.name
    if stabilization not in spec.stabilizations:
        raise InvalidArgumentError(
            f"integrator {integrator!r} does not support stabilization {stabilization!r}; "
            f"valid choices: {', '.join(spec.stabilizations)}"
        )
    method = method_name(method)
    caps = METHOD_CAPABILITIES[method]
    missing = [c for c in spec.method_capabilities if not getattr(caps, c)]
    if missing:
        able = [
            m
            for m in sorted(METHODS)
            if all(getattr(METHOD_CAPABILITIES[m], c) for c in spec.method_capabilities)
        ]
        raise InvalidArgumentError(
            f"integrator {integrator!r} needs a method with {', '.join(missing)}; "
            f"method {method!r} has not; valid choices: {', '.join(able)}"
        )
    if stab.accel_terms and not METHOD_CAPABILITIES[method].baumgarte:
        with_terms = [m for m in sorted(METHODS) if METHOD_CAPABILITIES[m].baumgarte]
        raise InvalidArgumentError(
            f"method {method!r} solves its own constraint equations and cannot apply the "
            "Baumgarte terms; use stabilization 'projection' or 'partitioning', or a "
            f"method among {', '.join(with_terms)}"
        )
    q0 = mech.check_q(q0, "q0")
    mech.check_limits(
        q0,
        "q0",
        urdf_limits=settings.check_limits,
        opt_out="SimulationSettings(check_limits=False) or --ignore-limits allows it",
    )
    v0 = mech.check_v(v0, "v0")
    check_positive("t_final", t_final, "the duration [s]")
    t_final = float(t_final)
    if tau is not None and not callable(tau):
        tau = mech.check_v(tau, "tau")
    if stab.partitions and mech.nq != mech.nv:
        raise InvalidArgumentError(
            f"stabilization {stabilization!r} integrates the independent coordinates of q as "
            f"a vector and needs nq == nv (this mechanism has nq={mech.nq}, nv={mech.nv}); "
            "valid choices here: "
            + ", ".join(s for s in spec.stabilizations if not STABILIZATIONS[s].partitions)
        )
    t_eval = check_t_eval(t_eval, t_final, settings)
    # A step control the integrator would ignore is a mistake, not a no-op.
    ignored = ("rtol", "atol") if fixed else ("dt",)
    given = [n for n, val in (("dt", dt), ("rtol", rtol), ("atol", atol)) if val is not None]
    if any(n in ignored for n in given):
        kinds = {"fixed": "dt", "adaptive": "rtol and atol"}
        raise InvalidArgumentError(
            f"integrator {integrator!r} is {spec.kind}-step and takes {kinds[spec.kind]}, "
            f"not {', '.join(n for n in given if n in ignored)}; fixed-step: "
            f"{', '.join(n for n, sp in INTEGRATORS.items() if sp.kind == 'fixed')}; adaptive: "
            f"{', '.join(n for n, sp in INTEGRATORS.items() if sp.kind == 'adaptive')}"
        )
    if fixed:
        dt = settings.dt if dt is None else dt
        check_positive("dt", dt, "the fixed step [s]")
        dt = float(dt)
        ratio = t_final / dt  # a float: inf when it overflows (dt near the underflow)
        n_steps = math.ceil(ratio - 1e-9) if math.isfinite(ratio) else math.inf
        if n_steps > settings.max_steps:
            raise InvalidArgumentError(
                f"dt = {dt:g} s over t_final = {t_final:g} s is {n_steps:.3g} steps, more than "
                f"SimulationSettings.max_steps = {settings.max_steps:.3g}; use a larger dt "
                f"(>= {t_final / settings.max_steps:.3g} s) or an adaptive integrator"
            )
        if t_eval is None and n_steps + 1 > settings.max_outputs:
            raise InvalidArgumentError(
                f"recording every one of {n_steps:.3g} steps is more than "
                f"SimulationSettings.max_outputs = {settings.max_outputs:.3g} samples; "
                "pass t_eval (the output times) to keep fewer"
            )
    else:
        default_rtol, default_atol = spec.tolerances or (settings.rtol, settings.atol)
        rtol = default_rtol if rtol is None else rtol
        atol = default_atol if atol is None else atol
        check_positive("rtol", rtol, "the relative tolerance")
        check_positive("atol", atol, "the absolute tolerance")
        rtol, atol = float(rtol), float(atol)
        if rtol < MIN_RTOL:
            raise InvalidArgumentError(
                f"rtol = {rtol:g} is below what double precision resolves (scipy would raise it "
                f"to {MIN_RTOL:.3g} without a word); valid range: [{MIN_RTOL:.3g}, inf)"
            )
        if atol < MIN_ATOL:
            raise InvalidArgumentError(
                f"atol = {atol:g} is so small that scipy's error norm overflows; "
                f"valid range: [{MIN_ATOL:.3g}, inf)"
            )

    original_solver_settings = solver_settings
    if stab.accel_terms:
        gains = (settings.baumgarte_alpha, settings.baumgarte_beta)
        solver_settings = replace(solver_settings, baumgarte=gains)
    problem = Problem(mech, method, tau, solver_settings, settings)
    # Passing singular positions takes a singular-robust method *and* accelerations
    # evaluated on the manifold only (stage projection) or an index-3 scheme; any
    # other configuration stops there with an error naming this one.
    problem.singular_robust = caps.singular_robust and (
        stab.projects_stages or spec.singular_robust
    )
    recorder = Recorder(mech, settings.drift_limit, problem.jacobian, problem.meter)
    problem.check_start(q0, compiled_rows=spec.backend == "compiled")
    check_start_velocity(mech, q0, v0, settings.start_velocity_tol, problem.start_jacobian)
    info = {
        "mechanism": mech.name,
        "method": method,
        "integrator": integrator,
        "backend": spec.backend,
        "stabilization": stabilization,
        "dt": dt,
        "rtol": rtol,
        "atol": atol,
        "t_final": float(t_final),
        "joint_names": list(mech.joint_names),
        "model_digest": mech.digest(),
        "coordinate_names": list(mech.coordinate_names) if mech.nq == mech.nv else None,
        "configuration_names": list(mech.configuration_names),
        "velocity_names": list(mech.coordinate_names),
        "independent": [mech.coordinate_names[i] for i in mech.independent_idx_v],
        "repartitions": [],
    }
    if stab.accel_terms:
        info["baumgarte"] = list(solver_settings.baumgarte)
    if fallback is not None:
        info["backend_fallback"] = fallback
    cpu0 = time.process_time()
    control = StepControl(dt=dt, rtol=rtol, atol=atol)
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
                problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
            )
    except (SingularConfigurationError, SimulationError) as exc:
        if spec.backend == "compiled" and not len(recorder):
            # The compiled loop hands its samples over at the end only: the
            # reference loop recovers the motion up to the stop (its error,
            # with exc.trajectory, is raised instead).
            logger.info("%s: compiled run stopped (%s); re-running with numpy", mech.name, exc)
            simulate(
                mech,
                q0,
                v0,
                t_final,
                method=method,
                integrator=integrator,
                dt=None if not fixed else control.dt,
                rtol=None if fixed else rtol,
                atol=None if fixed else atol,
                stabilization=stabilization,
                tau=tau,
                t_eval=t_eval,
                settings=settings,
                solver_settings=original_solver_settings,
                progress=progress,
                backend="numpy",
            )
        # Nothing is lost: the caller gets the motion up to the stop (e.g. to animate it).
        if getattr(exc, "t", None) is None:  # raised outside a timed evaluation
            exc.t = float(recorder.series()["t"][-1]) if len(recorder) else 0.0
        info["stopped"] = {"t": exc.t, "reason": str(exc)}
        info["cpu_time"] = time.process_time() - cpu0
        info["evaluations"] = problem.n_evals
        exc.trajectory = recorder.trajectory(info) if len(recorder) else None
        raise
    info["cpu_time"] = time.process_time() - cpu0
    info["row_reselections"] = problem.reselections
    info["steps"] = steps
    info["evaluations"] = problem.n_evals
    info["branch_changes"] = recorder.branch_changes
    series = recorder.series()
    info["max_constraint_residual"] = float(np.max(series["res"], initial=0.0))
    info["energy_drift"] = energy_drift(series["e"], series["ke"])
    work = None if recorder.meter is None else series["w"]
    info["energy_balance"] = energy_balance(series["e"], series["ke"], work)
    report_limit_violations(mech, recorder, info, settings)  # warns; raises: stop_at_limits
    traj = recorder.trajectory(SimulationInfo.from_dict(info))
    if settings.energy_tol is not None:
        check_energy(traj, settings.energy_tol)
    logger.info(
        "%s: %d steps, %d evaluations, %.3f s CPU",
        mech.name,
        steps,
        problem.n_evals,
        info["cpu_time"],
    )
    return traj
