"""Measure the compiled core against the numpy backend and the thirty-line peer.

1. Per evaluation [us] on the 4-bar and the Agile Eye at a random consistent
   state: the compiled right-hand side called from Python, the same inside the
   C++ loop (``Core.repeat``; methods kkt and augmented-lagrangian, each
   repetition a whole evaluation), the numpy method, and a tuned
   ``pinocchio.constraintDynamics`` call from Python (containers made once,
   ``ProximalSettings`` of the library's defaults). In-loop cost also as
   (CPU of a 10 s compiled run) / (its evaluations): DOP853 without
   stabilization, and the default configuration (augmented-lagrangian, rk4
   1 ms, stage projection: its CPU includes the projections), against the
   numpy backend on the same request.
2. Whole trajectories at matched error: closedchain.simulate (DOP853, no
   stabilization, default backend; methods kkt and augmented-lagrangian) against
   the thirty-line peer
   (pinocchio.constraintDynamics as the right-hand side of scipy's DOP853) on
   the 4-bar (crossed branch, from rest, 10 s; errors 1e-6 and 1e-9 rad) and
   the coasting Agile Eye (no gravity, 10 s; error 1e-6 rad). For each side the
   tolerance rtol = atol = 10^-k is swept; the error is max |q - q_ref| over
   101 output times against a DOP853 run at 1e-13; each side's CPU time at a
   target error is that of the cheapest tolerance reaching it. Repeats are
   interleaved; CPU times are process times (min over repeats); ratios come
   from the same run.
3. Coordinate partitioning against no stabilization (DOP853 at 1e-9, method
   kkt, 10 s, both compiled; the issue's target is a ratio <= 1.5) on the 4-bar
   and the coasting Agile Eye, with steps and evaluations of each side, and the
   numpy partitioning run of the same request; per evaluation, the compiled
   reduced method (from Python and in the C++ loop) against the numpy one.
4. The benchmark's N-four-bar scenario (nfourbar2-singular, N = 2 through its
   flat positions, 4 s, 0.05 s grid): closedchain's augmented Lagrangian with
   stage projection (rk4 at 5e-2 to 1e-2 s, semi-implicit at 1e-2 s; whole
   simulate calls) against the lesson's scheme (compiled, 1e-2 and 5e-3 s) and
   Pinocchio's own loop (constraintDynamics + semi-implicit Euler, 5e-4 and
   2e-4 s), all through the benchmark's runners; error against the scenario's
   exact reference; ratios at 1e-3 (seed) and 1e-6 (Pinocchio's loop).

Timing is noisy on a shared machine: run it alone.
Run: python scripts/bench_core.py [--repeat 3] [--sections evaluation runs matched nfourbar]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import scipy.integrate

import closedchain as cc
from closedchain import compiled
from closedchain.benchmark.evaluation import cpu_us_per_call
from closedchain.dynamics.base import DEFAULT_SETTINGS, get_method

MODELS = Path(__file__).resolve().parent.parent / "models"
T_FINAL = 10.0
TOLS = [10.0**-k for k in range(4, 14)]


def per_call_us(fn, number: int, repeat: int) -> float:
    """Median over ``repeat`` of the mean CPU time of ``number`` calls [us]."""
    return float(np.median([cpu_us_per_call(fn, number) for _ in range(repeat)]))


def peer_setup(mech):
    cms, cds, _, pdata = mech.pinocchio_constraints()
    prox = DEFAULT_SETTINGS.pinocchio_proximal()
    return cms, cds, pdata, prox


def per_evaluation(name: str, number: int, repeat: int) -> None:
    mech = cc.load(MODELS / f"{name}.urdf")
    q, v = cc.random_consistent_state(mech, np.random.default_rng(0))
    tau = np.zeros(mech.nv)
    fd = compiled.compiled_dynamics(mech, "kkt")
    fd_al = compiled.compiled_dynamics(mech, "augmented-lagrangian")
    cms, cds, pdata, prox = peer_setup(mech)
    kkt = get_method("kkt")
    n_loop = 20 * number
    loops = {"compiled rhs in the C++ loop": fd, "same, augmented-lagrangian": fd_al}
    rows = {
        "compiled rhs from Python": lambda: fd.forward(q, v, tau),
        "compiled rhs in the C++ loop": None,
        "same, augmented-lagrangian": None,
        "numpy rhs (method kkt)": lambda: kkt(mech, q, v, tau, DEFAULT_SETTINGS),
        "pin.constraintDynamics (tuned)": lambda: pin.constraintDynamics(
            mech.model, pdata, q, v, tau, cms, cds, prox
        ),
    }
    res: dict[str, list[float]] = {k: [] for k in rows}
    for _ in range(repeat):  # interleaved
        for label, fn in rows.items():
            if fn is None:
                t0 = time.process_time()
                loops[label].core.repeat(q, v, tau, n_loop)
                res[label].append((time.process_time() - t0) / n_loop * 1e6)
            else:
                res[label].append(per_call_us(fn, number, 1))
    print(f"\n{name} (nv = {mech.nv}, nc = {mech.nc}): CPU us per evaluation (median)")
    ref = float(np.median(res["pin.constraintDynamics (tuned)"]))
    for label, r in res.items():
        m = float(np.median(r))
        print(f"  {label:34s} {m:8.2f}   {m / ref:6.2f} x pin.constraintDynamics")


def per_evaluation_reduced(name: str, number: int, repeat: int) -> None:
    """The reduced method per evaluation: compiled (from Python, in the C++ loop) vs numpy."""
    mech = cc.load(MODELS / f"{name}.urdf")
    q, v = cc.random_consistent_state(mech, np.random.default_rng(0))
    tau = np.zeros(mech.nv)
    fd = compiled.compiled_dynamics(mech, "reduced")
    reduced = get_method("reduced")
    n_loop = 20 * number
    res: dict[str, list[float]] = {"compiled from Python": [], "compiled in the C++ loop": [],
                                   "numpy": []}  # fmt: skip
    for _ in range(repeat):  # interleaved
        res["compiled from Python"].append(per_call_us(lambda: fd.forward(q, v, tau), number, 1))
        t0 = time.process_time()
        fd.core.repeat(q, v, tau, n_loop)
        res["compiled in the C++ loop"].append((time.process_time() - t0) / n_loop * 1e6)
        res["numpy"].append(
            per_call_us(lambda: reduced(mech, q, v, tau, DEFAULT_SETTINGS), number, 1)
        )
    ref = float(np.median(res["numpy"]))
    print(f"\n{name}: method reduced, CPU us per evaluation (median)")
    for label, r in res.items():
        m = float(np.median(r))
        print(f"  {label:34s} {m:8.2f}   {ref / m:7.1f} x faster than numpy")


def per_evaluation_in_runs(name: str, problem, repeat: int) -> None:
    """CPU of whole 10 s runs divided by their evaluations; compiled against numpy."""
    mech, q0, v0 = problem()
    t_eval = np.linspace(0.0, T_FINAL, 11)
    runs = {
        "DOP853 1e-9, kkt, none": dict(
            integrator="DOP853", rtol=1e-9, atol=1e-9, method="kkt", stabilization="none"
        ),
        "DOP853 1e-9, augmented-lagrangian, none": dict(
            integrator="DOP853", rtol=1e-9, atol=1e-9, stabilization="none"
        ),
        "default: augmented-lagrangian, rk4 1 ms, stage-projection": dict(),
    }
    print(f"\n{name}, {T_FINAL:g} s: CPU per evaluation inside whole runs [us] (min)")
    for label, kw in runs.items():
        res: dict[str, list[tuple[float, int]]] = {"compiled": [], "numpy": []}
        for i in range(repeat):  # interleaved; the numpy run once (it takes seconds)
            for backend in ("compiled", "numpy") if i == 0 else ("compiled",):
                t0 = time.process_time()
                traj = cc.simulate(mech, q0, v0, T_FINAL, t_eval=t_eval, backend=backend, **kw)
                res[backend].append((time.process_time() - t0, traj.info.evaluations))
        c_cpu, c_n = min(res["compiled"])
        n_cpu, n_n = min(res["numpy"])
        print(
            f"  {label:58s} compiled {c_cpu * 1e6 / c_n:7.3f} us x {c_n} ({c_cpu:.4f} s), "
            f"numpy {n_cpu * 1e6 / n_n:7.1f} us ({n_cpu:.2f} s): ratio {c_cpu / n_cpu:.4f}"
        )


# -- whole trajectories -----------------------------------------------------------------


def fourbar_problem():
    mech = cc.load(MODELS / "fourbar.urdf")
    q0 = cc.assemble(mech, np.radians((10.0, -65.0, -104.0)), fixed=["crank_joint"])
    return mech, q0, np.zeros(mech.nv)


def agile_eye_problem():
    mech = cc.load(MODELS / "agile_eye.urdf")
    mech.model.gravity.linear[:] = 0.0
    v = np.zeros(mech.nv)
    v[mech.independent_idx_v] = (0.3, -0.2, 0.1)
    return mech, mech.q_ref.copy(), cc.project_velocity(mech, mech.q_ref, v, fixed="independent")


def peer_run(mech, q0, v0, tol, t_eval):
    """The thirty-line peer: pin.constraintDynamics in scipy's DOP853."""
    model = mech.model
    cms, cds, pdata, prox = peer_setup(mech)
    nv = model.nv
    tau = np.zeros(nv)

    def rhs(t, y):
        a = pin.constraintDynamics(model, pdata, y[:nv], y[nv:], tau, cms, cds, prox)
        return np.concatenate([y[nv:], a])

    t0 = time.process_time()
    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, T_FINAL), np.concatenate([q0, v0]), method="DOP853",
        rtol=tol, atol=tol, t_eval=t_eval,
    )  # fmt: skip
    cpu = time.process_time() - t0
    return sol.y[:nv].T, cpu


