"""Write the small test mechanisms of tests/data/ (one URDF per loop type).

Each mechanism is a URDF tree with axes not aligned with the coordinate axes
and non-trivial joint origins, closed by one URDF+ ``<loop>``. The loop's
predecessor origin is chosen freely; its successor origin is computed here so
that the two cut frames coincide (up to the motion the loop allows) at a
stated configuration ``q_star``, written into the file's header. The tests
check phi(q_star) = 0 from the file alone, so this script is not a reference:
it only saves writing the closing placement by hand.

Run:  python tests/data/make_test_mechanisms.py  (rewrites the *.urdf files next to it)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

HERE = Path(__file__).resolve().parent


def _fmt(values) -> str:
    return " ".join(repr(float(x)) for x in values)


def _link(name: str, mass: float, com, diag, off=(0.0, 0.0, 0.0)) -> str:
    if mass == 0.0:
        return f'  <link name="{name}"/>\n'
    ixx, iyy, izz = diag
    ixy, ixz, iyz = off
    return (
        f'  <link name="{name}">\n'
        f"    <inertial>\n"
        f'      <origin xyz="{_fmt(com)}" rpy="0 0 0"/>\n'
        f'      <mass value="{mass!r}"/>\n'
        f'      <inertia ixx="{ixx!r}" ixy="{ixy!r}" ixz="{ixz!r}" iyy="{iyy!r}" '
        f'iyz="{iyz!r}" izz="{izz!r}"/>\n'
        f"    </inertial>\n"
        f"  </link>\n"
    )


def _joint(name, jtype, parent, child, xyz, rpy, axis, limit=None, extra="") -> str:
    lim = ""
    if limit is not None:
        lim = f'    <limit lower="{limit[0]!r}" upper="{limit[1]!r}" effort="10" velocity="10"/>\n'
    return (
        f'  <joint name="{name}" type="{jtype}"{extra}>\n'
        f'    <parent link="{parent}"/>\n'
        f'    <child link="{child}"/>\n'
        f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>\n'
        f'    <axis xyz="{_fmt(axis)}"/>\n'
        f"{lim}"
        f"  </joint>\n"
    )


def _transmission(joint: str) -> str:
    return (
        f'  <transmission name="{joint}_transmission">\n'
        f"    <type>transmission_interface/SimpleTransmission</type>\n"
        f'    <joint name="{joint}">\n'
        f"      <hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>\n"
        f"    </joint>\n"
        f'    <actuator name="{joint}_motor"><mechanicalReduction>1</mechanicalReduction>'
        f"</actuator>\n"
        f"  </transmission>\n"
    )


def _close(tree: str, q_star_v, loop) -> str:
    """Return the ``<loop>`` element closing ``tree`` at the configuration q_star_v.

    Args:
        tree: URDF text without the loop.
        q_star_v: joint displacements, shape (nv,) (continuous joints by angle).
        loop: dict with name, type, predecessor, successor, pred_xyz, pred_rpy,
            axis, succ_rpy (free rotation of the successor frame where the
            loop type allows it) and slide (offset along the axis, prismatic).
    """
    model = pin.buildModelFromXML(tree)
    data = model.createData()
    q = pin.integrate(model, pin.neutral(model), np.asarray(q_star_v, dtype=float))
    pin.framesForwardKinematics(model, data, q)
    oMp_link = data.oMf[model.getFrameId(loop["predecessor"], pin.FrameType.BODY)]
    oMs_link = data.oMf[model.getFrameId(loop["successor"], pin.FrameType.BODY)]
    p_origin = pin.SE3(pin.rpy.rpyToMatrix(np.array(loop["pred_rpy"])), np.array(loop["pred_xyz"]))
    oMc1 = oMp_link * p_origin
    if isinstance(loop.get("axis"), str):
        # The slider's line passes through the crank centre (the origin of the
        # first joint): then the crank turns fully (conrod 0.35 m > crank 0.1 m).
        centre = data.oMi[1].translation
        u = oMp_link.translation - centre
        axis = oMc1.rotation.T @ (u / np.linalg.norm(u))
        loop = {**loop, "axis": tuple(float(x) for x in axis)}
    if loop["type"] == "spherical":
        # Only the origins must coincide: any rotation of c2 will do.
        oMc2 = pin.SE3(pin.rpy.rpyToMatrix(np.array(loop["succ_rpy"])), oMc1.translation)
    elif loop["type"] == "prismatic":
        axis = np.array(loop["axis"], dtype=float)
        oMc2 = oMc1 * pin.SE3(np.eye(3), loop["slide"] * axis)
    else:  # fixed
        oMc2 = oMc1
    s_origin = oMs_link.actInv(oMc2)
    rpy_s = pin.rpy.matrixToRpy(s_origin.rotation)
    axis = ""
    if loop["type"] in ("prismatic", "revolute"):
        axis = f'    <axis xyz="{_fmt(loop["axis"])}"/>\n'
    return (
        f'  <loop name="{loop["name"]}" type="{loop["type"]}">\n'
        f'    <predecessor link="{loop["predecessor"]}"/>\n'
        f'    <successor link="{loop["successor"]}"/>\n'
        f'    <predecessor_origin xyz="{_fmt(loop["pred_xyz"])}" '
        f'rpy="{_fmt(loop["pred_rpy"])}"/>\n'
        f'    <successor_origin xyz="{_fmt(s_origin.translation)}" rpy="{_fmt(rpy_s)}"/>\n'
        f"{axis}"
        f"  </loop>\n"
    )


def _write(name: str, header: str, tree_body: str, q_star_v, loop, actuated) -> None:
    tree = f'<robot name="{name}">\n{tree_body}</robot>\n'
    closing = _close(tree, q_star_v, loop)
    text = (
        '<?xml version="1.0"?>\n<!--\n'
        + header.strip("\n")
        + "\n\n  Generated by tests/data/make_test_mechanisms.py. The loop closes at\n"
        + f"  q_star_v = [{', '.join(repr(float(x)) for x in q_star_v)}]\n"
        + "  (joint displacements in velocity order; q_star = pin.integrate(neutral, q_star_v)).\n"
        + "-->\n"
        + f'<robot name="{name}">\n'
        + tree_body
        + closing
        + "".join(_transmission(j) for j in actuated)
        + "</robot>\n"
    )
    (HERE / f"{name}.urdf").write_text(text)


def spherical_chain() -> None:
    """Spatial 4R chain whose last link is pinned to the ground by a spherical loop."""
    body = _link("base", 0.0, None, None)
    body += _link("l1", 0.8, (0.15, 0.01, 0.0), (0.002, 0.006, 0.0065), (1e-4, 0.0, -2e-4))
    body += _link("l2", 0.6, (0.12, 0.0, 0.02), (0.0015, 0.004, 0.0045), (0.0, 2e-4, 0.0))
    body += _link("l3", 0.5, (0.1, -0.02, 0.0), (0.001, 0.003, 0.0032), (-1e-4, 0.0, 1e-4))
    body += _link("l4", 0.4, (0.12, 0.0, 0.01), (0.0008, 0.0025, 0.0026), (0.0, -1e-4, 0.0))
    lim = (-2 * np.pi, 2 * np.pi)
    body += _joint(
        "j1", "revolute", "base", "l1", (0.05, -0.02, 0.1), (0.3, -0.2, 0.5), (0.6, 0.0, 0.8), lim
    )
    body += _joint(
        "j2", "revolute", "l1", "l2", (0.3, 0.05, 0.0), (-0.4, 0.25, 0.1), (0.48, 0.6, 0.64), lim
    )
    body += _joint(
        "j3", "revolute", "l2", "l3", (0.25, -0.03, 0.04), (0.2, 0.5, -0.3), (0.0, 0.28, 0.96), lim
    )
    body += _joint(
        "j4", "revolute", "l3", "l4", (0.2, 0.02, -0.05), (-0.1, -0.3, 0.6), (0.8, -0.36, 0.48), lim
    )
    header = """
  Spatial four-link chain closed by a spherical loop (test mechanism).

  base -j1- l1 -j2- l2 -j3- l3 -j4- l4, four revolute joints with skew axes;
  the point of l4 at the loop's predecessor origin is pinned to a point of
  the base by the spherical loop S (3 equations). Mobility 4 - 3 = 1.
