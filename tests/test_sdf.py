"""SDF models: the frames, the spanning tree and its loops, safe parsing, and Cassie.

References, none computed by the code under test:

* frames worked out by hand from the numbers of ``tests/data/fourbar.sdf``
  (its header states the 4-bar's pivots);
* pinocchio.constraintDynamics on the same tree and loops (``validate`` on the
  4-bar without its gearbox); on Cassie, Pinocchio's mass matrix, bias forces and
  loop constraints with the gearboxes' couplings eliminated by hand;
* SDFormat's gearbox (theta_child = -gearbox_ratio theta_parent) and a geared
  pendulum's reduced equation, written by hand;
* the ``standing`` configuration of example-robot-data's cassie_v2.srdf,
  written for Pinocchio's own SDF reader: our loops close on it before assembly;
* Cassie's stance linearized by central differences (scripts/cassie_stand.py): a
  constant torque is an equilibrium whose modes grow as exp(rate t), so a 2 s run
  from it moves the pelvis by at most its round-off seed times exp(rate 2 s);
* the joint springs of ``tests/data/spring_legs.sdf`` (written here from its numbers)
  and the principle of virtual work: the motor torques that hold a closed chain
  at rest are the gradient of its potential energy (Pinocchio's gravity term plus
  the springs') along the motion, by central differences over motor angles.
"""

from __future__ import annotations

import json
import logging
import math
import re
import subprocess
import sys
from importlib import metadata
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest
import scipy.linalg
from conftest import DATA_DIR, MODELS, ROOT
from lxml import etree

import closedchain as cc
from closedchain import robots
from closedchain.cli import main
from closedchain.constraints import build_pinocchio_constraints
from closedchain.sdf import read_sdf

FOURBAR = DATA_DIR / "fourbar.sdf"
SPRING_LEGS = DATA_DIR / "spring_legs.sdf"

#: forward_dynamics with the springs against a KKT solve of Pinocchio's terms, relative
#: to max |a| (round-off of two dense solves).
TOL_SPRING_ACCEL = 1e-9
#: The heel springs of spring_legs.sdf as its <dynamics> write them: joint ->
#: (spring_stiffness [N m/rad], spring_reference [rad]).
SPRING_LEGS_SPRINGS = {
    "left-heel-spring-joint": (400.0, 0.0),
    "right-heel-spring-joint": (400.0, 0.0),
}

#: Placements computed by hand agree to this [m or rad] (round-off of rpy <-> matrix).
TOL_FRAME = 1e-12
#: Loops closed at the reference configuration [m or -].
TOL_CLOSED = 1e-12
#: cassie_v2.srdf's "standing" values close our loops to this before assembly (they
#: are printed with 8 digits) [m or -].
TOL_SRDF_CLOSURE = 1e-7
#: Accelerations agree with pinocchio.constraintDynamics to this, relative to max |a|
#: (Cassie's J has condition ~1e6 at its reference: absolute round-off is ~1e-9 there).
TOL_A_REL = 1e-9
#: The mimic reference's reduced mass matrix agrees with G^T M G to this, relative to its
#: largest entry (round-off of two products).
TOL_REDUCED_M = 1e-12
#: Generalized constraint forces agree to this (absolute below 1, relative above).
TOL_FORCE = 1e-8
#: Size [rad or m] of the random steps along the motion from Cassie's reference.
STEP = 0.05
#: Largest |a| [rad/s^2, m/s^2] the holding torque leaves at Cassie's standing reference:
#: round-off through the rotors' coupling rows (ratios to 0.02; measured 7.4e-10).
TOL_HOLD = 1e-6
#: Largest multiplier [N or N m] of Cassie's hold: the spare motor torques balance the
#: stance's weak direction (sigma_min(J) = 1.8e-5); measured 5.1e3. The minimum-norm
#: torques left that load to the welds, which squeezed the feet with 1.5e6 N.
LAM_HOLD_MAX = 1e4
#: Largest growth rate [1/s] of Cassie's stance under constant gravity_torque: the
#: pelvis tipping over its hip-pitch axes, an inverted pendulum (the pelvis alone:
#: sqrt(m g d / I) = sqrt(10.3 kg 9.81 m/s^2 0.155 m / 0.30 kg m^2) = 7 /s; measured
#: 9.7 /s with the legs). Not 914 /s: that mode came from the knee-spring toggle and
#: from holding torques that squeezed the legs with 1e6 N (docs/guide/robots-and-
#: moving-bases.md).
STAND_RATE_MAX = 12.0
#: Start error [m or rad] of Cassie's 2 s stand, beside the seed of the hold's
#: acceleration at rest a0 (the test: a0 / (2 rate^2); measured 5.5e-4 rad after 2 s at
#: 9.7 /s with a0 = 7.4e-10).
STAND_SEED = 1e-13
#: Margin over the growth of the stand's seed (another CPU's round-off of a0).
STAND_MARGIN = 10.0
#: How long Cassie stands [s].
STAND_T = 2.0
#: Step h [rad] of the central differences of the potential energy over the motor angles.
FD_STEP = 1e-4
#: Holding torques agree with the potential energy's gradient to this, relative to
#: max |tau| (~1e3 N m: the heel springs turn fast with the hips): the fourth-order
#: difference's truncation (h^4 |V'(5)| / 30, measured ~2e-11 relative) and the
#: assembly's closure error (phi <= 1e-12, times |grad V| over h).
TOL_VIRTUAL_WORK = 1e-7
#: Largest pelvis displacement [m] and closure residual over 2 s of standing: the
#: stance has one mode growing as exp(4.3 t) under constant torques (the springs
#: hold the others), so a round-off of 1e-16 grows to ~1e-12.
TOL_STAND_DRIFT = 1e-9
#: Relative singular-value cut-off of the rows of Cassie's reference with its couplings
#: eliminated (a revolute loop's 6 point rows have rank 5: one singular value ~1e-16).
REFERENCE_RCOND = 1e-10


def _se3(xyz, rpy) -> pin.SE3:
    return pin.SE3(pin.rpy.rpyToMatrix(np.array(rpy, dtype=float)), np.array(xyz, dtype=float))


def _close(A: pin.SE3, B: pin.SE3) -> bool:
    return float(np.max(np.abs(A.homogeneous - B.homogeneous))) < TOL_FRAME


def _frame_loops(mech):
    """The loops of a mechanism that close frames (not the gearboxes' couplings)."""
    return [lp for lp in mech.description.loops if lp.type != "coupling"]


#: fourbar.sdf's gearbox joint, which ties its motor rotor to the crank.
FOURBAR_GEARBOX = re.compile(r'\n\s*<joint name="crank_gear".*?</joint>', re.S)


@pytest.fixture(scope="module")
def fourbar():
    return cc.load(FOURBAR)


def test_fourbar_tree_cuts_the_joint_whose_child_has_two_parents():
    _, tree = read_sdf(FOURBAR)
    assert tree.root == "ground"
    assert set(tree.tree_joints) == {"crank_joint", "coupler_joint", "rocker_joint", "motor_joint"}
    assert tree.cut_joints == ("coupler_rocker",)
    assert tree.reversed_joints == ()
    assert tree.gearboxes == ("crank_gear",)


def test_fourbar_loop_frames_equal_the_hand_computed_ones(fourbar):
    (loop,) = _frame_loops(fourbar)
    assert (loop.name, loop.type, loop.predecessor, loop.successor) == (
        "coupler_rocker",
        "revolute",
        "coupler",
        "rocker",
    )
    # Coupler frame: at B = (0, 0.1, 0), turned by atan2(0.1, 0.3); C = (0.3, 0.2, 0) lies
    # |BC| = sqrt(0.1) along its x. The joint frame: the rocker's (pi/2) turned by 0.7.
    yaw_coupler = math.atan2(0.1, 0.3)
    expected_p = _se3([math.sqrt(0.1), 0, 0], [0, 0, math.pi / 2 + 0.7 - yaw_coupler])
    assert _close(loop.predecessor_origin, expected_p)
    assert _close(loop.successor_origin, _se3([0.2, 0, 0], [0, 0, 0.7]))
    assert np.linalg.norm(loop.axis - [0, 0, 1]) < TOL_FRAME


def test_fourbar_bodies_sit_where_the_sdf_puts_them(fourbar):
    model, data = fourbar.model, fourbar.data
    pin.forwardKinematics(model, data, pin.neutral(model))
    pin.updateFramePlacements(model, data)
    coupler = data.oMf[model.getFrameId("coupler", pin.FrameType.BODY)]
    assert _close(coupler, _se3([0, 0.1, 0], [0, 0, math.atan2(0.1, 0.3)]))
    # Centre of mass of the coupler: its <inertial><pose> is sqrt(0.1)/2 along its x.
    joint = model.getJointId("coupler_joint")
    com = data.oMi[joint].act(model.inertias[joint].lever)
    assert np.linalg.norm(com - [0.15, 0.15, 0]) < TOL_FRAME
    assert abs(model.inertias[joint].mass - 0.3) < TOL_FRAME
    # Its principal axes are turned 0.3 rad about the coupler's y (the <inertial><pose>).
    R = pin.rpy.rpyToMatrix(0.0, 0.3, 0.0)
    expected = R @ np.diag([1e-4, 3e-3, 3e-3]) @ R.T
    assert np.max(np.abs(model.inertias[joint].inertia - expected)) < TOL_FRAME
    assert np.max(np.abs(cc.compute_phi(fourbar, fourbar.q_ref))) < TOL_CLOSED