def cc_run(mech, q0, v0, tol, t_eval, stabilization="none", method="kkt"):
    t0 = time.process_time()
    traj = cc.simulate(
        mech, q0, v0, T_FINAL, integrator="DOP853", rtol=tol, atol=tol, t_eval=t_eval,
        stabilization=stabilization, method=method,
    )  # fmt: skip
    return traj.q, time.process_time() - t0, traj.info


def matched(name, problem, targets, repeat):
    mech, q0, v0 = problem()
    t_eval = np.linspace(0.0, T_FINAL, 101)
    q_ref = cc.simulate(
        mech, q0, v0, T_FINAL, integrator="DOP853", rtol=1e-13, atol=1e-13, t_eval=t_eval
    ).q
    sides = ("peer", "kkt", "augmented-lagrangian")
    err: dict[str, dict] = {side: {} for side in sides}
    cpu: dict[str, dict] = {side: {tol: [] for tol in TOLS} for side in sides}
    backend = None
    for _ in range(repeat):
        for tol in TOLS:
            qp, cp = peer_run(mech, q0, v0, tol, t_eval)
            err["peer"][tol] = float(np.max(np.abs(qp - q_ref)))
            cpu["peer"][tol].append(cp)
            for method in sides[1:]:
                qc, ccpu, info = cc_run(mech, q0, v0, tol, t_eval, method=method)
                backend = info.backend
                err[method][tol] = float(np.max(np.abs(qc - q_ref)))
                cpu[method][tol].append(ccpu)
    print(f"\n{name}, {T_FINAL:g} s, DOP853 (closedchain backend: {backend}): error [rad], CPU [s]")
    print(f"  {'tol':>7s}" + "".join(f" {s[:10] + ' err':>14s} {'CPU':>8s}" for s in sides))
    for tol in TOLS:
        print(
            f"  {tol:7.0e}"
            + "".join(f" {err[s][tol]:14.2e} {min(cpu[s][tol]):8.4f}" for s in sides)
        )
    for target in targets:
        best = {}
        for side in sides:
            ok = [min(cpu[side][t]) for t in TOLS if err[side][t] <= target]
            best[side] = min(ok) if ok else float("nan")
        print(
            f"  error <= {target:.0e}: peer {best['peer']:.4f} s; "
            + "; ".join(
                f"{m} {best[m]:.4f} s, ratio {best[m] / best['peer']:.3f}" for m in sides[1:]
            )
        )


