"""Loops on any frame (``<predecessor frame=...>``) and the example-parallel-robots YAML.

References, none computed by the code under test:

* the frames the YAML names, read from Pinocchio's own model of the tree
  (``data.oMf`` of ``model.getFrameId(name)``): a ``6d`` pair has equal
  placements and a ``3d`` pair equal positions at every assembled
  configuration, while a ``3d`` pair's orientations move apart;
* mobility by Gruebler-Kutzbach, counted in tests/data/make_yaml_mechanisms.py;
* pinocchio.constraintDynamics on the same tree and loops (``validate``);
* the base URDF as Pinocchio reads it, for the joints the YAML converts.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, ROOT
from lxml import etree

import closedchain as cc
from closedchain.cli import main
from closedchain.closure import layer_phi, max_declared_residual

#: Assembled configurations close every declared row to this [m or -].
TOL_PHI = 1e-12
#: Frames the YAML pairs coincide to this at assembled configurations [m, rad].
TOL_FRAMES = 1e-10
#: Accelerations agree with pinocchio.constraintDynamics to this [rad/s^2].
TOL_A = 1e-9
#: Every declared row stays below this during a 0.2 s run [m or -].
TOL_ROWS = 1e-9
#: A 3d pair's orientations differ by at least this after the motors turn [rad].
MIN_TURN = 1e-3
#: Motor displacement [rad] from q_ref to the second assembled configuration.
MOTOR_STEP = 0.1
#: Mass matrices of the same tree built two ways agree to this [kg m^2] (round-off).
TOL_MASS = 1e-15
#: Validation states per mechanism.
N_STATES = 10
#: Simulated time [s].
T_RUN = 0.2

#: case -> (URDF, YAML, nv, mobility by Gruebler-Kutzbach, motors).
CASES = {
    "fivebar_6d": ("yaml_fivebar.urdf", "yaml_fivebar_6d.yaml", 5, 2, ("mot1", "mot2")),
    "fivebar_3d": ("yaml_fivebar.urdf", "yaml_fivebar_3d.yaml", 4, 2, ("mot1", "mot2")),
    "delta": ("yaml_delta.urdf", "yaml_delta.yaml", 15, 9, ("mot0", "mot1", "mot2")),
    "ujoint_leg": ("yaml_ujoint_leg.urdf", "yaml_ujoint_leg.yaml", 5, 2, ("hip", "crank_mot")),
    "offset_rod_ball": ("yaml_offset_rod.urdf", "yaml_offset_rod_ball.yaml", 5, 2, ("mot1",)),
}

#: case -> the YAML's frame pairs and types (as written in tests/data).
PAIRS = {
    "fivebar_6d": [("tip1", "tip2", "6d")],
    "fivebar_3d": [("tip1", "tip2", "3d")],
    "delta": [("rod_tip1", "platform_att1", "3d"), ("rod_tip2", "platform_att2", "3d")],
    "ujoint_leg": [("rod_tip", "shin_att", "3d")],
    "offset_rod_ball": [("rod_end", "rocker_tip", "3d")],
}


@pytest.fixture(scope="module")
def mechs():
    cache: dict[str, cc.Mechanism] = {}

    def get(case: str) -> cc.Mechanism:
        if case not in cache:
            urdf, loops = CASES[case][:2]
            cache[case] = cc.load(DATA_DIR / urdf, loops=DATA_DIR / loops)
        return cache[case]

    return get


def _max_phi(mech: cc.Mechanism, q: np.ndarray) -> float:
    """Max |phi| over every declared row (redundant ones included) at q."""
    return max_declared_residual(mech, np.atleast_2d(q))


def _pair_errors(mech: cc.Mechanism, q: np.ndarray, a: str, b: str) -> tuple[float, float]:
    """(|position difference| [m], relative rotation angle [rad]) of two named frames at q."""
    model = mech.model
    assert model.existFrame(a) and model.existFrame(b)
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    oMa, oMb = data.oMf[model.getFrameId(a)], data.oMf[model.getFrameId(b)]
    dp = float(np.linalg.norm(oMa.translation - oMb.translation))
    return dp, float(np.linalg.norm(pin.log3(oMa.rotation.T @ oMb.rotation)))


@pytest.mark.parametrize("case", CASES)
def test_sizes_mobility_and_motors(mechs, case):
    _, _, nv, mobility, motors = CASES[case]
    mech = mechs(case)
    assert (mech.nv, mech.mobility) == (nv, mobility)
    assert mech.actuated_joints == motors
    assert len(mech.description.loops) == len(PAIRS[case])


@pytest.mark.parametrize("case", CASES)
def test_named_frames_coincide_where_assembled(mechs, case):
    """At q_ref and after the motors turn: 6d pairs coincide, 3d pairs share a point only."""
    mech = mechs(case)
    assert _max_phi(mech, mech.q_ref) <= TOL_PHI
    motors_q = [mech.model.joints[mech.model.getJointId(j)].idx_q for j in mech.actuated_joints]
    q = mech.q_ref.copy()
    q[motors_q] += MOTOR_STEP
    q = cc.assemble(mech, q, fixed="actuated")
    assert _max_phi(mech, q) <= TOL_PHI
    assert np.allclose(q[motors_q], mech.q_ref[motors_q] + MOTOR_STEP, rtol=0.0, atol=1e-15)
    for a, b, kind in PAIRS[case]:
        for config in (mech.q_ref, q):
            dp, angle = _pair_errors(mech, config, a, b)
            assert dp <= TOL_FRAMES
            if kind == "6d":
                assert angle <= TOL_FRAMES
    if case in ("fivebar_3d", "ujoint_leg"):
        # A 3d loop leaves the orientations free: they move apart as the motors turn.
        assert _pair_errors(mech, q, *PAIRS[case][0][:2])[1] >= MIN_TURN


@pytest.mark.parametrize("case", CASES)
def test_validate_against_pinocchio(mechs, case):
    rep = cc.validate(mechs(case), n_samples=N_STATES, seed=5)
    assert rep.n_singular == 0
    assert rep.max_da <= TOL_A, rep
    assert rep.passed


@pytest.mark.parametrize("case", CASES)
def test_simulate_keeps_the_loops_closed(mechs, case):
    mech = mechs(case)
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), T_RUN)
    assert traj.t[-1] == pytest.approx(T_RUN)
    assert max_declared_residual(mech, traj.q) <= TOL_ROWS
    assert np.all(np.isfinite(traj.q))


# -- joint conversions, against the base URDF as Pinocchio reads it ------------------------


def _base_model(name: str) -> pin.Model:
    return pin.buildModelFromUrdf(str(DATA_DIR / name))


def test_fixed_conversion_removes_the_joint_and_keeps_its_frame(mechs):
    mech, base = mechs("fivebar_3d"), _base_model("yaml_fivebar.urdf")
    assert base.existJointName("pin") and not mech.model.existJointName("pin")
    assert mech.model.existFrame("pin", pin.FrameType.FIXED_JOINT)
    # Fixed at its zero position: the tree's frames are where the base puts them at q = 0.
    data, base_data = mech.model.createData(), base.createData()
    pin.framesForwardKinematics(mech.model, data, pin.neutral(mech.model))
    pin.framesForwardKinematics(base, base_data, pin.neutral(base))
    for name in ("tip1", "tip2", "pin_link"):
        oMf = data.oMf[mech.model.getFrameId(name)]
        assert oMf.isApprox(base_data.oMf[base.getFrameId(name)], 1e-14)


def test_ujoint_conversion(mechs):
    """UJOINT_YX: revolute joints about Y then X at the old joint's origin, through a
    massless link, the child link unchanged."""
    model, base = mechs("ujoint_leg").model, _base_model("yaml_ujoint_leg.urdf")
    old = base.getJointId("rod_ujoint")
    assert not model.existJointName("rod_ujoint")
    first, second = model.getJointId("rod_ujoint_Y"), model.getJointId("rod_ujoint_X")
    assert model.joints[first].shortname() == "JointModelRY"
    assert model.joints[second].shortname() == "JointModelRX"
    assert model.names[model.parents[first]] == base.names[base.parents[old]]
    assert model.parents[second] == first
    assert model.jointPlacements[first].isApprox(base.jointPlacements[old], 1e-15)
    assert model.jointPlacements[second].isIdentity()
    assert model.inertias[first].mass == 0.0
    assert model.inertias[second].isApprox(base.inertias[old], 1e-14)
    q_idx = [model.joints[j].idx_q for j in (first, second)]
    assert np.all(model.upperPositionLimit[q_idx] == np.pi)


@pytest.mark.parametrize("joint", ["elbow1", "wrist0"])
def test_spherical_conversion_is_a_pinocchio_spherical_joint(mechs, joint):
    """SPHERICAL: one JointModelSpherical with the old joint's name, parent, placement and
    body; the frames of the child link move with it as the old child did with its joint."""
    mech, base = mechs("delta"), _base_model("yaml_delta.urdf")
    model, old = mech.model, base.getJointId(joint)
    j = model.getJointId(joint)
    assert model.joints[j].shortname() == "JointModelSpherical"
    assert model.names[model.parents[j]] == base.names[base.parents[old]]
    assert model.jointPlacements[j].isApprox(base.jointPlacements[old], 1e-15)
    assert model.inertias[j].isApprox(base.inertias[old], 1e-14)
    assert model.existFrame(joint, pin.FrameType.JOINT)
    assert not any(model.existFrame(f"{joint}_{a}", pin.FrameType.JOINT) for a in "XYZ")
    # Turned by R, the child's frames are the base's child turned about the joint by R.
    R = pin.rpy.rpyToMatrix(0.3, -0.5, 1.1)
    q = pin.neutral(model)
    jm = model.joints[j]
    q[jm.idx_q : jm.idx_q + 4] = pin.Quaternion(R).coeffs()
    data, base_data = model.createData(), base.createData()
    pin.framesForwardKinematics(model, data, q)
    pin.framesForwardKinematics(base, base_data, pin.neutral(base))
    child = {"elbow1": "rod1", "wrist0": "platform"}[joint]
    oMj = base_data.oMi[old]
    expected = oMj * pin.SE3(R, np.zeros(3)) * oMj.actInv(base_data.oMf[base.getFrameId(child)])
    assert data.oMf[model.getFrameId(child)].isApprox(expected, 1e-14)


# -- the URDF+ frame= syntax ---------------------------------------------------------------

FIVEBAR_LOOP = """<robot name="fivebar_frames">
  <loop name="weld" type="fixed">
    <predecessor {pred}/>
    <successor frame="tip2"/>
    {origin}
  </loop>
  <transmission name="t1"><type>SimpleTransmission</type><joint name="mot1"/></transmission>
  <transmission name="t2"><type>SimpleTransmission</type><joint name="mot2"/></transmission>
