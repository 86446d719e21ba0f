"""The checks of a :func:`closedchain.simulate` request, before anything runs.

:func:`check_request` turns the arguments of ``simulate`` into a :class:`Request`:
the integrator, stabilization and method resolved from their registries and
checked against each other, the backend chosen, the settings classes checked,
q0 and v0 checked (shape, limits), and the step control (``dt`` or
``rtol``/``atol``) and the output times bounded. Every refusal is one
InvalidArgumentError naming the argument and the valid choices.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from ..dynamics import SolverSettings
from ..dynamics.base import DEFAULT_METHOD, METHOD_CAPABILITIES, METHODS, method_name
from ..exceptions import InvalidArgumentError, check_positive, check_settings, resolve_choice
from ..kinematics import compute_jacobian
from .registry import (
    COMPILED_INTEGRATORS,
    INTEGRATORS,
    STABILIZATIONS,
    IntegratorSpec,
    StabilizationSpec,
    StepControl,
    get_integrator,
    get_stabilization,
)
from .settings import (
    ADAPTIVE_TOLERANCES,
    DEFAULT_SIMULATION_SETTINGS,
    SimulationSettings,
    TorqueInput,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

#: The integrator of ``simulate(integrator=None)``: DOP853 far from singular positions,
#: rk43 (rk4 with stage projection) near them, an adaptive step under rtol/atol
#: (:mod:`closedchain.simulate.dop853_rk43`; the measurements: docs/bench/front.md).
DEFAULT_INTEGRATOR = "dop853-rk43"
#: The integrator of ``simulate(integrator=None, dt=...)``, and of a stabilization that
#: the default does not support: fixed-step rk4.
DEFAULT_FIXED_INTEGRATOR = "rk4"
#: The integrator of ``simulate(integrator=None, rtol=..., stabilization=...)`` with a
#: stabilization that the default does not support.
DEFAULT_ADAPTIVE_INTEGRATOR = "DOP853"

#: Values of ``simulate(backend=...)``.
BACKENDS = ("auto", "compiled", "numpy")

#: Smallest relative tolerance accepted: 100 machine epsilons, the floor scipy's
#: solvers silently raise a smaller rtol to.
MIN_RTOL = 100 * float(np.finfo(float).eps)

#: Smallest absolute tolerance accepted: scipy's error norm squares
#: error / (atol + rtol |y|), and below 1e-150 the square of an O(1) error over
#: atol overflows double precision (1e300 against the largest double, 1.8e308).
MIN_ATOL = 1e-150


@dataclass(frozen=True)
class Request:
    """A checked simulation request (made by :func:`check_request`).

    Attributes:
        mech: the mechanism.
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        t_final: duration [s].
        method: canonical name of the forward-dynamics method.
        spec: the integrator entry that runs (numpy or compiled).
        stab: the stabilization.
        control: ``dt`` [s] (fixed-step) or ``rtol``/``atol`` (adaptive).
        tau: None, an array of shape (nv,) [N m or N], or a callable ``tau(t, q, v)``.
        t_eval: output times [s], or None (every step).
        settings: simulation settings.
        solver_settings: the method's settings as given.
        progress: called with the current time [s] after each step, or None.
    """

    mech: Mechanism
    q0: np.ndarray
    v0: np.ndarray
    t_final: float
    method: str
    spec: IntegratorSpec
    stab: StabilizationSpec
    control: StepControl
    tau: TorqueInput
    t_eval: np.ndarray | None
    settings: SimulationSettings
    solver_settings: SolverSettings
    progress: Callable[[float], None] | None = None

    def on_numpy(self) -> Request:
        """Return the same request on the numpy integrator of the same name."""
        return replace(self, spec=INTEGRATORS[self.spec.name])


def check_request(
    mech: Mechanism,
    q0: np.ndarray,
    v0: np.ndarray,
    t_final: float,
    *,
    method: str,
    integrator: str | None,
    dt: float | None,
    rtol: float | None,
    atol: float | None,
    stabilization: str | None,
    tau: TorqueInput,
    t_eval: np.ndarray | None,
    settings: SimulationSettings,
    solver_settings: SolverSettings,
    progress: Callable[[float], None] | None,
    backend: str,
) -> Request:
    """Check the arguments of :func:`closedchain.simulate` (same names) into a Request.

    Raises:
        UnknownChoiceError: unknown integrator, stabilization, method or backend.
        InvalidArgumentError: a combination the registries' capabilities exclude,
            an argument out of range, or q0 outside the joint limits.
        ClosedChainError: q0, v0 or tau of the wrong shape or not finite.
    """
    check_settings("settings", settings, SimulationSettings)
    check_settings("solver_settings", solver_settings, SolverSettings)
    if integrator is None:
        integrator = default_integrator(dt, rtol, atol, stabilization)
    spec = get_integrator(integrator)
    if stabilization is None:
        stabilization = spec.default_stabilization
    spec = select_backend(spec, backend, stabilization, method)
    stab = get_stabilization(stabilization)
    method = method_name(method)
    _check_pairing(spec, stab, method)
    q0 = mech.check_q(q0, "q0")
    mech.check_limits(
        q0,
        "q0",
        urdf_limits=settings.check_limits,
        opt_out="SimulationSettings(check_limits=False) or --ignore-limits allows it",
    )
    v0 = mech.check_v(v0, "v0")
    check_positive("t_final", t_final, "the duration [s]")
    t_final = float(t_final)
    if tau is not None and not callable(tau):
        tau = mech.check_v(tau, "tau")
    _check_partitions(spec, stab, mech)
    t_eval = check_t_eval(t_eval, t_final, settings)
    control = _check_step_control(spec, t_final, dt, rtol, atol, t_eval, settings)
    return Request(
        mech=mech,
        q0=q0,
        v0=v0,
        t_final=t_final,
        method=method,
        spec=spec,
        stab=stab,
        control=control,
        tau=tau,
        t_eval=t_eval,
        settings=settings,
        solver_settings=solver_settings,
        progress=progress,
    )


def _check_pairing(spec: IntegratorSpec, stab: StabilizationSpec, method: str) -> None:
    """Raise unless the integrator, the stabilization and the method go together."""
    if stab.name not in spec.stabilizations:
        raise InvalidArgumentError(
            f"integrator {spec.name!r} does not support stabilization {stab.name!r}; "
            f"valid choices: {', '.join(spec.stabilizations)}"
        )
    caps = METHOD_CAPABILITIES[method]
    missing = [c for c in spec.method_capabilities if not getattr(caps, c)]
    if missing:
        able = [
            m
            for m in sorted(METHODS)
            if all(getattr(METHOD_CAPABILITIES[m], c) for c in spec.method_capabilities)
        ]
        raise InvalidArgumentError(
            f"integrator {spec.name!r} needs a method with {', '.join(missing)}; "
            f"method {method!r} has not; valid choices: {', '.join(able)}"
        )
    if stab.accel_terms and not caps.baumgarte:
        with_terms = [m for m in sorted(METHODS) if METHOD_CAPABILITIES[m].baumgarte]
        raise InvalidArgumentError(
            f"method {method!r} solves its own constraint equations and cannot apply the "
            "Baumgarte terms; use stabilization 'projection' or 'partitioning', or a "
            f"method among {', '.join(with_terms)}"
        )


def _check_partitions(spec: IntegratorSpec, stab: StabilizationSpec, mech: Mechanism) -> None:
    """Raise when a partitioning stabilization meets a mechanism with nq != nv."""
    if stab.partitions and mech.nq != mech.nv:
        raise InvalidArgumentError(
            f"stabilization {stab.name!r} integrates the independent coordinates of q as "
            f"a vector and needs nq == nv (this mechanism has nq={mech.nq}, nv={mech.nv}); "
            "valid choices here: "
            + ", ".join(s for s in spec.stabilizations if not STABILIZATIONS[s].partitions)
        )


def _check_step_control(
    spec: IntegratorSpec,
    t_final: float,
    dt: float | None,
    rtol: float | None,
    atol: float | None,
    t_eval: np.ndarray | None,
    settings: SimulationSettings,
) -> StepControl:
    """Return the step control of ``spec`` (defaults from ``settings``), or raise."""
    fixed = spec.kind == "fixed"
    # A step control the integrator would ignore is a mistake, not a no-op.
    ignored = ("rtol", "atol") if fixed else ("dt",)
    given = [n for n, val in (("dt", dt), ("rtol", rtol), ("atol", atol)) if val is not None]
    if any(n in ignored for n in given):
        kinds = {"fixed": "dt", "adaptive": "rtol and atol"}
        raise InvalidArgumentError(
            f"integrator {spec.name!r} is {spec.kind}-step and takes {kinds[spec.kind]}, "
            f"not {', '.join(n for n in given if n in ignored)}; fixed-step: "
            f"{', '.join(n for n, sp in INTEGRATORS.items() if sp.kind == 'fixed')}; adaptive: "
            f"{', '.join(n for n, sp in INTEGRATORS.items() if sp.kind == 'adaptive')}"
        )
    if fixed:
        dt = settings.dt if dt is None else dt
        return StepControl(dt=_check_dt(dt, t_final, t_eval, settings))
    own_rtol, own_atol = spec.tolerances or ADAPTIVE_TOLERANCES
    rtol = rtol if rtol is not None else settings.rtol if settings.rtol is not None else own_rtol
    atol = atol if atol is not None else settings.atol if settings.atol is not None else own_atol
    check_positive("rtol", rtol, "the relative tolerance")
    check_positive("atol", atol, "the absolute tolerance")
    rtol, atol = float(rtol), float(atol)
    if rtol < MIN_RTOL:
        raise InvalidArgumentError(
            f"rtol = {rtol:g} is below what double precision resolves (scipy would raise it "
            f"to {MIN_RTOL:.3g} without a word); valid range: [{MIN_RTOL:.3g}, inf)"
        )
    if atol < MIN_ATOL:
        raise InvalidArgumentError(
            f"atol = {atol:g} is so small that scipy's error norm overflows; "
            f"valid range: [{MIN_ATOL:.3g}, inf)"
        )
    return StepControl(rtol=rtol, atol=atol)


def _check_dt(
    dt: float, t_final: float, t_eval: np.ndarray | None, settings: SimulationSettings
) -> float:
    """Return the fixed step ``dt`` [s] as a float, or raise when the run is too long."""
    check_positive("dt", dt, "the fixed step [s]")
    dt = float(dt)
    ratio = t_final / dt  # a float: inf when it overflows (dt near the underflow)
    n_steps = math.ceil(ratio - 1e-9) if math.isfinite(ratio) else math.inf
    if n_steps > settings.max_steps:
        raise InvalidArgumentError(
            f"dt = {dt:g} s over t_final = {t_final:g} s is {n_steps:.3g} steps, more than "
            f"SimulationSettings.max_steps = {settings.max_steps:.3g}; use a larger dt "
            f"(>= {t_final / settings.max_steps:.3g} s) or an adaptive integrator"
        )
    if t_eval is None and n_steps + 1 > settings.max_outputs:
        raise InvalidArgumentError(
            f"recording every one of {n_steps:.3g} steps is more than "
            f"SimulationSettings.max_outputs = {settings.max_outputs:.3g} samples; "
            "pass t_eval (the output times) to keep fewer"
        )
    return dt


def select_backend(
    spec: IntegratorSpec, backend: str, stabilization: str, method: str
) -> IntegratorSpec:
    """Return the integrator entry that runs the request (see ``simulate``'s ``backend``):
    the compiled core holds every row kind, so only the integrator, stabilization and
    method decide."""
    backend = resolve_choice("backend", backend, BACKENDS)
    if backend == "numpy":
        return spec
    method = method_name(method)
    cspec = COMPILED_INTEGRATORS.get(spec.name)
    reasons = []
    if cspec is None:
        reasons.append(f"integrator {spec.name!r} has no compiled loop")
    elif stabilization not in cspec.stabilizations:
        reasons.append(
            f"the compiled {spec.name!r} supports stabilizations "
            f"{', '.join(cspec.stabilizations)}, not {stabilization!r}"
        )
    if not METHOD_CAPABILITIES[method].compiled:
        reasons.append(f"method {method!r} has no compiled implementation")
    if not reasons:
        return cspec
    if backend == "compiled":
        raise InvalidArgumentError(
            "backend='compiled' cannot run this request: " + "; ".join(reasons)
        )
    return spec


def check_start_velocity(
    mech: Mechanism,
    q0: np.ndarray,
    v0: np.ndarray,
    tol: float,
    jacobian: Callable[[np.ndarray], np.ndarray] | None = None,
) -> None:
    """Raise InvalidArgumentError when v0 violates the loops' velocity constraint J(q0) v0 = 0.

    The residual is compared with ``tol * max(1, max |v0|)`` [m/s or rad/s per row].

    Args:
        jacobian: J(q) of the kept rows (e.g. ``Problem.jacobian``, which reuses the J
            its start check computed at q0); default: :func:`closedchain.compute_jacobian`.
    """
    if jacobian is None:

        def jacobian(q):
            return compute_jacobian(mech, q)

    residual = float(np.max(np.abs(jacobian(q0) @ v0), initial=0.0))
    bound = tol * max(1.0, float(np.max(np.abs(v0), initial=0.0)))
    if residual > bound:
        raise InvalidArgumentError(
            f"{mech.name}: v0 violates the loops' velocity constraint J(q0) v0 = 0: max |J v0| "
            f"= {residual:.3g} > {bound:.3g} (SimulationSettings.start_velocity_tol x "
            "max(1, max |v0|)); project it first: v0 = closedchain.project_velocity(mech, q0, v0)"
        )


def check_t_eval(
    t_eval, t_final: float, settings: SimulationSettings = DEFAULT_SIMULATION_SETTINGS
) -> np.ndarray | None:
    """Return ``t_eval`` as a float array, or raise naming what is wrong with it.

    Valid: None, or a 1-D array of 1 to ``settings.max_outputs`` finite,
    strictly increasing times within [0, t_final].
    """
    if t_eval is None:
        return None
    t_eval = np.asarray(t_eval, dtype=float)
    valid = (
        f"valid: 1 to {settings.max_outputs} finite, strictly increasing times within "
        f"[0, t_final = {t_final:g}] s"
    )
    if t_eval.ndim != 1 or t_eval.size == 0:
        raise InvalidArgumentError(f"t_eval has shape {t_eval.shape}; {valid}")
    if t_eval.size > settings.max_outputs:
        raise InvalidArgumentError(
            f"t_eval has {t_eval.size} times, more than SimulationSettings.max_outputs; {valid}"
        )
    if not np.all(np.isfinite(t_eval)):
        raise InvalidArgumentError(f"t_eval contains non-finite times; {valid}")
    if np.any(np.diff(t_eval) <= 0):
        k = int(np.argmax(np.diff(t_eval) <= 0))
        raise InvalidArgumentError(
            f"t_eval is not strictly increasing (t_eval[{k}] = {t_eval[k]:g}, "
            f"t_eval[{k + 1}] = {t_eval[k + 1]:g}); {valid}"
        )
    if t_eval[0] < 0 or t_eval[-1] > t_final * (1 + 1e-12):
        raise InvalidArgumentError(
            f"t_eval spans [{t_eval[0]:g}, {t_eval[-1]:g}] s, outside [0, t_final]; {valid}"
        )
    return t_eval


def describe_default() -> str:
    """The default configuration of :func:`~closedchain.simulate` in a few words, from the
    constants that make it (``"augmented-lagrangian, dop853-rk43 at rtol 1e-11,
    stage-projection"``): the documentation and the generated benchmark pages state it
    with this, so they cannot name another default than the one that runs."""
    spec = get_integrator(DEFAULT_INTEGRATOR)
    rtol = f" at rtol {short_number(spec.tolerances[0])}" if spec.tolerances else ""
    return f"{DEFAULT_METHOD}, {spec.name}{rtol}, {spec.default_stabilization}"


def short_number(x: float) -> str:
    """``1e-9`` rather than Python's ``1e-09`` (one significant digit)."""
    mantissa, _, exponent = f"{x:.0e}".partition("e")
    return f"{mantissa}e{int(exponent)}"


def default_integrator(
    dt: float | None, rtol: float | None, atol: float | None, stabilization: str | None
) -> str:
    """Return the integrator of ``simulate(integrator=None, ...)``: :data:`DEFAULT_INTEGRATOR`
    unless the request needs another kind (``dt``: :data:`DEFAULT_FIXED_INTEGRATOR`) or a
    stabilization it does not support (then the fixed or, with ``rtol`` or ``atol``, the
    adaptive :data:`DEFAULT_ADAPTIVE_INTEGRATOR`)."""
    if dt is not None:
        return DEFAULT_FIXED_INTEGRATOR
    default = get_integrator(DEFAULT_INTEGRATOR)
    if stabilization is None or get_stabilization(stabilization).name in default.stabilizations:
        return default.name
    if rtol is not None or atol is not None:
        return DEFAULT_ADAPTIVE_INTEGRATOR
    return DEFAULT_FIXED_INTEGRATOR
