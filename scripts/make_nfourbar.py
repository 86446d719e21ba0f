"""Write models/nfourbar_<N>.urdf: the IFToMM multibody benchmark problem A02, "N-four-bar".

The mechanism (IFToMM Technical Committee for Multibody Dynamics, library of
computational benchmark problems, A02): N four-bar loops in a row in a vertical
plane, made of 2N + 1 uniform rods of length L = 1 m and mass m = 1 kg:

* N + 1 cranks, crank i (i = 0..N) pinned to the ground at A_i = (i L, 0, 0),
* N couplers, coupler i (i = 1..N) pinned between the tips B_{i-1} and B_i of
  cranks i - 1 and i.

The plane of motion is the world x-z plane, gravity -9.81 m/s^2 along world z
(closedchain's default), every joint axis (0, -1, 0) as in models/fourbar.urdf,
so a positive angle turns world x towards world z. At t = 0 the cranks are
vertical (angle pi/2 from the ground line) and the couplers horizontal; in the
benchmark every crank turns at 1 rad/s, so the couplers translate at 1 m/s.
All rods stay parallel (every loop is a parallelogram), and twice per turn
(crank angle 0 and pi) all rods are horizontal: the loops are flat, each loop's
constraint Jacobian loses rank, and the motion may continue on the parallelogram
branch or the anti-parallelogram one.

Tree (chosen so that M is block diagonal and J banded, whatever N): every
crank is a child of the ground, coupler i is a child of crank i - 1 (joint at
B_{i-1}), and each coupler is cut from crank i at B_i by a revolute <loop>.
Joint coordinates: crank_i = absolute crank angle theta_i; coupler_i = angle of
the coupler relative to crank i - 1 (so the t = 0 state is crank_i = pi/2,
coupler_i = -pi/2).

The benchmark's point B0 is the tip of crank 0, which is the left end of coupler 1
(frame ``crank_0_tip``, index zero-padded: ``crank_00_tip`` for N = 40): at
crank angle theta it is at (L cos theta, 0, L sin theta).

Each rod is a thin rod (inertia m L^2 / 12 about its centre across the rod, 0
along it). The first crank is actuated (<transmission>), so it is the
independent coordinate.

The benchmark's initial state is the model's default scene (``<scene>``): the
cranks vertical, the couplers horizontal, crank 0 at -1 rad/s (so
``closedchain simulate models/nfourbar_<N>.urdf --t-final 20`` runs the
benchmark). The reference configuration q_ref stays the neutral one, which is
the flat (singular) position.

Run:  python scripts/make_nfourbar.py N [--out PATH]   (default models/nfourbar_<N>.urdf)
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from closedchain.benchmark.families import nfourbar_urdf

logger = logging.getLogger("make_nfourbar")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, help="number of four-bar loops N (>= 1)")
    parser.add_argument("--out", type=Path, default=None, help="output file")
    args = parser.parse_args(argv)
    if args.n < 1:
        parser.error(f"N must be >= 1, got {args.n}")
    out = args.out or Path(__file__).resolve().parent.parent / "models" / f"nfourbar_{args.n}.urdf"
    out.write_text(nfourbar_urdf(args.n))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logger.info("wrote %s", out)


if __name__ == "__main__":
    main()
