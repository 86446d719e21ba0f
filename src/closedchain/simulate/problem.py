"""The evaluation shared by every integrator: accelerations, partition, projection, output.

:class:`Problem` evaluates the right-hand side and tracks the coordinate
partition; :func:`project` is the seed's position/velocity projection;
:class:`Recorder` collects output samples with their residuals and energy.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin
import scipy.linalg

from .. import compiled
from .._arrays import same_array
from ..closure import RowCheckSettings
from ..dynamics.augmented_lagrangian import (
    NormalSolver,
    PenalizedSolver,
    penalized_solver,
    solve_augmented_lagrangian,
)
from ..dynamics.base import (
    METHOD_CAPABILITIES,
    METHODS,
    get_method,
    mass_matrix,
    position_terms,
)
from ..exceptions import ClosedChainError, SingularConfigurationError
from ..kinematics import AssemblySettings, compute_jacobian, solve_closure
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
        self.method = method
        #: The configuration passes singular positions: no stop on cond(J) (set by
        #: simulate from the method's, integrator's and stabilization's capabilities).
        self.singular_robust = False
        self.solver_settings = solver_settings
        self._unpolished = dataclasses.replace(solver_settings, al_polish=False)
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
        self._start_J: np.ndarray | None = None  # J(q0) of check_start (compiled rows)
        self._normal = None
        self._normal_layer = None
        self._J: np.ndarray | None = None
        #: Row re-selections made during the run: [t, kept row labels, reason].
        self.reselections: list[list] = []
        self.row_check = RowCheckSettings(
            dropped_tol=mech.closure.dropped_row_tol(settings.dropped_row_tol),
            dropped_ratio=settings.dropped_row_ratio,
            cond_max=settings.singular_cond,
            open_tol=settings.open_row_tol,
        )

    def normal_solver(self):
        """Return the banded normal-equation solver of the kept rows, or None when they
        do not couple in a narrow band (then projections use dense ``lstsq``)."""
        layer = self.mech.constraints
        if self._normal_layer is not layer:  # first call, or rows re-selected
            solver = NormalSolver(self.mech, layer) if layer.nc else None
            self._normal = solver if solver is not None and solver.banded else None
            self._normal_layer = layer
        return self._normal

    def penalized_solver(self) -> PenalizedSolver:
        """Return the factorization of M + alpha J^T J for the kept rows: the
        augmented-Lagrangian method's (banded where it is), shared with it."""
        return penalized_solver(self.mech)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Return J(q), reusing the last one when q is the same (each step asks several
        times at one q: dependent solve, J_D checks, regularity check, projection)."""
        if not same_array(q, self._J_at):
            self._J = compute_jacobian(self.mech, q)
            self._J_at = np.array(q)
        return self._J

    def residual_and_jacobian(self, q: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Fill phi(q) of the kept rows and return J(q), in one pass over the loops (the
        Jacobian memo of :meth:`jacobian` then holds it)."""
        ws = position_terms(self.mech, q, phi)
        self._J = ws.J.copy()
        self._J_at = np.array(q)
        return self._J

    def torque(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return tau(t, q, v), shape (nv,), or raise SimulationError when it is malformed."""
        tau = np.asarray(self.tau(t, q, v), dtype=float)
        if tau.shape != (self.mech.nv,) or not np.all(np.isfinite(tau)):
            raise SimulationError(
                f"tau(t, q, v) returned {tau!r} at t = {t:.6g} s; expected finite shape "
                f"({self.mech.nv},)",
                t,
            )
        return tau

    def accel(
        self, t: float, q: np.ndarray, v: np.ndarray, *, multipliers: bool = True
    ) -> np.ndarray:
        """Return the accelerations at (t, q, v), shape (nv,); :attr:`lam` holds the
        multipliers, polished only with ``multipliers`` (``SolverSettings.al_polish``:
        off for evaluations whose multipliers nobody reads, such as rk4's inner stages)."""
        tau = self.torque(t, q, v)
        settings = self.solver_settings
        if not multipliers and settings.al_polish:
            settings = self._unpolished
        try:
            a, lam = self.func(self.mech, q, v, tau, settings)
        except SingularConfigurationError as exc:
            raise exc.at_time(t, hint=passing_hint()) from None
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
        """Return cond(J_D) at q (1 when there are no dependent coordinates)."""
        if not len(self.dep):
            return 1.0
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
        _, dep, cond = self.mech.closure.partition_at(J)
        if cond > self.settings.partition_singular_cond:
            raise SingularConfigurationError.build(
                self.mech.name,
                "the best-conditioned J_D of any partition of the coordinates",
                q=q,
                cond=cond,
                bound=self.settings.partition_singular_cond,
                bound_name="partition_singular_cond",
                hint=f"no partition has a regular J_D: a singular configuration; {passing_hint()}",
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

    def check_rows(
        self,
        q: np.ndarray,
        t: float,
        kept_cond: float | None = None,
        phi: np.ndarray | None = None,
    ) -> bool:
        """Check every declared row at q; re-select the kept rows when they stop describing
        the loops (:meth:`LoopClosure.check_rows`; ``phi``: the declared rows' phi(q) if
        known). Returns True when re-selected."""
        mech = self.mech
        if self.singular_robust:
            kept_cond = None  # rank loss is passed through, not re-selected around
        try:
            changed = mech.closure.check_rows(
                mech.model,
                mech.data,
                q,
                t=t,
                kept_cond=kept_cond,
                settings=self.row_check,
                phi=phi,
            )
        except SingularConfigurationError as exc:
            raise exc.with_hint(passing_hint(), t=t) from None
        if not changed:
            return False
        self._J_at = None  # the memo holds the old rows
        self._start_J = None
        self.reselections.append(
            [t, list(mech.closure.selection.kept), mech.closure.selection.reason]
        )
        if self.dep.size and self.cond_JD(q) > self.settings.repartition_cond:
            self.repartition(q, t)
        return True

    def check_start(self, q0: np.ndarray, compiled_rows: bool = False) -> None:
        """Check every declared row at the initial configuration (re-select if needed).

        Args:
            compiled_rows: evaluate phi and J in the compiled core
                (:func:`closedchain.compiled.declared_rows`: the same rows, to round-off,
                in microseconds) instead of the numpy layer; :meth:`start_jacobian` then
                returns that J. For the compiled backend, whose loop evaluates them so.
        """
        mech = self.mech
        if mech.nc == 0:
            return
        phi = None
        if compiled_rows:
            phi, J_declared = compiled.declared_rows(mech, q0)
            self._start_J = J_declared[list(mech.selected_rows)]
        kept_cond = None
        # The kept rows' condition number matters only where check_rows reads it: rows
        # were dropped (LoopClosure.check_rows) and rank loss is not passed through.
        if not self.singular_robust and mech.declared.nc != mech.nc:
            s = np.linalg.svd(self.start_jacobian(q0), compute_uv=False)
            kept_cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        self.check_rows(q0, 0.0, kept_cond=kept_cond, phi=phi)

    def start_jacobian(self, q0: np.ndarray) -> np.ndarray:
        """Return J(q0) of the kept rows: :meth:`check_start`'s compiled one when it made
        one (and kept the rows), else :meth:`jacobian`'s."""
        if self._start_J is not None:
            return self._start_J
        return self.jacobian(q0)

    def check_regular(self, q: np.ndarray, t: float, phi: np.ndarray | None = None) -> None:
        """Raise SingularConfigurationError when cond(J(q)) exceeds ``settings.singular_cond``.

        Every declared row is checked first (:meth:`check_rows`; ``phi``: the declared
        rows' phi(q) if known): a kept set that degenerates where the mechanism does
        not is re-selected, not reported singular.
        When :attr:`singular_robust` (a singular-robust method with stage
        projection, or an index-3 integrator such as ALI3-P) only the dropped
        rows are checked: rank loss is passed through, never reported.
        """
        if self.mech.nc == 0:
            return
        if self.singular_robust:
            self.check_rows(q, t, phi=phi)
            return
        s = np.linalg.svd(self.jacobian(q), compute_uv=False)
        cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        if self.check_rows(q, t, kept_cond=cond, phi=phi):
            s = np.linalg.svd(self.jacobian(q), compute_uv=False)
            cond = float(s[0] / s[-1]) if s[-1] > 0 else math.inf
        if cond > self.settings.singular_cond:
            raise SingularConfigurationError.build(
                self.mech.name,
                "the constraint Jacobian",
                q=q,
                cond=cond,
                bound=self.settings.singular_cond,
                bound_name="singular_cond",
                state="is close to losing rank",
                hint="a singular configuration, where the motion is not determined by the "
                f"equations and method {self.method!r} loses accuracy without any error "
                f"estimate noticing; {passing_hint()}",
                t=t,
            )


def passing_hint() -> str:
    """Name the configurations that pass singular positions (from the registries' capabilities)."""
    from .registry import INTEGRATORS, STABILIZATIONS

    methods = [m for m in sorted(METHODS) if METHOD_CAPABILITIES[m].singular_robust]
    integrators = [n for n, spec in INTEGRATORS.items() if spec.singular_robust]
    if not methods:
        return "no registered method passes singular positions"
    stages = [n for n, st in STABILIZATIONS.items() if st.projects_stages]
    text = f"to pass singular positions use method={methods[0]!r}"
    if stages:
        text += f" with stabilization={stages[0]!r} (and a fixed-step integrator)"
    if integrators:
        text += f", or integrator={integrators[0]!r}"
    if len(methods) > 1:
        text += f"; methods that pass them: {', '.join(methods)}"
    return text


def project(
    problem: Problem, q: np.ndarray, v: np.ndarray, t: float, *, mass_orthogonal: bool = False
):
    """Seed-style projection: Gauss-Newton on q (min-norm), then v onto J v = 0.

    The minimum-norm corrections are ``lstsq`` solves, or, when the rows couple in a
    narrow band (many loops in a chain: :class:`~closedchain.dynamics.augmented_lagrangian.
    NormalSolver`), J^T x with banded regularized normal equations (J J^T + eps I) x = r:
    cost linear in the number of loops instead of a dense SVD.

    With ``mass_orthogonal`` (the stage projection) v is projected in the metric of M
    instead: v+ = argmin (v+ - v)^T M (v+ - v) subject to J v+ = 0, by the
    augmented-Lagrangian iteration on P = M + alpha J^T J (the acceleration solve with
    right-hand side M v and gamma = 0, as ALI3-P's projections): the kinetic energy
    changes only to second order in the correction, and a row that J nearly loses (near
    a singular position) is enforced at the rate 1 / (1 + rho sigma^2) per iteration
    instead of amplifying the position residual by 1 / sigma^2. Only a run that passes
    singular positions (``problem.singular_robust``: a singular-robust method with stage
    projection) projects so; the other methods stop at singular positions, keep the
    minimum-norm correction and need no M + alpha J^T J (which is indefinite for, e.g., a
    1000-link chain, whose kkt runs it would refuse).
    """
    mech, s = problem.mech, problem.settings
    model = mech.model
    normal = problem.normal_solver()

    def min_norm(J: np.ndarray, r: np.ndarray) -> np.ndarray:
        if normal is None:
            return np.linalg.lstsq(J, r, rcond=None)[0]
        return J.T @ normal.solve(J, r)

    phi = np.zeros(mech.nc)
    J = None
    for _ in range(s.projection_iters):
        J = problem.residual_and_jacobian(q, phi)  # J is needed at the last q too
        if np.max(np.abs(phi), initial=0.0) <= s.projection_tol:
            break
        q = pin.integrate(model, q, min_norm(J, -phi))
        J = None
    if s.project_velocities:
        if J is None:  # the iterations ran out (J of the last q not evaluated)
            J = problem.residual_and_jacobian(q, phi)
        if mass_orthogonal and problem.singular_robust and mech.nc:
            # M at q; the accelerations that follow at this q reuse M, J and P's factor.
            M = mass_matrix(mech, q).M
            ss = problem.solver_settings
            solver = problem.penalized_solver()
            alpha = solver.factor_relative(M, J, ss.al_penalty, mech, q)
            # From v itself (a0): the first iterate is the same, but as a correction of v
            # (small: J v is small here), whose round-off of the badly conditioned P
            # (about rho eps of the correction) is far below that of a solve from
            # scratch: two iterations instead of four on the N-four-bar.
            v, _, _ = solve_augmented_lagrangian(
                solver,
                M,
                J,
                M @ v,
                np.zeros(mech.nc),
                alpha,
                tol=ss.al_tol,
                max_iter=ss.al_max_iter,
                polish=False,
                a0=v,
            )
        else:
            v = v - min_norm(J, J @ v)
    return q, v


class Recorder:
    """Collects output samples and their residuals and energy."""

    #: Per-sample series: t, res, vres, e, ke scalars; q, v, a, lam vectors.
    _SERIES = ("t", "q", "v", "a", "lam", "res", "vres", "e", "ke")

    def __init__(self, mech: Mechanism, drift_limit: float, jacobian) -> None:
        self.mech = mech
        self.drift_limit = drift_limit
        self.jacobian = jacobian  # J(q), shared with the problem's memo
        #: Samples of :meth:`add` not yet moved into :attr:`_blocks` (one entry per sample).
        self.rows: dict[str, list] = {k: [] for k in self._SERIES}
        self.rows["branch"], self.rows["branch_t"] = [], []
        #: Recorded segments in order, each a dict of arrays with one row per sample:
        #: :meth:`extend`'s blocks as given (no per-sample Python objects), :meth:`add`'s
        #: rows stacked when a block follows or at :meth:`trajectory`.
        self._blocks: list[dict[str, np.ndarray]] = []
        self._n = 0
        self._phi = np.zeros(mech.declared.nc)
        self.dep = np.array(mech.dependent_idx_v, dtype=int)
        #: Branch changes [t_before, t_after, from, to] (see Trajectory.branch).
        self.branch_changes: list[list[float]] = []

    def declared_phi(self, q: np.ndarray) -> np.ndarray:
        """Return phi(q) of every declared row (a buffer of the recorder, overwritten by
        the next call). Leaves ``mech.data``'s joint placements at q (the loop frames'
        ``oMf`` too unless a batched layer reused the kept rows' placements at q)."""
        mech = self.mech
        pin.forwardKinematics(mech.model, mech.data, q)
        # q: a batched layer reuses the frame placements of the kept rows' evaluation at q.
        mech.declared.evaluate(mech.model, mech.data, phi=self._phi, q=q)
        return self._phi

    def declared_residual(self, t: float, q: np.ndarray, phi: np.ndarray | None = None) -> float:
        """Return max |phi| over every declared row at q, or raise beyond ``drift_limit``.

        Dropped rows included: a loop is never reported closed while one of its
        rows is open. ``phi``: :meth:`declared_phi` at q if known.
        """
        mech = self.mech
        if phi is None:
            phi = self.declared_phi(q)
        res = float(np.max(np.abs(phi), initial=0.0))
        if not math.isfinite(res) or res > self.drift_limit:
            label, _ = mech.closure.worst_row(np.nan_to_num(phi, nan=np.inf))
            raise SimulationError(
                f"{mech.name}: the state left the constraint manifold at t = {t:.9g} s "
                f"(max |phi| = {res:.3e} > drift_limit {self.drift_limit:.1e}, row {label}); "
                "use a stabilization or a smaller step",
                t,
            )
        return res

    def add(self, t, q, v, a, lam) -> None:
        mech = self.mech
        model, data = mech.model, mech.data
        res = self.declared_residual(t, q)
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
        self._n += 1
        self._add_branch(t, J)

    def __len__(self) -> int:
        """Number of samples recorded."""
        return self._n

    def _widths(self) -> dict[str, int]:
        m = self.mech
        return {"q": m.nq, "v": m.nv, "a": m.nv, "lam": m.nc}

    def _flush(self) -> None:
        """Move the pending rows of :meth:`add` into one block (in recording order)."""
        r = self.rows
        if not r["t"]:
            return
        widths = self._widths()
        n = len(r["t"])
        block = {}
        for key in self._SERIES:
            if key in widths:
                # n rows, not -1: a mechanism without loops has lam of width 0.
                block[key] = np.array(r[key], dtype=float).reshape(n, widths[key])
            else:
                block[key] = np.array(r[key], dtype=float)
            r[key] = []
        self._blocks.append(block)

    def _add_branch(self, t: float, J: np.ndarray) -> None:
        """Record the sign of det(J_D) at the sample just added (time t, Jacobian J)."""
        mech = self.mech
        if mech.nc and len(self.dep) == mech.nc:
            # Sign of det(J_D): flips only through a singular J_D (assembly branch).
            self._record_branch(t, float(np.linalg.slogdet(J[:, self.dep])[0]))

    def _record_branch(self, t: float, sign: float) -> None:
        r = self.rows
        if r["branch"] and sign != r["branch"][-1]:
            self.branch_changes.append([r["branch_t"][-1], t, r["branch"][-1], sign])
        r["branch"].append(sign)
        r["branch_t"].append(t)

    def extend(
        self, samples: dict, jacobian: Callable[[np.ndarray], np.ndarray] | None = None
    ) -> None:
        """Append samples computed elsewhere (the compiled loops).

        The compiled loop has checked them as :meth:`add` does: ``res`` is max
        |phi| over every declared row (dropped ones included), within
        ``drift_limit`` at every step, not only at the outputs.

        Args:
            samples: arrays ``t, res, vres, e, ke`` (n, 1) and ``q, v, a, lam`` (n, k);
                ``branch`` (n, 1), the sign of det(J_D) at each sample, when the
                compiled loop recorded it.
            jacobian: J(q) of the kept rows for the branch series when ``branch`` is
                absent (default: the numpy layer's).
        """
        self._flush()
        widths = self._widths()
        times = np.asarray(samples["t"], dtype=float).ravel()
        if not len(times):
            return
        block = {}
        for key in self._SERIES:  # C order, as the rows of add (the core's are column-major)
            a = np.ascontiguousarray(samples[key], dtype=float)
            # len(times) rows, not -1: a mechanism without loops has lam of width 0.
            block[key] = a.reshape(len(times), widths[key]) if key in widths else a.ravel()
        self._blocks.append(block)
        self._n += len(times)
        if self.mech.nc and len(self.dep) == self.mech.nc:  # the branch series, as in add
            if "branch" in samples:
                signs = np.asarray(samples["branch"], dtype=float).ravel()
            else:
                qs = np.asarray(samples["q"], dtype=float).reshape(-1, self.mech.nq)
                jac = jacobian or self.jacobian
                signs = np.linalg.slogdet(np.stack([jac(q)[:, self.dep] for q in qs]))[0]
            self._record_branches(times, signs)

    def _record_branches(self, times: np.ndarray, signs: np.ndarray) -> None:
        """:meth:`_record_branch` for arrays of samples (times and signs, shape (n,))."""
        r = self.rows
        # prev[i - off] precedes sample i (off = 1 when the series starts here).
        prev = np.concatenate([r["branch"][-1:], signs[:-1]])
        prev_t = np.concatenate([r["branch_t"][-1:], times[:-1]])
        off = len(signs) - len(prev)
        for i in np.flatnonzero(signs[off:] != prev) + off:
            self.branch_changes.append(
                [float(prev_t[i - off]), float(times[i]), float(prev[i - off]), float(signs[i])]
            )
        r["branch"].extend(signs.tolist())
        r["branch_t"].extend(times.tolist())

    def series(self) -> dict[str, np.ndarray]:
        """Return every recorded series as one array (one row per sample, in order)."""
        self._flush()
        widths = self._widths()
        blocks = self._blocks
        out = {}
        for key in self._SERIES:
            if len(blocks) == 1:
                out[key] = blocks[0][key]
            elif blocks:
                out[key] = np.concatenate([b[key] for b in blocks])
            else:
                out[key] = np.zeros((0, widths[key]) if key in widths else 0)
        if len(blocks) > 1:
            self._blocks = [out]  # later calls reuse the concatenation
        return out

    def trajectory(self, info) -> Trajectory:
        """Return the recorded samples as a Trajectory with ``info`` (a mapping or
        :class:`~closedchain.trajectory.SimulationInfo`)."""
        s = self.series()
        r = self.rows
        return Trajectory(
            t=s["t"],
            q=s["q"],
            v=s["v"],
            a=s["a"],
            lam=s["lam"],
            constraint_residual=s["res"],
            velocity_residual=s["vres"],
            energy=s["e"],
            kinetic_energy=s["ke"],
            branch=np.array(r["branch"]) if r["branch"] else None,
            info=info,
        )
