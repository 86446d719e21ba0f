r"""dop853-rk43: DOP853 far from singular positions, rk43 near them.

Far from singular positions (the rank indicator of J, :func:`.fixed.rank_indicator`, at
its cap :data:`.fixed.RANK_INDICATOR_CAP` at the step's start) a step is Dormand and
Prince's 8(5,3) pair (the tableau of scipy's DOP853) in the chart x -> q (+) x about the
step's start. Its stages are not projected (J is well conditioned there: a stage off the
manifold by its local error costs nothing); its end is projected mass-orthogonally onto
phi = 0, J v = 0, and the accelerations there are the next step's first stage (first
same as last). Its error is scipy's DOP853 estimate,

.. math::

    \mathrm{err} = h\,\frac{|e_5|^2}{\sqrt{(|e_5|^2 + 0.01\,|e_3|^2)\,n}}, \qquad
    e_k = \frac{\sum_i E_{k,i} K_i}{\mathrm{scale}},

with one weight for all positions, ``atol + rtol max |x+|`` (x+ the step's displacement
in the chart, as rk43 weighs positions by displacement, but over all coordinates: a
slider at its dead centre, whose own displacement vanishes, does not shrink the
tolerance to atol), and scipy's per velocity, ``atol + rtol max(|v|, |v+|)`` (one weight
for all velocities left the slider of the driven slider-crank 32 times less accurate
than scipy's DOP853 at rtol 1e-7, the crank's rate setting it). The next
step is h (0.9 err^(-1/7)) within [0.2 h, 10 h], at most h after a rejection (scipy's
rule; the exponent is that of an estimate of order 7 relative to a weight that grows
with h). Far from singular positions the solves are kkt's where the run's method is the
augmented Lagrangian (which converges to the same solution there at about twice the
cost), and the step's end is projected with the minimum-norm correction. The outputs
within a DOP853 step are its dense output (order 7, scipy's, with its three extra
stages), projected as a step's end.

The trial samples the indicator, uncapped, at its start, at two stages (c = 1/3 and
0.65) and at its end. A step is at most FAR_RHO_FRACTION of the time the indicator would
take to fall to 0 at the steepest rate between the last trial's samples, so approaching
a singular position the steps shrink until a sample falls below the cap; that trial is
discarded and the step is rk43's (:mod:`.rk43`: rk4 with every stage projected, the
evaluation points kept away from the crossing by retakes), at tolerances at least
(NEAR_RTOL, NEAR_ATOL), at most NEAR_ENTRY_FRACTION of the time the indicator takes to
cross its cap. Where the indicator is below its cap at a step's start or end, the rk43
step is kept and its size too, whatever its estimate (which measures there what the
crossing amplifies, not the step's error: rejecting on it shrank the steps onto the
crossing until they stalled). Each controller keeps its own step size.

``info`` gets rk43's entries (``rejected_steps`` counts the rejected trials of both;
``error_estimate_max`` and ``_sum`` leave out the steps within the cap), ``far_steps``
(the DOP853 steps) and ``zone_steps`` (the rk43 steps within the cap).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from scipy.integrate._ivp import dop853_coefficients as dop

from .chart import tangent_rate
from .fixed import RANK_INDICATOR_CAP, rank_indicator
from .problem import Problem, project
from .rk43 import _Estimator, run_projected
from .settings import SimulationError

#: Step-size control of the DOP853 steps (scipy's): safety factor, bounds of the change
#: per step, error exponent (the estimate is of order 7 and its position weight grows
#: with the step's displacement: err ~ h^7).
SAFETY = 0.9
MIN_FACTOR = 0.2
MAX_FACTOR = 10.0
ERROR_EXPONENT = -1.0 / 7.0
#: The method of the DOP853 steps' solves for the run's method (others: the run's own).
FAR_METHODS = {"augmented-lagrangian": "kkt"}
#: The stages [index] at which a DOP853 trial samples the rank indicator, besides its
#: start and end: c = 1/3 and c = 0.65.
INDICATOR_STAGE_A = 5
INDICATOR_STAGE_B = 8
#: A DOP853 step is at most this fraction of the time the rank indicator would take to
#: fall to 0 at its steepest rate over the last trial: approaching a singular position
#: the steps shrink (the indicator at most halves per step) until a sample falls below
#: its cap, and none steps over one between its samples.
FAR_RHO_FRACTION = 0.5
#: The tolerances of the rk43 steps are at least these (rtol, atol), rk43's own default:
#: tighter, its steps about a crossing are more and the passages less accurate (the
#: N-four-bar, N = 1, 20 s at rtol 1e-12: B0 off by 8.7e-9 m without the floor, 9e-10 m
#: with it; rk43 alone leaves the branch at rtol 1e-12).
NEAR_RTOL = 1e-9
NEAR_ATOL = 1e-10
#: An rk43 step (near a singular position) is at most this fraction of the time the
#: indicator takes to cross its cap at the steepest rate the last DOP853 trial saw:
#: rk43's crossing estimate then has samples within the cap before a step reaches the
#: crossing (rk43 alone takes such steps for its own error; a step sized for DOP853's
#: error may not).
NEAR_ENTRY_FRACTION = 0.25


def step_factor(err: float, rejected: bool) -> float:
    """Return the factor of the next step after an accepted estimate ``err`` (relative to
    the tolerance; at most 1 when the step was rejected before)."""
    factor = MAX_FACTOR if err == 0.0 else min(MAX_FACTOR, SAFETY * err**ERROR_EXPONENT)
    return min(1.0, factor) if rejected else factor


def indicator_rate(samples: list[tuple[float, float]]) -> float:
    """Return the steepest rate [1/s] of the rank indicator between consecutive samples
    (t [s], rho), in time order."""
    rate = 0.0
    for (t0, r0), (t1, r1) in zip(samples, samples[1:], strict=False):
        if t1 > t0:
            rate = max(rate, abs(r1 - r0) / (t1 - t0))
    return rate


class Dop853Far:
    """The DOP853 trials of dop853-rk43 (module docstring); ``h`` is the next trial step."""

    def __init__(self, problem: Problem, rtol: float, atol: float, method: str) -> None:
        self.problem = problem
        # J regular: the augmented Lagrangian converges to kkt's solution, at twice its cost.
        self.method = FAR_METHODS.get(method)
        self.model = problem.mech.model
        self.rtol, self.atol = rtol, atol
        self.h = problem.settings.dt  # the first trial step
        self.rejected = False  # the step being taken was rejected before
        self.rate = 0.0  # the indicator's steepest rate over the last trial [1/s]
        self.start = (math.nan, 0.0)  # (t, uncapped rho) of the last accepted DOP853 end

    def rho(self, q: np.ndarray) -> float:
        """The uncapped rank indicator at q (:func:`.fixed.rank_indicator`)."""
        problem = self.problem
        return rank_indicator(problem.jacobian(q), problem.normal_solver(), cap=math.inf)

    def near_estimator(self) -> _Estimator:
        """rk43's estimator at tolerances at least (NEAR_RTOL, NEAR_ATOL)."""
        return _Estimator(self.problem, max(self.rtol, NEAR_RTOL), max(self.atol, NEAR_ATOL))

    def near_step(self, h: float) -> float:
        """An rk43 step [s]: h at most NEAR_ENTRY_FRACTION cap / rate."""
        if self.rate > 0.0:
            return min(h, NEAR_ENTRY_FRACTION * RANK_INDICATOR_CAP / self.rate)
        return h

    def trial(self, t, q, v, a, t_land):
        """One trial from (q, v, a) at t toward t_land [s] (the end of the run): None when
        the rank indicator
        falls below its cap at a sample (the caller takes an rk43 step), "rejected"
        (``h`` reduced), or the accepted end (t+, q+, v+, a+, err, largest position error
        estimate [rad or m], rank indicator at q+ capped)."""
        problem, model = self.problem, self.model
        loops = problem.mech.nc > 0
        if loops and self.start[0] != t:  # the start was an rk43 step's end
            self.start = (t, self.rho(q))
        samples = [self.start]
        if loops and self.rate > 0.0:
            self.h = min(self.h, FAR_RHO_FRACTION * self.start[1] / self.rate)
        h = self.h
        clipped = t + h >= t_land * (1.0 - 1e-15)
        if clipped:
            h = t_land - t
        if not h > 10.0 * abs(math.nextafter(t, t_land) - t):
            raise SimulationError(
                f"{problem.mech.name}: integrator dop853-rk43 failed at t = {t:.9g} s: the "
                "step fell below the spacing of the times",
                t,
            )
        n_st = dop.N_STAGES
        kx = np.empty((n_st + 1, len(v)))
        ka = np.empty((n_st + 1, len(v)))
        kx[0], ka[0] = v, a
        for s in range(1, n_st):
            x = h * (dop.A[s, :s] @ kx[:s])
            vs = v + h * (dop.A[s, :s] @ ka[:s])
            qs = pin.integrate(model, q, x)
            ka[s] = problem.accel(t + dop.C[s] * h, qs, vs, multipliers=False, method=self.method)
            kx[s] = tangent_rate(model, q, x, vs)
            if loops and s in (INDICATOR_STAGE_A, INDICATOR_STAGE_B):
                samples.append((t + dop.C[s] * h, self.rho(qs)))
                if samples[-1][1] < RANK_INDICATOR_CAP:
                    self.rate = indicator_rate(samples)
                    return None
        x_new = h * (dop.B @ kx[:n_st])
        v_new = v + h * (dop.B @ ka[:n_st])
        q_new = pin.integrate(model, q, x_new)
        t_new = t_land if clipped else t + h
        if not (np.all(np.isfinite(q_new)) and np.all(np.isfinite(v_new))):
            raise SimulationError(
                f"{problem.mech.name}: non-finite state at t = {t_new:.9g} s", t_new
            )
        q_new, v_new = project(problem, q_new, v_new, t_new)  # J regular: minimum norm
        if loops:
            samples.append((t_new, self.rho(q_new)))
            self.rate = indicator_rate(samples)
            if samples[-1][1] < RANK_INDICATOR_CAP:
                return None
        a_new = problem.accel(t_new, q_new, v_new, method=self.method)
        x_new = pin.difference(model, q, q_new)  # the chart about q: x = 0 at the start
        kx[n_st], ka[n_st] = tangent_rate(model, q, x_new, v_new), a_new
        # One weight for the positions, scipy's per velocity (module docstring).
        sx = self.atol + self.rtol * float(np.max(np.abs(x_new), initial=0.0))
        sv = self.atol + self.rtol * np.maximum(np.abs(v), np.abs(v_new))
        scale = np.concatenate([np.full(len(v), sx), sv])
        k = np.hstack([kx, ka])
        e5, e3 = (dop.E5 @ k) / scale, (dop.E3 @ k) / scale
        n5, n3 = float(e5 @ e5), float(e3 @ e3)
        err = 0.0 if n5 == 0.0 and n3 == 0.0 else h * n5 / math.sqrt((n5 + 0.01 * n3) * len(scale))
        if err > 1.0:
            self.h = h * max(MIN_FACTOR, SAFETY * err**ERROR_EXPONENT)
            self.rejected = True
            return "rejected"
        proposed = self.h
        self.h = h * step_factor(err, self.rejected)
        if clipped:
            self.h = max(self.h, proposed)
        self.rejected = False
        self.last = (t, q, v, h, kx, ka, x_new, v_new)
        if loops:
            self.start = samples[-1]
        ex = h * float(np.max(np.abs(dop.E5 @ kx), initial=0.0))
        rho_new = min(samples[-1][1], RANK_INDICATOR_CAP) if loops else RANK_INDICATOR_CAP
        return t_new, q_new, v_new, a_new, err, ex, rho_new

    def record_outputs(self, recorder, pending: list, end: tuple) -> None:
        """Record the output times of ``pending`` within the step just accepted and drop
        them from it: at its end its state ``end`` = (t, q, v, a, lam), before it DOP853's
        dense output (order 7: scipy's Dop853DenseOutput with its three extra stages), q
        and v projected as at the step's end."""
        problem, model = self.problem, self.model
        t, q, v, h, kx, ka, x_new, v_new = self.last
        t_new = end[0]
        dense = None
        while pending and pending[0] <= t_new:
            t_out = pending.pop(0)
            if t_out == t_new:
                recorder.add(*end)
                continue
            if dense is None:
                dense = self._dense_coefficients(t, q, v, h, kx, ka, x_new, v_new)
            x_out, v_out = _dense_state(dense, (t_out - t) / h)
            q_out, v_out = project(problem, pin.integrate(model, q, x_out), v_out, t_out)
            problem.check_regular(q_out, t_out)
            recorder.declared_residual(t_out, q_out)
            a_out = problem.accel(t_out, q_out, v_out, method=self.method)
            recorder.add(t_out, q_out, v_out, a_out, problem.lam)

    def _dense_coefficients(self, t, q, v, h, kx, ka, x_new, v_new):
        """The coefficients F (7 rows) of the dense output of y = (x, v) over the step."""
        problem, model = self.problem, self.model
        n_st = dop.N_STAGES + 1
        kx = np.vstack([kx, np.empty((3, len(v)))])
        ka = np.vstack([ka, np.empty((3, len(v)))])
        for e, (a_row, c) in enumerate(zip(dop.A[n_st:], dop.C[n_st:], strict=True)):
            s = n_st + e
            x = h * (a_row[:s] @ kx[:s])
            vs = v + h * (a_row[:s] @ ka[:s])
            qs = pin.integrate(model, q, x)
            ka[s] = problem.accel(t + c * h, qs, vs, multipliers=False, method=self.method)
            kx[s] = tangent_rate(model, q, x, vs)
        k = np.hstack([kx, ka])
        y_old = np.concatenate([np.zeros(len(v)), v])
        delta = np.concatenate([x_new, v_new]) - y_old
        F = np.empty((dop.INTERPOLATOR_POWER, len(y_old)))
        F[0] = delta
        F[1] = h * k[0] - delta
        F[2] = 2 * delta - h * (k[dop.N_STAGES] + k[0])
        F[3:] = h * (dop.D @ k)
        return y_old, F


def _dense_state(dense, theta: float):
    """(x, v) of the dense output at the fraction theta of the step (scipy's evaluation)."""
    y_old, F = dense
    y = np.zeros_like(y_old)
    for i, f in enumerate(reversed(F)):
        y += f
        y *= theta if i % 2 == 0 else 1.0 - theta
    y += y_old
    n = len(y) // 2
    return y[:n], y[n:]


def run_dop853_rk43(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Integrate with dop853-rk43 (module docstring); return the accepted steps.

    Args:
        control: ``control.rtol``, ``control.atol``: the tolerances, with scipy's meaning.
    """
    far = Dop853Far(problem, control.rtol, control.atol, info["method"])
    return run_projected(problem, recorder, q, v, t_final, control, t_eval, progress, info, far)
