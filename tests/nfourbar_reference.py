r"""Independent reference motion of the N-four-bar (IFToMM benchmark A02), by quadrature.

Every loop of ``models/nfourbar_<N>.urdf`` (``scripts/make_nfourbar.py``) is a
parallelogram: on the branch the benchmark follows, all N + 1 cranks keep one
angle theta (from the ground line, world x towards world z) and the N couplers
translate, with the velocity of a crank tip. With rods of mass m and length L:

.. math::

    T = \tfrac12 I \dot\theta^2, \quad
    I = (N + 1) \frac{m L^2}{3} + N m L^2, \qquad
    V = g\, c \sin\theta, \quad c = (N + 1) \frac{m L}{2} + N m L.

The benchmark starts at theta = pi/2 with thetadot = -1 rad/s (every crank
turning, the couplers moving at +1 m/s along world x). Energy gives, with
phi = pi/2 - theta (the angle turned),

.. math::

    \dot\phi^2 = 1 + k (1 - \cos\phi), \qquad k = 2 g c / I,

which never vanishes (the motion is a full rotation: the cranks pass the flat,
singular positions phi = pi/2 and 3 pi/2 at speed), so
``t(phi) = int_0^phi dphi' / sqrt(1 + k (1 - cos phi'))``. The crank angle at
time t is found by inverting t(phi): whole periods P = t(2 pi), then a root of
the remainder. It is computed two ways: scipy ``quad`` + ``brentq`` in double
precision, and mpmath at 30 digits (``quad`` + ``findroot``); the two agree to
1e-12 rad (tests/test_nfourbar.py).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.integrate
import scipy.optimize

#: The benchmark's data: rod length [m], rod mass [kg], gravity [m/s^2], crank rate [rad/s].
LENGTH = 1.0
MASS = 1.0
GRAVITY = 9.81
OMEGA0 = -1.0
#: Absolute tolerance of the double-precision quadratures [s] and root [rad].
QUAD_TOL = 1e-14
#: Relative tolerance of the quadratures (below it quad reports round-off).
QUAD_REL = 1e-13
#: Digits of the mpmath reference.
MP_DIGITS = 30


def constants(n: int) -> tuple[float, float, float]:
    """Return (I [kg m^2], c [kg m], k [1/s^2]) of the reduced one-degree-of-freedom motion."""
    inertia = (n + 1) * MASS * LENGTH**2 / 3.0 + n * MASS * LENGTH**2
    c = (n + 1) * MASS * LENGTH / 2.0 + n * MASS * LENGTH
    return inertia, c, 2.0 * GRAVITY * c / inertia


def _rate(phi: float, k: float) -> float:
    """Return dphi/dt [rad/s] at angle turned phi (|OMEGA0| = 1 rad/s)."""
    return math.sqrt(OMEGA0**2 + k * (1.0 - math.cos(phi)))


def crank_angle(n: int, t: float) -> float:
    """Return the crank angle theta(t) [rad] (unwrapped: pi/2 - angle turned), double precision."""
    _, _, k = constants(n)

    def time_to(phi: float) -> float:
        return scipy.integrate.quad(
            lambda p: 1.0 / _rate(p, k), 0.0, phi, epsabs=QUAD_TOL, epsrel=QUAD_REL, limit=200
        )[0]

    period = time_to(2.0 * math.pi)
    turns = math.floor(t / period)
    rest = t - turns * period
    phi = scipy.optimize.brentq(lambda p: time_to(p) - rest, 0.0, 2.0 * math.pi, xtol=QUAD_TOL)
    return math.pi / 2.0 - (2.0 * math.pi * turns + phi)


def crank_angle_mp(n: int, t: float) -> float:
    """Return theta(t) [rad] as :func:`crank_angle`, computed with mpmath at MP_DIGITS digits."""
    import mpmath as mp

    with mp.workdps(MP_DIGITS):
        inertia = mp.mpf(n + 1) / 3 + n
        c = mp.mpf(n + 1) / 2 + n
        k = 2 * mp.mpf(GRAVITY) * c / inertia

        def time_to(phi):
            return mp.quad(lambda p: 1 / mp.sqrt(1 + k * (1 - mp.cos(p))), [0, phi])

        period = time_to(2 * mp.pi)
        tt = mp.mpf(t)
        turns = mp.floor(tt / period)
        rest = tt - turns * period
        # Newton on t(phi) = rest: dt/dphi = 1 / rate.
        phi = mp.findroot(
            lambda p: time_to(p) - rest, rest, df=lambda p: 1 / mp.sqrt(1 + k * (1 - mp.cos(p)))
        )
        return float(mp.pi / 2 - (2 * mp.pi * turns + phi))


def point_b0(theta: float) -> np.ndarray:
    """Return the world position [m] of B0, the tip of crank 0 (crank pivot at the origin)."""
    return np.array([LENGTH * math.cos(theta), 0.0, LENGTH * math.sin(theta)])


def initial_state(mech) -> tuple[np.ndarray, np.ndarray]:
    """Return the benchmark's (q0, v0): cranks vertical, couplers horizontal, crank rate OMEGA0.

    Coordinates of scripts/make_nfourbar.py: crank joints hold the absolute crank angle,
    coupler joints the coupler's angle relative to its parent crank.
    """
    q0 = np.zeros(mech.nq)
    v0 = np.zeros(mech.nv)
    for i, name in enumerate(mech.coordinate_names):
        if name.startswith("crank"):
            q0[i], v0[i] = math.pi / 2.0, OMEGA0
        else:
            q0[i], v0[i] = -math.pi / 2.0, -OMEGA0
    return q0, v0


def energy(n: int, theta: float, theta_dot: float) -> float:
    """Return the energy [J] of the parallelogram motion (zero potential at the ground line)."""
    inertia, c, _ = constants(n)
    return 0.5 * inertia * theta_dot**2 + GRAVITY * c * math.sin(theta)


def characteristic_energy(n: int) -> float:
    """Return the energy scale [J] of the drift measure: the largest kinetic energy of the motion.

    Reached at the lowest crank position (theta = -pi/2): 1/2 I (1 + 2 k).
    """
    inertia, _, k = constants(n)
    return 0.5 * inertia * (OMEGA0**2 + 2.0 * k)
