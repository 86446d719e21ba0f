"""Small array helpers of the per-evaluation path."""

from __future__ import annotations

import numpy as np


def same_array(a: np.ndarray, b: np.ndarray | None) -> bool:
    """Return whether ``a`` and ``b`` hold the same float64 values bit for bit (a memo's
    key check: -0.0 and 0.0 differ, which only costs a recomputation).

    Comparing the bytes is ~15 times cheaper than ``np.array_equal`` for the vectors and
    small matrices of one evaluation (81 coordinates: 0.08 us against 1.2 us).
    """
    return b is not None and a.shape == b.shape and a.tobytes() == b.tobytes()
