"""Adaptive integrators from scipy.integrate, with dense output at t_eval."""

from __future__ import annotations

import numpy as np
import scipy.integrate

from ..exceptions import SingularConfigurationError
from .chart import Chart
from .problem import Problem, gauss_work, passing_hint, project
from .settings import SimulationError


def run_adaptive(
    problem: Problem, recorder, q0, v0, t_final, control, spec, stab, t_eval, progress, info
) -> int:
    """Integrate with scipy's ``spec.name`` solver and stabilization ``stab``; return steps.

    Args:
        control: the step control; ``control.rtol`` and ``control.atol`` are
            the tolerances, with scipy's meaning.
    """
    mech = problem.mech
    nv = mech.nv
    rtol, atol, integrator = control.rtol, control.atol, spec.name
    partition = stab.partitions
    solver_cls = getattr(scipy.integrate, spec.name)
    state = {"q": np.array(q0)}  # warm start of the dependent solve
    chart = None

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
    elif mech.nq != nv:
        # Unit quaternions or (cos, sin) pairs: integrate a chart coordinate (chart.py).
        q, v = np.array(q0), np.array(v0)
        chart = Chart(mech.model, q0)

        def pack(q, v):
            return np.concatenate([chart.x(q), v])

        def unpack(y, t):
            return chart.q(y[:nv]), y[nv:]
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
        if chart is not None:
            return np.concatenate([chart.rate(y[:nv], v), a])
        return np.concatenate([v, a])

    def output(t, y):
        q, v = unpack(y, t)
        a = problem.accel(t, q, v)
        recorder.add(t, q, v, a, problem.lam)

    t0 = 0.0
    y = pack(q, v)
    problem.step_end(0.0, q, v, None)  # the work of tau: Gauss on each step (WorkMeter)
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
            **({"first_step": min(first_step, t_final - t0)} if first_step else {}),
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
            if problem.meter is not None:  # before the dense outputs within the step
                dense = solver.dense_output()
                # Not named `state`: that is the dict of the dependent solve's warm start.
                step_state = lambda s, d=dense: unpack(d(s), s)  # noqa: E731
                work = gauss_work(problem.meter.force, step_state, solver.t_old)
                problem.step_end(t_new, *unpack(solver.y, t_new), None, work)
            if pending is not None:
                if pending and pending[0] <= t_new:
                    sol = solver.dense_output()
                    while pending and pending[0] <= t_new * (1 + 1e-15):
                        output(pending[0], sol(pending[0]))
                        pending.pop(0)
            if stab.projects:
                q, v = project(problem, *unpack(solver.y, t_new), t_new)
                solver.y = pack(q, v)
                if hasattr(solver, "f"):
                    solver.f = fun(t_new, solver.y)
            # Every stabilization, partitioning included: near a branch point of
            # q_D(q_I) the error estimate is fooled and the dependent solve can jump
            # to another assembly branch (measured on the 4-bar's change point with
            # method "schur": energy drift 0.9 with max |phi| 1e-13).
            q_step = unpack(solver.y, t_new)[0]
            problem.check_regular(q_step, t_new)
            recorder.declared_residual(t_new, q_step)  # drift limit, every declared row
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
                    raise SingularConfigurationError.build(
                        mech.name,
                        "det(J_D)",
                        q=q,
                        cond=problem.cond_JD(q),
                        state="changed sign within the last step, ending",
                        detail=" of J_D at the step's end",
                        hint="the motion crossed a singular configuration, which adaptive "
                        "partitioning cannot follow; use a fixed-step integrator; "
                        f"{passing_hint()}",
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
            if chart is not None and t_new < t_final and chart.needs_recentre(solver.y[:nv]):
                chart.recentre(solver.y[:nv])
                t0, y = t_new, np.concatenate([np.zeros(nv), solver.y[nv:]])
                first_step = getattr(solver, "h_abs", None) or None
                restart = True
                break
        if not restart:
            break
    return steps
