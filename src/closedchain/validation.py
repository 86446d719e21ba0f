r"""Validation against ``pinocchio.constraintDynamics``.

At random assembled states (q on phi = 0, v with J v = 0, random tau) the
accelerations of a closedchain method are compared with Pinocchio's proximal
constrained dynamics on the same mechanism (revolute loops expressed as two
CONTACT_3D points on the axis). The generalized constraint force
:math:`J^\top\lambda` is compared rather than the multipliers, because it does
not depend on how a closure is parameterized; Pinocchio's sign convention is
the opposite of ``M a + h + J^T lam = tau``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .dynamics import DEFAULT_SETTINGS, METHODS, SolverSettings, forward_dynamics
from .dynamics.base import method_name
from .dynamics.pinocchio_method import pinocchio_constrained_dynamics
from .exceptions import InvalidArgumentError, SingularConfigurationError, UnknownChoiceError
from .kinematics import random_consistent_state
from .mechanism import Mechanism

#: Default tolerance on max |a_ours - a_pin| [rad/s^2].
TOL_ACCELERATION = 1e-9
#: Default tolerance on the generalized constraint force, absolute below
#: 1 N m and relative to |J^T lam_pin| above.
TOL_FORCE = 1e-8


@dataclass(frozen=True)
class ValidationReport:
    """Outcome of :func:`validate`.

    Attributes:
        mechanism: mechanism name.
        method: closedchain method compared.
        n_samples: states compared.
        n_singular: states the method refused as singular (not compared).
        seed: random seed.
        max_da: max over states of max |a_ours - a_pin| [rad/s^2].
        max_dforce: max over states of
            max|J^T lam_ours - J^T lam_pin| / max(1, max|J^T lam_pin|) [N m, relative above 1].
        max_constraint_residual: max |J a + gamma| of our accelerations.
        max_pin_constraint_residual: the same for Pinocchio's accelerations.
        tol_a: tolerance on ``max_da``.
        tol_force: tolerance on ``max_dforce``.
    """

    mechanism: str
    method: str
    n_samples: int
    n_singular: int
    seed: int
    max_da: float
    max_dforce: float
    max_constraint_residual: float
    max_pin_constraint_residual: float
    tol_a: float
    tol_force: float

    @property
    def passed(self) -> bool:
        # States are drawn away from singular J, so a refusal is a failure too.
        return bool(
            self.max_da <= self.tol_a and self.max_dforce <= self.tol_force and self.n_singular == 0
        )

    def as_dict(self) -> dict:
        return {**asdict(self), "passed": self.passed}


#: ``(a, J^T lam)`` from ``pinocchio.constraintDynamics`` in our sign convention
#: (one implementation, shared with the "pinocchio" method).
pinocchio_forward_dynamics = pinocchio_constrained_dynamics


def validate(
    mech: Mechanism,
    *,
    n_samples: int = 100,
    seed: int = 0,
    method: str = "kkt",
    tol_a: float = TOL_ACCELERATION,
    tol_force: float = TOL_FORCE,
    settings: SolverSettings = DEFAULT_SETTINGS,
    velocity_scale: float = 1.0,
    tau_scale: float | None = None,
) -> ValidationReport:
    """Compare a method with ``pinocchio.constraintDynamics`` at random consistent states.

    Args:
        mech: the mechanism (no prismatic loops: Pinocchio has no reference for them).
        n_samples: number of states.
        seed: random seed.
        method: closedchain method to check.
        tol_a: tolerance on max |delta a| [rad/s^2].
        tol_force: tolerance on the generalized constraint force (absolute
            below 1 N m, relative above).
        settings: solver settings for both sides.
        velocity_scale: std of the random velocities before projection [rad/s].
        tau_scale: std of the random generalized forces [N m]; None: the
            mechanism's gravity load, :meth:`Mechanism.gravity_torque_scale`
            (torques of the order the actuators really apply).

    Returns:
        The report; ``report.passed`` says whether both tolerances hold.

    Raises:
        InvalidArgumentError: ``n_samples`` is not an integer >= 1.
        UnknownChoiceError: ``method`` is "pinocchio" (the reference itself).
    """
    if isinstance(n_samples, bool) or not isinstance(n_samples, int | np.integer) or n_samples < 1:
        raise InvalidArgumentError(
            f"n_samples must be an integer >= 1 (a check on no states proves nothing), "
            f"got {n_samples!r}"
        )
    method = method_name(method)
    if method == "pinocchio":
        raise UnknownChoiceError(
            "method to validate against pinocchio.constraintDynamics (it is the reference)",
            method,
            [m for m in METHODS if m != "pinocchio"],
        )
    mech.pinocchio_constraints()  # raise early for prismatic loops
    rng = np.random.default_rng(seed)
    if tau_scale is None:
        tau_scale = mech.gravity_torque_scale() or 1.0
    max_da = max_df = max_res = max_pres = 0.0
    singular = 0
    for _ in range(n_samples):
        q, v = random_consistent_state(mech, rng, velocity_scale=velocity_scale)
        tau = tau_scale * rng.standard_normal(mech.nv)
        try:
            ours = forward_dynamics(mech, q, v, tau, method=method, settings=settings)
        except SingularConfigurationError:
            singular += 1
            continue
        a_pin, f_pin = pinocchio_forward_dynamics(mech, q, v, tau, settings)
        if not (np.all(np.isfinite(a_pin)) and np.all(np.isfinite(f_pin))):
            # A failed reference is a failed comparison, never a skipped one
            # (max() would silently drop a NaN).
            max_da = max_df = float("inf")
            continue
        f_ours = ours.generalized_constraint_force()
        max_da = max(max_da, float(np.max(np.abs(ours.a - a_pin))))
        scale = max(1.0, float(np.max(np.abs(f_pin))))
        max_df = max(max_df, float(np.max(np.abs(f_ours - f_pin))) / scale)
        max_res = max(max_res, ours.constraint_residual())
        max_pres = max(max_pres, float(np.max(np.abs(ours.J @ a_pin + ours.gamma), initial=0.0)))
    return ValidationReport(
        mechanism=mech.name,
        method=method,
        n_samples=n_samples,
        n_singular=singular,
        seed=seed,
        max_da=max_da,
        max_dforce=max_df,
        max_constraint_residual=max_res,
        max_pin_constraint_residual=max_pres,
        tol_a=tol_a,
        tol_force=tol_force,
    )
