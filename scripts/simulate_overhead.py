"""Measure what ``closedchain.simulate`` costs around the compiled integration loop.

Every call pays a fixed cost in Python (argument checks, the start checks of q0 and
v0, the core's configuration, the Trajectory and its SimulationInfo) and a cost per
output sample (moving the core's samples into the Trajectory); short runs such as
the benchmark's work-precision jobs pay it on top of the integration. Measured, on
the compiled backend and the default configuration (augmented-lagrangian, rk4,
stage projection):

* fixed cost per call [us]: a one-step run of the 4-bar (crossed branch, at rest)
  minus the same step run by the compiled core alone (``Core.run_fixed``);
* cost per output sample [us]: a 1 s run of the 4-bar at 1 ms (the lesson's scheme, the
  cheapest compiled step) with every step an output (1001 samples) minus the same run
  with 2 outputs, per extra sample; the core's own share (the same difference of
  ``Core.run_fixed`` calls) alongside;
* whole calls [us]: the benchmark's N-four-bar scenario (nfourbar2-singular, N = 2,
  4 s on its 0.05 s grid, rk4 at 0.05 and 0.01 s) and the 4-bar for 10 s at the
  default step (10001 samples), with the core's time for the same request.

With ``--against REV`` the same calls run on the ``closedchain`` package of git
revision REV (its ``src/closedchain`` exported to a temporary directory and
imported beside this tree's, sharing the compiled core: the C++ is the same when
only Python changed), interleaved with this tree's in every repeat; the table
gives both and their ratio, and says whether every call's results (arrays and info)
are identical to REV's. CPU times (``time.process_time``), median over repeats.

Run: python scripts/simulate_overhead.py [--repeat 7] [--against c7d7625]
"""

from __future__ import annotations

import argparse
import importlib
import io
import os
import platform
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

import closedchain
from closedchain import compiled
from closedchain.benchmark import scenarios as S
from closedchain.benchmark.evaluation import cpu_us_per_call
from closedchain.dynamics import DEFAULT_SETTINGS
from closedchain.simulate import compiled_loops
from closedchain.simulate.fixed import output_grid
from closedchain.simulate.problem import Problem
from closedchain.simulate.registry import get_stabilization
from closedchain.simulate.settings import DEFAULT_SIMULATION_SETTINGS, lesson_settings

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"
#: The per-sample rows run the lesson's scheme (kkt, semi-implicit Euler, projection at
#: 1 ms): the cheapest compiled step, so that the samples' cost stands out of the noise.
LESSON = {
    "method": "kkt",
    "integrator": "semi-implicit",
    "stabilization": "projection",
    "dt": 1e-3,
    "settings": lesson_settings(),
}