</robot>
"""

#: tip1's placement in pin_link (and so in the frame of joint pin), as written in the URDF.
TIP1_ORIGIN = '<predecessor_origin xyz="0.03 0.0 0.01" rpy="0.2 0.3 0.1"/>'


@pytest.mark.parametrize(
    ("pred", "origin"),
    [
        ('frame="tip1"', ""),  # a fixed joint's frame
        ('frame="pin"', TIP1_ORIGIN),  # a joint's frame, with the origin in it
        ('link="pin_link"', TIP1_ORIGIN),  # the link, as before
        ('frame="tip1_link"', ""),  # a link named as a frame
    ],
)
def test_frame_sides_match_the_yaml_weld(mechs, tmp_path, rng, pred, origin):
    """Written with frame= on any frame (or link=), the weld has the YAML loop's phi and J."""
    overlay = tmp_path / "weld.urdf"
    overlay.write_text(FIVEBAR_LOOP.format(pred=pred, origin=origin))
    mech = cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=overlay)
    ref = mechs("fivebar_6d")
    assert mech.mobility == ref.mobility
    # Resolved to the link: the frame itself, else the first link on the frame's joint.
    assert mech.description.loops[0].predecessor == (
        "tip1_link" if "tip1_link" in pred else "pin_link"
    )
    assert mech.description.loops[0].successor == "dist2"
    for _ in range(5):
        q = ref.random_configuration(rng)
        phi, phi_ref = _all_rows(mech, q), _all_rows(ref, q)
        assert np.max(np.abs(phi - phi_ref)) <= 1e-14
    summary = mech.summary()["loops"][0]
    assert summary["successor"] == "tip2"


