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
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
import scipy.integrate
import scipy.linalg

from .dynamics import DEFAULT_SETTINGS as DEFAULT_SOLVER_SETTINGS
from .dynamics import SolverSettings
from .dynamics.base import METHODS, get_method
from .exceptions import ClosedChainError, SingularConfigurationError, UnknownChoiceError
from .kinematics import AssemblySettings, compute_jacobian, partition_coordinates, solve_closure
from .trajectory import Trajectory

if TYPE_CHECKING:
    from .mechanism import Mechanism

logger = logging.getLogger(__name__)

#: Fixed-step integrators (need ``dt``).
FIXED_STEP = ("euler", "semi-implicit", "rk4")
#: Adaptive integrators from scipy.integrate (use ``rtol``/``atol``, dense output).
ADAPTIVE = ("RK45", "DOP853", "Radau", "BDF", "LSODA")
INTEGRATORS = FIXED_STEP + ADAPTIVE
STABILIZATIONS = ("none", "baumgarte", "projection", "partitioning")
#: Methods that solve their own constraint equations (pinocchio.constraintDynamics)
#: and so cannot take the Baumgarte terms of the acceleration constraint.
_NO_BAUMGARTE = ("pinocchio",)

TorqueInput = None | np.ndarray | Callable[[float, np.ndarray, np.ndarray], np.ndarray]


class SimulationError(ClosedChainError):
    """A simulation failed: non-finite state, integrator failure or drift beyond the limit.

    Attributes:
        t: simulation time [s] at which it happened.
    """

    def __init__(self, message: str, t: float) -> None:
        super().__init__(message)
        self.t = t


@dataclass(frozen=True)
class SimulationSettings:
    """Settings of :func:`simulate`.

    Attributes:
        dt: default fixed step [s].
        rtol: default relative tolerance of adaptive integrators.
        atol: default absolute tolerance of adaptive integrators.
        baumgarte_alpha: velocity gain alpha [1/s] (2 alpha J v).
        baumgarte_beta: position gain beta [1/s] (beta^2 phi).
        projection_tol: target max |phi| of the position projection [m or -].
        projection_iters: Gauss-Newton iterations of the position projection
            (stops earlier at ``projection_tol``).
        project_velocities: project v onto J v = 0 after each step.
        dependent_tol: max |phi| of the dependent-coordinate solve (partitioning).
        repartition_cond: re-partition when cond(J_D) exceeds this.
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
        drift_limit: raise SimulationError when max |phi| exceeds this [m or -]:
            a trajectory never leaves the manifold unreported.
    """

    dt: float = 1e-3
    rtol: float = 1e-8
    atol: float = 1e-10
    baumgarte_alpha: float = 10.0
    baumgarte_beta: float = 10.0
    projection_tol: float = 1e-13
    projection_iters: int = 10
    project_velocities: bool = True
    dependent_tol: float = 1e-13
    repartition_cond: float = 100.0
    singular_cond: float = 1e3
    partition_singular_cond: float = 1e4
    drift_limit: float = 1e-2


def seed_settings() -> SimulationSettings:
    """Settings reproducing the seed's Python program (two Newton steps, no velocity projection).

    Use with ``integrator="semi-implicit", stabilization="projection"``. The
    seed's loop checks nothing but the KKT solve, so ``singular_cond`` is
    infinite: started from the seed's crank angle (10 deg, open assembly) and
    driven by its crank torque (1 N m), the linkage passes its change point
    (theta2 = -180 deg) near step 600, which the default settings would stop at.
    """
    return SimulationSettings(
        projection_iters=2,
        projection_tol=0.0,
        project_velocities=False,
        singular_cond=math.inf,
    )


