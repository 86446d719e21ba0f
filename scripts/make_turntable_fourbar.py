"""Write models/turntable_fourbar.urdf: the lesson's 4-bar on a turntable (a moving base).

The smallest moving-base example of issue 8: ``models/fourbar.urdf`` unchanged
(links, joints, loop C, crank transmission), its ground link mounted on a
turntable that turns about the world vertical z through the middle of the
ground line AD (x = 0.25 m). The turntable is a uniform disk of 2 kg and
radius 0.3 m, 0.02 m thick, its top face 0.05 m below the ground line; it is
actuated (a transmission), and passive when driven by zero torque.

Tree: base -turntable_joint (revolute, z)- turntable -ground_mount (fixed,
x = -0.25 m)- ground - the 4-bar. nv = 4, mobility 2 (turntable, crank).

Run:  python scripts/make_turntable_fourbar.py  (rewrites models/turntable_fourbar.urdf)
"""

from __future__ import annotations

from pathlib import Path

from lxml import etree

ROOT = Path(__file__).resolve().parent.parent
SOURCE = ROOT / "models" / "fourbar.urdf"
TARGET = ROOT / "models" / "turntable_fourbar.urdf"

AXIS_X = 0.25  # [m] turntable axis through the middle of AD
DISK_MASS, DISK_RADIUS, DISK_THICKNESS = 2.0, 0.3, 0.02  # [kg], [m], [m]
DISK_DROP = 0.05  # [m] from the ground line down to the disk's top face

HEADER = f"""
  The lesson's planar 4-bar (models/fourbar.urdf, unchanged) on a turntable.

  The 4-bar's ground link is mounted on a turntable that turns about the world
  vertical z through the middle of its ground line AD (x = {AXIS_X} m, y = 0):
  its plane of motion, the turntable's x-z plane, turns with it. The smallest
  moving-base example: the loop C must stay closed in every turntable angle.
  Turntable: uniform disk, {DISK_MASS} kg, radius {DISK_RADIUS} m, {DISK_THICKNESS} m thick,
  top face {DISK_DROP} m below the ground line; inertia about its centre
  Izz = m r^2 / 2, Ixx = Iyy = m (3 r^2 + h^2) / 12. Actuated (transmission);
  passive when driven by zero torque.

  Tree: base -turntable_joint (revolute, z)- turntable -ground_mount (fixed)-
  ground -crank_joint ... as in fourbar.urdf. q = [turntable_joint, crank_joint,
  coupler_joint, rocker_joint]; mobility 2.

  Written by scripts/make_turntable_fourbar.py from models/fourbar.urdf.
"""


def main() -> None:
    parser = etree.XMLParser(remove_blank_text=False)
    tree = etree.parse(str(SOURCE), parser)
    robot = tree.getroot()
    robot.set("name", "turntable_fourbar")
    for node in robot.xpath("comment()"):
        robot.remove(node)
    for node in tree.xpath("/comment()"):
        node.text = HEADER
    m, r, h = DISK_MASS, DISK_RADIUS, DISK_THICKNESS
    izz = m * r * r / 2.0
    ixx = m * (3.0 * r * r + h * h) / 12.0
    zc = -DISK_DROP - h / 2.0
    xml = f"""
  <material name="turntable"><color rgba="0.55 0.55 0.60 1"/></material>
  <link name="base"/>
  <link name="turntable">
    <inertial>
      <origin xyz="0 0 {zc!r}" rpy="0 0 0"/>
      <mass value="{m!r}"/>
      <inertia ixx="{ixx!r}" ixy="0" ixz="0" iyy="{ixx!r}" iyz="0" izz="{izz!r}"/>
    </inertial>
    <visual>
      <origin xyz="0 0 {zc!r}" rpy="0 0 0"/>
      <geometry><cylinder radius="{r!r}" length="{h!r}"/></geometry>
      <material name="turntable"/>
    </visual>
  </link>
  <joint name="turntable_joint" type="revolute">
    <parent link="base"/>
    <child link="turntable"/>
    <origin xyz="{AXIS_X!r} 0 0" rpy="0 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1e6" upper="1e6" effort="100" velocity="100"/>
  </joint>
  <joint name="ground_mount" type="fixed">
    <parent link="turntable"/>
    <child link="ground"/>
    <origin xyz="{-AXIS_X!r} 0 0" rpy="0 0 0"/>
  </joint>
  <transmission name="turntable_transmission">
    <type>transmission_interface/SimpleTransmission</type>
    <joint name="turntable_joint">
      <hardwareInterface>hardware_interface/EffortJointInterface</hardwareInterface>
    </joint>
    <actuator name="turntable_motor">
      <mechanicalReduction>1</mechanicalReduction>
    </actuator>
  </transmission>
"""
    fragment = etree.fromstring(f"<r>{xml}</r>")
    # Materials first (before the links), the rest after the existing materials.
    first_link = robot.find("link")
    index = list(robot).index(first_link)
    for k, el in enumerate(fragment):
        robot.insert(index + k, el)
    TARGET.write_bytes(etree.tostring(tree, xml_declaration=True, encoding="utf-8"))


if __name__ == "__main__":
    main()
