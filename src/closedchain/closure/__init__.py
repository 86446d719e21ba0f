r"""The loop rows of a mechanism and its coordinate partition: one object, built at load.

:class:`LoopClosure` owns the declared rows of every loop, the subset kept as
independent (the rows every dynamics method uses) and the partition of the
velocity coordinates into independent and dependent ones. It is built once by
:func:`closedchain.load`; the simulator asks it for a new partition
(:meth:`LoopClosure.partition_at`) and, when the kept rows stop describing the
loops, for a new row selection (:meth:`LoopClosure.check_rows`).

Row selection (:meth:`LoopClosure.select_rows`) works on the declared
Jacobian at many configurations spread along the motion: random assembled
configurations (every joint drawn at random, so base joints such as a
turntable or a free flyer take random poses) and short walks from each of
them along the null space of J. The generic rank r is the largest numerical
rank met; samples of lower rank are singular configurations and are set
aside. The kept rows are chosen greedily, each time the declared row that
maximizes the worst case, over the regular samples, of the smallest singular
value of the kept rows' Jacobian:

.. math::

    k_{j+1} = \arg\max_{i \notin K_j} \min_s \sigma_{\min}(J_s[K_j \cup \{i\}]),

until r rows are kept (a rank-revealing selection over all samples at once,
not at one pose); when there are few subsets of r rows (at most
:data:`MAX_EXHAUSTIVE_SUBSETS`, e.g. one loop) the max-min is taken over all of them.

The package holds, one module each: the row selection and run-time row checks
(:mod:`.selection`: :class:`LoopClosure`); the model-level tools both it and
:mod:`kinematics` need (:mod:`.assembly`): the Gauss-Newton solve onto
phi = 0 (:func:`solve_closure`), the assembly that also closes loops from far
away (:func:`assemble_closure`: least squares on the closure residual, zero
exactly at the closure) and the sampling of the motion
(:func:`sample_configurations`); the pivoted-QR partition (:mod:`.partition`:
:func:`partition_coordinates`); and the smallest singular values of the greedy
choice (:mod:`.secular`). Module dependencies: :mod:`constraints` only;
:mod:`mechanism` builds the object and :mod:`kinematics` (the Mechanism-level
functions) builds on it: no cycle.
"""

from __future__ import annotations

from .assembly import DEFAULT_ASSEMBLY_SETTINGS as DEFAULT_ASSEMBLY_SETTINGS
from .assembly import (
    AssemblySettings,
    RowFunctions,
    SelectionSettings,
    assemble_closure,
    closure_error,
    layer_jacobian,
    layer_phi,
    sample_configurations,
    solve_closure,
)
from .assembly import _clip_into as _clip_into
from .assembly import _free_bounds as _free_bounds
from .assembly import _least_squares as _least_squares
from .assembly import max_declared_residual as max_declared_residual
from .partition import PIVOT_TIE_RTOL as PIVOT_TIE_RTOL
from .partition import partition_coordinates
from .secular import _sigma_min_with_each_row as _sigma_min_with_each_row
from .selection import DEFAULT_ROW_CHECK_SETTINGS as DEFAULT_ROW_CHECK_SETTINGS
from .selection import MAX_EXHAUSTIVE_SUBSETS as MAX_EXHAUSTIVE_SUBSETS
from .selection import (
    LoopClosure,
    RowCheckSettings,
    RowSelection,
)

__all__ = [
    "LoopClosure",
    "RowCheckSettings",
    "RowFunctions",
    "RowSelection",
    "SelectionSettings",
    "layer_jacobian",
    "layer_phi",
    "partition_coordinates",
    "solve_closure",
    "AssemblySettings",
    "assemble_closure",
    "closure_error",
    "sample_configurations",
]
