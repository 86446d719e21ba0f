"""Reading MuJoCo MJCF (closedchain.mjcf): tree, inertias, equalities as loops.

References: models/fourbar.urdf (the same 4-bar, its dynamics checked elsewhere
against the seed's closed forms), Pinocchio's own MJCF reader
(``buildModelAndConstraintsFromMJCF``) for the tree, and
``pin.constraintDynamics`` through ``closedchain.validate`` for the loop.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, MODELS
from lxml import etree

import closedchain as cc
from closedchain.exceptions import URDFError
from closedchain.export.mjcf import export_mjcf

FOURBAR_MJCF = DATA_DIR / "fourbar_mjcf.xml"
GRIPPER = DATA_DIR / "mimic_gripper.urdf"

#: The hand-written 4-bar's qpos0 in fourbar.urdf's coordinates [rad] (its header: the
#: crank at 90 deg, coupler and rocker where the loop closes).
FOURBAR_MJCF_OFFSET = np.radians([90.0, -78.48280264635115, 111.11126558050931])

#: Relative tolerance of accelerations between two readings of one mechanism.
ACCEL_RTOL = 1e-9

#: Tolerance of M and h [SI] between two readers of one tree.
TREE_TOL = 1e-12

N_STATES = 5


@pytest.fixture(scope="module")
def fourbar_mjcf() -> cc.Mechanism:
    return cc.load(FOURBAR_MJCF)


def _same_dynamics(m1: cc.Mechanism, m2: cc.Mechanism, rng, offset=0.0) -> None:
    """Assert equal forward dynamics at random consistent states of m1 (q2 = q1 - offset)."""
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(m1, rng)
        tau = rng.standard_normal(m1.nv)
        a1 = cc.forward_dynamics(m1, q, v, tau, method="kkt").a
        a2 = cc.forward_dynamics(m2, q - offset, v, tau, method="kkt").a
        assert np.linalg.norm(a1 - a2) <= ACCEL_RTOL * np.linalg.norm(a1)


def test_export_round_trip_gives_the_same_dynamics(fourbar, rng, tmp_path):
    path = tmp_path / "fourbar.xml"
    export_mjcf(fourbar, path)
    back = cc.load(path)
    assert back.coordinate_names == fourbar.coordinate_names
    assert back.mobility == fourbar.mobility
    np.testing.assert_array_equal(back.gravity, fourbar.gravity)
    # The revolute loop comes back as two connects on its axis (6 rows of rank 2).
    assert [s.type for s in back.urdf.loops] == ["spherical", "spherical"]
    _same_dynamics(fourbar, back, rng)


def test_export_round_trip_keeps_couplings(rng, tmp_path):
    gripper = cc.load(GRIPPER)
    path = tmp_path / "gripper.xml"
    export_mjcf(gripper, path)
    back = cc.load(path)
    coupled = {(s.joint, s.mimics, s.multiplier, s.offset) for s in back.urdf.loops}
    assert coupled == {(s.joint, s.mimics, s.multiplier, s.offset) for s in gripper.urdf.loops}
    _same_dynamics(gripper, back, rng)


def test_hand_written_fourbar_reads_as_the_urdf_one(fourbar_mjcf, fourbar, rng):
    assert (fourbar_mjcf.nq, fourbar_mjcf.nv, fourbar_mjcf.mobility) == (3, 3, 1)
    assert fourbar_mjcf.actuated_joints == ("crank_joint",)  # from <actuator><motor joint>
    np.testing.assert_array_equal(fourbar_mjcf.gravity, [0.0, 0.0, -9.81])
    (loop,) = fourbar_mjcf.urdf.loops
    assert (loop.type, loop.predecessor, loop.successor) == ("spherical", "coupler", "rocker")
    _same_dynamics(fourbar, fourbar_mjcf, rng, offset=FOURBAR_MJCF_OFFSET)


def test_hand_written_fourbar_tree_matches_pinocchio_mjcf_reader(fourbar_mjcf, rng):
    model, *_ = pin.buildModelAndConstraintsFromMJCF(str(FOURBAR_MJCF))
    model.gravity.linear = fourbar_mjcf.gravity
    assert list(model.names) == list(fourbar_mjcf.model.names)
    data, ours = model.createData(), fourbar_mjcf.model.createData()
    for _ in range(N_STATES):
        q = rng.uniform(-math.pi, math.pi, model.nq)
        v = rng.standard_normal(model.nv)
        M1 = pin.crba(model, data, q)
        M2 = pin.crba(fourbar_mjcf.model, ours, q)
        assert np.linalg.norm(np.triu(M1) - np.triu(M2)) <= TREE_TOL
        h1 = pin.nonLinearEffects(model, data, q, v)
        h2 = pin.nonLinearEffects(fourbar_mjcf.model, ours, q, v)
        assert np.linalg.norm(h1 - h2) <= TREE_TOL


def test_hand_written_fourbar_validates_and_simulates(fourbar_mjcf):
    report = cc.validate(fourbar_mjcf, n_samples=10)
    assert report.passed, report
    traj = cc.simulate(fourbar_mjcf, fourbar_mjcf.q_ref, np.zeros(3), 0.5)
    assert traj.info.max_constraint_residual <= 1e-9
    assert np.ptp(traj.q[:, 0]) > 1e-2  # gravity moved it


def _edit(tmp_path, edit) -> cc.Mechanism:
    """Load the hand-written 4-bar after ``edit(root)`` changed its parsed tree."""
    root = etree.parse(str(FOURBAR_MJCF)).getroot()
    edit(root)
    path = tmp_path / "edited.xml"
    path.write_bytes(etree.tostring(root))
    return path


def test_sibling_root_bodies_are_kept(fourbar_mjcf, tmp_path, rng):
    """Crank and rocker hinged straight to <worldbody> (Pinocchio's reader keeps the first)."""

    def unwrap(root):
        world = root.find("worldbody")
        ground = world.find("body")
        for body in ground.findall("body"):
            world.append(body)
        world.remove(ground)

    mech = cc.load(_edit(tmp_path, unwrap))
    assert mech.nv == 3
    _same_dynamics(fourbar_mjcf, mech, rng)


def test_option_gravity_is_read_and_an_argument_overrides_it(tmp_path):
    path = _edit(tmp_path, lambda root: root.find("option").set("gravity", "0 0 -1.62"))
    np.testing.assert_array_equal(cc.load(path).gravity, [0.0, 0.0, -1.62])
    np.testing.assert_array_equal(cc.load(path, gravity=(0, 0, -9.81)).gravity, [0, 0, -9.81])


def test_weld_becomes_a_fixed_loop_closed_at_qpos0(tmp_path):
    def weld(root):
        eq = root.find("equality")
        eq.remove(eq.find("connect"))
        etree.SubElement(eq, "weld", name="W", body1="coupler", body2="rocker")

    mech = cc.load(_edit(tmp_path, weld))
    (loop,) = mech.urdf.loops
    assert loop.type == "fixed"
    assert mech.mobility == 0
    assert np.linalg.norm(cc.compute_phi(mech, np.zeros(3))) <= 1e-12


#: A body's mass and inertia, for the bodies of the refused inputs below.
INERTIAL = '<inertial mass="1" diaginertia="1 1 1"/>'


@pytest.mark.parametrize(
    ("xml", "match"),
    [
        (
            f'<body name="b"><joint type="ball"/>{INERTIAL}</body>',
            r"<joint>: ball joints are not supported .*valid: hinge, slide, free",
        ),
        (
            f'<body name="b"><body name="c"><freejoint/>{INERTIAL}</body></body>',
            r"<freejoint>: a free joint must be the only joint of a top-level body",
        ),
        (
            f'<body name="b"><joint name="j" ref="0.3"/>{INERTIAL}</body>',
            r"<joint name='j'>: ref= other than 0 is not supported",
        ),
        (
            '<body name="b"><joint name="j"/><geom size="0.1"/></body>',
            r"<body name='b'>: has joints and geoms but no <inertial>",
        ),
        (f'<body name="b" quat="0 0 0 0"><joint name="j"/>{INERTIAL}</body>', r"quat is zero"),
        ('<body name="b"><geom size="big"/></body>', r"<geom>: size='big' must be 1 to 3"),
    ],
)
def test_bad_bodies_are_refused(tmp_path, xml, match):
    path = tmp_path / "bad.xml"
    path.write_text(f"<mujoco><worldbody>{xml}</worldbody></mujoco>")
    with pytest.raises(URDFError, match=match):
        cc.load(path)


@pytest.mark.parametrize(
    ("equality", "match"),
    [
        (
            '<joint joint1="coupler_joint" joint2="crank_joint" polycoef="0 1 0.5 0 0"/>',
            r"only a linear coupling q1 = c0 \+ c1 q2 is supported; valid: c2 = c3 = c4 = 0",
        ),
        (
            '<joint joint1="coupler_joint"/>',
            r"a joint equality without joint2 \(a locked joint\) is not supported",
        ),
        (
            '<connect body1="coupler" body2="wheel" anchor="0 0 0"/>',
            r"body2='wheel' names no body; bodies: coupler, crank, ground, rocker, world",
        ),
        ('<tendon tendon1="t"/>', r"equality type <tendon> is not supported; valid: connect"),
    ],
)
def test_bad_equalities_are_refused(tmp_path, equality, match):
    def replace(root):
        eq = root.find("equality")
        eq.remove(eq.find("connect"))
        eq.append(etree.fromstring(equality))

    with pytest.raises(URDFError, match=match):
        cc.load(_edit(tmp_path, replace))


def test_defaults_that_change_the_mechanism_are_refused(tmp_path):
    def default(root):
        root.insert(0, etree.fromstring('<default><joint damping="1"/></default>'))

    with pytest.raises(URDFError, match=r"a <default> <joint> would change the mechanism"):
        cc.load(_edit(tmp_path, default))


def test_doctype_is_refused(tmp_path):
    path = tmp_path / "dtd.xml"
    path.write_text('<!DOCTYPE m [<!ENTITY e "x">]><mujoco><worldbody/></mujoco>')
    with pytest.raises(URDFError, match="DOCTYPE"):
        cc.load(path)


def test_unknown_models_stay_urdf(tmp_path):
    """A URDF file ending in .xml is still read as URDF (the root element decides)."""
    path = tmp_path / "fourbar.xml"
    path.write_bytes((MODELS / "fourbar.urdf").read_bytes())
    assert cc.load(path).urdf.loops[0].type == "revolute"


def test_free_joint_is_the_free_flyer_root(tmp_path, rng):
    """A <freejoint> on the top-level body is Pinocchio's free flyer: the same dynamics as
    ``root_joint="free"`` on the fixed-base file (the ground given a mass for both)."""

    def ground_mass(root):
        ground = root.find("worldbody/body")
        ground.insert(0, etree.fromstring('<inertial mass="2" diaginertia="0.1 0.2 0.3"/>'))

    fixed = cc.load(_edit(tmp_path, ground_mass), root_joint="free")

    def free(root):
        ground_mass(root)
        root.find("worldbody/body").insert(0, etree.Element("freejoint", name="base"))

    floating = cc.load(_edit(tmp_path, free))
    assert floating.model.joints[1].shortname() == "JointModelFreeFlyer"
    assert (floating.nq, floating.nv) == (fixed.nq, fixed.nv) == (10, 9)
    _same_dynamics(fixed, floating, rng)


def test_passive_joint_terms_are_logged_as_ignored(tmp_path, caplog):
    def damped(root):
        root.find(".//joint[@name='crank_joint']").set("damping", "0.5")

    with caplog.at_level("WARNING", logger="closedchain.mjcf"):
        cc.load(_edit(tmp_path, damped))
    assert "damping=0.5 ignored" in caplog.text


def test_several_joints_in_one_body_match_pinocchio_composite_joint(tmp_path, rng):
    """Two hinges at different ``pos`` in one body: a chain through a massless link here,
    a composite joint in Pinocchio's MJCF reader; the same M and h."""
    path = tmp_path / "two_hinges.xml"
    path.write_text(
        '<mujoco><compiler angle="radian"/><worldbody><body name="b" pos="0 0 1">'
        '<joint name="j1" axis="1 0 0" pos="0 0 0.1"/><joint name="j2" axis="0 1 0" '
        'pos="0 0 0.2"/><inertial pos="0.1 0 -0.3" mass="1" diaginertia="0.01 0.02 0.03"/>'
        "</body></worldbody></mujoco>"
    )
    mech = cc.load(path)
    assert mech.joint_names == ("j1", "j2")
    model = pin.buildModelFromMJCF(str(path))
    model.gravity.linear = mech.gravity
    assert model.njoints == 2  # one composite joint
    data, ours = model.createData(), mech.model.createData()
    for _ in range(N_STATES):
        q, v = rng.uniform(-math.pi, math.pi, 2), rng.standard_normal(2)
        M1, M2 = pin.crba(model, data, q), pin.crba(mech.model, ours, q)
        assert np.linalg.norm(np.triu(M1) - np.triu(M2)) <= TREE_TOL
        h1 = pin.nonLinearEffects(model, data, q, v)
        assert np.linalg.norm(h1 - pin.nonLinearEffects(mech.model, ours, q, v)) <= TREE_TOL
