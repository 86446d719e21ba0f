"""The evaluation shared by every integrator: accelerations, partition, projection, output.

:class:`Problem` evaluates the right-hand side and tracks the coordinate
partition; :func:`project` is the seed's position/velocity projection;
:class:`Recorder` collects output samples with their residuals and energy.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
import scipy.linalg

from ..dynamics.base import get_method
from ..exceptions import ClosedChainError, SingularConfigurationError
from ..kinematics import AssemblySettings, compute_jacobian, partition_coordinates, solve_closure
from ..trajectory import Trajectory
from .settings import SimulationError

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)


class Problem:
    """Evaluates accelerations and tracks the partition; shared by every integrator."""

    def __init__(self, mech, method, tau, solver_settings, settings):
        self.mech = mech
        self.func = get_method(method)
        self.solver_settings = solver_settings
        self.settings = settings
        self.n_evals = 0
        self.lam = np.zeros(mech.nc)
        self.tau_input = tau  # as given: None, constant or callable (compiled loops)
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


def project(problem: Problem, q: np.ndarray, v: np.ndarray, t: float):
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


class Recorder:
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

    def extend(self, samples: dict) -> None:
        """Append samples computed elsewhere (the compiled loops), checked the same way.

        Args:
            samples: arrays ``t, res, vres, e, ke`` (n, 1) and ``q, v, a, lam`` (n, k).
        """
        res = np.asarray(samples["res"]).ravel()
        if res.size and not (np.all(np.isfinite(res)) and res.max() <= self.drift_limit):
            raise ClosedChainError("compiled loop returned samples beyond the drift limit")
        r = self.rows
        for key in ("t", "res", "vres", "e", "ke"):
            r[key].extend(np.asarray(samples[key]).ravel().tolist())
        for key in ("q", "v", "a", "lam"):
            r[key].extend(np.asarray(samples[key]))

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
