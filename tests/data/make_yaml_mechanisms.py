"""Write the test mechanisms in the example-parallel-robots convention (URDF + loops YAML).

Like the robots of Gepetto/example-parallel-robots, each is a URDF tree
exported at an assembled pose (the loops close at q = 0) whose loop frames are
frames of fixed joints, plus a YAML file naming the frame pairs (6d or 3d),
the motors and the joint conversions:

- ``yaml_fivebar.urdf``: a planar five-bar in the x-z plane (joint axes along
  y). Leg 1 ends in a revolute ``pin`` joint carrying the small link
  ``pin_link``, whose fixed joint ``tip1`` coincides with the fixed joint
  ``tip2`` of leg 2. ``yaml_fivebar_6d.yaml`` welds ``tip1`` to ``tip2`` (the
  pin is then the five-bar's fifth joint); ``yaml_fivebar_3d.yaml`` makes
  ``pin`` FIXED and joins the two points (a spherical joint, planar here).
  Mobility 2 either way, motors ``mot1`` and ``mot2``.
- ``yaml_delta.urdf`` / ``.yaml``: a delta-like 3-RSS: three motors at 120
  degrees, upper arms, rods with SPHERICAL conversions at the elbows; leg 0's
  rod carries the platform through a SPHERICAL wrist, legs 1 and 2 join it by
  3d loops. Mobility 9 by Gruebler-Kutzbach (7 bodies, 3 revolute and 6
  spherical joints: 6*7 - 3*5 - 6*3), of which 3 are the rods' spins.
- ``yaml_delta_light.urdf``: the same delta with rods of LIGHT_ROD_MASS,
  like the corpus's near-massless links (M's eigenvalues from 5e-8 to 0.15
  kg m^2: the rods' spins); it reads ``yaml_delta.yaml``.
- ``yaml_ujoint_leg.urdf`` / ``.yaml``: a planar leg (hip and knee about y)
  whose knee is driven by a crank and a rod; the rod hangs from the crank by a
  UJOINT_YX conversion and joins the shin by a 3d loop. Mobility 2
  (hip and crank motors).
- ``yaml_offset_rod.urdf`` / ``.yaml``: a four-bar whose rocker tip stands
  OFFSET_ROD_GAP off the plane of the crank, the rod hanging from the crank by
  a revolute placeholder of a ball joint: as written its loop cannot close
  (the kangaroo robots' root cause); it does not close at q = 0.
  ``yaml_offset_rod_ball.yaml`` converts the placeholder into a SPHERICAL
  joint: the loop closes, mobility 2 (5 - 3: the crank and the rod's spin).
- ``yaml_parallel_leg.urdf`` / ``.yaml``: a leg in the manner of the corpus's
  talos_like: hip yaw, roll and pitch motors in series, a passive knee driven by
  a knee motor on the thigh (crank, rod on a UJOINT_YX, the rod's tip welded 6d
  to a SPHERICAL link of the shin) and a passive ankle driven by an ankle motor
  on the shin (crank, rod on a UJOINT_YX, 3d loop to the foot). Mobility 5.

The numbers below place every frame; the tests check from the files alone
that the named frames coincide at q = 0, so this script is not a reference.

Run:  python tests/data/make_yaml_mechanisms.py  (rewrites the files next to it)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

#: Rod mass [kg] of yaml_delta_light (1e-4 of yaml_delta's): a condition number of M of 3e6.
LIGHT_ROD_MASS = 2e-5


def _fmt(values) -> str:
    return " ".join(repr(round(float(x), 15) + 0.0) for x in values)


def _rz(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _stick(mass: float, d: np.ndarray, radius: float = 0.01) -> np.ndarray:
    """Rotational inertia [kg m^2] about the centre of a solid rod along d (length |d|)."""
    length = float(np.linalg.norm(d))
    u = d / length
    P = np.outer(u, u)
    return mass * length**2 / 12.0 * (np.eye(3) - P) + mass * radius**2 / 4.0 * (np.eye(3) + P)


def _link(name: str, mass: float = 0.0, com=(0.0, 0.0, 0.0), inertia=None) -> str:
    if mass == 0.0:
        return f'  <link name="{name}"/>\n'
    I = np.asarray(inertia, dtype=float)
    return (
        f'  <link name="{name}">\n'
        f"    <inertial>\n"
        f'      <origin xyz="{_fmt(com)}" rpy="0 0 0"/>\n'
        f'      <mass value="{mass!r}"/>\n'
        f'      <inertia ixx="{I[0, 0]:.15g}" ixy="{I[0, 1]:.15g}" ixz="{I[0, 2]:.15g}" '
        f'iyy="{I[1, 1]:.15g}" iyz="{I[1, 2]:.15g}" izz="{I[2, 2]:.15g}"/>\n'
        f"    </inertial>\n"
        f"  </link>\n"
    )


def _rod_link(name: str, mass: float, d, radius: float = 0.01) -> str:
    """A uniform rod from the link origin to d (in the link frame)."""
    d = np.asarray(d, dtype=float)
    return _link(name, mass, d / 2.0, _stick(mass, d, radius))


def _joint(name, jtype, parent, child, xyz, rpy=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0)) -> str:
    extra = ""
    if jtype == "revolute":
        extra = (
            f'    <axis xyz="{_fmt(axis)}"/>\n'
            '    <limit lower="-3.14" upper="3.14" effort="10" velocity="20"/>\n'
        )
    return (
        f'  <joint name="{name}" type="{jtype}">\n'
        f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>\n'
        f'    <parent link="{parent}"/>\n'
        f'    <child link="{child}"/>\n'
        f"{extra}"
        f"  </joint>\n"
    )


def _write(name: str, header: str, body: str, note: str = "loops close at q = 0") -> None:
    text = (
        '<?xml version="1.0"?>\n<!--\n'
        + header.strip("\n")
        + f"\n\n  Generated by tests/data/make_yaml_mechanisms.py ({note}).\n-->\n"
        + f'<robot name="{name}">\n{body}</robot>\n'
    )
    (HERE / f"{name}.urdf").write_text(text)


def _circle_point(a: np.ndarray, b: np.ndarray, ra: float, rb: float) -> np.ndarray:
    """The point of the x-z plane at distance ra from a and rb from b, on the -z side."""
    d = float(np.linalg.norm(b - a))
    x = (ra**2 - rb**2 + d**2) / (2.0 * d)
    h = np.sqrt(ra**2 - x**2)
    u = (b - a) / d
    n = np.array([-u[2], 0.0, u[0]])  # u turned by 90 degrees in the x-z plane
    p = a + x * u + h * n
    return p if p[2] < a[2] else a + x * u - h * n


def fivebar() -> None:
    m1, m2 = np.array([-0.1, 0.0, 0.0]), np.array([0.1, 0.0, 0.0])
    tip = np.array([0.02, 0.0, -0.33])
    e1 = _circle_point(m1, tip, 0.2, 0.25)
    e2 = _circle_point(m2, tip, 0.22, 0.26)
    # tip1: a frame of pin_link away from the pin, turned: tip2 must match it exactly.
    t_xyz, t_rpy = np.array([0.03, 0.0, 0.01]), np.array([0.2, 0.3, 0.1])
    body = _link("base")
    body += _rod_link("prox1", 0.3, e1 - m1) + _rod_link("dist1", 0.25, tip - e1)
    body += _link("pin_link", 0.05, (0.0, 0.0, 0.0), np.diag([2e-5, 2e-5, 2e-5]))
    body += _link("tip1_link")
    body += _rod_link("prox2", 0.3, e2 - m2) + _rod_link("dist2", 0.25, tip - e2)
    body += _link("tip2_link")
    body += _joint("mot1", "revolute", "base", "prox1", m1)
    body += _joint("free1", "revolute", "prox1", "dist1", e1 - m1)
    body += _joint("pin", "revolute", "dist1", "pin_link", tip - e1)
    body += _joint("tip1", "fixed", "pin_link", "tip1_link", t_xyz, t_rpy)
    body += _joint("mot2", "revolute", "base", "prox2", m2)
    body += _joint("free2", "revolute", "prox2", "dist2", e2 - m2)
    body += _joint("tip2", "fixed", "dist2", "tip2_link", tip + t_xyz - e2, t_rpy)
    header = f"""
  Planar five-bar (x-z plane, joint axes along y) in the example-parallel-robots
  convention: motors mot1 at {_fmt(m1)}, mot2 at {_fmt(m2)} [m]; elbows at
  {_fmt(e1)} and {_fmt(e2)}; the pin at {_fmt(tip)}. The fixed joints tip1
  (on pin_link) and tip2 (on dist2) have the same placement at q = 0.
