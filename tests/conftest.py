"""Shared fixtures: mechanisms loaded once per session, a seeded generator, the 4-bar
closed forms, and kinematic trajectories (no simulator needed).

The 4-bar closed forms are the *independent* reference of the constraint
layer: they are written from the lesson (the course text the project grew from,
Chapter 15, Lesson 3, cited in docs/references.md; here its Section 2 and Problem 2)
and Freudenstein's equation, with the link lengths stated in
the header of ``models/fourbar.urdf``, and share no code with ``closedchain``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import closedchain as cc


def pytest_addoption(parser):
    parser.addoption(
        "--run-benchmark",
        action="store_true",
        help="also run the tests marked benchmark (minutes of CPU each on the numpy path)",
    )


def pytest_collection_modifyitems(config, items):
    if config.getoption("--run-benchmark"):
        return
    skip = pytest.mark.skip(reason="benchmark: run with pytest --run-benchmark")
    for item in items:
        if "benchmark" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def core_testing():
    """The compiled test helpers, closedchain._core_testing (src/cpp/expose-testing.cpp).

    Built by the test install only (``scripts/setup_venv.sh test``: CMake option
    CLOSEDCHAIN_TESTING); a missing module fails the test, never skips it.
    """
    try:
        from closedchain import _core_testing
    except ImportError as exc:
        pytest.fail(
            f"closedchain._core_testing is not built ({exc}): install with "
            "`bash scripts/setup_venv.sh test` (CMake option CLOSEDCHAIN_TESTING=ON)"
        )
    return _core_testing


ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"
DATA_DIR = Path(__file__).resolve().parent / "data"
ARTIFACTS = ROOT / "test-artifacts"

#: Every mechanism the tests load, by name: the two models and the small
#: test mechanisms of tests/data/ (one per loop type).
MECHANISM_FILES = {
    "fourbar": MODELS / "fourbar.urdf",
    "agile_eye": MODELS / "agile_eye.urdf",
    "turntable_fourbar": MODELS / "turntable_fourbar.urdf",
    "bricard": MODELS / "bricard.urdf",
    "spherical_chain": DATA_DIR / "spherical_chain.urdf",
    "slider_crank": DATA_DIR / "slider_crank.urdf",
    "slider_crank_planar": DATA_DIR / "slider_crank_planar.urdf",
    "fixed_branches": DATA_DIR / "fixed_branches.urdf",
}

#: The lists tests parametrize over (one place, so that a new model, method or
#: integrator is tested everywhere it belongs).
ALL_MECHANISMS = tuple(MECHANISM_FILES)
#: The models shipped in models/.
SHIPPED_MECHANISMS = ("fourbar", "agile_eye", "turntable_fourbar", "bricard")
#: Mechanisms Pinocchio has a constrained-dynamics reference for (no prismatic loops).
VALIDATABLE_MECHANISMS = (
    "fourbar",
    "agile_eye",
    "turntable_fourbar",
    "bricard",
    "spherical_chain",
    "fixed_branches",
)
#: Forward-dynamics methods; "kkt" is the reference the others are compared with.
ALL_METHODS = ("kkt", "schur", "nullspace", "reduced", "pinocchio")
#: Fixed-step and adaptive integrators.
FIXED_STEP_INTEGRATORS = ("euler", "semi-implicit", "rk4")
ADAPTIVE_INTEGRATORS = ("RK45", "DOP853", "Radau", "BDF", "LSODA")
ALL_INTEGRATORS = FIXED_STEP_INTEGRATORS + ADAPTIVE_INTEGRATORS

#: Seed of the ``rng`` fixture (every test gets a fresh generator with it).
RNG_SEED = 20251121


# -- mechanisms and randomness ----------------------------------------------------------


@pytest.fixture(scope="session")
def mechanism_files() -> dict[str, Path]:
    """Return name -> URDF path of every test mechanism."""
    return dict(MECHANISM_FILES)


@pytest.fixture(scope="session")
def load_mechanism():
    """Return ``get(name) -> Mechanism``, loading each mechanism once per session."""
    cache: dict[str, cc.Mechanism] = {}

    def get(name: str) -> cc.Mechanism:
        if name not in cache:
            cache[name] = cc.load(MECHANISM_FILES[name])
        return cache[name]

    return get


@pytest.fixture(scope="session")
def fourbar(load_mechanism) -> cc.Mechanism:
    return load_mechanism("fourbar")


@pytest.fixture(scope="session")
def agile_eye(load_mechanism) -> cc.Mechanism:
    return load_mechanism("agile_eye")


@pytest.fixture
def rng() -> np.random.Generator:
    """A generator seeded with :data:`RNG_SEED`, fresh for every test."""
    return np.random.default_rng(RNG_SEED)


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    return ARTIFACTS


# -- the lesson's planar 4-bar in closed form ---------------------------------------------


@dataclass(frozen=True)
class FourBarClosedForms:
    r"""The lesson's planar 4-bar (Section 2, Problem 2) and Freudenstein's equation.

    Absolute angles ``theta = [theta2, theta3, theta4]`` [rad] are measured from
    the ground line AD; ``models/fourbar.urdf`` maps them to its joint
    coordinates by ``theta = T q`` (its header): q = [theta2, theta3 - theta2,
    theta4]. The lesson's planar (x, y) are world (x, z).

    Attributes:
        a, b, c, d: crank, coupler, rocker and ground lengths [m] (the URDF header).
    """

    a: float = 0.2
    b: float = 0.4
    c: float = 0.3
    d: float = 0.5

    #: d theta / d q, shape (3, 3).
    T = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])

    def theta(self, q: np.ndarray) -> np.ndarray:
        """Return the absolute angles of joint coordinates q, shape (3,)."""
        return self.T @ np.asarray(q, dtype=float)

    def q_from_theta(self, theta: np.ndarray) -> np.ndarray:
        """Return joint coordinates q of absolute angles, shape (3,)."""
        th2, th3, th4 = theta
        return np.array([th2, th3 - th2, th4])

    def phi(self, theta: np.ndarray) -> np.ndarray:
        """Lesson Section 2: phi = p_C(coupler) - p_C(rocker), shape (2,) [m]."""
        a, b, c, d = self.a, self.b, self.c, self.d
        th2, th3, th4 = theta
        return np.array(
            [
                a * math.cos(th2) + b * math.cos(th3) - d - c * math.cos(th4),
                a * math.sin(th2) + b * math.sin(th3) - c * math.sin(th4),
            ]
        )

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """Lesson Section 2: J_c = d phi / d theta, shape (2, 3) [m]."""
        a, b, c = self.a, self.b, self.c
        th2, th3, th4 = theta
        return np.array(
            [
                [-a * math.sin(th2), -b * math.sin(th3), c * math.sin(th4)],
                [a * math.cos(th2), b * math.cos(th3), -c * math.cos(th4)],
            ]
        )

    def det_dependent(self, theta: np.ndarray) -> float:
        """Lesson Section 2: det of J_c's coupler and rocker columns, b c sin(theta3 - theta4)
        [m^2]. Its sign names the assembly branch (open or crossed); it changes only where
        coupler and rocker align (for this linkage: at its change point, theta2 = 180 deg)."""
        return self.b * self.c * math.sin(theta[1] - theta[2])

    def jacobian_dot(self, theta: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
        """Lesson Problem 2: dJ_c/dt, shape (2, 3) [m/s], with the lesson's sign error corrected.

        The lesson prints entry (2, 3) as ``-c sin(theta4) theta4_dot`` (and so
        the term ``-c sin(theta4) theta4_dot^2`` of its second acceleration
        equation, and ``Jcdot(2,3)`` of its MATLAB function in Section 10); the
        time derivative of J_c(2, 3) = -c cos(theta4) is ``+c sin(theta4)
        theta4_dot``. tests/test_constraints.py checks this matrix against a
        finite difference of :meth:`jacobian`.
        """
        a, b, c = self.a, self.b, self.c
        th2, th3, th4 = theta
        w2, w3, w4 = theta_dot
        return np.array(
            [
                [-a * math.cos(th2) * w2, -b * math.cos(th3) * w3, c * math.cos(th4) * w4],
                [-a * math.sin(th2) * w2, -b * math.sin(th3) * w3, c * math.sin(th4) * w4],
            ]
        )

    def jacobian_dot_as_printed(self, theta: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
        """Lesson Problem 2 exactly as printed (entry (2, 3) with the wrong sign)."""
        Jd = self.jacobian_dot(theta, theta_dot)
        Jd[1, 2] = -Jd[1, 2]
        return Jd

    # -- the closure in the coupler's cut frame (the rows closedchain writes) --------------
    #: Unit vectors n1, n2 of the cut frame across the loop axis (0, -1, 0), in the
    #: coupler frame: (n1, n2, axis) right-handed orthonormal.
    N1 = np.array([0.0, 0.0, 1.0])
    N2 = np.array([-1.0, 0.0, 0.0])

    @staticmethod
    def cut_basis(theta3: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return Q, dQ/dtheta3, d2Q/dtheta3^2, shapes (2, 2): columns R_p n1, R_p n2 in the
        the lesson's planar axes (world x, z); the coupler is turned by theta3 about (0, -1, 0)."""
        c, s = math.cos(theta3), math.sin(theta3)
        Q = np.array([[-s, -c], [c, -s]])
        dQ = np.array([[-c, s], [-s, -c]])
        return Q, dQ, -Q

    def phi_cut(self, theta: np.ndarray) -> np.ndarray:
        """The lesson's closure in the coupler's cut frame, Q(theta3)^T phi, shape (2,) [m]."""
        Q, _, _ = self.cut_basis(theta[1])
        return Q.T @ self.phi(theta)

    def jacobian_cut(self, theta: np.ndarray) -> np.ndarray:
        """d phi_cut / d theta = Q^T J_c + (dQ^T phi) e3^T, shape (2, 3) [m]."""
        Q, dQ, _ = self.cut_basis(theta[1])
        J = Q.T @ self.jacobian(theta)
        J[:, 1] += dQ.T @ self.phi(theta)
        return J

    def gamma_cut(self, theta: np.ndarray, theta_dot: np.ndarray) -> np.ndarray:
        """d^2/dt^2 phi_cut at zero angular acceleration, shape (2,) [m/s^2]:
        Q''^T phi w3^2 + 2 w3 Q'^T J_c theta_dot + Q^T Jdot_c theta_dot."""
        Q, dQ, ddQ = self.cut_basis(theta[1])
        w3 = theta_dot[1]
        return (
            ddQ.T @ self.phi(theta) * w3**2
            + 2.0 * w3 * dQ.T @ (self.jacobian(theta) @ theta_dot)
            + Q.T @ (self.jacobian_dot(theta, theta_dot) @ theta_dot)
        )

    def freudenstein(self, theta2: float) -> list[np.ndarray]:
        r"""Return both assembly branches ``theta = [theta2, theta3, theta4]`` at a crank angle.

        Freudenstein's equation (Norton, Design of Machinery, Sec. 4.5),

        .. math::

            K_1 \cos\theta_4 - K_2 \cos\theta_2 + K_3 = \cos(\theta_2 - \theta_4),
            \quad K_1 = d/a,\; K_2 = d/c,\; K_3 = (a^2 - b^2 + c^2 + d^2) / (2 a c),

        with t = tan(theta4 / 2) becomes A t^2 + B t + C = 0, A = cos th2 - K1 -
        K2 cos th2 + K3, B = -2 sin th2, C = K1 - (K2 + 1) cos th2 + K3, so
        theta4 = 2 atan2(-B -+ sqrt(B^2 - 4 A C), 2 A) (open, crossed); theta3
        follows from the closure b e(theta3) = D + c e(theta4) - a e(theta2).
        """
        a, b, c, d = self.a, self.b, self.c, self.d
        K1, K2, K3 = d / a, d / c, (a * a - b * b + c * c + d * d) / (2.0 * a * c)
        c2, s2 = math.cos(theta2), math.sin(theta2)
        A = c2 - K1 - K2 * c2 + K3
        B = -2.0 * s2
        C = K1 - (K2 + 1.0) * c2 + K3
        disc = B * B - 4.0 * A * C
        if disc < 0.0:
            raise ValueError(f"no assembly at theta2 = {theta2} (discriminant {disc})")
        out = []
        for sign in (-1.0, 1.0):
            th4 = 2.0 * math.atan2(-B + sign * math.sqrt(disc), 2.0 * A)
            th3 = math.atan2(c * math.sin(th4) - a * s2, d + c * math.cos(th4) - a * c2)
            out.append(np.array([theta2, th3, th4]))
        return out


