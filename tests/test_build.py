"""The model built from a URDF's description against Pinocchio's own URDF reader.

:func:`closedchain.build.build_model` of :func:`closedchain.urdf.parse_urdf`'s
description must equal ``pinocchio.buildModelFromUrdf`` of the same file (the
reference, used in tests only): sizes, joint kinds, names, parents and placements,
inertias, every limit vector, frames (names, types, parents, placements,
inertias), and the mass matrix and inverse dynamics at random configurations;
for every URDF of models/ and tests/data, a set of example-robot-data robots, and
each with a free-flyer and a planar root joint. Then the tree errors urdfdom
used to report, now reported by the reader itself.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from closedchain import ModelFileError
from closedchain import urdf as urdf_module
from closedchain.build import build_model
from closedchain.robots import erd_robots_dir
from closedchain.urdf import parse_urdf

ROOT = Path(__file__).resolve().parent.parent

#: Overlays of the repository (merged into a base, no tree of their own).
OVERLAYS = (
    "cassie_standing.urdf",
    "solo12_pinned.urdf",
    "spring_legs_pinned.urdf",
    "spring_legs_standing.urdf",
    "talos_standing.urdf",
    "ur5_crank.urdf",
)

#: URDF files of the repository that are whole trees.
LOCAL_URDFS = sorted(
    p
    for p in (*ROOT.glob("models/*.urdf"), *(ROOT / "tests" / "data").glob("*.urdf"))
    if p.name not in OVERLAYS
)

#: example-robot-data robots: humanoids with fixed joints and mimic grippers, arms
#: with negative axes, quadrupeds, continuous joints (baxter, double pendulum, PR2's
#: reader-refused transmissions aside), a floating joint in the tree (quadrotor).
ERD_URDFS = (
    "talos_data/robots/talos_reduced.urdf",
    "talos_data/robots/talos_full_v2.urdf",
    "solo_description/robots/solo12.urdf",
    "ur_description/urdf/ur5_robot.urdf",
    "ur_description/urdf/ur5_gripper.urdf",
    "panda_description/urdf/panda.urdf",
    "baxter_description/urdf/baxter.urdf",
    "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
    "romeo_description/urdf/romeo.urdf",
    "icub_description/robots/icub.urdf",
    "centauro_description/urdf/centauro.urdf",
    "hector_description/robots/quadrotor_base.urdf",
    "xarm_description/urdf/xarm7.urdf",
    "go2_description/urdf/go2.urdf",
)

#: Root joints the comparison is made with (None: the root link is fixed).
ROOT_JOINTS = {"fixed": None, "free": pin.JointModelFreeFlyer, "planar": pin.JointModelPlanar}

#: Random configurations at which the dynamics are compared.
N_SAMPLES = 3


#: Tolerance on placements, inertias and limits [m, rad, kg, kg m^2]: the two readers turn
#: rpy into rotations through different round-offs (urdfdom: a quaternion).
PLACEMENT_TOL = 1e-12

#: Relative tolerance on the mass matrix and inverse dynamics at random q (round-off of
#: the placements above through a chain of up to ~40 joints).
DYNAMICS_RTOL = 1e-10

LIMIT_VECTORS = (
    "lowerPositionLimit",
    "upperPositionLimit",
    "lowerVelocityLimit",
    "upperVelocityLimit",
    "lowerEffortLimit",
    "upperEffortLimit",
    "lowerDryFrictionLimit",
    "upperDryFrictionLimit",
    "damping",
)


def differences(ours: pin.Model, reference: pin.Model, rng: np.random.Generator) -> list[str]:
    """Return what differs between two models (empty: equal within the tolerances)."""
    out: list[str] = []
    if (ours.nq, ours.nv, ours.njoints, ours.nframes) != (
        reference.nq,
        reference.nv,
        reference.njoints,
        reference.nframes,
    ):
        return [
            f"sizes {ours.nq, ours.nv, ours.njoints, ours.nframes} != "
            f"{reference.nq, reference.nv, reference.njoints, reference.nframes}"
        ]
    if ours.name != reference.name:
        out.append(f"name {ours.name!r} != {reference.name!r}")
    for j in range(ours.njoints):
        a, b = ours.joints[j], reference.joints[j]
        name = reference.names[j]
        if (ours.names[j], a.shortname(), ours.parents[j]) != (
            name,
            b.shortname(),
            reference.parents[j],
        ):
            out.append(
                f"joint {j}: {ours.names[j], a.shortname(), ours.parents[j]} != "
                f"{name, b.shortname(), reference.parents[j]}"
            )
        if not ours.jointPlacements[j].isApprox(reference.jointPlacements[j], PLACEMENT_TOL):
            out.append(f"joint {name}: placement differs")
        ia, ib = ours.inertias[j], reference.inertias[j]
        if not np.allclose(
            ia.toDynamicParameters(), ib.toDynamicParameters(), rtol=0, atol=PLACEMENT_TOL
        ):
            out.append(
                f"joint {name}: inertia {ia.toDynamicParameters()} != {ib.toDynamicParameters()}"
            )
    for vector in LIMIT_VECTORS:
        a, b = np.asarray(getattr(ours, vector)), np.asarray(getattr(reference, vector))
        if not np.array_equal(a, b):
            out.append(f"{vector} {a} != {b}")
    for f in range(ours.nframes):
        a, b = ours.frames[f], reference.frames[f]
        if (a.name, a.type, a.parentJoint, a.parentFrame) != (
            b.name,
            b.type,
            b.parentJoint,
            b.parentFrame,
        ):
            out.append(
                f"frame {f}: {a.name, a.type, a.parentJoint, a.parentFrame} != "
                f"{b.name, b.type, b.parentJoint, b.parentFrame}"
            )
        if not a.placement.isApprox(b.placement, PLACEMENT_TOL):
            out.append(f"frame {b.name}: placement differs")
        if not np.allclose(
            a.inertia.toDynamicParameters(),
            b.inertia.toDynamicParameters(),
            rtol=0,
            atol=PLACEMENT_TOL,
        ):
            out.append(f"frame {b.name}: inertia differs")
    if out or reference.nv == 0:
        return out
    da, db = ours.createData(), reference.createData()
    for _ in range(N_SAMPLES):
        q = pin.randomConfiguration(reference, -np.ones(reference.nq), np.ones(reference.nq))
        v, a = rng.standard_normal(reference.nv), rng.standard_normal(reference.nv)
        ma, mb = pin.crba(ours, da, q), pin.crba(reference, db, q)
        scale = max(1.0, float(np.max(np.abs(mb))))
        if not np.allclose(ma, mb, rtol=0, atol=DYNAMICS_RTOL * scale):
            out.append(f"crba differs by {np.max(np.abs(ma - mb)):.3g}")
        ta, tb = pin.rnea(ours, da, q, v, a), pin.rnea(reference, db, q, v, a)
        scale = max(1.0, float(np.max(np.abs(tb))))
        if not np.allclose(ta, tb, rtol=0, atol=DYNAMICS_RTOL * scale):
            out.append(f"rnea differs by {np.max(np.abs(ta - tb)):.3g}")
    return out


def check_against_pinocchio(
    path: Path, root: str, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Assert the built model of ``path`` equals Pinocchio's reader's, with ``root``."""
    joint = ROOT_JOINTS[root]
    reference = (
        pin.buildModelFromUrdf(str(path))
        if joint is None
        else pin.buildModelFromUrdf(str(path), joint())
    )
    # The inertia checks are parse_urdf's (tested in test_urdf.py); some robots'
    # inertias violate the triangle inequality, which Pinocchio's reader takes as
    # given: here the builder is under test, so the reader builds them too.
    monkeypatch.setattr(urdf_module, "_check_inertial", lambda path, link: None)
    urdf = parse_urdf(path)
    ours = build_model(urdf.tree, None if joint is None else joint())
    assert differences(ours, reference, rng) == []