"""
    _write("yaml_fivebar", header, body)
    (HERE / "yaml_fivebar_6d.yaml").write_text(
        "# tip1 welded to tip2: the revolute joint pin closes the five-bar.\n"
        "closed_loop: [['tip1', 'tip2']]\n"
        "type: ['6d']\n"
        "name_mot: ['mot1', 'mot2']\n"
    )
    (HERE / "yaml_fivebar_3d.yaml").write_text(
        "# pin made FIXED; the points tip1 and tip2 joined (a spherical joint).\n"
        "closed_loop:\n  - [tip1, tip2]\n"
        "type: [3D]\n"
        "name_mot: [mot1, mot2]\n"
        "joint_name: [pin]\n"
        "joint_type: [FIXED]\n"
    )


def delta(name: str = "yaml_delta", rod_mass: float = 0.2) -> None:
    radius, arm, beta = 0.15, 0.2, 0.5
    centre, r_p = np.array([0.0, 0.0, -0.35]), 0.06
    body = _link("base", 2.0, (0.0, 0.0, 0.02), np.diag([0.01, 0.01, 0.02]))  # on the world
    joints = ""
    thetas = [2.0 * np.pi * k / 3.0 for k in range(3)]
    elbows, attach = [], []
    for k, theta in enumerate(thetas):
        R = _rz(theta)
        b = R @ np.array([radius, 0.0, 0.0])
        e_local = np.array([arm * np.cos(beta), 0.0, -arm * np.sin(beta)])
        e = b + R @ e_local
        p = centre + R @ np.array([r_p, 0.0, 0.0])
        elbows.append(e)
        attach.append(p)
        rod_local = R.T @ (p - e)  # the rod frame is turned like the arm's at q = 0
        body += _rod_link(f"arm{k}", 0.3, e_local) + _rod_link(f"rod{k}", rod_mass, rod_local, 0.1)
        joints += _joint(f"mot{k}", "revolute", "base", f"arm{k}", b, (0.0, 0.0, theta))
        joints += _joint(f"elbow{k}", "revolute", f"arm{k}", f"rod{k}", e_local, axis=(1, 0, 0))
        if k == 0:
            joints += _joint("wrist0", "revolute", "rod0", "platform", rod_local, axis=(1, 0, 0))
        else:
            body += _link(f"rod_tip{k}_link") + _link(f"platform_att{k}_link")
            joints += _joint(f"rod_tip{k}", "fixed", f"rod{k}", f"rod_tip{k}_link", rod_local)
            # The platform frame is world-parallel at q = 0 (leg 0 is at theta = 0).
            joints += _joint(
                f"platform_att{k}", "fixed", "platform", f"platform_att{k}_link", p - attach[0]
            )
    platform_com = centre - attach[0]
    body += _link("platform", 0.5, platform_com, np.diag([1e-3, 1e-3, 1.8e-3]))
    header = f"""
  Delta-like 3-RSS in the example-parallel-robots convention: motors mot0..2
  at radius {radius} m, 120 degrees apart, about the tangent; upper arms
  {arm} m long, {beta} rad below the horizontal; rods of {rod_mass!r} kg from the
  elbows to the platform's attachment points at radius {r_p} m around
  {_fmt(centre)} [m].
  The elbows and the wrist of leg 0 are revolute placeholders that the YAML
  converts into SPHERICAL joints.