def test_fourbar_gearbox_ties_the_rotor_to_the_crank(fourbar):
    # The crank's one degree of freedom: the gearbox ties the motor rotor to it, with
    # SDFormat's theta_child = -gearbox_ratio theta_parent (both joints hang from the
    # reference body with the gearbox's axis: q_crank = -0.1 q_motor).
    assert (fourbar.nv, fourbar.nc, fourbar.mobility) == (4, 3, 1)
    (gear,) = [lp for lp in fourbar.description.loops if lp.type == "coupling"]
    assert (gear.name, gear.joint, gear.mimics, gear.multiplier, gear.offset) == (
        "crank_gear",
        "crank_joint",
        "motor_joint",
        -0.1,
        0.0,
    )


def _fourbar_without_gearbox(tmp_path, text: str | None = None):
    text = FOURBAR_GEARBOX.sub("", FOURBAR.read_text() if text is None else text)
    assert "gearbox" not in text.split("-->")[1]
    return _write(tmp_path, text, "no_gear.sdf")


def test_fourbar_validates_against_pinocchio(tmp_path):
    # Pinocchio has no coupling constraint: the 4-bar without its gearbox.
    mech = cc.load(_fourbar_without_gearbox(tmp_path))
    report = cc.validate(mech, n_samples=20)
    assert report.passed, report


def test_cut_joints_chooses_the_cut(tmp_path):
    mech = cc.load(_fourbar_without_gearbox(tmp_path), cut_joints=["rocker_joint"])
    (loop,) = mech.description.loops
    assert (loop.name, loop.predecessor, loop.successor) == ("rocker_joint", "ground", "rocker")
    # The rocker pivot D = (0.3, 0, 0) seen from the ground, with the rocker's turn.
    assert _close(loop.predecessor_origin, _se3([0.3, 0, 0], [0, 0, math.pi / 2]))
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) < TOL_CLOSED
    assert cc.validate(mech, n_samples=10).passed
    with pytest.raises(cc.ModelFileError, match=r"cut_joints names 'nope', which is not a joint"):
        cc.load(FOURBAR, cut_joints=["nope"])


def test_cut_joints_is_refused_for_a_urdf():
    with pytest.raises(cc.ModelFileError, match=r"cut_joints=\['crank_joint'\] is for SDF models"):
        cc.load(MODELS / "fourbar.urdf", cut_joints=["crank_joint"])


def _body(mech, name: str):
    """The body named ``name`` of a mechanism read into a description."""
    (body,) = [b for b in mech.description.tree.bodies if b.name == name]
    return body


def test_visuals_keep_their_geometry_colour_pose_and_mesh_file(fourbar, tmp_path):
    # The crank's <visual>: a cylinder 0.05 m along its x, turned pi/2 about y (its
    # <pose>, in the link frame), coloured by <diffuse>.
    (visual,) = _body(fourbar, "crank").visuals
    assert (visual.kind, visual.dims, visual.rgba) == ("cylinder", (0.01, 0.1), (0.8, 0.2, 0.2, 1))
    assert _close(visual.placement, _se3([0.05, 0, 0], [0, math.pi / 2, 0]))
    # model://name/sub is sub, looked up beside the SDF and in its parent directories.
    text = _edit(
        "<cylinder><radius>0.01</radius><length>0.1</length></cylinder>",
        "<mesh><uri>model://fourbar/meshes/crank.stl</uri><scale>2 2 2</scale></mesh>",
    )
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "crank.stl").write_text("solid crank\nendsolid crank\n")
    folder = tmp_path / "fourbar" / "robots"
    folder.mkdir(parents=True)
    urdf, _ = read_sdf(_write(folder, text))
    (body,) = [b for b in urdf.tree.bodies if b.name == "crank"]
    (mesh,) = body.visuals
    assert (mesh.kind, mesh.dims, mesh.mesh_file) == (
        "mesh",
        (2.0, 2.0, 2.0),
        tmp_path / "meshes" / "crank.stl",
    )


def _write(tmp_path, text: str, name: str = "m.sdf"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _edit(old: str, new: str) -> str:
    text = FOURBAR.read_text()
    assert old in text
    return text.replace(old, new)


@pytest.mark.parametrize(
    ("prolog", "match"),
    [
        ('<!DOCTYPE sdf [<!ENTITY a "b">]>\n', r"DOCTYPE/DTD is not allowed in the SDF file"),
        ('<!DOCTYPE sdf [<!ENTITY x SYSTEM "file:///etc/passwd">]>\n', r"DOCTYPE/DTD"),
    ],
)
def test_unsafe_sdf_is_refused(tmp_path, prolog, match):
    text = FOURBAR.read_text().replace(
        '<?xml version="1.0"?>\n', '<?xml version="1.0"?>\n' + prolog
    )
    with pytest.raises(cc.ModelFileError, match=match):
        cc.load(_write(tmp_path, text))


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        ('version="1.6"', 'version="1.4"', r"<sdf version='1.4'> is not read; valid: 1.5, 1.6"),
        ('type="gearbox"', 'type="screw"', r"joint type 'screw' is not read; valid: revolute"),
        (
            "<parent>crank</parent><child>coupler</child>",
            "<parent>crank</parent><child>nowhere</child>",
            r"<child>nowhere</child> is not a link; valid: ground, crank",
        ),
        (
            "<pose>0.2 0 0 0 0 0.7</pose>",
            "<pose>0.2 0 0 0 0 nan</pose>",
            r"line \d+: <pose>: '0.2 0 0 0 0 nan' must be 6 finite numbers",
        ),
        (
            "<pose>0.2 0 0 0 0 0.7</pose>",
            '<pose relative_to="elsewhere">0.2 0 0 0 0 0.7</pose>',
            r"unknown frame 'elsewhere'; valid: __model__, ground",
        ),
        (
            '<joint name="coupler_rocker" type="revolute">',
            '<joint name="coupler_rocker" type="universal">',
            r"a universal joint needs <axis2>",
        ),
        (
            '<joint name="motor_joint" type="revolute">',
            '<joint name="motor_joint" type="ball">',
            r"'crank_gear'>: joint 'motor_joint' between 'motor' and the "
            r"gearbox_reference_body is ball; valid: a revolute tree joint",
        ),
        (
            '<joint name="crank_joint" type="revolute">\n      <parent>ground</parent>'
            "<child>crank</child>\n      <axis><xyz>0 0 1</xyz></axis>",
            '<joint name="crank_joint" type="universal">\n      <parent>ground</parent>'
            "<child>crank</child>\n      <axis><xyz>0 0 1</xyz></axis>"
            "<axis2><xyz>0 0 -1</xyz></axis2>",
            r"'crank_joint'>: <axis> and <axis2> are parallel",
        ),
        (
            '<xyz>0 0 1</xyz></axis>\n    </joint>\n    <joint name="coupler_joint"',
            '<xyz>0 0 0</xyz></axis>\n    </joint>\n    <joint name="coupler_joint"',
            r"<xyz> in <axis> is zero",
        ),
    ],
)
def test_invalid_sdf_is_refused_naming_the_element(tmp_path, old, new, match):
    with pytest.raises(cc.ModelFileError, match=match):
        cc.load(_write(tmp_path, _edit(old, new)))


def test_a_ball_joint_is_cut_first_into_a_spherical_loop(tmp_path):
    # A ball joint anywhere on the cycle is cut, whichever link has two parents.
    text = _edit(
        '<joint name="coupler_joint" type="revolute">',
        '<joint name="coupler_joint" type="ball">',
    )
    mech = cc.load(_write(tmp_path, text))
    (loop,) = _frame_loops(mech)
    assert (loop.name, loop.type, loop.predecessor, loop.successor) == (
        "coupler_joint",
        "spherical",
        "crank",
        "coupler",
    )
    assert "coupler_rocker" in mech.joint_names
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) < TOL_CLOSED


def test_a_reversed_joint_keeps_the_sign_of_its_sdf_coordinate(tmp_path):
    # With a ball crank joint cut, the crank hangs from the coupler: coupler_joint is
    # reversed, yet +q still turns its SDF child (coupler) by +q about z from its parent.
    text = _edit(
        '<joint name="crank_joint" type="revolute">', '<joint name="crank_joint" type="ball">'
    )
    path = _fourbar_without_gearbox(tmp_path, text)  # the gearbox needs crank_joint
    _, tree = read_sdf(path)
    assert tree.cut_joints == ("crank_joint",)
    assert "coupler_joint" in tree.reversed_joints
    mech = cc.load(path)
    model, data = mech.model, mech.data

    def relative_yaw(q) -> float:
        pin.framesForwardKinematics(model, data, q)
        crank, coupler = (
            data.oMf[model.getFrameId(name, pin.FrameType.BODY)] for name in ("crank", "coupler")
        )
        R = crank.rotation.T @ coupler.rotation
        return math.atan2(R[1, 0], R[0, 0])

    q = pin.neutral(model)
    # The links' frames are their SDF frames: at q = 0, the yaws of the file's poses.
    at_zero = math.atan2(0.1, 0.3) - math.pi / 2
    assert abs(math.remainder(relative_yaw(q) - at_zero, 2 * math.pi)) < TOL_FRAME
    q[model.joints[model.getJointId("coupler_joint")].idx_q] = 0.1
    assert abs(math.remainder(relative_yaw(q) - at_zero - 0.1, 2 * math.pi)) < TOL_FRAME


