"""Reading MuJoCo MJCF (closedchain.mjcf) through MuJoCo's compiler.

References: MuJoCo's own compiled arrays and dynamics of the same files
(M from ``mj_fullM``, body and site poses at qpos0, ``qacc`` with stiff
equalities, and a rigid KKT solve from MuJoCo's M, bias forces and equality
Jacobian: closedchain.mjcf_reference), models/fourbar.urdf (the same 4-bar,
its dynamics checked elsewhere against the lesson's closed forms), Pinocchio's
own MJCF reader (``buildModelAndConstraintsFromMJCF``) for trees, and
``pin.constraintDynamics`` through ``closedchain.validate`` for the loop.
The models of tests/data/mjcf carry the features of the public models
(defaults and classes through an include, childclass, frame, inertia from
geoms, sites placed by classes and fromto, ball and free joints, joint ref,
polycoef "0 3", torquescale 0, an inactive equality, keyframes; passive.xml:
armature, damping and springs through classes). The models compared with
MuJoCo's dynamics have no passive terms, so that the comparisons hold whether
closedchain's dynamics apply them or not.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, MODELS
from lxml import etree

import closedchain as cc
from closedchain.exceptions import ModelFileError
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
    assert [s.type for s in back.description.loops] == ["spherical", "spherical"]
    _same_dynamics(fourbar, back, rng)


def test_export_round_trip_keeps_couplings(rng, tmp_path):
    gripper = cc.load(GRIPPER)
    path = tmp_path / "gripper.xml"
    export_mjcf(gripper, path)
    back = cc.load(path)
    coupled = {(s.joint, s.mimics, s.multiplier, s.offset) for s in back.description.loops}
    assert coupled == {
        (s.joint, s.mimics, s.multiplier, s.offset) for s in gripper.description.loops
    }
    _same_dynamics(gripper, back, rng)


def test_hand_written_fourbar_reads_as_the_urdf_one(fourbar_mjcf, fourbar, rng):
    assert (fourbar_mjcf.nq, fourbar_mjcf.nv, fourbar_mjcf.mobility) == (3, 3, 1)
    assert fourbar_mjcf.actuated_joints == ("crank_joint",)  # from <actuator><motor joint>
    np.testing.assert_array_equal(fourbar_mjcf.gravity, [0.0, 0.0, -9.81])
    (loop,) = fourbar_mjcf.description.loops
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
    (loop,) = mech.description.loops
    assert loop.type == "fixed"
    assert mech.mobility == 0
    assert np.linalg.norm(cc.compute_phi(mech, np.zeros(3))) <= 1e-12


def test_doctype_is_refused(tmp_path):
    path = tmp_path / "dtd.xml"
    path.write_text('<!DOCTYPE m [<!ENTITY e "x">]><mujoco><worldbody/></mujoco>')
    with pytest.raises(ModelFileError, match="DOCTYPE"):
        cc.load(path)


def test_unknown_models_stay_urdf(tmp_path):
    """A URDF file ending in .xml is still read as URDF (the root element decides)."""
    path = tmp_path / "fourbar.xml"
    path.write_bytes((MODELS / "fourbar.urdf").read_bytes())
    assert cc.load(path).description.loops[0].type == "revolute"


def test_free_joint_is_the_free_flyer_root(tmp_path, rng):
    """A <freejoint> on the top-level body is Pinocchio's free flyer: the same dynamics as
    ``root_joint="free"`` on the fixed-base file (the ground given a mass for both)."""

    def ground_mass(root):
        ground = root.find("worldbody/body")
        ground.insert(
            0, etree.fromstring('<inertial pos="0 0 0" mass="2" diaginertia="0.1 0.2 0.3"/>')
        )

    fixed = cc.load(_edit(tmp_path, ground_mass), root_joint="free")

    def free(root):
        ground_mass(root)
        root.find("worldbody/body").insert(0, etree.Element("freejoint", name="base"))

    floating = cc.load(_edit(tmp_path, free))
    assert floating.model.joints[1].shortname() == "JointModelFreeFlyer"
    assert (floating.nq, floating.nv) == (fixed.nq, fixed.nv) == (10, 9)
    _same_dynamics(fixed, floating, rng)


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


# -- against MuJoCo's own compiled model ------------------------------------------------

MJCF_DIR = DATA_DIR / "mjcf"
LINKAGE = MJCF_DIR / "linkage.xml"
FLOATING = MJCF_DIR / "floating.xml"
TREE = MJCF_DIR / "tree.xml"
PASSIVE = MJCF_DIR / "passive.xml"
COMPARED = [LINKAGE, FLOATING, FOURBAR_MJCF, TREE]

#: Tolerance [SI] of M, body and site poses between closedchain's model and MuJoCo's
#: (both compiled from one file; MuJoCo stores inertias in double).
MUJOCO_TREE_TOL = 1e-12

#: Relative tolerance of accelerations against MuJoCo's own answer with its equalities in
#: the rigid limit (mjcf_reference: solimp at MuJoCo's cap, its regulariser scaled by
#: RIGID_LIMIT_SCALE = 1e-8, so R = 1e-12 of its approximate diagonal; measured <= 4e-11
#: on these models, the rest is the conditioning of MuJoCo's Newton step).
LIMIT_RTOL = 1e-7

#: Relative tolerance against the rigid KKT solve built from MuJoCo's M, bias and
#: equality rows (its J-dot v by central differences: mjcf_reference.JDOT_STEP).
RIGID_RTOL = 1e-9

#: Distance [rad] of q_ref from a key that closes the loop exactly (the assembly's tolerance
#: and the file's 17 digits).
KEYFRAME_TOL = 1e-8


@pytest.fixture(scope="module", params=COMPARED, ids=lambda p: p.stem)
def compared(request):
    from closedchain.mjcf_reference import mujoco_model

    mech = cc.load(request.param)
    return mech, mujoco_model(request.param, mech.model)


def test_mass_matrix_matches_mujoco(compared, rng):
    """M at random configurations (armature zeroed in MuJoCo's spec: the tree alone)."""
    from closedchain.mjcf_reference import mujoco_mass_matrix

    mech, ref = compared
    for _ in range(N_STATES):
        q = pin.randomConfiguration(mech.model, -np.ones(mech.nq), np.ones(mech.nq))
        M = pin.crba(mech.model, mech.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        tol = MUJOCO_TREE_TOL * max(1.0, np.linalg.norm(M))
        assert np.linalg.norm(mujoco_mass_matrix(ref, q) - M) <= tol


def test_bodies_and_sites_at_qpos0_match_mujoco(compared):
    import mujoco

    from closedchain.build import configuration

    mech, ref = compared
    m, d = ref.mj, ref.data
    d.qpos[:] = m.qpos0
    mujoco.mj_forward(m, d)
    q0 = configuration(mech.model, mech.description.tree.reference_values())
    pin.framesForwardKinematics(mech.model, mech.data, q0)
    for b in range(1, m.nbody):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
        oMb = mech.data.oMf[mech.model.getFrameId(name, pin.FrameType.BODY)]
        assert np.linalg.norm(oMb.translation - d.xpos[b]) <= MUJOCO_TREE_TOL, name
        assert np.linalg.norm(oMb.rotation - d.xmat[b].reshape(3, 3)) <= MUJOCO_TREE_TOL, name
    for s in range(m.nsite):
        name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, s)
        oMs = mech.data.oMf[mech.model.getFrameId(name, pin.FrameType.OP_FRAME)]
        assert np.linalg.norm(oMs.translation - d.site_xpos[s]) <= MUJOCO_TREE_TOL, name
        assert np.linalg.norm(oMs.rotation - d.site_xmat[s].reshape(3, 3)) <= MUJOCO_TREE_TOL


def test_accelerations_match_mujoco(compared, rng):
    """Closed random states: MuJoCo's qacc with its equalities in the rigid limit (contacts
    and limits off) to LIMIT_RTOL, and the rigid KKT solve from MuJoCo's own arrays to
    RIGID_RTOL."""
    from closedchain.mjcf_reference import mujoco_accelerations, to_mujoco

    mech, ref = compared
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a = cc.forward_dynamics(mech, q, v, tau, method="kkt").a
        a_mj = to_mujoco(ref, q, v, a)[2]
        limit, rigid, _ = mujoco_accelerations(ref, q, v, tau)
        assert np.linalg.norm(a_mj - limit) <= LIMIT_RTOL * np.linalg.norm(limit)
        assert np.linalg.norm(a_mj - rigid) <= RIGID_RTOL * np.linalg.norm(rigid)


def test_tree_matches_pinocchio_mjcf_reader(rng):
    """The builder against Pinocchio's own MJCF reader on a tree in one root body."""
    mech = cc.load(TREE)
    model, *_ = pin.buildModelAndConstraintsFromMJCF(str(TREE))
    model.gravity.linear = mech.gravity
    assert (model.nq, model.nv) == (mech.nq, mech.nv)
    data = model.createData()
    for _ in range(N_STATES):
        q = pin.randomConfiguration(mech.model, -np.ones(mech.nq), np.ones(mech.nq))
        v = rng.standard_normal(mech.nv)
        M1, M2 = pin.crba(model, data, q), pin.crba(mech.model, mech.data, q)
        assert np.linalg.norm(np.triu(M1) - np.triu(M2)) <= TREE_TOL
        h1 = pin.nonLinearEffects(model, data, q, v)
        assert np.linalg.norm(h1 - pin.nonLinearEffects(mech.model, mech.data, q, v)) <= TREE_TOL


def test_equalities_become_loops_by_mujocos_rules(caplog):
    with caplog.at_level("INFO", logger="closedchain.mjcf"):
        mech = cc.load(LINKAGE)
    loops = {s.name: s for s in mech.description.loops}
    assert {n: s.type for n, s in loops.items()} == {
        "fourbar_loop": "spherical",  # connect of two sites
        "rod_end": "spherical",
        "gears": "coupling",
        "tip_pin": "spherical",  # weld with torquescale 0: a point constraint
    }
    gears = loops["gears"]
    # polycoef "0 3" padded with zeros; MuJoCo's polynomial is in q - ref (gear2: 10 deg).
    assert (gears.joint, gears.mimics, gears.multiplier) == ("gear1_joint", "gear2_joint", 3.0)
    assert gears.offset == pytest.approx(-3.0 * math.radians(10.0), abs=1e-15)
    assert mech.summary()["inactive_equalities"] == ["connect spare"]
    assert "inactive equalities (eq_active0 = 0), kept out of the loops: connect spare" in (
        caplog.text
    )
    assert mech.actuated_joints == ("crank_joint", "wheel_joint", "gear1_joint")


#: A weld's torquescale other than 0 and 1 (MuJoCo's test model weld.xml has 0.002).
SCALED_WELD = 0.002

#: Relative tolerance of accelerations against MuJoCo's rigid limit with that weld: MuJoCo
#: scales the weld's rotation rows by the torquescale, its regulariser's diagonal does not
#: see the scale, so those rows keep R = RIGID_LIMIT_SCALE * 1e-4 / torquescale^2 = 2.5e-7
#: of their diagonal (measured 9.4e-8); ten times that.
SCALED_WELD_RTOL = 10 * 1e-8 * 1e-4 / SCALED_WELD**2


def test_other_torquescale_is_a_rigid_weld_with_a_note(caplog, rng):
    """A weld with torquescale 0.002 is held rigidly: MuJoCo's rigid limit agrees (its
    scaled rotation rows hold the same constraint), and so does the rigid KKT solve."""
    from closedchain.mjcf_reference import (
        RIGID_LIMIT_SCALE,
        mujoco_accelerations,
        mujoco_model,
        to_mujoco,
    )

    assert RIGID_LIMIT_SCALE == 1e-8  # SCALED_WELD_RTOL's derivation
    text = LINKAGE.read_text().replace('torquescale="0"', f'torquescale="{SCALED_WELD}"')
    path = MJCF_DIR / "_torquescale.xml"  # beside its include
    path.write_text(text)
    try:
        with caplog.at_level("INFO", logger="closedchain.mjcf"):
            mech = cc.load(path)
        ref = mujoco_model(path, mech.model)
    finally:
        path.unlink()
    assert next(s for s in mech.description.loops if s.name == "tip_pin").type == "fixed"
    assert f"torquescale={SCALED_WELD:g} weights MuJoCo's soft rotation rows" in caplog.text
    for _ in range(N_STATES):
        q, v = cc.random_consistent_state(mech, rng)
        tau = rng.standard_normal(mech.nv)
        a = to_mujoco(ref, q, v, cc.forward_dynamics(mech, q, v, tau, method="kkt").a)[2]
        limit, rigid, _ = mujoco_accelerations(ref, q, v, tau)
        assert np.linalg.norm(a - limit) <= SCALED_WELD_RTOL * np.linalg.norm(limit)
        assert np.linalg.norm(a - rigid) <= RIGID_RTOL * np.linalg.norm(rigid)


def test_passive_terms_are_read(caplog):
    """Armature, damping and springs given through classes; MuJoCo's M with its armature
    equals Pinocchio's with model.armature set from what was read."""
    from closedchain.mjcf_reference import mujoco_mass_matrix, mujoco_model

    with caplog.at_level("INFO", logger="closedchain.mjcf"):
        mech = cc.load(PASSIVE)
    urdf = mech.description
    motors = ["a_joint", "b_ball", "c_slide"]  # class "motor" and its child "spring"
    assert [(a.joint, a.armature) for a in urdf.armatures] == [(j, 0.01) for j in motors]
    assert [(d.joint, d.damping) for d in urdf.dampings] == [(j, 0.1) for j in motors]
    assert [(s.joint, s.stiffness, s.reference) for s in urdf.springs] == [("c_slide", 50.0, 0.02)]
    assert "friction loss (frictionloss) is not modelled: b_ball" in caplog.text
    model = pin.Model(mech.model)
    for a in urdf.armatures:
        model.armature[mech.joint_indices_v(a.joint)] = a.armature
    ref = mujoco_model(PASSIVE, mech.model, rigid=False)
    q = pin.randomConfiguration(mech.model, -np.ones(mech.nq), np.ones(mech.nq))
    M = pin.crba(model, model.createData(), q)
    assert np.linalg.norm(np.triu(M) - np.triu(mujoco_mass_matrix(ref, q))) <= MUJOCO_TREE_TOL


def _mirrored_fourbar() -> np.ndarray:
    """The hand-written 4-bar's other assembly at the same crank angle [rad].

    The coupler and rocker mirrored across the line from the crank's tip C to the rocker's
    pivot R (from MuJoCo's poses at qpos0): each turns by twice the angle between that
    line and its own direction (angles about -y, the joints' axis, are atan2(z, x)).
    """
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(FOURBAR_MJCF))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    coupler = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "coupler")
    C = d.xpos[coupler]
    D = C + 0.4 * d.xmat[coupler].reshape(3, 3)[:, 0]  # the connect's anchor
    R = d.xanchor[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "rocker_joint")]

    def angle(u):
        return math.atan2(u[2], u[0])

    phi = angle(R - C)
    turn = [2.0 * (phi - angle(D - C)), 2.0 * (phi - angle(D - R))]
    return np.array([0.0, *(math.remainder(t, 2.0 * math.pi) for t in turn)])


