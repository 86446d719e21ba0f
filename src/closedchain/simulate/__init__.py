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

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..dynamics import DEFAULT_SETTINGS as DEFAULT_SOLVER_SETTINGS
from ..dynamics import SolverSettings
from ..dynamics.base import METHOD_CAPABILITIES, METHODS, get_method
from ..exceptions import ClosedChainError, UnknownChoiceError
from ..trajectory import Trajectory
from .problem import Problem, Recorder
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
from .settings import SimulationError, SimulationSettings, TorqueInput, seed_settings

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)

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


def _select_backend(
    spec: IntegratorSpec, backend: str, stabilization: str, method: str
) -> IntegratorSpec:
    """Return the integrator entry that runs the request (see ``simulate``'s ``backend``)."""
    if backend not in BACKENDS:
        raise UnknownChoiceError("backend", backend, BACKENDS)
    if backend == "numpy":
        return spec
    cspec = COMPILED_INTEGRATORS.get(spec.name)
    get_method(method)
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
        return cspec
    if backend == "compiled":
        raise ClosedChainError("backend='compiled' cannot run this request: " + "; ".join(reasons))
    return spec


def simulate(
    mech: Mechanism,
    q0: np.ndarray,
    v0: np.ndarray,
    t_final: float,
    *,
    method: str = "kkt",
    integrator: str = "DOP853",
    dt: float | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    stabilization: str | None = None,
    tau: TorqueInput = None,
    t_eval: np.ndarray | None = None,
    settings: SimulationSettings | None = None,
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
        integrator: a name in :data:`INTEGRATORS`.
        dt: fixed step [s] (fixed-step integrators; default ``settings.dt``).
        rtol: relative tolerance (adaptive integrators; default ``settings.rtol``).
        atol: absolute tolerance (adaptive integrators; default ``settings.atol``).
        stabilization: a name in :data:`STABILIZATIONS`; default: the
            integrator's ``default_stabilization`` (``"projection"`` for
            fixed-step integrators, ``"none"`` for adaptive ones).
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
            (message and attributes give the time and condition number).
        SimulationError: non-finite state, integrator failure, or drift
            beyond ``settings.drift_limit``.
    """
    settings = settings or SimulationSettings()
    spec = get_integrator(integrator)
    fixed = spec.kind == "fixed"
    if stabilization is None:
        stabilization = spec.default_stabilization
    spec = _select_backend(spec, backend, stabilization, method)
    stab = get_stabilization(stabilization)
    if stabilization not in spec.stabilizations:
        raise ClosedChainError(
            f"integrator {integrator!r} does not support stabilization {stabilization!r}; "
            f"valid choices: {', '.join(spec.stabilizations)}"
        )
    get_method(method)
    if stab.accel_terms and not METHOD_CAPABILITIES[method].baumgarte:
        with_terms = [m for m in sorted(METHODS) if METHOD_CAPABILITIES[m].baumgarte]
        raise ClosedChainError(
            f"method {method!r} solves its own constraint equations and cannot apply the "
            "Baumgarte terms; use stabilization 'projection' or 'partitioning', or a "
            f"method among {', '.join(with_terms)}"
        )
    q0 = mech.check_q(q0, "q0")
    v0 = mech.check_v(v0, "v0")
    if not (t_final > 0 and math.isfinite(t_final)):
        raise ClosedChainError(f"t_final must be a positive number of seconds, got {t_final}")
    if (spec.vector_state or stab.partitions) and mech.nq != mech.nv:
        raise ClosedChainError(
            f"integrator {integrator!r} with stabilization {stabilization!r} integrates q as a "
            f"vector and needs nq == nv (this mechanism has nq={mech.nq}, nv={mech.nv}); use "
            "a fixed-step integrator (euler, semi-implicit, rk4) with projection"
        )
    if t_eval is not None:
        t_eval = np.asarray(t_eval, dtype=float)
        if (
            t_eval.ndim != 1
            or np.any(np.diff(t_eval) <= 0)
            or t_eval[0] < 0
            or (t_eval[-1] > t_final * (1 + 1e-12))
        ):
            raise ClosedChainError("t_eval must be increasing times within [0, t_final]")
    if fixed:
        dt = settings.dt if dt is None else float(dt)
        if not dt > 0:
            raise ClosedChainError(f"dt must be positive, got {dt}")
    else:
        rtol = settings.rtol if rtol is None else float(rtol)
        atol = settings.atol if atol is None else float(atol)

    if stab.accel_terms:
        gains = (settings.baumgarte_alpha, settings.baumgarte_beta)
        solver_settings = replace(solver_settings, baumgarte=gains)
    problem = Problem(mech, method, tau, solver_settings, settings)
    recorder = Recorder(mech, settings.drift_limit, problem.jacobian)
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
        "coordinate_names": list(mech.coordinate_names) if mech.nq == mech.nv else None,
        "configuration_names": list(mech.configuration_names),
        "velocity_names": list(mech.coordinate_names),
        "independent": [mech.coordinate_names[i] for i in mech.independent_idx_v],
        "repartitions": [],
    }
    if stab.accel_terms:
        info["baumgarte"] = list(solver_settings.baumgarte)
    cpu0 = time.process_time()
    control = StepControl(dt=dt, rtol=rtol, atol=atol)
    steps = spec.run(
        problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
    )
    info["cpu_time"] = time.process_time() - cpu0
    info["steps"] = steps
    info["evaluations"] = problem.n_evals
    traj = recorder.trajectory(info)
    info["max_constraint_residual"] = traj.max_constraint_residual
    info["energy_drift"] = traj.energy_drift
    logger.info(
        "%s: %d steps, %d evaluations, %.3f s CPU",
        mech.name,
        steps,
        problem.n_evals,
        info["cpu_time"],
    )
    return traj
