"""The integrator and stabilization registries.

Each entry declares what it can do, so :func:`closedchain.simulate` never
special-cases an integrator or stabilization by name: a new integrator (a
compiled one, an implicit scheme) is one :func:`register_integrator` call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from .. import compiled
from ..exceptions import resolve_choice
from . import adaptive, ali3p, compiled_loops, fixed, rk43


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


#: rk43's default (rtol, atol), chosen to meet the bars of tests/test_rk43.py and
#: tests/test_singular.py with margin (numpy backend): the driven slider-crank (2 s, 146
#: rad/s) is off by 2.9e-8 m (13,200 steps; 1.2e-7 m at rtol 1e-8), the N-four-bar
#: N = 1 by 6.8e-8 m after 20 s (6,300 steps; 5.7e-7 m at rtol 1e-8, thin against the
#: benchmark's 1e-6 m).
RK43_TOLERANCES = (1e-9, 1e-10)


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


for _spec in (
    StabilizationSpec("none", description="acceleration-level constraint only; phi drifts"),
    StabilizationSpec(
        "baumgarte",
        accel_terms=True,
        description="J a + gamma + 2 alpha J v + beta^2 phi = 0 (Baumgarte 1972)",
    ),
    StabilizationSpec(
        "projection",
        projects=True,
        description="Gauss-Newton projection of q onto phi = 0 and of v onto J v = 0 after a step",
    ),
    StabilizationSpec(
        "partitioning",
        partitions=True,
        description="coordinate partitioning with re-partitioning (Wehage & Haug 1982)",
    ),
    StabilizationSpec(
        "stage-projection",
        projects=True,
        projects_stages=True,
        description="projection of q and v onto the manifold at every stage and after each "
        "step: accelerations are only evaluated on phi = 0, J v = 0",
    ),
    StabilizationSpec(
        "mass-orthogonal",
        description="index-3 penalty with augmented-Lagrangian multipliers, then "
        "M-orthogonal projections of v and a (ALI3-P; its integrator only)",
    ),
):
    register_stabilization(_spec)

for _name, _step, _order, _what in (
    ("euler", fixed.step_euler, 1, "explicit Euler"),
    ("semi-implicit", fixed.step_semi_implicit, 1, "semi-implicit (symplectic) Euler"),
    ("rk4", fixed.step_rk4, 4, "classical Runge-Kutta 4"),
):
    register_integrator(
        IntegratorSpec(
            _name,
            "fixed",
            fixed.run_fixed,
            _order,
            step=_step,
            stabilizations=("none", "baumgarte", "projection", "partitioning", "stage-projection"),
            default_stabilization="stage-projection",
            description=f"{_what}, fixed step, on the manifold through pin.integrate",
        )
    )

for _name, _order, _what in (
    ("RK45", 5, "Dormand-Prince 5(4)"),
    ("DOP853", 8, "Dormand-Prince 8(5,3)"),
    ("Radau", 5, "implicit Radau IIA (stiff)"),
    ("BDF", 5, "backward differentiation formulas (stiff)"),
    ("LSODA", 12, "LSODA, switching Adams/BDF"),
):
    register_integrator(
        IntegratorSpec(
            _name,
            "adaptive",
            adaptive.run_adaptive,
            _order,
            description=f"scipy.integrate.{_name}: {_what}, adaptive, dense output; "
            "q in a chart x -> q0 (+) x when nq != nv",
        )
    )

register_integrator(
    IntegratorSpec(
        "rk43",
        "adaptive",
        rk43.run_rk43,
        4,
        stabilizations=("stage-projection",),
        default_stabilization="stage-projection",
        tolerances=RK43_TOLERANCES,
        description="classical Runge-Kutta 4 with stage projection, adaptive step from the "
        "embedded third-order estimate of its stages (FSAL), on the manifold through "
        "pin.integrate",
    )
)

register_integrator(
    IntegratorSpec(
        "ali3p",
        "fixed",
        ali3p.run_ali3p,
        2,
        stabilizations=("mass-orthogonal",),
        default_stabilization="mass-orthogonal",
        method_capabilities=("singular_robust",),
        singular_robust=True,
        description="ALI3-P: index-3 augmented Lagrangian, implicit trapezoidal rule with "
        "Newton, mass-orthogonal projections (Bayo & Ledesma 1996; Cuadrado et al. 2000)",
    )
)

# The compiled core's loops: same names, same semantics, the numpy entry's
# stabilizations (partitioning included) and tolerances; registered only when the core
# imports and has the loop (a core built before rk43 runs it on numpy).
if compiled.available():
    for _name, _kind, _order, _run, _member in (
        ("euler", "fixed", 1, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("semi-implicit", "fixed", 1, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("rk4", "fixed", 4, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("rk43", "adaptive", 4, compiled_loops.run_rk43_compiled, "run_rk43"),
        ("RK45", "adaptive", 5, compiled_loops.run_adaptive_compiled, "run_adaptive"),
        ("DOP853", "adaptive", 8, compiled_loops.run_adaptive_compiled, "run_adaptive"),
    ):
        if not compiled.has(_member):
            continue
        _ref = INTEGRATORS[_name]
        register_integrator(
            IntegratorSpec(
                _name,
                _kind,
                _run,
                _order,
                backend="compiled",
                stabilizations=_ref.stabilizations,
                default_stabilization=_ref.default_stabilization,
                tolerances=_ref.tolerances,
                description=f"{_ref.description.split(',')[0]}, loop in C++ (compiled core)",
            )
        )
    _ref = INTEGRATORS["ali3p"]
    register_integrator(
        IntegratorSpec(
            "ali3p",
            "fixed",
            compiled_loops.run_ali3p_compiled,
            _ref.order,
            backend="compiled",
            stabilizations=_ref.stabilizations,
            default_stabilization=_ref.default_stabilization,
            method_capabilities=_ref.method_capabilities,
            singular_robust=True,
            description="ALI3-P, loop in C++ (compiled core)",
        )
    )
