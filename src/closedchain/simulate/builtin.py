"""The built-in integrators and stabilizations, registered in :mod:`.registry`.

The numpy loops (:mod:`.fixed`, :mod:`.adaptive`, :mod:`.ali3p`) are the
reference; the compiled core's loops (:mod:`.compiled_loops`) are registered
under the same names when the core imports.
"""

from __future__ import annotations

from .. import compiled
from . import adaptive, ali3p, compiled_loops, dop853_rk43, fixed, rk43
from .registry import (
    INTEGRATORS,
    IntegratorSpec,
    StabilizationSpec,
    register_integrator,
    register_stabilization,
)

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

#: rk43's default (rtol, atol), chosen to meet the bars of tests/test_rk43.py and
#: tests/test_singular.py with margin (numpy backend): the driven slider-crank (2 s, 146
#: rad/s) is off by 2.9e-8 m (13,200 steps; 1.2e-7 m at rtol 1e-8), the N-four-bar
#: N = 1 by 6.8e-8 m after 20 s (6,300 steps; 5.7e-7 m at rtol 1e-8, thin against the
#: benchmark's 1e-6 m).
RK43_TOLERANCES = (1e-9, 1e-10)

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

#: dop853-rk43's default (rtol, atol): see tests/test_dop853_rk43.py for what they meet.
DOP853_RK43_TOLERANCES = (1e-11, 1e-12)

register_integrator(
    IntegratorSpec(
        "dop853-rk43",
        "adaptive",
        dop853_rk43.run_dop853_rk43,
        8,
        stabilizations=("stage-projection",),
        default_stabilization="stage-projection",
        tolerances=DOP853_RK43_TOLERANCES,
        description="Dormand-Prince 8(5,3) far from singular positions (its step's end "
        "projected), rk43 near them (every stage projected), adaptive, on the manifold "
        "through pin.integrate",
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
# stabilizations (partitioning included); registered only when the core imports.
if compiled.available():
    for _name, _kind, _order, _run, _member in (
        ("euler", "fixed", 1, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("semi-implicit", "fixed", 1, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("rk4", "fixed", 4, compiled_loops.run_fixed_compiled, "run_fixed"),
        ("rk43", "adaptive", 4, compiled_loops.run_rk43_compiled, "run_rk43"),
        ("dop853-rk43", "adaptive", 8, compiled_loops.run_dop853_rk43_compiled, "run_dop853_rk43"),
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