@pytest.fixture(scope="session")
def fourbar_closed_forms() -> FourBarClosedForms:
    return FourBarClosedForms()


@pytest.fixture(scope="session")
def angle_difference():
    """Return ``f(x, y)``: x - y wrapped into [-pi, pi), elementwise [rad]."""
    return lambda x, y: (np.asarray(x) - np.asarray(y) + np.pi) % (2.0 * np.pi) - np.pi


# -- kinematic trajectories (drive some joints, assemble the rest) ----------------------


def sweep_trajectory(
    mech: cc.Mechanism,
    drives: dict[str, Callable[[float], float]],
    t: np.ndarray,
    *,
    q_start: np.ndarray | None = None,
) -> cc.Trajectory:
    """Return a kinematic trajectory: drive some joints, assemble the rest.

    Each driven joint (a 1-dof joint) follows its function of time; at every
    sample the others are assembled onto phi = 0 holding the driven ones,
    warm-started from the previous sample (so the assembly mode is kept).
    v, a, lam, residuals and energy are zeros of the right shapes.

    Args:
        mech: the mechanism.
        drives: joint name -> angle [rad] (or position [m]) as a function of time [s].
        t: sample times [s], shape (N,).
        q_start: first guess, shape (nq,); default ``mech.q_ref``.
    """
    model = mech.model
    idx_q = {name: model.joints[model.getJointId(name)].idx_q for name in drives}
    q = np.array(mech.q_ref if q_start is None else q_start, dtype=float)
    qs = np.empty((len(t), mech.nq))
    for k, tk in enumerate(t):
        for name, f in drives.items():
            q[idx_q[name]] = f(float(tk))
        q = cc.assemble(mech, q, fixed=list(drives))
        qs[k] = q
    return kinematic_trajectory(
        mech, t, qs, info={"mechanism": mech.name, "method": "kinematic sweep"}
    )


