"""Forward dynamics of closed chains: one module per method, registered by name.

Use :func:`forward_dynamics`; :data:`METHODS` lists the registered names.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .._locking import exclusive
from .._percall import backend_name, evaluator
from ..compiled import jacobian_rows
from ..exceptions import NonFiniteError, check_settings
from . import augmented_lagrangian as _augmented_lagrangian  # noqa: F401  (registers it)
from . import kkt as _kkt  # noqa: F401  (registers "kkt")
from . import nullspace as _nullspace  # noqa: F401  (registers "nullspace")
from . import pinocchio_method as _pinocchio_method  # noqa: F401  (registers "pinocchio")
from . import proximal as _proximal  # noqa: F401  (registers "proximal")
from . import reduced as _reduced  # noqa: F401  (registers "reduced")
from . import schur as _schur  # noqa: F401  (registers "schur")
from .base import (
    DEFAULT_METHOD,
    DEFAULT_SETTINGS,
    METHODS,
    ForwardDynamicsResult,
    SolverSettings,
    method_name,
    new_frozen,
    workspace,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "ForwardDynamicsResult",
    "SolverSettings",
    "forward_dynamics",
]


@exclusive
def forward_dynamics(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray | None = None,
    *,
    method: str = DEFAULT_METHOD,
    settings: SolverSettings = DEFAULT_SETTINGS,
    backend: str = "auto",
) -> ForwardDynamicsResult:
    """Compute the constrained accelerations and multipliers.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N]; zeros when None.
        method: a name in :data:`METHODS` (any case); default :data:`DEFAULT_METHOD`
            (``"augmented-lagrangian"``, as :func:`~closedchain.simulate`: well posed
            where J loses rank; ``"kkt"`` is the lesson's block system).
        settings: numerical settings.
        backend: ``"auto"`` (the compiled core when it is built, holds the mechanism's
            rows and has the method; else numpy), ``"compiled"`` or ``"numpy"`` (the
            reference implementation). The two agree to round-off.

    Returns:
        The result, with accelerations, multipliers and the J, gamma used.

    Raises:
        UnknownChoiceError: unknown method or backend (lists the valid ones).
        InvalidArgumentError: ``backend="compiled"`` where the core cannot run it.
        SingularConfigurationError: the method cannot solve at q (names q and
            the condition number).
        NonFiniteError: v or tau so large that the result overflows.
    """
    check_settings("settings", settings, SolverSettings)
    method = method_name(method)
    fd = evaluator(mech, method, settings, backend_name(backend))
    if fd is not None:
        # The core checks q, v and tau (the messages below) and the result's finiteness.
        a, lam, J, gamma = fd.core.forward_checked(q, v, tau)
        J = jacobian_rows(J, mech.nv)
        return new_frozen(ForwardDynamicsResult, a=a, lam=lam, method=method, J=J, gamma=gamma)
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    tau = np.zeros(mech.nv) if tau is None else mech.check_v(tau, "tau")
    # An overflow is reported by the finiteness check below, not as a warning.
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        a, lam = METHODS[method](mech, q, v, tau, settings)
    a, lam = np.array(a), np.array(lam)
    if not (np.isfinite(a).all() and np.isfinite(lam).all()):
        raise NonFiniteError(
            f"{mech.name}: method {method!r} overflowed to non-finite accelerations or "
            f"multipliers at max|v| = {np.max(np.abs(v), initial=0):.3g}, "
            f"max|tau| = {np.max(np.abs(tau), initial=0):.3g}: v and tau must be small enough "
            "for M a + h (quadratic in v) to stay finite in double precision"
        )
    ws = workspace(mech)
    return ForwardDynamicsResult(a, lam, method, ws.J.copy(), ws.gamma.copy())