"""
    loop = {
        "name": "S",
        "type": "spherical",
        "predecessor": "l4",
        "successor": "base",
        "pred_xyz": (0.25, 0.03, -0.02),
        "pred_rpy": (0.1, 0.2, 0.3),
        "succ_rpy": (0.4, -0.3, 0.2),
    }
    _write("spherical_chain", header, body, (0.4, -0.7, 1.1, 0.5), loop, ["j1"])


def slider_crank_spatial() -> None:
    """Spatial R-S-U-P slider-crank: continuous crank, slider closed by a prismatic loop."""
    body = _link("ground", 0.0, None, None)
    body += _link("crank", 0.5, (0.05, 0.0, 0.0), (2e-4, 6e-4, 6e-4))
    # The spherical joint at the crank pin: three revolutes with skew axes and
    # two small intermediate bodies (so the tree mass matrix stays positive
    # definite through the gimbal lock of the three-revolute chain).
    body += _link("s_a", 0.01, (0.0, 0.0, 0.0), (1e-6, 1e-6, 1e-6))
    body += _link("s_b", 0.01, (0.0, 0.0, 0.0), (1e-6, 1e-6, 1e-6))
    body += _link("conrod", 0.7, (0.17, 0.0, 0.0), (3e-4, 0.007, 0.007), (0.0, 1e-4, 0.0))
    body += _link("u_a", 0.01, (0.0, 0.0, 0.0), (1e-6, 1e-6, 1e-6))
    body += _link("slider", 0.9, (0.01, 0.0, 0.0), (6e-4, 8e-4, 9e-4), (1e-5, 0.0, 0.0))
    body += _joint(
        "crank_joint",
        "continuous",
        "ground",
        "crank",
        (0.0, 0.0, 0.1),
        (0.2, 0.0, 0.0),
        (0.0, 0.6, 0.8),
    )
    lim = (-2 * np.pi, 2 * np.pi)
    # s1 turns about the crank axis (it takes the crank's full revolution), s2
    # and s3 complete an orthonormal triad: the three-revolute chain stays far
    # from its gimbal lock (s2 = +-90 deg) while the conrod wobbles.
    body += _joint(
        "s1", "revolute", "crank", "s_a", (0.1, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.6, 0.8), lim
    )
    body += _joint(
        "s2", "revolute", "s_a", "s_b", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.8, 0.48, -0.36), lim
    )
    body += _joint(
        "s3",
        "revolute",
        "s_b",
        "conrod",
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (-0.6, 0.64, -0.48),
        lim,
    )
    body += _joint(
        "u1",
        "revolute",
        "conrod",
        "u_a",
        (0.35, 0.0, 0.0),
        (-0.2, 0.3, 0.1),
        (0.48, 0.6, 0.64),
        lim,
    )
    body += _joint(
        "u2", "revolute", "u_a", "slider", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.36, 0.48, -0.8), lim
    )
    header = """
  Spatial R-S-U-P slider-crank (test mechanism).

  ground -crank_joint (continuous, nq 2)- crank -s1 s2 s3 (a spherical joint as
  three revolutes with skew axes)- conrod -u1 u2 (universal)- slider; the
  slider is closed onto the ground by the prismatic loop P, which leaves only
  translation along its axis (5 equations). The slider's line passes through
  the crank centre, tilted out of the crank plane, so the crank turns fully.
  Tree nv = 1 + 3 + 2 = 6, nq = 7; mobility 6 - 5 = 1 (Gruebler:
  6 (4 - 1) - 5 - 3 - 4 - 5 = 1).