@pytest.mark.parametrize("root", ROOT_JOINTS)
@pytest.mark.parametrize("path", LOCAL_URDFS, ids=lambda p: p.name)
def test_repository_urdf_builds_as_pinocchio_reads_it(path, root, rng, monkeypatch):
    check_against_pinocchio(path, root, rng, monkeypatch)


@pytest.mark.parametrize("root", ROOT_JOINTS)
@pytest.mark.parametrize("name", ERD_URDFS, ids=lambda n: Path(n).stem)
def test_robot_urdf_builds_as_pinocchio_reads_it(name, root, rng, monkeypatch):
    check_against_pinocchio(erd_robots_dir() / name, root, rng, monkeypatch)


#: A tree of every URDF joint kind: continuous about an aligned and a tilted axis,
#: prismatic about -y, planar and floating joints below the root, fixed joints
#: welding links with and without inertia, limits, damping and friction.
EVERY_KIND = """<robot name="every_kind">
  <link name="base"><inertial><origin xyz="0.1 0 0" rpy="0.3 0 0"/><mass value="2"/>
    <inertia ixx="0.1" ixy="0.01" ixz="0" iyy="0.2" iyz="0" izz="0.25"/></inertial></link>
  <link name="wheel"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="tilted"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="weight"><inertial><origin xyz="0 0 0.2"/><mass value="0.5"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="tag"/>
  <link name="slider"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="puck"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial></link>
  <link name="drone"><inertial><mass value="1"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.03"/></inertial></link>
  <joint name="z_wheel" type="continuous"><parent link="base"/><child link="wheel"/>
    <origin xyz="0 0.3 0" rpy="0 0 1.2"/><axis xyz="0 0 1"/>
    <limit effort="7" velocity="8"/><dynamics damping="0.1" friction="0.3"/></joint>
  <joint name="a_tilted" type="continuous"><parent link="base"/><child link="tilted"/>
    <origin xyz="0.2 0 0" rpy="0.1 0.2 0.3"/><axis xyz="0 0.6 0.8"/></joint>
  <joint name="weld" type="fixed"><parent link="tilted"/><child link="weight"/>
    <origin xyz="0 0 0.5" rpy="0 1 0"/></joint>
  <joint name="tag_joint" type="fixed"><parent link="weight"/><child link="tag"/>
    <origin xyz="0.1 0 0"/></joint>
  <joint name="slide" type="prismatic"><parent link="tag"/><child link="slider"/>
    <axis xyz="0 -1 0"/><limit lower="-0.5" upper="0.25" effort="3" velocity="4"/>
    <dynamics damping="0.5"/></joint>
  <joint name="glide" type="planar"><parent link="slider"/><child link="puck"/>
    <origin xyz="0 0 0.1" rpy="0.5 0 0"/><axis xyz="0 0 1"/></joint>
  <joint name="fly" type="floating"><parent link="wheel"/><child link="drone"/>
    <origin xyz="1 2 3"/></joint>
</robot>
"""