def kinematic_trajectory(
    mech: cc.Mechanism, t: np.ndarray, q: np.ndarray, *, info: dict | None = None
) -> cc.Trajectory:
    """Return a Trajectory of the configurations q, shape (N, nq), at times t [s];
    v, a, lam, residuals and energy are zeros of the right shapes."""
    n = len(t)
    return cc.Trajectory(
        t=np.asarray(t, dtype=float),
        q=np.asarray(q, dtype=float),
        v=np.zeros((n, mech.nv)),
        a=np.zeros((n, mech.nv)),
        lam=np.zeros((n, mech.nc)),
        constraint_residual=np.zeros(n),
        velocity_residual=np.zeros(n),
        energy=np.zeros(n),
        info={} if info is None else info,
    )


#: Crank swing of the 4-bar about q_ref [rad]: keeps clear of its change point
#: at theta2 = 180 deg (a + d = b + c).
FOURBAR_SWING = 0.8
#: Actuator swing of the Agile Eye about its home configuration [rad].
AGILE_EYE_SWING = 0.35
#: Period of the sweeps [s].
SWEEP_PERIOD = 2.0


def fourbar_sweep(mech: cc.Mechanism, t: np.ndarray) -> cc.Trajectory:
    """Swing the 4-bar's crank sinusoidally about its reference angle."""
    q0 = float(mech.q_ref[0])
    w = 2 * np.pi / SWEEP_PERIOD
    return sweep_trajectory(mech, {"crank_joint": lambda s: q0 + FOURBAR_SWING * np.sin(w * s)}, t)


