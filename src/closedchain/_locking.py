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
the results of a serial run. The compiled integration loops release the GIL
(src/cpp/gil.hpp), the numpy path does not: for parallel work, give each thread
its own mechanism, a :func:`replica` (:func:`closedchain.simulate_batch` does) or
one loaded per thread or process (:func:`closedchain.load` is deterministic: the
same rows, partition and results).
"""

from __future__ import annotations

import copy
import functools
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from .exceptions import NonFiniteError
from .pindata import new_data

if TYPE_CHECKING:
    from .mechanism import Mechanism

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


#: Attributes of a Mechanism whose name starts with an underscore that are part of its
#: model, not a cache (:func:`replica` copies them; every other one is a cache, dropped).
_MODEL_ATTRIBUTES = frozenset({"_revolute_idx_q"})
#: Caches that :class:`~closedchain.Mechanism` declares in its constructor (as it does).
_DECLARED_CACHES = ("_pin_constraints", "_workspace")


def replica(mech: Mechanism) -> Mechanism:
    """Return a copy of ``mech`` as :func:`closedchain.load` made it, for another thread.

    The model, rows, partition and settings are deep copies; the lock, the Pinocchio
    data and every cache (workspaces, compiled cores, memos) are new: the copy gives the
    results of ``mech`` bit for bit (results do not depend on call history) and shares
    no state with it. About 1 ms for the Agile Eye.
    """
    with mech.lock:
        state = {
            key: value
            for key, value in mech.__dict__.items()
            if key not in ("lock", "data") and (not key.startswith("_") or key in _MODEL_ATTRIBUTES)
        }
        state = copy.deepcopy(state)
    twin = object.__new__(type(mech))
    twin.__dict__.update(state)
    twin.lock = threading.RLock()
    twin.data = new_data(twin.model)
    for key in _DECLARED_CACHES:
        setattr(twin, key, None)
    return twin