class _Problem:
    """Evaluates accelerations and tracks the partition; shared by every integrator."""

    def __init__(self, mech, method, tau, solver_settings, settings):
        self.mech = mech
        self.func = get_method(method)
        self.solver_settings = solver_settings
        self.settings = settings
        self.n_evals = 0
        self.lam = np.zeros(mech.nc)
        if tau is None:
            zero = np.zeros(mech.nv)
            self.tau = lambda t, q, v: zero
        elif callable(tau):
            self.tau = tau
        else:
            const = mech.check_v(tau, "tau")
            self.tau = lambda t, q, v: const
        self.ind = np.array(mech.independent_idx_v)
        self.dep = np.array(mech.dependent_idx_v)
        self.asm = AssemblySettings(tol=settings.dependent_tol, max_iter=20)
        self._J_at: np.ndarray | None = None
        self._J: np.ndarray | None = None

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Return J(q), reusing the last one when q is the same (each step asks several
        times at one q: dependent solve, J_D checks, regularity check, projection)."""
        if self._J_at is None or not np.array_equal(q, self._J_at):
            self._J = compute_jacobian(self.mech, q)
            self._J_at = np.array(q)
        return self._J

    def accel(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        tau = np.asarray(self.tau(t, q, v), dtype=float)
        if tau.shape != (self.mech.nv,) or not np.all(np.isfinite(tau)):
            raise SimulationError(
                f"tau(t, q, v) returned {tau!r} at t = {t:.6g} s; expected finite shape "
                f"({self.mech.nv},)",
                t,
            )
        try:
            a, lam = self.func(self.mech, q, v, tau, self.solver_settings)
        except SingularConfigurationError as exc:
            raise SingularConfigurationError(
                f"at t = {t:.9g} s: {exc}", q=exc.q, condition_number=exc.condition_number, t=t
            ) from None
        self.n_evals += 1
        if not np.all(np.isfinite(a)):
            raise SimulationError(f"non-finite acceleration at t = {t:.9g} s, q = {q}", t)
        self.lam = lam
        return a

    # -- partitioning ---------------------------------------------------------
    def complete(self, q_guess: np.ndarray, v_ind: np.ndarray, t: float):
        """Solve q_D from phi = 0 (q_I held) and v_D from J v = 0; return (q, v)."""
        mech = self.mech
        try:
            q = solve_closure(mech.model, mech.data, mech.constraints, q_guess, self.dep, self.asm)
        except ClosedChainError as exc:
            raise SimulationError(
                f"at t = {t:.9g} s the dependent coordinates could not be solved: {exc}", t
            ) from None
        J = self.jacobian(q)
        JD, JI = J[:, self.dep], J[:, self.ind]
        v = np.zeros(mech.nv)
        v[self.ind] = v_ind
        v[self.dep] = -scipy.linalg.solve(JD, JI @ v_ind)
        return q, v

    def cond_JD(self, q: np.ndarray) -> float:
        return float(np.linalg.cond(self.jacobian(q)[:, self.dep]))

    def repartition(self, q: np.ndarray, t: float) -> bool:
        """Choose the best-conditioned J_D at q by pivoted QR of J (Wehage-Haug).

        Returns:
            True when the partition changed (integration restarts from the
            current state), False when the current one is already the best.

        Raises:
            SingularConfigurationError: even the chosen J_D has a condition
                number above ``settings.partition_singular_cond``.
        """
        J = self.jacobian(q)
        _, dep = partition_coordinates(J)
        cond = float(np.linalg.cond(J[:, dep]))
        if cond > self.settings.partition_singular_cond:
            raise SingularConfigurationError(
                f"{self.mech.name}: at t = {t:.9g} s no partition of the coordinates has a "
                f"regular J_D (condition number {cond:.3e} > partition_singular_cond "
                f"{self.settings.partition_singular_cond:.1e}): a singular configuration",
                q=np.array(q),
                condition_number=cond,
                t=t,
            )
        if np.array_equal(dep, self.dep):
            return False
        self.dep = dep
        self.ind = np.setdiff1d(np.arange(self.mech.nv), self.dep)
        logger.info(
            "%s: re-partitioned at t = %.9g s (cond(J_D) = %.3e); independent: %s",
            self.mech.name,
            t,
            cond,
            ", ".join(self.mech.coordinate_names[i] for i in self.ind),
        )
        return True

    def det_sign_JD(self, q: np.ndarray) -> float:
        """Return the sign of det(J_D) at q (0 when singular)."""
        return float(np.linalg.slogdet(self.jacobian(q)[:, self.dep])[0])

    def check_regular(self, q: np.ndarray, t: float) -> None:
        """Raise SingularConfigurationError when cond(J(q)) exceeds ``settings.singular_cond``."""
        if self.mech.nc == 0:
            return
        s = np.linalg.svd(self.jacobian(q), compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        if cond > self.settings.singular_cond:
            raise SingularConfigurationError(
                f"{self.mech.name}: at t = {t:.9g} s the constraint Jacobian is close to losing "
                f"rank (condition number {cond:.3e} > singular_cond "
                f"{self.settings.singular_cond:.1e}): a singular configuration, where the motion "
                "is not determined by the equations; a fixed-step integrator with "
                "stabilization='partitioning' can step across some (see SimulationSettings)",
                q=np.array(q),
                condition_number=cond,
                t=t,
            )


def _project(problem: _Problem, q: np.ndarray, v: np.ndarray, t: float):
    """Seed-style projection: Gauss-Newton on q (min-norm), then v onto J v = 0."""
    mech, s = problem.mech, problem.settings
    model, data, layer = mech.model, mech.data, mech.constraints
    phi = np.zeros(mech.nc)
    for _ in range(s.projection_iters):
        pin.forwardKinematics(model, data, q)
        layer.evaluate(model, data, phi=phi)
        if np.max(np.abs(phi), initial=0.0) <= s.projection_tol:
            break
        J = problem.jacobian(q)
        q = pin.integrate(model, q, np.linalg.lstsq(J, -phi, rcond=None)[0])
    if s.project_velocities:
        J = problem.jacobian(q)
        v = v - np.linalg.lstsq(J, J @ v, rcond=None)[0]
    return q, v


class _Recorder:
    """Collects output samples and their residuals and energy."""

    def __init__(self, mech: Mechanism, drift_limit: float, jacobian) -> None:
        self.mech = mech
        self.drift_limit = drift_limit
        self.jacobian = jacobian  # J(q), shared with the problem's memo
        self.rows: dict[str, list] = {
            k: [] for k in ("t", "q", "v", "a", "lam", "res", "vres", "e", "ke")
        }
        self._phi = np.zeros(mech.nc)

    def add(self, t, q, v, a, lam) -> None:
        mech = self.mech
        model, data = mech.model, mech.data
        pin.forwardKinematics(model, data, q)
        mech.constraints.evaluate(model, data, phi=self._phi)
        res = float(np.max(np.abs(self._phi), initial=0.0))
        if not math.isfinite(res) or res > self.drift_limit:
            raise SimulationError(
                f"{mech.name}: the state left the constraint manifold at t = {t:.9g} s "
                f"(max |phi| = {res:.3e} > drift_limit {self.drift_limit:.1e}); use a "
                "stabilization or a smaller step",
                t,
            )
        J = self.jacobian(q)
        vres = float(np.max(np.abs(J @ v), initial=0.0))
        kinetic = pin.computeKineticEnergy(model, data, q, v)
        energy = kinetic + pin.computePotentialEnergy(model, data, q)
        r = self.rows
        r["t"].append(t)
        r["q"].append(np.array(q))
        r["v"].append(np.array(v))
        r["a"].append(np.array(a))
        r["lam"].append(np.array(lam))
        r["res"].append(res)
        r["vres"].append(vres)
        r["e"].append(energy)
        r["ke"].append(kinetic)

    def trajectory(self, info: dict) -> Trajectory:
        r = self.rows
        nc = self.mech.nc
        return Trajectory(
            t=np.array(r["t"]),
            q=np.array(r["q"]).reshape(-1, self.mech.nq),
            v=np.array(r["v"]).reshape(-1, self.mech.nv),
            a=np.array(r["a"]).reshape(-1, self.mech.nv),
            lam=np.array(r["lam"]).reshape(-1, nc),
            constraint_residual=np.array(r["res"]),
            velocity_residual=np.array(r["vres"]),
            energy=np.array(r["e"]),
            kinetic_energy=np.array(r["ke"]),
            info=info,
        )


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
) -> Trajectory:
    """Integrate the constrained dynamics from (q0, v0) over [0, t_final].

    Args:
        mech: the mechanism.
        q0: initial configuration, shape (nq,), on phi = 0 (see :func:`assemble`).
        v0: initial velocity, shape (nv,), with J v0 = 0 (see :func:`project_velocity`).
        t_final: duration [s].
        method: forward-dynamics method (a name in ``closedchain.METHODS``).
        integrator: one of :data:`INTEGRATORS`.
        dt: fixed step [s] (fixed-step integrators; default ``settings.dt``).
        rtol: relative tolerance (adaptive integrators; default ``settings.rtol``).
        atol: absolute tolerance (adaptive integrators; default ``settings.atol``).
        stabilization: one of :data:`STABILIZATIONS`; default ``"projection"``
            for fixed-step integrators and ``"none"`` for adaptive ones.
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
    if integrator not in INTEGRATORS:
        raise UnknownChoiceError("integrator", integrator, INTEGRATORS)
    fixed = integrator in FIXED_STEP
    if stabilization is None:
        stabilization = "projection" if fixed else "none"
    if stabilization not in STABILIZATIONS:
        raise UnknownChoiceError("stabilization", stabilization, STABILIZATIONS)
    get_method(method)
    if stabilization == "baumgarte" and method in _NO_BAUMGARTE:
        raise ClosedChainError(
            f"method {method!r} solves its own constraint equations and cannot apply the "
            f"Baumgarte terms; use stabilization 'projection' or 'partitioning', or a method "
            f"among {', '.join(m for m in sorted(METHODS) if m not in _NO_BAUMGARTE)}"
        )
    q0 = mech.check_q(q0, "q0")
    v0 = mech.check_v(v0, "v0")
    if not (t_final > 0 and math.isfinite(t_final)):
        raise ClosedChainError(f"t_final must be a positive number of seconds, got {t_final}")
    if (not fixed or stabilization == "partitioning") and mech.nq != mech.nv:
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

    if stabilization == "baumgarte":
        gains = (settings.baumgarte_alpha, settings.baumgarte_beta)
        solver_settings = replace(solver_settings, baumgarte=gains)
    problem = _Problem(mech, method, tau, solver_settings, settings)
    recorder = _Recorder(mech, settings.drift_limit, problem.jacobian)
    info = {
        "mechanism": mech.name,
        "method": method,
        "integrator": integrator,
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
    if stabilization == "baumgarte":
        info["baumgarte"] = list(solver_settings.baumgarte)
    cpu0 = time.process_time()
    if fixed:
        steps = _run_fixed(
            problem,
            recorder,
            q0,
            v0,
            t_final,
            dt,
            integrator,
            stabilization,
            t_eval,
            progress,
            info,
        )
    else:
        steps = _run_adaptive(
            problem,
            recorder,
            q0,
            v0,
            t_final,
            rtol,
            atol,
            integrator,
            stabilization,
            t_eval,
            progress,
            info,
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


def _run_fixed(
    problem, recorder, q, v, t_final, dt, integrator, stabilization, t_eval, progress, info
) -> int:
    mech = problem.mech
    model = mech.model
    # Output times on the step grid: shorten dt so each output interval is whole steps.
    if t_eval is None:
        n_steps = int(math.ceil(t_final / dt - 1e-9))
        dt = t_final / n_steps
        out_steps = set(range(n_steps + 1))
    else:
        gaps = np.diff(np.concatenate([[0.0], t_eval]))
        per = [max(1, int(math.ceil(g / dt - 1e-9))) if g > 0 else 0 for g in gaps]
        # Uniform grid when outputs are uniform (the common case).
        h = min((g / p for g, p in zip(gaps, per, strict=True) if p), default=dt)
        n_steps = int(round(t_eval[-1] / h))
        dt = t_eval[-1] / n_steps
        out_steps = {int(round(te / dt)) for te in t_eval}
    info["dt"] = dt
    partition = stabilization == "partitioning"
    if partition:
        q, v = problem.complete(q, v[problem.ind], 0.0)
    t = 0.0
    a = problem.accel(t, q, v)
    if 0 in out_steps:
        recorder.add(t, q, v, a, problem.lam)

    def deriv(t, q, v):
        if partition:
            q, v = problem.complete(q, v[problem.ind], t)
        return v, problem.accel(t, q, v)

    for k in range(1, n_steps + 1):
        if integrator == "euler":
            q_new = pin.integrate(model, q, dt * v)
            v_new = v + dt * a
        elif integrator == "semi-implicit":
            v_new = v + dt * a
            q_new = pin.integrate(model, q, dt * v_new)
        else:  # rk4, stages on the configuration manifold through pin.integrate
            k1v, k1a = v, a
            k2v, k2a = deriv(t + dt / 2, pin.integrate(model, q, dt / 2 * k1v), v + dt / 2 * k1a)
            k3v, k3a = deriv(t + dt / 2, pin.integrate(model, q, dt / 2 * k2v), v + dt / 2 * k2a)
            k4v, k4a = deriv(t + dt, pin.integrate(model, q, dt * k3v), v + dt * k3a)
            q_new = pin.integrate(model, q, dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))
            v_new = v + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a)
        t = k * dt
        if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
            raise SimulationError(f"{mech.name}: non-finite state at t = {t:.9g} s", t)
        if stabilization == "projection":
            q_new, v_new = _project(problem, q_new, v_new, t)
        elif partition:
            q_new, v_new = problem.complete(q_new, v_new[problem.ind], t)
            if problem.cond_JD(q_new) > problem.settings.repartition_cond and problem.repartition(
                q_new, t
            ):
                info["repartitions"].append([t, [mech.coordinate_names[i] for i in problem.ind]])
        if not partition:
            problem.check_regular(q_new, t)
        q, v = q_new, v_new
        a = problem.accel(t, q, v)
        if k in out_steps:
            recorder.add(t, q, v, a, problem.lam)
        if progress is not None:
            progress(t)
    return n_steps