def test_assembly_starts_from_a_keyframe(tmp_path):
    """Keys on the 4-bar's two assemblies: the first key, else the named one, is closed."""
    mirrored, drawn = _mirrored_fourbar(), np.zeros(3)

    def keys(root):
        frames = etree.SubElement(root, "keyframe")
        for name, q in (("elbow_down", mirrored), ("elbow_up", drawn)):
            etree.SubElement(frames, "key", name=name, qpos=" ".join(repr(float(x)) for x in q))

    path = _edit(tmp_path, keys)
    assert np.linalg.norm(mirrored - drawn) > 1.0  # two distinct assemblies
    for keyframe, q_key in ((None, mirrored), ("elbow_down", mirrored), ("elbow_up", drawn)):
        mech = cc.load(path, keyframe=keyframe)
        assert np.linalg.norm(mech.q_ref - q_key) <= KEYFRAME_TOL, keyframe
    with pytest.raises(
        ModelFileError, match=r"unknown keyframe 'side'; keyframes: elbow_down, elbow_up"
    ):
        cc.load(path, keyframe="side")
    with pytest.raises(ModelFileError, match=r"keyframe='up' is for MJCF models"):
        cc.load(MODELS / "fourbar.urdf", keyframe="up")


def test_floating_model_starts_from_its_keyframe():
    """Its key "crouch" closes the loop (see the file): q_ref is that key, not qpos0."""
    import mujoco

    from closedchain.mjcf_reference import mujoco_model, pin_configuration

    mech = cc.load(FLOATING)
    ref = mujoco_model(FLOATING, mech.model)
    key = pin_configuration(ref, mech.model, ref.mj.key_qpos[0])
    assert mujoco.mj_id2name(ref.mj, mujoco.mjtObj.mjOBJ_KEY, 0) == "crouch"
    assert np.linalg.norm(mech.q_ref - key) <= KEYFRAME_TOL


