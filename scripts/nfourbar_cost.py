"""Cost per step of simulate on the N-four-bar (IFToMM A02) against N, and its growth exponent.

For each N the script writes the model (closedchain.benchmark.families.nfourbar_urdf), runs a short
horizon of a configuration (default: simulate's defaults, i.e. method
augmented-lagrangian, rk43 at rtol 1e-9, stage-projection; each option given
overrides one) and reports CPU time per step and per dynamics evaluation; the
growth exponent is the slope of log(cost per step) against log(N) by least
squares over the N given. With ``--full`` it also runs the benchmark's 20 s
and reports its CPU time, the B0 error against the quadrature reference
(tests/nfourbar_reference.py) and the relative energy drift.

BLAS runs on one thread (OPENBLAS_NUM_THREADS=1 unless set): on a shared
2-core machine OpenBLAS's threads spin on the small solves and triple the CPU
time of a step (measured at N = 40: 93 ms against 30 ms per rk4 step).

Run:
    python scripts/nfourbar_cost.py [--n 1 2 5 10 20 40] [--t 0.2]
        [--integrator ali3p] [--dt 2.5e-4] [--method proximal] [--full] [--json]

Prints tidy rows (one per N), then the exponent. With ``--page docs/bench/nfourbar.md``
it runs the page's configurations (:data:`PAGE_CONFIGS`, each with ``--full``) instead
and writes the documentation site's generated N-four-bar page, its run in the header.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import bench_page  # noqa: E402  (scripts/bench_page.py: the generated pages' header)
import nfourbar_reference as ref  # noqa: E402

import closedchain as cc  # noqa: E402
from closedchain._io import atomic_write  # noqa: E402
from closedchain.benchmark.families import nfourbar_urdf  # noqa: E402
from closedchain.simulate.request import describe_default  # noqa: E402

logger = logging.getLogger("nfourbar_cost")

#: The configurations of the generated page (``--page``): label -> options of this script.
PAGE_CONFIGS = {
    f"default: {describe_default()} (compiled)": {},
    "rk4 1 ms (compiled)": {"dt": 1e-3},
    "rk4 5 ms (compiled)": {"dt": 5e-3},
    "rk4 5 ms (numpy)": {"dt": 5e-3, "backend": "numpy"},
    "ali3p 0.2 ms (compiled)": {"integrator": "ali3p", "dt": 2e-4},
}
#: The benchmark's accuracy bar: B0 within this of the reference after 20 s [m].
B0_BAR_M = 1e-6


def measure(n: int, args, folder: Path) -> dict:
    path = folder / f"nfourbar_{n}.urdf"
    path.write_text(nfourbar_urdf(n))
    mech = cc.load(path)
    q0, v0 = ref.initial_state(mech)
    given = dict(
        method=args.method,
        integrator=args.integrator,
        dt=args.dt,
        stabilization=args.stabilization,
        backend=args.backend,
    )
    kw = {k: v for k, v in given.items() if v is not None}
    cc.simulate(mech, q0, v0, 0.005, **kw)  # warm-up: buffers, imports
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
        "backend": traj.info.backend,
        "method": traj.info.method,
        "integrator": traj.info.integrator,
        "stabilization": traj.info.stabilization,
        "dt": traj.info.dt,
    }
    if args.full:
        t0 = time.process_time()
        full = cc.simulate(mech, q0, v0, 20.0, t_eval=np.linspace(0.0, 20.0, 201), **kw)
        row["cpu_20s"] = time.process_time() - t0
        row["us_per_step_20s"] = 1e6 * row["cpu_20s"] / full.info["steps"]
        theta = ref.crank_angle(n, 20.0)
        row["b0_error_m"] = float(np.linalg.norm(ref.point_b0(full.q[-1, 0]) - ref.point_b0(theta)))
        row["energy_drift"] = float(
            np.max(np.abs(full.energy - full.energy[0])) / ref.characteristic_energy(n)
        )
    return row


def growth_exponent(rows: list[dict], key: str = "us_per_step") -> float:
    """Slope of log(cost per step) against log(N), least squares (NaN for one N)."""
    if len(rows) < 2:
        return float("nan")
    ns = np.array([r["N"] for r in rows], dtype=float)
    cost = np.array([r[key] for r in rows])
    return float(np.polyfit(np.log(ns), np.log(cost), 1)[0])


def write_page(args, command: str) -> None:
    """Run every configuration of :data:`PAGE_CONFIGS` over ``args.n`` with the 20 s
    reference runs and write the generated page ``args.page``."""
    date, load_before = bench_page.today(), bench_page.load_average()
    lines = [
        "The IFToMM benchmark A02 over 20 s from its start (every crank at 1 rad/s), against "
        "the quadrature of its energy integral (`tests/nfourbar_reference.py`). B0 error: "
        "distance of B0 (the tip of crank 0) from its reference position at t = 20 s; the "
        f"benchmark's bar is {B0_BAR_M:g} m. Energy drift: max |E - E0| over 201 samples "
        "relative to the largest kinetic energy. CPU: process time of the 20 s run, and "
        "per step of it. BLAS on one thread.",
        "",
        "| configuration | N | B0 error [m] | meets the bar | energy drift "
        "| CPU for 20 s [s] | us per step |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    exponents = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, options in PAGE_CONFIGS.items():
            run = argparse.Namespace(**{**vars(args), **options, "full": True})
            rows = []
            for n in args.n:
                row = measure(n, run, Path(tmp))
                logger.info("%s N=%d: %s", label, n, row)
                rows.append(row)
                lines.append(
                    f"| {label} | {n} | {row['b0_error_m']:.1e} "
                    f"| {'yes' if row['b0_error_m'] <= B0_BAR_M else '**no**'} "
                    f"| {row['energy_drift']:.1e} | {row['cpu_20s']:.3g} "
                    f"| {row['us_per_step_20s']:.3g} |"
                )
            exponents[label] = growth_exponent(rows, "us_per_step_20s")
    lines += ["", "Growth exponent p of the cost per step (cost ~ N^p):", ""]
    lines += [f"- {label}: {p:.2f}" for label, p in exponents.items()]
    head = bench_page.run_header(
        "N-four-bar: accuracy and cost against N",
        command=command,
        date=date,
        load_before=load_before,
        about="The benchmark and the methods: "
        "[Singular positions](../guide/singular-positions.md).",
    )
    with atomic_write(args.page, "w") as f:  # a failed run leaves the previous page
        f.write("\n".join(head + lines) + "\n")
    logger.info("wrote %s", args.page)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, nargs="+", default=[1, 2, 5, 10, 20, 40])
    p.add_argument("--t", type=float, default=0.2, help="horizon of the cost runs [s]")
    p.add_argument("--method", default=None, help="default: simulate's")
    p.add_argument("--integrator", default=None, help="default: simulate's")
    p.add_argument("--stabilization", default=None, help="default: the integrator's")
    p.add_argument("--dt", type=float, default=None, help="[s], default: simulate's")
    p.add_argument(
        "--backend", default=None, choices=("compiled", "numpy"), help="default: simulate's (auto)"
    )
    p.add_argument("--full", action="store_true", help="also run 20 s against the reference")
    p.add_argument("--json", action="store_true")
    p.add_argument(
        "--page",
        type=Path,
        help="run PAGE_CONFIGS over --n and write the generated page (docs/bench/nfourbar.md)",
    )
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.page:
        write_page(args, " ".join(["python scripts/nfourbar_cost.py", *(argv or sys.argv[1:])]))
        return
    with tempfile.TemporaryDirectory() as tmp:
        rows = [measure(n, args, Path(tmp)) for n in args.n]
    exponent = growth_exponent(rows)
    if args.json:
        logger.info(json.dumps({"rows": rows, "growth_exponent": exponent}, indent=1))
        return
    for r in rows:
        cells = (f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items())
        logger.info("  ".join(cells))
    logger.info("growth exponent of cost per step in N: %.2f", exponent)


if __name__ == "__main__":
    main()