@pytest.mark.parametrize("root", ROOT_JOINTS)
def test_every_joint_kind_builds_as_pinocchio_reads_it(tmp_path, root, rng, monkeypatch):
    path = tmp_path / "every_kind.urdf"
    path.write_text(EVERY_KIND)
    check_against_pinocchio(path, root, rng, monkeypatch)
    model = build_model(parse_urdf(path).tree)
    kinds = {model.names[j]: model.joints[j].shortname() for j in range(1, model.njoints)}
    assert kinds == {
        "a_tilted": "JointModelRevoluteUnboundedUnaligned",
        "slide": "JointModelPrismaticUnaligned",
        "glide": "JointModelPlanar",
        "z_wheel": "JointModelRUBZ",
        "fly": "JointModelFreeFlyer",
    }


TREE = """<robot name="t">
  <link name="a"/><link name="b"/><link name="c"/>
  <joint name="ab" type="revolute"><parent link="a"/><child link="b"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <joint name="bc" type="revolute"><parent link="b"/><child link="c"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>
"""


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            '<link name="c"/>',
            '<link name="c"/><link name="d"/>',
            "the links and joints make no tree: 2 root links (a, d); valid: one root link",
        ),
        (
            '<parent link="b"/><child link="c"/>',
            '<parent link="c"/><child link="b"/>',
            "<joint name='bc'>: link 'b' is already the child of joint 'ab'; a link has one "
            "parent joint",
        ),
        (
            '<parent link="a"/>',
            '<parent link="nosuch"/>',
            "<joint name='ab'>: <parent link='nosuch'> names no <link> of this file; "
            "links: a, b, c",
        ),
        ('<child link="c"/>', "", "<joint name='bc'>: missing <child link=...>"),
        (
            '<parent link="b"/><child link="c"/>',
            '<parent link="c"/><child link="c"/>',
            "<joint name='bc'>: parent and child are the same link 'c'",
        ),
        (
            'type="revolute"><parent link="a"/>',
            'type="ball"><parent link="a"/>',
            "<joint name='ab'>: unknown joint type 'ball'; valid: revolute, continuous, "
            "prismatic, planar, floating, fixed",
        ),
        (
            '<child link="b"/>\n    <limit lower="-1" upper="1" effort="1" velocity="1"/>',
            '<child link="b"/>',
            "<joint name='ab'>: a revolute joint needs a <limit lower upper effort velocity>",
        ),
        (
            '<child link="b"/>\n    <limit lower="-1" upper="1" effort="1" velocity="1"/>',
            '<child link="b"/>\n    <limit lower="-1" upper="1" effort="1"/>',
            "<joint name='ab'> <limit>: missing velocity=",
        ),
    ],
)
def test_what_is_not_a_tree_is_refused(tmp_path, old, new, message):
    assert old in TREE
    path = tmp_path / "t.urdf"
    path.write_text(TREE.replace(old, new))
    with pytest.raises(ModelFileError, match=re.escape(str(path)) + ".*" + re.escape(message)):
        parse_urdf(path)