def _all_rows(mech: cc.Mechanism, q: np.ndarray) -> np.ndarray:
    return layer_phi(mech.model, mech.model.createData(), mech.declared, q)


def test_a_frame_of_the_world_holds_a_free_base(mechs, tmp_path):
    """frame="universe" (Pinocchio's world frame) welded to the root link's frame: the
    free-flying five-bar keeps the fixed one's mobility and its base stays put."""
    overlay = tmp_path / "welds.urdf"
    text = FIVEBAR_LOOP.format(pred='frame="tip1"', origin="")
    overlay.write_text(
        text.replace(
            "  <transmission",
            '  <loop name="ground" type="fixed"><predecessor frame="universe"/>'
            '<successor frame="base"/></loop>\n  <transmission',
            1,
        )
    )
    mech = cc.load(DATA_DIR / "yaml_fivebar.urdf", root_joint="free", loops=overlay)
    assert mech.description.loops[1].predecessor == "world"
    assert mech.nv == mechs("fivebar_6d").nv + 6
    assert mech.mobility == mechs("fivebar_6d").mobility
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), T_RUN)
    assert np.max(np.abs(traj.q[:, :7] - mech.q_ref[:7])) <= TOL_ROWS


@pytest.mark.parametrize(
    ("urdf", "name", "text", "where", "frames"),
    [
        (  # URDF+ overlay: every frame listed
            "yaml_fivebar.urdf",
            "weld.urdf",
            FIVEBAR_LOOP.format(pred='frame="tip3"', origin=""),
            "line 2: <loop name='weld'>: <predecessor frame='tip3'>",
            "base, dist1, dist2, free1, free2, mot1, mot2, pin, pin_link, prox1, prox2, tip1, "
            "tip1_link, tip2, tip2_link, universe$",
        ),
        (  # YAML: every frame listed
            "yaml_delta.urdf",
            "delta.yaml",
            (DATA_DIR / "yaml_delta.yaml").read_text().replace("'rod_tip1'", "'rod_tipl'"),
            "<loop name='rod_tipl--platform_att1'>: <predecessor frame='rod_tipl'>",
            "arm0, arm1, arm2, base, elbow0, elbow1, elbow2, mot0, mot1, mot2, platform, "
            "platform_att1, platform_att1_link, platform_att2, platform_att2_link, rod0, rod1, "
            "rod2, rod_tip1, rod_tip1_link, rod_tip2, rod_tip2_link, universe, wrist0$",
        ),
        (  # YAML, a tree of more than 30 frames: the list is cut
            str(ROOT / "models" / "nfourbar_40.urdf"),
            "nfourbar.yaml",
            "closed_loop: [['crank_00_tip', 'crank_0l']]\ntype: ['3d']\n",
            "<loop name='crank_00_tip--crank_0l'>: <successor frame='crank_0l'>",
            r"coupler_01, coupler_01_joint, .*, coupler_15_joint, \.\.\. and 216 more$",
        ),
    ],
)
def test_unknown_frame_lists_the_frames(tmp_path, urdf, name, text, where, frames):
    loops = tmp_path / name
    loops.write_text(text)
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(f"{loops}: {where} ") + "names no frame of the tree; frames: " + frames,
    ):
        cc.load(DATA_DIR / urdf, loops=loops)


@pytest.mark.parametrize(
    ("side", "message"),
    [
        ('<predecessor link="pin_link" frame="tip1"/>', "needs exactly one of link= .* or frame="),
        ("<predecessor/>", "needs exactly one of link= .* or frame="),
    ],
)
def test_a_side_names_a_link_or_a_frame(tmp_path, side, message):
    overlay = tmp_path / "weld.urdf"
    overlay.write_text(FIVEBAR_LOOP.format(pred="x", origin="").replace("<predecessor x/>", side))
    with pytest.raises(cc.ModelFileError, match=r"<loop name='weld'>: <predecessor> " + message):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=overlay)