"""
    loop = {
        "name": "P",
        "type": "prismatic",
        "predecessor": "slider",
        "successor": "ground",
        "pred_xyz": (0.02, 0.01, 0.0),
        "pred_rpy": (0.1, -0.2, 0.3),
        "axis": "towards_crank_centre",
        "slide": 0.05,
    }
    _write("slider_crank", header, body, (0.7, -0.3, 0.2, 0.1, 0.25, -0.35), loop, ["crank_joint"])


def slider_crank_planar() -> None:
    """Planar slider-crank in the world x-z plane, slider closed by a prismatic loop."""
    body = _link("ground", 0.0, None, None)
    body += _link("crank", 0.5, (0.05, 0.0, 0.0), (2e-4, 6e-4, 6e-4))
    body += _link("conrod", 0.7, (0.15, 0.0, 0.0), (3e-4, 0.005, 0.005))
    body += _link("slider", 0.9, (0.0, 0.0, 0.0), (6e-4, 8e-4, 9e-4))
    lim = (-2 * np.pi, 2 * np.pi)
    body += _joint(
        "crank_joint",
        "revolute",
        "ground",
        "crank",
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        lim,
    )
    body += _joint(
        "conrod_joint",
        "revolute",
        "crank",
        "conrod",
        (0.1, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        lim,
    )
    body += _joint(
        "slider_joint",
        "revolute",
        "conrod",
        "slider",
        (0.3, 0.0, 0.0),
        (0.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        lim,
    )
    header = """
  Planar slider-crank in the world x-z plane (test mechanism).

  Three revolute joints about world y; the slider slides along an inclined
  line of the x-z plane (prismatic loop P, axis at 0.3 rad in the plane).
  Of the prismatic loop's 5 equations only 2 are independent in a planar
  mechanism (the in-plane offset across the axis and the in-plane rotation):
  mobility 3 - 2 = 1.
