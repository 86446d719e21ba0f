"""Tests of closedchain.export.mjcf: the MJCF tree, inertias and loops against Pinocchio.

Independent references: Pinocchio's model (masses, tree, joint count) and the exact
constrained accelerations of closedchain's ``kkt`` method (itself validated against
``pinocchio.constraintDynamics``). MuJoCo enforces equalities softly, so its
accelerations match only to the accuracy its solref/solimp allow.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

import closedchain as cc
from closedchain import cli

mujoco = pytest.importorskip("mujoco", reason="MuJoCo export tests need `pip install mujoco`")

from closedchain.export.mjcf import STIFF, MjcfSettings, export_mjcf, load_mujoco, mujoco_state  # noqa: E402

#: Relative acceleration error of the stiff export at a regular state (measured:
#: 3.4e-6 on the 4-bar, 3.6e-4 on the Agile Eye, 1e-8..1e-5 on the test mechanisms).
STIFF_ACCEL_RTOL = {"fourbar": 2e-5, "agile_eye": 1e-3, "spherical_chain": 1e-3}
#: The default (soft) equalities are visibly soft on the 4-bar (measured 3.7e-3).
DEFAULT_SOFTNESS_MIN = 1e-4
#: Masses and inertias are copied: round-off [kg, kg m^2].
MASS_TOL = 1e-12
INERTIA_TOL = 1e-10

EXPORTABLE = ["fourbar", "agile_eye", "spherical_chain", "fixed_branches"]


def _accelerations(mech, settings, rng):
    q, v = cc.random_consistent_state(mech, rng)
    a = cc.forward_dynamics(mech, q, v, np.zeros(mech.nv), method="kkt").a
    m, d = load_mujoco(mech, settings=settings)
    d.qpos[:], d.qvel[:] = mujoco_state(mech, q, v)
    mujoco.mj_forward(m, d)
    return np.linalg.norm(d.qacc - a) / np.linalg.norm(a)


@pytest.mark.parametrize("name", sorted(STIFF_ACCEL_RTOL))
def test_stiff_export_reproduces_accelerations(load_mechanism, name, rng):
    mech = load_mechanism(name)
    err = _accelerations(mech, STIFF, rng)
    assert err < STIFF_ACCEL_RTOL[name]


def test_default_export_is_soft(fourbar, rng):
    err = _accelerations(fourbar, MjcfSettings(), rng)
    stiff = _accelerations(fourbar, STIFF, np.random.default_rng(20251121))
    assert err > DEFAULT_SOFTNESS_MIN
    assert stiff < err


@pytest.mark.parametrize("name", EXPORTABLE)
def test_tree_masses_and_inertias_match_pinocchio(load_mechanism, name):
    mech = load_mechanism(name)
    model = mech.model
    m, _ = load_mujoco(mech)
    assert m.nbody == model.njoints  # world + one body per joint
    assert m.nv == model.nv
    for j in range(1, model.njoints):
        body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, model.names[j])
        parent = model.parents[j]
        expected_parent = (
            0
            if parent == 0
            else mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, model.names[parent])
        )
        assert m.body_parentid[body] == expected_parent
        inertia = model.inertias[j]
        if inertia.mass < STIFF.min_mass:
            continue
        assert abs(m.body_mass[body] - inertia.mass) < MASS_TOL
        np.testing.assert_allclose(m.body_ipos[body], inertia.lever, atol=MASS_TOL)
        # Rebuild the rotational inertia about the CoM from MuJoCo's principal form.
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, m.body_iquat[body])
        R = R.reshape(3, 3)
        rebuilt = R @ np.diag(m.body_inertia[body]) @ R.T
        np.testing.assert_allclose(rebuilt, inertia.inertia, atol=INERTIA_TOL)


def test_loops_become_equalities(fourbar, agile_eye):
    m, _ = load_mujoco(fourbar)
    assert m.neq == 2  # one revolute loop: two connects along the axis
    assert {int(t) for t in m.eq_type} == {int(mujoco.mjtEq.mjEQ_CONNECT)}
    m, _ = load_mujoco(agile_eye)
    assert m.neq == 6


def test_prismatic_loop_raises(load_mechanism):
    with pytest.raises(cc.ClosedChainError, match="prismatic.*valid loop types"):
        export_mjcf(load_mechanism("slider_crank"))


def test_cli_export_mjcf(tmp_path, mechanism_files):
    out = tmp_path / "fourbar.xml"
    assert (
        cli.main(["export-mjcf", str(mechanism_files["fourbar"]), "-o", str(out), "--stiff"]) == 0
    )
    m = mujoco.MjModel.from_xml_path(str(out))
    assert m.neq == 2
    assert np.allclose(m.eq_solref[:, 0], STIFF.solref[0])


def test_export_nests_deeper_than_the_recursion_limit(tmp_path):
    """A chain of 1200 links nests 1200 bodies (written with an explicit stack, not by
    recursion): every body is opened and closed once, in order."""
    import sys

    from closedchain.benchmark.families import chain_urdf

    n = 1200
    assert n > sys.getrecursionlimit()
    path = tmp_path / "chain.urdf"
    path.write_text(chain_urdf(n, length=float(n)))
    text = export_mjcf(cc.load(path))
    assert text.count("<body ") == n
    assert text.count("</body>") == n
    assert text.index('<body name="j0"') < text.index(f'<body name="j{n - 1}"')


@pytest.mark.parametrize("family", ["chain", "leg_pair"])
def test_load_mujoco_in_pieces_is_the_model_of_the_whole_text(tmp_path, monkeypatch, family):
    """MuJoCo's XML parser nests a few hundred bodies at most: load_mujoco parses deeper
    trees in pieces of XML_DEPTH nested bodies joined with MjSpec. Cut every 4 bodies, a
    14-link chain and a leg pair (branched, 4 loops) give the model MuJoCo parses from the
    whole text: the same bodies, joints, sites and equalities by name, the same
    accelerations."""
    from closedchain.benchmark.families import chain_urdf, leg_pair_urdf
    from closedchain.export import mjcf

    path = tmp_path / f"{family}.urdf"
    path.write_text(chain_urdf(14) if family == "chain" else leg_pair_urdf(6))
    mech = cc.load(path)
    whole = mujoco.MjModel.from_xml_string(export_mjcf(mech))
    monkeypatch.setattr(mjcf, "XML_DEPTH", 4)
    pieces, _ = load_mujoco(mech)
    for kind, count in (
        (mujoco.mjtObj.mjOBJ_BODY, "nbody"),
        (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
        (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
        (mujoco.mjtObj.mjOBJ_EQUALITY, "neq"),
    ):
        assert getattr(pieces, count) == getattr(whole, count) > 0
        names = [
            [mujoco.mj_id2name(m, kind, i) for i in range(getattr(m, count))]
            for m in (whole, pieces)
        ]
        assert names[0] == names[1]
    q, v = cc.random_consistent_state(mech, np.random.default_rng(3))
    qacc = []
    for m in (whole, pieces):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = mujoco_state(mech, q, v)
        mujoco.mj_forward(m, d)
        qacc.append(d.qacc.copy())
    np.testing.assert_array_equal(qacc[0], qacc[1])


#: MuJoCo's mass matrix of an exported universal joint agrees with Pinocchio's to this,
#: relative to its largest entry (round-off of two implementations).
UNIVERSAL_M_RTOL = 1e-12


def test_a_universal_joint_exports_as_two_hinges_with_pinocchios_mass_matrix(tmp_path, rng):
    """An SDF universal joint (Pinocchio's JointModelUniversal) becomes two hinges in one
    body: MuJoCo's own mass matrix (mj_fullM) and kinematics agree with Pinocchio's."""
    sdf = tmp_path / "u.sdf"
    sdf.write_text(
        '<?xml version="1.0"?><sdf version="1.6"><model name="u">'
        '<link name="base"/><link name="arm"><pose>0.1 0.2 0.3 0.2 0 0.4</pose>'
        "<inertial><pose>0.1 0.05 -0.2 0 0.3 0</pose><mass>1.3</mass><inertia><ixx>0.02</ixx>"
        "<iyy>0.03</iyy><izz>0.01</izz></inertia></inertial></link>"
        '<link name="tip"><pose>0.3 0.1 0.0 0 0 0</pose><inertial><mass>0.4</mass><inertia>'
        "<ixx>0.001</ixx><iyy>0.002</iyy><izz>0.003</izz></inertia></inertial></link>"
        '<joint name="u" type="universal"><parent>base</parent><child>arm</child>'
        "<axis><xyz>1 0 0</xyz></axis><axis2><xyz>0 0.6 0.8</xyz></axis2></joint>"
        '<joint name="t" type="revolute"><parent>arm</parent><child>tip</child>'
        "<axis><xyz>0 0 1</xyz></axis></joint></model></sdf>"
    )
    mech = cc.load(sdf)
    assert mech.model.joints[mech.model.getJointId("u")].shortname() == "JointModelUniversal"
    m, d = load_mujoco(mech)
    q = rng.uniform(-1.0, 1.0, mech.nq)
    d.qpos[:], d.qvel[:] = mujoco_state(mech, q, np.zeros(mech.nv))
    mujoco.mj_forward(m, d)
    M_mj = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, M_mj)
    model, data = mech.model, mech.model.createData()
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    assert np.max(np.abs(M_mj - M)) < UNIVERSAL_M_RTOL * np.max(np.abs(M))
    # The tip's joint frame (a body of its own in the export) sits where Pinocchio puts it.
    tip = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "t")
    pin.forwardKinematics(model, data, q)
    assert np.linalg.norm(d.xpos[tip] - data.oMi[model.getJointId("t")].translation) < MASS_TOL
