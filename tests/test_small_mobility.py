"""Mechanisms of mobility 0 to 2 and one degree of freedom run under every integrator,
stabilization, backend and public function (issue 32).

Pinocchio and the compiled core return a matrix of one column as a vector; these
mechanisms make every (rows, nv) array of the library meet that case. The references
are independent of closedchain: ``pin.aba`` integrated by scipy's DOP853 (open chains),
the configuration held still (a pendulum locked by a loop), Pinocchio's frame
placements (kinematics).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from scipy.integrate import solve_ivp

import closedchain as cc
from closedchain import cli
from closedchain.simulate import COMPILED_INTEGRATORS, INTEGRATORS

#: The rod's box.
VISUAL = '<visual><origin xyz="0.15 0 0"/><geometry><box size="0.3 0.01 0.02"/></geometry></visual>'
#: Rod of the pendulums: 1 kg, 0.3 m, along its link's x axis, turning about -y.
ROD = """
  <link name="{name}">
    <inertial><origin xyz="0.15 0 0"/><mass value="1"/>
      <inertia ixx="0" ixy="0" ixz="0" iyy="0.0075" iyz="0" izz="0.0075"/></inertial>
    {visual}
  </link>
  <joint name="{joint}" type="revolute">
    <parent link="{parent}"/><child link="{name}"/><origin xyz="{x} 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="10"/>
  </joint>""".replace("{visual}", VISUAL)
MOTOR = """
  <transmission name="t_{joint}"><type>transmission_interface/SimpleTransmission</type>
    <joint name="{joint}"><hardwareInterface>EffortJointInterface</hardwareInterface></joint>
    <actuator name="m_{joint}"><mechanicalReduction>1</mechanicalReduction></actuator>
  </transmission>"""
#: A massless frame at the rod's tip (a fixed joint), off the joint axis.
TIP = """
  <link name="tip"/>
  <joint name="tip_joint" type="fixed">
    <parent link="rod1"/><child link="tip"/><origin xyz="0.3 0 0"/>
  </joint>"""
#: A revolute loop about world z at the rod's tip: the pendulum cannot move (mobility 0).
LOCK = """
  <loop name="lock" type="revolute">
    <predecessor link="base"/><successor link="rod1"/>
    <predecessor_origin xyz="0.3 0 0"/><successor_origin xyz="0.3 0 0"/>
    <axis xyz="0 0 1"/>
  </loop>"""


def _robot(*parts: str) -> str:
    return (
        '<?xml version="1.0"?>\n<robot name="small">\n  <link name="base"/>'
        + "".join(parts)
        + "\n</robot>\n"
    )


#: name -> (URDF text, mobility).
MODELS = {
    "pendulum": (
        _robot(
            ROD.format(name="rod1", joint="j1", parent="base", x=0), TIP, MOTOR.format(joint="j1")
        ),
        1,
    ),
    "locked_pendulum": (_robot(ROD.format(name="rod1", joint="j1", parent="base", x=0), LOCK), 0),
    "double_pendulum": (
        _robot(
            ROD.format(name="rod1", joint="j1", parent="base", x=0),
            ROD.format(name="rod2", joint="j2", parent="rod1", x=0.3),
            MOTOR.format(joint="j1"),
            MOTOR.format(joint="j2"),
        ),
        2,
    ),
}

#: Horizon [s] and output times of the runs.
T_FINAL = 0.3
T_EVAL = np.linspace(0.0, T_FINAL, 7)
#: Initial angle of every joint of the open chains [rad].
Q0_OPEN = 0.3
#: Tolerance of the scipy reference (rtol = atol).
REFERENCE_TOL = 1e-12
#: Largest |q - q_ref| [rad] over the outputs for the fixed-step schemes of order at most
#: 2 at the default step (measured: euler 5.0e-3, semi-implicit 3.4e-3, ali3p 3.2e-3).
LOW_ORDER_TOL = 2e-2
#: Same for rk4 and the adaptive integrators at their default tolerances (measured 2.5e-8).
HIGH_ORDER_TOL = 1e-6
#: A locked mechanism moves by round-off only [rad] (measured 1e-19).
LOCKED_TOL = 1e-12


def tau(t, q, v):
    """A torque on every joint that depends on time and velocity [N m]."""
    return 0.5 * np.cos(3.0 * t) - 0.2 * v


def combinations():
    """(backend, integrator, stabilization) of both registries."""
    for backend, registry in (("numpy", INTEGRATORS), ("compiled", COMPILED_INTEGRATORS)):
        for name, spec in registry.items():
            for stab in spec.stabilizations:
                yield backend, name, stab


def tolerance(integrator: str) -> float:
    spec = INTEGRATORS[integrator]
    return LOW_ORDER_TOL if spec.kind == "fixed" and spec.order <= 2 else HIGH_ORDER_TOL


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """name -> (URDF path, Mechanism)."""
    folder = tmp_path_factory.mktemp("small")
    out = {}
    for name, (text, _) in MODELS.items():
        path = folder / f"{name}.urdf"
        path.write_text(text)
        out[name] = (path, cc.load(path))
    return out


def start(mech: cc.Mechanism) -> tuple[np.ndarray, np.ndarray]:
    q0 = mech.q_ref.copy() if mech.nc else np.full(mech.nq, Q0_OPEN)
    return q0, np.zeros(mech.nv)


def aba_reference(mech: cc.Mechanism, q0, v0) -> np.ndarray:
    """q at T_EVAL under tau from pin.aba and scipy's DOP853, shape (len(T_EVAL), nq)."""
    model, data, nq = mech.model, mech.model.createData(), mech.nq

    def rhs(t, x):
        q, v = x[:nq], x[nq:]
        return np.concatenate([v, pin.aba(model, data, q, v, tau(t, q, v))])

    sol = solve_ivp(
        rhs, (0.0, T_FINAL), np.concatenate([q0, v0]), method="DOP853",
        rtol=REFERENCE_TOL, atol=REFERENCE_TOL, t_eval=T_EVAL,
    )  # fmt: skip
    return sol.y[:nq].T


