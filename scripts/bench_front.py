"""Where simulate's default stands on the accuracy-speed front (issue 34).

Usage::

    python scripts/bench_front.py [--repeat 3] [--page docs/bench/front.md]

One run, every configuration interleaved in a new random order each round, after one
untimed run per scene (CPU: ``time.process_time`` of the call,
the smallest of ``--repeat`` rounds; BLAS on one thread), on the scenes of the issue:

- the benchmark's scenes (``closedchain bench``: their ``--quick`` horizons, error the
  largest coordinate difference from the scene's reference on its comparison grid);
- the driven slider-crank (tests/data/slider_crank_driven.urdf, 2 s; error: the slider's
  distance from the closed-form reference at 2 s, tests/slider_crank_reference.py);
- the N-four-bar N = 1 through 20 flat positions (20 s; error: B0's distance from the
  quadrature reference at 20 s, tests/nfourbar_reference.py);
- the change-point 4-bar (open branch from rest at 10 deg, 2 s, through its change
  point four times; error: largest coordinate difference on a 0.01 s grid from rk4 with
  stage projection at 25 us).

For each scene the page gives every run (error, CPU) and the acceptance of the issue:
the default's CPU over the cheapest configuration's at the default's error (log-log
interpolation on the Pareto front of every other run), and the error of the default's
integrator over kkt + DOP853's at the same rtol. Written to ``--page`` with the header
of the other generated pages (scripts/bench_page.py).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy is imported

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

import bench_page  # noqa: E402  (the generated pages' header)
import nfourbar_reference as nref  # noqa: E402
import slider_crank_reference as sref  # noqa: E402

import closedchain as cc  # noqa: E402
from closedchain._io import atomic_write  # noqa: E402
from closedchain.benchmark.families import nfourbar_urdf  # noqa: E402
from closedchain.benchmark.references import EXACT_REFERENCES  # noqa: E402
from closedchain.benchmark.runner import scenario_grid  # noqa: E402
from closedchain.benchmark.scenarios import (  # noqa: E402
    SCENARIOS,
    initial_state,
    load_scenario_mechanism,
    torque_function,
)
from closedchain.simulate import INTEGRATORS, SimulationSettings  # noqa: E402
from closedchain.simulate.request import DEFAULT_INTEGRATOR  # noqa: E402

#: The benchmark's scenes measured here (their --quick horizons).
BENCH_SCENES = (
    "fourbar-driven",
    "agile_eye-coasting",
    "agile_eye-computed-torque",
    "nfourbar2-singular",
    "pendulum3-passive",
)
#: rtol grid of the adaptive configurations (atol: see CONFIG_FAMILIES).
RTOLS = (1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)
#: The families compared: label -> (simulate's keyword arguments, atol / rtol, rtols).
CONFIG_FAMILIES = {
    "kkt/DOP853/none": (dict(method="kkt", integrator="DOP853", stabilization="none"), 1.0, RTOLS),
    "kkt/RK45/none": (dict(method="kkt", integrator="RK45", stabilization="none"), 1.0, RTOLS[:6]),
    "augmented-lagrangian/DOP853/none": (
        dict(integrator="DOP853", stabilization="none"),
        1.0,
        RTOLS[2:],
    ),
    "augmented-lagrangian/rk43/stage-projection": (dict(integrator="rk43"), 0.1, RTOLS[2:6]),
    "augmented-lagrangian/dop853-rk43/stage-projection": (
        dict(integrator="dop853-rk43"),
        0.1,
        RTOLS[:7],
    ),
}
#: The kkt + DOP853 family the default's error is compared with at the same rtol.
DOP853_FAMILY = "kkt/DOP853/none"
#: The issue's bars: CPU over the cheapest at equal error, error over DOP853's.
CPU_BAR, ERROR_BAR = 1.5, 10.0
#: Seed of the order of the runs within a round (shuffled every round).
ORDER_SEED = 34
#: The settings of every run (the benchmark's: no energy check, which a run's error
#: measures here; no joint limits, which a crank's turns pass).
SETTINGS = SimulationSettings(energy_tol=None, check_limits=False)
#: Change-point reference: rk4 with stage projection at this step [s].
CHANGE_POINT_REFERENCE_DT = 2.5e-5


@dataclass
class Scene:
    """A scene: what ``simulate`` gets and how a run's error is measured."""

    name: str
    mech: cc.Mechanism
    q0: np.ndarray
    v0: np.ndarray
    t_final: float
    tau: object
    t_eval: np.ndarray
    error: object  # error(traj) -> float [rad or m]


def _coordinate_error(mech, q, q_ref) -> float:
    """Largest coordinate difference [rad or m] between two sampled motions."""
    return float(
        max(np.max(np.abs(pin.difference(mech.model, a, b))) for a, b in zip(q, q_ref, strict=True))
    )


