"""The minimum-torque Agile Eye example (scripts/agile_eye_min_torque.py) at a small size.

Multiple shooting with rk4 steps and their analytical derivatives, solved by SLSQP: it
must converge, reach the target orientation at rest, and leave dynamics defects below a
named tolerance.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "agile_eye_min_torque.py"
#: The small problem: shooting intervals, duration [s], SLSQP tolerance (measured: 23 s
#: CPU, 23 iterations).
N_INTERVALS = 4
T_FINAL = 0.4
FTOL = 1e-6
#: Largest terminal orientation error [rad] and rate [rad/s] (measured: 0, SLSQP meets
#: linear constraints exactly).
TERMINAL_TOL = 1e-9
#: Largest dynamics defect |x_k+1 - F_h(x_k, u_k)| [rad, rad/s] (measured: 1.1e-8).
DEFECT_TOL = 1e-6
#: The effort against the one at FTOL 1e-10, relative (measured: 0.022354186 against
#: 0.022354186: 3e-8).
EFFORT_RTOL = 1e-5
EFFORT_REFERENCE = 0.0223541859432265  # [N^2 m^2 s]


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("agile_eye_min_torque", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks the module up
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


def test_minimum_torque_reorientation_converges(example):
    r = example.solve(N_INTERVALS, T_FINAL, ftol=FTOL)
    assert r.success, r.message
    assert r.orientation_error <= TERMINAL_TOL
    assert r.terminal_rate <= TERMINAL_TOL
    assert r.max_defect <= DEFECT_TOL
    assert abs(r.effort - EFFORT_REFERENCE) <= EFFORT_RTOL * EFFORT_REFERENCE
    # The nodes are states of the mechanism: on phi = 0 and J v = 0.
    import closedchain as cc

    mech = cc.load(example.MODEL)
    for q, v in zip(r.q, r.v, strict=True):
        assert np.max(np.abs(cc.compute_phi(mech, q))) <= DEFECT_TOL
        assert np.max(np.abs(cc.compute_jacobian(mech, q) @ v)) <= DEFECT_TOL
    np.testing.assert_allclose(
        r.q[-1, mech.coordinate_indices(list(example.PLATFORM))], example.TARGET, atol=TERMINAL_TOL
    )
