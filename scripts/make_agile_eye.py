"""Write models/agile_eye.urdf: a 3-RRR spherical parallel wrist, Agile Eye geometry.

Geometry (Gosselin & Hamel's Agile Eye): every joint axis passes through the
centre O = (0, 0, 0); the three actuator axes u_i are the world axes x, y, z;
every link arc is 90 degrees; at the home configuration (all q = 0) the
intermediate axes are w_i = u_{i+1} and the platform axes v_i = u_{i+2}, so the
platform axes are mutually orthogonal and the wrist is isotropic.

Tree (the lesson's parameterization, Section 5): the platform orientation is
R = Rz(yaw) Ry(pitch) Rx(roll) (Z-Y-X Euler angles) through two massless
links; the pitch is limited to +-1.2 rad, a workspace that keeps 21 degrees
away from the gimbal lock of this parameterization (pitch = +-90 deg, where
the massless-link tree's mass matrix is singular);
each leg i is an actuated proximal joint about u_i and a passive distal joint
about w_i; the leg is closed onto the platform by a revolute <loop> about v_i.

Masses: each leg link is a thin uniform quarter-circle arc (aluminium tube),
proximal arcs of radius 0.10 m and 0.15 kg, distal arcs of radius 0.12 m and
0.10 kg. Its centre of mass is at 2 R / pi (e1 + e2) and its inertia is the
exact thin-arc inertia computed below. The platform is a 0.3 kg cube of side
0.06 m whose centre lies 0.05 m from O along (1, 1, 1)/sqrt(3).

Run:  python scripts/make_agile_eye.py  (rewrites models/agile_eye.urdf)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

R_PROX, M_PROX = 0.10, 0.15  # [m], [kg]
R_DIST, M_DIST = 0.12, 0.10
M_PLAT, SIDE_PLAT, D_PLAT = 0.3, 0.06, 0.05
PITCH_LIMIT = 1.2  # [rad], workspace bound 21 deg short of the Euler gimbal lock
ARC_SEGMENTS = 4  # boxes drawing each quarter-circle link (visual only)
E = np.eye(3)


def arc_inertial(radius: float, mass: float, e1: np.ndarray, e2: np.ndarray):
    """Return (com, inertia about com) of a thin uniform arc R (cos s e1 + sin s e2), 0..pi/2."""
    # Second moment int r r^T dm = m R^2 [1/2 e1e1^T + 1/2 e2e2^T + 1/pi (e1e2^T + e2e1^T)].
    S = (
        mass
        * radius**2
        * (
            0.5 * np.outer(e1, e1)
            + 0.5 * np.outer(e2, e2)
            + (np.outer(e1, e2) + np.outer(e2, e1)) / np.pi
        )
    )
    I_O = np.trace(S) * np.eye(3) - S
    com = 2.0 * radius / np.pi * (e1 + e2)
    I_c = I_O - mass * (com @ com * np.eye(3) - np.outer(com, com))
    return com, I_c


def rpy_from_x_to(direction: np.ndarray) -> tuple[float, float, float]:
    """rpy of a rotation whose x axis points along ``direction``."""
    d = direction / np.linalg.norm(direction)
    yaw = np.arctan2(d[1], d[0])
    pitch = -np.arcsin(d[2])
    return 0.0, float(pitch), float(yaw)


def rpy_z_to(axis: np.ndarray) -> tuple[float, float, float]:
    """rpy of a rotation whose z axis points along the unit ``axis`` (for URDF cylinders)."""
    r, p, y = rpy_from_x_to(axis)
    # Rotate x onto axis, then turn z onto x: Ry(+90 deg) before.
    Rx = _rpy_matrix((r, p, y)) @ _rpy_matrix((0.0, np.pi / 2, 0.0))
    return _matrix_rpy(Rx)


def _rpy_matrix(rpy):
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def _matrix_rpy(R):
    pitch = np.arcsin(-np.clip(R[2, 0], -1, 1))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return float(roll), float(pitch), float(yaw)


def fmt(x) -> str:
    return " ".join(f"{float(v):.12g}" for v in np.atleast_1d(x))


def inertial_xml(com, I, mass) -> str:
    return (
        f'    <inertial>\n      <origin xyz="{fmt(com)}" rpy="0 0 0"/>\n'
        f'      <mass value="{mass:g}"/>\n'
        f'      <inertia ixx="{I[0, 0]:.12g}" ixy="{I[0, 1]:.12g}" ixz="{I[0, 2]:.12g}" '
        f'iyy="{I[1, 1]:.12g}" iyz="{I[1, 2]:.12g}" izz="{I[2, 2]:.12g}"/>\n    </inertial>\n'
    )


def box_between(p1, p2, material, thickness) -> str:
    """A square-section box from point p1 to point p2 [m]."""
    mid = 0.5 * (p1 + p2)
    length = np.linalg.norm(p2 - p1)
    return (
        f'    <visual>\n      <origin xyz="{fmt(mid)}" rpy="{fmt(rpy_from_x_to(p2 - p1))}"/>\n'
        f'      <geometry><box size="{length:.6g} {thickness} {thickness}"/></geometry>\n'
        f'      <material name="{material}"/>\n    </visual>\n'
    )


def arc_visual(radius, e1, e2, material, thickness=0.012, segments=ARC_SEGMENTS) -> str:
    """Boxes along the great-circle arc of the given radius from unit e1 to unit e2.

    A polyline, not the single chord: a 90-degree chord cuts 0.3 R inside the
    arc and ran through the platform. Each box is lengthened by the thickness
    so that neighbours close the polyline's corners.
    """
    angle = np.arccos(np.clip(e1 @ e2, -1.0, 1.0))
    ortho = e2 - (e1 @ e2) * e1
    ortho /= np.linalg.norm(ortho)
    pts = [
        radius * (np.cos(s) * e1 + np.sin(s) * ortho) for s in np.linspace(0, angle, segments + 1)
    ]
    out = []
    for p1, p2 in zip(pts[:-1], pts[1:], strict=True):
        d = (p2 - p1) / np.linalg.norm(p2 - p1)
        out.append(
            box_between(p1 - 0.5 * thickness * d, p2 + 0.5 * thickness * d, material, thickness)
        )
    return "".join(out)


def pin_visual(point, axis, material, radius=0.011, length=0.035) -> str:
    return (
        f'    <visual>\n      <origin xyz="{fmt(point)}" rpy="{fmt(rpy_z_to(axis))}"/>\n'
        f'      <geometry><cylinder radius="{radius}" length="{length}"/></geometry>\n'
        f'      <material name="{material}"/>\n    </visual>\n'
    )


#: The default scene (closedchain's <scene> element): the platform driven along a
#: smooth orientation path by the computed-torque controller. Passive under
#: gravity the wrist falls into a leg singularity within about 1 s; along this
#: path cond(J) stays below 2.4 for 10 s (measured, tests/test_control.py).
SCENE = """  <!-- default scene of closedchain simulate/animate/plot (no -q0 given): the platform
       follows yaw/pitch/roll sinusoids under computed-torque control -->
  <scene>
    <track kp="100" kd="20">
      <sinusoid joint="platform_yaw" offset="0" amplitude="0.8" frequency="0.1"/>
      <sinusoid joint="platform_pitch" offset="0" amplitude="0.5" frequency="0.15"/>
      <sinusoid joint="platform_roll" offset="0" amplitude="0.5" frequency="0.2"/>
    </track>
  </scene>
