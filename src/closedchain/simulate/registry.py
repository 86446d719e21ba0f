"""The integrator and stabilization registries.

Each entry declares what it can do, so :func:`closedchain.simulate` never
special-cases an integrator or stabilization by name: a new integrator (a
compiled one, an implicit scheme) is one :func:`register_integrator` call.
The built-in entries are registered by :mod:`.builtin`; this module imports
none of the loops, so the loops may read the registries.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ..exceptions import resolve_choice


@dataclass(frozen=True)
class StepControl:
    """How the step is chosen: ``dt`` [s] for fixed-step, ``rtol``/``atol`` for adaptive."""

    dt: float | None = None
    rtol: float | None = None
    atol: float | None = None


@dataclass(frozen=True)
class IntegratorSpec:
    """A registered time integrator.

    Attributes:
        name: registry key.
        kind: ``"fixed"`` (takes ``dt``) or ``"adaptive"`` (takes ``rtol``/``atol``).
        run: ``run(problem, recorder, q0, v0, t_final, control, spec, stab, t_eval,
            progress, info) -> steps``.
        order: order of accuracy.
        backend: ``"numpy"`` (Python loop) or ``"compiled"``.
        stabilizations: names of the stabilizations it supports.
        default_stabilization: used when the caller gives none.
        step: the one-step map of a fixed-step integrator,
            ``step(model, deriv, t, q, v, a, dt) -> (q, v)``.
        method_capabilities: capabilities (fields of ``MethodCapabilities``) the
            forward-dynamics method must declare to pair with this integrator.
        singular_robust: the scheme itself stays well posed where J loses rank
            (the simulator does not stop it on cond(J)).
        tolerances: the default (rtol, atol) of an adaptive integrator; None:
            ``SimulationSettings.rtol`` and ``atol``.
        description: one line for ``--help`` and the README.
    """

    name: str
    kind: str
    run: Callable
    order: int
    backend: str = "numpy"
    stabilizations: tuple[str, ...] = ("none", "baumgarte", "projection", "partitioning")
    default_stabilization: str = "none"
    step: Callable | None = None
    method_capabilities: tuple[str, ...] = ()
    singular_robust: bool = False
    tolerances: tuple[float, float] | None = None
    description: str = ""


@dataclass(frozen=True)
class StabilizationSpec:
    """A registered drift control.

    Attributes:
        name: registry key.
        accel_terms: adds Baumgarte terms to the acceleration constraint (the
            method must declare ``MethodCapabilities.baumgarte``).
        projects: projects (q, v) onto the manifold after each step.
        partitions: integrates the independent coordinates only (needs nq == nv).
        projects_stages: also projects every stage state of a fixed-step
            integrator before its accelerations are evaluated.
        description: one line.
    """

    name: str
    accel_terms: bool = False
    projects: bool = False
    partitions: bool = False
    projects_stages: bool = False
    description: str = ""


#: name -> integrator, in registration order (the numpy backend: the reference).
INTEGRATORS: dict[str, IntegratorSpec] = {}
#: name -> compiled integrator of the same name (``backend="compiled"``), used by
#: :func:`closedchain.simulate` wherever it supports the request.
COMPILED_INTEGRATORS: dict[str, IntegratorSpec] = {}
#: name -> stabilization, in registration order.
STABILIZATIONS: dict[str, StabilizationSpec] = {}


def register_integrator(spec: IntegratorSpec) -> IntegratorSpec:
    """Add ``spec`` to :data:`INTEGRATORS`, or to :data:`COMPILED_INTEGRATORS` when
    ``spec.backend == "compiled"`` (replacing an entry of the same name)."""
    (COMPILED_INTEGRATORS if spec.backend == "compiled" else INTEGRATORS)[spec.name] = spec
    return spec


def register_stabilization(spec: StabilizationSpec) -> StabilizationSpec:
    """Add ``spec`` to :data:`STABILIZATIONS`."""
    STABILIZATIONS[spec.name] = spec
    return spec


def get_integrator(name: str) -> IntegratorSpec:
    """Return the integrator registered as ``name`` (any case), or raise listing the names."""
    return INTEGRATORS[resolve_choice("integrator", name, INTEGRATORS)]


def get_stabilization(name: str) -> StabilizationSpec:
    """Return the stabilization registered as ``name`` (any case), or raise listing the names."""
    return STABILIZATIONS[resolve_choice("stabilization", name, STABILIZATIONS)]