def test_frames_on_one_joint_close_nothing(tmp_path):
    overlay = tmp_path / "weld.urdf"
    overlay.write_text(
        FIVEBAR_LOOP.format(pred='frame="pin"', origin="").replace('"tip2"', '"tip1"')
    )
    with pytest.raises(
        cc.ModelFileError, match="predecessor 'pin' and successor 'tip1' move with the same joint"
    ):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=overlay)


# -- YAML errors ---------------------------------------------------------------------------

FIVEBAR_YAML = """closed_loop: [[tip1, tip2]]
type: [6d]
name_mot: [mot1, mot2]
"""


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            FIVEBAR_YAML + "closed_loops: []\n",
            "unknown key 'closed_loops'; valid keys: closed_loop, type, name_mot, joint_name, "
            "joint_type",
        ),
        (FIVEBAR_YAML.replace("[6d]", "[6d, 3d]"), "closed_loop has 1 pairs but type has 2"),
        (FIVEBAR_YAML.replace("[6d]", "[5d]"), r"type\[0\] = '5d' is not a constraint type; "),
        (
            FIVEBAR_YAML.replace("[[tip1, tip2]]", "[[tip1, tip2, tip1]]"),
            "closed_loop must be a list of pairs of frame names",
        ),
        (
            FIVEBAR_YAML.replace("[[tip1, tip2]]", "[[tip1, tip1]]"),
            r"closed_loop\[0\] pairs frame 'tip1' with itself",
        ),
        (
            FIVEBAR_YAML.replace("[[tip1, tip2]]", "[[tip1, tip2], [tip2, tip1]]").replace(
                "[6d]", "[6d, 6d]"
            ),
            r"closed_loop\[1\] repeats closed_loop\[0\]",
        ),
        (FIVEBAR_YAML.replace("[mot1, mot2]", "mot1"), "name_mot must be a list of names"),
        (FIVEBAR_YAML + "joint_name: [pin]\n", "joint_name has 1 entries but joint_type has 0"),
        (
            FIVEBAR_YAML + "joint_name: [pin]\njoint_type: [UJOINT_XX]\n",
            r"joint_type\[0\] = 'UJOINT_XX' \(joint 'pin'\) is not a conversion; valid: "
            r"SPHERICAL, FIXED, UJOINT_<A><B>",
        ),
        ("- 1\n- 2\n", "expected a mapping of keys closed_loop, "),
        ("closed_loop: [[tip1, tip2]\n", "not a YAML file: "),
        (
            "closed_loop: !!python/object:os.system {}\n",
            "not a YAML file: line 1: could not determine",
        ),
    ],
)
def test_yaml_errors_name_the_file_and_the_key(tmp_path, text, message):
    loops = tmp_path / "robot.yaml"
    loops.write_text(text)
    with pytest.raises(cc.ModelFileError, match=re.escape(f"{loops}: ") + message):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (
            "joint_name: [tip1]\njoint_type: [spherical]\n",
            r"joint_name\[0\] = 'tip1' is a fixed joint, which SPHERICAL cannot replace; valid: "
            "a revolute, continuous, prismatic joint",
        ),
        (
            "joint_name: [mot2]\njoint_type: [FIXED]\n",
            r"name_mot\[1\] = 'mot2' is converted to FIXED by joint_type, so it cannot be a motor",
        ),
    ],
)
def test_yaml_conversion_errors(tmp_path, extra, message):
    loops = tmp_path / "robot.yaml"
    loops.write_text(FIVEBAR_YAML + extra)
    with pytest.raises(cc.ModelFileError, match=re.escape(f"{loops}: ") + message):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


def test_a_conversion_of_no_joint_is_passed_over_with_a_warning(mechs, tmp_path, caplog):
    """As the authors' loader does (disney_robot spells a joint 'left_s\u0125erical_free_foot')."""
    loops = tmp_path / "robot.yaml"
    loops.write_text(FIVEBAR_YAML + "joint_name: [pn]\njoint_type: [FIXED]\n")
    with caplog.at_level(logging.WARNING, logger="closedchain.yaml_loops"):
        mech = cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)
    assert re.fullmatch(
        re.escape(f"{loops}: joint_name[0] = 'pn' is not a <joint> of ")
        + r".*yaml_fivebar\.urdf \(did you mean 'pin'\?\): ignored \(FIXED not applied\), as "
        "the authors' loader does",
        caplog.records[-1].getMessage(),
    )
    # The tree is the one without the entry: pin still turns.
    assert mech.nv == mechs("fivebar_6d").nv
    assert mech.model.existJointName("pin")


def test_more_motors_than_the_mobility_is_a_warning(mechs, tmp_path, caplog):
    """A 6d pair where the tree has no pin joint welds the tips of the planar five-bar:
    mobility 1 under 2 motors loads, with a one-line warning naming the file."""
    loops = tmp_path / "welded.yaml"
    loops.write_text(FIVEBAR_YAML + "joint_name: [pin]\njoint_type: [FIXED]\n")
    with caplog.at_level(logging.WARNING, logger="closedchain.mechanism"):
        mech = cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)
    assert mech.mobility == 1
    (record,) = [r for r in caplog.records if r.name == "closedchain.mechanism"]
    assert record.getMessage().startswith(
        f"{loops}: mobility 1 is less than the 2 motors (mot1, mot2): a loop over-constrains"
    )
    assert "3d" in record.getMessage() and "\n" not in record.getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="closedchain.mechanism"):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=DATA_DIR / "yaml_fivebar_3d.yaml")
    assert not caplog.records  # mobility 2, two motors: nothing to say


