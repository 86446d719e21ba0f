r"""Time integration of closed-chain dynamics with drift control.

The index-1 DAE of the lesson (Problem 5; see the references),

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
    (minimum-norm, as in the lesson's Python program) and v onto J v = 0.
``"partitioning"``
    coordinate partitioning (Wehage & Haug 1982; the lesson's Sections 4 and 6): only
    the independent coordinates (q_I, v_I) are integrated; the dependent ones
    are solved exactly from phi(q) = 0 and J v = 0 at every evaluation, so there
    is no drift by construction. When J_D becomes ill-conditioned the
    partition is changed (re-partitioning) and integration restarts from the
    current state.

The lesson's own algorithm is ``integrator="semi-implicit", stabilization=
"projection"`` with ``SimulationSettings(projection_iters=2,
project_velocities=False)`` (see :func:`lesson_settings`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from .._locking import exclusive
from ..dynamics import DEFAULT_SETTINGS as DEFAULT_SOLVER_SETTINGS
from ..dynamics import SolverSettings
from ..dynamics.base import DEFAULT_METHOD
from ..trajectory import Trajectory
from . import builtin  # noqa: F401  (registers the built-in integrators and stabilizations)
from .batch import BatchResult, Rollout, simulate_batch
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
from .request import (
    BACKENDS,
    DEFAULT_ADAPTIVE_INTEGRATOR,
    DEFAULT_FIXED_INTEGRATOR,
    DEFAULT_INTEGRATOR,
    MIN_ATOL,
    MIN_RTOL,
    check_request,
    default_integrator,
)
from .run import check_energy, run_request
from .settings import (
    ADAPTIVE_TOLERANCES,
    DEFAULT_ENERGY_TOL,
    DEFAULT_SIMULATION_SETTINGS,
    SimulationError,
    SimulationSettings,
    TorqueInput,
    lesson_settings,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

__all__ = [
    "ADAPTIVE_TOLERANCES",
    "BACKENDS",
    "BatchResult",
    "COMPILED_INTEGRATORS",
    "DEFAULT_ADAPTIVE_INTEGRATOR",
    "DEFAULT_ENERGY_TOL",
    "DEFAULT_FIXED_INTEGRATOR",
    "DEFAULT_INTEGRATOR",
    "INTEGRATORS",
    "MIN_ATOL",
    "MIN_RTOL",
    "Rollout",
    "STABILIZATIONS",
    "IntegratorSpec",
    "SimulationError",
    "SimulationSettings",
    "StabilizationSpec",
    "StepControl",
    "TorqueInput",
    "check_energy",
    "default_integrator",
    "get_integrator",
    "get_stabilization",
    "register_integrator",
    "register_stabilization",
    "lesson_settings",
    "simulate",
    "simulate_batch",
]


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
        rtol: relative tolerance (adaptive integrators; default ``settings.rtol``, whose
            default None means the integrator's own: 1e-9 for rk43, else 1e-8).
        atol: absolute tolerance (adaptive integrators; default ``settings.atol``, whose
            default None means the integrator's own: 1e-10).
        stabilization: a name in :data:`STABILIZATIONS`; default: the
            integrator's ``default_stabilization`` (``"stage-projection"`` for
            the explicit fixed-step integrators, ``"mass-orthogonal"`` for
            ``"ali3p"``, ``"none"`` for adaptive ones).
        tau: generalized forces [N m or N]: None (zero), a constant array of
            shape (nv,), or a callable ``tau(t, q, v) -> (nv,)`` (actuators,
            external springs or dampers, a controller); the model's own joint
            springs, damping and armature act without it (:mod:`closedchain.passive`).
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
        SimulationError: non-finite state, integrator failure, drift beyond
            ``settings.drift_limit`` (``exc.trajectory`` as above), or a relative energy
            balance beyond ``settings.energy_tol`` (1e-2 by default; ``exc.trajectory``
            the whole run): an inaccurate run is not returned as a success.
    """
    request = check_request(
        mech,
        q0,
        v0,
        t_final,
        method=method,
        integrator=integrator,
        dt=dt,
        rtol=rtol,
        atol=atol,
        stabilization=stabilization,
        tau=tau,
        t_eval=t_eval,
        settings=settings,
        solver_settings=solver_settings,
        progress=progress,
        backend=backend,
    )
    return run_request(request)
