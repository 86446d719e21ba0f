"""Settings and the torque input of :func:`closedchain.simulate` (and its SimulationError)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

# Declared in closedchain.exceptions; importable from here as before.
from ..exceptions import SimulationError as SimulationError

TorqueInput = None | np.ndarray | Callable[[float, np.ndarray, np.ndarray], np.ndarray]

#: Default of ``SimulationSettings.energy_tol`` (and of the command line's ``--energy-tol``):
#: a run whose relative energy balance (the drift without tau, E - E0 - the work of tau
#: with it) exceeds 1 % raises SimulationError instead of returning as a success (the
#: 4-bar's default run drifts by 2e-9; explicit Euler at 1 ms by 0.23).
DEFAULT_ENERGY_TOL = 1e-2

#: Relative and absolute tolerances of an adaptive integrator that declares none of its own
#: (``IntegratorSpec.tolerances``), when ``SimulationSettings.rtol``/``atol`` are None.
ADAPTIVE_TOLERANCES = (1e-8, 1e-10)


@dataclass(frozen=True)
class SimulationSettings:
    """Settings of :func:`simulate`.

    Attributes:
        dt: default fixed step [s]; also the first trial step of ``"rk43"``.
        rtol: relative tolerance of the adaptive integrators when ``simulate`` gets no
            ``rtol``; None (default): the integrator's own (``IntegratorSpec.tolerances``:
            1e-9 for rk43), else 1e-8 (:data:`ADAPTIVE_TOLERANCES`).
        atol: absolute tolerance, likewise; None (default): the integrator's own (1e-10
            for rk43), else 1e-10.
        baumgarte_alpha: velocity gain alpha [1/s] (2 alpha J v).
        baumgarte_beta: position gain beta [1/s] (beta^2 phi).
        projection_tol: target max |phi| of the position projection [m or -].
        projection_iters: Gauss-Newton iterations of the position projection
            (stops earlier at ``projection_tol``).
        project_velocities: project v onto J v = 0 after each step.
        start_velocity_tol: largest max |J(q0) v0| accepted at the start, relative
            to max(1, max |v0|) [-]; beyond it simulate refuses v0 (an
            inconsistent start would be recorded as the motion's first sample).
        dependent_tol: max |phi| of the dependent-coordinate solve (partitioning).
        repartition_cond: re-partition when cond(J_D) exceeds this. The error
            control of the independent coordinates shrinks the steps well before
            J_D is near singular (coasting Agile Eye, DOP853 at 1e-9: from
            cond(J_D) = 10 on, 22 steps over 10 s with 100 here against 17 with
            10 and without stabilization).
        singular_cond: stop with SingularConfigurationError when the 2-norm
            condition number of the constraint Jacobian J at a step exceeds this
            (every stabilization of adaptive integrators; fixed-step ones with
            none, baumgarte, projection): near a singular
            configuration (assembly branches meet, e.g. a change point) the
            motion is not determined by the equations and the acceleration-level
            formulation loses accuracy without any error estimate noticing
            (measured on the 4-bar's change point: energy drift 1e-4 with
            DOP853 at rtol 1e-10, 6e-3 with rk4 at dt 1e-3). A step too coarse
            can jump across a singular point without seeing cond(J) this large.
        partition_singular_cond: stop with SingularConfigurationError when even
            the best-conditioned J_D (after re-partitioning) has a condition
            number above this (stabilization partitioning). Fixed-step
            partitioning steps across the 4-bar's change point (the continuation
            is the one Newton finds from the previous state; energy drift 2e-7
            with rk4 at dt 1e-3).
        singular_zone: ALI3-P keeps its step ends at least this many steps away
            from a singular position (a crossing of assembly branches), and farther
            (up to half a step) where J's rank indicator would be below
            sqrt(10 / ali3p_penalty) there (many loops: N-four-bar N = 40), a step
            estimated to end closer being taken with the next as 1.5 + 0.5 or
            0.5 + 1.5 steps (see
            ``closedchain.simulate.ali3p``); 0 turns this off.
        stage_singular_zone: rk4 with stage projection keeps its evaluation points
            (stages and step ends) at least this many steps away from a singular
            position: a step with a point estimated closer is retaken as two
            substeps of one or of two grid steps (see ``closedchain.simulate.fixed``;
            some split always reaches 0.3); 0 turns this off.
        check_limits: refuse a start q0 outside the joint limits (the URDF
            ``<limit>`` elements, and |q| <= ``closedchain.mechanism.COORDINATE_BOUND``
            for every 1-dof coordinate); False turns the first check off.
        energy_tol: raise SimulationError (with the whole trajectory in
            ``exc.trajectory``) at the end of a run whose relative energy balance
            (``Trajectory.energy_balance``: the energy drift without tau, E - E0 - the
            work of tau and damping with them) exceeds this: the integration was not
            accurate, whatever the closure says. Default :data:`DEFAULT_ENERGY_TOL`
            (1e-2, as the command line's ``--energy-tol``); None: no check (a run
            meant to be inaccurate, such as a work-precision sweep).
        drift_limit: raise SimulationError when max |phi| over every declared
            row exceeds this [m or -]: a trajectory never leaves the manifold
            unreported.
        dropped_row_tol: a row dropped as redundant open by more than this
            [m or -] (and by ``dropped_row_ratio`` times the kept rows'
            residual) at a step means the kept rows no longer describe the
            loop: they are re-selected (``info["row_reselections"]``).
        dropped_row_ratio: see ``dropped_row_tol``.
        open_row_tol: an open dropped row that no re-selection takes in stops
            the run with LoopClosureError above this [m or -].
        max_steps: largest number of fixed steps a run may take; more is
            refused before any work (dt far too small for t_final).
        max_outputs: largest number of output samples (``t_eval`` times) a
            run may keep; memory grows with them, not with the steps.
        ali3p_tol: the ALI3-P integrator's Newton iterations stop when the
            largest correction of the step's displacement is below this
            [rad or m] and either 1e-4 of it or no longer shrinking by half per
            iteration (the round-off floor): an error e left in the displacement
            is an error 2 e / h in the velocity, and it accumulates (N-four-bar,
            N = 1, 20 s at h = 0.25 ms: B0 error 4.7e-6 m when stopping at the
            first correction below 1e-10, 8.2e-7 m with the floor; Newton
            iterations per step 2.0 -> 2.1).
        ali3p_phi_tol: ... and when max |phi| at the iterate is below this [m or -]:
            a residual closure error left at a flat position is amplified by the
            next passage through it (measured on the N-four-bar: 1e-10 left,
            1e-7 after the third flat position, then Newton stalls).
        ali3p_max_iter: its Newton iteration cap per step (then SimulationError).
        ali3p_penalty: relative penalty rho of ALI3-P, h^2 alpha / 4 = rho tr(M) /
            tr(J^T J) (dimensionless). A row of relative singular value sigma is
            enforced by the iterations' multiplier update at about the rate
            1 / (1 + rho sigma^2) per iteration, so near a singular position
            (sigma ~ distance d) steps must not end within d ~ rho^-1/2: with
            rho = 1e9 Newton stalls at the N-four-bar's second flat position
            (dt 1 ms), with 1e11 it converges in two iterations per step on
            average, and the steps keep singular_zone away from the crossings
            (N = 5, dt 0.2 ms: a step ending 0.002 step before one took 27
            iterations and left the crank angle 2.7e-6 rad off; N = 5 then
            stalled at t = 6.59 s). The tangent leaves out the
            geometric stiffness d(J^T lambda)/dq of the constraint forces; adding
            it (measured, by finite differences) changed nothing at that step and
            sent the next ones off the branch (the tangent is then indefinite).
            Round-off of the factorization (about rho eps) is removed by the
            residual form of the iterations.
        stop_at_limits: a recorded sample with a coordinate outside its limits
            (the rules of the start check, ``Mechanism.limit_checks``: URDF
            ``<limit>`` unless ``check_limits`` is off, and the coordinate bound)
            ends the run with SimulationError naming the joint and
            the time (``exc.trajectory``: the samples before it); when False
            (default) the run goes on and each such joint is logged as a warning
            and listed in ``info.limit_violations``. Checked on the recorded
            samples (the output times): an excursion between two outputs is not
            seen.
    """

    dt: float = 1e-3
    rtol: float | None = None
    atol: float | None = None
    baumgarte_alpha: float = 10.0
    baumgarte_beta: float = 10.0
    projection_tol: float = 1e-13
    projection_iters: int = 10
    project_velocities: bool = True
    dependent_tol: float = 1e-13
    repartition_cond: float = 10.0
    singular_cond: float = 1e3
    partition_singular_cond: float = 1e4
    singular_zone: float = 0.04
    stage_singular_zone: float = 0.3
    check_limits: bool = True
    energy_tol: float | None = DEFAULT_ENERGY_TOL
    drift_limit: float = 1e-2
    dropped_row_tol: float = 1e-9
    dropped_row_ratio: float = 100.0
    open_row_tol: float = 1e-6
    max_steps: int = 100_000_000
    max_outputs: int = 10_000_000
    start_velocity_tol: float = 1e-6
    ali3p_tol: float = 1e-10
    ali3p_phi_tol: float = 1e-13
    ali3p_max_iter: int = 50
    ali3p_penalty: float = 1e11
    stop_at_limits: bool = False


#: The default settings of :func:`simulate`, shared (settings are frozen).
DEFAULT_SIMULATION_SETTINGS = SimulationSettings()


def lesson_settings() -> SimulationSettings:
    """Settings reproducing the lesson's Python program (two Newton steps, no velocity
    projection; the lesson is in the references).

    Use with ``integrator="semi-implicit", stabilization="projection"``. That
    program checks nothing but the KKT solve, so ``singular_cond`` is infinite and
    the energy is not checked (``energy_tol`` None): started from its crank angle
    (10 deg, open assembly) and driven by its crank torque (1 N m), the linkage
    passes its change point (theta2 = -180 deg) near step 600, which the default
    settings would stop at.
    """
    return SimulationSettings(
        projection_iters=2,
        projection_tol=0.0,
        project_velocities=False,
        singular_cond=math.inf,
        energy_tol=None,
    )
