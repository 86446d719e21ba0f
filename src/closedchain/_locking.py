"""One mechanism, many threads: the public functions take turns on a Mechanism.

A :class:`~closedchain.Mechanism` keeps state between calls, as Pinocchio's
``Data`` does: the Pinocchio data, the dynamics workspaces, the factorization
of the augmented-Lagrangian method, the compiled core's buffers, and the row
selection that a simulation may change.
Two threads working on one mechanism at once would overwrite each other's
intermediate results and get wrong numbers without an error. Every public
function that reads or writes that state is therefore decorated with
:func:`exclusive`: it holds the mechanism's re-entrant lock while it runs, so
calls on one mechanism from several threads run one after the other and give
the results of a serial run. Neither the numpy path nor the compiled core
releases the GIL, so a lock costs no parallelism; for parallel work, load one
mechanism per thread or per process (:func:`closedchain.load` is
deterministic: the same rows, partition and results).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from .exceptions import NonFiniteError

F = TypeVar("F", bound=Callable)

#: numpy's error state inside every public function: an overflow, a division by zero or
#: an invalid operation raises FloatingPointError, which :func:`exclusive` reports as
#: NonFiniteError, instead of a RuntimeWarning on stderr and a NaN carried on. Code that
#: expects such values (an infinite condition number) must say so with its own errstate.
FLOATING_POINT_ERRORS = {"over": "raise", "divide": "raise", "invalid": "raise"}


def exclusive(func: F) -> F:
    """Run ``func`` holding the lock of the Mechanism given as its first argument.

    The lock is re-entrant: a decorated function may call another one (or a
    simulation's ``tau`` callback may call :func:`closedchain.inverse_dynamics`)
    on the same mechanism in the same thread.
    """

    @functools.wraps(func)
    def locked(mech, *args, **kwargs):
        with mech.lock, np.errstate(**FLOATING_POINT_ERRORS):
            try:
                return func(mech, *args, **kwargs)
            except FloatingPointError as exc:
                raise NonFiniteError(
                    f"{mech.name}: {func.__name__}: floating-point {exc} (a value too large "
                    "or too small for double precision: check the model's numbers and the "
                    "arguments' magnitudes)"
                ) from None

    return locked  # type: ignore[return-value]