def test_a_cycle_of_joints_is_refused(tmp_path):
    path = tmp_path / "cycle.urdf"
    path.write_text(
        TREE.replace(
            "</robot>",
            '<link name="x"/><link name="y"/>'
            '<joint name="xy" type="fixed"><parent link="x"/><child link="y"/></joint>'
            '<joint name="yx" type="fixed"><parent link="y"/><child link="x"/></joint></robot>',
        )
    )
    message = (
        f"{path}: the links and joints make no tree: links x, y are on a cycle of joints, "
        "not below the root link 'a'"
    )
    with pytest.raises(ModelFileError, match=re.escape(message)):
        parse_urdf(path)


def test_bodies_in_breadth_first_order_build_the_same_model(rng):
    """Pinocchio numbers a subtree's joints in a row: bodies listed breadth first (as a
    reader walking a graph may list them) must build the depth-first model, not one
    whose mass matrix is wrong without an error."""
    from dataclasses import replace

    description = parse_urdf(ROOT / "models" / "agile_eye.urdf").tree
    depth = {b.name: k for k, b in enumerate(description.bodies)}
    level: dict[str, int] = {}
    for body in description.bodies:
        level[body.name] = level.get(body.parent, -1) + 1
    breadth = tuple(sorted(description.bodies, key=lambda b: (level[b.name], depth[b.name])))
    assert [b.name for b in breadth] != [b.name for b in description.bodies]
    model = build_model(description)
    assert differences(build_model(replace(description, bodies=breadth)), model, rng) == []