def test_unknown_motor_lists_the_movable_joints(tmp_path):
    loops = tmp_path / "robot.yml"  # the other suffix
    loops.write_text(FIVEBAR_YAML.replace("mot2]", "mot3]"))
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(f"{loops}: name_mot[1] = 'mot3' is not a movable <joint> of ")
        + r".* \(did you mean 'mot2'\?\); movable joints: free1, free2, mot1, mot2, pin$",
    ):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


def test_conversion_names_must_be_free(tmp_path):
    urdf = tmp_path / "fivebar.urdf"
    text = (DATA_DIR / "yaml_fivebar.urdf").read_text()
    urdf.write_text(
        text.replace(
            "</robot>",
            '<link name="pin_X_link"/><joint name="tag" type="fixed"><parent link="base"/>'
            '<child link="pin_X_link"/></joint></robot>',
        )
    )
    loops = tmp_path / "robot.yaml"
    loops.write_text(FIVEBAR_YAML + "joint_name: [pin]\njoint_type: [UJOINT_XY]\n")
    with pytest.raises(
        cc.ModelFileError,
        match=re.escape(f"{loops}: joint_name[0] = 'pin': converting it needs the name ")
        + "'pin_X_link', which the tree already uses",
    ):
        cc.load(urdf, loops=loops)


def ball_chains(text: str, joints: tuple[str, ...]) -> str:
    """Return a URDF text with each named joint written as the corpus writes a ball joint:
    revolute joints ``<joint>_X, _Y, _Z`` in a row at its origin, through massless links."""
    root = etree.fromstring(text.encode())
    for name in joints:
        joint = root.find(f"joint[@name='{name}']")
        parent, child = joint.find("parent").get("link"), joint.find("child").get("link")
        links = [f"{name}_X_link", f"{name}_Y_link"]
        position = list(root).index(joint)
        root.remove(joint)
        new = [etree.Element("link", name=link) for link in links]
        for k, axis in enumerate("XYZ"):
            element = etree.Element("joint", name=f"{name}_{axis}", type="revolute")
            if k == 0 and joint.find("origin") is not None:
                element.append(joint.find("origin"))
            etree.SubElement(element, "parent", link=[parent, *links][k])
            etree.SubElement(element, "child", link=[*links, child][k])
            etree.SubElement(
                element, "axis", xyz=" ".join("1" if a == axis else "0" for a in "XYZ")
            )
            etree.SubElement(
                element, "limit", lower="-3.14", upper="3.14", effort="0", velocity="0"
            )
            new.append(element)
        for offset, element in enumerate(new):
            root.insert(position + offset, element)
    return etree.tostring(root, encoding="unicode")


#: The joints the delta's YAML converts to SPHERICAL.
DELTA_BALLS = ("elbow0", "elbow1", "elbow2", "wrist0")


def test_ball_chains_of_the_corpus_are_fused(mechs, tmp_path):
    """Three revolute joints through massless links at one point (how the corpus writes a
    ball joint) become one spherical joint named after the last, under a loops YAML;
    plain URDF keeps the three. The fused tree is the SPHERICAL conversion's."""
    urdf = tmp_path / "delta_chains.urdf"
    urdf.write_text(ball_chains((DATA_DIR / "yaml_delta.urdf").read_text(), DELTA_BALLS))
    loops = tmp_path / "robot.yaml"
    # The same loops and motors, no conversion.
    loops.write_text((DATA_DIR / "yaml_delta.yaml").read_text().split("joint_name")[0])
    fused, plain, ref = cc.load(urdf, loops=loops), cc.load(urdf), mechs("delta")
    assert fused.model.existJointName("elbow1_Z") and not fused.model.existJointName("elbow1_X")
    assert fused.model.existFrame("elbow1_X", pin.FrameType.FIXED_JOINT)
    assert (fused.nq, fused.nv, fused.mobility) == (ref.nq, ref.nv, ref.mobility)
    assert (plain.nq, plain.nv) == (ref.nv, ref.nv)
    masses = [sum(i.mass for i in m.model.inertias) for m in (fused, plain, ref)]
    assert masses[0] == pytest.approx(masses[1], rel=1e-15) == pytest.approx(masses[2], rel=1e-15)
    # Joint by joint, the fused model is the reference's: same kind, placement and
    # inertia, and the same mass matrix at the reference's configuration.
    joints = {
        name: ref.model.getJointId(name.removesuffix("_Z") if name[:-2] in DELTA_BALLS else name)
        for name in list(fused.model.names)[1:]
    }
    q, v_index = np.zeros(fused.nq), []
    for name, k in joints.items():
        ours, theirs = fused.model.joints[fused.model.getJointId(name)], ref.model.joints[k]
        assert ours.shortname() == theirs.shortname()
        j = fused.model.getJointId(name)
        assert fused.model.jointPlacements[j].isApprox(ref.model.jointPlacements[k], 1e-15)
        assert fused.model.inertias[j].isApprox(ref.model.inertias[k], 1e-15)
        q[ours.idx_q : ours.idx_q + ours.nq] = ref.q_ref[theirs.idx_q : theirs.idx_q + theirs.nq]
        v_index.extend(range(theirs.idx_v, theirs.idx_v + theirs.nv))
    M = pin.crba(fused.model, fused.model.createData(), q)
    M_ref = pin.crba(ref.model, ref.model.createData(), ref.q_ref)
    assert np.max(np.abs(M - M_ref[np.ix_(v_index, v_index)])) <= TOL_MASS