def partitioning_cost(name, problem, repeat, tol=1e-9):
    """Partitioning against no stabilization, both compiled (interleaved, min CPU), and
    the numpy partitioning run once."""
    mech, q0, v0 = problem()
    t_eval = np.linspace(0.0, T_FINAL, 101)
    runs: dict[str, list] = {"none": [], "partitioning": []}
    for _ in range(repeat):
        for stab in runs:
            _, c, info = cc_run(mech, q0, v0, tol, t_eval, stabilization=stab)
            runs[stab].append((c, info))
    t0 = time.process_time()
    ref = cc.simulate(
        mech, q0, v0, T_FINAL, integrator="DOP853", rtol=tol, atol=tol, t_eval=t_eval,
        stabilization="partitioning", method="kkt", backend="numpy",
    )  # fmt: skip
    numpy_cpu = time.process_time() - t0
    print(f"\n{name}, {T_FINAL:g} s, DOP853 at {tol:.0e}, method kkt: partitioning vs none")
    best = {}
    for stab, r in runs.items():
        c, info = min(r, key=lambda x: x[0])
        best[stab] = c
        print(
            f"  {stab:13s} {c:.4f} s CPU ({info.backend}), {info.steps} steps, "
            f"{info.evaluations} evaluations, {c / info.evaluations * 1e6:.2f} us per "
            f"evaluation, re-partitions {len(info.repartitions)}"
        )
    print(
        f"  ratio partitioning / none: {best['partitioning'] / best['none']:.2f}; numpy "
        f"partitioning {numpy_cpu:.3f} s ({ref.info.steps} steps, re-partitions "
        f"{len(ref.info.repartitions)}): compiled/numpy {best['partitioning'] / numpy_cpu:.4f}"
    )