def agile_eye_sweep(mech: cc.Mechanism, t: np.ndarray) -> cc.Trajectory:
    """Swing the Agile Eye's three actuators by phase-shifted sinusoids about 0."""
    w = 2 * np.pi / SWEEP_PERIOD
    drives = {
        f"actuator_{i + 1}": (lambda s, i=i: AGILE_EYE_SWING * np.sin(w * s + 2 * np.pi * i / 3))
        for i in range(3)
    }
    return sweep_trajectory(mech, drives, t)


@pytest.fixture(scope="session")
def fourbar_traj(fourbar) -> cc.Trajectory:
    """4 s of crank swing sampled at 100 Hz (not the display rate)."""
    return fourbar_sweep(fourbar, np.linspace(0.0, 4.0, 401))


@pytest.fixture(scope="session")
def agile_eye_traj(agile_eye) -> cc.Trajectory:
    """4 s of actuator swing sampled at 100 Hz (not the display rate)."""
    return agile_eye_sweep(agile_eye, np.linspace(0.0, 4.0, 401))


@pytest.fixture(scope="session")
def short_traj(fourbar) -> cc.Trajectory:
    """0.2 s of the 4-bar released from rest at q_ref, simulated (rk4, 10 ms)."""
    return cc.simulate(fourbar, fourbar.q_ref, np.zeros(3), 0.2, integrator="rk4", dt=1e-2)