def test_limits_without_a_range_are_no_limits(tmp_path):
    """A <limit> without lower and upper (URDF: [0, 0]; the corpus writes every joint so)
    gives no position limits under a loops YAML; plain URDF keeps URDF's reading."""
    urdf = tmp_path / "fivebar.urdf"
    text = (DATA_DIR / "yaml_fivebar.urdf").read_text()
    first = text.index('lower="-3.14" upper="3.14" ')  # mot1's, the first joint
    urdf.write_text(text[:first] + text[first + len('lower="-3.14" upper="3.14" ') :])
    mech = cc.load(urdf, loops=DATA_DIR / "yaml_fivebar_6d.yaml")
    plain = cc.load(urdf)
    lower, upper = mech.model.lowerPositionLimit, mech.model.upperPositionLimit
    k = mech.model.joints[mech.model.getJointId("mot1")].idx_q
    k_plain = plain.model.joints[plain.model.getJointId("mot1")].idx_q
    assert (lower[k], upper[k]) == (-np.inf, np.inf)
    assert (plain.model.lowerPositionLimit[k_plain], plain.model.upperPositionLimit[k_plain]) == (
        0.0,
        0.0,
    )
    others = np.arange(mech.nq) != k
    assert np.all(lower[others] == -3.14) and np.all(upper[others] == 3.14)


# -- command line and the corpus script ----------------------------------------------------


def test_cli_reads_the_yaml(capsys):
    urdf, loops = DATA_DIR / "yaml_ujoint_leg.urdf", DATA_DIR / "yaml_ujoint_leg.yaml"
    assert main(["info", str(urdf), "--loops", str(loops), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    # name_mot's order (the YAML's), not the coordinates' (crank_mot comes first there).
    assert s["mobility"] == 2 and s["actuated"] == ["hip", "crank_mot"]
    assert s["loops"][0]["predecessor"] == "rod_tip" and s["loops"][0]["type"] == "spherical"


def test_check_corpus_writes_its_table(tmp_path):
    """scripts/check_corpus.py on a corpus-shaped copy: one row per robot.urdf + robot.yaml."""
    robots = tmp_path / "robots"
    (robots / "fivebar").mkdir(parents=True)
    (robots / "no_yaml").mkdir()
    shutil.copy(DATA_DIR / "yaml_fivebar.urdf", robots / "fivebar" / "robot.urdf")
    shutil.copy(DATA_DIR / "yaml_fivebar_3d.yaml", robots / "fivebar" / "robot.yaml")
    shutil.copy(DATA_DIR / "yaml_fivebar.urdf", robots / "no_yaml" / "robot.urdf")
    (robots / "delta").mkdir()
    shutil.copy(DATA_DIR / "yaml_delta.urdf", robots / "delta" / "robot.urdf")
    shutil.copy(DATA_DIR / "yaml_delta.yaml", robots / "delta" / "robot.yaml")
    out = tmp_path / "table.md"
    run = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "check_corpus.py"), str(robots), "--out", str(out)],
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    table = out.read_text()
    header = next(ln for ln in table.splitlines() if ln.startswith("| robot "))
    assert [c.strip() for c in header.strip("|").split("|")][6:10] == [
        "validate da_M (judged)",
        "validate max abs da [rad/s^2]",
        "simulate 1 s CPU [s]",
        "animates",
    ]
    rows = {ln.split("|")[1].strip(): ln for ln in table.splitlines() if ln.startswith("| ")}
    cells = [c.strip() for c in rows["fivebar"].strip("|").split("|")]
    assert cells[1:4] == ["1 (0 6d, 1 3d)", "4", "2 / 2"]
    assert float(cells[5]) <= TOL_PHI
    assert float(cells[6]) <= TOL_A
    assert re.fullmatch(r"\d\S* MB, 0 meshes", cells[9])
    assert cells[10] == ""
    # Mobility above the motors: the motions left with the motors held, by their joints
    # (the rods' spins about their axes; the platform, held by three rods only, moves).
    delta = [c.strip() for c in rows["delta"].strip("|").split("|")]
    assert delta[3] == "9 / 3"
    assert "mobility 9 = 3 motors + 6 motions with the motors held" in delta[10]
    assert delta[10].split(";")[-2:] == [" elbow1", " elbow2"]
    assert "no_yaml" in run.stdout and not (tmp_path / "table.md.tmp").exists()


# -- loops that cannot close (kangaroo_like, kangaroo_like_2legs) ---------------------------

#: Numbers below 10 printed in a message (6 significant digits) agree with the reference to
#: this [m or rad]: half a unit of the sixth digit.
TOL_PRINTED = 5e-6
#: Random configurations on which the heights the proof names are checked invariant.
N_INVARIANCE = 200
#: The heights stay constant to this over them [m] (round-off of the forward kinematics).
TOL_INVARIANT = 1e-12

OFFSET_ROD = DATA_DIR / "yaml_offset_rod.urdf"
OFFSET_ROD_LOOP = "closed_loop: [[rod_end, rocker_tip]]\nname_mot: [mot1]\n"
NUMBER = r"(-?[0-9.e+-]+)"


