"""The compiled core: constraint rows, forward dynamics and integration loops in C++.

``closedchain._core`` (src/cpp/module.cpp and expose-*.cpp, built by CMake through
scikit-build-core against the Pinocchio of the ``pin`` wheel) evaluates the
same equations as the numpy backend: the rows of the constraint layer
(:meth:`ConstraintLayer.row_table`, and every declared row for the per-step
checks), the methods whose :class:`MethodCapabilities` declare ``compiled``
(kkt, schur, nullspace, augmented-lagrangian, reduced), and whole trajectories of
the integrators registered with ``backend="compiled"`` with every stabilization
of their numpy namesakes, coordinate partitioning with re-partitioning included
(see :mod:`closedchain.simulate.registry`). The Pinocchio model is passed by
reference; the URDF reading, the loop bookkeeping and the API stay in Python.

Use :func:`compiled_dynamics` for one evaluation from Python; ``simulate``
picks the compiled integrators by itself.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .dynamics.base import METHOD_CAPABILITIES, SolverSettings, get_method
from .exceptions import ClosedChainError

# Declared in closedchain.exceptions; importable from here as before.
from .exceptions import RowCheckRequired as RowCheckRequired

__all__ = [
    "CompiledDynamics",
    "available",
    "compiled_dynamics",
    "has",
    "supports_method",
]

if TYPE_CHECKING:
    from .mechanism import Mechanism


try:
    import pinocchio  # noqa: F401  (its converters must be registered first)

    from . import _core
except ImportError as exc:  # pragma: no cover - a broken installation
    _core = None
    IMPORT_ERROR: str | None = str(exc)
else:
    IMPORT_ERROR = None

#: The compiled core's tree path (src/cpp/core_tree.hpp: M^-1 x by the articulated-body
#: recursion in O(nv), M never formed, a dense solve of the loop rows only) serves every
#: method but schur on a mechanism of more than TREE_SOLVE_MIN_NV velocities and at
#: most nv / TREE_SOLVE_NV_PER_ROW rows, unless the band path was chosen: where it costs
#: less than the dense path (docs/design/compiled-core.md).
TREE_SOLVE_MIN_NV = 12
TREE_SOLVE_NV_PER_ROW = 4

#: Integrator codes of the compiled loops.
INTEGRATOR_CODES = (
    {}
    if _core is None
    else {
        "euler": _core.EULER,
        "semi-implicit": _core.SEMI_IMPLICIT,
        "rk4": _core.RK4,
        "RK45": _core.RK45,
        "DOP853": _core.DOP853,
    }
)


def available() -> bool:
    """Return True when the compiled core was built and imports."""
    return _core is not None


def has(member: str) -> bool:
    """Return True when the compiled core imports and its ``Core`` has ``member`` (a core
    built from an older tree lacks the loops added since)."""
    return available() and hasattr(_core.Core, member)


def supports_method(method: str) -> bool:
    """Return True when the compiled core implements forward-dynamics ``method``."""
    get_method(method)
    return available() and METHOD_CAPABILITIES[method].compiled


def make_core(mech: Mechanism, *, shared: bool = True):
    """Return a compiled core of the mechanism (its own Pinocchio Data and buffers).

    Args:
        shared: return the mechanism's shared core, built once per constraint
            layer (the simulator's, reconfigured by every run); False: a new one.
    """
    if _core is None:
        raise ClosedChainError(f"the compiled core is not available: {IMPORT_ERROR}")
    cache = mech.__dict__.setdefault("_compiled_cores", {})
    key = id(mech.constraints)
    entry = cache.get(key) if shared else None
    if entry is None or entry[0] is not mech.constraints:
        core = _core_of_rows(mech, mech.constraints)
        # Every declared row, checked at every step of a compiled loop.
        kept = np.zeros(mech.declared.nc, dtype=np.int32)
        kept[list(mech.selected_rows)] = 1
        set_declared_rows(core, mech, kept)
        # The reduced method's partition; the loops the dependent solve checks for
        # spurious closures (ConstraintLayer.misaligned_loops).
        core.set_partition(
            np.asarray(mech.independent_idx_v, dtype=np.int32), list(mech.coordinate_names)
        )
        set_alignment(core, mech.constraints)
        set_band(core, mech)
        entry = (mech.constraints, core)
        if shared:
            cache[key] = entry
    return entry[1]


def _core_of_rows(mech: Mechanism, layer) -> _core.Core:
    """A new core on ``mech``'s model whose rows are those of the constraint ``layer``."""
    tab = layer.row_table()
    core = _core.Core(
        mech.model,
        mech.name,
        tab.function.astype(np.int32),
        tab.frame_p.astype(np.int32),
        tab.frame_s.astype(np.int32),
        tab.u,
        tab.w,
    )
    # The joint springs and damping, a term of h as in the numpy methods (the armature is
    # the model's own, on M's diagonal in both).
    p = mech.passive
    core.set_passive(
        p.spring_idx_q.astype(np.int32),
        p.spring_idx_v.astype(np.int32),
        p.stiffness,
        p.reference,
        p.damping if p.has_damping else np.zeros(0),
    )
    return core


def declared_rows(mech: Mechanism, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return phi(q), shape (n_declared,), and J(q), shape (n_declared, nv), of every
    declared row of ``mech`` (the dropped ones included), evaluated in C++.

    The same rows as ``closure.layer_phi`` / ``layer_jacobian`` of ``mech.declared``
    (tests/test_compiled.py: to 1e-12) at a few microseconds instead of about 100:
    ``simulate``'s start checks on the compiled backend.
    """
    phi, J, _ = declared_core(mech).rows(np.asarray(q, dtype=float), np.zeros(mech.nv))
    return phi, jacobian_rows(J, mech.nv)


def jacobian_rows(J: np.ndarray, nv: int) -> np.ndarray:
    """Return a Jacobian of the core as a matrix, shape (rows, nv).

    The core returns a matrix of one column (a mechanism with nv = 1) as a vector.
    """
    return np.reshape(J, (-1, nv))


def declared_core(mech: Mechanism):
    """Return the core of every declared row of ``mech`` (:func:`declared_rows`; its
    ``assemble_checked``, ``phi_checked`` and ``jacobian_checked`` serve
    :func:`closedchain.assemble`, ``project_checked`` :func:`closedchain.project_velocity`),
    with the loops' alignment checks (``ConstraintLayer.misaligned_loops``). Built once per
    mechanism; it never runs a simulation (nothing of a run's settings enters it)."""
    if _core is None:
        raise ClosedChainError(f"the compiled core is not available: {IMPORT_ERROR}")
    entry = mech.__dict__.get("_compiled_declared_core")
    if entry is None or entry[0] is not mech.declared:
        core = _core_of_rows(mech, mech.declared)
        set_alignment(core, mech.declared)
        entry = (mech.declared, core)
        mech.__dict__["_compiled_declared_core"] = entry
    return entry[1]


def set_band(core, mech: Mechanism) -> tuple[int, int]:
    """Give ``core`` the band structure the numpy backend detects (many loops in a chain).

    The choice of :class:`~closedchain.dynamics.augmented_lagrangian.PenalizedSolver`
    (band Cholesky of M + alpha J^T J in its bandwidth-reducing order) and of its
    :class:`NormalSolver` (band Cholesky of J J^T): the compiled augmented
    Lagrangian, projections and regularity check then cost O(nv) instead of O(nv^3).
    Returns the core's half bandwidths ``(b_p, b_n)`` (those of the two solvers).
    """
    from .dynamics.augmented_lagrangian import PenalizedSolver

    if mech.nc == 0 or _band_excluded(mech):
        return 0, 0
    solver = PenalizedSolver(mech)
    return tuple(
        core.set_band(
            np.asarray(solver.perm, dtype=np.int32), bool(solver.banded), bool(solver.normal.banded)
        )
    )


def _band_excluded(mech: Mechanism) -> bool:
    """True when neither band factorization of :func:`set_band` can be chosen, judged in
    O(njoints) without forming the patterns (quadratic in nv: seconds at nv = 1000).

    In any order, a symmetric pattern holding a clique of k columns has half bandwidth at
    least k - 1; the velocity columns of the joints on one root path are a clique of M's
    pattern (the CRBA couples every pair). So M + alpha J^T J is not banded when the deepest
    path holds more than ``BANDED_FRACTION nv + 1`` columns; J J^T is never banded with at
    most BANDED_MIN_SIZE rows (:class:`~closedchain.dynamics.augmented_lagrangian.NormalSolver`).
    """
    from .dynamics.augmented_lagrangian import BANDED_FRACTION, BANDED_MIN_SIZE

    if mech.nc > BANDED_MIN_SIZE:
        return False
    model = mech.model
    depth = [0] * model.njoints  # velocity columns from the root to each joint
    for j in range(1, model.njoints):
        depth[j] = depth[model.parents[j]] + model.joints[j].nv
    return mech.nv <= BANDED_MIN_SIZE or max(depth) - 1 > BANDED_FRACTION * mech.nv


def set_declared_rows(core, mech: Mechanism, kept: np.ndarray) -> None:
    """Give ``core`` every declared row of ``mech`` to check, ``kept[i] = 1`` for the
    rows its methods use (the others are checked as dropped rows)."""
    dtab = mech.declared.row_table()
    core.set_declared(
        dtab.function.astype(np.int32),
        dtab.frame_p.astype(np.int32),
        dtab.frame_s.astype(np.int32),
        dtab.u,
        dtab.w,
        np.asarray(kept, dtype=np.int32),
        [r.label for r in mech.declared.declared_rows],
    )


def set_alignment(core, layer) -> None:
    """Give ``core`` the alignment checks of ``layer`` (its ``alignment_vectors()``)."""
    loops = layer.alignment_vectors()
    fp, fs, u, idx = [], [], [], []
    for i, (_, fid_p, fid_s, vectors) in enumerate(loops):
        for vec in vectors:
            fp.append(fid_p)
            fs.append(fid_s)
            u.append(vec)
            idx.append(i)
    core.set_alignment(
        np.asarray(fp, dtype=np.int32),
        np.asarray(fs, dtype=np.int32),
        np.asarray(u, dtype=float).reshape(-1, 3),
        np.asarray(idx, dtype=np.int32),
        [name for name, *_ in loops],
    )


def configure(
    core,
    method: str,
    solver_settings: SolverSettings,
    settings=None,
    *,
    stage_projects: bool = False,
    singular_robust: bool = False,
    partitions: bool = False,
    independent=None,
) -> None:
    """Set the core's method, solver settings and (optionally) simulation settings.

    Args:
        stage_projects: project every stage state of a fixed-step loop
            (stabilization ``stage-projection``).
        singular_robust: pass singular positions (no stop on cond(J); see
            ``Problem.singular_robust``).
        partitions: stabilization ``partitioning`` (integrate the independent
            coordinates, solve the dependent ones at every evaluation).
        independent: the partition a partitioning run starts from (velocity
            indices); None: the mechanism's.
    """
    if not supports_method(method):
        compiled = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)
        raise ClosedChainError(
            f"method {method!r} has no compiled implementation; compiled methods: "
            f"{', '.join(compiled)} (use backend='numpy')"
        )
    run = _core.RunOptions()
    run.method = method
    run.stage_projects = bool(stage_projects)
    run.singular_robust = bool(singular_robust)
    run.partitions = bool(partitions)
    if independent is not None:
        run.independent = np.asarray(independent, dtype=np.int32)
    # The defaults of the core's SimulationSettings are the dataclass's (tested).
    simulation = _core.SimulationSettings()
    if settings is not None:
        simulation = core_settings(_core.SimulationSettings, settings)
    core.configure(run, core_settings(_core.SolverSettings, solver_settings), simulation)


def core_settings(cls, source, prefix: str = ""):
    """Return an instance of the core's settings class ``cls`` filled from ``source``.

    Every field the core reads (``cls.fields``, src/cpp/expose-settings.cpp) is copied
    from the settings dataclass ``source``'s field of the same name after ``prefix``
    (a field the dataclass lacks raises AttributeError here), converted to the type of
    the core's default (bool, int or float) once, here.

    Args:
        cls: ``_core.SolverSettings``, ``_core.SimulationSettings`` or ``_core.Ali3pSettings``.
        source: a :class:`SolverSettings` or
            :class:`~closedchain.simulate.settings.SimulationSettings`.
        prefix: prefix of the dataclass's field names (``"ali3p_"`` for Ali3pSettings).
    """
    out = cls()
    for name in cls.fields:
        value = getattr(source, prefix + name)
        default = getattr(out, name)
        if isinstance(default, (bool, int, float)):
            value = type(default)(value)
        setattr(out, name, value)
    return out


def ali3p_settings(settings):
    """Return the core's Ali3pSettings of a SimulationSettings (its ``ali3p_*`` fields)."""
    return core_settings(_core.Ali3pSettings, settings, prefix="ali3p_")


class CompiledDynamics:
    """The compiled right-hand side of one mechanism and method, called from Python.

    Example::

        fd = CompiledDynamics(mech, "kkt")
        a, lam = fd.forward(q, v, tau)
    """

    def __init__(
        self, mech: Mechanism, method: str = "kkt", settings: SolverSettings | None = None
    ) -> None:
        self.mech = mech
        self.method = method
        self.core = make_core(mech, shared=False)  # its method and settings stay its own
        configure(self.core, method, settings or SolverSettings())
        self._zero = np.zeros(mech.nv)

    def forward(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray | None = None):
        """Return (a, lam) at (q, v) with generalized force ``tau`` (zero when None).

        Raises:
            SingularConfigurationError: the method's matrix is singular at q.
        """
        return self.core.forward(q, v, self._zero if tau is None else tau)

    def rows(self, q: np.ndarray, v: np.ndarray):
        """Return (phi, J, gamma) at (q, v) (gamma with Baumgarte terms when configured)."""
        return self.core.rows(q, v)


def compiled_dynamics(
    mech: Mechanism, method: str = "kkt", settings: SolverSettings | None = None
) -> CompiledDynamics:
    """Return the compiled right-hand side of ``mech`` with ``method``."""
    return CompiledDynamics(mech, method, settings)
