"""Which backend a public per-call function runs on, and its compiled evaluators.

The public functions (:func:`~closedchain.forward_dynamics`, the rows of
:mod:`closedchain.kinematics`) take ``backend="auto" | "compiled" | "numpy"``. With
``"auto"`` they run on the compiled core when it is built and has the method, else
on the numpy reference; ``"compiled"`` raises where it cannot. The compiled evaluators
are made once per mechanism, constraint layer, method and settings, and kept on the
mechanism.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .exceptions import ClosedChainError, InvalidArgumentError, resolve_choice

if TYPE_CHECKING:
    from .compiled import CompiledDynamics
    from .dynamics.base import SolverSettings
    from .mechanism import Mechanism

#: The backends of the per-call functions.
BACKENDS = ("auto", "compiled", "numpy")
#: Compiled evaluators kept per mechanism (other settings objects make new ones).
MAX_EVALUATORS = 8
#: A member of the compiled Core that has the per-call entry points (src/cpp/percall.hpp).
PERCALL_ENTRY = "forward_checked"


def backend_name(backend: str) -> str:
    """Return the registered spelling of ``backend`` (any case), or raise listing them."""
    return backend if backend in BACKENDS else resolve_choice("backend", backend, BACKENDS)


def why_not_compiled(method: str) -> str | None:
    """Why ``method`` cannot run on the compiled core, or None if it can (the core holds
    every row kind, couplings included)."""
    from . import compiled
    from .dynamics.base import METHOD_CAPABILITIES

    if not compiled.available():
        return f"the compiled core is not available ({compiled.IMPORT_ERROR})"
    if not compiled.has(PERCALL_ENTRY):
        return "the compiled core was built from an older tree (rebuild it: pip install -e .)"
    capabilities = METHOD_CAPABILITIES.get(method)
    if capabilities is None or not capabilities.compiled:
        valid = sorted(m for m, c in METHOD_CAPABILITIES.items() if c.compiled)
        return f"method {method!r} has no compiled version; compiled methods: {', '.join(valid)}"
    return None


def evaluator(
    mech: Mechanism, method: str, settings: SolverSettings, backend: str
) -> CompiledDynamics | None:
    """The compiled evaluator of ``method`` with ``settings`` on ``mech``, or None where
    the call runs on numpy (``backend`` ``"numpy"``, or ``"auto"`` without a compiled
    version).

    Raises:
        InvalidArgumentError: ``backend="compiled"`` where the core cannot run it (says why).
    """
    if backend == "numpy":
        return None
    layer = mech.constraints
    last = mech.__dict__.get("_percall_last")
    # The same method, settings object and rows as the last call: the common case.
    if last is not None and last[0] is layer and last[1] == method and last[2] is settings:
        entry = last[3]
    else:
        cache = mech.__dict__.setdefault("_percall_evaluators", {})
        key = (method, settings)
        entry = cache.get(key)
        if entry is None or entry[0] is not layer:
            entry = cache[key] = (layer, *_make(mech, method, settings))
            if len(cache) > MAX_EVALUATORS:
                cache.clear()
                cache[key] = entry
        mech.__dict__["_percall_last"] = (layer, method, settings, entry)
    if entry[1] is None and backend == "compiled":
        raise InvalidArgumentError(f"{mech.name}: backend='compiled': {entry[2]}")
    return entry[1]


def _make(mech: Mechanism, method: str, settings: SolverSettings):
    """``(evaluator, None)``, or ``(None, why not)`` where the core cannot run it."""
    reason = why_not_compiled(method)
    if reason is not None:
        return None, reason
    from .compiled import CompiledDynamics

    try:
        return CompiledDynamics(mech, method, settings), None
    except ClosedChainError as exc:  # e.g. declared rows of rank below their count
        return None, f"the compiled core cannot hold this mechanism ({exc})"


def rows_evaluator(mech: Mechanism, backend: str) -> CompiledDynamics | None:
    """The compiled evaluator of the kept rows' phi, J and gamma (no Baumgarte terms),
    or None where they are evaluated by numpy."""
    return evaluator(mech, "kkt", _default_settings(), backend)


def _default_settings() -> SolverSettings:
    """``dynamics.base.DEFAULT_SETTINGS`` (imported on first use: that package imports
    this module)."""
    global _DEFAULT_SETTINGS
    if _DEFAULT_SETTINGS is None:
        from .dynamics.base import DEFAULT_SETTINGS

        _DEFAULT_SETTINGS = DEFAULT_SETTINGS
    return _DEFAULT_SETTINGS


_DEFAULT_SETTINGS: SolverSettings | None = None