def test_a_universal_joint_is_one_pinocchio_universal_joint(tmp_path):
    text = _edit(
        '<joint name="coupler_joint" type="revolute">',
        '<joint name="coupler_joint" type="universal">',
    ).replace(
        "<use_parent_model_frame>1</use_parent_model_frame></axis>",
        "<use_parent_model_frame>1</use_parent_model_frame></axis><axis2><xyz>1 0 0</xyz></axis2>",
    )
    path = _fourbar_without_gearbox(tmp_path, text)
    mech = cc.load(path)
    model, data = mech.model, mech.data
    joint = model.joints[model.getJointId("coupler_joint")]
    assert (joint.shortname(), joint.nq, joint.nv) == ("JointModelUniversal", 2, 2)
    assert [lp.name for lp in mech.description.loops] == ["coupler_rocker"]
    # At the reference both angles are 0 (the file's pose closes the loop): the first axis
    # is the model's z (use_parent_model_frame), the second the coupler's x: B -> C.
    assert np.max(np.abs(mech.q_ref[joint.idx_q : joint.idx_q + 2])) < TOL_CLOSED
    pin.computeJointJacobians(model, data, mech.q_ref)
    frame = pin.LOCAL_WORLD_ALIGNED
    J = pin.getJointJacobian(model, data, model.getJointId("coupler_joint"), frame)
    axes = J[3:, joint.idx_v : joint.idx_v + 2].T
    assert np.linalg.norm(axes[0] - [0.0, 0.0, 1.0]) < TOL_FRAME
    assert np.linalg.norm(axes[1] - np.array([3.0, 1.0, 0.0]) / math.sqrt(10.0)) < TOL_FRAME
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) < TOL_CLOSED
    assert cc.validate(mech, n_samples=10).passed
    with pytest.raises(
        cc.ModelFileError, match=r"'coupler_joint'>: a universal joint cannot be cut"
    ):
        cc.load(path, cut_joints=["coupler_joint"])


#: A bob on a ball joint whose frame sits off the bob's (a <pose>). Link poses [m, rad].
BALL_SDF = """<?xml version="1.0"?>
<sdf version="1.6">
  <model name="ball_pendulum">
    <link name="ground"/>
    <link name="bob"><pose>0.2 0.1 -0.5 0.3 0 0.1</pose>
      <inertial><pose>0 0 -0.1 0 0 0</pose><mass>2</mass>
        <inertia><ixx>0.01</ixx><iyy>0.02</iyy><izz>0.03</izz></inertia></inertial>
    </link>
    <joint name="{name}" type="ball">
      <pose>0.05 0 0.4 0 0.2 0</pose>
      <parent>{parent}</parent><child>{child}</child>
    </joint>
  </model>
</sdf>
"""


@pytest.mark.parametrize("reverse", [False, True])
def test_a_ball_joint_in_the_tree_turns_its_body_about_its_anchor(tmp_path, reverse):
    # Written from the bob, the tree reaches it from 'ground' through the joint reversed.
    parent, child = ("bob", "ground") if reverse else ("ground", "bob")
    text = BALL_SDF.format(name="socket", parent=parent, child=child)
    if reverse:  # the joint's pose is in its child's frame: the same point, from 'ground'
        text = text.replace("<pose>0.05 0 0.4 0 0.2 0</pose>", "<pose>0.25 0.1 -0.1 0 0 0</pose>")
    path = _write(tmp_path, text)
    _, tree = read_sdf(path)
    assert tree.reversed_joints == (("socket",) if reverse else ())
    mech = cc.load(path)
    model, data = mech.model, mech.data
    joint = model.joints[model.getJointId("socket")]
    assert (joint.shortname(), mech.nv) == ("JointModelSpherical", 3)
    # By hand: the anchor A in the world, from the file's numbers (the joint's <pose> is
    # in its SDF child's frame: the bob's, or reversed the ground's, the world).
    bob0 = _se3([0.2, 0.1, -0.5], [0.3, 0, 0.1])
    if reverse:
        anchor = np.array([0.25, 0.1, -0.1])
    else:
        anchor = (bob0 * _se3([0.05, 0, 0.4], [0, 0.2, 0])).translation
    # The quaternion turns the bob by R about A, R in the bob's axes: the bob's frame is
    # bob0 T(p) R T(-p), p = A in the bob's frame; A stays where it is.
    R = pin.rpy.rpyToMatrix(0.4, -0.3, 0.7)
    quat = pin.Quaternion(R)
    q = pin.neutral(model)
    q[joint.idx_q : joint.idx_q + 4] = [quat.x, quat.y, quat.z, quat.w]
    pin.framesForwardKinematics(model, data, q)
    bob = data.oMf[model.getFrameId("bob", pin.FrameType.BODY)]
    p_bob = bob0.inverse().act(anchor)
    expected = bob0 * _se3(p_bob, [0, 0, 0]) * pin.SE3(R, np.zeros(3)) * _se3(-p_bob, [0, 0, 0])
    assert _close(bob, expected)
    assert np.linalg.norm(bob.act(p_bob) - anchor) < TOL_FRAME
    # At the neutral quaternion the bob sits at its SDF pose.
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    assert _close(data.oMf[model.getFrameId("bob", pin.FrameType.BODY)], bob0)


# -- Cassie -----------------------------------------------------------------------


