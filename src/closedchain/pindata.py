"""One place that creates ``pinocchio.Data``, and its memory cost.

``pinocchio.Data(model)`` in Pinocchio 4.1 allocates and zeroes four
nv x nv x nv tensors (``d2tau_dqdq``, ``d2tau_dvdv``, ``d2tau_dqdv``,
``d2tau_dadq``; ``src/multibody/data.hxx`` of the pin wheel's headers): 32 nv^3
bytes that only ``computeRNEASecondOrderDerivatives`` reads, and 32 GB for a
1000-joint chain. ``setZero()`` touches every page, so Linux overcommit does not
help. The compiled core's ``lean_data`` builds the same Data without them
(src/cpp/lean_data.cpp, checked field by field against Pinocchio's constructor
in tests/test_pindata.py); every algorithm closedchain calls reads the same
fields either way. Without the compiled core, :func:`new_data` falls back to
``pinocchio.Data(model)``.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin

__all__ = [
    "data_bytes",
    "max_nv_for",
    "new_data",
]

try:
    from . import _core
except ImportError:  # pragma: no cover - a build without the compiled core
    _core = None

#: Measured memory [bytes] of one lean Data per nv^2 (planar chains, pin 4.1:
#: 618, 571, 561 at nv = 300, 1000, 2000; nv x nv matrices such as M, Minv,
#: the derivative matrices and the joint-torque regressor).
LEAN_DATA_BYTES_PER_NV2 = 620

#: Memory [bytes] of one ``pinocchio.Data(model)`` per nv^3 (measured 33.7, 33.0
#: at nv = 200, 300: the four tensors above). ``model.createData()`` returns a
#: copy and peaks at twice that, so closedchain never calls it.
PINOCCHIO_DATA_BYTES_PER_NV3 = 33


def lean_available() -> bool:
    """Return True when Data without the nv^3 tensors can be built (compiled core present)."""
    return _core is not None


def new_data(model: pin.Model) -> pin.Data:
    """Return a fresh ``pinocchio.Data`` of ``model``, without the nv^3 tensors when possible.

    Args:
        model: the Pinocchio model.

    Returns:
        A Data usable by every Pinocchio algorithm except
        ``computeRNEASecondOrderDerivatives`` (whose tensors it lacks when the
        compiled core is present).
    """
    if _core is not None:
        return _core.lean_data(model)
    return pin.Data(model)


def data_bytes(nv: int) -> float:
    """Return the memory [bytes] one Data of :func:`new_data` takes for ``nv`` dofs."""
    if _core is not None:
        return LEAN_DATA_BYTES_PER_NV2 * float(nv) ** 2
    return PINOCCHIO_DATA_BYTES_PER_NV3 * float(nv) ** 3


def data_cost_formula() -> str:
    """Return how :func:`data_bytes` grows, for messages."""
    if _core is not None:
        return (
            f"about {LEAN_DATA_BYTES_PER_NV2} nv^2 bytes (Pinocchio Data without its nv^3 tensors)"
        )
    return (
        f"about {PINOCCHIO_DATA_BYTES_PER_NV3} nv^3 bytes (Pinocchio Data's second-order "
        "derivative tensors; the compiled core, which avoids them, is not built)"
    )


def max_nv_for(budget: float) -> int:
    """Return the largest nv with :func:`data_bytes` (nv) <= ``budget`` [bytes]."""
    if _core is not None:
        n = int(math.sqrt(budget / LEAN_DATA_BYTES_PER_NV2))
    else:
        n = int((budget / PINOCCHIO_DATA_BYTES_PER_NV3) ** (1 / 3))
    while data_bytes(n + 1) <= budget:
        n += 1
    while n > 0 and data_bytes(n) > budget:
        n -= 1
    return n


def frame_jacobian(
    model: pin.Model, data: pin.Data, frame_id: int, reference: pin.ReferenceFrame
) -> np.ndarray:
    """Return ``pin.getFrameJacobian`` as a matrix, shape (6, nv), for every nv.

    Pinocchio's Python layer returns a 6 x 1 Jacobian (a mechanism with one degree
    of freedom) as a vector of shape (6,); the rows are the same.

    Args:
        model: the Pinocchio model.
        data: its Data, with the joint Jacobians computed at q.
        frame_id: the frame's index in ``model.frames``.
        reference: the frame the Jacobian is expressed in (``pin.LOCAL``, ...).
    """
    return np.reshape(pin.getFrameJacobian(model, data, frame_id, reference), (6, model.nv))
