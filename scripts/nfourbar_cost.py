"""Cost per step of simulate on the N-four-bar (IFToMM A02) against N, and its growth exponent.

For each N the script writes the model (scripts/make_nfourbar.py), runs a short
horizon of a configuration (default: simulate's default method, integrator and
stabilization at dt = 2 ms) and reports CPU time per step and per dynamics
evaluation; the growth exponent is the slope of log(cost per step) against
log(N) by least squares over the N given. With ``--full`` it also runs the
benchmark's 20 s and reports the B0 error against the quadrature reference
(tests/nfourbar_reference.py) and the relative energy drift.

Run:
    PYTHONPATH=src python scripts/nfourbar_cost.py [--n 1 2 5 10 20 40] [--t 0.2]
        [--integrator rk4] [--dt 2e-3] [--method augmented-lagrangian] [--full] [--json]

Prints tidy rows (one per N), then the exponent.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import nfourbar_reference as ref  # noqa: E402

import closedchain as cc  # noqa: E402

logger = logging.getLogger("nfourbar_cost")


def _generator():
    spec = importlib.util.spec_from_file_location(
        "make_nfourbar", ROOT / "scripts" / "make_nfourbar.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def measure(n: int, args, folder: Path) -> dict:
    path = folder / f"nfourbar_{n}.urdf"
    path.write_text(_generator().build(n))
    mech = cc.load(path)
    q0, v0 = ref.initial_state(mech)
    kw = dict(method=args.method, integrator=args.integrator, dt=args.dt)
    if args.stabilization:
        kw["stabilization"] = args.stabilization
    cc.simulate(mech, q0, v0, 5 * args.dt, **kw)  # warm-up: buffers, imports
    t0 = time.process_time()
    traj = cc.simulate(mech, q0, v0, args.t, **kw)
    cpu = time.process_time() - t0
    steps = traj.info.steps
    row = {
        "N": n,
        "nv": mech.nv,
        "nc": mech.nc,
        "steps": steps,
        "cpu_s": cpu,
        "us_per_step": 1e6 * cpu / steps,
        "us_per_eval": 1e6 * cpu / max(traj.info.evaluations, 1),
    }
    if args.full:
        t0 = time.process_time()
        full = cc.simulate(mech, q0, v0, 20.0, t_eval=np.linspace(0.0, 20.0, 21), **kw)
        row["cpu_20s"] = time.process_time() - t0
        theta = ref.crank_angle(n, 20.0)
        row["b0_error_m"] = float(np.linalg.norm(ref.point_b0(full.q[-1, 0]) - ref.point_b0(theta)))
        row["energy_drift"] = float(
            np.max(np.abs(full.energy - full.energy[0])) / ref.characteristic_energy(n)
        )
    return row


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 5, 10, 20, 40])
    p.add_argument("--t", type=float, default=0.2, help="horizon of the cost runs [s]")
    p.add_argument("--method", default="augmented-lagrangian")
    p.add_argument("--integrator", default="rk4")
    p.add_argument("--stabilization", default=None)
    p.add_argument("--dt", type=float, default=2e-3)
    p.add_argument("--full", action="store_true", help="also run 20 s against the reference")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        rows = [measure(n, args, Path(tmp)) for n in args.n]
    ns = np.array([r["N"] for r in rows], dtype=float)
    cost = np.array([r["us_per_step"] for r in rows])
    exponent = float(np.polyfit(np.log(ns), np.log(cost), 1)[0]) if len(rows) > 1 else float("nan")
    if args.json:
        logger.info(json.dumps({"rows": rows, "growth_exponent": exponent}, indent=1))
        return
    for r in rows:
        cells = (f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items())
        logger.info("  ".join(cells))
    logger.info("growth exponent of cost per step in N: %.2f", exponent)


if __name__ == "__main__":
    main()
