r"""rk43: rk4 with stage projection, its step chosen by an embedded error estimate.

The step is the projected rk4 step of :mod:`.fixed` (every stage and the end projected
mass-orthogonally onto phi = 0, J v = 0; evaluation points kept
``SimulationSettings.stage_singular_zone`` steps away from singular positions by the
same retakes). Its error is estimated by the third-order solution that rk4's stages
make with the accelerations at the step's end (first same as last: they are the next
step's first stage, so the estimate costs no evaluation),

.. math::

    b^* = (\tfrac16, \tfrac13, \tfrac13, 0, \tfrac16), \qquad
    e = y_4 - y_3 = \frac{h}{6}\,(k_4 - k_5), \qquad k_5 = f(t + h, y_{n+1}),

(the order conditions of order 3 hold for b*, those of order 4 do not). Positions are
compared in the chart x about the step's start (x = 0 there, x+ = ``pin.difference(q,
q+)``; :func:`.chart.tangent_rate`). With scipy's weights ``scale = atol + rtol
max(|y|, |y+|)`` on y = (x, v) the step is accepted when the RMS of e / scale is at most
1, and the next step is h (0.9 err^(-1/4)) within [0.2 h, 5 h] (the fourth-order solution
is kept: local extrapolation). The position weight is thus about atol (plus rtol times
the step's displacement) per step: it does not loosen as a crank's angle grows over the
turns, as scipy's weight on an absolute angle does (the N-four-bar, N = 1, 20 s at rtol
1e-9: B0 off by 6.6e-6 m with that weight, 6.8e-8 m with this one). A step retaken as
substeps near a singular position is accepted on its substeps' own estimates (the plain
step's points near the crossing are what the retake avoids).

``info`` gets ``rejected_steps``, ``error_estimate_max`` (the largest accepted estimate,
relative to the tolerance: at most 1) and ``error_estimate_sum`` (the sum over the
accepted steps of the largest absolute position error estimate [rad or m]: a first-order
bound on the accumulated position error, not counting how the motion amplifies it), and
``singular_splits``.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

from .chart import tangent_rate
from .fixed import (
    RANK_INDICATOR_CAP,
    _record_interpolated,
    crossing_estimate,
    rank_indicator,
    retake_plan,
    rk4_projected,
)
from .problem import Problem
from .settings import SimulationError

#: Step-size control: safety factor, bounds of the change per step, error exponent
#: (the estimate is of order 3: err ~ h^4).
SAFETY = 0.9
MIN_FACTOR = 0.2
MAX_FACTOR = 5.0
ERROR_EXPONENT = -1.0 / 4.0


def step_factor(err: float) -> float:
    """Return the factor of the next step after an estimate ``err`` (relative to the
    tolerance): 0.9 err^(-1/4) within [MIN_FACTOR, MAX_FACTOR]."""
    if err == 0.0:
        return MAX_FACTOR
    return min(MAX_FACTOR, max(MIN_FACTOR, SAFETY * err**ERROR_EXPONENT))


class _Estimator:
    """The embedded estimate of one projected rk4 step, in scipy's weighted RMS norm."""

    def __init__(self, problem: Problem, rtol: float, atol: float) -> None:
        self.problem = problem
        self.model = problem.mech.model
        self.rtol, self.atol = rtol, atol

    def step(self, t, q, v, a, h):
        """One projected rk4 step; return (q+, v+, a+, J at the midpoint, err, position
        error estimate [rad or m, max abs])."""
        problem, model = self.problem, self.model
        last = []
        q_new, v_new, J_mid = rk4_projected(problem, t, q, v, a, h, last_stage=last)
        a_new = problem.accel(t + h, q_new, v_new)
        k4x, k4a = last[0]
        x_new = pin.difference(model, q, q_new)  # the chart about q: x = 0 at the start
        k5x = tangent_rate(model, q, x_new, v_new)
        ex, ev = (h / 6.0) * (k4x - k5x), (h / 6.0) * (k4a - a_new)
        sx = self.atol + self.rtol * np.abs(x_new)
        sv = self.atol + self.rtol * np.maximum(np.abs(v), np.abs(v_new))
        e = np.concatenate([ex / sx, ev / sv])
        err = float(np.linalg.norm(e)) / math.sqrt(len(e)) if len(e) else 0.0
        return q_new, v_new, a_new, J_mid, err, float(np.max(np.abs(ex), initial=0.0))


def record_outputs(problem: Problem, recorder, pending: list, start: tuple, end: tuple) -> None:
    """Record the output times of ``pending`` within the step (start, end] and drop them
    from it: at the step's end its state, before it the cubic Hermite interpolant of the
    step projected onto phi = 0 (:func:`.fixed._record_interpolated`).

    Steps do not land on the output times: an output time near a singular position would
    put a step's end where the retakes keep every evaluation point away from.

    Args:
        pending: increasing output times [s]; those recorded are removed.
        start: (t, q, v, a) at the step's start.
        end: (t, q, v, a) at the step's end; the work of tau must have been advanced to
            it (:meth:`Problem.step_end`).
    """
    t0, q0, v0, a0 = start
    t1 = end[0]
    while pending and pending[0] <= t1:
        t = pending.pop(0)
        if t == t1:
            recorder.add(t1, end[1], end[2], problem.accel(t1, end[1], end[2]), problem.lam)
        else:
            _record_interpolated(
                problem, recorder, t, (t - t0) / (t1 - t0), t1 - t0, *start[1:], *end[1:]
            )


