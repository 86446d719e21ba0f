"""Families of mechanisms of growing size, written as URDF+ text (the scaling study).

* :func:`chain_urdf`: an n-link planar chain whose tip is pinned to the ground by
  one revolute ``<loop>`` (a long tree, one loop);
* :func:`leg_pair_urdf`: a humanoid-like pair of legs hanging from a fixed pelvis,
  each a hip roll joint and m pitch links with a parallelogram at the hip and one at
  the ankle (a branched tree, four loops, whatever m);
* :func:`nfourbar_urdf`: the IFToMM A02 N-four-bar (N loops in a row; every loop is
  a parallelogram that flattens twice per turn).

:data:`FAMILIES` names them with the sizes of the scaling page and the state each
is timed at.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: Joint axis of every planar family (positive angles turn world x towards world z).
PLANAR_AXIS = "0 -1 0"
#: Length of the leg pair's legs [m] (m pitch links of length LEG_LENGTH / m each).
LEG_LENGTH = 1.0
#: Offset of each parallelogram's second bar from the leg [m].
PARALLELOGRAM_OFFSET = 0.05
#: Inertia of the leg pair's links about their own axis [kg m^2] (no massless direction).
AXIAL_INERTIA = 1e-3


def chain_urdf(n: int, length: float = 1.0, reach: float = 0.6) -> str:
    """Return the URDF+ text of an n-link planar chain (x-z plane) closed onto the ground.

    Each rod is ``length / n`` long with 1 kg, joints about -y; the tip is pinned
    by a revolute ``<loop>`` to the ground at x = ``reach`` ``length`` (mobility n - 2).
    As ``reach`` nears 1 the closed chain nears its stretched, singular pose
    (sigma_min(J) about the square root of 1 - reach).

    Args:
        n: number of links (n >= 3).
        length: total length of the chain [m].
        reach: distance of the ground pin from the base, a fraction of ``length`` in (0, 1].
    """
    if n < 3:
        raise ValueError(f"chain_urdf: n must be >= 3 links (mobility n - 2), got {n}")
    if not 0.0 < reach <= 1.0:
        raise ValueError(f"chain_urdf: reach must be in (0, 1] (a fraction of length), got {reach}")
    rod = length / n
    inertia = rod * rod / 12
    out = ['<?xml version="1.0"?>', f'<robot name="chain{n}">', '<link name="ground"/>']
    for i in range(n):
        out.append(
            f'<link name="l{i}"><inertial><origin xyz="{rod / 2} 0 0"/><mass value="1"/>'
            f'<inertia ixx="0" ixy="0" ixz="0" iyy="{inertia}" iyz="0" izz="{inertia}"/>'
            "</inertial></link>"
        )
        parent = "ground" if i == 0 else f"l{i - 1}"
        xyz = "0 0 0" if i == 0 else f"{rod} 0 0"
        pitch = 0.3 if i == 0 else -0.01
        out.append(
            f'<joint name="j{i}" type="revolute"><parent link="{parent}"/>'
            f'<child link="l{i}"/><origin xyz="{xyz}" rpy="0 {pitch} 0"/>'
            f'<axis xyz="{PLANAR_AXIS}"/>'
            '<limit lower="-3.14" upper="3.14" effort="10" velocity="10"/></joint>'
        )
    out.append(
        f'<loop name="tip" type="revolute"><predecessor link="l{n - 1}"/>'
        f'<successor link="ground"/><predecessor_origin xyz="{rod} 0 0"/>'
        f'<successor_origin xyz="{reach * length!r} 0 0"/><axis xyz="{PLANAR_AXIS}"/></loop>'
    )
    out.append("</robot>")
    return "\n".join(out)


def _rod(name: str, length: float) -> str:
    """A 1 kg rod hanging along -z from its joint, inertia m L^2 / 12 across it."""
    across = max(length * length / 12, AXIAL_INERTIA)
    return (
        f'<link name="{name}"><inertial><origin xyz="0 0 {-length / 2!r}"/><mass value="1"/>'
        f'<inertia ixx="{across!r}" ixy="0" ixz="0" iyy="{across!r}" iyz="0" '
        f'izz="{AXIAL_INERTIA!r}"/></inertial></link>'
    )


def _revolute(name: str, parent: str, child: str, xyz: str, axis: str) -> str:
    return (
        f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>'
        '<limit lower="-3.14" upper="3.14" effort="100" velocity="10"/></joint>'
    )


def leg_pair_urdf(m: int) -> str:
    """Return the URDF+ text of two legs of ``m`` pitch links each under a fixed pelvis.

    Each leg (left at y = +0.1 m, right at y = -0.1 m): a hip roll joint (about x) to a
    hip link, then m pitch joints (about -y) down a chain of 1 kg rods of length
    ``LEG_LENGTH / m``, hanging straight down at q = 0. Two parallelograms per leg
    keep a link parallel to an earlier one: a bar pinned to the hip link beside the
    first pitch joint, closed on link 2 by a revolute ``<loop>`` (the thigh bar), and
    a bar pinned to link m - 2 beside joint m - 1, closed on link m (the ankle bar).
    Mobility 2 (m - 1); the loops flatten only where a link turns by 90 degrees.

    Args:
        m: pitch links per leg (m >= 3).
    """
    if m < 3:
        raise ValueError(f"leg_pair_urdf: m must be >= 3 pitch links per leg, got {m}")
    rod = LEG_LENGTH / m
    d = PARALLELOGRAM_OFFSET
    out = ['<?xml version="1.0"?>', f'<robot name="leg_pair_{m}">', '<link name="pelvis"/>']
    loops = []
    for side, y in (("left", 0.1), ("right", -0.1)):
        hip = f"{side}_hip"
        out.append(_rod(hip, 0.0))
        out.append(_revolute(f"{side}_hip_roll", "pelvis", hip, f"0 {y!r} 0", "1 0 0"))
        links = [hip] + [f"{side}_{k:03d}" for k in range(1, m + 1)]
        for k in range(1, m + 1):
            out.append(_rod(links[k], rod))
            xyz = "0 0 0" if k == 1 else f"0 0 {-rod!r}"
            out.append(_revolute(f"{links[k]}_pitch", links[k - 1], links[k], xyz, PLANAR_AXIS))
        # A parallelogram beside pitch joint k: a bar of the link's length pinned to link
        # k - 1 at d beside joint k, closed on link k + 1 at d beside its joint.
        for bar, k in (("thigh_bar", 1), ("ankle_bar", m - 1)):
            name = f"{side}_{bar}"
            z = 0.0 if k == 1 else -rod
            out.append(_rod(name, rod))
            out.append(_revolute(f"{name}_pin", links[k - 1], name, f"{d!r} 0 {z!r}", PLANAR_AXIS))
            loops.append(
                f'<loop name="{name}_loop" type="revolute"><predecessor link="{name}"/>'
                f'<successor link="{links[k + 1]}"/><predecessor_origin xyz="0 0 {-rod!r}"/>'
                f'<successor_origin xyz="{d!r} 0 0"/><axis xyz="{PLANAR_AXIS}"/></loop>'
            )
    out.extend(loops)
    out.append("</robot>")
    return "\n".join(out)


#: N-four-bar: length [m] and mass [kg] of every rod (IFToMM A02).
NFOURBAR_LENGTH = 1.0
NFOURBAR_MASS = 1.0
#: N-four-bar joint limit [rad]: the cranks turn for many revolutions (limits only bound
#: sampling).
NFOURBAR_LIMIT = 6.283185307179586
#: N-four-bar crank angle at t = 0 [rad] (vertical) and crank 0's rate [rad/s]: the
#: benchmark's 1 rad/s, turning world z towards world x.
NFOURBAR_HALF_PI = 1.5707963267948966
NFOURBAR_CRANK_RATE = -1.0
NFOURBAR_ROD_WIDTH = 0.03  # [m], visual only


def _nfourbar_rod(name: str, material: str) -> str:
    inertia = NFOURBAR_MASS * NFOURBAR_LENGTH**2 / 12.0
    half = NFOURBAR_LENGTH / 2.0
    width = NFOURBAR_ROD_WIDTH
    return f"""  <link name="{name}">
    <inertial>
      <origin xyz="{half!r} 0 0" rpy="0 0 0"/>
      <mass value="{NFOURBAR_MASS!r}"/>
      <inertia ixx="0" ixy="0" ixz="0" iyy="{inertia!r}" iyz="0" izz="{inertia!r}"/>
    </inertial>
    <visual>
      <origin xyz="{half!r} 0 0" rpy="0 0 0"/>
      <geometry><box size="{NFOURBAR_LENGTH!r} {width} {width}"/></geometry>
      <material name="{material}"/>
    </visual>
  </link>