def test_missing_meshes(tmp_path, caplog):
    """A missing mesh is left out where the body's inertia is explicit, else refused."""
    body = (
        '<mujoco><asset><mesh name="m" file="gone.stl"/></asset><worldbody>'
        '<body name="b"><joint name="j"/>{}<geom type="mesh" mesh="m"/>'
        '<geom type="sphere" size="0.1" pos="0 0 -0.3"/></body></worldbody></mujoco>'
    )
    path = tmp_path / "meshes.xml"
    path.write_text(body.format('<inertial pos="0 0 -0.3" mass="1" diaginertia="1 1 1"/>'))
    with caplog.at_level("WARNING", logger="closedchain.mjcf"):
        mech = cc.load(path)
    assert "mesh files missing" in caplog.text and "gone.stl" in caplog.text
    assert mech.model.inertias[1].mass == 1.0
    path.write_text(body.format(""))
    with pytest.raises(ModelFileError, match=r"mesh file 'gone.stl' is missing, and MuJoCo infers"):
        cc.load(path)


@pytest.mark.parametrize(
    ("equality", "match"),
    [
        (
            '<joint joint1="coupler_joint" joint2="crank_joint" polycoef="0 1 0.5"/>',
            r"polycoef 0 1 0.5 0 0: only a linear coupling q1 = c0 \+ c1 q2 is read; "
            r"valid: c2 = c3 = c4 = 0",
        ),
        ('<joint joint1="coupler_joint"/>', r"a joint equality without joint2 locks joint"),
        (
            '<joint joint1="coupler_joint" joint2="crank_joint" polycoef="0 1e300"/>',
            r"polycoef c1 = 1e\+300, .* beyond the bounds; valid: \|c1\| <= 1e\+06",
        ),
        (
            '<connect body1="coupler" body2="wheel" anchor="0 0 0"/>',
            r"MuJoCo cannot compile it: .*unknown element 'wheel'",
        ),
    ],
)
def test_bad_equalities_are_refused(tmp_path, equality, match):
    def replace(root):
        eq = root.find("equality")
        eq.remove(eq.find("connect"))
        eq.append(etree.fromstring(equality))

    with pytest.raises(ModelFileError, match=match):
        cc.load(_edit(tmp_path, replace))