def bench_scene(name: str) -> Scene:
    scenario = SCENARIOS[name]
    mech = load_scenario_mechanism(str(ROOT / "models"), scenario)
    q0, v0 = initial_state(mech, scenario)
    tau = torque_function(mech, scenario)
    grid = scenario_grid(scenario, True)
    if scenario.exact:
        q_ref = EXACT_REFERENCES[scenario.exact][0](mech, q0, v0, grid)
    else:
        q_ref = cc.simulate(
            mech,
            q0,
            v0,
            grid[-1],
            tau=tau,
            t_eval=grid,
            method="kkt",
            integrator="DOP853",
            stabilization="none",
            rtol=1e-13,
            atol=1e-13,
            settings=SETTINGS,
        ).q
    return Scene(
        name, mech, q0, v0, grid[-1], tau, grid, lambda traj: _coordinate_error(mech, traj.q, q_ref)
    )


def slider_crank_scene() -> Scene:
    mech = cc.load(ROOT / "tests" / "data" / "slider_crank_driven.urdf")
    q0, v0, tau = sref.start_state(mech)
    theta, _ = sref.crank_state(sref.T_DRIVEN)
    x_ref = sref.slider(theta)
    return Scene(
        "slider-crank-driven (2 s)",
        mech,
        q0,
        v0,
        sref.T_DRIVEN,
        tau,
        np.array([0.0, sref.T_DRIVEN]),
        lambda traj: abs(traj.q[-1, -1] - x_ref),
    )


def nfourbar_scene(folder: Path) -> Scene:
    path = folder / "nfourbar_1.urdf"
    path.write_text(nfourbar_urdf(1))
    mech = cc.load(path)
    q0, v0 = nref.initial_state(mech)
    t_final = 20.0
    b0 = nref.point_b0(nref.crank_angle(1, t_final))
    return Scene(
        "nfourbar1-singular (20 s)",
        mech,
        q0,
        v0,
        t_final,
        None,
        np.linspace(0.0, t_final, 201),
        lambda traj: float(np.linalg.norm(nref.point_b0(traj.q[-1, 0]) - b0)),
    )


def change_point_scene() -> Scene:
    mech = cc.load(ROOT / "models" / "fourbar.urdf")
    q0 = cc.assemble(mech, np.radians([10.0, 50.0, 30.0]), fixed=["crank_joint"])
    v0 = np.zeros(mech.nv)
    t_final = 2.0
    grid = np.linspace(0.0, t_final, 201)
    q_ref = cc.simulate(
        mech, q0, v0, t_final, t_eval=grid, dt=CHANGE_POINT_REFERENCE_DT, settings=SETTINGS
    ).q
    return Scene(
        "fourbar-change-point (2 s)",
        mech,
        q0,
        v0,
        t_final,
        None,
        grid,
        lambda traj: _coordinate_error(mech, traj.q, q_ref),
    )


def configurations() -> list[tuple[str, float | None, dict]]:
    """(family, rtol or None, simulate's keyword arguments) of every run; the first is
    the default (no argument)."""
    configs = [("default", None, {})]
    for family, (kwargs, atol_ratio, rtols) in CONFIG_FAMILIES.items():
        for rtol in rtols:
            configs.append((family, rtol, dict(kwargs, rtol=rtol, atol=atol_ratio * rtol)))
    return configs


def run(scene: Scene, kwargs: dict) -> tuple[float, float, str]:
    """(error, CPU [s], status) of one run (NaN and the message's first line on failure)."""
    t0 = time.process_time()
    try:
        traj = cc.simulate(
            scene.mech,
            scene.q0,
            scene.v0,
            scene.t_final,
            tau=scene.tau,
            t_eval=scene.t_eval,
            settings=SETTINGS,
            **kwargs,
        )
    except cc.ClosedChainError as exc:
        return math.nan, math.nan, str(exc).splitlines()[0][:80]
    cpu = time.process_time() - t0
    return scene.error(traj), cpu, "ok"


def front_cpu(points: list[tuple[float, float]], error: float) -> float | None:
    """CPU [s] at ``error`` on the Pareto front of (error, CPU) ``points``, log-log
    interpolated between the two front points around it; None when no point reaches it."""
    front, best = [], math.inf
    for e, c in sorted(points):
        if c < best:
            front.append((e, c))
            best = c
    reach = [(e, c) for e, c in front if e <= error]
    if not reach:
        return None
    lo = reach[-1]  # the cheapest point at or below the error
    above = [(e, c) for e, c in front if e > error]
    if not above:
        return lo[1]
    hi = above[0]
    w = (math.log(error) - math.log(lo[0])) / (math.log(hi[0]) - math.log(lo[0]))
    return math.exp((1 - w) * math.log(lo[1]) + w * math.log(hi[1]))


