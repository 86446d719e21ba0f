"""Tests of closedchain.parallel, the parallel-robot workflow, against closed forms.

* the lesson's 4-bar: forward kinematics from the crank = Freudenstein's equation (conftest);
* the planar five-bar of tests/data/five_bar.urdf: forward kinematics = the intersection of
  the distal links' circles, inverse kinematics of the end point = the intersection of each
  leg's crank and distal circles (both working modes), motor torques at rest = the
  gradient of the potential energy (virtual work), sigma_min of J_D = its closed form near
  the type II singularity where the distal links align;
* the Agile Eye and a leg in the corpus's URDF + YAML form: inverse kinematics of the
  platform (sole) placement round-trips with forward kinematics; the leg's forward
  kinematics = its two four-bars' circle intersections, its motor torques = virtual work
  at rest and Pinocchio's constrained dynamics in motion, its type II singularity where a
  rod passes through the knee axis, its type I ones where hip axes align.

The five-bar's closed forms below are written from the geometry stated in the URDF's
header and share no code with closedchain.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import pytest
from conftest import DATA_DIR, MODELS

import closedchain as cc
from closedchain.exceptions import InvalidArgumentError, UnknownChoiceError

#: Joint angles of a forward / inverse kinematics solution against a closed form [rad].
ANGLE_TOL = 1e-9
#: Motor angles of the Agile Eye's IK -> FK round trip [rad].
ROUND_TRIP_TOL = 1e-10
#: Central-difference step of the potential energy [rad].
FD_STEP = 1e-6
#: Motor torques against the central difference of the potential energy [N m]
#: (truncation ~ FD_STEP^2, round-off ~ eps V / FD_STEP ~ 1e-10).
TORQUE_TOL = 1e-7
#: sigma_min of J_D against its closed form [m].
SIGMA_TOL = 1e-10
#: sigma_min of J_D at the type II singularity itself [m].
SINGULAR_TOL = 1e-12
#: Relative spread of sigma_min / delta over halvings of delta (a simple root) [-].
LINEAR_RTOL = 0.02

FIVE_BAR = DATA_DIR / "five_bar.urdf"
END_POINT = "P::predecessor"


def wrap(x):
    """Return x wrapped into [-pi, pi) [rad], elementwise."""
    return (np.asarray(x) + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class FiveBarClosedForms:
    """The five-bar of tests/data/five_bar.urdf in its vertical plane (world x, z).

    Ground pivots A = (0, 0) and E = (0.2, 0); cranks of length l1 = 0.15 m, distal links
    l2 = 0.25 m; each a uniform 0.5 kg rod; angles turn x towards z. Coordinates
    q = [theta1, psi1, theta2, psi2] (crank angles and the distal joints' relative angles).
    """

    base: float = 0.2
    l1: float = 0.15
    l2: float = 0.25
    mass: float = 0.5
    g: float = 9.81

    @staticmethod
    def e(angle: float) -> np.ndarray:
        return np.array([math.cos(angle), math.sin(angle)])

    @staticmethod
    def circles(c1, r1, c2, r2, side: int) -> np.ndarray:
        """The intersection of circles (c1, r1) and (c2, r2) on ``side`` (+1: left of
        c1 -> c2)."""
        u = np.asarray(c2) - np.asarray(c1)
        d = float(np.linalg.norm(u))
        a = (r1 * r1 - r2 * r2 + d * d) / (2.0 * d)
        h = math.sqrt(r1 * r1 - a * a)
        return np.asarray(c1) + (a * u + side * h * np.array([-u[1], u[0]])) / d

    def pivots(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(2), np.array([self.base, 0.0])

    def forward(self, theta1: float, theta2: float, side: int) -> np.ndarray:
        """q with the cranks at theta1, theta2 and the end point on ``side`` of B1 -> B2."""
        A, E = self.pivots()
        B1, B2 = A + self.l1 * self.e(theta1), E + self.l1 * self.e(theta2)
        P = self.circles(B1, self.l2, B2, self.l2, side)
        return self.q_of(theta1, theta2, B1, B2, P)

    def inverse(self, P: np.ndarray, sides: tuple[int, int]) -> np.ndarray:
        """q with the end point at P (x, z), each elbow B on ``sides`` of pivot -> P."""
        A, E = self.pivots()
        B1 = self.circles(A, self.l1, P, self.l2, sides[0])
        B2 = self.circles(E, self.l1, P, self.l2, sides[1])
        t1 = math.atan2(B1[1] - A[1], B1[0] - A[0])
        t2 = math.atan2(B2[1] - E[1], B2[0] - E[0])
        return self.q_of(t1, t2, B1, B2, P)

    def q_of(self, t1, t2, B1, B2, P) -> np.ndarray:
        d1 = math.atan2(P[1] - B1[1], P[0] - B1[0])
        d2 = math.atan2(P[1] - B2[1], P[0] - B2[0])
        return wrap(np.array([t1, d1 - t1, t2, d2 - t2]))

    def end_point(self, q) -> np.ndarray:
        A, _ = self.pivots()
        return A + self.l1 * self.e(q[0]) + self.l2 * self.e(q[0] + q[1])

    def potential(self, q) -> float:
        """m g times the heights of the four rods' centres [J]."""
        A, E = self.pivots()
        z = 0.0
        for pivot, t, psi in ((A, q[0], q[1]), (E, q[2], q[3])):
            B = pivot + self.l1 * self.e(t)
            z += (pivot + 0.5 * self.l1 * self.e(t))[1] + (B + 0.5 * self.l2 * self.e(t + psi))[1]
        return self.mass * self.g * z

    def sigma_min_jd(self, q) -> float:
        """sigma_min of J_D = [l2 n1, -l2 n2] (n_i the distal links' normals): the
        translation rows of the loop in any rotated frame; l2 sqrt(1 - |cos alpha|)."""
        alpha = (q[0] + q[1]) - (q[2] + q[3])
        return self.l2 * math.sqrt(1.0 - abs(math.cos(alpha)))


FB = FiveBarClosedForms()


@pytest.fixture(scope="module")
def five_bar() -> cc.Mechanism:
    return cc.load(FIVE_BAR)


def nearest_branch(q, candidates) -> np.ndarray:
    return min(candidates, key=lambda c: float(np.linalg.norm(wrap(q - c))))


# -- forward kinematics ---------------------------------------------------------------


@pytest.mark.parametrize("theta2_deg", [-150, -90, -20, 0, 30, 90, 150])
def test_fourbar_forward_kinematics_is_freudenstein(fourbar, fourbar_closed_forms, rng, theta2_deg):
    cf = fourbar_closed_forms
    theta2 = math.radians(theta2_deg)
    for theta in cf.freudenstein(theta2):
        q_exact = cf.q_from_theta(theta)
        guess = q_exact + np.r_[0.0, rng.uniform(-0.05, 0.05, 2)]
        r = cc.forward_kinematics(fourbar, [theta2], q_guess=guess)
        assert np.linalg.norm(wrap(r.q - q_exact)) <= ANGLE_TOL
        assert r.motors[0] == theta2
        assert r.closure_residual <= ANGLE_TOL
        # sigma_min of J_D: the lesson's J_c (Section 2) in joint coordinates, columns of
        # the coupler and rocker (the rows' rotation into the cut frame keeps it).
        Jc = cf.jacobian(theta) @ cf.T
        sd = np.linalg.svd(Jc[:, 1:], compute_uv=False)[-1]
        assert abs(r.sigma_min_JD - sd) <= SIGMA_TOL


@pytest.mark.parametrize("motors_deg", [(100, 80), (120, 40), (60, 100), (150, 10)])
@pytest.mark.parametrize("side", [1, -1])
def test_five_bar_forward_kinematics_is_circle_intersection(five_bar, rng, motors_deg, side):
    t1, t2 = np.radians(motors_deg)
    q_exact = FB.forward(t1, t2, side)
    r = cc.forward_kinematics(five_bar, [t1, t2], q_guess=q_exact + rng.uniform(-0.1, 0.1, 4))
    assert np.linalg.norm(wrap(r.q - q_exact)) <= ANGLE_TOL
    np.testing.assert_array_equal(r.motors, [t1, t2])
    assert r.closure_residual <= ANGLE_TOL
    assert abs(r.sigma_min_JD - FB.sigma_min_jd(q_exact)) <= SIGMA_TOL


def test_forward_kinematics_errors(five_bar, fourbar, tmp_path):
    with pytest.raises(InvalidArgumentError, match=r"motors must be 2 finite numbers .*"):
        cc.forward_kinematics(five_bar, [1.0])
    with pytest.raises(InvalidArgumentError, match="left_crank_joint, right_crank_joint"):
        cc.forward_kinematics(five_bar, [1.0, math.nan])
    # A non-Grashof 4-bar (rocker 0.25 m: s + l = 0.7 > p + q = 0.65): the crank cannot
    # point away from the rocker (tip 0.7 m from the rocker pivot > b + c = 0.65 m).
    text = (MODELS / "fourbar.urdf").read_text()
    old = '<successor_origin xyz="0.3 0 0"'
    assert text.count(old) == 1
    path = tmp_path / "triple_rocker.urdf"
    path.write_text(text.replace(old, '<successor_origin xyz="0.25 0 0"'))
    mech = cc.load(path)
    with pytest.raises(cc.AssemblyError, match=r"no closed configuration with motors crank_joint"):
        cc.forward_kinematics(mech, [math.pi])


# -- inverse kinematics ---------------------------------------------------------------


@pytest.mark.parametrize("P", [(0.1, 0.3), (0.05, 0.25), (0.18, 0.2)])
@pytest.mark.parametrize("sides", [(-1, 1), (1, -1)])  # q_ref's working mode and the other
def test_five_bar_inverse_kinematics_is_circle_intersection(five_bar, rng, P, sides):
    q_exact = FB.inverse(np.array(P), sides)
    assert np.linalg.norm(FB.end_point(q_exact) - P) <= ANGLE_TOL  # the reference holds
    target = np.array([P[0], 0.0, P[1]])
    r = cc.inverse_kinematics(
        five_bar, END_POINT, target, mode="3d", q_guess=q_exact + rng.uniform(-0.1, 0.1, 4)
    )
    assert np.linalg.norm(wrap(r.q - q_exact)) <= ANGLE_TOL
    assert np.linalg.norm(wrap(r.motors - q_exact[[0, 2]])) <= ANGLE_TOL
    assert r.frame_error <= cc.parallel.IK_TOL
    assert r.closure_residual <= ANGLE_TOL


@pytest.mark.parametrize("name, frame, samples", [("agile_eye", "platform", 5), ("leg", "sole", 3)])
def test_inverse_kinematics_round_trips(request, rng, name, frame, samples):
    """The pose forward kinematics gives to random motors takes inverse kinematics,
    started from q_ref, back to those motors (the Agile Eye's platform; the sole of
    the corpus-style leg below, 6d with five motors)."""
    mech = request.getfixturevalue(name)
    fid = mech.model.getFrameId(frame)
    data = mech.model.createData()
    for _ in range(samples):
        motors = rng.uniform(-0.4, 0.4, len(mech.actuated_joints))
        fk = cc.forward_kinematics(mech, motors)
        pin.framesForwardKinematics(mech.model, data, fk.q)
        target = data.oMf[fid].copy()
        ik = cc.inverse_kinematics(mech, frame, target)  # from q_ref
        assert np.linalg.norm(wrap(ik.motors - motors)) <= ROUND_TRIP_TOL
        assert np.linalg.norm(pin.difference(mech.model, fk.q, ik.q)) <= ROUND_TRIP_TOL
        pin.framesForwardKinematics(mech.model, data, ik.q)
        assert np.linalg.norm(pin.log6(target.actInv(data.oMf[fid])).vector) <= ROUND_TRIP_TOL


def test_inverse_kinematics_errors(five_bar):
    with pytest.raises(UnknownChoiceError, match=r"unknown five_bar frame 'tip'; .*P::predecessor"):
        cc.inverse_kinematics(five_bar, "tip", pin.SE3.Identity())
    with pytest.raises(UnknownChoiceError, match=r"inverse-kinematics mode '2d'; .*3d, 6d"):
        cc.inverse_kinematics(five_bar, END_POINT, pin.SE3.Identity(), mode="2d")
    with pytest.raises(InvalidArgumentError, match=r"target of mode '6d' must be a pinocchio.SE3"):
        cc.inverse_kinematics(five_bar, END_POINT, np.zeros(3))
    # 0.6 m above the left pivot: beyond the reach of both legs (0.4 m).
    with pytest.raises(
        cc.AssemblyError, match=r"frame 'P::predecessor' cannot reach the target \(3d\)"
    ) as info:
        cc.inverse_kinematics(five_bar, END_POINT, [0.0, 0.0, 0.6], mode="3d")
    assert info.value.residual > 0.1


# -- motor torques -------------------------------------------------------------------


@pytest.mark.parametrize("motors_deg", [(100, 80), (130, 30)])
def test_five_bar_motor_torques_at_rest_are_virtual_work(five_bar, motors_deg):
    """At rest the motors hold the potential energy V(theta1, theta2) of the closed
    five-bar (virtual work): tau = dV/dtheta, by central differences on the closed form."""
    t = np.radians(motors_deg)
    fk = cc.forward_kinematics(five_bar, t)
    side = 1 if FB.end_point(fk.q)[1] > 0 else -1  # the branch reached: P above or below

    def V(t1, t2):
        return FB.potential(FB.forward(t1, t2, side))

    ref = np.array(
        [
            (V(t[0] + FD_STEP, t[1]) - V(t[0] - FD_STEP, t[1])) / (2 * FD_STEP),
            (V(t[0], t[1] + FD_STEP) - V(t[0], t[1] - FD_STEP)) / (2 * FD_STEP),
        ]
    )
    res = cc.inverse_dynamics(five_bar, fk.q, np.zeros(4), np.zeros(2), coordinates="actuated")
    assert np.linalg.norm(res.tau[five_bar.actuated_idx_v] - ref) <= TORQUE_TOL


# -- actuation singularities ---------------------------------------------------------


def distal_aligned() -> np.ndarray:
    """The type II singularity of this five-bar: both cranks at the point B where their
    circles meet, both distal links from B straight up (aligned)."""
    h = math.sqrt(FB.l1**2 - (FB.base / 2) ** 2)
    t1, t2 = math.atan2(h, FB.base / 2), math.atan2(h, -FB.base / 2)
    return np.array([t1, math.pi / 2 - t1, t2, math.pi / 2 - t2])


def test_five_bar_type_ii_singularity(five_bar):
    q_star = distal_aligned()
    assert np.max(np.abs(cc.compute_phi(five_bar, q_star))) <= SINGULAR_TOL
    assert cc.actuation_singularities(five_bar, q_star).parallel <= SINGULAR_TOL
    with pytest.raises(cc.SingularConfigurationError, match="type II"):
        cc.forward_kinematics(five_bar, q_star[[0, 2]], q_guess=q_star)
    # Turning the cranks apart by +-delta keeps the end point above B: sigma_min(J_D)
    # follows the closed form and vanishes like delta (a simple root).
    ratios = []
    for delta in (4e-3, 2e-3, 1e-3):
        motors = q_star[[0, 2]] + np.array([delta, -delta])
        r = cc.forward_kinematics(five_bar, motors, q_guess=q_star)
        q_cf = nearest_branch(r.q, [FB.forward(*motors, side) for side in (1, -1)])
        assert np.linalg.norm(wrap(r.q - q_cf)) <= ANGLE_TOL
        s = cc.actuation_singularities(five_bar, r.q).parallel
        assert abs(s - FB.sigma_min_jd(q_cf)) <= SIGMA_TOL
        assert s == r.sigma_min_JD
        ratios.append(s / delta)
    assert np.ptp(ratios) <= LINEAR_RTOL * np.mean(ratios)


def test_five_bar_type_i_singularity(five_bar):
    """A stretched left leg (distal joint at 0): the end point no longer determines the
    left crank, so the serial measure of the end point's position vanishes, like the
    distal joint's angle, while J_D stays regular."""
    serial = []
    for psi in (0.0, 2e-3, 1e-3):
        t1 = math.radians(70)
        P = FB.end_point([t1, psi, 0.0, 0.0])
        _, E = FB.pivots()
        B2 = FB.circles(E, FB.l1, P, FB.l2, 1)  # the right elbow of q_ref's working mode
        t2 = math.atan2(B2[1], B2[0] - E[0])
        q = FB.q_of(t1, t2, FB.l1 * FB.e(t1), B2, P)
        assert np.max(np.abs(cc.compute_phi(five_bar, q))) <= SINGULAR_TOL
        m = cc.actuation_singularities(five_bar, q, frame=END_POINT, mode="3d")
        assert abs(m.parallel - FB.sigma_min_jd(q)) <= SIGMA_TOL  # regular: ~0.05 m
        assert m.parallel > 0.01
        serial.append(m.serial)
    assert serial[0] <= SINGULAR_TOL
    assert abs(serial[1] / 2e-3 - serial[2] / 1e-3) <= LINEAR_RTOL * serial[2] / 1e-3
    far = cc.actuation_singularities(five_bar, five_bar.q_ref, frame=END_POINT, mode="3d")
    assert far.serial > 0.01
    assert math.isnan(cc.actuation_singularities(five_bar, five_bar.q_ref).serial)


# -- the guide's example -------------------------------------------------------------

GUIDE = MODELS.parent / "docs" / "guide" / "robots-and-moving-bases.md"


def test_guide_examples_run(tmp_path, monkeypatch):
    """The ```python blocks of the guide's section "The parallel-robot workflow" run:
    the Agile Eye's, and the leg's (tests/data/yaml_parallel_leg)."""
    text = GUIDE.read_text().split("## The parallel-robot workflow", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^```python\n(.*?)^```$", text, re.M | re.S)
    assert len(blocks) == 2
    (tmp_path / "models").symlink_to(MODELS)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "data").symlink_to(DATA_DIR)
    monkeypatch.chdir(tmp_path)
    eye, leg = ({"__name__": "guide_example"} for _ in blocks)
    for block, namespace in zip(blocks, (eye, leg), strict=True):
        exec(compile(block, str(GUIDE), "exec"), namespace)
    assert eye["ik"].frame_error <= cc.parallel.IK_TOL
    assert eye["s"].parallel > 0.1  # the Agile Eye's workspace centre is regular
    assert np.linalg.norm(wrap(leg["ik"].motors - leg["fk"].motors)) <= ROUND_TRIP_TOL
    assert min(leg["s"].parallel, leg["s"].serial) > 1e-3  # a bent leg is regular


# -- a leg in the example-parallel-robots convention (URDF + loops YAML) -----------------
#
# tests/data/yaml_parallel_leg: hip yaw, roll and pitch motors in series; the knee and the
# ankle passive, each turned by a crank motor through a rod (the knee's rod welded 6d to a
# spherical link of the shin, the ankle's joined 3d to the foot). Its two four-bars lie in
# the x-z plane of their frames (joint axes along y): thigh frame for the knee, shin frame
# for the ankle. Their closed forms below are written from the numbers in the URDF header.

LEG = DATA_DIR / "yaml_parallel_leg.urdf"
LEG_MOTORS = ("hip_z", "hip_x", "hip_y", "knee_mot", "ankle_mot")
#: Accelerations of the motors that Pinocchio's constrained dynamics gives under the
#: inverse-dynamics torques, against the prescribed ones [rad/s^2].
LEG_ACCEL_TOL = 1e-8


@dataclass(frozen=True)
class FourBar:
    """A crank-rod-arm four-bar in the x-z plane of a link frame (points (x, z) [m]).

    The crank turns about y at ``pivot`` with its tip at ``tip`` (angle 0); the arm turns
    about y at ``joint`` carrying the rod's end ``end`` (angle 0); the rod joins tip to end.
    """

    pivot: np.ndarray
    tip: np.ndarray
    joint: np.ndarray
    end: np.ndarray

    @staticmethod
    def rot(theta: float, p) -> np.ndarray:
        """(x, z) turned by theta about +y: x' = x cos + z sin, z' = -x sin + z cos."""
        c, s = math.cos(theta), math.sin(theta)
        return np.array([c * p[0] + s * p[1], -s * p[0] + c * p[1]])

    @staticmethod
    def angle(a, b) -> float:
        """The angle about +y that turns direction a into direction b [rad]."""
        return math.atan2(a[1] * b[0] - a[0] * b[1], a[0] * b[0] + a[1] * b[1])

    @property
    def rod(self) -> float:
        return float(np.linalg.norm(self.end - self.tip))

    def crank_tip(self, phi: float) -> np.ndarray:
        return self.pivot + self.rot(phi, self.tip - self.pivot)

    def arm_angle(self, phi: float, guess: float = 0.0) -> float:
        """The arm's angle with the crank at phi: its end on the circle of radius |rod| about
        the crank tip (the intersection nearest ``guess``)."""
        c = self.crank_tip(phi)
        arm = self.end - self.joint
        a, d = float(np.linalg.norm(arm)), float(np.linalg.norm(c - self.joint))
        x = (a**2 - self.rod**2 + d**2) / (2 * d)
        h = math.sqrt(a**2 - x**2)
        u = (c - self.joint) / d
        n = np.array([-u[1], u[0]])
        angles = [self.angle(arm, x * u + sign * h * n) for sign in (1.0, -1.0)]
        return min(angles, key=lambda t: abs(wrap(t - guess)))

    def toggle(self) -> tuple[float, float]:
        """(crank, arm) angles where the rod passes through the arm's joint (type II):
        |tip - joint| = rod - arm, the arm pointing away from the tip."""
        arm = self.end - self.joint
        r, d = float(np.linalg.norm(self.tip - self.pivot)), self.rod - float(np.linalg.norm(arm))
        e = float(np.linalg.norm(self.joint - self.pivot))
        x = (r**2 - d**2 + e**2) / (2 * e)
        u = (self.joint - self.pivot) / e
        c = self.pivot + x * u + math.sqrt(r**2 - x**2) * np.array([-u[1], u[0]])
        phi = self.angle(self.tip - self.pivot, c - self.pivot)
        return phi, self.angle(arm, self.joint - c)


#: The knee's four-bar in the thigh frame, the ankle's in the shin frame (header numbers).
KNEE = FourBar(*(np.array(p) for p in ((0.06, -0.05), (0.12, -0.05), (0.0, -0.4), (0.06, -0.45))))
ANKLE = FourBar(
    *(np.array(p) for p in ((-0.06, -0.05), (-0.12, -0.05), (0.0, -0.4), (-0.06, -0.42)))
)


@pytest.fixture(scope="module")
def leg() -> cc.Mechanism:
    return cc.load(LEG, loops=LEG.with_suffix(".yaml"))


def _leg_q(leg, name: str, q) -> float:
    return float(q[leg.model.joints[leg.model.getJointId(name)].idx_q])


def test_leg_loads_with_its_motors(leg):
    # 14 coordinates (2 U-joints, a spherical joint), 9 rows (6d + 3d): 5 motors.
    assert (leg.nv, leg.nc, leg.mobility, leg.actuated_joints) == (14, 9, 5, LEG_MOTORS)


@pytest.mark.parametrize("motors", [(0.1, -0.2, 0.3, 0.4, -0.3), (-0.3, 0.2, -0.5, -0.6, 0.5)])
def test_leg_forward_kinematics_is_its_four_bars(leg, motors):
    fk = cc.forward_kinematics(leg, motors)
    assert np.linalg.norm(wrap(fk.motors - motors)) <= ANGLE_TOL
    assert abs(wrap(_leg_q(leg, "knee", fk.q) - KNEE.arm_angle(motors[3]))) <= ANGLE_TOL
    assert abs(wrap(_leg_q(leg, "ankle", fk.q) - ANKLE.arm_angle(motors[4]))) <= ANGLE_TOL
    assert fk.closure_residual <= ANGLE_TOL


def test_motor_order_is_name_mot_everywhere(leg):
    """The leg's name_mot order is not its coordinates' order; actuated_joints,
    actuated_idx_v, forward_kinematics' motors and inverse_dynamics(coordinates=
    "actuated") all follow name_mot."""
    idx_tree = [leg.model.joints[leg.model.getJointId(n)].idx_v for n in LEG_MOTORS]
    assert idx_tree != sorted(idx_tree)  # else this test could not fail
    assert tuple(leg.actuated_joints) == LEG_MOTORS
    assert leg.actuated_idx_v.tolist() == idx_tree
    assert [leg.coordinate_names[i] for i in leg.actuated_idx_v] == list(LEG_MOTORS)
    motors = np.array([0.2, -0.1, 0.4, 0.3, -0.2])
    fk = cc.forward_kinematics(leg, motors)
    idx_q = [leg.model.joints[leg.model.getJointId(n)].idx_q for n in leg.actuated_joints]
    assert np.max(np.abs(wrap(fk.q[idx_q] - motors))) <= ANGLE_TOL
    a_motors = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    res = cc.inverse_dynamics(leg, fk.q, np.zeros(leg.nv), a_motors, coordinates="actuated")
    assert np.max(np.abs(res.a[leg.actuated_idx_v] - a_motors)) <= LEG_ACCEL_TOL


def test_leg_motor_torques_at_rest_are_virtual_work(leg):
    motors = np.array([0.2, -0.1, 0.4, 0.3, -0.2])
    q = cc.forward_kinematics(leg, motors).q
    tau = cc.gravity_torque(leg, q)[leg.actuated_idx_v]  # in name_mot's order, as motors
    data = leg.model.createData()

    def V(m):
        return pin.computePotentialEnergy(
            leg.model, data, cc.forward_kinematics(leg, m, q_guess=q).q
        )

    steps = FD_STEP * np.eye(5)
    ref = np.array([(V(motors + h) - V(motors - h)) / (2 * FD_STEP) for h in steps])
    assert np.linalg.norm(tau - ref) <= TORQUE_TOL


def test_leg_motor_torques_give_pinocchios_accelerations(leg, rng):
    """Inverse dynamics in motion: under its torques, pinocchio.constraintDynamics
    accelerates the motors as prescribed."""
    from closedchain.validation import pinocchio_reference_dynamics

    q = cc.forward_kinematics(leg, [0.1, 0.2, -0.3, 0.2, 0.1]).q
    v = cc.project_velocity(leg, q, rng.standard_normal(leg.nv), fixed=list(LEG_MOTORS))
    a_motors = rng.standard_normal(5)
    res = cc.inverse_dynamics(leg, q, v, a_motors, coordinates="actuated")
    a_pin = pinocchio_reference_dynamics(leg, q, v, res.tau)[0]
    assert np.max(np.abs(a_pin[leg.actuated_idx_v] - a_motors)) <= LEG_ACCEL_TOL
    assert np.max(np.abs(a_pin - res.a)) <= LEG_ACCEL_TOL


def test_leg_actuation_singularities(leg):
    # Away from both: a bent leg (q_ref, the straight leg, is a type I singularity: its
    # hip pitch, knee and ankle axes are parallel and lie in one plane).
    bent = cc.forward_kinematics(leg, [0.1, -0.2, 0.3, 0.4, -0.3]).q
    s = cc.actuation_singularities(leg, bent, frame="sole")
    assert min(s.parallel, s.serial) > 1e-3
    assert cc.actuation_singularities(leg, leg.q_ref, frame="sole").serial <= SINGULAR_TOL
    # Type II: the knee rod passes through the knee axis (closed form of the four-bar).
    phi, theta = KNEE.toggle()
    q = leg.q_ref.copy()
    for name, x in (("knee_mot", phi), ("knee", theta)):
        q[leg.model.joints[leg.model.getJointId(name)].idx_q] = x
    q = cc.assemble(leg, q, fixed=["knee_mot", "knee"])
    assert cc.actuation_singularities(leg, q).parallel <= SINGULAR_TOL
    with pytest.raises(cc.SingularConfigurationError, match="type II"):
        cc.forward_kinematics(leg, [0.0, 0.0, 0.0, phi, 0.0], q_guess=q)
    # Type I: hip roll at 90 deg turns the hip pitch axis onto the yaw axis, so the
    # sole stays put while yaw and pitch turn opposite ways; sigma_min is linear in
    # the distance delta to it.
    sigma = []
    for delta in (0.0, 1e-3, 5e-4, 2.5e-4):
        fk = cc.forward_kinematics(leg, [0.3, math.pi / 2 - delta, 0.2, 0.4, -0.3])
        sigma.append(cc.actuation_singularities(leg, fk.q, frame="sole").serial)
    assert sigma[0] <= SINGULAR_TOL
    ratios = np.array(sigma[1:]) / np.array([1e-3, 5e-4, 2.5e-4])
    assert np.ptp(ratios) <= LINEAR_RTOL * ratios.mean()


# -- orientation targets and the limits that stop a solve -----------------------------


def test_inverse_kinematics_orients_the_agile_eye_platform(agile_eye, rng):
    """An orientation target (rotation matrix or SE3, the position free) reached by
    forward kinematics' poses: Pinocchio's own frame placement at the solution has the
    target rotation, and the motors are those forward kinematics started from."""
    fid = agile_eye.model.getFrameId("platform")
    data = agile_eye.model.createData()
    for _ in range(3):
        motors = rng.uniform(-0.4, 0.4, len(agile_eye.actuated_joints))
        fk = cc.forward_kinematics(agile_eye, motors)
        pin.framesForwardKinematics(agile_eye.model, data, fk.q)
        rotation = data.oMf[fid].rotation.copy()
        for target in (rotation, pin.SE3(rotation, np.array([5.0, 5.0, 5.0]))):
            ik = cc.inverse_kinematics(agile_eye, "platform", target, mode="orientation")
            pin.framesForwardKinematics(agile_eye.model, data, ik.q)
            assert np.linalg.norm(pin.log3(rotation.T @ data.oMf[fid].rotation)) <= ROUND_TRIP_TOL
            assert np.linalg.norm(wrap(ik.motors - motors)) <= ROUND_TRIP_TOL
            assert ik.mode == "orientation"


def test_inverse_kinematics_refuses_a_matrix_that_is_not_a_rotation(agile_eye):
    with pytest.raises(InvalidArgumentError, match=r"mode 'orientation' must be .* rotation"):
        cc.inverse_kinematics(agile_eye, "platform", 2.0 * np.eye(3), mode="orientation")


#: Slider-crank of tests/data/slider_crank_driven.urdf (r = 0.1, L = 0.35 m: the slider
#: reaches 0.25 to 0.45 m) with the slider's lower limit raised to this [m].
SLIDER_LOWER = 0.3


def test_an_unreachable_target_names_the_limit_that_stops_it(tmp_path):
    """0.27 m is within the linkage's reach (0.25 m) but below the slider's lower limit:
    the message names that limit; 0.47 m is beyond the reach (0.45 m), no limit binds."""
    text = (DATA_DIR / "slider_crank_driven.urdf").read_text()
    text = text.replace('lower="0.2"', f'lower="{SLIDER_LOWER}"')
    path = tmp_path / "slider_crank_limited.urdf"
    path.write_text(text)
    mech = cc.load(path)
    with pytest.raises(
        cc.AssemblyError, match=r"stopped by the joint limits: slider_joint at its lower limit 0\.3"
    ):
        cc.inverse_kinematics(mech, "slider", [0.27, 0.0, 0.0], mode="3d")
    with pytest.raises(cc.AssemblyError, match=r"no joint at a limit: beyond the linkage's reach"):
        cc.inverse_kinematics(mech, "slider", [0.47, 0.0, 0.0], mode="3d")


# -- argument validation (issue 32) ----------------------------------------------------------


def _se3(R=None, p=(0.1, 0.0, 0.3)) -> pin.SE3:
    return pin.SE3(np.eye(3) if R is None else np.array(R, dtype=float), np.array(p, dtype=float))


@pytest.mark.parametrize(
    ("target", "kwargs", "message"),
    [
        (_se3(p=(math.nan, 0, 0)), {}, r"target must be a finite pinocchio.SE3"),
        (_se3(p=(math.inf, 0, 0)), {}, r"target must be a finite pinocchio.SE3"),
        (_se3(R=np.diag([1.0, 1.0, 1.01])), {}, r"target's rotation must be a rotation matrix"),
        (_se3(R=np.diag([1.0, 1.0, -1.0])), {}, r"target's rotation must be a rotation matrix"),
        ("tip", {}, r"target of mode '6d' must be a pinocchio.SE3"),
        ({"x": 1}, {"mode": "3d"}, r"target of mode '3d' must be a pinocchio.SE3 or a position"),
        (["a", "b", "c"], {"mode": "3d"}, r"target of mode '3d' must be"),
        (_se3(), {"tol": math.nan}, r"tol \(the largest frame error \[m or rad\]\) must be a"),
        (_se3(), {"tol": -1e-3}, r"tol .* must be a finite number > 0, got -0.001"),
        (_se3(), {"tol": "1e-3"}, r"tol .* must be a finite number > 0"),
        (_se3(), {"max_nfev": 2.5}, r"max_nfev .* must be an integer >= 1, got 2.5"),
        (_se3(), {"max_nfev": 0}, r"max_nfev .* must be an integer >= 1, got 0"),
        (_se3(), {"max_nfev": True}, r"max_nfev .* must be an integer >= 1, got True"),
    ],
)
def test_inverse_kinematics_refuses_bad_arguments_by_name(five_bar, target, kwargs, message):
    """Each was a hang (max_nfev=2.5), a wrong success (tol=nan: a 10 m frame error), an
    accepted non-rotation, or scipy's ValueError or TypeError; now one line each."""
    with pytest.raises(InvalidArgumentError, match=message) as info:
        cc.inverse_kinematics(five_bar, END_POINT, target, **kwargs)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("motors", "kwargs", "message"),
    [
        (["1", "2"], {}, r"motors must be 2 finite numbers"),
        ("12", {}, r"motors must be 2 finite numbers"),
        ({"a": 1}, {}, r"motors must be 2 finite numbers"),
        ([[0.1, 0.2]], {}, r"motors must be 2 finite numbers"),
        (np.zeros((40, 40)), {}, r"motors must be 2 finite numbers"),
        ([True, False], {}, r"motors must be 2 finite numbers"),
        ([0.1, 0.2], {"type_ii_rtol": math.nan}, r"type_ii_rtol .* must be a finite number > 0"),
    ],
)
def test_forward_kinematics_refuses_bad_arguments_by_name(five_bar, motors, kwargs, message):
    with pytest.raises(InvalidArgumentError, match=message) as info:
        cc.forward_kinematics(five_bar, motors, **kwargs)
    assert "\n" not in str(info.value) and len(str(info.value)) < 500