def _run_adaptive(
    problem,
    recorder,
    q0,
    v0,
    t_final,
    rtol,
    atol,
    integrator,
    stabilization,
    t_eval,
    progress,
    info,
) -> int:
    mech = problem.mech
    nv = mech.nv
    partition = stabilization == "partitioning"
    solver_cls = getattr(scipy.integrate, integrator)
    state = {"q": np.array(q0)}  # warm start of the dependent solve

    if partition:
        q, v = problem.complete(q0, v0[problem.ind], 0.0)

        def pack(q, v):
            return np.concatenate([q[problem.ind], v[problem.ind]])

        def unpack(y, t):
            guess = state["q"].copy()
            m = len(problem.ind)
            guess[problem.ind] = y[:m]
            q, v = problem.complete(guess, y[m:], t)
            return q, v
    else:
        q, v = np.array(q0), np.array(v0)

        def pack(q, v):
            return np.concatenate([q, v])

        def unpack(y, t):
            return y[:nv], y[nv:]

    def fun(t, y):
        q, v = unpack(y, t)
        a = problem.accel(t, q, v)
        if partition:
            state["q"] = q
            return np.concatenate([v[problem.ind], a[problem.ind]])
        return np.concatenate([v, a])

    def output(t, y):
        q, v = unpack(y, t)
        a = problem.accel(t, q, v)
        recorder.add(t, q, v, a, problem.lam)

    t0 = 0.0
    y = pack(q, v)
    pending = list(t_eval) if t_eval is not None else None
    if pending is None or (pending and pending[0] <= 0.0):
        output(0.0, y)
        if pending:
            pending.pop(0)
    steps = 0
    first_step = None
    while t0 < t_final:
        solver = solver_cls(
            fun,
            t0,
            y,
            t_final,
            rtol=rtol,
            atol=atol,
            **({"first_step": first_step} if first_step else {}),
        )
        restart = False
        while solver.status == "running":
            message = solver.step()
            if solver.status == "failed":
                raise SimulationError(
                    f"{mech.name}: integrator {integrator} failed at t = {solver.t:.9g} s: "
                    f"{message}",
                    solver.t,
                )
            steps += 1
            t_new = solver.t
            if pending is not None:
                if pending and pending[0] <= t_new:
                    sol = solver.dense_output()
                    while pending and pending[0] <= t_new * (1 + 1e-15):
                        output(pending[0], sol(pending[0]))
                        pending.pop(0)
            if stabilization == "projection":
                q, v = _project(problem, solver.y[:nv], solver.y[nv:], t_new)
                solver.y = np.concatenate([q, v])
                if hasattr(solver, "f"):
                    solver.f = fun(t_new, solver.y)
            # Every stabilization, partitioning included: near a branch point of
            # q_D(q_I) the error estimate is fooled and the dependent solve can jump
            # to another assembly branch (measured on the 4-bar's change point with
            # method "schur": energy drift 0.9 with max |phi| 1e-13).
            problem.check_regular(unpack(solver.y, t_new)[0], t_new)
            if pending is None:
                output(t_new, solver.y)
            if progress is not None:
                progress(t_new)
            if partition:
                q, v = unpack(solver.y, t_new)
                # det(J_D) changes sign only through a singular configuration: the
                # step crossed one, where the error estimate cannot be trusted and the
                # dependent solve may have jumped to another assembly branch.
                sign = problem.det_sign_JD(q)
                if sign * state.setdefault("sign", sign) <= 0.0:
                    raise SingularConfigurationError(
                        f"{mech.name}: at t = {t_new:.9g} s det(J_D) changed sign within the "
                        f"last step (condition number of J_D {problem.cond_JD(q):.3e} at its "
                        "end): the motion crossed a singular configuration, which adaptive "
                        "partitioning cannot follow; use a fixed-step integrator",
                        q=np.array(q),
                        condition_number=problem.cond_JD(q),
                        t=t_new,
                    )
                if (
                    problem.cond_JD(q) > problem.settings.repartition_cond
                    and t_new < t_final
                    and problem.repartition(q, t_new)
                ):
                    info["repartitions"].append(
                        [t_new, [mech.coordinate_names[i] for i in problem.ind]]
                    )
                    state["q"] = q
                    state["sign"] = problem.det_sign_JD(q)
                    t0, y = t_new, pack(q, v)
                    first_step = getattr(solver, "h_abs", None) or None
                    restart = True
                    break
        if not restart:
            break
    return steps