def _have_erd() -> bool:
    try:
        metadata.distribution(robots.ERD_DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return False
    return True


needs_erd = pytest.mark.skipif(
    not _have_erd(), reason=f"example-robot-data is not installed ({robots.INSTALL_HINT})"
)


@pytest.fixture(scope="module")
def cassie():
    return cc.load("erd:cassie")


@needs_erd
def test_cassie_tree_and_loops():
    path, entry = robots.resolve_model("erd:cassie")
    _, tree = read_sdf(path, fixed_joints=entry.fixed_joints)
    assert tree.root == "pelvis"
    assert set(tree.cut_joints) == {
        f"{side}-{name}"
        for side in ("left", "right")
        for name in ("pitch-rod-joint", "knee-spring-joint", "plantar-foot-joint")
    }
    assert set(tree.reversed_joints) == {
        "left-achilles-spring-joint",
        "right-achilles-spring-joint",
    }
    assert len(tree.gearboxes) == 10
    assert tree.held_joints == ("left-knee-shin-joint", "right-knee-shin-joint")


@needs_erd
def test_cassie_mobility_and_closure(cassie):
    # 32 tree joints (the knee-shin joints held); 22 independent rows of 32 (per leg:
    # achilles 3, plantar 2, knee spring 1: its slider is held, and 5 gearboxes);
    # mobility 10: per leg the 5 motors, each rotor tied to its output.
    assert (cassie.nv, cassie.declared.nc, cassie.nc, cassie.mobility) == (32, 32, 22, 10)
    assert len(cassie.constraints.couplings) == 10
    assert np.max(np.abs(cc.compute_phi(cassie, cassie.q_ref))) < TOL_CLOSED
    assert cassie.within_limits(cassie.q_ref)


@needs_erd
def test_cassie_srdf_standing_closes_our_loops_before_assembly():
    # The file as written (erd:cassie holds the knee-shin joints at 0, where the SRDF
    # has -7.9e-6 rad: that moves the achilles loops by 1.3e-6 m before assembly).
    raw = cc.load(robots.resolve_model("erd:cassie")[0])
    probe = raw.model.copy()
    srdf = robots.erd_robots_dir() / "cassie_description/srdf/cassie_v2.srdf"
    pin.loadReferenceConfigurations(probe, str(srdf), False)
    q = np.array(probe.referenceConfigurations["standing"])
    # The SRDF leaves the motor rotors at 0: turn each by its output's angle / ratio.
    for gear in raw.description.loops:
        if gear.type == "coupling":
            out = raw.model.joints[raw.model.getJointId(gear.joint)].idx_q
            rotor = raw.model.joints[raw.model.getJointId(gear.mimics)].idx_q
            q[rotor] = (q[out] - gear.offset) / gear.multiplier
    assert np.max(np.abs(cc.compute_phi(raw, q))) < TOL_SRDF_CLOSURE


def _coupled_reference(mech, q, v, tau) -> np.ndarray:
    r"""Accelerations from Pinocchio's terms with the couplings eliminated by hand.

    Each coupling q_j = m q_i + c is linear, so v = G v_r and a = G a_r, with G the
    identity without column j and with m at (j, i). The frame loops are Pinocchio's
    rigid constraint models (J_c and its drift b_c from Pinocchio itself); then
    :math:`J_c G a_r = b_c` and :math:`G^\top M G a_r + G^\top h = G^\top \tau + (J_c G)^\top f`,
    solved in the null space of J_c G (its redundant rows: a revolute loop is 6 point rows).
    """
    model = mech.model
    couplings = [lp for lp in mech.description.loops if lp.type == "coupling"]
    driven = [model.joints[model.getJointId(lp.joint)].idx_v for lp in couplings]
    G = np.eye(model.nv)
    for lp, j in zip(couplings, driven, strict=True):
        G[j, model.joints[model.getJointId(lp.mimics)].idx_v] = lp.multiplier
    G = np.delete(G, driven, axis=1)
    frames = SimpleNamespace(
        loops=[lp for lp in mech.constraints.loops if lp.type != "coupling"],
        frame_ids=[
            ids
            for lp, ids in zip(mech.constraints.loops, mech.constraints.frame_ids, strict=True)
            if lp.type != "coupling"
        ],
    )
    cms, _ = build_pinocchio_constraints(model, frames)
    cds = pin.StdVec_RigidConstraintData()
    for cm in cms:
        cds.append(cm.createData())
    data = model.createData()
    pin.initConstraintDynamics(model, data, cms, cds)
    pin.constraintDynamics(model, data, q, v, tau, cms, cds)  # fills J_c and b_c
    Jc = pin.getConstraintsJacobian(model, data, cms, cds)
    b = np.array(data.primal_rhs_contact[: Jc.shape[0]])
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    h = pin.rnea(model, data, q, v, np.zeros(model.nv))
    A = Jc @ G
    a_p = np.linalg.lstsq(A, b, rcond=REFERENCE_RCOND)[0]
    N = scipy.linalg.null_space(A, rcond=REFERENCE_RCOND)
    Mr = G.T @ M @ G
    z = np.linalg.solve(N.T @ Mr @ N, N.T @ (G.T @ (tau - h) - Mr @ a_p))
    return G @ (a_p + N @ z)


@needs_erd
def test_cassie_agrees_with_pinocchio_terms_with_its_gearboxes_eliminated(cassie):
    # States along the motion from q_ref (its tangent space), assembled; the rotors'
    # reflected inertia (G^T M G) acts on the legs.
    rng = np.random.default_rng(0)
    for _ in range(3):
        dq = cc.project_velocity(cassie, cassie.q_ref, STEP * rng.standard_normal(cassie.nv))
        q = cc.assemble(cassie, pin.integrate(cassie.model, cassie.q_ref, dq))
        v = cc.project_velocity(cassie, q, rng.standard_normal(cassie.nv))
        tau = cassie.gravity_torque_scale() * rng.standard_normal(cassie.nv)
        # Pinocchio has no joint damping or springs: their force (checked against
        # MuJoCo's qfrc_passive in test_passive.py) goes into its tau.
        a_ref = _coupled_reference(cassie, q, v, cassie.passive.added_to(tau, q, v))
        res = cc.forward_dynamics(cassie, q, v, tau, method="kkt")
        da = np.max(np.abs(res.a - a_ref))
        assert da < TOL_A_REL * max(1.0, np.max(np.abs(a_ref))), da


@needs_erd
def test_cassie_validates_against_pinocchio_mimic_joints(cassie):
    """Its gearbox outputs are mimic joints below other mimic joints (each output carries
    the next stage's rotor and output): the reference's reduced mass matrix is G^T M G,
    M from Pinocchio's crba on the whole tree (its crba on the mimic model is 3 % off)."""
    from closedchain.validation import mimic_reference

    reference = mimic_reference(cassie)
    rng = np.random.default_rng(1)
    q = cc.assemble(
        cassie,
        pin.integrate(
            cassie.model,
            cassie.q_ref,
            cc.project_velocity(cassie, cassie.q_ref, STEP * rng.standard_normal(cassie.nv)),
        ),
    )
    M = pin.crba(cassie.model, cassie.model.createData(), q)
    M = np.triu(M) + np.triu(M, 1).T
    _, _, M_r = reference.dynamics(q, np.zeros(cassie.nv), np.zeros(cassie.nv))
    G = reference.G
    assert np.max(np.abs(M_r - G.T @ M @ G)) < TOL_REDUCED_M * np.max(np.abs(M_r))
    report = cc.validate(cassie, n_samples=10)
    assert report.reference == "pinocchio mimic joints"
    assert report.passed, report


@needs_erd
def test_cassie_simulates_from_rest(cassie):
    traj = cc.simulate(cassie, cassie.q_ref, np.zeros(cassie.nv), 0.2)
    assert traj.t[-1] == pytest.approx(0.2)
    assert traj.info.max_constraint_residual < TOL_CLOSED


@needs_erd
def test_cassie_animates_with_its_meshes(cassie, tmp_path, capsys):
    """The SDF's model:// meshes are example-robot-data's, embedded within the budget."""
    bodies = cassie.description.tree.bodies
    meshes = [v.mesh_file for b in bodies for v in b.visuals if v.kind == "mesh"]
    folder = robots.erd_robots_dir() / "cassie_description" / "meshes"
    assert meshes and all(m.is_file() and m.parent == folder for m in meshes)
    out = tmp_path / "cassie.html"
    assert main(["animate", "erd:cassie", "--t-final", "0.1", "-o", str(out)]) == 0
    assert f"meshes: {len(meshes)} embedded (" in capsys.readouterr().out
    assert b"model://" not in out.read_bytes()


@pytest.fixture(scope="module")
def cassie_standing():
    return cc.load("erd:cassie", root_joint="free", loops=MODELS / "cassie_standing.urdf")


@needs_erd
def test_cassie_standing_is_held_at_rest_by_the_gravity_torque(cassie_standing):
    mech = cassie_standing
    # Two welded feet add 12 rows: 38 - 34 = 4 (the pelvis on its legs; the rotors are
    # tied to their outputs).
    assert (mech.nv, mech.nc, mech.mobility) == (38, 34, 4)
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) < TOL_CLOSED
    tau = cc.gravity_torque(mech, mech.q_ref)
    rest = np.zeros(mech.nv)
    held = cc.forward_dynamics(mech, mech.q_ref, rest, tau, method="augmented-lagrangian")
    assert np.max(np.abs(held.a)) < TOL_HOLD
    assert np.max(np.abs(held.lam)) < LAM_HOLD_MAX
    falls = cc.forward_dynamics(mech, mech.q_ref, rest, 0 * tau, method="augmented-lagrangian")
    assert np.max(np.abs(falls.a)) > 1.0


@needs_erd
def test_cassie_stands_two_seconds_under_the_gravity_torque():
    """scripts/cassie_stand.py: the stance's modes grow slowly, and 2 s from rest under
    constant gravity_torque (default method and integrator) keep the pelvis within its
    round-off seed times exp(rate 2 s), the loops closed."""
    out = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "cassie_stand.py"), "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    row = json.loads(out.stdout)
    rate = row["rates"][0]
    assert 0.0 < rate < STAND_RATE_MAX, row["rates"]
    assert row["t_final"] == pytest.approx(STAND_T)
    # The hold's acceleration a0 left at rest seeds the fastest mode: x(t) = a0 / rate^2
    # (cosh(rate t) - 1) <= a0 / (2 rate^2) exp(rate t), with STAND_SEED for the start.
    seed = STAND_SEED + row["max_abs_a_at_rest"] / (2.0 * rate**2)
    bound = STAND_MARGIN * seed * math.exp(rate * STAND_T)
    assert max(row["pelvis_m"], row["pelvis_rad"]) < bound, (row, bound)
    assert row["max_constraint_residual"] < TOL_CLOSED


@pytest.fixture(scope="module")
def spring_legs_pinned():
    return cc.load(SPRING_LEGS, loops=DATA_DIR / "spring_legs_pinned.urdf")


def test_sdf_springs_become_joint_springs():
    mech = cc.load(SPRING_LEGS)
    springs = {s.joint: (s.stiffness, s.reference) for s in mech.description.springs}
    assert springs == SPRING_LEGS_SPRINGS
    # The achilles rods hang on reversed joints; the springs' joints are kept as written.
    _, tree = read_sdf(SPRING_LEGS)
    assert set(tree.reversed_joints) == {"left-achilles-heel", "right-achilles-heel"}
    q = mech.q_ref.copy()
    expected = np.zeros(mech.nv)
    for name, (k, q0) in SPRING_LEGS_SPRINGS.items():
        joint = mech.model.joints[mech.model.getJointId(name)]
        q[joint.idx_q] = 0.3
        expected[joint.idx_v] = -k * (0.3 - q0)
    np.testing.assert_array_equal(cc.spring_torque(mech, q), expected)