"""
    loop = {
        "name": "P",
        "type": "prismatic",
        "predecessor": "slider",
        "successor": "ground",
        "pred_xyz": (0.0, 0.0, 0.0),
        "pred_rpy": (0.0, 0.0, 0.0),
        "axis": (0.8, 0.0, 0.6),
        "slide": 0.0,
    }
    _write("slider_crank_planar", header, body, (0.5, -0.9, 0.7), loop, ["crank_joint"])


def fixed_branches() -> None:
    """Two serial branches from the ground welded together by a fixed loop."""
    body = _link("ground", 0.0, None, None)
    inert = [
        ("a1", 0.6, (0.1, 0.0, 0.0), (0.001, 0.003, 0.003), (0.0, 1e-4, 0.0)),
        ("a2", 0.5, (0.08, 0.01, 0.0), (8e-4, 0.002, 0.0022), (1e-4, 0.0, 0.0)),
        ("a3", 0.4, (0.1, 0.0, 0.01), (6e-4, 0.0018, 0.002), (0.0, 0.0, 1e-4)),
        ("a4", 0.3, (0.05, 0.0, 0.0), (4e-4, 8e-4, 9e-4)),
        ("b1", 0.6, (0.1, 0.0, 0.0), (0.001, 0.003, 0.003)),
        ("b2", 0.5, (0.1, -0.01, 0.0), (8e-4, 0.0025, 0.0026), (0.0, -1e-4, 0.0)),
        ("b3", 0.4, (0.06, 0.0, 0.0), (5e-4, 0.001, 0.0011)),
    ]
    for name, m, com, diag, *off in inert:
        body += _link(name, m, com, diag, *off)
    lim = (-2 * np.pi, 2 * np.pi)
    body += _joint(
        "a_j1", "revolute", "ground", "a1", (0.0, 0.0, 0.1), (0.1, 0.0, 0.0), (0.6, 0.0, 0.8), lim
    )
    body += _joint(
        "a_j2",
        "prismatic",
        "a1",
        "a2",
        (0.2, 0.05, 0.0),
        (0.0, 0.3, -0.2),
        (0.36, 0.48, 0.8),
        (-0.5, 0.5),
    )
    body += _joint(
        "a_j3", "revolute", "a2", "a3", (0.15, 0.0, 0.03), (0.4, -0.1, 0.2), (0.0, 0.28, 0.96), lim
    )
    body += _joint(
        "a_j4", "revolute", "a3", "a4", (0.2, 0.0, 0.0), (-0.3, 0.2, 0.1), (0.8, -0.36, 0.48), lim
    )
    body += _joint(
        "b_j1",
        "revolute",
        "ground",
        "b1",
        (0.4, -0.1, 0.05),
        (0.0, -0.2, 0.3),
        (0.0, 0.6, 0.8),
        lim,
    )
    body += _joint(
        "b_j2", "revolute", "b1", "b2", (0.2, 0.0, 0.02), (0.2, 0.1, -0.4), (0.64, 0.48, 0.6), lim
    )
    body += _joint(
        "b_j3", "revolute", "b2", "b3", (0.2, 0.03, 0.0), (-0.2, 0.4, 0.0), (0.48, 0.64, -0.6), lim
    )
    header = """
  Two branches welded by a fixed loop (test mechanism).

  ground -a_j1 (revolute)- a1 -a_j2 (prismatic)- a2 -a_j3- a3 -a_j4- a4 and
  ground -b_j1- b1 -b_j2- b2 -b_j3- b3, axes skew to the coordinate axes; the
  fixed loop W welds a4 to b3 (6 equations). Tree nv = 7; mobility 7 - 6 = 1.