"""
    _write(name, header, body + joints)
    if name != "yaml_delta":  # a variant: it reads yaml_delta.yaml
        return
    (HERE / "yaml_delta.yaml").write_text(
        "closed_loop: [['rod_tip1', 'platform_att1'], ['rod_tip2', 'platform_att2']]\n"
        "type: ['3d', '3d']\n"
        "name_mot: ['mot0', 'mot1', 'mot2']\n"
        "joint_name: ['elbow0', 'elbow1', 'elbow2', 'wrist0']\n"
        "joint_type: ['SPHERICAL', 'SPHERICAL', 'SPHERICAL', 'SPHERICAL']\n"
    )


def ujoint_leg() -> None:
    hip, knee = np.zeros(3), np.array([0.0, 0.0, -0.4])
    foot = np.array([0.0, 0.0, -0.8])
    pivot, crank_tip = np.array([0.08, 0.0, 0.0]), np.array([0.14, 0.0, 0.0])
    attach = np.array([0.05, 0.0, -0.5])
    body = _link("base")
    body += _rod_link("thigh", 1.0, knee - hip) + _rod_link("shin", 0.6, foot - knee)
    body += _rod_link("crank", 0.1, crank_tip - pivot) + _rod_link("rod", 0.15, attach - crank_tip)
    body += _link("rod_tip_link") + _link("shin_att_link")
    body += _joint("hip", "revolute", "base", "thigh", hip)
    body += _joint("knee", "revolute", "thigh", "shin", knee - hip)
    body += _joint("crank_mot", "revolute", "base", "crank", pivot)
    body += _joint("rod_ujoint", "revolute", "crank", "rod", crank_tip - pivot)
    body += _joint("rod_tip", "fixed", "rod", "rod_tip_link", attach - crank_tip)
    body += _joint("shin_att", "fixed", "shin", "shin_att_link", attach - knee)
    header = f"""
  Leg in the example-parallel-robots convention: hip at {_fmt(hip)}, knee at
  {_fmt(knee)} [m] (axes along y); a crank about y at {_fmt(pivot)} drives the
  knee through a rod from the crank tip {_fmt(crank_tip)} to the shin point
  {_fmt(attach)}. The YAML makes the rod's joint a UJOINT_YX and joins its tip
  to the shin point (3d).
