"""The driven slider-crank (tests/data/slider_crank_driven.urdf) in closed form.

Its one-degree-of-freedom Lagrange equation in the crank angle, written here
independently of closedchain, integrated by scipy's DOP853 at 1e-12: the reference of
tests/test_rk43.py, tests/test_dop853_rk43.py and scripts/bench_front.py.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.integrate

#: tests/data/slider_crank_driven.urdf: crank and rod lengths [m], crank, rod and slider
#: masses [kg] (uniform thin rods), the crank torque [N m] and the horizon [s].
CRANK, ROD = 0.1, 0.35
CRANK_MASS, ROD_MASS, SLIDER_MASS = 1.5, 1.0, 2.0
TORQUE = 1.5
T_DRIVEN = 2.0


def inertia_and_slope(theta: float) -> tuple[float, float]:
    r"""The slider-crank's generalized inertia I(theta) [kg m^2] and dI/dtheta.

    Slider on the x axis through the crank pivot A; lam = r / L, s = sin theta,
    c = cos theta, k = sqrt(1 - lam^2 s^2): rod angle psi with sin psi = -lam s,
    slider x = r c + L k, rod centre G = B + (L / 2)(cos psi, sin psi), and

    .. math::

        I = \frac{m_c r^2}{3} + m_r |G'|^2 + \frac{m_r L^2}{12} \psi'^2 + m_s x'^2

    (primes: d / d theta).
    """
    r, L, lam = CRANK, ROD, CRANK / ROD
    s, c = math.sin(theta), math.cos(theta)
    k = math.sqrt(1.0 - lam**2 * s**2)
    dk = -(lam**2) * s * c / k
    dpsi = -lam * c / k
    ddpsi = lam * s / k - lam**3 * s * c**2 / k**3
    dx = -r * s * (1.0 + lam * c / k)
    ddx = -r * c * (1.0 + lam * c / k) + r * lam * s**2 / k - r * lam**3 * s**2 * c**2 / k**3
    a = L / 2.0
    dG = np.array([-r * s + a * dpsi * lam * s, r * c + a * dpsi * k])
    ddG = np.array(
        [-r * c + a * lam * (ddpsi * s + dpsi * c), -r * s + a * (ddpsi * k + dpsi * dk)]
    )
    i_g = ROD_MASS * L**2 / 12.0
    inertia = CRANK_MASS * r**2 / 3.0 + ROD_MASS * dG @ dG + i_g * dpsi**2 + SLIDER_MASS * dx**2
    d_inertia = 2.0 * ROD_MASS * dG @ ddG + 2.0 * i_g * dpsi * ddpsi + 2.0 * SLIDER_MASS * dx * ddx
    return float(inertia), float(d_inertia)


def slider(theta: float) -> float:
    """Slider position x [m] at crank angle theta [rad]."""
    lam = CRANK / ROD
    return CRANK * math.cos(theta) + ROD * math.sqrt(1.0 - lam**2 * math.sin(theta) ** 2)


#: Tolerances (rtol = atol) of the reference's DOP853.
REFERENCE_TOL = 1e-12


def crank_state(t_final: float = T_DRIVEN, tol: float = REFERENCE_TOL) -> tuple[float, float]:
    """(theta [rad], thetadot [rad/s]) at t_final [s] from rest at theta = 0: the Lagrange
    equation I(theta) theta'' + I'(theta) theta'^2 / 2 = TORQUE by DOP853 at ``tol``."""

    def rhs(_, y):
        inertia, d_inertia = inertia_and_slope(y[0])
        return [y[1], (TORQUE - 0.5 * d_inertia * y[1] ** 2) / inertia]

    sol = scipy.integrate.solve_ivp(
        rhs, (0.0, t_final), [0.0, 0.0], method="DOP853", rtol=tol, atol=tol
    )
    return float(sol.y[0, -1]), float(sol.y[1, -1])


def start_state(mech):
    """(q0, v0, tau) of the driven run: crank and rod along x (continuous joints: cos,
    sin), the slider at r + L, at rest, the crank torque [N m]."""
    import closedchain as cc

    q0 = cc.assemble(mech, np.array([1.0, 0.0, 1.0, 0.0, CRANK + ROD]), fixed=["crank_joint"])
    return q0, np.zeros(mech.nv), np.array([TORQUE, 0.0, 0.0])
