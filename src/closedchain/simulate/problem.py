"""The evaluation shared by every integrator: accelerations, partition, projection, output.

:class:`Problem` evaluates the right-hand side and tracks the coordinate
partition; :func:`project` is the lesson's position/velocity projection;
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
from ..trajectory import Trajectory, first_samples
from .registry import INTEGRATORS, STABILIZATIONS
from .settings import SimulationError

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)


class WorkMeter:
    r"""The work of the non-conservative generalized forces, :math:`W(t) = \int_0^t
    (\tau - D v) \cdot v\, dt`: the actuators' tau and the joint damping D
    (:class:`~closedchain.passive.PassiveTerms`; the springs are conservative, their
    potential is part of the recorded energy), accumulated over the points (step ends or
    samples) it is fed, in time order.

    Between two points (t0, tau0, v0, a0) and (t1, tau1, v1, a1) the power
    :math:`P = \tau \cdot v - v^\top D v` is integrated by the cubic Hermite rule (the
    corrected trapezoid),

    .. math::

        \int_{t_0}^{t_1} P\, dt \approx \frac{h}{2} (P_0 + P_1)
        + \frac{h^2}{12} (\dot P_0 - \dot P_1), \qquad
        \dot P = \tau \cdot a + \dot\tau \cdot v - 2\, v^\top D a,

    exact for a cubic P: its error is h^5 / 720 max |d^4 P / dt^4| per interval, fourth
    order in the spacing of the points, as rk4. :math:`\dot\tau` is 0 for a constant
    tau; for a callable it is differentiated along the points (no extra calls of tau):
    the derivatives at t0 and t1 of the parabola through tau at the point before t0,
    t0 and t1 (the secant on the first interval), second-order accurate, so that part
    of the rule is third order (measured on the 4-bar with tau = 1 + 1.5 sin(5 t) N m,
    rk4 at 1 ms: W within 4e-9 J of an independent DOP853 reference over 1 s; with the
    secant alone, 5e-6 J).

    Where the points come from:

    * numpy fixed-step loops and ALI3-P: every step end (and substep end), so W is
      fourth order in dt however sparse the outputs (an output between two step ends
      integrates the Hermite interpolant of P up to it);
    * numpy adaptive loops: the step's own dense output, by the three-point
      Gauss-Legendre rule (:func:`gauss_work`: exact for P of degree 5, error
      O(h^7) per step), up to each output within the step too;
    * compiled loops, which return samples only: W by the sixth-order rule of
      :func:`work_polynomials` on samples at every step end
      (:meth:`Recorder.sample_work`). With tau and sparse outputs the fixed-step and
      ALI3-P loops record every step and keep the outputs after; the adaptive loops
      run twice, the first run giving the step ends (``compiled_loops``). The
      4-bar under 2 N m on the crank, 1 s, 11 outputs, against an independent
      integration: energy balance 3.5e-12 with rk4 at 1 ms, 7.9e-8 with DOP853 at
      1e-10 (6e-5 on the 11 outputs alone; the numpy loop's Gauss rule: 5.9e-10).
      A callable tau is differentiated along the samples by :func:`sample_rate`.

    Args:
        torque: ``tau(t, q, v)``, shape (nv,) [N m or N] (e.g. :meth:`Problem.torque`).
        constant: tau does not change (then :math:`\dot\tau = 0` exactly).
        damping: D per velocity coordinate, shape (nv,) [N m s/rad or N s/m].
    """

    def __init__(self, torque: Callable, constant: bool, damping: np.ndarray) -> None:
        self.torque = torque
        self.constant = constant
        self.damping = damping
        #: W [J] at the last point fed.
        self.W = 0.0
        self._point: tuple | None = None  # (t, tau, v, a, P) of the last point
        self._before: tuple | None = None  # (t, tau) of the point before it
        #: (t0, W0, integral) of the last interval: integral(s) = W(s) - W0, s in [t0, t].
        self._interval: tuple | None = None

    def feed(
        self,
        t: float,
        q: np.ndarray,
        v: np.ndarray,
        a: np.ndarray | None,
        integral: Callable[[float], float] | None = None,
    ) -> float:
        """Advance W to the point (t, q, v, a) after the last one; return W [J].

        Args:
            t: time [s]; a point at the time of the last one (a step end checked
                twice) leaves W as it is.
            q: configuration, shape (nq,).
            v: velocity, shape (nv,) [rad/s or m/s].
            a: acceleration, shape (nv,) [rad/s^2 or m/s^2] (None with ``integral``).
            integral: ``s -> integral of P from the last point to s`` [J] for s up to
                t (e.g. :func:`gauss_work` on a dense output); default: the Hermite
                rule from the two points.
        """
        tau = np.asarray(self.torque(t, q, v), dtype=float)
        p = float(tau @ v) - float(v @ (self.damping * v))
        if self._point is not None:
            t0 = self._point[0]
            if t <= t0:
                return self.W
            if integral is None:
                integral = self._hermite(t, tau, v, a, p)
            self._interval = (t0, self.W, integral)
            self.W += integral(t)
            self._before = self._point[:2]
        self._point = (t, tau, np.array(v), None if a is None else np.array(a), p)
        return self.W

    def _hermite(self, t1, tau1, v1, a1, p1):
        """The Hermite rule's integral from the last point, as a function of its end."""
        t0, tau0, v0, a0, p0 = self._point
        h = t1 - t0
        d = self.damping
        dp0 = float(tau0 @ a0) - 2.0 * float(v0 @ (d * a0))
        dp1 = float(tau1 @ a1) - 2.0 * float(v1 @ (d * a1))
        if not self.constant:
            rate0 = rate1 = (tau1 - tau0) / h  # the secant: first interval
            if self._before is not None:
                # The parabola through (t_m, tau_m), (t0, tau0), (t1, tau1), differentiated
                # at t0 and t1 (np.gradient's second-order formulas, uneven spacing).
                t_m, tau_m = self._before
                g = t0 - t_m
                slope_m = (tau0 - tau_m) / g
                curvature = (rate1 - slope_m) / (g + h)  # half the second derivative
                rate0 = rate1 - curvature * h
                rate1 = rate1 + curvature * h
            dp0, dp1 = dp0 + float(rate0 @ v0), dp1 + float(rate1 @ v1)

        def integral(t: float) -> float:
            s = min(max((t - t0) / h, 0.0), 1.0)
            # Integrals over [0, s] of the cubic Hermite basis h00, h10, h01, h11.
            i00 = s - s**3 + s**4 / 2.0
            i10 = s**2 / 2.0 - 2.0 * s**3 / 3.0 + s**4 / 4.0
            i01 = s**3 - s**4 / 2.0
            i11 = s**4 / 4.0 - s**3 / 3.0
            return h * (i00 * p0 + i10 * h * dp0 + i01 * p1 + i11 * h * dp1)

        return integral

    def force(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Return the non-conservative force tau(t, q, v) - D v, shape (nv,) [N m or N]."""
        return np.asarray(self.torque(t, q, v), dtype=float) - self.damping * v

    def at(self, t: float) -> float:
        """Return W(t) [J] for t in the last interval fed (its integral up to t: outputs
        between step ends), else W at the last point."""
        if self._interval is None or t >= self._point[0]:
            return self.W
        t0, w0, integral = self._interval
        return w0 + integral(t)


#: Three-point Gauss-Legendre rule on [0, 1]: nodes and weights.
GAUSS_NODES = (0.5 - math.sqrt(0.15), 0.5, 0.5 + math.sqrt(0.15))
GAUSS_WEIGHTS = (5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0)


def gauss_work(torque: Callable, state: Callable, t0: float) -> Callable[[float], float]:
    """Return ``s -> integral of tau . v from t0 to s`` [J] by three-point Gauss-Legendre
    on a dense output (exact for a power of degree 5).

    Args:
        torque: ``tau(t, q, v)``, shape (nv,).
        state: ``t -> (q, v)`` within the step (the integrator's dense output).
        t0: the start of the interval [s].
    """

    def integral(s: float) -> float:
        h = s - t0
        total = 0.0
        for x, w in zip(GAUSS_NODES, GAUSS_WEIGHTS, strict=True):
            q, v = state(t0 + x * h)
            total += w * float(np.asarray(torque(t0 + x * h, q, v), dtype=float) @ v)
        return h * total

    return integral


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
        #: W(t) of tau and the joint damping (None when neither acts: no work); fed by
        #: :meth:`step_end`.
        damping = mech.passive.damping
        self.meter = (
            None
            if tau is None and not mech.passive.has_damping
            else WorkMeter(self.torque, not callable(tau), damping)
        )
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
        self._start_J: np.ndarray | None = None  # J(q0) of check_start (compiled rows)
        self._normal = None
        self._normal_layer = None
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
        """Return J(q) of the kept rows, shape (nc, nv)."""
        return compute_jacobian(self.mech, q, backend="numpy")

    def residual_and_jacobian(self, q: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Fill phi(q) of the kept rows and return J(q), in one pass over the loops."""
        return position_terms(self.mech, q, phi).J.copy()

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

    def step_end(self, *point) -> None:
        """Advance the work W(t) of tau to a step's end ``point`` = (t, q, v, a[, integral])
        (:meth:`WorkMeter.feed`'s arguments; nothing without tau); every loop calls it at
        t = 0 and at each accepted step end, in time order."""
        if self.meter is not None:
            self.meter.feed(*point)

    def accel(
        self,
        t: float,
        q: np.ndarray,
        v: np.ndarray,
        *,
        multipliers: bool = True,
        method: str | None = None,
    ) -> np.ndarray:
        """Return the accelerations at (t, q, v), shape (nv,); :attr:`lam` holds the
        multipliers, polished only with ``multipliers`` (``SolverSettings.al_polish``:
        off for evaluations whose multipliers nobody reads, such as rk4's inner stages).
        ``method``: another method's solve than the run's (dop853-rk43's kkt far from
        singular positions), None: the run's."""
        settings = self.solver_settings
        if not multipliers and settings.al_polish:
            settings = self._unpolished
        # An overflow is reported by the finiteness checks of tau (in torque), of the
        # inverse dynamics of a controller and of a below, not as a RuntimeWarning.
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            tau = self.torque(t, q, v)
            try:
                func = self.func if method is None else get_method(method)
                a, lam = func(self.mech, q, v, tau, settings)
            except SingularConfigurationError as exc:
                raise exc.at_time(t, hint=passing_hint()) from None
        self.n_evals += 1
        if not np.all(np.isfinite(a)):
            raise SimulationError(nonfinite_message(self.mech.name, t, q, v), t)
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
            raise self._singular(
                "the best-conditioned J_D of any partition of the coordinates",
                q,
                t,
                cond,
                "partition_singular_cond",
                f"no partition has a regular J_D: a singular configuration; {passing_hint()}",
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
        cond = _cond(self.jacobian(q))
        if self.check_rows(q, t, kept_cond=cond, phi=phi):
            cond = _cond(self.jacobian(q))
        if cond > self.settings.singular_cond:
            raise self._singular_J(q, t, cond)

    def check_stage_regular(self, q: np.ndarray, t: float, J: np.ndarray) -> None:
        """Raise :meth:`check_regular`'s error when cond(J) of the kept rows at a projected
        stage point (t, q) of a projected rk4 step exceeds ``settings.singular_cond``.

        The step's ends alone can straddle a singular position that its stages come
        close to (rk43's steps pass the 4-bar's change point so). Not when
        :attr:`singular_robust`; nor where the kept rows degenerate while the declared
        ones do not (the step's end re-selects them).

        Args:
            q: the stage's configuration, shape (nq,).
            t: its time [s].
            J: the kept rows' J at q, shape (nc, nv).
        """
        if self.mech.nc == 0 or self.singular_robust:
            return
        cond = _cond(J)
        if cond <= self.settings.singular_cond:
            return
        mech = self.mech
        closure = mech.closure
        if closure.declared.nc > closure.active.nc and (
            closure.declared_cond(mech.model, mech.data, q) <= self.settings.singular_cond
        ):
            return
        raise self._singular_J(q, t, cond)

    def _singular_J(self, q: np.ndarray, t: float, cond: float) -> SingularConfigurationError:
        """Return the error of a constraint Jacobian with cond(J) = ``cond`` above
        ``settings.singular_cond`` at (t, q)."""
        return self._singular(
            "the constraint Jacobian",
            q,
            t,
            cond,
            "singular_cond",
            "a singular configuration, where the motion is not determined by the "
            f"equations and method {self.method!r} loses accuracy without any error "
            f"estimate noticing; {passing_hint()}",
            state="is close to losing rank",
        )

    def _singular(
        self,
        what: str,
        q: np.ndarray,
        t: float,
        cond: float,
        bound_name: str,
        hint: str,
        *,
        state: str = "is singular",
    ) -> SingularConfigurationError:
        """Return the error of ``what`` with condition number ``cond`` above the setting
        ``bound_name`` at (t, q)."""
        return SingularConfigurationError.build(
            self.mech.name,
            what,
            q=q,
            cond=cond,
            bound=getattr(self.settings, bound_name),
            bound_name=bound_name,
            state=state,
            hint=hint,
            t=t,
        )


def _cond(J: np.ndarray) -> float:
    """Return the 2-norm condition number of J, shape (nc, nv) (inf when rank-deficient)."""
    s = np.linalg.svd(J, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else math.inf


#: What the message of non-finite accelerations says of the cause and the remedy (the
#: compiled core's too).
NONFINITE_HINT = (
    "the state diverged or the method failed there; a fixed step beyond the motion's "
    "stability limit diverges: use integrator='rk43' or a smaller dt"
)


def nonfinite_message(name: str, t: float, q: np.ndarray, v: np.ndarray) -> str:
    """Return the one-line message of non-finite accelerations at (t, q, v) (the compiled
    core's too): the size of the state says whether the integration diverged before.

    Args:
        name: the mechanism's name.
        t: time [s].
        q: configuration, shape (nq,).
        v: velocity, shape (nv,) [rad/s or m/s].
    """
    with np.errstate(invalid="ignore"):
        q_max = float(np.max(np.abs(q), initial=0.0))
        v_max = float(np.max(np.abs(v), initial=0.0))
    return (
        f"{name}: non-finite acceleration at t = {t:.9g} s (max |q| = {q_max:.3e}, max |v| = "
        f"{v_max:.3e}): {NONFINITE_HINT}"
    )


def passing_hint() -> str:
    """Name the configurations that pass singular positions (from the registries' capabilities)."""
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
    """Lesson-style projection: Gauss-Newton on q (min-norm), then v onto J v = 0.

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
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(v))):
        raise SimulationError(f"{mech.name}: non-finite state at t = {t:.9g} s", t)
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
                max_iter=solver.max_iter(ss.al_max_iter),
                polish=False,
                a0=v,
            )
        else:
            v = v - min_norm(J, J @ v)
    return q, v


class Recorder:
    """Collects output samples and their residuals and energy."""

    #: Per-sample series: t, res, vres, e, ke, w scalars; q, v, a, lam vectors.
    SERIES = ("t", "q", "v", "a", "lam", "res", "vres", "e", "ke", "w")

    def __init__(
        self, mech: Mechanism, drift_limit: float, jacobian, meter: WorkMeter | None = None
    ) -> None:
        self.mech = mech
        #: The work of tau (:attr:`Problem.meter`), or None: the ``w`` series is then NaN.
        self.meter = meter
        self.drift_limit = drift_limit
        self.jacobian = jacobian  # J(q) of the kept rows (Problem.jacobian)
        #: Samples of :meth:`add` not yet moved into :attr:`_blocks` (one entry per sample).
        self.rows: dict[str, list] = {k: [] for k in self.SERIES}
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
        the next call). Leaves ``mech.data``'s joint and loop frame placements at q."""
        mech = self.mech
        pin.forwardKinematics(mech.model, mech.data, q)
        mech.declared.evaluate(mech.model, mech.data, phi=self._phi)
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
        kinetic = mech.passive.kinetic_energy(model, data, q, v)  # armature included
        energy = kinetic + pin.computePotentialEnergy(model, data, q)
        energy += mech.passive.spring_energy(q)  # the joint springs' potential
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
        r["w"].append(math.nan if self.meter is None else self.meter.at(t))
        self._n += 1
        self._add_branch(t, J)

    def __len__(self) -> int:
        """Number of samples recorded."""
        return self._n

    def _widths(self) -> dict[str, int]:
        m = self.mech
        return {"q": m.nq, "v": m.nv, "a": m.nv, "lam": m.nc}

    def sample_rows(self, samples: dict, key: str) -> np.ndarray:
        """Return the series ``key`` of compiled-loop ``samples`` in rows, shape (n, k).

        The core returns a series of width 1 (a mechanism with nv = 1) as a 1-D
        array, and one of width 0 (no loops) without its columns.
        """
        times = np.asarray(samples["t"], dtype=float).ravel()
        return np.ascontiguousarray(samples[key], dtype=float).reshape(
            len(times), self._widths()[key]
        )

    def _flush(self) -> None:
        """Move the pending rows of :meth:`add` into one block (in recording order)."""
        r = self.rows
        if not r["t"]:
            return
        widths = self._widths()
        n = len(r["t"])
        block = {}
        for key in self.SERIES:
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
        for key in self.SERIES:  # C order, as the rows of add (the core's are column-major)
            if key == "w":
                continue
            # len(times) rows, not -1: a mechanism without loops has lam of width 0.
            block[key] = (
                self.sample_rows(samples, key)
                if key in widths
                else np.asarray(samples[key], dtype=float).ravel()
            )
        if self.mech.passive.has_springs:  # the core's e is T + gravity's potential
            block["e"] = block["e"] + self.mech.passive.spring_energies(block["q"])
        if "w" in samples:  # computed on more samples than kept (compiled_loops)
            block["w"] = np.asarray(samples["w"], dtype=float).ravel()
        else:
            block["w"] = self.sample_work(block)
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

    def sample_work(self, samples: dict) -> np.ndarray:
        """Return W at samples computed elsewhere (the compiled loops record no work),
        shape (n,) [J]; NaN without tau.

        From the meter's last point (t = 0) to the first sample: :meth:`WorkMeter.feed`;
        between samples: :func:`work_polynomials` (sixth order in their spacing, any
        spacing: outputs a round-off from a step end included). The meter is left at
        the last sample.

        Args:
            samples: arrays ``t`` (n,) [s], ``q`` (n, nq), ``v``, ``a`` (n, nv).
        """
        t = np.asarray(samples["t"], dtype=float).ravel()
        if self.meter is None:
            return np.full(len(t), math.nan)
        mech, meter = self.mech, self.meter
        q = np.asarray(samples["q"], dtype=float).reshape(-1, mech.nq)
        v = np.asarray(samples["v"], dtype=float).reshape(-1, mech.nv)
        a = np.asarray(samples["a"], dtype=float).reshape(-1, mech.nv)
        if len(t) < 3:
            return np.array([meter.feed(*x) for x in zip(t, q, v, a, strict=True)])
        w0 = meter.feed(t[0], q[0], v[0], a[0])
        if meter.constant:  # one call: a Python call per sample cost 36 % of a 2F-85 run
            tau = np.broadcast_to(meter.torque(t[0], q[0], v[0]), v.shape)
        else:
            tau = np.array([meter.torque(*x) for x in zip(t, q, v, strict=True)])
        dv = meter.damping * v
        power = np.einsum("ij,ij->i", tau, v) - np.einsum("ij,ij->i", dv, v)
        rate = np.einsum("ij,ij->i", tau, a) - 2.0 * np.einsum("ij,ij->i", dv, a)
        if not meter.constant:  # d tau / dt from the samples
            rate += np.einsum("ij,ij->i", sample_rate(t, tau), v)
        h, coeffs = work_polynomials(t, power, rate)
        increments = h * (coeffs @ (1.0 / (np.arange(coeffs.shape[1]) + 1.0)))
        w = w0 + np.concatenate([[0.0], np.cumsum(increments)])
        meter.feed(t[-1], q[-1], v[-1], a[-1], integral=lambda s: w[-1] - w0)
        return w

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
        for key in self.SERIES:
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
            work=None if self.meter is None else s["w"],
            branch=np.array(r["branch"]) if r["branch"] else None,
            info=info,
        )


#: Samples per window of :func:`sample_rate` (a quartic: fourth-order derivatives).
RATE_WINDOW = 5
#: :func:`sample_rate` merges a sample this close to the one before, relative to the
#: median spacing, into it.
RATE_MERGE_FRACTION = 1e-6


def sample_rate(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Return dx/dt at the samples, shape of ``x``: the derivative of the quartic through
    the RATE_WINDOW samples around each (fourth order in their spacing, any spacing;
    ``np.gradient``'s second-order one with fewer samples).

    Args:
        t: sample times [s], shape (n,), increasing.
        x: values at the samples, shape (n, m).
    """
    # A sample a round-off after the one before (an output beside a step end) would make
    # the windows' Vandermonde systems singular: it takes that sample's derivative.
    spacing = np.diff(t)
    distinct = np.concatenate([[True], spacing > RATE_MERGE_FRACTION * np.median(spacing)])
    if not np.all(distinct):
        return sample_rate(t[distinct], x[distinct])[np.cumsum(distinct) - 1]
    n = len(t)
    if n < RATE_WINDOW:
        return np.gradient(x, t, axis=0)
    start = np.clip(np.arange(n) - RATE_WINDOW // 2, 0, n - RATE_WINDOW)
    idx = start[:, None] + np.arange(RATE_WINDOW)
    scale = t[idx[:, -1]] - t[idx[:, 0]]
    z = (t[idx] - t[:, None]) / scale[:, None]  # each sample at z = 0
    A = z[:, :, None] ** np.arange(RATE_WINDOW)  # (n, window, window) Vandermonde
    coeffs = np.linalg.solve(A, x[idx])  # (n, window, m)
    return coeffs[:, 1, :] / scale[:, None]


#: The sixth-order rule of :func:`work_polynomials` takes a neighbouring interval at most
#: this many times longer or shorter than the interval (beyond, the linear system of the
#: quintic is ill-conditioned: an interval a round-off long beside a step).
WORK_STENCIL_RATIO = 16.0


def work_polynomials(
    t: np.ndarray, power: np.ndarray, rate: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    r"""Return the polynomials of the power P on the intervals between samples: their
    lengths h, shape (n - 1,) [s], and coefficients c, shape (n - 1, 6) [W], with
    :math:`P(t_k + z h_k) = \sum_p c_{k,p} z^p` on :math:`z \in [0, 1]`.

    On each interval [t_k, t_k+1] the quintic through P and dP/dt at its two ends and at
    a third sample: the nearest one at least h_k / WORK_STENCIL_RATIO before t_k (t_k-1
    on evenly spaced samples), else after t_k+1, at most WORK_STENCIL_RATIO h_k from
    the interval: exact for P of degree 5, error O(h^7) per interval (sixth order in the
    sample spacing h), the linear system well-conditioned for any spacing. Without such
    a sample (an interval much shorter than those beside it) the cubic Hermite of its
    two ends (c_4 = c_5 = 0; error h^5 / 720 max |d^4 P / dt^4|, small where h is).

    Args:
        t: sample times [s], shape (n,), increasing, n >= 2.
        power: P = tau . v at the samples [W], shape (n,).
        rate: dP/dt at the samples [W/s], shape (n,).
    """
    n = len(t)
    k = np.arange(n - 1)
    h = t[k + 1] - t[k]
    ratio = WORK_STENCIL_RATIO
    # The nearest sample at least h / ratio before the interval, else after it; usable
    # within ratio x h of it (a sample a round-off beside the interval is skipped).
    before = np.minimum(np.searchsorted(t, t[k] - h / ratio, side="right") - 1, k - 1)
    after = np.maximum(np.searchsorted(t, t[k + 1] + h / ratio, side="left"), k + 2)
    gap_before = t[k] - t[np.maximum(before, 0)]
    gap_after = t[np.minimum(after, n - 1)] - t[k + 1]
    use_left = (before >= 0) & (gap_before >= h / ratio) & (gap_before <= ratio * h)
    use_right = ~use_left & (after < n) & (gap_after >= h / ratio) & (gap_after <= ratio * h)
    third = np.where(use_left, before, np.where(use_right, after, k))
    idx = np.stack([k, k + 1, third], axis=1)  # (n - 1, 3); the third unused without one
    z = (t[idx] - t[k][:, None]) / h[:, None]  # local coordinate, interval = [0, 1]
    powers = np.arange(6)
    A = np.concatenate(
        [
            z[:, :, None] ** powers,  # P(z) rows
            powers * np.where(powers > 0, z[:, :, None], 1.0) ** np.maximum(powers - 1, 0),
        ],
        axis=1,
    )  # (n - 1, 6, 6), rows P(z0), P(z1), P(z2), P'(z0), P'(z1), P'(z2); dP/dz = h dP/dt
    b = np.concatenate([power[idx], h[:, None] * rate[idx]], axis=1)
    alone = ~(use_left | use_right)  # the cubic Hermite: rows of z2 become c4 = c5 = 0
    A[alone, 2, :] = np.eye(6)[4]
    A[alone, 5, :] = np.eye(6)[5]
    b[alone, 2] = b[alone, 5] = 0.0
    coeffs = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    return h, coeffs


def limit_violations(
    mech: Mechanism, t: np.ndarray, q: np.ndarray, *, urdf_limits: bool = True
) -> list[list]:
    """Return ``[joint, t_first, value, limit]`` for each joint whose coordinate leaves its
    limits in the samples (t, q).

    The rules of the start check (:meth:`~closedchain.Mechanism.limit_checks`): 1-dof
    joints, their finite URDF ``<limit>`` (with ``urdf_limits``) and the coordinate
    bound (limits bound the coordinate, not the pose).

    Args:
        mech: the mechanism.
        t: sample times [s], shape (N,).
        q: configurations, shape (N, nq).
        urdf_limits: check the URDF limits (else only the coordinate bound).

    Returns:
        One entry per joint, in tree order: the first time it is beyond a limit [s], its
        coordinate there and the limit passed [rad or m].
    """
    out = []
    for j, outside, low, high in mech.limit_checks(q, urdf_limits=urdf_limits):
        if np.any(outside):
            k = int(np.argmax(outside))
            value = float(q[k, mech.model.joints[j].idx_q])
            out.append([mech.model.names[j], float(t[k]), value, low if value < low else high])
    return out


def report_limit_violations(mech: Mechanism, recorder: Recorder, info: dict, settings) -> None:
    """Record the joint-limit violations of a finished run in ``info["limit_violations"]``.

    URDF limits count unless ``settings.check_limits`` is off (as for the start).
    Each is logged as a warning; with ``settings.stop_at_limits`` the first one stops
    the run: SimulationError naming the joint and the time, ``exc.trajectory`` holding
    the samples before it.
    """
    s = recorder.series()
    found = limit_violations(mech, s["t"], s["q"], urdf_limits=settings.check_limits)
    info["limit_violations"] = found
    for joint, t, value, limit in found:
        logger.warning(
            "%s: joint %r left its <limit> at t = %.6g s: q = %.6g beyond %.6g",
            mech.name,
            joint,
            t,
            value,
            limit,
        )
    if found and settings.stop_at_limits:
        joint, t, value, limit = min(found, key=lambda v: v[1])
        exc = SimulationError(
            f"{mech.name}: joint {joint!r} left its <limit> at t = {t:.6g} s (q = {value:.6g} "
            f"beyond {limit:.6g}); SimulationSettings.stop_at_limits is set",
            t,
        )
        keep = s["t"] < t
        info["stopped"] = {"t": t, "reason": str(exc)}
        if np.any(keep):
            traj = recorder.trajectory(info)
            exc.trajectory = first_samples(traj, int(np.count_nonzero(keep)))
        raise exc