"""


def _nfourbar_joint(name: str, parent: str, child: str, xyz: str) -> str:
    return f"""  <joint name="{name}" type="revolute">
    <parent link="{parent}"/>
    <child link="{child}"/>
    <origin xyz="{xyz}" rpy="0 0 0"/>
    <axis xyz="{PLANAR_AXIS}"/>
    <limit lower="{-NFOURBAR_LIMIT!r}" upper="{NFOURBAR_LIMIT!r}" effort="0" velocity="100"/>
  </joint>
"""


def nfourbar_urdf(n: int) -> str:
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
        parts.append(_nfourbar_rod(f"crank_{k(i)}", "crank"))
        parts.append(
            _nfourbar_joint(
                f"crank_{k(i)}_joint", "ground", f"crank_{k(i)}", f"{i * NFOURBAR_LENGTH!r} 0 0"
            )
        )
        # B_i as a frame (fixed joint to a massless link): the benchmark's output point.
        parts.append(f'  <link name="crank_{k(i)}_tip"/>\n')
        parts.append(
            f'  <joint name="crank_{k(i)}_tip_joint" type="fixed">\n'
            f'    <parent link="crank_{k(i)}"/>\n    <child link="crank_{k(i)}_tip"/>\n'
            f'    <origin xyz="{NFOURBAR_LENGTH!r} 0 0" rpy="0 0 0"/>\n  </joint>\n'
        )
        if i >= 1:
            # Coupler i hangs from crank i - 1 (listed after crank i: URDF order is free,
            # the reader builds the tree depth-first).
            parts.append(_nfourbar_rod(f"coupler_{k(i)}", "coupler"))
            parts.append(
                _nfourbar_joint(
                    f"coupler_{k(i)}_joint",
                    f"crank_{k(i - 1)}",
                    f"coupler_{k(i)}",
                    f"{NFOURBAR_LENGTH!r} 0 0",
                )
            )
    for i in range(1, n + 1):
        parts.append(
            f"""  <loop name="B{k(i)}" type="revolute">
    <predecessor link="coupler_{k(i)}"/>
    <successor link="crank_{k(i)}"/>
    <predecessor_origin xyz="{NFOURBAR_LENGTH!r} 0 0" rpy="0 0 0"/>
    <successor_origin xyz="{NFOURBAR_LENGTH!r} 0 0" rpy="0 0 0"/>
    <axis xyz="{PLANAR_AXIS}"/>
  </loop>