def test_the_springs_act_in_forward_dynamics_without_tau(spring_legs_pinned, rng):
    """forward_dynamics with tau = 0 against a KKT solve from Pinocchio's crba and rnea
    with the springs of this file's numbers as a generalized force."""
    mech = spring_legs_pinned
    q, v = cc.random_consistent_state(mech, rng)
    springs = np.zeros(mech.nv)
    for name, (k, q0) in SPRING_LEGS_SPRINGS.items():
        joint = mech.model.joints[mech.model.getJointId(name)]
        springs[joint.idx_v] = -k * (q[joint.idx_q] - q0)
    assert np.max(np.abs(springs)) > 1.0
    data = mech.model.createData()
    M = pin.crba(mech.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    rhs = springs - pin.rnea(mech.model, data, q, v, np.zeros(mech.nv))
    res = cc.forward_dynamics(mech, q, v, method="kkt", backend="numpy")
    K = np.block([[M, res.J.T], [res.J, np.zeros((mech.nc, mech.nc))]])
    a_ref = np.linalg.lstsq(K, np.concatenate([rhs, -res.gamma]), rcond=None)[0][: mech.nv]
    assert np.max(np.abs(res.a - a_ref)) <= TOL_SPRING_ACCEL * max(1.0, np.max(np.abs(a_ref)))


def test_a_spring_on_a_cut_joint_is_left_out_with_a_warning(tmp_path, caplog):
    ball = """    <joint name="left-achilles-hip" type="ball">
      <parent>left-thigh</parent>
      <child>left-achilles-rod</child>
      <axis>
        <xyz>0 1 0</xyz>"""
    assert ball in SPRING_LEGS.read_text()
    dynamics = (
        "\n        <dynamics><damping>0</damping><spring_stiffness>5</spring_stiffness></dynamics>"
    )
    text = SPRING_LEGS.read_text().replace(ball, ball + dynamics)
    with caplog.at_level(logging.WARNING, logger="closedchain.sdf"):
        mech = cc.load(_write(tmp_path, text))
    assert "the springs of left-achilles-hip are left out" in caplog.text
    assert {s.joint for s in mech.description.springs} == set(SPRING_LEGS_SPRINGS)


def _potential_energy(mech, q) -> float:
    """Gravity's potential energy (Pinocchio) plus the springs' (this file's numbers) [J]."""
    V = pin.computePotentialEnergy(mech.model, mech.data, q)
    for name, (k, q0) in SPRING_LEGS_SPRINGS.items():
        V += 0.5 * k * (q[mech.model.joints[mech.model.getJointId(name)].idx_q] - q0) ** 2
    return float(V)


@pytest.mark.parametrize("motors", [(0.0, 0.0), (0.05, -0.04)])
def test_gravity_torque_with_springs_is_the_gradient_of_the_potential(spring_legs_pinned, motors):
    mech = spring_legs_pinned
    assert (mech.mobility, mech.actuated_joints) == (2, ("left-hip", "right-hip"))
    q = cc.forward_kinematics(mech, motors).q
    tau = cc.gravity_torque(mech, q)[mech.actuated_idx_v]
    grad = np.zeros(2)
    for i in range(2):
        V = {}
        for step in (-2, -1, 1, 2):
            m = np.array(motors, dtype=float)
            m[i] += step * FD_STEP
            V[step] = _potential_energy(mech, cc.forward_kinematics(mech, m, q_guess=q).q)
        # Fourth-order central difference.
        grad[i] = (8 * (V[1] - V[-1]) - (V[2] - V[-2])) / (12 * FD_STEP)
    assert np.max(np.abs(tau - grad)) < TOL_VIRTUAL_WORK * np.max(np.abs(tau))


def test_the_command_line_applies_the_springs(spring_legs_pinned, tmp_path, capsys):
    """Released at a state where the heel springs pull hard (~1e3 N m on the hips),
    under --torque gravity the legs stay at rest only if the springs act too."""
    q0 = cc.forward_kinematics(spring_legs_pinned, [0.05, -0.04]).q
    out = tmp_path / "run.npz"
    argv = ["simulate", str(SPRING_LEGS), "--loops", str(DATA_DIR / "spring_legs_pinned.urdf")]
    argv += [
        "--q0",
        *(repr(float(x)) for x in q0),
        "--torque",
        "gravity",
        "--t-final",
        "0.2",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    traj = cc.Trajectory.load(out)
    assert np.max(np.abs(traj.q - q0)) < TOL_STAND_DRIFT


def test_spring_legs_stand_2_s_on_welded_feet_under_gravity_torque(tmp_path, monkeypatch):
    """The guide's example (section "Joint springs") runs: 2 s of standing."""
    guide = DATA_DIR.parent.parent / "docs" / "guide" / "robots-and-moving-bases.md"
    text = guide.read_text().split("### Joint springs", 1)[1].split("\n### ", 1)[0]
    (block,) = re.findall(r"^```python\n(.*?)^```$", text, re.M | re.S)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(DATA_DIR)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "guide_example"}
    exec(compile(block, str(guide), "exec"), namespace)
    mech, traj = namespace["legs"], namespace["traj"]
    # 16 coordinates, 13 rows (the welds' out-of-plane rows are redundant): the pelvis on
    # its legs, the motors (hips, knees) and the heel springs share 3 freedoms.
    assert (mech.nv, mech.nc, mech.mobility, len(mech.description.springs)) == (16, 13, 3, 2)
    assert traj.t[-1] == pytest.approx(2.0)
    assert np.max(np.abs(traj.q[:, :3] - mech.q_ref[:3])) < TOL_STAND_DRIFT
    assert traj.info.max_constraint_residual < TOL_STAND_DRIFT


# -- gearboxes, link frames, reversed joints, damping ------------------------------------

#: A rotor and a pendulum arm on one axis, joined by a gearbox (SDFormat: theta_child =
#: -gearbox_ratio theta_parent, both angles from the reference body "ground"). {rotor}
#: is the rotor's joint: written from ground, or from the rotor (reversed in the tree).
GEARBOX_SDF = """<?xml version="1.0"?>
<sdf version="1.6">
  <model name="geared_arm">
    <link name="ground"/>
    <link name="rotor">
      <inertial><mass>0.1</mass>
        <inertia><ixx>1e-5</ixx><iyy>1e-5</iyy><izz>{Jr}</izz></inertia></inertial>
    </link>
    <link name="arm">
      <inertial><pose>{l} 0 0 0 0 0</pose><mass>{m}</mass>
        <inertia><ixx>1e-4</ixx><iyy>1e-3</iyy><izz>{Ic}</izz></inertia></inertial>
    </link>
    {rotor}
    <joint name="arm_joint" type="revolute">
      <parent>ground</parent><child>arm</child>
      <axis><xyz>0 0 1</xyz><dynamics><damping>0.25</damping></dynamics></axis>
    </joint>
    <joint name="gear" type="gearbox">
      <parent>rotor</parent><child>arm</child>
      <gearbox_reference_body>ground</gearbox_reference_body>
      <gearbox_ratio>{r}</gearbox_ratio>
      <axis><xyz>0 0 1</xyz></axis>
      <axis2><xyz>0 0 1</xyz></axis2>
    </joint>
  </model>
</sdf>
"""
#: The rotor's joint as the file may write it: (text, rotor angle about +z per unit q).
ROTOR_JOINTS = {
    "from_ground": (
        '<joint name="rotor_joint" type="revolute"><parent>ground</parent>'
        "<child>rotor</child><axis><xyz>0 0 1</xyz></axis></joint>",
        1.0,
    ),
    "axis_flipped": (
        '<joint name="rotor_joint" type="revolute"><parent>ground</parent>'
        "<child>rotor</child><axis><xyz>0 0 -1</xyz></axis></joint>",
        -1.0,
    ),
    "from_rotor": (
        '<joint name="rotor_joint" type="revolute"><parent>rotor</parent>'
        "<child>ground</child><axis><xyz>0 0 1</xyz></axis></joint>",
        -1.0,
    ),
}
#: The geared arm's numbers: rotor inertia [kg m^2], ratio, arm mass [kg], arm centre of
#: mass [m], arm inertia about its centre [kg m^2].
GEARED_ARM = {"Jr": 2e-5, "r": 0.05, "m": 0.5, "l": 0.2, "Ic": 3e-3}
#: Gravity along -y [m/s^2], in the arm's plane.
GRAVITY_Y = 9.81


@pytest.mark.parametrize("rotor", sorted(ROTOR_JOINTS))
def test_a_gearbox_ties_the_rotor_with_the_sdf_sign_and_reflects_its_inertia(tmp_path, rotor):
    text, turn = ROTOR_JOINTS[rotor]
    path = _write(tmp_path, GEARBOX_SDF.format(rotor=text, **GEARED_ARM))
    mech = cc.load(path, gravity=(0.0, -GRAVITY_Y, 0.0))
    assert (mech.nv, mech.nc, mech.mobility) == (2, 1, 1)
    model, data = mech.model, mech.data
    arm_v = model.joints[model.getJointId("arm_joint")].idx_v
    # At arm angle theta (rotor on the manifold), the rotor turns about +z at
    # -theta_dot / r (SDFormat's theta_2 = -r theta_1): its reflected inertia Jr / r^2.
    theta, theta_dot, tau_arm = 0.4, 0.7, 0.3
    q = cc.assemble(mech, np.where(np.arange(mech.nq) == arm_v, theta, 0.0), fixed=["arm_joint"])
    v = cc.project_velocity(
        mech, q, np.where(np.arange(mech.nv) == arm_v, theta_dot, 0.0), fixed=["arm_joint"]
    )
    pin.forwardKinematics(model, data, q, v)
    pin.updateFramePlacements(model, data)
    rotor_w = pin.getFrameVelocity(
        model, data, model.getFrameId("rotor", pin.FrameType.BODY), pin.ReferenceFrame.WORLD
    ).angular
    r, Jr, m, l, Ic = (GEARED_ARM[k] for k in ("r", "Jr", "m", "l", "Ic"))
    assert abs(rotor_w[2] - (-theta_dot / r)) < TOL_FRAME
    # Reduced model by hand, with the arm joint's <dynamics><damping> D = 0.25 N m s/rad:
    # (Ic + m l^2 + Jr / r^2) theta_ddot = tau - m g l cos(theta) - D theta_dot.
    tau = np.zeros(mech.nv)
    tau[arm_v] = tau_arm
    damping = 0.25
    expected = (tau_arm - m * GRAVITY_Y * l * math.cos(theta) - damping * theta_dot) / (
        Ic + m * l**2 + Jr / r**2
    )
    a = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
    assert abs(a[arm_v] - expected) < TOL_FRAME * max(1.0, abs(expected))
    rotor_v = model.joints[model.getJointId("rotor_joint")].idx_v
    assert abs(turn * a[rotor_v] - (-expected / r)) < TOL_FRAME * max(1.0, abs(expected) / r)
    # The arm joint's <dynamics><damping> [N m s/rad].
    assert [(d.joint, d.damping) for d in mech.description.dampings] == [("arm_joint", damping)]


def test_a_damped_geared_arm_validates_against_pinocchio_mimic_joints(tmp_path):
    """The arm joint's damping is a force Pinocchio does not model: validate gives it to
    the mimic reference as it gives it to pinocchio.constraintDynamics."""
    text = GEARBOX_SDF.format(rotor=ROTOR_JOINTS["from_ground"][0], **GEARED_ARM)
    mech = cc.load(_write(tmp_path, text), gravity=(0.0, -GRAVITY_Y, 0.0))
    assert mech.description.dampings
    report = cc.validate(mech, n_samples=10)
    assert report.reference == "pinocchio mimic joints"
    assert report.passed, report


def test_a_gearbox_without_a_joint_to_its_reference_body_is_refused(tmp_path):
    text = GEARBOX_SDF.format(rotor=ROTOR_JOINTS["from_ground"][0], **GEARED_ARM).replace(
        "<gearbox_reference_body>ground</gearbox_reference_body>",
        "<gearbox_reference_body>arm</gearbox_reference_body>",
    )
    with pytest.raises(cc.ModelFileError, match=r"'gear'>: the gearbox angle of link 'rotor' is "):
        cc.load(_write(tmp_path, text))


#: A chain base - a - b whose joint to 'a' is written from 'a' (reversed in the tree) and
#: placed off both links; 'b' hangs from 'a' on a joint with a pose. Link poses [m, rad].
REVERSED_SDF = """<?xml version="1.0"?>
<sdf version="1.6">
  <model name="reversed_chain">
    <link name="base"><pose>0.1 0 0.5 0 0 0.2</pose></link>
    <link name="a"><pose>0.4 0.1 0.5 0.1 0 0.9</pose></link>
    <link name="b"><pose>0.7 -0.2 0.4 0 0.3 0</pose></link>
    <joint name="a_base" type="{type}">
      <pose>0.05 0.02 0 0 0 0.3</pose>
      <parent>a</parent><child>base</child>
      <axis><xyz>1 0 0</xyz></axis>
      <axis2><xyz>0 1 0</xyz></axis2>
    </joint>
    <joint name="a_b" type="revolute">
      <pose>-0.1 0 0.02 0 0 0.4</pose>
      <parent>a</parent><child>b</child>
      <axis><xyz>0 0 1</xyz></axis>
    </joint>
  </model>
</sdf>
"""


def _sdf_link_poses(path) -> dict[str, pin.SE3]:
    """Each link's <pose> (model frame), read here from the file's plain numbers."""
    poses = {}
    for link in etree.parse(str(path)).getroot().iter("link"):
        x = [float(t) for t in link.findtext("pose").split()]
        poses[link.get("name")] = _se3(x[:3], x[3:])
    return poses


@pytest.mark.parametrize("jtype", ["revolute", "universal"])
def test_every_link_frame_sits_at_its_sdf_pose_across_a_reversed_joint(tmp_path, jtype):
    path = _write(tmp_path, REVERSED_SDF.format(type=jtype))
    _, tree = read_sdf(path)
    assert tree.reversed_joints == ("a_base",)
    mech = cc.load(path)
    model, data = mech.model, mech.data
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    poses = _sdf_link_poses(path)
    # The root link 'base' is Pinocchio's origin: compare placements relative to it.
    base = data.oMf[model.getFrameId("base", pin.FrameType.BODY)]
    for name, pose in poses.items():
        placed = base.inverse() * data.oMf[model.getFrameId(name, pin.FrameType.BODY)]
        assert _close(placed, poses["base"].inverse() * pose), name


@pytest.mark.parametrize("reverse", [False, True])
def test_a_universal_joint_has_its_coordinates_in_sdf_axis_order(tmp_path, reverse):
    # SDFormat: R(parent -> child) = Rot(axis, q_axis) Rot(axis2, q_axis2) in the joint
    # frame (here every link's and the joint's axes are alike at q = 0). Reversed in the
    # tree, the body turns about <axis2> (fixed in its tree parent, the SDF child) first:
    # two revolute joints, a_base::axis2 then a_base, each holding its own axis' angle.
    text = REVERSED_SDF.format(type="universal")
    if not reverse:
        text = text.replace(
            "<parent>a</parent><child>base</child>", "<parent>base</parent><child>a</child>"
        )
        text = text.replace("<pose>0.05 0.02 0 0 0 0.3</pose>\n", "")
        text = text.replace(
            '<link name="a"><pose>0.4 0.1 0.5 0.1 0 0.9</pose>',
            '<link name="a"><pose>0.1 0 0.5 0 0 0.2</pose>',
        )
    text = text.replace("<pose>0.05 0.02 0 0 0 0.3</pose>\n", "")
    text = text.replace(
        '<link name="base"><pose>0.1 0 0.5 0 0 0.2</pose>',
        '<link name="base"><pose>0.4 0.1 0.5 0 0 0.2</pose>',
    )
    text = text.replace(
        '<link name="a"><pose>0.4 0.1 0.5 0.1 0 0.9</pose>',
        '<link name="a"><pose>0.4 0.1 0.5 0 0 0.2</pose>',
    )
    path = _write(tmp_path, text)
    _, tree = read_sdf(path)
    assert ("a_base" in tree.reversed_joints) == reverse
    mech = cc.load(path)
    model, data = mech.model, mech.data
    q_axis, q_axis2 = 0.3, -0.5
    q = pin.neutral(model)
    joint = model.joints[model.getJointId("a_base")]
    if reverse:
        second = model.joints[model.getJointId("a_base::axis2")]
        assert (second.nq, joint.nq) == (1, 1)
        assert second.idx_q < joint.idx_q
        q[joint.idx_q], q[second.idx_q] = q_axis, q_axis2
    else:
        assert joint.shortname() == "JointModelUniversal"
        q[joint.idx_q : joint.idx_q + 2] = (q_axis, q_axis2)
    pin.framesForwardKinematics(model, data, q)
    parent, child = ("a", "base") if reverse else ("base", "a")
    R = (
        data.oMf[model.getFrameId(parent, pin.FrameType.BODY)].rotation.T
        @ data.oMf[model.getFrameId(child, pin.FrameType.BODY)].rotation
    )
    expected = pin.rpy.rpyToMatrix(q_axis, 0.0, 0.0) @ pin.rpy.rpyToMatrix(0.0, q_axis2, 0.0)
    assert np.max(np.abs(R - expected)) < TOL_FRAME
    # The joint's anchor, the SDF child's origin (the joint has no <pose>), stays where the
    # file's poses put it in the SDF parent's frame.
    poses = _sdf_link_poses(path)
    oMp, oMc = (data.oMf[model.getFrameId(n, pin.FrameType.BODY)] for n in (parent, child))
    anchor = (poses[parent].inverse() * poses[child]).translation
    assert np.linalg.norm((oMp.inverse() * oMc).translation - anchor) < TOL_FRAME


def test_a_reversed_universal_joint_keeps_each_axis_limits_and_damping(tmp_path):
    text = REVERSED_SDF.format(type="universal").replace(
        "<axis><xyz>1 0 0</xyz></axis>\n      <axis2><xyz>0 1 0</xyz></axis2>",
        "<axis><xyz>1 0 0</xyz><limit><lower>-0.4</lower><upper>0.7</upper></limit>"
        "<dynamics><damping>0.3</damping></dynamics></axis>\n"
        "      <axis2><xyz>0 1 0</xyz><limit><lower>-1.1</lower><upper>0.2</upper></limit>"
        "<dynamics><damping>0.05</damping></dynamics></axis2>",
    )
    assert "<damping>0.05</damping>" in text
    mech = cc.load(_write(tmp_path, text))
    model = mech.model
    # Values from the file above: <axis> -0.4..0.7, damping 0.3; <axis2> -1.1..0.2, 0.05.
    for name, (lower, upper, damping) in {
        "a_base": (-0.4, 0.7, 0.3),
        "a_base::axis2": (-1.1, 0.2, 0.05),
    }.items():
        jm = model.joints[model.getJointId(name)]
        assert model.lowerPositionLimit[jm.idx_q] == pytest.approx(lower, abs=1e-15)
        assert model.upperPositionLimit[jm.idx_q] == pytest.approx(upper, abs=1e-15)
        assert mech.passive.damping[jm.idx_v] == pytest.approx(damping, abs=1e-15)


@needs_erd
def test_every_cassie_link_frame_sits_at_its_sdf_pose():
    """All 35 links, at the SDF's own pose (every coordinate 0), relative to the pelvis."""
    path, _ = robots.resolve_model("erd:cassie")
    poses = _sdf_link_poses(path)
    assert len(poses) == 35
    mech = cc.load("erd:cassie")
    model, data = mech.model, mech.data
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    pelvis = data.oMf[model.getFrameId("pelvis", pin.FrameType.BODY)]
    for name, pose in poses.items():
        placed = pelvis.inverse() * data.oMf[model.getFrameId(name, pin.FrameType.BODY)]
        assert _close(placed, poses["pelvis"].inverse() * pose), name


@needs_erd
def test_cassie_reads_the_dampings_of_its_tree_joints(cassie):
    # <dynamics><damping> of the SDF's joints, read here from the file; the cut ball
    # joints and the held knee-shin joints have no coordinate of their own.
    path, entry = robots.resolve_model("erd:cassie")
    _, tree = read_sdf(path, fixed_joints=entry.fixed_joints)
    expected = {}
    for joint in etree.parse(str(path)).getroot().iter("joint"):
        damping = float(joint.findtext("axis/dynamics/damping", "0"))
        name = joint.get("name")
        if damping > 0 and name in tree.tree_joints and name not in tree.held_joints:
            expected[name] = damping
    assert {d.joint: d.damping for d in cassie.description.dampings} == expected
    assert len(expected) == 14


@needs_erd
def test_validation_walks_along_the_motion_where_random_starts_fail(cassie_standing, monkeypatch):
    """Cassie on welded feet rarely closes from a random start: validate's states walk
    from its closed reference (here at once), closed, consistent and within limits."""
    from closedchain import validation

    mech = cassie_standing
    monkeypatch.setattr(validation, "DRAW_ATTEMPTS", 1)
    states = list(validation._validation_states(mech, 3, 0, 1.0, None))
    assert len(states) == 3
    previous = mech.q_ref
    for q, v, tau in states:
        assert np.max(np.abs(cc.compute_phi(mech, q))) < TOL_CLOSED
        assert np.max(np.abs(cc.compute_jacobian(mech, q) @ v)) < TOL_CLOSED * max(
            1.0, np.max(np.abs(v))
        )
        assert mech.within_limits(q)
        assert np.linalg.norm(pin.difference(mech.model, previous, q)) > validation.WALK_STEP
        previous = q
        assert np.all(tau[:6] == 0.0)  # no actuator pushes the free-flyer root


# -- a long relative_to chain (issue 32) ------------------------------------------------------

#: Links in the relative_to chain (RecursionError at this length before).
CHAIN_LINKS = 3_000
#: Each link's pose along x relative to the previous one [m].
CHAIN_STEP = 1e-3
#: Round-off of CHAIN_LINKS placements composed [m] (measured 4e-13).
CHAIN_TOL = 1e-9
INERTIAL = (
    "<inertial><mass>1</mass><inertia><ixx>1</ixx><iyy>1</iyy><izz>1</izz></inertia></inertial>"
)


def _chain_sdf(n: int, *, cycle: bool = False) -> str:
    """A base, n massless links fixed to it each posed relative to the previous one, and an
    arm on a revolute joint posed relative to the last (``cycle``: the first link's pose
    is relative to the last)."""
    links = [f'<link name="base">{INERTIAL}</link>']
    for i in range(n):
        rel = (f"l{n - 1}" if cycle else "base") if i == 0 else f"l{i - 1}"
        links.append(
            f'<link name="l{i}"><pose relative_to="{rel}">{CHAIN_STEP} 0 0 0 0 0</pose></link>'
        )
    links.append(
        f'<link name="arm"><pose relative_to="l{n - 1}">0 0 0 0 0 0</pose>{INERTIAL}</link>'
    )
    joints = ['<joint name="j" type="revolute"><parent>base</parent><child>arm</child>'
              "<axis><xyz>0 0 1</xyz></axis></joint>"]  # fmt: skip
    joints += [
        f'<joint name="fx{i}" type="fixed"><parent>base</parent><child>l{i}</child></joint>'
        for i in range(n)
    ]
    body = "".join(links + joints)
    return f'<?xml version="1.0"?><sdf version="1.7"><model name="m">{body}</model></sdf>'


def test_a_relative_to_chain_of_thousands_of_frames_is_walked(tmp_path):
    path = tmp_path / "chain.sdf"
    path.write_text(_chain_sdf(CHAIN_LINKS))
    mech = cc.load(path)
    data = mech.model.createData()
    pin.framesForwardKinematics(mech.model, data, pin.neutral(mech.model))
    arm = data.oMf[mech.model.getFrameId("arm")].translation
    assert np.linalg.norm(arm - [CHAIN_LINKS * CHAIN_STEP, 0, 0]) < CHAIN_TOL


def test_a_relative_to_cycle_of_thousands_of_frames_is_one_bounded_line(tmp_path):
    path = tmp_path / "cycle.sdf"
    path.write_text(_chain_sdf(CHAIN_LINKS, cycle=True))
    with pytest.raises(
        cc.ModelFileError, match="poses are relative to each other in a cycle"
    ) as info:
        cc.load(path)
    message = str(info.value)
    assert "\n" not in message and len(message) < 3_000


# -- the mass matrix of an SDF tree against Pinocchio's URDF reader -------------------------

#: An SDF tree written from these numbers: link -> (pose [m, rad], inertial pose in the
#: link frame, mass [kg], ixx, ixy, ixz, iyy, iyz, izz [kg m^2]).
TREE_LINKS = {
    "base": ((0.1, -0.2, 0.3, 0.2, -0.1, 0.4), (0.01, 0.02, 0.03, 0, 0, 0), 3.0,
             (0.05, 0, 0, 0.06, 0, 0.07)),
    "a": ((0.4, 0.1, 0.5, 0.1, 0.2, 0.9), (0.1, 0, 0.05, 0.3, 0, 0.2), 1.5,
          (0.02, 0.001, 0, 0.03, 0, 0.04)),
    "b": ((0.7, -0.2, 0.4, 0, 0.3, 0), (0, 0.04, 0, 0, 0.1, 0), 0.8,
          (0.004, 0, 0.0005, 0.005, 0, 0.006)),
    "c": ((0.9, 0.1, 0.2, 0.2, 0, -0.3), (0.02, 0, -0.03, 0, 0, 0.5), 0.6,
          (0.003, 0, 0, 0.002, 0.0002, 0.0025)),
    "d": ((1.0, 0.2, 0.1, 0, 0, 0.1), (0, 0, 0.02, 0, 0, 0), 0.3,
          (0.001, 0, 0, 0.001, 0, 0.001)),
}  # fmt: skip
#: Joints: name -> (type, parent, child, pose in the child's frame, axis, axis2). a_base
#: is written from 'a', so the tree (rooted at 'base', the first link) reverses it.
TREE_JOINTS = {
    "a_base": ("revolute", "a", "base", (0.05, 0.02, 0, 0, 0, 0.3), (1, 0, 0), None),
    "a_b": ("prismatic", "a", "b", (-0.1, 0, 0.02, 0, 0, 0.4), (0, 0.6, 0.8), None),
    "b_c": ("universal", "b", "c", (0, 0.05, 0, 0.1, 0, 0), (1, 0, 0), (0, 0, 1)),
    "c_d": ("fixed", "c", "d", (0, 0, 0, 0, 0, 0), None, None),
}
#: Mass matrices and bias forces agree to this [kg m^2, N m] (round-off of two builds).
TOL_TREE_M = 1e-12
#: Joint limits of the hand-written URDF [rad or m] (beyond the states drawn).
URDF_LIMIT = 10.0


def _tree_sdf() -> str:
    def numbers(x) -> str:
        return " ".join(repr(float(v)) for v in x)

    out = ['<?xml version="1.0"?>\n<sdf version="1.6"><model name="tree">']
    for name, (pose, ipose, mass, inertia) in TREE_LINKS.items():
        names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
        tags = "".join(f"<{t}>{v!r}</{t}>" for t, v in zip(names, inertia, strict=True))
        out.append(
            f'<link name="{name}"><pose>{numbers(pose)}</pose><inertial><pose>{numbers(ipose)}'
            f"</pose><mass>{mass!r}</mass><inertia>{tags}</inertia></inertial></link>"
        )
    for name, (jtype, parent, child, pose, axis, axis2) in TREE_JOINTS.items():
        axes = "" if axis is None else f"<axis><xyz>{numbers(axis)}</xyz></axis>"
        axes += "" if axis2 is None else f"<axis2><xyz>{numbers(axis2)}</xyz></axis2>"
        out.append(
            f'<joint name="{name}" type="{jtype}"><pose>{numbers(pose)}</pose>'
            f"<parent>{parent}</parent><child>{child}</child>{axes}</joint>"
        )
    return "".join(out) + "</model></sdf>\n"


def _tree_urdf() -> str:
    """The same tree as plain URDF, written here: each URDF link's frame is its joint's
    SDF frame (the root's: its SDF pose), inertials re-expressed in it; the reversed
    joint's axis negated; the universal joint two revolutes through a massless link."""

    def origin(M: pin.SE3) -> str:
        xyz = " ".join(repr(float(v)) for v in M.translation)
        rpy = " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(M.rotation))
        return f'<origin xyz="{xyz}" rpy="{rpy}"/>'

    def inertial(name: str, frame: pin.SE3) -> str:
        pose, ipose, mass, (ixx, ixy, ixz, iyy, iyz, izz) = TREE_LINKS[name]
        M = frame.inverse() * _se3(pose[:3], pose[3:]) * _se3(ipose[:3], ipose[3:])
        return (
            f"<inertial>{origin(M)}<mass value='{mass!r}'/><inertia ixx='{ixx!r}' "
            f"ixy='{ixy!r}' ixz='{ixz!r}' iyy='{iyy!r}' iyz='{iyz!r}' izz='{izz!r}'/></inertial>"
        )

    def world(name: str) -> pin.SE3:
        return _se3(TREE_LINKS[name][0][:3], TREE_LINKS[name][0][3:])

    def joint_frame(name: str) -> pin.SE3:
        _, _, child, pose, _, _ = TREE_JOINTS[name]
        return world(child) * _se3(pose[:3], pose[3:])

    def joint(name, jtype, parent, child, M, axis=None) -> str:
        xyz = "" if axis is None else " ".join(repr(float(v)) for v in axis)
        axis_text = "" if axis is None else f"<axis xyz='{xyz}'/>"
        limit = (
            ""
            if jtype == "fixed"
            else (f"<limit lower='{-URDF_LIMIT}' upper='{URDF_LIMIT}' effort='1' velocity='1'/>")
        )
        return (
            f"<joint name='{name}' type='{jtype}'><parent link='{parent}'/><child link='{child}'/>"
            f"{origin(M)}{axis_text}{limit}</joint>"
        )

    frames = {
        "base": world("base"),
        "a": joint_frame("a_base"),
        "b": joint_frame("a_b"),
        "c": joint_frame("b_c"),
        "d": joint_frame("c_d"),
    }
    links = [f"<link name='{n}'>{inertial(n, frames[n])}</link>" for n in TREE_LINKS]
    links.append("<link name='b_c_cross'/>")
    joints = [
        joint("a_base", "revolute", "base", "a", frames["base"].inverse() * frames["a"],
              -np.array(TREE_JOINTS["a_base"][4])),
        joint("a_b", "prismatic", "a", "b", frames["a"].inverse() * frames["b"],
              TREE_JOINTS["a_b"][4]),
        joint("b_c", "revolute", "b", "b_c_cross", frames["b"].inverse() * frames["c"],
              TREE_JOINTS["b_c"][4]),
        joint("b_c_2", "revolute", "b_c_cross", "c", pin.SE3.Identity(), TREE_JOINTS["b_c"][5]),
        joint("c_d", "fixed", "c", "d", frames["c"].inverse() * frames["d"]),
    ]  # fmt: skip
    return "<robot name='tree'>" + "".join(links + joints) + "</robot>"


def test_an_sdf_tree_has_the_mass_matrix_of_the_same_tree_read_by_pinocchio(tmp_path, rng):
    mech = cc.load(_write(tmp_path, _tree_sdf()))
    _, tree = read_sdf(tmp_path / "m.sdf")
    assert tree.reversed_joints == ("a_base",)
    ref = pin.buildModelFromXML(_tree_urdf())
    assert (mech.nv, ref.nv) == (4, 4)
    model = mech.model
    # Each coordinate of ours -> the reference's: the universal joint's two in SDF order.
    ours = [model.joints[model.getJointId(n)].idx_v for n in ("a_base", "a_b", "b_c")]
    order = [ours[0], ours[1], ours[2], ours[2] + 1]
    theirs = [ref.joints[ref.getJointId(n)].idx_v for n in ("a_base", "a_b", "b_c", "b_c_2")]
    model.gravity.linear = ref.gravity.linear = np.array([0.3, -1.2, -9.81])
    data, ref_data = model.createData(), ref.createData()
    for _ in range(5):
        q, v, a = rng.uniform(-1.0, 1.0, (3, 4))
        q_ref, v_ref, a_ref = np.zeros((3, 4))
        q_ref[theirs], v_ref[theirs], a_ref[theirs] = q, v, a
        q_ours, v_ours, a_ours = np.zeros((3, 4))
        q_ours[order], v_ours[order], a_ours[order] = q, v, a
        M = pin.crba(model, data, q_ours)[np.ix_(order, order)]
        M_ref = pin.crba(ref, ref_data, q_ref)[np.ix_(theirs, theirs)]
        assert np.max(np.abs(np.triu(M) - np.triu(M_ref))) < TOL_TREE_M
        tau = pin.rnea(model, data, q_ours, v_ours, a_ours)[order]
        tau_ref = pin.rnea(ref, ref_data, q_ref, v_ref, a_ref)[theirs]
        assert np.max(np.abs(tau - tau_ref)) < TOL_TREE_M


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("loops.yaml", "loops: []\n", r"loops.yaml: a loops YAML file converts a URDF's joints"),
        (
            "motor.urdf",
            '<robot name="x"><transmission name="t"><joint name="nope"/></transmission></robot>',
            r"motor.urdf: line 1: <transmission name='t'>: names joint 'nope', which is not a",
        ),
    ],
)
def test_an_overlay_an_sdf_model_cannot_take_is_refused_naming_it(tmp_path, name, text, match):
    overlay = tmp_path / name
    overlay.write_text(text)
    with pytest.raises(cc.ModelFileError, match=match):
        cc.load(FOURBAR, loops=overlay)


