"""Stability map: where each configuration stays on the manifold, drifts, diverges or raises.

For every case (a scenario and a horizon) and step size, each configuration
(method x fixed-step integrator x stabilization from the registries, plus
Pinocchio's Euler loop with Baumgarte gains) is classified as

* ``ok``: finite, every declared constraint row within :data:`DRIFT_ROW_TOL`;
* ``drift``: finite but a declared row above it (or closedchain's drift limit hit);
* ``diverged``: a non-finite state;
* ``raised``: an error (singular configuration, integrator failure), with its message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..closure import max_declared_residual
from ..dynamics.base import METHOD_CAPABILITIES, METHODS
from ..exceptions import ClosedChainError
from ..simulate import INTEGRATORS, STABILIZATIONS, SimulationError
from .peers import run_closedchain, run_pinocchio_euler
from .scenarios import (
    SCENARIOS,
    Scenario,
    fresh_compiled_core,
    initial_state,
    load_scenario_mechanism,
    torque_function,
)

#: A declared constraint row above this is "drift" [m or -].
DRIFT_ROW_TOL = 1e-6
#: Step sizes of the map [s] (each divides the output spacing of 0.1 s).
STEPS = (1e-1, 5e-2, 2e-2, 1e-2, 5e-3, 2e-3)
#: Output spacing of the map's runs [s]; a larger step is its own output spacing (it must
#: divide the case's horizon).
OUTPUT_DT = 0.1
#: The N-four-bar's steps: the grid goes on to 1 s, since on its parallelogram branch every
#: Euler step of Pinocchio's loop stays closed (a declared row below 1e-7 at every step up to
#: 1 s over 2 s), so only a longer horizon and larger steps separate the configurations.
NFOURBAR_STEPS = (1.0, 0.5, 0.2) + STEPS
#: The default stabilized fixed-step configuration (always reported beside the best one).
BEST_FIXED = "kkt/rk4/projection"
PEER = "pinocchio-euler/baumgarte"
#: Extra, smaller steps for the peer (cheap per step) [s].
PEER_EXTRA_STEPS = (1e-3, 5e-4, 2e-4, 1e-4)

STABILITY_COLUMNS = ("case", "config", "step", "status", "residual", "message")


@dataclass(frozen=True)
class StabilityCase:
    """A map row group: a scenario run for ``t_final`` seconds, all or only ``configs``."""

    name: str
    scenario: Scenario
    t_final: float
    configs: tuple[str, ...] | None = None
    steps: tuple[float, ...] = STEPS
    peer_extra_steps: tuple[float, ...] = PEER_EXTRA_STEPS


_OPEN_BRANCH = tuple(math.radians(x) for x in (10.0, 50.0, 30.0))

#: Agile Eye platform pitch driven towards pi/2, where J_D is singular (sigma_min of the
#: actuated partition 0.6 at home, 0.008 at pitch 1.45 rad: ``closedchain workspace``), by
#: computed torque, reached at t = 1 s, with yaw and roll sinusoids (pitch alone is a
#: rotation about an actuator axis, which any integrator keeps closed).
_TOWARDS_SINGULAR = replace(
    SCENARIOS["agile_eye-computed-torque"],
    name="agile_eye-towards-singular",
    scene=False,
    track=(
        ("platform_yaw", 0.0, 0.3, 0.2),
        ("platform_pitch", 0.0, 1.45, 0.25),
        ("platform_roll", 0.0, 0.2, 0.15),
    ),
)
_BRICARD = Scenario(
    "bricard-passive",
    "bricard.urdf",
    t_final=2.0,
    quick_t_final=1.0,
    description="Bricard linkage (overconstrained), released from q_ref under gravity",
)

#: name -> case.
CASES: dict[str, StabilityCase] = {
    c.name: c
    for c in (
        StabilityCase("fourbar regular 2 s", SCENARIOS["fourbar-passive"], 2.0),
        StabilityCase(
            "fourbar change point (open branch) 1 s",
            replace(SCENARIOS["fourbar-passive"], name="fourbar-open", guess=_OPEN_BRANCH),
            1.0,
        ),
        StabilityCase("agile_eye coasting 1 s", SCENARIOS["agile_eye-coasting"], 1.0),
        # Every evaluation runs the Python controller (~1.5 ms): fewer configurations.
        StabilityCase(
            "agile_eye driven towards a singular orientation 1 s",
            _TOWARDS_SINGULAR,
            1.0,
            configs=(
                BEST_FIXED,
                "kkt/rk4/stage-projection",
                "kkt/rk4/baumgarte",
                "kkt/semi-implicit/projection",
                "kkt/euler/projection",
                "augmented-lagrangian/rk4/projection",
                "augmented-lagrangian/ali3p/mass-orthogonal",
                PEER,
            ),
            peer_extra_steps=(1e-3, 5e-4),
        ),
        # 20 s: about a dozen flat positions. Over 2 s (the case before) Pinocchio's loop
        # and closedchain's stabilized configurations were ok at every step up to 1 s (ratio
        # 1 by structure); over 20 s the peer's Euler steps diverge from 0.1 s on.
        StabilityCase(
            "nfourbar N=2 through flat positions 20 s",
            SCENARIOS["nfourbar2-singular"],
            20.0,
            steps=NFOURBAR_STEPS,
        ),
        StabilityCase("bricard 2 s", _BRICARD, 2.0),
        StabilityCase(
            "fourbar passive 100 s",
            SCENARIOS["fourbar-passive"],
            100.0,
            # Configurations the compiled core runs (100 s at every step of the grid).
            configs=(BEST_FIXED, "kkt/semi-implicit/projection", "kkt/rk4/baumgarte", PEER),
            steps=(1e-1, 5e-2, 2e-2, 1e-2, 5e-3, 2e-3),
            # The peer is never ok on the 2 s case down to 1e-4 s; 1e6 Python steps here.
            peer_extra_steps=(1e-3, 5e-4),
        ),
    )
}


def stability_configurations() -> list[str]:
    """``method/integrator/stabilization`` names: kkt with every fixed-step integrator and
    every stabilization it supports (an integrator that needs a method capability, such as
    ALI3-P, with the first method that has it), every method with rk4 and projection, every
    singular-robust method with rk4 and stage projection (the configuration that passes
    singular positions), and the peer."""
    out = []
    for name, spec in INTEGRATORS.items():
        if spec.kind != "fixed":
            continue
        method = "kkt"
        if spec.method_capabilities:
            able = [
                m
                for m in sorted(METHODS)
                if all(getattr(METHOD_CAPABILITIES[m], c) for c in spec.method_capabilities)
            ]
            if not able:
                continue
            method = able[0]
        for stab in spec.stabilizations:
            if stab in STABILIZATIONS:
                out.append(f"{method}/{name}/{stab}")
    for method in sorted(METHODS):
        if method == "kkt" or "rk4" not in INTEGRATORS:
            continue
        out.append(f"{method}/rk4/projection")
        if (
            METHOD_CAPABILITIES[method].singular_robust
            and "stage-projection" in INTEGRATORS["rk4"].stabilizations
        ):
            out.append(f"{method}/rk4/stage-projection")
    out.append(PEER)
    return out


def make_stability_jobs(cases: list[str], models_dir: str) -> list[dict]:
    """One job per case x configuration x step."""
    jobs = []
    for case in cases:
        c = CASES[case]
        for cfg in c.configs or stability_configurations():
            for dt in c.steps + (c.peer_extra_steps if cfg == PEER else ()):
                jobs.append(dict(case=case, config=cfg, step=dt, models_dir=models_dir))
    return jobs


def run_stability_job(job: dict) -> dict:
    """Classify one (case, configuration, step)."""
    c = CASES[job["case"]]
    sc = c.scenario
    mech = load_scenario_mechanism(job["models_dir"], sc)
    fresh_compiled_core(mech)
    q0, v0 = initial_state(mech, sc)
    tau_fn = torque_function(mech, sc)
    spacing = max(OUTPUT_DT, job["step"])
    n = round(c.t_final / spacing)
    t_grid = np.linspace(0.0, n * spacing, n + 1)
    out = dict(
        case=job["case"], config=job["config"], step=job["step"], residual=math.nan, message=""
    )
    try:
        if job["config"] == PEER:
            res = run_pinocchio_euler(mech, q0, v0, t_grid, tau_fn, dt=job["step"])
        else:
            method, integrator, stab = job["config"].split("/")
            with np.errstate(all="ignore"):
                res = run_closedchain(
                    mech,
                    q0,
                    v0,
                    t_grid,
                    tau_fn,
                    method=method,
                    integrator=integrator,
                    stabilization=stab,
                    dt=job["step"],
                )
    except SimulationError as exc:
        status = (
            "drift" if "drift" in str(exc) else ("diverged" if "finite" in str(exc) else "raised")
        )
        out.update(status=status, message=str(exc).splitlines()[0][:200])
        return out
    except (ClosedChainError, np.linalg.LinAlgError, ValueError) as exc:
        out.update(status="raised", message=str(exc).splitlines()[0][:200])
        return out
    if res.status != "ok" or not (np.all(np.isfinite(res.q)) and np.all(np.isfinite(res.v))):
        out.update(status="diverged", message=res.message or "non-finite state")
        return out
    r = max_declared_residual(mech, res.q)
    out.update(residual=r, status="ok" if r <= DRIFT_ROW_TOL else "drift")
    return out


def largest_ok_step(rows: list[dict], case: str, config: str) -> float:
    """Largest step at which ``config`` is "ok" on ``case`` with every smaller step also ok
    (0 when none)."""
    mine = sorted(
        (r for r in rows if r["case"] == case and r["config"] == config), key=lambda r: r["step"]
    )
    best = 0.0
    for r in mine:
        if r["status"] != "ok":
            break
        best = r["step"]
    return best


def best_fixed(rows: list[dict], case: str) -> tuple[str, float]:
    """closedchain's stabilized fixed-step configuration with the largest ok step on ``case``
    and that step (ties: :data:`BEST_FIXED`, else the first name)."""
    configs = sorted(
        {
            r["config"]
            for r in rows
            if r["case"] == case and r["config"] != PEER and not r["config"].endswith("/none")
        }
    )
    best = ("", 0.0)
    for cfg in configs:
        step = largest_ok_step(rows, case, cfg)
        if step > best[1]:
            best = (cfg, step)
    if best[1] > 0 and largest_ok_step(rows, case, BEST_FIXED) == best[1]:
        best = (BEST_FIXED, best[1])
    return best


def _extrapolated_ratio(rows: list[dict], case: str, best: float) -> str:
    """When the peer is never ok: its drift at its smallest step, and, with the drift
    proportional to the step (first order, as measured), the step it would need."""
    peer = sorted(
        (r for r in rows if r["case"] == case and r["config"] == PEER), key=lambda r: r["step"]
    )
    if not peer:
        return "peer not run"
    small = peer[0]
    text = f"peer never ok down to {small['step']:g} s"
    residual = small.get("residual", math.nan)
    if small["status"] == "drift" and math.isfinite(residual) and residual > 0:
        needed = DRIFT_ROW_TOL * small["step"] / residual
        text += f" (max row {residual:.1e} there; ok would need ~{needed:.1e} s if drift ~ dt"
        text += f": ratio ~{best / needed:.3g})" if best > 0 else ")"
    elif best == 0:
        text = "neither ok"
    return text


def stability_summary(rows: list[dict]) -> str:
    """Markdown: per case, the largest ok step of closedchain's best stabilized fixed-step
    configuration, of the default one (:data:`BEST_FIXED`) and of Pinocchio's Euler loop with
    Baumgarte gains, and the ratio best / peer (target >= 10)."""
    lines = [
        f"| case | best stabilized fixed-step config | its largest ok step [s] "
        f"| {BEST_FIXED} [s] | {PEER} [s] | ratio best / peer |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for case in sorted({r["case"] for r in rows}):
        cfg, a = best_fixed(rows, case)
        d = largest_ok_step(rows, case, BEST_FIXED)
        b = largest_ok_step(rows, case, PEER)
        if b > 0:
            ratio = f"{a / b:.3g}"
        else:
            ratio = _extrapolated_ratio(rows, case, a)
        lines.append(f"| {case} | {cfg or '-'} | {a:g} | {d:g} | {b:g} | {ratio} |")
    return "\n".join(lines) + "\n"