"""
    _write("yaml_ujoint_leg", header, body)
    (HERE / "yaml_ujoint_leg.yaml").write_text(
        "closed_loop: [['rod_tip', 'shin_att']]\n"
        "type: ['3d']\n"
        "name_mot: ['hip', 'crank_mot']\n"
        "joint_name: ['rod_ujoint']\n"
        "joint_type: ['UJOINT_YX']\n"
    )


def offset_rod() -> None:
    crank_tip, rod_end = np.array([0.1, 0.0, 0.0]), np.array([0.35, 0.0, 0.0])
    pivot, rocker_tip = np.array([0.35, 0.0, -0.2]), np.array([0.35, OFFSET_ROD_GAP, 0.0])
    body = _link("base")
    body += _rod_link("crank", 0.1, crank_tip) + _rod_link("rod", 0.15, rod_end - crank_tip)
    body += _rod_link("rocker", 0.1, rocker_tip - pivot) + _link("rod_end_link")
    body += _link("rocker_tip_link")
    body += _joint("mot1", "revolute", "base", "crank", np.zeros(3))
    body += _joint("spherical_rod", "revolute", "crank", "rod", crank_tip, axis=(1, 0, 0))
    body += _joint("rod_end", "fixed", "rod", "rod_end_link", rod_end - crank_tip)
    body += _joint("rocker_pivot", "revolute", "base", "rocker", pivot)
    body += _joint("rocker_tip", "fixed", "rocker", "rocker_tip_link", rocker_tip - pivot)
    header = f"""
  Four-bar off its plane, in the example-parallel-robots convention (the
  root cause of kangaroo_like and kangaroo_like_2legs not closing): a crank
  mot1 about y at the origin, a rod from the crank tip {_fmt(crank_tip)} to
  rod_end {_fmt(rod_end)}, a rocker about y at {_fmt(pivot)} whose tip
  rocker_tip {_fmt(rocker_tip)} [m] stands {OFFSET_ROD_GAP} m off the plane
  y = 0. The rod hangs from the crank by spherical_rod, a revolute joint
  about the rod's own axis x (the corpus's placeholder of a ball joint).
  As written (yaml_offset_rod.yaml, rod_end and rocker_tip joined 3d) the rod
  end stays at y = 0 in every configuration: the loop cannot close. Made a
  ball (joint_type SPHERICAL) the rod swings off the plane and it closes;
  welded (6d) instead, the ball's centre stays at y = 0 on the crank and at
  y = {OFFSET_ROD_GAP} through the weld: open again.