def run_rk43(
    problem: Problem, recorder, q, v, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Integrate with rk43 (module docstring); return the accepted steps.

    The steps end at the last output time (``t_final`` without ``t_eval``); the outputs
    before it are interpolated (:func:`record_outputs`).

    Args:
        control: ``control.rtol``, ``control.atol``: the tolerances, with scipy's meaning.
    """
    return run_projected(problem, recorder, q, v, t_final, control, t_eval, progress, info)


def run_projected(
    problem: Problem, recorder, q, v, t_final, control, t_eval, progress, info, far=None
) -> int:
    """The loop of rk43, and of :mod:`.dop853_rk43` with ``far``; return the accepted steps.

    Args:
        far: None (rk43), or a stepper taken wherever the rank indicator at the step's
            start is at its cap (far from singular positions): ``far.trial(t, q, v, a,
            t_land)`` returns None (the rk43 step is taken instead), "rejected", or the
            accepted step's end (t, q, v, a, err, position error estimate [rad or m]);
            ``t_land`` is the time it must not step past (the next output time). Its
            trials are counted with the rk43 ones in ``info``.
    """
    settings = problem.settings
    est = _Estimator(problem, control.rtol, control.atol) if far is None else far.near_estimator()
    zone = settings.stage_singular_zone
    t = 0.0
    a = problem.accel(t, q, v)
    problem.step_end(t, q, v, a)
    pending = None if t_eval is None else [float(s) for s in t_eval]
    t_stop = t_final if t_eval is None else pending[-1]
    if pending is None or pending[0] <= 0.0:
        recorder.add(t, q, v, a, problem.lam)
        if pending:
            pending.pop(0)

    def rho(q):
        return rank_indicator(problem.jacobian(q), problem.normal_solver())

    def check(t, q):
        phi = recorder.declared_phi(q)
        problem.check_regular(q, t, phi)  # checks every declared row too
        recorder.declared_residual(t, q, phi)  # drift limit, every declared row

    rho_start = rho(q)
    h = settings.dt  # the first trial step
    steps = rejected = splits = far_steps = zone_steps = 0
    err_max = err_sum = 0.0
    while t < t_stop:
        if far is not None and rho_start >= RANK_INDICATOR_CAP:
            out = far.trial(t, q, v, a, t_stop)
            if out == "rejected":
                rejected += 1
                continue
            if out is not None:
                t_new, q_new, v_new, a_new, err, ex, rho_new = out
                lam_new = problem.lam
                check(t_new, q_new)
                problem.step_end(t_new, q_new, v_new, a_new)
                t, q, v, a, rho_start = t_new, q_new, v_new, a_new, rho_new
                steps += 1
                far_steps += 1
                err_max, err_sum = max(err_max, err), err_sum + ex
                if pending is None:
                    recorder.add(t, q, v, a, lam_new)
                else:
                    far.record_outputs(recorder, pending, (t, q, v, a, lam_new))
                if progress is not None:
                    progress(t)
                continue
        if far is not None:  # near a singular position: steps that see it coming
            h = far.near_step(h)
        proposed = h
        clipped = t + h >= t_stop * (1.0 - 1e-15)
        if clipped:
            h = t_stop - t
        if not h > 10.0 * abs(math.nextafter(t, t_stop) - t):
            raise SimulationError(
                f"{problem.mech.name}: integrator rk43 failed at t = {t:.9g} s: the step "
                "fell below the spacing of the times",
                t,
            )
        q_new, v_new, a_new, J_mid, err, ex = est.step(t, q, v, a, h)
        rho_new = rho(q_new)
        plan = None
        if zone > 0:
            rho_mid = rank_indicator(J_mid, problem.normal_solver())
            plan = retake_plan(crossing_estimate(rho_start, rho_mid, rho_new), zone)
        span, substep = 1.0, None
        if plan is not None:
            double, f = plan
            span = 2.0 if double else 1.0
            if double and t + 2.0 * h > t_stop * (1.0 + 1e-15):
                h = 0.5 * (t_stop - t)  # re-plan with two steps ending at the stop
                continue
            if f < span:
                q1, v1, a1, _, err1, ex1 = est.step(t, q, v, a, f * h)
                substep = (t + f * h, q1)
                out = est.step(t + f * h, q1, v1, a1, (span - f) * h)
                q_new, v_new, a_new, _, err2, ex2 = out
                err, ex = max(err1, err2), ex1 + ex2
            else:  # one substep of two steps
                q_new, v_new, a_new, _, err, ex = est.step(t, q, v, a, span * h)
            rho_new = rho(q_new)
        # dop853-rk43 within the indicator's cap: the step is kept, its size too (an
        # estimate there measures what the crossing amplifies, not the step's error).
        in_zone = far is not None and min(rho_start, rho_new) < RANK_INDICATOR_CAP
        if err > 1.0 and not in_zone:
            rejected += 1
            h *= step_factor(err)
            continue
        splits += plan is not None
        zone_steps += in_zone
        if substep is not None:
            check(*substep)
        t_new = t_stop if clipped or t + span * h >= t_stop else t + span * h
        check(t_new, q_new)
        problem.step_end(t_new, q_new, v_new, a_new)
        start = (t, q, v, a)
        t, q, v, a, rho_start = t_new, q_new, v_new, a_new, rho_new
        steps += 1
        if not in_zone:
            err_max, err_sum = max(err_max, err), err_sum + ex
        if pending is None:
            recorder.add(t, q, v, a, problem.lam)
        else:
            record_outputs(problem, recorder, pending, start, (t, q, v, a))
        if progress is not None:
            progress(t)
        if not in_zone:
            h *= step_factor(err)
        if clipped:
            h = max(h, proposed)
    info["rejected_steps"] = rejected
    info["error_estimate_max"] = err_max
    info["error_estimate_sum"] = err_sum
    info["singular_splits"] = splits
    if far is not None:
        info["far_steps"] = far_steps
        info["zone_steps"] = zone_steps
    return steps