def fmt(x: float | None, spec: str = ".2e") -> str:
    return "" if x is None or not math.isfinite(x) else format(x, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="interleaved rounds (min CPU)")
    parser.add_argument("--page", type=Path, help="write the generated page here")
    args = parser.parse_args()
    command = "python scripts/bench_front.py " + " ".join(sys.argv[1:])
    load_before, date = bench_page.load_average(), bench_page.today()
    with tempfile.TemporaryDirectory() as tmp:
        scenes = [bench_scene(n) for n in BENCH_SCENES]
        scenes += [slider_crank_scene(), nfourbar_scene(Path(tmp)), change_point_scene()]
        configs = configurations()
        results: dict[tuple[int, int], list] = {}
        rng = np.random.default_rng(ORDER_SEED)
        for scene in scenes:  # untimed: imports, caches and the compiled core built
            run(scene, configs[0][2])
        for _ in range(args.repeat):
            for i, scene in enumerate(scenes):
                # A new order every round: no configuration always runs first.
                for j in map(int, rng.permutation(len(configs))):
                    kwargs = configs[j][2]
                    err, cpu, status = run(scene, kwargs)
                    prev = results.get((i, j))
                    if prev is None or (math.isfinite(cpu) and not cpu >= prev[1]):
                        results[(i, j)] = [err, cpu, status]
                    family, rtol, _ = configs[j]
                    print(
                        f"{scene.name} {family} {rtol}: {err:.2e} {cpu:.3f} {status}",
                        file=sys.stderr,
                    )
    default = INTEGRATORS[DEFAULT_INTEGRATOR]
    lines = bench_page.run_header(
        "The default on the accuracy-speed front",
        command=command,
        date=date,
        load_before=load_before,
        about="The measurements of issue 34 (a default on the front).",
    )
    lines += [
        f"Default: `simulate` without arguments ({default.name} at rtol "
        f"{default.tolerances[0]:g}, atol {default.tolerances[1]:g}). Runs: "
        + "; ".join(f"{k} (atol = {r:g} rtol)" for k, (_, r, _) in CONFIG_FAMILIES.items())
        + f". CPU: smallest of {args.repeat} interleaved rounds, process time of the call.",
        "",
        "## Acceptance",
        "",
        f"CPU ratio: the default's CPU over the cheapest other run's at the default's error "
        f"(interpolated on their Pareto front, the default's own configuration left out; bar "
        f"{CPU_BAR}). Error ratio: the largest, over "
        f"the rtols both ran, of the error of {default.name} over {DOP853_FAMILY}'s at the "
        f"same rtol (bar {ERROR_BAR}).",
        "",
        "| scene | default error | default CPU [s] | cheapest other at that error [s] | CPU ratio "
        f"| error ratio to {DOP853_FAMILY} (worst rtol) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    body = []
    own = f"augmented-lagrangian/{default.name}/{default.default_stabilization}"
    for i, scene in enumerate(scenes):
        err0, cpu0, status0 = results[(i, 0)]
        others = [  # every run but the default's own configuration
            (results[(i, j)][0], results[(i, j)][1])
            for j in range(1, len(configs))
            if results[(i, j)][2] == "ok"
            and results[(i, j)][0] > 0
            and not (configs[j][0] == own and configs[j][1] == default.tolerances[0])
        ]
        ref_cpu = front_cpu(others, err0) if status0 == "ok" else None
        ratio = cpu0 / ref_cpu if ref_cpu else None
        worst, worst_rtol = None, None
        for j, (fam, rtol, _) in enumerate(configs):
            if fam != own:
                continue
            k = next(
                (k for k, c in enumerate(configs) if c[0] == DOP853_FAMILY and c[1] == rtol), None
            )
            if k is None or results[(i, k)][2] != "ok" or results[(i, j)][2] != "ok":
                continue
            r = results[(i, j)][0] / max(results[(i, k)][0], 1e-300)
            if worst is None or r > worst:
                worst, worst_rtol = r, rtol
        cheapest = fmt(ref_cpu, ".3g") if ref_cpu else "no other run reaches it"
        lines.append(
            f"| {scene.name} | {fmt(err0)} | {fmt(cpu0, '.3g')} | {cheapest} | "
            f"{fmt(ratio, '.2f')} | "
            + (f"{worst:.2f} (rtol {worst_rtol:g})" if worst is not None else "DOP853 does not run")
            + " |"
        )
        body += [
            f"## {scene.name}",
            "",
            "| configuration | rtol | error | CPU [s] | status |",
            "| --- | --- | --- | --- | --- |",
        ]
        for j, (fam, rtol, _) in enumerate(configs):
            err, cpu, status = results[(i, j)]
            body.append(f"| {fam} | {fmt(rtol, 'g')} | {fmt(err)} | {fmt(cpu, '.3g')} | {status} |")
        body.append("")
    lines += ["", *body]
    text = "\n".join(lines) + "\n"
    if args.page:
        with atomic_write(args.page, "w", encoding="utf-8") as f:
            f.write(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
