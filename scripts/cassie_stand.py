"""Report Cassie standing on its welded feet under constant ``gravity_torque``.

Loads ``erd:cassie`` with a free-flyer root and ``models/cassie_standing.urdf`` (both
feet welded where cassie_v2.srdf's ``standing`` state puts them; example-robot-data
must be installed), computes the holding torques, the growth rates of the stance
linearized about that equilibrium, and simulates from rest (default method and
integrator) with those constant torques. Prints the figures (``--json``: one JSON
object) that docs/guide/robots-and-moving-bases.md quotes:

- the largest multiplier [N or N m] and motor torque [N m] of the hold;
- the growth rates [1/s] of the linearization: the reduced coordinates are the
  null space of J at the equilibrium, each step h along one of them is assembled
  back onto phi = 0, and A = d(a)/dx by central differences; a mode grows as
  exp(sqrt(mu) t) for each eigenvalue mu > 0 of A;
- the pelvis's largest displacement over the run [m] and rotation [rad], the largest
  closure residual, the CPU time.

Run: ``python scripts/cassie_stand.py [--t-final 2] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import scipy.linalg

import closedchain as cc

#: The standing overlay (feet welded, motors as transmissions).
OVERLAY = Path(__file__).resolve().parent.parent / "models" / "cassie_standing.urdf"
#: Simulated time [s].
T_FINAL = 2.0
#: Step [rad or m] of the central differences along the motion.
LIN_STEP = 1e-6
#: Singular values of J below this (relative to the largest) span its null space [-].
NULL_RCOND = 1e-12
#: The body whose displacement is reported.
PELVIS = "pelvis"


def growth_rates(mech, q, tau, *, h: float = LIN_STEP) -> np.ndarray:
    """Return the linearized stance's rates [1/s], largest first (real parts).

    Args:
        mech: the mechanism.
        q: equilibrium configuration, shape (nq,), assembled.
        tau: constant generalized forces that hold it, shape (nv,) [N m or N].
        h: step of the central differences [rad or m].
    """
    N = scipy.linalg.null_space(cc.compute_jacobian(mech, q), rcond=NULL_RCOND)
    rest = np.zeros(mech.nv)

    def accel(step):
        qs = cc.assemble(mech, pin.integrate(mech.model, q, step))
        return N.T @ cc.forward_dynamics(mech, qs, rest, tau).a

    A = np.column_stack([(accel(h * n) - accel(-h * n)) / (2.0 * h) for n in N.T])
    mu = np.linalg.eigvals(A).astype(complex)
    return np.sort(np.sqrt(mu).real)[::-1]


def pelvis_drift(mech, traj) -> tuple[float, float]:
    """Return the pelvis's largest displacement [m] and rotation [rad] from its start."""
    fid = mech.model.getFrameId(PELVIS, pin.FrameType.BODY)
    placements = []
    for qk in traj.q:
        pin.framesForwardKinematics(mech.model, mech.data, qk)
        placements.append(mech.data.oMf[fid].copy())
    logs = [pin.log(placements[0].inverse() * M) for M in placements]
    return (
        max(float(np.linalg.norm(d.linear)) for d in logs),
        max(float(np.linalg.norm(d.angular)) for d in logs),
    )


def measure(t_final: float = T_FINAL) -> dict:
    """Return the hold's, the linearization's and the run's figures (see the module doc)."""
    mech = cc.load("erd:cassie", root_joint="free", loops=OVERLAY)
    q = mech.q_ref
    rest = np.zeros(mech.nv)
    tau = cc.gravity_torque(mech, q)
    held = cc.forward_dynamics(mech, q, rest, tau)
    rates = growth_rates(mech, q, tau)
    start = time.process_time()
    traj = cc.simulate(mech, q, rest, t_final, tau=tau)
    cpu = time.process_time() - start
    moved, turned = pelvis_drift(mech, traj)
    return {
        "nv": mech.nv,
        "nc": mech.nc,
        "mobility": mech.mobility,
        "max_abs_a_at_rest": float(np.max(np.abs(held.a))),
        "max_abs_lam": float(np.max(np.abs(held.lam))),
        "max_abs_tau": float(np.max(np.abs(tau))),
        "rates": [float(r) for r in rates[:4]],
        "t_final": float(traj.t[-1]),
        "pelvis_m": moved,
        "pelvis_rad": turned,
        "max_constraint_residual": traj.info.max_constraint_residual,
        "cpu_s": cpu,
        "method": traj.info.method,
        "integrator": traj.info.integrator,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--t-final", type=float, default=T_FINAL, help="simulated time [s]")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    row = measure(args.t_final)
    if args.json:
        print(json.dumps(row))
        return 0
    print(f"erd:cassie standing: nv {row['nv']}, nc {row['nc']}, mobility {row['mobility']}")
    print(
        f"hold: max |tau| {row['max_abs_tau']:.3g} N m, max |lam| {row['max_abs_lam']:.3g}, "
        f"max |a| at rest {row['max_abs_a_at_rest']:.2g}"
    )
    print("largest growth rates [1/s]: " + ", ".join(f"{r:.3g}" for r in row["rates"]))
    print(
        f"{row['t_final']:g} s ({row['method']}, {row['integrator']}): pelvis moves "
        f"{row['pelvis_m']:.2g} m, turns {row['pelvis_rad']:.2g} rad; max |phi| "
        f"{row['max_constraint_residual']:.2g}; CPU {row['cpu_s']:.3g} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
