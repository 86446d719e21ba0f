"""The N-four-bar (IFToMM benchmark A02): generator, model and the quadrature reference.

The reference (``tests/nfourbar_reference.py``) shares no code with closedchain: it is
the energy integral of the one-degree-of-freedom parallelogram motion.
"""

from __future__ import annotations

import math

import nfourbar_reference as ref
import numpy as np
import pinocchio as pin
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain.benchmark.families import nfourbar_urdf

#: Loop counts of the benchmark runs and of the shipped models.
N_VALUES = (1, 2, 5, 10, 20, 40)
SHIPPED = (2, 40)
#: Benchmark horizon [s].
T_BENCHMARK = 20.0
#: The two quadratures agree to this [rad].
REFERENCE_AGREEMENT_TOL = 1e-12
#: Model vs closed form: energy [J], position [m], closure [m] (round-off).
MODEL_TOL = 1e-12


@pytest.mark.parametrize("n", N_VALUES)
def test_reference_two_ways(n):
    """scipy quad + brentq and 30-digit mpmath give the same crank angle at 20 s."""
    a = ref.crank_angle(n, T_BENCHMARK)
    b = ref.crank_angle_mp(n, T_BENCHMARK)
    assert abs(a - b) <= REFERENCE_AGREEMENT_TOL


def test_reference_is_a_rotation_through_the_flat_positions():
    """The crank turns through theta = 0 and pi (all rods flat) about 10 times in 20 s."""
    for n in N_VALUES:
        # thetadot^2 = 1 + k (1 - cos(turned)) >= 1: never zero, so a rotation.
        turned = math.pi / 2 - ref.crank_angle(n, T_BENCHMARK)
        assert turned > 2 * math.pi * 9  # measured: 9.9 to 10.1 turns
        _, _, k = ref.constants(n)


def test_reference_against_an_ode_at_short_time():
    """Third way, at 1 s: the pendulum ODE of the reduced motion, DOP853 at 1e-13."""
    import scipy.integrate

    n = 3
    inertia, c, _ = ref.constants(n)
    sol = scipy.integrate.solve_ivp(
        lambda t, y: [y[1], -ref.GRAVITY * c * math.cos(y[0]) / inertia],
        (0.0, 1.0),
        [math.pi / 2, ref.OMEGA0],
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    assert abs(sol.y[0, -1] - ref.crank_angle(n, 1.0)) <= 1e-10


@pytest.mark.parametrize("n", SHIPPED)
def test_shipped_models_are_the_generator_output(n):
    assert (MODELS / f"nfourbar_{n}.urdf").read_text() == nfourbar_urdf(n)


def test_generator_rejects_bad_n():
    with pytest.raises(ValueError, match="N must be a positive number of loops"):
        nfourbar_urdf(0)


@pytest.mark.parametrize("n", (1, 2, 5))
def test_model_matches_the_reduced_motion(nfourbar, n):
    """At the start and along the parallelogram motion, closure, B0 and energy match the
    closed forms the reference is built on (masses, inertias, lengths, coordinates)."""
    mech = nfourbar(n)
    assert mech.nv == 2 * n + 1 and mech.nc == 2 * n and mech.mobility == 1
    q0, v0 = ref.initial_state(mech)
    assert mech.constraints.nc == 2 * n
    model, data = mech.model, mech.data
    for theta, thetadot in ((math.pi / 2, -1.0), (0.3, 2.0), (-2.0, -3.5), (math.pi, 1.0)):
        # Parallelogram: every crank at theta, every coupler at -theta relative to its crank.
        q = np.where(q0 > 0, theta, -theta)
        v = np.where(v0 < 0, thetadot, -thetadot)
        pin.forwardKinematics(model, data, q)
        pin.updateFramePlacements(model, data)
        b0 = data.oMf[model.getFrameId(mech.coordinate_names[0].replace("_joint", "_tip"))]
        assert np.linalg.norm(b0.translation - ref.point_b0(theta)) <= MODEL_TOL
        phi = np.zeros(mech.nc)
        mech.constraints.evaluate(model, data, phi=phi)
        assert np.linalg.norm(phi) <= MODEL_TOL
        energy = pin.computeKineticEnergy(model, data, q, v) + pin.computePotentialEnergy(
            model, data, q
        )
        assert abs(energy - ref.energy(n, theta, thetadot)) <= MODEL_TOL * 100


@pytest.mark.slow
def test_nfourbar_40_keeps_every_independent_row():
    """Two rows per loop (t1, t2 of 5 declared): the scene's start seeds the row sampling
    (random assemblies of 40 loops fall onto flat positions: 77 of 80 rows were kept)."""
    mech = cc.load(MODELS / "nfourbar_40.urdf")
    assert mech.closure.selection.rank == 80
    assert mech.nc == 80
    assert {r.kind for r in mech.constraints.rows} == {"t1", "t2"}