def _offset_rod_heights(rng) -> tuple[float, float, float]:
    """Heights along y [m] of the crank tip, the rod end and the rocker tip, and their spread.

    From Pinocchio's own model of the tree as written (spherical_rod a revolute
    joint), over random configurations: the heights the proof of
    :func:`closedchain._invariants.prove_unclosable` says no joint changes.
    """
    model = pin.buildModelFromUrdf(str(OFFSET_ROD))
    data = model.createData()
    heights = []
    for _ in range(N_INVARIANCE):
        pin.framesForwardKinematics(model, data, rng.uniform(-np.pi, np.pi, model.nq))
        crank_tip = data.oMi[model.getJointId("spherical_rod")].translation
        ends = [data.oMf[model.getFrameId(name)].translation for name in ("rod_end", "rocker_tip")]
        heights.append([crank_tip[1], ends[0][1], ends[1][1]])
    heights = np.array(heights)
    assert float(np.max(np.ptp(heights, axis=0))) <= TOL_INVARIANT
    return tuple(float(h) for h in heights[0])


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (  # kangaroo_like_2legs: a ball left revolute, a 3d loop
            "type: [3d]\n",
            rf"\(spherical\) cannot close in any configuration: joints mot1, rocker_pivot turn "
            rf"about .* the axis \[0 1 0\] .* stays in \[{NUMBER}, {NUMBER}\] m \(joint "
            rf"'spherical_rod'\), that of the other at {NUMBER} m",
        ),
        (  # kangaroo_like: a ball, a 6d loop
            "type: [6d]\njoint_name: [spherical_rod]\njoint_type: [SPHERICAL]\n",
            rf"\(fixed\) cannot close in any configuration: .* the centre of joint "
            rf"'spherical_rod' is at height {NUMBER} m along it on its side and {NUMBER} m "
            "through the weld",
        ),
        (
            "type: [6d]\njoint_name: [spherical_rod]\njoint_type: [FIXED]\n",
            rf"\(fixed\) cannot close .* the frames' heights along it differ by {NUMBER} m",
        ),
    ],
)
def test_a_loop_that_cannot_close_is_refused_with_the_proof(tmp_path, rng, extra, message):
    crank_tip, rod_end, rocker_tip = _offset_rod_heights(rng)
    loops = tmp_path / "robot.yaml"
    loops.write_text(OFFSET_ROD_LOOP + extra)
    with pytest.raises(cc.LoopClosureError) as info:
        cc.load(OFFSET_ROD, loops=loops)
    text = str(info.value)
    assert text.startswith(f"{loops}: loop 'rod_end--rocker_tip' ")
    assert text.endswith("; check the loop's type and its joints' types")
    found = re.search(message, text)
    assert found, text
    printed = [float(x) for x in found.groups()]
    expected = {
        3: [rod_end, rod_end, rocker_tip],  # the rod end on the placeholder's axis
        2: [crank_tip, rocker_tip],
        1: [abs(rocker_tip - rod_end)],
    }[len(printed)]
    assert np.max(np.abs(np.subtract(printed, expected))) <= TOL_PRINTED
    assert abs(rocker_tip - rod_end) > TOL_PRINTED  # the file's gap, so the case can fail


def test_an_axis_the_weld_tilts_is_refused_with_the_angles(tmp_path):
    """kangaroo_like's loop 7: a weld after a joint about another axis (angles, not heights)."""
    urdf = tmp_path / "offset_rod.urdf"
    # The rocker tip back in the plane, turned by TILT about z: the rod's axis x, welded
    # to it, would leave the plane y = 0 that mot1 and rocker_pivot keep it in.
    text = OFFSET_ROD.read_text()
    old = '<origin xyz="0.0 0.01 0.2" rpy="0.0 0.0 0.0"/>'
    assert text.count(old) == 1
    urdf.write_text(text.replace(old, f'<origin xyz="0.0 0.0 0.2" rpy="0.0 0.0 {TILT!r}"/>'))
    loops = tmp_path / "robot.yaml"
    loops.write_text(OFFSET_ROD_LOOP + "type: [6d]\n")
    with pytest.raises(cc.LoopClosureError) as info:
        cc.load(urdf, loops=loops)
    found = re.search(
        rf"the angle between it and the axis of joint 'spherical_rod' is {NUMBER} rad on its "
        rf"side and {NUMBER} rad through the weld",
        str(info.value),
    )
    assert found, str(info.value)
    expected = [np.pi / 2, np.pi / 2 - TILT]  # x against y, then x turned by TILT about z
    assert np.max(np.abs(np.subtract([float(x) for x in found.groups()], expected))) <= TOL_PRINTED


#: Turn [rad] of the rocker tip frame in test_an_axis_the_weld_tilts_is_refused_with_the_angles.
TILT = 0.1


# -- hostile YAML files (issue 32): bounded time, memory and messages -----------------------