def test_the_models_have_the_mobility_they_claim(small):
    for name, (_, mobility) in MODELS.items():
        mech = small[name][1]
        assert mech.mobility == mobility, name
    assert small["pendulum"][1].nv == small["locked_pendulum"][1].nv == 1


@pytest.mark.parametrize(("backend", "integrator", "stabilization"), list(combinations()))
@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_integrator_runs_small_mechanisms_with_a_callable_tau(
    small, name, backend, integrator, stabilization
):
    mech = small[name][1]
    q0, v0 = start(mech)
    traj = cc.simulate(
        mech, q0, v0, T_FINAL, integrator=integrator, stabilization=stabilization,
        backend=backend, tau=tau, t_eval=T_EVAL,
    )  # fmt: skip
    assert traj.q.shape == (len(T_EVAL), mech.nq)
    if mech.mobility == 0:
        assert np.linalg.norm(traj.q - q0, np.inf) < LOCKED_TOL
        return
    q_ref = aba_reference(mech, q0, v0)
    assert np.linalg.norm(traj.q - q_ref, np.inf) < tolerance(integrator)


@pytest.mark.parametrize("backend", ("numpy", "compiled"))
@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_method_and_row_function_on_small_mechanisms(small, name, backend, rng):
    mech = small[name][1]
    q, _ = start(mech)
    v = np.zeros(mech.nv)
    tau_ = rng.uniform(-1.0, 1.0, mech.nv)
    J = cc.compute_jacobian(mech, q, backend=backend)
    assert J.shape == (mech.nc, mech.nv)
    assert cc.compute_phi(mech, q, backend=backend).shape == (mech.nc,)
    assert cc.compute_gamma(mech, q, v, backend=backend).shape == (mech.nc,)
    assert cc.project_velocity(mech, q, np.ones(mech.nv), backend=backend).shape == (mech.nv,)
    a_ref = pin.aba(mech.model, mech.model.createData(), q, v, tau_)
    methods = [m for m in cc.METHODS if backend == "numpy" or m in COMPILED_METHODS]
    for method in methods:
        res = cc.forward_dynamics(mech, q, v, tau_, method=method, backend=backend)
        assert res.J.shape == (mech.nc, mech.nv), method
        if mech.mobility == 0:
            np.testing.assert_allclose(res.a, 0.0, atol=ACCEL_TOL, err_msg=method)
        elif mech.nc == 0:
            np.testing.assert_allclose(res.a, a_ref, rtol=0, atol=ACCEL_TOL, err_msg=method)


#: Largest |a - a_ref| [rad/s^2] of forward dynamics against pin.aba (measured 1e-14).
ACCEL_TOL = 1e-10
COMPILED_METHODS = tuple(m for m, c in cc.dynamics.base.METHOD_CAPABILITIES.items() if c.compiled)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_validate_passes_on_small_mechanisms(small, name):
    report = cc.validate(small[name][1], n_samples=3)
    assert report.passed


def test_one_dof_forward_and_inverse_kinematics(small):
    """The rod's tip reached by IK is where Pinocchio puts it at the angle found."""
    mech = small["pendulum"][1]
    model, data = mech.model, mech.model.createData()
    fid = model.getFrameId("tip")
    q_goal = np.array([0.7])
    pin.framesForwardKinematics(model, data, q_goal)
    target = data.oMf[fid].copy()
    for mode, goal in (("6d", target), ("3d", target.translation.copy())):
        res = cc.inverse_kinematics(mech, "tip", goal, mode=mode, q_guess=np.array([0.3]))
        assert abs(res.q[0] - q_goal[0]) < IK_ANGLE_TOL, mode
        assert res.motors.shape == (1,)
    fk = cc.forward_kinematics(mech, [0.4])
    assert fk.q.shape == (1,) and fk.q[0] == 0.4
    # The output map of the tip's position: J_f = 0.3 [m] times the unit tangent
    # (sigma_min of [J; J_f] with J empty); the rod's origin is on the axis (sigma 0).
    tip = cc.actuation_singularities(mech, np.array([0.4]), frame="tip", mode="3d")
    assert abs(tip.serial - 0.3) < IK_ANGLE_TOL
    assert cc.actuation_singularities(mech, np.array([0.4]), frame="rod1", mode="3d").serial == 0