def test_an_overlay_adds_a_link_to_an_sdf_model_where_it_says(tmp_path):
    # A 1 kg point mass fixed 0.2 m along the crank's x: its world position at q_ref is the
    # crank frame's (the SDF pose, checked elsewhere) moved by 0.2 m along its x axis.
    overlay = tmp_path / "tip.urdf"
    overlay.write_text(
        '<robot name="tip"><link name="tip"><inertial><mass value="1"/>'
        '<inertia ixx="0" iyy="0" izz="0" ixy="0" ixz="0" iyz="0"/></inertial></link>'
        '<joint name="tip_joint" type="fixed"><parent link="crank"/><child link="tip"/>'
        '<origin xyz="0.2 0 0"/></joint></robot>'
    )
    plain, mech = cc.load(FOURBAR), cc.load(FOURBAR, loops=overlay)
    placed = []
    for m, frame in ((plain, "crank"), (mech, "tip")):
        data = m.model.createData()
        pin.framesForwardKinematics(m.model, data, plain.q_ref)
        placed.append(data.oMf[m.model.getFrameId(frame, pin.FrameType.BODY)])
    crank, tip = placed
    assert np.max(np.abs(tip.translation - crank.act(np.array([0.2, 0.0, 0.0])))) < TOL_FRAME
    assert mech.nv == plain.nv