#: 4-bars of the 4-bar's nq that a 4-bar trajectory does not belong to: other joint
#: names (the rocker's joint renamed), and the same joints with the rocker's loop pin
#: 0.32 m from its pivot instead of 0.3 m.
FOURBAR_LOOKALIKES = {
    "renamed": ("rocker_joint", "rocker_pivot"),
    "longer_rocker": ('<successor_origin xyz="0.3 0 0"', '<successor_origin xyz="0.32 0 0"'),
}


@pytest.fixture(scope="session")
def fourbar_lookalikes(tmp_path_factory) -> dict[str, cc.Mechanism]:
    """Name -> mechanism of :data:`FOURBAR_LOOKALIKES`, each written to its own file."""
    text = (MODELS / "fourbar.urdf").read_text()
    folder = tmp_path_factory.mktemp("lookalikes")
    out = {}
    for name, (old, new) in FOURBAR_LOOKALIKES.items():
        assert old in text
        path = folder / f"{name}.urdf"
        path.write_text(text.replace(old, new))
        out[name] = cc.load(path)
    return out


@pytest.fixture(scope="module")
def nfourbar(tmp_path_factory):
    """``get(n) -> Mechanism``: the N-four-bar, the shipped model when there is one
    (models/nfourbar_2.urdf, nfourbar_40.urdf), else written by ``nfourbar_urdf``;
    each N loaded once per test module."""
    cache: dict[int, cc.Mechanism] = {}
    folder = tmp_path_factory.mktemp("nfourbar")

    from closedchain.benchmark.families import nfourbar_urdf

    def get(n: int) -> cc.Mechanism:
        if n not in cache:
            path = MODELS / f"nfourbar_{n}.urdf"
            if not path.exists():
                path = folder / f"nfourbar_{n}.urdf"
                path.write_text(nfourbar_urdf(n))
            cache[n] = cc.load(path)
        return cache[n]

    return get


#: The crank's <limit> of models/fourbar.urdf (+-2 pi).
FOURBAR_CRANK_LIMIT = '<limit lower="-6.283185307179586" upper="6.283185307179586" effort="50"'


def fourbar_with_crank_limits(directory: Path, lower: float, upper: float) -> Path:
    """Write models/fourbar.urdf with the crank's <limit> set to [lower, upper] [rad] into
    ``directory``; return the file's path."""
    text = (MODELS / "fourbar.urdf").read_text()
    assert text.count(FOURBAR_CRANK_LIMIT) == 1
    text = text.replace(
        FOURBAR_CRANK_LIMIT, f'<limit lower="{lower!r}" upper="{upper!r}" effort="50"'
    )
    path = directory / "fourbar_limited.urdf"
    path.write_text(text)
    return path
