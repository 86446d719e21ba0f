"""closedchain.pindata: a Pinocchio Data without the nv^3 tensors, and its memory model.

The reference is Pinocchio's own ``pinocchio.Data(model)``: the lean Data must
equal it field by field (Pinocchio's ``operator==``) once the four tensors it
leaves out are copied in, and every algorithm closedchain calls must give
bit-identical results on both.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pinocchio as pin
import pytest
from conftest import ALL_MECHANISMS, VALIDATABLE_MECHANISMS

import closedchain as cc
from closedchain import pindata
from closedchain.build import build_model

pytestmark = pytest.mark.skipif(
    not pindata.lean_available(), reason="the compiled core (lean Data) is not built"
)


def _pinocchio_equality_is_reflexive(model) -> bool:
    # Pinocchio's Data == Data is False for some joint types (RevoluteUnaligned:
    # even a Data and its own copy compare unequal), so field equality is only
    # a test where it holds for two full Datas.
    return pin.Data(model) == pin.Data(model).copy()


@pytest.mark.parametrize("name", ALL_MECHANISMS)
@pytest.mark.parametrize("root", [None, "free"])
def test_lean_data_equals_pinocchio_data_apart_from_the_tensors(
    load_mechanism, name, root, core_testing
):
    model = load_mechanism(name).model
    if root == "free":
        model = build_model(load_mechanism(name).description.tree, pin.JointModelFreeFlyer())
    if not _pinocchio_equality_is_reflexive(model):
        pytest.skip("pinocchio.Data == is not reflexive for this model's joints")
    assert core_testing._lean_data_matches_full(model)


def test_lean_data_equals_pinocchio_data_on_pinocchio_sample_models(core_testing):
    for model in (pin.buildSampleModelHumanoidRandom(), pin.buildSampleModelManipulator()):
        assert _pinocchio_equality_is_reflexive(model)
        assert core_testing._lean_data_matches_full(model)


@pytest.mark.parametrize("name", ALL_MECHANISMS)
def test_algorithms_agree_bitwise_on_lean_and_full_data(load_mechanism, rng, name):
    mech = load_mechanism(name)
    model = mech.model
    lean, full = pindata.new_data(model), pin.Data(model)
    q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
    v, a = rng.standard_normal(model.nv), rng.standard_normal(model.nv)
    for d in (lean, full):
        pin.crba(model, d, q)
        pin.nonLinearEffects(model, d, q, v)
        pin.rnea(model, d, q, v, a)
        pin.computeJointJacobians(model, d, q)
        pin.forwardKinematics(model, d, q, v, a)
        pin.updateFramePlacements(model, d)
        pin.aba(model, d, q, v, a)
        pin.computeMechanicalEnergy(model, d, q, v)
    np.testing.assert_array_equal(lean.M, full.M)
    np.testing.assert_array_equal(lean.nle, full.nle)
    np.testing.assert_array_equal(lean.tau, full.tau)
    np.testing.assert_array_equal(lean.J, full.J)
    np.testing.assert_array_equal(lean.ddq, full.ddq)
    assert lean.mechanical_energy == full.mechanical_energy
    for k in range(model.nframes):
        np.testing.assert_array_equal(lean.oMf[k].homogeneous, full.oMf[k].homogeneous)
        frame_jacobians = [
            pin.getFrameJacobian(model, d, k, pin.LOCAL_WORLD_ALIGNED) for d in (lean, full)
        ]
        np.testing.assert_array_equal(*frame_jacobians)


@pytest.mark.parametrize("name", VALIDATABLE_MECHANISMS)
def test_pinocchio_constraint_dynamics_agrees_bitwise_on_lean_data(load_mechanism, rng, name):
    mech = load_mechanism(name)
    cms, cds, _, _ = mech.pinocchio_constraints()
    q, v = mech.q_ref, np.zeros(mech.nv)
    tau = rng.standard_normal(mech.nv)
    out = []
    for d in (pindata.new_data(mech.model), pin.Data(mech.model)):
        cds_d = pin.StdVec_RigidConstraintData()
        for cm in cms:
            cds_d.append(cm.createData())
        pin.initConstraintDynamics(mech.model, d, cms, cds_d)
        out.append(
            pin.constraintDynamics(
                mech.model, d, q, v, tau, cms, cds_d, pin.ProximalSettings(1e-12, 1e-8, 20)
            ).copy()
        )
    np.testing.assert_array_equal(*out)


def test_a_1000_dof_data_fits_in_a_3_gb_address_space():
    # pinocchio.Data of a 1000-joint chain zeroes 32 GB of tensors (33 nv^3
    # bytes measured); the lean one takes ~620 nv^2 = 0.6 GB. Built in a
    # subprocess whose address space is capped, so a regression fails the
    # test (MemoryError) instead of taking the machine down.
    code = textwrap.dedent(
        """
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))
        import pinocchio as pin
        from closedchain.pindata import new_data
        m = pin.Model()
        parent = 0
        for i in range(1000):
            parent = m.addJoint(parent, pin.JointModelRY(), pin.SE3.Identity(), f"j{i}")
            m.appendBodyToJoint(parent, pin.Inertia.FromCylinder(1.0, 0.01, 1.0),
                                pin.SE3.Identity())
        d = new_data(m)
        pin.crba(m, d, pin.neutral(m))
        # The peak resident set of this process image (VmHWM, kB): ru_maxrss would also
        # carry the forking pytest process's peak across exec.
        hwm = [ln for ln in open("/proc/self/status") if ln.startswith("VmHWM:")][0]
        print(d.M.shape, hwm.split()[1])
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    shape, maxrss_kb = out.stdout.rsplit(")", 1)
    assert shape.strip() == "(1000, 1000"
    assert int(maxrss_kb) * 1024 < 1.5e9


def test_memory_model_and_size_limit_agree():
    # Independent reference: the largest n with 620 n^2 <= budget, by search.
    for budget in (1e6, 2e9, 5e9):
        expected = max(
            n for n in range(1, 4000) if pindata.LEAN_DATA_BYTES_PER_NV2 * n * n <= budget
        )
        assert pindata.max_nv_for(budget) == expected
        assert cc.mechanism.max_nv(cc.LoadSettings(max_data_bytes=budget)) == expected
    assert pindata.data_bytes(1000) == pytest.approx(6.2e8)