def test_an_overlay_adds_loops_and_motors_to_an_sdf_model(tmp_path):
    # Pin the 4-bar's coupler to the world where it is drawn (its frame's origin B), and
    # drive the motor: the overlay's loop closes at the reference, the motor is actuated.
    overlay = tmp_path / "pinned.urdf"
    overlay.write_text(
        '<robot name="pinned"><loop name="pin_b" type="spherical"><predecessor link="world"/>'
        '<successor link="coupler"/><predecessor_origin xyz="0 0.1 0"/></loop>'
        '<transmission name="t"><joint name="motor_joint"/></transmission></robot>'
    )
    mech = cc.load(FOURBAR, loops=overlay)
    assert (mech.name, mech.actuated_joints) == ("pinned", ("motor_joint",))
    assert [lp.name for lp in mech.description.loops][-1] == "pin_b"
    assert np.max(np.abs(cc.compute_phi(mech, mech.q_ref))) < TOL_CLOSED


def test_an_sdf_tree_beyond_the_size_limit_is_refused_before_it_is_described(tmp_path):
    # The 4-bar's tree: four revolute joints (nv 4), one beyond a limit of 3; the chain of
    # 3000 fixed links above counts no degree of freedom.
    from closedchain.pindata import data_bytes

    budget = (data_bytes(3) + data_bytes(4)) / 2
    with pytest.raises(cc.ModelTooLargeError, match=r"fourbar.sdf: 4 joints with nv = 4 .*nv <= 3"):
        cc.load(FOURBAR, settings=cc.LoadSettings(max_data_bytes=budget))
    path = tmp_path / "chain.sdf"
    path.write_text(_chain_sdf(CHAIN_LINKS))
    assert cc.load(path, settings=cc.LoadSettings(max_data_bytes=budget)).nv == 1