def nfourbar_against_euler(repeat: int) -> None:
    """CPU of the nfourbar2-singular scenario: closedchain's configurations of its front at
    1e-3 and 1e-6 against the lesson's scheme and Pinocchio's Euler loop at the steps around
    those errors (the benchmark's runners and grid, interleaved); the ratios from the cheapest
    run reaching each error and at exactly it (log-log on each front, as ``ratios.md``)."""
    from closedchain.benchmark.analysis import cheapest_at, cpu_at
    from closedchain.benchmark.peers import RUNNERS
    from closedchain.benchmark.references import EXACT_REFERENCES
    from closedchain.benchmark.runner import scenario_grid
    from closedchain.benchmark.scenarios import (
        SCENARIOS,
        fresh_compiled_core,
        initial_state,
        load_scenario_mechanism,
        torque_function,
    )

    sc = SCENARIOS["nfourbar2-singular"]
    mech = load_scenario_mechanism(str(MODELS), sc)
    q0, v0 = initial_state(mech, sc)
    tau = torque_function(mech, sc)
    grid = scenario_grid(sc, False)
    q_ref = EXACT_REFERENCES[sc.exact][0](mech, q0, v0, grid)

    def ours(integrator: str, dt: float):
        kw = dict(method=sc.method, integrator=integrator, stabilization="stage-projection")
        return lambda: RUNNERS["closedchain"](mech, q0, v0, grid, tau, dt=dt, **kw)

    runs = {
        ("closedchain", f"{sc.method}/rk4/stage-projection dt={dt:g}"): ours("rk4", dt)
        for dt in (5e-2, 2.5e-2, 1.25e-2, 1e-2)
    }
    runs[("closedchain", f"{sc.method}/semi-implicit/stage-projection dt=0.01")] = ours(
        "semi-implicit", 1e-2
    )
    for dt in (1e-2, 5e-3):
        runs[("lesson", f"euler/2 newton (compiled) dt={dt:g}")] = lambda dt=dt: RUNNERS["lesson"](
            mech, q0, v0, grid, tau, dt=dt, backend="compiled"
        )
    for dt in (5e-4, 2e-4):
        runs[("pinocchio-euler", f"constraintDynamics/semi-implicit/baumgarte dt={dt:g}")] = (
            lambda dt=dt: RUNNERS["pinocchio-euler"](mech, q0, v0, grid, tau, dt=dt)
        )
    cpu: dict[tuple, list[float]] = {k: [] for k in runs}
    err: dict[tuple, float] = {}
    for _ in range(repeat):
        for key, run in runs.items():
            fresh_compiled_core(mech)
            out = run()
            cpu[key].append(out.cpu_s)
            err[key] = max(
                float(np.max(np.abs(pin.difference(mech.model, a, b))))
                for a, b in zip(out.q, q_ref, strict=True)
            )
    t = float(grid[-1])
    print(f"\nnfourbar2-singular ({t:g} s): CPU [s/s] (median of {repeat}), error [rad]")
    rows = []
    for (family, label), c in cpu.items():
        rows.append(
            dict(
                family=family, cpu_s=float(np.median(c)) / t, error=err[family, label], status="ok"
            )
        )
        print(f"  {family:16s} {label:52s} {rows[-1]['cpu_s']:9.5f}  error {rows[-1]['error']:.2e}")
    mine = [r for r in rows if r["family"] == "closedchain"]
    for peer, target in (("lesson", 1e-3), ("pinocchio-euler", 1e-6)):
        theirs = [r for r in rows if r["family"] == peer]
        a, b = cheapest_at(mine, target), cheapest_at(theirs, target)
        print(
            f"  closedchain / {peer} at {target:.0e}: {a['cpu_s'] / b['cpu_s']:.4f} "
            f"(interpolated on the fronts {cpu_at(mine, target) / cpu_at(theirs, target):.4f})"
        )


