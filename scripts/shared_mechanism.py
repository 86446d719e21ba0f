"""Count the calls that differ when one Mechanism is shared by a thread pool.

    python scripts/shared_mechanism.py [--no-lock] [--calls 2000] [--threads 2]

Runs ``forward_dynamics`` on random consistent states of the Agile Eye, first
serially, then the same calls in a thread pool on the same mechanism, and
prints how many results differ. ``--no-lock`` replaces the mechanism's lock by
a no-op (the behaviour before closedchain._locking): interleaved calls then
overwrite each other's intermediate results.
"""

from __future__ import annotations

import argparse
import contextlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

import closedchain as cc

MODEL = Path(__file__).resolve().parents[1] / "models" / "agile_eye.urdf"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-lock", action="store_true", help="make the lock a no-op")
    parser.add_argument("--calls", type=int, default=2000, help="calls per method")
    parser.add_argument("--threads", type=int, default=2, help="threads in the pool")
    args = parser.parse_args()
    mech = cc.load(MODEL)
    if args.no_lock:
        mech.lock = contextlib.nullcontext()
    rng = np.random.default_rng(0)
    states = [cc.random_consistent_state(mech, rng) for _ in range(args.calls)]
    tau = np.zeros(mech.nv)
    for method in ("kkt", "augmented-lagrangian"):

        def accel(state, method=method):
            try:
                return cc.forward_dynamics(mech, *state, tau, method=method).a
            except cc.ClosedChainError:
                return None  # a spurious error from an interleaved call

        serial = [accel(s) for s in states]
        with ThreadPoolExecutor(args.threads) as pool:
            pooled = list(pool.map(accel, states))
        differ = sum(
            b is None or not np.array_equal(a, b) for a, b in zip(serial, pooled, strict=True)
        )
        print(f"{method}: {differ} of {args.calls} calls differ from the serial run")


if __name__ == "__main__":
    main()