"""
    _write("yaml_offset_rod", header, body, note="its loop does not close at q = 0")
    (HERE / "yaml_offset_rod.yaml").write_text(
        "# As the corpus writes it: spherical_rod left revolute, rod_end joined 3d.\n"
        "closed_loop: [['rod_end', 'rocker_tip']]\n"
        "type: ['3d']\n"
        "name_mot: ['mot1']\n"
    )
    (HERE / "yaml_offset_rod_ball.yaml").write_text(
        "# The remedy: spherical_rod made a ball joint, the loop closes.\n"
        "closed_loop: [['rod_end', 'rocker_tip']]\n"
        "type: ['3d']\n"
        "name_mot: ['mot1']\n"
        "joint_name: ['spherical_rod']\n"
        "joint_type: ['SPHERICAL']\n"
    )


#: How far [m] yaml_offset_rod's rocker tip stands off the plane of the rod's motion.
OFFSET_ROD_GAP = 0.01


def parallel_leg() -> None:
    # Thigh frame at the hip pitch joint; shin frame at the knee; foot frame at the ankle.
    hip_x = hip_y = np.array([0.0, 0.0, -0.05])  # the three hip axes meet there
    knee, ankle = np.array([0.0, 0.0, -0.4]), np.array([0.0, 0.0, -0.4])  # each from its parent
    p1, c1, s1 = (
        np.array([0.06, 0.0, -0.05]),
        np.array([0.12, 0.0, -0.05]),
        np.array([0.06, 0.0, -0.05]),
    )
    p2, c2, s2 = (
        np.array([-0.06, 0.0, -0.05]),
        np.array([-0.12, 0.0, -0.05]),
        np.array([-0.06, 0.0, -0.02]),
    )
    sole = np.array([0.05, 0.0, -0.05])
    # p1, c1 (thigh frame): the knee crank's pivot and tip; s1 (shin frame): the rod's end.
    # p2, c2 (shin frame): the ankle crank's pivot and tip; s2 (foot frame): its rod's end.
    rod1 = (knee + s1) - c1  # thigh frame, at q = 0
    rod2 = (ankle + s2) - c2  # shin frame, at q = 0
    body = _link("pelvis")
    body += _link("hip_z_link", 0.5, (0.0, 0.0, -0.025), np.diag([5e-4, 5e-4, 5e-4]))
    body += _link("hip_x_link", 0.5, (0.0, 0.0, -0.025), np.diag([5e-4, 5e-4, 5e-4]))
    body += _rod_link("thigh", 2.0, knee, 0.04) + _rod_link("shin", 1.0, ankle, 0.03)
    body += _link("foot", 0.4, (0.03, 0.0, -0.04), np.diag([4e-4, 8e-4, 8e-4]))
    body += _rod_link("knee_crank", 0.1, c1 - p1) + _rod_link("knee_rod", 0.15, rod1)
    body += _rod_link("ankle_crank", 0.1, c2 - p2) + _rod_link("ankle_rod", 0.1, rod2)
    body += _link("knee_ball", 0.02, (0.0, 0.0, 0.0), np.diag([1e-6, 1e-6, 1e-6]))
    for frame in ("knee_rod_tip", "knee_att", "ankle_rod_tip", "ankle_att", "sole"):
        body += _link(f"{frame}_link")
    body += _joint("hip_z", "revolute", "pelvis", "hip_z_link", np.zeros(3), axis=(0, 0, 1))
    body += _joint("hip_x", "revolute", "hip_z_link", "hip_x_link", hip_x, axis=(1, 0, 0))
    body += _joint("hip_y", "revolute", "hip_x_link", "thigh", hip_y - hip_x)
    body += _joint("knee", "revolute", "thigh", "shin", knee)
    body += _joint("ankle", "revolute", "shin", "foot", ankle)
    body += _joint("sole", "fixed", "foot", "sole_link", sole)
    body += _joint("knee_mot", "revolute", "thigh", "knee_crank", p1)
    body += _joint("knee_rod_u", "revolute", "knee_crank", "knee_rod", c1 - p1)
    body += _joint("knee_rod_tip", "fixed", "knee_rod", "knee_rod_tip_link", rod1)
    body += _joint("knee_ball_joint", "revolute", "shin", "knee_ball", s1)
    body += _joint("knee_att", "fixed", "knee_ball", "knee_att_link", np.zeros(3))
    body += _joint("ankle_mot", "revolute", "shin", "ankle_crank", p2)
    body += _joint("ankle_rod_u", "revolute", "ankle_crank", "ankle_rod", c2 - p2)
    body += _joint("ankle_rod_tip", "fixed", "ankle_rod", "ankle_rod_tip_link", rod2)
    body += _joint("ankle_att", "fixed", "foot", "ankle_att_link", s2)
    header = f"""
  Leg in the example-parallel-robots convention (a small talos_like): hip yaw
  (z), roll (x) and pitch (y) motors at the origin, {_fmt(hip_x)} and {_fmt(hip_y)}
  (the three axes meet at the second point);
  knee {_fmt(knee)} below the hip pitch, ankle {_fmt(ankle)} below the knee, the
  frame sole {_fmt(sole)} from the ankle [m]; knee and ankle about y, passive.
  Knee drive, thigh frame: crank knee_mot about y at {_fmt(p1)}, tip {_fmt(c1)};
  rod on knee_rod_u (UJOINT_YX) to the knee_ball joint {_fmt(s1)} from the knee
  (SPHERICAL), welded 6d. Ankle drive, shin frame: crank ankle_mot about y at
  {_fmt(p2)}, tip {_fmt(c2)}; rod on ankle_rod_u (UJOINT_YX) to the foot point
  {_fmt(s2)} from the ankle, 3d.
"""
    _write("yaml_parallel_leg", header, body)
    (HERE / "yaml_parallel_leg.yaml").write_text(
        "closed_loop: [['knee_rod_tip', 'knee_att'], ['ankle_rod_tip', 'ankle_att']]\n"
        "type: ['6d', '3d']\n"
        "name_mot: ['hip_z', 'hip_x', 'hip_y', 'knee_mot', 'ankle_mot']\n"
        "joint_name: ['knee_rod_u', 'ankle_rod_u', 'knee_ball_joint']\n"
        "joint_type: ['UJOINT_YX', 'UJOINT_YX', 'SPHERICAL']\n"
    )


if __name__ == "__main__":
    fivebar()
    delta()
    delta("yaml_delta_light", rod_mass=LIGHT_ROD_MASS)
    ujoint_leg()
    offset_rod()
    parallel_leg()