#: Sections of the script (--sections): 1. per evaluation, in whole runs; 2. matched
#: error (with partitioning); 3. the N-four-bar against Pinocchio's Euler loop.
SECTIONS = ("evaluation", "runs", "matched", "partitioning", "nfourbar")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--number", type=int, default=2000)
    parser.add_argument(
        "--sections",
        nargs="+",
        choices=SECTIONS,
        default=list(SECTIONS),
        help="which measurements to run (default: all)",
    )
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {platform.platform()}")
    print(f"nproc {os.cpu_count()}, load average {os.getloadavg()}")
    if "evaluation" in args.sections:
        for name in ("fourbar", "agile_eye"):
            per_evaluation(name, args.number, args.repeat)
    if "runs" in args.sections:
        per_evaluation_in_runs("4-bar", fourbar_problem, args.repeat)
    if "matched" in args.sections:
        matched("4-bar (crossed, from rest)", fourbar_problem, [1e-6, 1e-9], args.repeat)
        matched("Agile Eye (coasting, no gravity)", agile_eye_problem, [1e-6], args.repeat)
    if "partitioning" in args.sections:
        for name in ("fourbar", "agile_eye", "nfourbar_2"):
            per_evaluation_reduced(name, args.number, args.repeat)
        partitioning_cost("4-bar (crossed, from rest)", fourbar_problem, args.repeat)
        partitioning_cost("Agile Eye (coasting, no gravity)", agile_eye_problem, args.repeat)
    if "nfourbar" in args.sections:
        nfourbar_against_euler(args.repeat)
    print(f"load average at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