def test_include_outside_the_models_folder_is_refused(tmp_path):
    (tmp_path / "model").mkdir()
    (tmp_path / "outside.xml").write_text("<mujoco/>")
    path = tmp_path / "model" / "m.xml"
    path.write_text('<mujoco><include file="../outside.xml"/><worldbody/></mujoco>')
    with pytest.raises(
        ModelFileError, match=r"<include file='../outside.xml'> is outside the model"
    ):
        cc.load(path)


def test_without_mujoco_one_line_names_what_to_install(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mujoco", None)
    with pytest.raises(ModelFileError, match=r"needs MuJoCo's compiler: pip install mujoco"):
        cc.load(FOURBAR_MJCF)


def test_overlays_are_refused_on_mjcf(tmp_path):
    overlay = tmp_path / "loops.urdf"
    overlay.write_text('<robot name="x"/>')
    with pytest.raises(ModelFileError, match=r"an MJCF model takes its loops from its <equality>"):
        cc.load(FOURBAR_MJCF, loops=overlay)


#: Tolerance [m] of mesh vertices against MuJoCo's compiled ones (stored in float32).
MESH_VERTEX_TOL = 1e-6


def test_mesh_visuals_sit_where_mujoco_puts_them(tmp_path):
    """A mesh geom (scaled, posed; MuJoCo recentres the mesh and moves the geom) is drawn
    from its file: the file's vertices, scaled and placed, are MuJoCo's compiled ones."""
    import mujoco
    import trimesh

    from closedchain.visualize.shapes import read_visuals

    box = trimesh.creation.box(extents=[0.1, 0.2, 0.3])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.3, [1, 1, 0]))
    box.apply_translation([0.1, 0.2, 0.3])
    (tmp_path / "assets").mkdir()
    box.export(tmp_path / "assets" / "part.obj")
    path = tmp_path / "mesh.xml"
    path.write_text(
        '<mujoco><compiler meshdir="assets"/><asset><mesh name="part" file="part.obj" '
        'scale="2 1 0.5"/></asset><worldbody><body name="b" pos="0 0 1"><joint name="j"/>'
        '<geom type="mesh" mesh="part" pos="0.1 0 0" euler="10 20 30"/>'
        '<geom type="capsule" size="0.02 0.1"/></body></worldbody></mujoco>'
    )
    mech = cc.load(path)
    (shape,) = [v for v in read_visuals(mech) if v.kind == "mesh"]
    assert shape.link == "b" and shape.mesh == (tmp_path / "assets" / "part.obj").resolve()
    drawn = (shape.origin[:3, :3] @ (np.asarray(shape.dims) * box.vertices).T).T
    drawn += shape.origin[:3, 3]
    m = mujoco.MjModel.from_xml_path(str(path))
    g = int(np.flatnonzero(m.geom_type == mujoco.mjtGeom.mjGEOM_MESH)[0])
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, m.geom_quat[g])
    compiled = m.mesh_vert[m.mesh_vertadr[0] : m.mesh_vertadr[0] + m.mesh_vertnum[0]]
    expected = compiled @ R.reshape(3, 3).T + m.geom_pos[g]
    assert np.linalg.norm(np.sort(drawn, axis=0) - np.sort(expected, axis=0)) <= MESH_VERTEX_TOL
    # The capsule: its cylinder and two end spheres.
    assert sorted(v.kind for v in read_visuals(mech) if v.kind != "mesh" and v.link == "b") == [
        "cylinder", "sphere", "sphere"
    ]  # fmt: skip


def test_linkage_simulates_and_animates(tmp_path):
    mech = cc.load(LINKAGE)
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), 0.2)
    assert traj.info.max_constraint_residual <= 1e-9
    page = cc.write_html(mech, traj, tmp_path / "linkage.html")
    assert (tmp_path / "linkage.html").stat().st_size > 0
    assert page.meshes.n_embedded == 0