"""
    loop = {
        "name": "W",
        "type": "fixed",
        "predecessor": "a4",
        "successor": "b3",
        "pred_xyz": (0.1, 0.02, -0.01),
        "pred_rpy": (0.5, -0.2, 0.3),
    }
    _write("fixed_branches", header, body, (0.3, 0.1, -0.6, 0.8, 0.5, -0.4, 0.9), loop, ["a_j1"])


#: Offset [m] of the off-centre wrist's cut frames along their loop axes.
WRIST_CUT_OFFSET = 0.1


def off_centre_wrist() -> None:
    """The Agile Eye with its loop cut frames moved off the sphere centre along the axes.

    Same tree and closure set as models/agile_eye.urdf, but every ``<loop>`` places
    both cut frames at ``WRIST_CUT_OFFSET * axis`` instead of at the centre: the
    revolute closures are the same constraints (the frames turn about the centre
    together), but the translation rows no longer vanish identically. With world
    translation rows kept at one pose, assembly from guesses 0.05 rad away reached,
    in 6 of 200 random orientations, configurations satisfying the kept rows with
    other declared rows open by up to 5e-2 (issue 8).
    """
    from lxml import etree

    source = HERE.parent.parent / "models" / "agile_eye.urdf"
    tree = etree.parse(str(source))
    robot = tree.getroot()
    robot.set("name", "off_centre_wrist")
    for loop in robot.findall("loop"):
        axis = np.array([float(x) for x in loop.find("axis").get("xyz").split()])
        axis /= np.linalg.norm(axis)
        for side in ("predecessor_origin", "successor_origin"):
            el = loop.find(side)
            assert el.get("xyz").split() == ["0", "0", "0"] and el.get("rpy") == "0 0 0"
            el.set("xyz", _fmt(WRIST_CUT_OFFSET * axis))
    for node in tree.xpath("/comment()"):
        node.text = (
            "\n  Agile Eye (models/agile_eye.urdf) with every loop's cut frames moved "
            f"{WRIST_CUT_OFFSET} m\n  along the loop axis, off the sphere centre "
            "(test mechanism, issue 8).\n\n  Generated by "
            "tests/data/make_test_mechanisms.py from models/agile_eye.urdf.\n"
        )
    (HERE / "off_centre_wrist.urdf").write_bytes(
        etree.tostring(tree, xml_declaration=True, encoding="utf-8")
    )


def fourbar_fixed_loop() -> None:
    """The lesson's 4-bar with its pin C as a tree joint and the loop closed by welding."""
    from lxml import etree

    source = HERE.parent.parent / "models" / "fourbar.urdf"
    tree = etree.parse(str(source))
    robot = tree.getroot()
    robot.set("name", "fourbar_fixed_loop")
    loop = robot.find("loop")
    pin_link = etree.fromstring('<link name="pin_c"/>')
    pin_joint = etree.fromstring(
        '<joint name="pin_joint" type="revolute"><parent link="coupler"/>'
        '<child link="pin_c"/><origin xyz="0.4 0 0" rpy="0 0 0"/><axis xyz="0 -1 0"/>'
        '<limit lower="-6.283185307179586" upper="6.283185307179586" effort="0" '
        'velocity="50"/></joint>'
    )
    weld = etree.fromstring(
        '<loop name="C" type="fixed"><predecessor link="pin_c"/><successor link="rocker"/>'
        '<predecessor_origin xyz="0 0 0" rpy="0 0 0"/>'
        '<successor_origin xyz="0.3 0 0" rpy="0 0 0"/></loop>'
    )
    index = list(robot).index(loop)
    robot.remove(loop)
    for k, el in enumerate((pin_link, pin_joint, weld)):
        robot.insert(index + k, el)
    for node in tree.xpath("/comment()"):
        node.text = (
            "\n  The lesson's 4-bar (models/fourbar.urdf) with the pin C written as a tree joint"
            "\n  (pin_joint, coupler -> massless link pin_c) and the loop closed by a fixed"
            "\n  <loop> welding pin_c to the rocker's end: 6 declared rows where 3 suffice"
            "\n  (planar), the same motion as the revolute loop (test mechanism, issue 8)."
            "\n\n  Generated by tests/data/make_test_mechanisms.py from models/fourbar.urdf.\n"
        )
    (HERE / "fourbar_fixed_loop.urdf").write_bytes(
        etree.tostring(tree, xml_declaration=True, encoding="utf-8")
    )


#: 6-UPS Stewart platform: base and platform anchor radii [m], anchor half-spread
#: [rad], leg limits [m].
STEWART = dict(r_base=0.5, r_platform=0.3, spread=0.25, legs=(0.3, 1.0))