"""
        )
    # The benchmark's start as the default scene: cranks vertical, couplers horizontal
    # (guesses assembled holding crank 0), crank 0 turning at -1 rad/s (the couplers move
    # at +1 m/s along world x; the other cranks take the velocity with J v = 0).
    parts.append("  <scene>\n")
    parts.append(
        f'    <initial joint="crank_{k(0)}_joint" value="{NFOURBAR_HALF_PI!r}" '
        f'velocity="{NFOURBAR_CRANK_RATE!r}"/>\n'
    )
    for i in range(1, n + 1):
        parts.append(f'    <initial joint="crank_{k(i)}_joint" value="{NFOURBAR_HALF_PI!r}"/>\n')
        parts.append(f'    <initial joint="coupler_{k(i)}_joint" value="{-NFOURBAR_HALF_PI!r}"/>\n')
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


@dataclass(frozen=True)
class Family:
    """A family of mechanisms of growing size.

    Attributes:
        urdf: size n -> URDF+ text.
        sizes: the sizes n of the scaling page.
        about: one sentence: what n counts and the loops.
        start: ``start(mech) -> q`` near a regular configuration (assembled holding the
            independent coordinates), or None for the model's ``q_ref``.
    """

    urdf: Callable[[int], str]
    sizes: tuple[int, ...]
    about: str
    start: Callable | None = None


def nfourbar_start(mech) -> np.ndarray:
    """The N-four-bar's benchmark start: cranks vertical, couplers horizontal."""
    q = mech.q_ref.copy()
    for i, name in enumerate(mech.coordinate_names):
        if name.startswith("crank"):
            q[i] = math.pi / 2
        elif name.startswith("coupler"):
            q[i] = -math.pi / 2
    return q


#: The families of the scaling study, by name.
FAMILIES: dict[str, Family] = {
    "chain": Family(
        chain_urdf,
        (10, 30, 100, 300, 1000),
        "n-link planar chain, 1 m long, its tip pinned to the ground by one revolute loop "
        "(a long tree, 2 independent rows).",
    ),
    "leg-pair": Family(
        leg_pair_urdf,
        (3, 10, 30, 100, 300),
        "two legs of n pitch links under a fixed pelvis, a parallelogram at each hip and "
        "ankle (a branched tree, 4 loops, 8 independent rows).",
    ),
    "nfourbar": Family(
        nfourbar_urdf,
        (1, 2, 5, 10, 20, 40),
        "the IFToMM A02 N-four-bar with n loops (2n independent rows).",
        nfourbar_start,
    ),
}