#: Angle [rad] of the IK answer (its tolerance, 1e-10 on the frame error, over 1 m).
IK_ANGLE_TOL = 1e-8


@pytest.mark.parametrize("name", sorted(MODELS))
def test_small_mechanisms_on_the_command_line(small, name, tmp_path, capsys):
    """simulate (the default integrator, dop853-rk43 on the compiled core), animate and plot."""
    path, mech = small[name]
    q0, v0 = start(mech)
    npz = tmp_path / "run.npz"
    args = ["simulate", str(path), "--t-final", str(T_FINAL), "--out", str(npz)]
    args += ["--q0", *map(str, q0)]
    assert cli.main(args) == 0, capsys.readouterr().err
    traj = cc.Trajectory.load(npz)
    assert traj.info.integrator == "dop853-rk43"
    if mech.mobility:  # unforced: the reference with tau = 0
        model, data, nq = mech.model, mech.model.createData(), mech.nq
        sol = solve_ivp(
            lambda t, x: np.concatenate([x[nq:], pin.aba(model, data, x[:nq], x[nq:], 0 * x[nq:])]),
            (0.0, traj.t[-1]), np.concatenate([q0, v0]), method="DOP853",
            rtol=REFERENCE_TOL, atol=REFERENCE_TOL,
        )  # fmt: skip
        assert np.linalg.norm(traj.q[-1] - sol.y[:nq, -1], np.inf) < HIGH_ORDER_TOL
    else:
        assert np.linalg.norm(traj.q - q0, np.inf) < LOCKED_TOL
    assert cli.main(["plot", str(npz), "-o", str(tmp_path / "run.png")]) == 0
    html = tmp_path / "run.html"
    anim = ["animate", str(path), "--t-final", str(T_FINAL), "-o", str(html), "--q0"]
    assert cli.main([*anim, *map(str, q0)]) == 0, capsys.readouterr().err
    assert html.stat().st_size > 0
    assert cli.main(["validate", str(path), "--samples", "3"]) == 0


def test_a_model_without_visuals_animates_as_stick_figures(tmp_path, capsys):
    """A one-link pendulum with inertials only (it crashed animate before; its links are
    now drawn as stick figures): the page is written and holds the stick figure of the
    moving link."""
    from closedchain.visualize.shapes import read_visuals

    text = MODELS["pendulum"][0]
    bare = text.replace(VISUAL, "").split("<transmission")[0] + "</robot>\n"
    path = tmp_path / "bare.urdf"
    path.write_text(bare)
    out = tmp_path / "a.html"
    status = cli.main(["animate", str(path), "--t-final", "0.1", "-o", str(out)])
    capsys.readouterr()
    assert status == 0 and out.stat().st_size > 0
    mech = cc.load(path)
    moving = {mech.model.frames[f].name for f in range(mech.model.nframes)} - {"world"}
    assert {v.link for v in read_visuals(mech)} & moving


def test_a_massless_moving_leaf_is_refused_at_load_by_name(tmp_path, capsys):
    """Its coordinate has no kinetic energy and no loop: M is singular (LinAlgError in
    simulate before); a massless link that a loop holds, or one on a fixed joint, loads."""
    leaf = """
  <link name="leaf"/><link name="leaf_tip"/>
  <joint name="leaf_joint" type="revolute">
    <parent link="rod1"/><child link="leaf"/><origin xyz="0.3 0 0"/><axis xyz="0 -1 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="10"/>
  </joint>
  <joint name="leaf_tip_joint" type="prismatic">
    <parent link="leaf"/><child link="leaf_tip"/><axis xyz="1 0 0"/>
    <limit lower="-3" upper="3" effort="10" velocity="10"/>
  </joint>"""
    path = tmp_path / "leaf.urdf"
    path.write_text(_robot(ROD.format(name="rod1", joint="j1", parent="base", x=0), leaf))
    with pytest.raises(
        cc.ModelFileError,
        match=r"subtree of joint 'leaf_joint' \(links leaf, leaf_tip\) has no mass",
    ):
        cc.load(path)
    assert cli.main(["simulate", str(path), "--t-final", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "leaf_joint" in err
    # The 4-bar with a massless rocker: the loop holds it (M + alpha J^T J is regular).
    from conftest import MODELS as SHIPPED

    text = (SHIPPED / "fourbar.urdf").read_text()
    start = text.index("<inertial>", text.index('<link name="rocker">'))
    end = text.index("</inertial>", start) + len("</inertial>")
    held = tmp_path / "fourbar_massless_rocker.urdf"
    held.write_text(text[:start] + text[end:])
    mech = cc.load(held)
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), 0.05)
    assert traj.max_constraint_residual < LOOP_RESIDUAL_TOL


#: Constraint residual of a short run with stage projection [m] (measured 1.5e-15).
LOOP_RESIDUAL_TOL = 1e-10
