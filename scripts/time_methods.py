"""Time one forward-dynamics call of every registered method, beside Pinocchio's own.

Prints microseconds per call (median of repeats) on both shipped models at a
random consistent state: pinocchio.computeAllTerms, the constraint layer's
evaluate(J, gamma), compute_terms (both plus copies), pinocchio.constraintDynamics
(the bar to measure against, called from Python with its containers), and each
method in closedchain.METHODS. Timing is noisy on a shared machine: run it alone.

Run: python scripts/time_methods.py [--repeat 7] [--number 2000]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pinocchio as pin

import closedchain as cc
from closedchain.benchmark.evaluation import cpu_us_per_call
from closedchain.dynamics.base import DEFAULT_SETTINGS, compute_terms, get_method

MODELS = Path(__file__).resolve().parent.parent / "models"


def median_us(fn, *, number: int, repeat: int) -> float:
    """Median over ``repeat`` runs of the mean CPU time of ``number`` calls [us]."""
    return float(np.median([cpu_us_per_call(fn, number) for _ in range(repeat)]))


def time_model(name: str, *, number: int, repeat: int) -> None:
    """Print the table for ``models/<name>.urdf``."""
    mech = cc.load(MODELS / f"{name}.urdf")
    q, v = cc.random_consistent_state(mech, np.random.default_rng(0))
    tau = np.zeros(mech.nv)
    ws = compute_terms(mech, q, v)
    cms, cds, _, pdata = mech.pinocchio_constraints()
    prox = DEFAULT_SETTINGS.pinocchio_proximal()
    rows = {
        "pin.computeAllTerms": lambda: pin.computeAllTerms(mech.model, mech.data, q, v),
        "constraints.evaluate(J, gamma)": lambda: mech.constraints.evaluate(
            mech.model, mech.data, J=ws.J, gamma=ws.gamma
        ),
        "compute_terms": lambda: compute_terms(mech, q, v),
        "pin.constraintDynamics": lambda: pin.constraintDynamics(
            mech.model, pdata, q, v, tau, cms, cds, prox
        ),
    }
    for method in sorted(cc.METHODS):
        func = get_method(method)
        rows[f"method {method}"] = lambda f=func: f(mech, q, v, tau, DEFAULT_SETTINGS)
    print(f"{name} (nv = {mech.nv}, nc = {mech.nc}): us per call")
    for label, fn in rows.items():
        print(f"  {label:32s} {median_us(fn, number=number, repeat=repeat):8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--number", type=int, default=2000)
    args = parser.parse_args()
    for name in ("fourbar", "agile_eye"):
        time_model(name, number=args.number, repeat=args.repeat)


if __name__ == "__main__":
    main()
