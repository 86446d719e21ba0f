"""A generated planar chain of n thin rods whose tip is pinned to the ground (one loop).

Used by the size-limit tests; ``python tests/chain_urdf.py N OUT`` writes one.
"""

from __future__ import annotations

import sys


def chain_urdf(n: int, length: float = 1.0) -> str:
    """Return the URDF+ text of an n-link planar chain (x-z plane) closed onto the ground.

    Each rod is ``length / n`` long with 1 kg, joints about -y; the tip is pinned
    by a revolute ``<loop>`` to the ground at x = 0.6 ``length`` (mobility n - 2).
    """
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
            f'<child link="l{i}"/><origin xyz="{xyz}" rpy="0 {pitch} 0"/><axis xyz="0 -1 0"/>'
            '<limit lower="-3.14" upper="3.14" effort="10" velocity="10"/></joint>'
        )
    out.append(
        f'<loop name="tip" type="revolute"><predecessor link="l{n - 1}"/>'
        f'<successor link="ground"/><predecessor_origin xyz="{rod} 0 0"/>'
        f'<successor_origin xyz="{0.6 * length} 0 0"/><axis xyz="0 -1 0"/></loop>'
    )
    out.append("</robot>")
    return "\n".join(out)


if __name__ == "__main__":
    with open(sys.argv[2], "w") as f:
        f.write(chain_urdf(int(sys.argv[1])))