def import_revision(rev: str, workdir: Path):
    """Import ``src/closedchain`` of git revision ``rev`` as package ``closedchain_ref``."""
    data = subprocess.run(
        ["git", "-C", str(ROOT), "archive", rev, "src/closedchain"],
        check=True,
        capture_output=True,
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        tar.extractall(workdir, filter="data")
    src = workdir / "src"
    (src / "closedchain").rename(src / "closedchain_ref")
    # One compiled core in the process: the reference package uses this tree's.
    sys.modules["closedchain_ref._core"] = compiled._core
    sys.path.insert(0, str(src))
    try:
        return importlib.import_module("closedchain_ref")
    finally:
        sys.path.remove(str(src))


class Case:
    """The mechanisms and starts of one package (this tree's or the reference's)."""

    def __init__(self, pkg) -> None:
        self.pkg = pkg
        sim = importlib.import_module(pkg.__name__ + ".simulate")
        self.simulate = sim.simulate
        fb = S.get_scenario("fourbar-passive")
        self.fourbar = pkg.load(MODELS / fb.urdf)
        self.fb_q0 = pkg.assemble(self.fourbar, np.asarray(fb.guess), fixed=list(fb.fixed))
        self.fb_v0 = np.zeros(self.fourbar.nv)
        nfb = S.get_scenario("nfourbar2-singular")
        self.nfb = nfb
        self.nfourbar = pkg.load(MODELS / nfb.urdf)
        q0 = pkg.assemble(self.nfourbar, np.asarray(nfb.guess), fixed=list(nfb.fixed))
        v0 = np.zeros(self.nfourbar.nv)
        v0[self.nfourbar.independent_idx_v] = nfb.v_independent
        self.nfb_q0 = q0
        self.nfb_v0 = pkg.project_velocity(self.nfourbar, q0, v0, fixed="independent")
        self.nfb_grid = np.linspace(0.0, nfb.t_final, round(nfb.t_final / nfb.output_dt) + 1)

    def calls(self) -> dict:
        """name -> zero-argument call of ``simulate``."""
        sim, fb, nfb = self.simulate, self.fourbar, self.nfourbar
        q0, v0 = self.fb_q0, self.fb_v0
        every = np.linspace(0.0, 1.0, 1001)
        two = np.array([0.0, 1.0])
        out = {
            "4-bar, 1 step": lambda: sim(fb, q0, v0, 1e-3, dt=1e-3),
            "4-bar 1 s, 1001 samples": lambda: sim(fb, q0, v0, 1.0, t_eval=every, **LESSON),
            "4-bar 1 s, 2 samples": lambda: sim(fb, q0, v0, 1.0, t_eval=two, **LESSON),
            "4-bar 10 s, default": lambda: sim(fb, q0, v0, 10.0),
        }
        for dt in (0.05, 0.01):
            out[f"N-four-bar 4 s, rk4 {dt:g} s"] = lambda dt=dt: sim(
                nfb,
                self.nfb_q0,
                self.nfb_v0,
                self.nfb.t_final,
                method=self.nfb.method,
                dt=dt,
                t_eval=self.nfb_grid,
            )
        return out


def core_calls(case: Case) -> dict:
    """name -> the compiled core's run of the same request (this tree's setup)."""

    def run(mech, q0, v0, t_final, dt, t_eval, method="augmented-lagrangian", lesson=False):
        stab = get_stabilization("projection" if lesson else "stage-projection")
        settings = lesson_settings() if lesson else DEFAULT_SIMULATION_SETTINGS
        problem = Problem(mech, method, None, DEFAULT_SETTINGS, settings)
        problem.singular_robust = not lesson
        core = compiled_loops._prepare(problem, {"method": method}, stab)
        # A core of its own (simulate reconfigures the mechanism's shared one every call).
        mech.__dict__.pop("_compiled_cores", None)
        code = compiled.INTEGRATOR_CODES["semi-implicit" if lesson else "rk4"]
        dt, n, steps = output_grid(t_final, dt, t_eval)
        steps = np.arange(n + 1) if steps is None else steps
        steps = np.asarray(steps, dtype=np.int32)
        return lambda: core.run_fixed(code, q0, v0, float(dt), int(n), steps, True, None)

    fb, q0, v0 = case.fourbar, case.fb_q0, case.fb_v0
    every, two = np.linspace(0.0, 1.0, 1001), np.array([0.0, 1.0])
    out = {
        "4-bar, 1 step": run(fb, q0, v0, 1e-3, 1e-3, None),
        "4-bar 1 s, 1001 samples": run(fb, q0, v0, 1.0, 1e-3, every, "kkt", True),
        "4-bar 1 s, 2 samples": run(fb, q0, v0, 1.0, 1e-3, two, "kkt", True),
        "4-bar 10 s, default": run(fb, q0, v0, 10.0, 1e-3, None),
    }
    for dt in (0.05, 0.01):
        out[f"N-four-bar 4 s, rk4 {dt:g} s"] = run(
            case.nfourbar, case.nfb_q0, case.nfb_v0, case.nfb.t_final, dt, case.nfb_grid
        )
    return out


def number_for(name: str) -> int:
    if "10 s" in name:
        return 2
    if "1 s," in name:
        return 10
    if "N-four-bar" in name:
        return 20
    return 300


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--against", metavar="REV", help="git revision to compare with")
    args = parser.parse_args()

    sides = {"this tree": Case(closedchain)}
    tmp = None
    if args.against:
        tmp = tempfile.TemporaryDirectory()
        sides[args.against] = Case(import_revision(args.against, Path(tmp.name)))
    core = core_calls(sides["this tree"])
    calls = {side: case.calls() for side, case in sides.items()}
    for fns in [core, *calls.values()]:  # warm up (cores built, caches filled)
        for fn in fns.values():
            fn()
    if args.against:  # the same results: every array and the run's info, bit for bit
        for name in core:
            ta, tb = (calls[s][name]() for s in sides)
            same = all(
                np.array_equal(getattr(ta, k), getattr(tb, k))
                for k in ("t", "q", "v", "a", "lam", "constraint_residual", "energy", "branch")
            )
            ia, ib = ({**t.info.to_dict(), "cpu_time": None} for t in (ta, tb))
            print(f"{name}: results identical to {args.against}: {same and ia == ib}")
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.repeat):
        for name in core:  # interleaved: every side of a row in the same repeat
            for side, fn in [("core", core[name]), *((s, calls[s][name]) for s in sides)]:
                times.setdefault((side, name), []).append(cpu_us_per_call(fn, number_for(name)))
    med = {k: float(np.median(v)) for k, v in times.items()}

    print(
        f"# {platform.node()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; "
        f"median of {args.repeat} interleaved repeats, CPU us per call"
    )
    names = list(sides)
    header = f"{'call':28s} {'core alone':>11s}" + "".join(f" {s:>12s}" for s in names)
    if len(names) == 2:
        header += "  ratio"
    print(header)
    for name in core:
        row = f"{name:28s} {med[('core', name)]:11.0f}" + "".join(
            f" {med[(s, name)]:12.0f}" for s in names
        )
        if len(names) == 2:
            row += f"  {med[(names[0], name)] / med[(names[1], name)]:.2f}"
        print(row)
    print()
    for s in names:
        fixed = med[(s, "4-bar, 1 step")] - med[("core", "4-bar, 1 step")]
        per = (med[(s, "4-bar 1 s, 1001 samples")] - med[(s, "4-bar 1 s, 2 samples")]) / 999
        print(f"{s}: fixed cost {fixed:.0f} us per call; {per:.2f} us per output sample")
    core_per = med[("core", "4-bar 1 s, 1001 samples")] - med[("core", "4-bar 1 s, 2 samples")]
    print(f"core alone: {core_per / 999:.2f} us per output sample")
    for s in names:
        for dt in (0.05, 0.01):
            name = f"N-four-bar 4 s, rk4 {dt:g} s"
            over = med[(s, name)] - med[("core", name)]
            print(f"{s}: {name}: {over:.0f} us around the core ({over / med[(s, name)]:.0%})")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
