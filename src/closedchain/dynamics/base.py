"""Shared pieces of the forward-dynamics methods: settings, result, registry, terms.

Every method solves the constrained equations of motion of the lesson
(Section 3; see the references),

.. math::

    M(q)\\,a + h(q, v) + J(q)^\\top \\lambda = \\tau, \\qquad J(q)\\,a + \\gamma(q, v) = 0,

with ``M`` from CRBA (the joints' armature on its diagonal), ``h`` from the
nonlinear effects (Coriolis, centrifugal, gravity) minus the joint springs' and
dampers' forces (:mod:`closedchain.passive`), ``J`` and ``gamma = Jdot v`` from
the constraint layer's independent rows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from ..exceptions import SingularConfigurationError, resolve_choice

if TYPE_CHECKING:
    from ..mechanism import Mechanism


@dataclass(frozen=True)
class SolverSettings:
    """Numerical settings shared by the forward-dynamics methods.

    Attributes:
        cond_max: largest acceptable condition number of the matrix a method
            factorizes (KKT matrix, Delassus matrix, J_D, reduced mass
            matrix); above it the method raises SingularConfigurationError.
        baumgarte: gains (alpha, beta) [1/s] of Baumgarte stabilization
            (Baumgarte 1972): the acceleration constraint becomes
            J a + gamma + 2 alpha J v + beta^2 phi = 0. None (default): exact
            J a + gamma = 0. The simulator sets it for ``stabilization="baumgarte"``.
        pinocchio_mu: proximal regularization of pinocchio.constraintDynamics
            (mu = 0 returns NaN with redundant rows).
        pinocchio_accuracy: absolute accuracy of its proximal iterations.
        pinocchio_max_iter: its iteration cap.
        al_penalty: relative penalty rho of the augmented-Lagrangian method,
            alpha = rho tr(M) / tr(J^T J) (dimensionless) to start with; alpha is
            lowered where P's Cholesky shows that M cannot take it
            (``PenalizedSolver.factor_relative``). Larger: fewer
            iterations, but P = M + alpha J^T J is worse conditioned (each solve
            loses about log10(rho) digits, which the iteration, written in
            residual form, recovers). A direction of J with singular value sigma
            (relative to the largest) is enforced once rho sigma^2 >> 1: with
            1e11 the method agrees with kkt to 1e-13 and passes the
            N-four-bar's flat positions; with 1e7 (sigma < 3e-4 unenforced)
            rk4 and DOP853 leave them with errors of 1e-3 rad (measured).
        al_tol: the augmented-Lagrangian iteration stops when the largest
            change of an acceleration is below al_tol (1 + max |a|).
        al_max_iter: its iteration cap (reached only along directions where J
            is nearly rank-deficient; the result is then the best iterate), times one
            plus the number of times the penalty was lowered.
        al_polish: correct its multipliers by the normal equations of J^T lam (their
            update alpha (J a + gamma) carries alpha times the round-off of J a); the
            accelerations do not depend on it. The numpy simulator turns it off where
            only accelerations are used (rk4's inner stages); the compiled core ignores
            it (it polishes every evaluation).
        prox_mu: proximal regularization mu of the "proximal" method
            (dimensionless, relative to the Delassus matrix's diagonal scale).
        prox_tol: its convergence threshold on the change of the multipliers'
            generalized force, relative to max |tau - h| + 1.
        prox_max_iter: its iteration cap.
        weak_rcond: inverse dynamics of an over-actuated mechanism
            (:func:`closedchain.inverse_dynamics`, :func:`closedchain.gravity_torque`):
            directions of J whose singular value is below ``weak_rcond`` times the
            largest are near-null (a loop near a singular position, or rows a rounded
            file makes nearly redundant); the spare actuators balance the load along
            them too, which the loops could carry only with multipliers of order
            load / sigma. Also the smallest cosine between the spare torques and those
            directions that is used (dimensionless).
    """

    cond_max: float = 1e12
    baumgarte: tuple[float, float] | None = None
    pinocchio_mu: float = 1e-8
    pinocchio_accuracy: float = 1e-13
    pinocchio_max_iter: int = 50
    al_penalty: float = 1e11
    al_tol: float = 1e-13
    al_max_iter: int = 30
    al_polish: bool = True
    prox_mu: float = 1e-8
    prox_tol: float = 1e-13
    prox_max_iter: int = 50
    weak_rcond: float = 1e-3

    def pinocchio_proximal(self) -> pin.ProximalSettings:
        """Pinocchio's ProximalSettings of these settings: absolute accuracy
        ``pinocchio_accuracy`` with relative accuracy 0 (iterate to it or to
        ``pinocchio_max_iter``), ``pinocchio_mu``; the "pinocchio" method, validation
        and the benchmark's library-settings peer all call Pinocchio with these."""
        return pin.ProximalSettings(
            self.pinocchio_accuracy, 0.0, self.pinocchio_mu, self.pinocchio_max_iter
        )


DEFAULT_SETTINGS = SolverSettings()


@dataclass(frozen=True)
class ForwardDynamicsResult:
    """Accelerations and multipliers of one forward-dynamics evaluation.

    Attributes:
        a: joint accelerations, shape (nv,) [rad/s^2 or m/s^2].
        lam: multipliers of the independent constraint rows, shape (nc,), in
            the convention ``M a + h + J^T lam = tau``.
        method: name of the method that produced them.
        J: constraint Jacobian used, shape (nc, nv).
        gamma: Jdot v used, shape (nc,) [m/s^2 or 1/s^2 per row].
    """

    a: np.ndarray
    lam: np.ndarray
    method: str
    J: np.ndarray = field(repr=False, compare=False)
    gamma: np.ndarray = field(repr=False, compare=False)

    def constraint_residual(self) -> float:
        """Return max |J a + gamma|, the acceleration-level constraint violation."""
        if self.lam.size == 0:
            return 0.0
        return float(np.max(np.abs(self.J @ self.a + self.gamma)))

    def generalized_constraint_force(self) -> np.ndarray:
        """Return J^T lam, shape (nv,): the generalized force the loops exert."""
        return self.J.T @ self.lam


def new_frozen(cls, /, **fields):
    """An instance of the frozen dataclass ``cls`` with these fields (every one of them),
    made without its ``__init__``, whose ``object.__setattr__`` per field costs 0.3 to
    0.6 us of a per-call budget of about 8 us (the per-call functions' results; tests check
    that every field is set)."""
    obj = object.__new__(cls)
    obj.__dict__.update(fields)
    return obj


MethodFunction = Callable[
    ["Mechanism", np.ndarray, np.ndarray, np.ndarray, SolverSettings],
    tuple[np.ndarray, np.ndarray],
]

#: name -> method function ``f(mech, q, v, tau, settings) -> (a, lam)``.
METHODS: dict[str, MethodFunction] = {}

#: The default method of :func:`~closedchain.forward_dynamics`, :func:`~closedchain.simulate`
#: and the CLI: the augmented-Lagrangian iteration on the positive definite
#: M + alpha J^T J stays well posed where J loses rank (singular positions, redundant rows),
#: where ``kkt``'s block system is singular; on regular configurations it agrees with
#: ``kkt`` to its tolerance ``SolverSettings.al_tol``.
DEFAULT_METHOD = "augmented-lagrangian"


@dataclass(frozen=True)
class MethodCapabilities:
    """What a registered method can do (read by the simulator, never its name).

    Attributes:
        baumgarte: the method solves ``J a + gamma' = 0`` with the gamma of
            :func:`compute_terms`, so it applies Baumgarte terms.
        singular_robust: the method stays well posed where J loses rank
            (singular configurations): the simulator does not stop there on
            cond(J), and names such methods in its singularity errors.
        redundant_rows: the method accepts linearly dependent constraint rows.
        compiled: the compiled core (``closedchain._core``) implements the
            method under the same name, so compiled integrators can use it.
    """

    baumgarte: bool = True
    singular_robust: bool = False
    redundant_rows: bool = False
    compiled: bool = False


#: name -> capabilities of the method registered under that name.
METHOD_CAPABILITIES: dict[str, MethodCapabilities] = {}


def register(
    name: str, capabilities: MethodCapabilities = MethodCapabilities()
) -> Callable[[MethodFunction], MethodFunction]:
    """Register a forward-dynamics method under ``name`` with its capabilities."""

    def decorator(func: MethodFunction) -> MethodFunction:
        METHODS[name] = func
        METHOD_CAPABILITIES[name] = capabilities
        return func

    return decorator


def method_name(name: str) -> str:
    """Return the registered spelling of method ``name`` (any case), or raise listing them."""
    return name if name in METHODS else resolve_choice("forward-dynamics method", name, METHODS)


def get_method(name: str) -> MethodFunction:
    """Return the method registered as ``name`` (any case), or raise listing the valid names."""
    return METHODS[method_name(name)]


class Workspace:
    """Preallocated buffers of one mechanism (made once, reused every call)."""

    def __init__(self, mech: Mechanism) -> None:
        nv, nc = mech.nv, mech.nc
        self.M = np.zeros((nv, nv))
        self.h = np.zeros(nv)
        self.J = np.zeros((nc, nv))
        self.gamma = np.zeros(nc)
        self.K = np.zeros((nv + nc, nv + nc), order="F")  # LAPACK's layout
        self.rhs = np.zeros(nv + nc)
        self.phi = np.zeros(nc)
        self.lower_mask = np.tri(nv, k=-1, dtype=bool)  # CRBA fills the upper triangle only
        #: Per-method buffers, keyed by method name, made on a method's first
        #: call ("schur", "nullspace", "reduced", "pinocchio": see their modules).
        self.method_buffers: dict[str, object] = {}


def method_buffers(ws: Workspace, name: str, factory: Callable[[], object]):
    """Return the buffers method ``name`` keeps in ``ws``, made by ``factory()`` on first use."""
    buf = ws.method_buffers.get(name)
    if buf is None:
        buf = ws.method_buffers[name] = factory()
    return buf


def singular_error(
    mech: Mechanism,
    q: np.ndarray,
    what: str,
    cond: float,
    bound: float,
    hint: str,
    *,
    bound_name: str = "cond_max",
) -> SingularConfigurationError:
    """Return the error for a matrix ``what`` whose condition number exceeds ``bound`` at q.

    A shorthand of :meth:`SingularConfigurationError.build`, the one builder.
    """
    return SingularConfigurationError.build(
        mech.name, what, q=q, cond=cond, bound=bound, bound_name=bound_name, hint=hint
    )


#: Why a matrix made of J (J, J_D, the Delassus matrix) is singular: the hint of its error.
RANK_LOSS_HINT = "the constraint Jacobian has lost rank or the configuration is a singularity"
#: Why the mass matrix M (or its restriction to the motion, N^T M N) is singular.
MASS_HINT = (
    "the mass matrix is ill-conditioned: links far lighter or smaller than others (a long "
    "chain of light links) or a massless subtree"
)
#: Why the KKT matrix [[M, J^T], [J, 0]] is singular: either.
KKT_HINT = (
    "the constraint Jacobian has lost rank (a singular configuration) or the mass matrix is "
    "ill-conditioned (a long chain of light links; method='augmented-lagrangian' runs there)"
)


def check_condition(
    mech,
    q,
    what: str,
    rcond: float,
    info: int,
    settings: SolverSettings,
    hint: str = RANK_LOSS_HINT,
):
    """Raise SingularConfigurationError when ``rcond`` says the factorized matrix is singular.

    Args:
        mech: the mechanism (for the message).
        q: configuration, shape (nq,).
        what: name of the matrix.
        rcond: LAPACK reciprocal condition estimate.
        info: LAPACK info of the factorization (> 0: exactly singular).
        settings: ``cond_max``.
        hint: why the matrix can be singular (:data:`RANK_LOSS_HINT`, :data:`MASS_HINT`,
            :data:`KKT_HINT`).
    """
    cond = float("inf") if info > 0 or rcond <= 0 else 1.0 / rcond
    if cond > settings.cond_max:
        raise singular_error(mech, q, what, cond, settings.cond_max, hint)


def workspace(mech: Mechanism) -> Workspace:
    """Return the mechanism's workspace, creating it on first use."""
    ws = mech._workspace
    if ws is None:
        ws = mech._workspace = Workspace(mech)
    return ws


def position_terms(mech: Mechanism, q: np.ndarray, phi: np.ndarray | None = None) -> Workspace:
    """Fill J (and ``phi`` if given) at q in one pass; see :func:`mass_matrix` for M.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        phi: output of the kept rows' phi(q), shape (nc,), if wanted.

    Returns:
        The workspace, whose ``J`` is current.
    """
    ws = workspace(mech)
    model, data = mech.model, mech.data
    pin.computeJointJacobians(model, data, q)  # placements and joint Jacobians
    mech.constraints.evaluate(model, data, phi=phi, J=ws.J)
    return ws


def _symmetric_mass(ws: Workspace, upper: np.ndarray) -> None:
    """Set ws.M to the symmetric matrix whose upper triangle is ``upper``'s (CRBA's)."""
    np.copyto(ws.M, upper)
    np.copyto(ws.M, upper.T, where=ws.lower_mask)


def mass_matrix(mech: Mechanism, q: np.ndarray) -> Workspace:
    """Fill M at q (CRBA, symmetric, full).

    The stage projection of the simulator evaluates M and J at the projected q for the
    mass-orthogonal velocity step.
    """
    ws = workspace(mech)
    _symmetric_mass(ws, pin.crba(mech.model, mech.data, q))
    return ws


def compute_terms(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    baumgarte: tuple[float, float] | None = None,
) -> Workspace:
    """Fill M, h, J and gamma at (q, v) (one ``computeAllTerms`` call).

    ``h`` is the bias forces minus the passive joint forces,
    :math:`h(q, v) - \tau_p(q, v)` (:class:`~closedchain.passive.PassiveTerms`).

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        baumgarte: gains (alpha, beta) [1/s]; when given, ``gamma`` holds
            gamma + 2 alpha J v + beta^2 phi (see :class:`SolverSettings`).

    Returns:
        The workspace, whose ``M`` (symmetric, full), ``h``, ``J`` and ``gamma`` are current.
    """
    ws = workspace(mech)
    model, data = mech.model, mech.data
    # CRBA (upper triangle), nonLinearEffects, joint Jacobians, forward kinematics with
    # zero acceleration (the frames' bias accelerations of gamma).
    pin.computeAllTerms(model, data, q, v)
    _symmetric_mass(ws, data.M)
    ws.h[:] = data.nle
    mech.passive.subtract_from_bias(q, v, ws.h)  # h - tau_p: joint springs and damping
    if mech.nc:
        if baumgarte is None:
            mech.constraints.evaluate(model, data, J=ws.J, gamma=ws.gamma)
        else:
            alpha, beta = baumgarte
            mech.constraints.evaluate(model, data, phi=ws.phi, J=ws.J, gamma=ws.gamma)
            ws.gamma += 2.0 * alpha * (ws.J @ v) + beta * beta * ws.phi
    return ws
