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

logger = logging.getLogger("make_nfourbar")

LENGTH = 1.0  # [m], every rod
MASS = 1.0  # [kg], every rod
#: Joint limit [rad]: the cranks turn for many revolutions (limits only bound sampling).
LIMIT = 6.283185307179586
AXIS = "0 -1 0"
HALF_PI = 1.5707963267948966  # [rad], crank angle at t = 0 (vertical)
#: Crank rate at t = 0 [rad/s]: the benchmark's 1 rad/s, turning world z towards world x.
CRANK_RATE = -1.0
ROD_WIDTH = 0.03  # [m], visual only


def _rod_link(name: str, material: str) -> str:
    inertia = MASS * LENGTH**2 / 12.0
    half = LENGTH / 2.0
    return f"""  <link name="{name}">
    <inertial>
      <origin xyz="{half!r} 0 0" rpy="0 0 0"/>
      <mass value="{MASS!r}"/>
      <inertia ixx="0" ixy="0" ixz="0" iyy="{inertia!r}" iyz="0" izz="{inertia!r}"/>
    </inertial>
    <visual>
      <origin xyz="{half!r} 0 0" rpy="0 0 0"/>
      <geometry><box size="{LENGTH!r} {ROD_WIDTH} {ROD_WIDTH}"/></geometry>
      <material name="{material}"/>
    </visual>
  </link>
"""


def _joint(name: str, parent: str, child: str, xyz: str) -> str:
    return f"""  <joint name="{name}" type="revolute">
    <parent link="{parent}"/>
    <child link="{child}"/>
    <origin xyz="{xyz}" rpy="0 0 0"/>
    <axis xyz="{AXIS}"/>
    <limit lower="{-LIMIT!r}" upper="{LIMIT!r}" effort="0" velocity="100"/>
  </joint>
"""


def build(n: int) -> str:
    """Return the URDF+ text of the N-four-bar with ``n`` loops (n >= 1).

    Indices in names are zero-padded to a common width (``crank_07``) because
    Pinocchio's URDF reader orders sibling joints by name: then the joint
    order is crank_0, coupler_1, crank_1, coupler_2, ... whatever N.
    """
    if n < 1:
        raise ValueError(f"N must be a positive number of loops, got {n}")
    w = len(str(n))

    def k(i: int) -> str:
        return f"{i:0{w}d}"

    parts = [
        '<?xml version="1.0"?>\n',
        f"<!-- IFToMM benchmark A02, N-four-bar with N = {n}: written by "
        "scripts/make_nfourbar.py (see its docstring for geometry, tree and coordinates). -->\n",
        f'<robot name="nfourbar_{n}">\n',
        '  <material name="crank"><color rgba="0.85 0.33 0.10 1"/></material>\n',
        '  <material name="coupler"><color rgba="0.00 0.45 0.74 1"/></material>\n',
        '  <link name="ground"/>\n',
    ]
    for i in range(n + 1):
        parts.append(_rod_link(f"crank_{k(i)}", "crank"))
        parts.append(
            _joint(f"crank_{k(i)}_joint", "ground", f"crank_{k(i)}", f"{i * LENGTH!r} 0 0")
        )
        # B_i as a frame (fixed joint to a massless link): the benchmark's output point.
        parts.append(f'  <link name="crank_{k(i)}_tip"/>\n')
        parts.append(
            f'  <joint name="crank_{k(i)}_tip_joint" type="fixed">\n'
            f'    <parent link="crank_{k(i)}"/>\n    <child link="crank_{k(i)}_tip"/>\n'
            f'    <origin xyz="{LENGTH!r} 0 0" rpy="0 0 0"/>\n  </joint>\n'
        )
        if i >= 1:
            # Coupler i hangs from crank i - 1 (listed after crank i: URDF order is free,
            # the reader builds the tree depth-first).
            parts.append(_rod_link(f"coupler_{k(i)}", "coupler"))
            parts.append(
                _joint(
                    f"coupler_{k(i)}_joint",
                    f"crank_{k(i - 1)}",
                    f"coupler_{k(i)}",
                    f"{LENGTH!r} 0 0",
                )
            )
    for i in range(1, n + 1):
        parts.append(
            f"""  <loop name="B{k(i)}" type="revolute">
    <predecessor link="coupler_{k(i)}"/>
    <successor link="crank_{k(i)}"/>
    <predecessor_origin xyz="{LENGTH!r} 0 0" rpy="0 0 0"/>
    <successor_origin xyz="{LENGTH!r} 0 0" rpy="0 0 0"/>
    <axis xyz="{AXIS}"/>
  </loop>
"""
        )
    # The benchmark's start as the default scene: cranks vertical, couplers horizontal
    # (guesses assembled holding crank 0), crank 0 turning at -1 rad/s (the couplers move
    # at +1 m/s along world x; the other cranks take the velocity with J v = 0).
    parts.append("  <scene>\n")
    parts.append(
        f'    <initial joint="crank_{k(0)}_joint" value="{HALF_PI!r}" velocity="{CRANK_RATE!r}"/>\n'
    )
    for i in range(1, n + 1):
        parts.append(f'    <initial joint="crank_{k(i)}_joint" value="{HALF_PI!r}"/>\n')
        parts.append(f'    <initial joint="coupler_{k(i)}_joint" value="{-HALF_PI!r}"/>\n')
    parts.append("  </scene>\n")
    parts.append(
        f"""  <transmission name="crank_{k(0)}_transmission">
    <type>transmission_interface/SimpleTransmission</type>
    <joint name="crank_{k(0)}_joint">
      <hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>
    </joint>
    <actuator name="crank_{k(0)}_motor"><mechanicalReduction>1</mechanicalReduction></actuator>
  </transmission>
</robot>
"""
    )
    return "".join(parts)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("n", type=int, help="number of four-bar loops N (>= 1)")
    parser.add_argument("--out", type=Path, default=None, help="output file")
    args = parser.parse_args(argv)
    if args.n < 1:
        parser.error(f"N must be >= 1, got {args.n}")
    out = args.out or Path(__file__).resolve().parent.parent / "models" / f"nfourbar_{args.n}.urdf"
    out.write_text(build(args.n))
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logger.info("wrote %s", out)


if __name__ == "__main__":
    main()