def alias_bomb(levels: int) -> str:
    """Nested aliases: each level names the previous one 9 times (9^levels strings if
    expanded; 9 levels x 9 aliases)."""
    names = [f"n{i}" for i in range(levels + 1)]
    return (
        f"closed_loop: [&{names[0]} [tip1, tip2], "
        + ", ".join(
            f"&{c} [" + ", ".join([f"*{p}"] * 9) + "]"
            for p, c in zip(names, names[1:], strict=False)
        )
        + "]\ntype: [6d]\n"
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (alias_bomb(12), r"line 1: more than 100 aliases; valid: a loops file$"),
        # 99 aliases pass the bound: the message shows a bounded part of the value.
        (alias_bomb(11), r"closed_loop must be a list of pairs of frame names, got \[\['tip1'"),
        ("closed_loop: " + "[" * 20 + "]" * 20 + "\n", r"line 1: lists or mappings nested deeper"),
        ("closed_loop: " + "[" * 20_000 + "]" * 20_000 + "\n", r"not a YAML file: line 1: "),
        (
            "closed_loop: " + "9" * 4_400 + "\n",
            r"not a YAML file: Exceeds the limit \(4300 digits\)",
        ),
        (FIVEBAR_YAML.replace("tip1", '"tip1\\0"'), r"closed_loop\[0\]\[0\] = 'tip1\\x00' holds"),
        (FIVEBAR_YAML.replace("tip1", '"tip1\\x07"'), r"closed_loop\[0\]\[0\] = 'tip1\\x07' holds"),
        (FIVEBAR_YAML.replace("mot2", '"mot2\\x85"'), r"name_mot\[1\] = 'mot2\\x85' holds"),
        (FIVEBAR_YAML.replace("tip1", '"tip1\\ud800"'), r"not a YAML file: line 1: found invalid"),
        (FIVEBAR_YAML.replace("mot2", "mot1"), r"name_mot\[1\] repeats name_mot\[0\] \('mot1'\)"),
    ],
)
def test_hostile_yaml_is_refused_in_one_line(tmp_path, text, message):
    loops = tmp_path / "robot.yaml"
    loops.write_text(text)
    with pytest.raises(cc.ModelFileError, match=re.escape(f"{loops}: ") + message) as info:
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)
    assert "\n" not in str(info.value) and len(str(info.value)) < MESSAGE_BOUND


#: A message's length bound [characters] (names cut at 80, the path and the text around).
MESSAGE_BOUND = 600


def test_a_lone_surrogate_from_the_pure_python_reader_is_refused(tmp_path, monkeypatch):
    """libyaml refuses the escape; PyYAML's Python reader builds the string, which lxml
    cannot write (UnicodeEncodeError before)."""
    from closedchain import yaml_loops

    monkeypatch.setattr(yaml_loops, "_SAFE_LOADER", yaml_loops.yaml.SafeLoader)
    loops = tmp_path / "robot.yaml"
    loops.write_text(FIVEBAR_YAML.replace("tip1", '"tip1\\ud800"'))
    with pytest.raises(cc.ModelFileError, match=r"closed_loop\[0\]\[0\] = 'tip1\\ud800' holds"):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


@pytest.mark.parametrize("kind", ("fifo", "device", "large"))
def test_a_yaml_file_goes_through_the_input_file_checks(tmp_path, kind):
    """A FIFO blocked, /dev/zero filled the memory, a large file took minutes to parse."""
    from closedchain.yaml_loops import MAX_YAML_BYTES

    loops = tmp_path / "robot.yaml"
    if kind == "fifo":
        os.mkfifo(loops)
        message = "loops file is a named pipe (FIFO); valid: a regular file"
    elif kind == "device":
        loops.symlink_to("/dev/zero")
        message = "loops file is a character device; valid: a regular file"
    else:
        loops.write_text(FIVEBAR_YAML + "#" + "x" * MAX_YAML_BYTES + "\n")
        message = "loops file of 1.049e+06 bytes is larger than the limit of 1.049e+06 bytes"
    with pytest.raises(cc.ModelFileError, match=re.escape(f"{loops}: {message}")):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


#: Names in the long lists below (the quadratic checks took 41 s at this size).
LONG_LIST = 60_000


def test_long_name_lists_are_checked_in_linear_time_with_one_warning(tmp_path, caplog):
    """No timing: the checks are linear (a quadratic one is minutes at this size, which
    the suite's time would show) and the missing joints make one warning line."""
    loops = tmp_path / "robot.yaml"
    names = ", ".join(f"j{i}" for i in range(LONG_LIST))
    fixed = ", ".join(["FIXED"] * LONG_LIST)
    loops.write_text(FIVEBAR_YAML + f"joint_name: [{names}]\njoint_type: [{fixed}]\n")
    with caplog.at_level(logging.WARNING, logger="closedchain.yaml_loops"):
        mech = cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)
    (record,) = caplog.records
    assert record.getMessage().endswith(f"; so are {LONG_LIST - 1} more joint_name entries")
    assert mech.nv == 5
    motors = ", ".join(f"m{i}" for i in range(LONG_LIST))
    loops.write_text(FIVEBAR_YAML.replace("[mot1, mot2]", f"[mot1, mot2, {motors}, m0]"))
    with pytest.raises(
        cc.ModelFileError, match=rf"name_mot\[{LONG_LIST + 2}\] repeats name_mot\[2\]"
    ):
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)


def test_yaml_messages_have_a_real_line_number_or_none(tmp_path):
    """Elements written from a YAML file have no source line: "line None" before."""
    loops = tmp_path / "robot.yaml"
    loops.write_text(FIVEBAR_YAML.replace("tip2", "x" * 5000))
    with pytest.raises(cc.ModelFileError) as info:
        cc.load(DATA_DIR / "yaml_fivebar.urdf", loops=loops)
    message = str(info.value)
    assert "line None" not in message and "xxx...xxx" in message
    assert len(message) < MESSAGE_BOUND * 2