def stewart() -> None:
    """6-UPS Stewart platform: six legs (universal, prismatic, spherical), the platform
    carried by leg 1 (its spherical joint written as three revolutes) and closed on legs
    2..6 by five spherical loops. At the neutral configuration every leg has length 0
    (outside its limits [0.3, 1.0] m)."""
    g = STEWART
    base_angles = [k * 2 * np.pi / 3 + s * g["spread"] for k in range(3) for s in (-1, 1)]
    plat_angles = [
        k * 2 * np.pi / 3 + s * (np.pi / 3 - g["spread"]) for k in range(3) for s in (-1, 1)
    ]
    b = [g["r_base"] * np.array([np.cos(t), np.sin(t), 0.0]) for t in base_angles]
    p = [g["r_platform"] * np.array([np.cos(t), np.sin(t), 0.0]) for t in plat_angles]
    body = '  <link name="base"/>\n'
    lim_u = (-1.2, 1.2)
    zero = (0.0, 0.0, 0.0)
    for i in range(6):
        n = i + 1
        body += _link(f"cross_{n}", 0.05, (0, 0, 0), (1e-5, 1e-5, 1e-5))
        body += _link(f"cylinder_{n}", 0.4, (0, 0, 0.15), (3e-3, 3e-3, 2e-4))
        body += _link(f"rod_{n}", 0.3, (0, 0, -0.15), (2.5e-3, 2.5e-3, 1e-4))
        for args in (
            (f"u{n}_x", "revolute", "base", f"cross_{n}", b[i], (1, 0, 0), lim_u),
            (f"u{n}_y", "revolute", f"cross_{n}", f"cylinder_{n}", zero, (0, 1, 0), lim_u),
            (f"leg_{n}", "prismatic", f"cylinder_{n}", f"rod_{n}", zero, (0, 0, 1), g["legs"]),
        ):
            body += _joint(*args[:5], zero, *args[5:])
    lim_s = (-1.5, 1.5)
    body += _link("s1_a", 0.02, (0, 0, 0), (1e-6, 1e-6, 1e-6))
    body += _link("s1_b", 0.02, (0, 0, 0), (1e-6, 1e-6, 1e-6))
    body += _link("platform", 2.0, -p[0], (0.04, 0.04, 0.08))
    for name, parent, child, axis in (
        ("s1_x", "rod_1", "s1_a", (1, 0, 0)),
        ("s1_y", "s1_a", "s1_b", (0, 1, 0)),
        ("s1_z", "s1_b", "platform", (0, 0, 1)),
    ):
        body += _joint(name, "revolute", parent, child, zero, zero, axis, lim_s)
    loops = "".join(
        f'  <loop name="S{i + 1}" type="spherical">\n'
        f'    <predecessor link="platform"/>\n'
        f'    <successor link="rod_{i + 1}"/>\n'
        f'    <predecessor_origin xyz="{_fmt(p[i] - p[0])}" rpy="0 0 0"/>\n'
        f'    <successor_origin xyz="0 0 0" rpy="0 0 0"/>\n'
        f"  </loop>\n"
        for i in range(1, 6)
    )
    text = (
        '<?xml version="1.0"?>\n<!--\n'
        "  6-UPS Stewart platform (test mechanism): six legs of universal joint (u*_x,\n"
        "  u*_y), prismatic leg (leg_*, limits [0.3, 1.0] m) and spherical joint; the\n"
        "  platform sits on leg 1 (its spherical joint: s1_x, s1_y, s1_z) and is closed on\n"
        "  legs 2..6 by five spherical loops (15 rows). Mobility 21 - 15 = 6, the six legs\n"
        f"  actuated. Anchors: base radius {g['r_base']} m, platform radius\n"
        f"  {g['r_platform']} m. The neutral configuration (every leg of length 0) is\n"
        "  outside the leg limits.\n\n"
        "  Generated by tests/data/make_test_mechanisms.py.\n"
        "-->\n"
        '<robot name="stewart">\n'
        + body
        + loops
        + "".join(_transmission(f"leg_{i + 1}") for i in range(6))
        + "</robot>\n"
    )
    (HERE / "stewart.urdf").write_text(text)


if __name__ == "__main__":
    spherical_chain()
    slider_crank_spatial()
    slider_crank_planar()
    fixed_branches()
    off_centre_wrist()
    fourbar_fixed_loop()
    stewart()