"""


def build() -> str:
    out = ['<?xml version="1.0"?>\n<!--\n' + __doc__.replace("--", "- -") + "-->\n"]
    out.append('<robot name="agile_eye">\n')
    colors = {
        "base": "0.35 0.35 0.38 1",
        "proximal": "0.85 0.33 0.10 1",
        "distal": "0.00 0.45 0.74 1",
        "platform": "0.47 0.67 0.19 1",
        "actuator": "0.15 0.15 0.15 1",
        "loop": "0.93 0.69 0.13 1",
    }
    for name, rgba in colors.items():
        out.append(f'  <material name="{name}"><color rgba="{rgba}"/></material>\n')
    # Base: actuator housings on the three axes, and a sphere marking O.
    out.append('  <link name="base">\n')
    out.append(
        '    <visual>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
        '      <geometry><sphere radius="0.008"/></geometry>\n'
        '      <material name="base"/>\n    </visual>\n'
    )
    for i in range(3):
        out.append(pin_visual(0.075 * E[i], E[i], "actuator", radius=0.018, length=0.03))
    out.append("  </link>\n")
    out.append('  <link name="euler_link_z"/>\n  <link name="euler_link_y"/>\n')
    # Platform.
    com = D_PLAT * np.ones(3) / np.sqrt(3)
    I_cube = M_PLAT * SIDE_PLAT**2 / 6.0 * np.eye(3)
    out.append('  <link name="platform">\n' + inertial_xml(com, I_cube, M_PLAT))
    out.append(
        f'    <visual>\n      <origin xyz="{fmt(com)}" rpy="0 0 0"/>\n'
        f'      <geometry><box size="{SIDE_PLAT} {SIDE_PLAT} {SIDE_PLAT}"/></geometry>\n'
        '      <material name="platform"/>\n    </visual>\n'
    )
    # Platform frame: arcs from the three loop pins (R_DIST v_i) to a hub on the
    # diagonal, and a stem from the hub to the cube.
    diagonal = np.ones(3) / np.sqrt(3)
    for i in range(3):
        v = E[(i + 2) % 3]
        out.append(arc_visual(R_DIST, v, diagonal, "platform", 0.01, segments=3))
    out.append(box_between(com, R_DIST * diagonal, "platform", 0.012))
    out.append("  </link>\n")
    for axis, limit, (name, parent, child) in zip(
        ("0 0 1", "0 1 0", "1 0 0"),
        (np.pi, PITCH_LIMIT, np.pi),
        (
            ("platform_yaw", "base", "euler_link_z"),
            ("platform_pitch", "euler_link_z", "euler_link_y"),
            ("platform_roll", "euler_link_y", "platform"),
        ),
        strict=True,
    ):
        out.append(
            f'  <joint name="{name}" type="revolute">\n    <parent link="{parent}"/>\n'
            f'    <child link="{child}"/>\n    <origin xyz="0 0 0" rpy="0 0 0"/>\n'
            f'    <axis xyz="{axis}"/>\n'
            f'    <limit lower="{-limit:.12g}" upper="{limit:.12g}" effort="0" '
            'velocity="20"/>\n  </joint>\n'
        )
    for i in range(3):
        u, w, v = E[i], E[(i + 1) % 3], E[(i + 2) % 3]
        leg = i + 1
        c, I = arc_inertial(R_PROX, M_PROX, u, w)
        out.append(f'  <link name="proximal_{leg}">\n' + inertial_xml(c, I, M_PROX))
        out.append(arc_visual(R_PROX, u, w, "proximal"))
        out.append(pin_visual(R_PROX * w, w, "distal"))
        out.append("  </link>\n")
        c, I = arc_inertial(R_DIST, M_DIST, w, v)
        out.append(f'  <link name="distal_{leg}">\n' + inertial_xml(c, I, M_DIST))
        out.append(arc_visual(R_DIST, w, v, "distal"))
        out.append(pin_visual(R_DIST * v, v, "loop", radius=0.013, length=0.03))
        out.append("  </link>\n")
        out.append(
            f'  <joint name="actuator_{leg}" type="revolute">\n    <parent link="base"/>\n'
            f'    <child link="proximal_{leg}"/>\n    <origin xyz="0 0 0" rpy="0 0 0"/>\n'
            f'    <axis xyz="{fmt(u)}"/>\n'
            '    <limit lower="-3.141592653589793" upper="3.141592653589793" effort="10" '
            'velocity="20"/>\n  </joint>\n'
        )
        out.append(
            f'  <joint name="distal_joint_{leg}" type="revolute">\n'
            f'    <parent link="proximal_{leg}"/>\n    <child link="distal_{leg}"/>\n'
            f'    <origin xyz="0 0 0" rpy="0 0 0"/>\n    <axis xyz="{fmt(w)}"/>\n'
            '    <limit lower="-3.141592653589793" upper="3.141592653589793" effort="0" '
            'velocity="20"/>\n  </joint>\n'
        )
        out.append(
            f"  <!-- leg {leg} closed onto the platform: revolute about v_{leg} through O -->\n"
            f'  <loop name="leg{leg}_platform" type="revolute">\n'
            f'    <predecessor link="distal_{leg}"/>\n    <successor link="platform"/>\n'
            '    <predecessor_origin xyz="0 0 0" rpy="0 0 0"/>\n'
            '    <successor_origin xyz="0 0 0" rpy="0 0 0"/>\n'
            f'    <axis xyz="{fmt(v)}"/>\n  </loop>\n'
        )
        out.append(
            f'  <transmission name="actuator_{leg}_transmission">\n'
            "    <type>transmission_interface/SimpleTransmission</type>\n"
            f'    <joint name="actuator_{leg}">\n'
            "      <hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>\n"
            f'    </joint>\n    <actuator name="motor_{leg}">\n'
            "      <mechanicalReduction>1</mechanicalReduction>\n    </actuator>\n"
            "  </transmission>\n"
        )
    out.append(SCENE)
    out.append("</robot>\n")
    return "".join(out)


if __name__ == "__main__":
    target = Path(__file__).resolve().parent.parent / "models" / "agile_eye.urdf"
    target.write_text(build())
    print(f"wrote {target}")
