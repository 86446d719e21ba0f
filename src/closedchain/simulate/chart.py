"""Local coordinates for the adaptive integrators when nq != nv.

scipy's integrators (and the compiled Dormand-Prince loops, which reproduce
them) add stage increments to a state vector, so a configuration with unit
quaternions or (cos, sin) pairs cannot be their state. They integrate instead
the chart coordinate x in R^nv of q = integrate(q_c, x) (``pin.integrate``)
about a centre q_c, with

    dx/dt = D(x)^-1 v,   D(x) = d integrate(q_c, x) / dx   (``pin.dIntegrate``, ARG1).

For joints whose configuration space is a vector space (nq == nv) or a circle
(continuous joints: nv == 1) D is the identity block and the chart covers the
whole motion: this is what a user's script does with ``pin.integrate(q0, x)``.
For free-flyer, spherical and planar joints D is the right Jacobian of the
exponential map, which degenerates at rotation angles of 2 pi: the chart is
re-centred (q_c <- integrate(q_c, x), x <- 0) at the end of a step where such
a joint's block of x exceeds ``RECENTRE_NORM``. The error control measures x and
v, as scipy does for a vector state.

The fixed-step rk4 uses the same map with the chart centred at the step's start
(Runge-Kutta-Munthe-Kaas with the exact D^-1): adding the stages' velocities v_i,
each expressed at its own stage configuration, would be second order only on a
rotating free-flyer.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

#: Re-centre the chart when a curved joint's block of x exceeds this norm [rad or m]
#: (its D stays well conditioned: cond(D) <= 1.1 for a rotation of 1 rad).
RECENTRE_NORM = 1.0

#: cond(D) of a joint's block beyond which its chart has degenerated: the rotation within
#: one step came within about 1e-6 rad of 2 pi (cond(D) ~ 2 pi / distance).
DEGENERATE_COND = 1e6


def curved_blocks(model: pin.Model) -> list[slice]:
    """The velocity blocks of the joints whose ``integrate`` is not x + v (nv > 1, nq != nv)."""
    return [slice(j.idx_v, j.idx_v + j.nv) for j in model.joints[1:] if j.nv > 1 and j.nq != j.nv]


_CURVED: dict[int, tuple[pin.Model, list[slice]]] = {}


def _curved(model: pin.Model) -> list[slice]:
    hit = _CURVED.get(id(model))
    if hit is None or hit[0] is not model:
        hit = _CURVED[id(model)] = (model, curved_blocks(model))
    return hit[1]


def tangent_rate(model: pin.Model, q_c: np.ndarray, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """dx/dt of q = integrate(q_c, x) moving with velocity v: D(x)^-1 v, joint by joint."""
    curved = _curved(model)
    if not curved:
        return v
    D = pin.dIntegrate(model, q_c, x, pin.ArgumentPosition.ARG1)
    out = np.array(v, dtype=float)
    for b in curved:
        if np.linalg.cond(D[b, b]) > DEGENERATE_COND:
            # A joint turned by about 2 pi within one step (the state has diverged): a
            # non-finite rate, which the integrator's checks report with the time.
            out[b] = np.nan
        else:
            out[b] = np.linalg.solve(D[b, b], v[b])
    return out


class Chart:
    """q = integrate(q_c, x) about a movable centre q_c (see the module docstring)."""

    def __init__(self, model: pin.Model, q_centre: np.ndarray) -> None:
        self.model = model
        self.centre = np.array(q_centre, dtype=float)
        self.curved = curved_blocks(model)

    def q(self, x: np.ndarray) -> np.ndarray:
        """The configuration of chart coordinate x."""
        return pin.integrate(self.model, self.centre, x)

    def x(self, q: np.ndarray) -> np.ndarray:
        """The chart coordinate of configuration q."""
        return pin.difference(self.model, self.centre, q)

    def rate(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """dx/dt for velocity v at x: v where D is the identity, D(x)^-1 v elsewhere."""
        return tangent_rate(self.model, self.centre, x, v)

    def needs_recentre(self, x: np.ndarray) -> bool:
        return any(np.linalg.norm(x[b]) > RECENTRE_NORM for b in self.curved)

    def recentre(self, x: np.ndarray) -> None:
        self.centre = self.q(x)
