r"""Derivatives of the closed-chain dynamics and of the loop rows (the numpy reference).

**Forward dynamics.** Every method solves (:mod:`closedchain.dynamics`)

.. math::

    M(q)\, a + h(q, v) - \tau_p(q, v) + J(q)^\top \lambda = \tau, \qquad
    J(q)\, a + \gamma(q, v) = 0,

with :math:`\tau_p = -K (q - q_0) - D v` the joint springs and dampers
(:mod:`closedchain.passive`). Differentiating both rows at the solution (a, lam) in a
direction x of (q, v, tau) gives one linear system with the KKT matrix,

.. math::

    \begin{bmatrix} M & J^\top \\ J & 0 \end{bmatrix}
    \begin{bmatrix} \partial a / \partial x \\ \partial \lambda / \partial x \end{bmatrix}
    = -\begin{bmatrix} \partial_x \bigl(M a + h - \tau_p + J^\top \lambda - \tau\bigr) \\
    \partial_x \bigl(J a + \gamma\bigr) \end{bmatrix},

the partial derivatives taken at fixed a and lam:

* :math:`\partial_q (M a + h)` and :math:`\partial_v h` are the derivatives of the
  recursive Newton-Euler algorithm (Pinocchio's ``computeRNEADerivatives``, Carpentier
  and Mansard 2018); :math:`\partial_q \tau_p = -K` on the springs' coordinates,
  :math:`\partial_v \tau_p = -D`;
* the constraint acceleration :math:`c(q, v, a) = J(q) a + \gamma(q, v)` is the second
  time derivative of the rows phi; :func:`constraint_derivatives` differentiates it
  (below), and :math:`\partial_v c = \partial \gamma / \partial v`;
* :math:`\partial_q (J^\top \lambda)`, at fixed lam, is read from the same function
  (below);
* :math:`\partial (\cdot) / \partial \tau = -[I; 0]`.

c is linear in a, so :math:`\partial_q c(q, 0, e_j) = \partial_q (J e_j)` and

.. math::

    \frac{\partial (J^\top \lambda)_j}{\partial q_k}
    = \sum_i \lambda_i \frac{\partial J_{ij}}{\partial q_k}
    = \left[\lambda^\top \frac{\partial c}{\partial q}(q, 0, e_j)\right]_k,

one evaluation per column j (nv in all: the readable reference, not the fast path).

Derivatives with respect to q are in the tangent space, as Pinocchio's: column k is
the derivative along :math:`q \oplus \epsilon e_k` (``pin.integrate(model, q, eps *
e_k)``), so ``da_dq`` is comparable with ``ddq_dq`` of
``pinocchio.computeConstraintDynamicsDerivatives``.

**The rows' derivatives.** With the notation of :mod:`closedchain.constraints` (world
placements :math:`(R_p, p_p)`, :math:`(R_s, p_s)` of the cut frames, :math:`U = R_p n`
or :math:`R_p u`, :math:`W = R_s w`, :math:`d = p_p - p_s`), the constraint
acceleration of a translation and of a rotation row is

.. math::

    c_t = \ddot U^\top d + 2 \dot U^\top \dot d + U^\top \ddot d, \qquad
    c_r = \ddot U^\top W + 2 \dot U^\top \dot W + U^\top \ddot W,

with :math:`\dot U = \omega_p \times U`, :math:`\ddot U = \alpha_p \times U +
\omega_p \times \dot U` (the same for W with the successor's), :math:`\dot d = v_p -
v_s` and :math:`\ddot d = a_p - a_s`: the frames' world-aligned velocities and
*classical* accelerations at the actual a (at a = 0 the formula is gamma). Each of
these vectors is a function of (q, v, a) whose derivatives follow from Pinocchio's
LOCAL frame derivatives (``computeForwardKinematicsDerivatives``,
``getFrameAccelerationDerivatives``) rotated to the world: for a vector
:math:`x = R x_L` carried by a frame of world angular Jacobian :math:`J_\omega`,

.. math::

    \frac{\partial x}{\partial q} = R \frac{\partial x_L}{\partial q} - [x]_\times
    J_\omega, \qquad
    a_{cl,L} = a_L + \omega_L \times v_L \quad \text{(classical from spatial)},

and :math:`\partial p / \partial q = R J_{v,L}`, :math:`\partial U / \partial q =
-[U]_\times J_{\omega,p}`. The product rule through the row formulas gives
:math:`\partial c / \partial (q, v, a)`; :math:`\partial c / \partial a = J`. A
coupling row :math:`q_j - m q_i - c` has :math:`c = a_j - m a_i`: its q and v
derivatives are zero. With Baumgarte gains (``SolverSettings.baumgarte``) the
acceleration row is :math:`c + 2 \alpha J v + \beta^2 \phi` and its derivatives
gain :math:`2 \alpha\, \partial_q (J v) + \beta^2 J` and :math:`2 \alpha J`.

**Where the derivative is defined.** The derivative is that of the exact solution of
the KKT system, which every method returns at a regular configuration: ``kkt``
exactly, ``augmented-lagrangian`` (the default) to its tolerance ``al_tol``, the
proximal methods (``proximal``, ``pinocchio``, with regularization ``prox_mu``,
``pinocchio_mu``) at the fixed point of their iteration, which the regularization
does not move. It is evaluated at the (a, lam) that method returned, so it inherits
their accuracy. It is defined where the KKT matrix is regular: J of full row rank (the
independent rows that the row selection keeps) and M positive definite on the null
space of J. Near a singular position the multipliers' derivatives grow like
:math:`1/\sigma_{min}(J)^2` (the accelerations' more slowly) and are still exact
(measured on the 4-bar's change point: max |dlam/dq| 3e3, 3e5, 3e7 at sigma_min 2e-2,
2e-3, 2e-4); where the equilibrated KKT matrix's condition number exceeds
``SolverSettings.cond_max`` (the bound of method ``kkt``) J has lost rank, the solution
(a, lam) is not a differentiable function of q there (the multipliers are not even
unique, and the regularized methods' answers depend on their penalty), and
:func:`forward_dynamics_derivatives` raises :class:`SingularConfigurationError` rather
than return the derivative of a regularized solution. The result carries the condition
number (``kkt_cond``) so that a caller sees how near a singular position it is.

**The default method near a singular position.** The augmented Lagrangian (the default,
:mod:`closedchain.dynamics.augmented_lagrangian`) regularizes with its penalty
:math:`\alpha = \rho\, \mathrm{tr}(M) / \mathrm{tr}(J^\top J)` (:math:`\rho` =
``SolverSettings.al_penalty``): each iteration solves :math:`(M + \alpha J^\top J)\, a =
\tau - h - J^\top \lambda_k - \alpha J^\top \gamma`, whose fixed point is the KKT
solution whatever :math:`\alpha`. Where J has full rank the iteration converges to it
(to ``al_tol``; short of the 4-bar's change point at sigma_min 2e-3 and 2e-4, in the
tests, its derivatives agree with kkt's to 1e-9), so the derivative returned for the
default method is the KKT one, and it does not depend on the penalty. At the singular
position itself the augmented Lagrangian still returns accelerations (Gauss's
principle's minimizer) and multipliers (those its ``al_max_iter`` iterations from
:math:`\lambda_0 = 0` reach, which depend on :math:`\alpha`); the derivative of that
regularized answer would be the derivative of :math:`[M, J^\top; J, -\alpha^{-1} I]`'s
solution, whose multipliers' derivative along the lost row grows with :math:`\alpha`
(as :math:`1/\sigma^2` grows as sigma_min falls to 0): a property of the penalty, not of
the mechanism: :func:`forward_dynamics_derivatives` refuses it (above). The same
holds for :func:`step_derivatives`, whose stages' accelerations are differentiated so.

**Inverse dynamics.** :func:`inverse_dynamics_derivatives` differentiates the optimality
system of :func:`closedchain.inverse_dynamics`' minimum-norm torques (its docstring),
with the same partial derivatives and :math:`\partial_q (J \mu)` at fixed mu.

**One integration step.** :func:`step_derivatives` differentiates one step of rk4 with
stage projection and of the default integrator (dop853-rk43) in forward mode, stage by
stage, the projections included (its docstring); every tangent is carried as the
(nv, 3 nv) matrix of its derivatives in (q, v, tau) at the step's start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.integrate._ivp import dop853_coefficients as dop
from scipy.linalg import lapack

from ._locking import exclusive
from .constraints import ConstraintLayer
from .dynamics import DEFAULT_METHOD, forward_dynamics
from .dynamics.base import (
    DEFAULT_SETTINGS,
    KKT_HINT,
    METHOD_CAPABILITIES,
    SolverSettings,
    get_method,
    mass_matrix,
    singular_error,
)
from .dynamics.kkt import estimate_scaled_inverse_norm, kkt_scaling
from .exceptions import ClosedChainError, UnknownChoiceError, check_settings
from .inverse import _svd, inverse_dynamics
from .kinematics import compute_jacobian, compute_phi
from .mechanism import Mechanism
from .pindata import frame_jacobian
from .simulate.chart import curved_blocks
from .simulate.dop853_rk43 import FAR_METHODS, INDICATOR_STAGE_A, INDICATOR_STAGE_B
from .simulate.fixed import RANK_INDICATOR_CAP, rank_indicator
from .simulate.settings import DEFAULT_SIMULATION_SETTINGS, SimulationSettings

__all__ = [
    "ConstraintDerivatives",
    "ForwardDynamicsDerivatives",
    "InverseDynamicsDerivatives",
    "StepDerivatives",
    "constraint_derivatives",
    "forward_dynamics_derivatives",
    "inverse_dynamics_derivatives",
    "step_derivatives",
]

_LOCAL = pin.ReferenceFrame.LOCAL


@dataclass(frozen=True)
class ConstraintDerivatives:
    """The independent loop rows at (q, v) and their derivatives (tangent space in q).

    Attributes:
        phi: the rows, shape (nc,) [m or -].
        J: d phi / dq, shape (nc, nv).
        gamma: Jdot v, shape (nc,) [m/s^2 or 1/s^2].
        dJv_dq: d (J(q) v) / dq at fixed v, shape (nc, nv) [m/s or 1/s per rad or m].
        dgamma_dq: d gamma / dq, shape (nc, nv).
        dgamma_dv: d gamma / dv, shape (nc, nv).
    """

    phi: np.ndarray
    J: np.ndarray
    gamma: np.ndarray
    dJv_dq: np.ndarray
    dgamma_dq: np.ndarray
    dgamma_dv: np.ndarray


@dataclass(frozen=True)
class ForwardDynamicsDerivatives:
    """Constrained accelerations, multipliers and their derivatives at (q, v, tau).

    Attributes:
        a: joint accelerations, shape (nv,) [rad/s^2 or m/s^2], as
            :func:`closedchain.forward_dynamics` returns them.
        lam: multipliers of the independent rows, shape (nc,), in the convention
            ``M a + h + J^T lam = tau`` (the order of ``mech.constraints.rows``).
        method: the method that gave a and lam.
        da_dq: d a / dq in the tangent space (along ``pin.integrate``), shape (nv, nv).
        da_dv: d a / dv, shape (nv, nv).
        da_dtau: d a / d tau, shape (nv, nv).
        dlam_dq: d lam / dq, shape (nc, nv).
        dlam_dv: d lam / dv, shape (nc, nv).
        dlam_dtau: d lam / d tau, shape (nc, nv).
        kkt_cond: 1-norm condition number estimate of the equilibrated KKT matrix,
            as method ``kkt`` judges it (its equilibration rescales a row of J that
            vanishes as a whole, as at the 4-bar's change point, so it can stay small
            while the multipliers' derivatives grow like 1 / sigma_min(J)^2).
    """

    a: np.ndarray
    lam: np.ndarray
    method: str
    da_dq: np.ndarray
    da_dv: np.ndarray
    da_dtau: np.ndarray
    dlam_dq: np.ndarray
    dlam_dv: np.ndarray
    dlam_dtau: np.ndarray
    kkt_cond: float


# -- forward-mode vectors: (value, tangent) with tangent columns [q | v | a] ---------------


def _cross(x, y):
    """(x0 x y0, d(x x y)) of two (value (3,), tangent (3, m)) pairs."""
    sx = pin.skew(x[0])  # np.cross costs 20 times more on 3-vectors
    return sx @ y[0], sx @ y[1] - pin.skew(y[0]) @ x[1]


def _dot(x, y):
    """(x0 . y0, d(x . y)) of two (value (3,), tangent (3, m)) pairs."""
    return float(x[0] @ y[0]), y[0] @ x[1] + x[0] @ y[1]


def _add(x, y, s: float = 1.0):
    """x + s y of two pairs (value, tangent)."""
    return x[0] + s * y[0], x[1] + s * y[1]


class _FrameMotion:
    """World vectors of one frame at (q, v, a) with tangents over (q, v, a), shape (3, 3 nv).

    Attributes (each a pair (value (3,), tangent (3, 3 nv))):
        p: origin position; w, v: angular and origin velocity; alpha, acc: angular and
        classical linear acceleration of the origin. R: its rotation, Jw: its world
        angular Jacobian, shape (3, nv).
    """

    def __init__(self, model: pin.Model, data: pin.Data, fid: int) -> None:
        nv = model.nv
        R = data.oMf[fid].rotation
        JL = frame_jacobian(model, data, fid, _LOCAL)
        self.R, self.Jw = R, R @ JL[3:]
        vel = pin.getFrameVelocity(model, data, fid, _LOCAL)
        acc = pin.getFrameAcceleration(model, data, fid, _LOCAL)
        dv_dq, da_dq, da_dv, da_da = (
            np.reshape(x, (6, nv))
            for x in pin.getFrameAccelerationDerivatives(model, data, fid, _LOCAL)
        )
        z = np.zeros((6, nv))
        dvel = np.hstack([dv_dq, JL, z])  # LOCAL spatial velocity over (q, v, a)
        dacc = np.hstack([da_dq, da_dv, da_da])  # LOCAL spatial acceleration
        wL, vL = (vel.angular, dvel[3:]), (vel.linear, dvel[:3])
        # classical linear acceleration of the origin: a_L + omega_L x v_L
        accL = _add((acc.linear, dacc[:3]), _cross(wL, vL))
        self.w = self._world(wL)
        self.v = self._world(vL)
        self.alpha = self._world((acc.angular, dacc[3:]))
        self.acc = self._world(accL)
        dp = np.zeros((3, 3 * nv))
        dp[:, :nv] = R @ JL[:3]
        self.p = (data.oMf[fid].translation.copy(), dp)

    def _world(self, xL):
        """R x_L with d/dq = R dx_L/dq - [R x_L]x J_w."""
        x = self.R @ xL[0]
        dx = self.R @ xL[1]
        dx[:, : self.Jw.shape[1]] -= pin.skew(x) @ self.Jw
        return x, dx

    def carried(self, u: np.ndarray):
        """R u for a constant u in the frame, with d/dq = -[R u]x J_w."""
        x = self.R @ u
        dx = np.zeros((3, 3 * self.Jw.shape[1]))
        dx[:, : self.Jw.shape[1]] = -pin.skew(x) @ self.Jw
        return x, dx


def _vector_kinematics(f: _FrameMotion, x):
    """(x dot, x ddot) of a vector x carried by frame f: w x x, alpha x x + w x x dot."""
    xd = _cross(f.w, x)
    return xd, _add(_cross(f.alpha, x), _cross(f.w, xd))


def _acceleration_rows(
    model: pin.Model, data: pin.Data, layer: ConstraintLayer, a: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return c = J a + gamma and dc/d(q, v, a), shapes (nc,), (nc, 3 nv), from ``data``.

    ``data`` must hold ``computeJointJacobians(q)``, then
    ``computeForwardKinematicsDerivatives(q, v, a)`` and ``updateFramePlacements``.
    """
    nv = model.nv
    c = np.zeros(layer.nc)
    dc = np.zeros((layer.nc, 3 * nv))
    for blk, sl in layer.per_loop():
        if blk.n == 0:
            continue
        if blk.coupling:  # c = a_j - m a_i: only its a-columns, which are J's row
            ji = model.frames[blk.fid_p].parentJoint
            jj = model.frames[blk.fid_s].parentJoint
            iv, jv = model.joints[ji].idx_v, model.joints[jj].idx_v
            dc[sl.start, 2 * nv + jv] += 1.0
            dc[sl.start, 2 * nv + iv] -= blk.spec.multiplier
            c[sl.start] = a[jv] - blk.spec.multiplier * a[iv]
            continue
        fp = _FrameMotion(model, data, blk.fid_p)
        fs = _FrameMotion(model, data, blk.fid_s)
        d = _add(fp.p, fs.p, -1.0)
        d_dot = _add(fp.v, fs.v, -1.0)
        d_ddot = _add(fp.acc, fs.acc, -1.0)
        r = sl.start
        for n in blk.trans:  # c_t = U'' . d + 2 U' . d' + U . d''
            U = fp.carried(n)
            Ud, Udd = _vector_kinematics(fp, U)
            terms = (_dot(Udd, d), _dot(Ud, d_dot), _dot(U, d_ddot))
            c[r] = terms[0][0] + 2.0 * terms[1][0] + terms[2][0]
            dc[r] = terms[0][1] + 2.0 * terms[1][1] + terms[2][1]
            r += 1
        for u, w in zip(blk.rot_u, blk.rot_w, strict=True):  # c_r = U'' . W + 2 U' . W' + U . W''
            U, W = fp.carried(u), fs.carried(w)
            Ud, Udd = _vector_kinematics(fp, U)
            Wd, Wdd = _vector_kinematics(fs, W)
            terms = (_dot(Udd, W), _dot(Ud, Wd), _dot(U, Wdd))
            c[r] = terms[0][0] + 2.0 * terms[1][0] + terms[2][0]
            dc[r] = terms[0][1] + 2.0 * terms[1][1] + terms[2][1]
            r += 1
    return c, dc


def _constraint_acceleration(mech: Mechanism, data, q, v, a) -> tuple[np.ndarray, np.ndarray]:
    """c(q, v, a) = J a + gamma and its derivatives over (q, v, a), shape (nc, 3 nv)."""
    model = mech.model
    pin.computeJointJacobians(model, data, q)
    pin.computeForwardKinematicsDerivatives(model, data, q, v, a)
    pin.updateFramePlacements(model, data)
    return _acceleration_rows(model, data, mech.constraints, a)


def _dJTlam_dq(mech: Mechanism, data, q, lam) -> np.ndarray:
    """d (J^T lam) / dq at fixed lam, shape (nv, nv): row j is lam^T d(J e_j)/dq."""
    nv = mech.nv
    out = np.zeros((nv, nv))
    zero = np.zeros(nv)
    for j in range(nv):
        _, dc = _constraint_acceleration(mech, data, q, zero, np.eye(nv)[j])
        out[j] = lam @ dc[:, :nv]
    return out


@exclusive
def constraint_derivatives(mech: Mechanism, q: np.ndarray, v: np.ndarray) -> ConstraintDerivatives:
    r"""Return the independent rows phi, J, gamma at (q, v) and their derivatives.

    Derivatives in q are in the tangent space (along ``pin.integrate``); the formulas
    are in the module docstring. gamma = Jdot v is quadratic in v and
    :math:`\partial \gamma / \partial v` is not :math:`\dot J` in general.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,) (need not be closed).
        v: velocity, shape (nv,) (need not satisfy J v = 0).

    Returns:
        The rows and ``dJv_dq``, ``dgamma_dq``, ``dgamma_dv`` (see
        :class:`ConstraintDerivatives`).
    """
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    nv, model = mech.nv, mech.model
    data = model.createData()
    zero = np.zeros(nv)
    gamma, dg = _constraint_acceleration(mech, data, q, v, zero)
    phi, J = np.zeros(mech.nc), np.zeros((mech.nc, nv))
    mech.constraints.evaluate(model, data, phi=phi, J=J)
    _, dJv = _constraint_acceleration(mech, data, q, zero, v)
    return ConstraintDerivatives(
        phi=phi,
        J=J,
        gamma=gamma,
        dJv_dq=dJv[:, :nv].copy(),
        dgamma_dq=dg[:, :nv].copy(),
        dgamma_dv=dg[:, nv : 2 * nv].copy(),
    )


def _passive_derivatives(mech: Mechanism) -> tuple[np.ndarray, np.ndarray]:
    """d tau_p / dq (tangent) and d tau_p / dv, shapes (nv, nv): -K and -D on the diagonal."""
    p, nv = mech.passive, mech.nv
    dq = np.zeros((nv, nv))
    dq[p.spring_idx_v, p.spring_idx_v] = -p.stiffness  # springs sit on 1-dof joints
    return dq, -np.diag(p.damping)


@exclusive
def forward_dynamics_derivatives(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray | None = None,
    *,
    method: str = DEFAULT_METHOD,
    settings: SolverSettings = DEFAULT_SETTINGS,
) -> ForwardDynamicsDerivatives:
    r"""Compute the constrained accelerations, multipliers and their derivatives.

    a and lam are :func:`closedchain.forward_dynamics`'s with the same method and
    settings; the derivatives are those of the exact KKT solution, evaluated at them
    (module docstring: the linear system, and what the derivative is near a singular
    position).

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N]; zeros when None.
        method: a forward-dynamics method (:data:`closedchain.METHODS`).
        settings: its numerical settings; ``cond_max`` bounds the KKT matrix's
            condition number, ``baumgarte`` adds its terms to the acceleration rows.

    Returns:
        a, lam and ``da_dq``, ``da_dv``, ``da_dtau``, ``dlam_dq``, ``dlam_dv``,
        ``dlam_dtau`` (:class:`ForwardDynamicsDerivatives`).

    Raises:
        SingularConfigurationError: the equilibrated KKT matrix's condition number
            exceeds ``settings.cond_max`` (J has lost rank: the derivative is not
            defined).
    """
    check_settings("settings", settings, SolverSettings)
    res = forward_dynamics(mech, q, v, tau, method=method, settings=settings)
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    a, lam = np.array(res.a), np.array(res.lam)
    model, nv, nc = mech.model, mech.nv, mech.nc
    data = model.createData()
    # Row 1 at fixed (a, lam): d(M a + h)/d(q, v) by RNEA, M = d/da (armature included).
    drnea_dq, drnea_dv, M = (np.array(x) for x in pin.computeRNEADerivatives(model, data, q, v, a))
    M = np.triu(M) + np.triu(M, 1).T
    dtp_dq, dtp_dv = _passive_derivatives(mech)
    F1q = drnea_dq - dtp_dq
    F1v = drnea_dv - dtp_dv
    # Row 2: c(q, v, a) = J a + gamma (+ Baumgarte terms).
    _, dc = _constraint_acceleration(mech, data, q, v, a)
    F2q, F2v, J = dc[:, :nv], dc[:, nv : 2 * nv], dc[:, 2 * nv :]
    if nc:
        F1q = F1q + _dJTlam_dq(mech, data, q, lam)
        if settings.baumgarte is not None:
            alpha, beta = settings.baumgarte
            _, dJv = _constraint_acceleration(mech, data, q, np.zeros(nv), v)
            F2q = F2q + 2.0 * alpha * dJv[:, :nv] + beta * beta * J
            F2v = F2v + 2.0 * alpha * J
    K = np.zeros((nv + nc, nv + nc), order="F")
    K[:nv, :nv], K[:nv, nv:], K[nv:, :nv] = M, J.T, J
    rhs = np.zeros((nv + nc, 3 * nv), order="F")
    rhs[:nv, :nv], rhs[nv:, :nv] = -F1q, -F2q
    rhs[:nv, nv : 2 * nv], rhs[nv:, nv : 2 * nv] = -F1v, -F2v
    rhs[:nv, 2 * nv :] = np.eye(nv)
    lu, piv, info = lapack.dgetrf(K)
    cond = _kkt_condition(K, lu, piv, info, M, J)
    if cond > settings.cond_max:
        raise singular_error(
            mech,
            q,
            "the KKT matrix [[M, J^T], [J, 0]] (equilibrated) of the derivatives",
            cond,
            settings.cond_max,
            KKT_HINT + "; the derivatives of a and lam are not defined there",
        )
    X = lapack.dgetrs(lu, piv, rhs)[0]
    return ForwardDynamicsDerivatives(
        a=a,
        lam=lam,
        method=res.method,
        da_dq=X[:nv, :nv].copy(),
        da_dv=X[:nv, nv : 2 * nv].copy(),
        da_dtau=X[:nv, 2 * nv :].copy(),
        dlam_dq=X[nv:, :nv].copy(),
        dlam_dv=X[nv:, nv : 2 * nv].copy(),
        dlam_dtau=X[nv:, 2 * nv :].copy(),
        kkt_cond=cond,
    )


def _kkt_condition(K, lu, piv, info, M, J) -> float:
    """The 1-norm condition number estimate of the equilibrated K (as method ``kkt``)."""
    if info > 0:
        return float("inf")
    d = np.concatenate(kkt_scaling(M, J))
    scaled_norm = float(np.max(d * (d @ np.abs(K)), initial=0.0))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        est = estimate_scaled_inverse_norm(lu, piv, 1.0 / d)
    return est * scaled_norm if est < float("inf") else float("inf")


# -- inverse dynamics ------------------------------------------------------------------------


@dataclass(frozen=True)
class InverseDynamicsDerivatives:
    """Actuator torques of :func:`closedchain.inverse_dynamics` and their derivatives.

    The inputs are (q, v, a_P): the configuration (derivatives in the tangent space, along
    ``pin.integrate``), the velocity and the accelerations of the prescribed coordinates
    P (``coordinates``, the independent ones by default); ``tau_passive`` is held fixed.

    Attributes:
        tau: generalized forces, shape (nv,) [N m or N], zero off the actuated coordinates.
        a: accelerations of every coordinate, shape (nv,) [rad/s^2 or m/s^2].
        lam: multipliers of the independent rows, shape (nc,), in the convention
            ``M a + h + J^T lam = tau``.
        actuated_idx_v: velocity indices where tau acts, shape (na,).
        prescribed_idx_v: velocity indices of a_P, shape (mobility,).
        dtau_dq: d tau / dq (tangent), shape (nv, nv) [N m or N per rad or m]; zero rows
            off the actuated coordinates.
        dtau_dv: d tau / dv, shape (nv, nv) [N m s or N s per rad or m].
        dtau_da: d tau / d a_P, shape (nv, mobility) [kg m^2 or kg].
        da_dq: d a / dq (tangent), shape (nv, nv) [1/s^2].
        da_dv: d a / dv, shape (nv, nv) [1/s].
        da_da: d a / d a_P, shape (nv, mobility) [-]: the identity on the rows P.
        dlam_dq: d lam / dq (tangent), shape (nc, nv).
        dlam_dv: d lam / dv, shape (nc, nv).
        dlam_da: d lam / d a_P, shape (nc, mobility).
    """

    tau: np.ndarray
    a: np.ndarray
    lam: np.ndarray
    actuated_idx_v: np.ndarray
    prescribed_idx_v: np.ndarray
    dtau_dq: np.ndarray
    dtau_dv: np.ndarray
    dtau_da: np.ndarray
    da_dq: np.ndarray
    da_dv: np.ndarray
    da_da: np.ndarray
    dlam_dq: np.ndarray
    dlam_dv: np.ndarray
    dlam_da: np.ndarray


def _dJw_dq(mech: Mechanism, data, q, w) -> np.ndarray:
    """d (J(q) w) / dq at fixed w, shape (nc, nv) (tangent): c(q, 0, w) = J w."""
    _, dc = _constraint_acceleration(mech, data, q, np.zeros(mech.nv), w)
    return dc[:, : mech.nv]


def _dMu_dq(model: pin.Model, data, q, u) -> np.ndarray:
    """d (M(q) u) / dq at fixed u, shape (nv, nv) (tangent): rnea(q, 0, u) - rnea(q, 0, 0)."""
    zero = np.zeros(model.nv)
    d_u = np.array(pin.computeRNEADerivatives(model, data, q, zero, u)[0])
    d_0 = np.array(pin.computeRNEADerivatives(model, data, q, zero, zero)[0])
    return d_u - d_0


@exclusive
def inverse_dynamics_derivatives(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    a_independent: np.ndarray,
    *,
    actuated="actuated",
    coordinates="independent",
    tau_passive: np.ndarray | None = None,
    settings: SolverSettings = DEFAULT_SETTINGS,
) -> InverseDynamicsDerivatives:
    r"""Compute the actuator torques of prescribed accelerations and their derivatives.

    tau, a and lam are :func:`closedchain.inverse_dynamics`'s (same arguments). Its
    torques are the minimum-norm solution of the equations of motion (the unique one
    with as many actuators as degrees of freedom), so with a multiplier :math:`\mu` of
    that minimization the unknowns :math:`z = (a_F, \tau_A, \lambda, \mu)` solve the
    square system

    .. math::

        J_F a_F + J_P a_P + \gamma = 0, \quad
        M a + h - \tau_p - \tau_{passive} - B \tau_A + J^\top \lambda = 0, \quad
        \tau_A + B^\top \mu = 0, \quad J \mu = 0,

    regular where :func:`closedchain.inverse_dynamics` is defined (J_F and J of full
    rank, N^T B of full row rank). Differentiated at the solution in (q, v, a_P) with
    the same partial derivatives as :func:`forward_dynamics_derivatives` (RNEA, the
    constraint acceleration, :math:`\partial_q (J^\top \lambda)`, :math:`\partial_q (J
    \mu)`) it gives one linear solve for dz.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0 [rad/s or m/s].
        a_independent: accelerations of ``coordinates``, shape (mobility,)
            [rad/s^2 or m/s^2].
        actuated: as :func:`closedchain.inverse_dynamics`.
        coordinates: as :func:`closedchain.inverse_dynamics`.
        tau_passive: generalized forces besides the actuators, shape (nv,) [N m or N],
            held fixed (no derivative), or None.
        settings: as :func:`closedchain.inverse_dynamics` (``cond_max``).

    Returns:
        tau, a, lam and their derivatives (:class:`InverseDynamicsDerivatives`).

    Raises:
        ClosedChainError: what :func:`closedchain.inverse_dynamics` raises; and, with
            more actuators than degrees of freedom, where its torques balance J's
            near-null directions (``weak_rcond``) instead of being the minimum-norm
            ones: their derivative is not implemented.
        SingularConfigurationError: as :func:`closedchain.inverse_dynamics`.
    """
    res = inverse_dynamics(
        mech,
        q,
        v,
        a_independent,
        actuated=actuated,
        coordinates=coordinates,
        tau_passive=tau_passive,
        settings=settings,
    )
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    model, nv, nc = mech.model, mech.nv, mech.nc
    P, A = np.asarray(res.prescribed_idx_v), np.asarray(res.actuated_idx_v)
    F = np.setdiff1d(np.arange(nv), P)
    nP, nF, nA = len(P), len(F), len(A)
    a, lam, tau = np.array(res.a), np.array(res.lam), np.array(res.tau)
    J = np.array(res.J)
    if nc and nA > nP:
        s = _svd(J)[1]
        if np.any(s < settings.weak_rcond * s[0]):
            raise ClosedChainError(
                f"{mech.name}: over-actuated inverse dynamics balances J's near-null "
                f"directions here (sigma_min / sigma_max = {s[-1] / s[0]:.3g} < weak_rcond "
                f"= {settings.weak_rcond:g}): the derivatives of those torques are not "
                "implemented, only of the minimum-norm ones"
            )
    B = np.zeros((nv, nA))
    B[A, np.arange(nA)] = 1.0
    # mu from tau_A + B^T mu = 0, J mu = 0 (consistent for the minimum-norm torques).
    mu = np.linalg.lstsq(np.vstack([B.T, J]), np.concatenate([-tau[A], np.zeros(nc)]), rcond=None)[
        0
    ]
    data = model.createData()
    drnea_dq, drnea_dv, M = (np.array(x) for x in pin.computeRNEADerivatives(model, data, q, v, a))
    M = np.triu(M) + np.triu(M, 1).T
    dtp_dq, dtp_dv = _passive_derivatives(mech)
    _, dc = _constraint_acceleration(mech, data, q, v, a)
    # Unknowns z = (a_F, tau_A, lam, mu); rows R1 (nc), R2 (nv), R3 (nA), R4 (nc).
    n = nF + nA + nc + nv
    r2, r3, r4 = nc, nc + nv, nc + nv + nA
    cA, cL, cM = nF, nF + nA, nF + nA + nc
    K = np.zeros((n, n))
    K[:nc, :nF] = J[:, F]
    K[r2:r3, :nF] = M[:, F]
    K[r2:r3, cA:cL] = -B
    K[r2:r3, cL:cM] = J.T
    K[r3:r4, cA:cL] = np.eye(nA)
    K[r3:r4, cM:] = B.T
    K[r4:, cM:] = J
    # The rows' partial derivatives in (q, v, a_P), at fixed z.
    R = np.zeros((n, 2 * nv + nP))
    R[:nc, :nv], R[:nc, nv : 2 * nv], R[:nc, 2 * nv :] = dc[:, :nv], dc[:, nv : 2 * nv], J[:, P]
    R[r2:r3, :nv] = drnea_dq - dtp_dq
    R[r2:r3, nv : 2 * nv] = drnea_dv - dtp_dv
    R[r2:r3, 2 * nv :] = M[:, P]
    if nc:
        R[r2:r3, :nv] += _dJTlam_dq(mech, data, q, lam)
        R[r4:, :nv] = _dJw_dq(mech, data, q, mu)
    lu, piv, info = lapack.dgetrf(K)
    if info != 0:  # pragma: no cover - inverse_dynamics refuses these configurations
        raise singular_error(mech, q, "the inverse dynamics' linearization", np.inf, 0.0, "")
    X = -lapack.dgetrs(lu, piv, R)[0]
    da = np.zeros((nv, 2 * nv + nP))
    da[F] = X[:nF]
    da[P, 2 * nv + np.arange(nP)] = 1.0
    dtau = np.zeros((nv, 2 * nv + nP))
    dtau[A] = X[cA:cL]
    dlam = X[cL:cM]
    return InverseDynamicsDerivatives(
        tau=tau,
        a=a,
        lam=lam,
        actuated_idx_v=A,
        prescribed_idx_v=P,
        dtau_dq=dtau[:, :nv].copy(),
        dtau_dv=dtau[:, nv : 2 * nv].copy(),
        dtau_da=dtau[:, 2 * nv :].copy(),
        da_dq=da[:, :nv].copy(),
        da_dv=da[:, nv : 2 * nv].copy(),
        da_da=da[:, 2 * nv :].copy(),
        dlam_dq=dlam[:, :nv].copy(),
        dlam_dv=dlam[:, nv : 2 * nv].copy(),
        dlam_da=dlam[:, 2 * nv :].copy(),
    )


# -- one integration step --------------------------------------------------------------------

#: The integrators whose one step :func:`step_derivatives` differentiates ("default" is
#: :data:`closedchain.simulate.DEFAULT_INTEGRATOR`).
STEP_INTEGRATORS = ("rk4", "dop853-rk43", "default")


@dataclass(frozen=True)
class StepDerivatives:
    """The state after one integration step and its derivatives in the start state and tau.

    Tangent spaces as :func:`forward_dynamics_derivatives`: column k of a ``d*_dq`` is
    along ``pin.integrate(model, q, eps e_k)``, and a ``dq_d*`` is the displacement of the
    end configuration q+ in its tangent space (``pin.difference(model, q+, q+(eps))``).

    Attributes:
        q: configuration after the step, shape (nq,).
        v: velocity after the step, shape (nv,) [rad/s or m/s].
        scheme: the step taken: ``"rk4-projected"`` (rk4, every stage and the end
            projected) or ``"dop853"`` (DOP853, its end projected).
        h: the step [s].
        dq_dq: d q+ / dq, shape (nv, nv) [-].
        dq_dv: d q+ / dv, shape (nv, nv) [s].
        dq_dtau: d q+ / d tau, shape (nv, nv) [rad or m per N m or N].
        dv_dq: d v+ / dq, shape (nv, nv) [1/s].
        dv_dv: d v+ / dv, shape (nv, nv) [-].
        dv_dtau: d v+ / d tau, shape (nv, nv) [rad/s or m/s per N m or N].
    """

    q: np.ndarray
    v: np.ndarray
    scheme: str
    h: float
    dq_dq: np.ndarray
    dq_dv: np.ndarray
    dq_dtau: np.ndarray
    dv_dq: np.ndarray
    dv_dv: np.ndarray
    dv_dtau: np.ndarray


class _FarFromJ(Exception):
    """A DOP853 sample of the rank indicator fell below its cap: the step is rk43's."""


class _Stepper:
    """Forward-mode arithmetic of one step: every quantity is a pair (value, tangent) with
    tangent columns [dq | dv | dtau] of the start state, shape (nv, 3 nv). On joints whose
    ``integrate`` is x + v (revolute, prismatic, continuous) the tangent of
    ``integrate(q, x)`` is the tangent of q plus that of x."""

    def __init__(self, mech, tau, method, settings, sim_settings, mass_orthogonal) -> None:
        self.mech, self.tau = mech, tau
        self.method, self.settings, self.sim = method, settings, sim_settings
        self.mass_orthogonal = mass_orthogonal and mech.nc > 0
        self.data = mech.model.createData()
        nv = mech.nv
        self.dtau = np.hstack([np.zeros((nv, 2 * nv)), np.eye(nv)])

    def accel(self, q, dq, v, dv, method: str):
        """a(q, v, tau) of ``method`` and its tangent (:func:`forward_dynamics_derivatives`)."""
        d = forward_dynamics_derivatives(
            self.mech, q, v, self.tau, method=method, settings=self.settings
        )
        return d.a, d.da_dq @ dq + d.da_dv @ dv + d.da_dtau @ self.dtau

    def min_norm(self, q, J, r, dr, dq):
        """w = J^+ r (minimum norm) and its tangent: with y = (J J^T)^-1 r, w = J^T y,
        dw = d(J^T y)|_y + J^T (J J^T)^-1 (dr - d(J w)|_w - J d(J^T y)|_y)."""
        mech, data = self.mech, self.data
        w = np.linalg.lstsq(J, r, rcond=None)[0]  # as simulate.problem.project
        G = J @ J.T
        y = np.linalg.solve(G, r)
        D2 = _dJTlam_dq(mech, data, q, y) @ dq
        rhs = dr - _dJw_dq(mech, data, q, w) @ dq - J @ D2
        return w, D2 + J.T @ np.linalg.solve(G, rhs)

    def project(self, q, dq, v, dv):
        """:func:`closedchain.simulate.problem.project` and its tangent: Gauss-Newton on q
        (minimum-norm corrections) to ``projection_tol``, then v onto J v = 0 (minimum
        norm, or mass-orthogonal: the KKT solution that the augmented-Lagrangian
        iteration of the stage projection converges to)."""
        mech, sim = self.mech, self.sim
        model = mech.model
        J = None
        for _ in range(sim.projection_iters):
            phi = compute_phi(mech, q, backend="numpy")
            J = compute_jacobian(mech, q, backend="numpy")
            if np.max(np.abs(phi), initial=0.0) <= sim.projection_tol:
                break
            w, dw = self.min_norm(q, J, -phi, -J @ dq, dq)
            q, dq = pin.integrate(model, q, w), dq + dw
            J = None
        if J is None:
            J = compute_jacobian(mech, q, backend="numpy")
        if mech.nc:
            # The derivative of the iteration's limit: one more iteration at phi = 0 maps
            # dq to (I - J^+ J) dq. Without it a start already within projection_tol
            # (where the iteration stops at once) would not be projected at all.
            dq = dq - np.linalg.lstsq(J, J @ dq, rcond=None)[0]
        if not sim.project_velocities:
            return q, dq, v, dv
        data = self.data
        if self.mass_orthogonal:
            # M (v+ - v) + J^T mu = 0, J v+ = 0, differentiated at the solution.
            M = mass_matrix(mech, q).M.copy()
            nv, nc = mech.nv, mech.nc
            K = np.zeros((nv + nc, nv + nc))
            K[:nv, :nv], K[:nv, nv:], K[nv:, :nv] = M, J.T, J
            sol = np.linalg.solve(K, np.concatenate([M @ v, np.zeros(nc)]))
            v_new, mu = sol[:nv], sol[nv:]
            rhs = np.vstack(
                [
                    M @ dv
                    - _dMu_dq(model, data, q, v_new - v) @ dq
                    - _dJTlam_dq(mech, data, q, mu) @ dq,
                    -_dJw_dq(mech, data, q, v_new) @ dq,
                ]
            )
            return q, dq, v_new, np.linalg.solve(K, rhs)[:nv]
        dr = J @ dv + _dJw_dq(mech, data, q, v) @ dq
        w, dw = self.min_norm(q, J, J @ v, dr, dq)
        return q, dq, v - w, dv - dw

    def rk4_projected(self, q, v, h):
        """:func:`closedchain.simulate.fixed.rk4_projected` (stages and end projected)."""
        model, nv = self.mech.model, self.mech.nv
        dq0 = np.hstack([np.eye(nv), np.zeros((nv, 2 * nv))])
        dv0 = np.hstack([np.zeros((nv, nv)), np.eye(nv), np.zeros((nv, nv))])
        a, da = self.accel(q, dq0, v, dv0, self.method)
        kx, dkx, ka, dka = [v], [dv0], [a], [da]
        for c in (0.5, 0.5, 1.0):  # stage i from stage i - 1: x = c h k_x, v + c h k_a
            qs = pin.integrate(model, q, c * h * kx[-1])
            dqs = dq0 + c * h * dkx[-1]
            vs, dvs = v + c * h * ka[-1], dv0 + c * h * dka[-1]
            qs, dqs, vs, dvs = self.project(qs, dqs, vs, dvs)
            a, da = self.accel(qs, dqs, vs, dvs, self.method)
            kx.append(vs)  # chart.tangent_rate: the identity on these joints
            dkx.append(dvs)
            ka.append(a)
            dka.append(da)
        w = np.array([1.0, 2.0, 2.0, 1.0]) * h / 6.0
        q_new = pin.integrate(model, q, sum(wi * k for wi, k in zip(w, kx, strict=True)))
        dq_new = dq0 + sum(wi * k for wi, k in zip(w, dkx, strict=True))
        v_new = v + sum(wi * k for wi, k in zip(w, ka, strict=True))
        dv_new = dv0 + sum(wi * k for wi, k in zip(w, dka, strict=True))
        return self.project(q_new, dq_new, v_new, dv_new)

    def dop853(self, q, v, h, far_method: str):
        """The DOP853 step of :class:`closedchain.simulate.dop853_rk43.Dop853Far`
        (stages unprojected, the end projected with the minimum-norm correction); raises
        _FarFromJ where a trial would hand over to rk43."""
        mech = self.mech
        model, nv = mech.model, mech.nv

        def near(qs) -> bool:
            J = compute_jacobian(mech, qs, backend="numpy")
            return mech.nc > 0 and rank_indicator(J, cap=math.inf) < RANK_INDICATOR_CAP

        if near(q):
            raise _FarFromJ
        dq0 = np.hstack([np.eye(nv), np.zeros((nv, 2 * nv))])
        dv0 = np.hstack([np.zeros((nv, nv)), np.eye(nv), np.zeros((nv, nv))])
        n_st = dop.N_STAGES
        kx, ka = np.empty((n_st, nv)), np.empty((n_st, nv))
        dkx, dka = np.empty((n_st, nv, 3 * nv)), np.empty((n_st, nv, 3 * nv))
        kx[0], dkx[0] = v, dv0
        ka[0], dka[0] = self.accel(q, dq0, v, dv0, far_method)
        for s in range(1, n_st):
            A = h * dop.A[s, :s]
            x, dx = A @ kx[:s], np.tensordot(A, dkx[:s], axes=1)
            vs, dvs = v + A @ ka[:s], dv0 + np.tensordot(A, dka[:s], axes=1)
            qs = pin.integrate(model, q, x)
            ka[s], dka[s] = self.accel(qs, dq0 + dx, vs, dvs, far_method)
            kx[s], dkx[s] = vs, dvs
            if s in (INDICATOR_STAGE_A, INDICATOR_STAGE_B) and near(qs):
                raise _FarFromJ
        B = h * dop.B
        q_new = pin.integrate(model, q, B @ kx)
        dq_new = dq0 + np.tensordot(B, dkx, axes=1)
        v_new, dv_new = v + B @ ka, dv0 + np.tensordot(B, dka, axes=1)
        saved, self.mass_orthogonal = self.mass_orthogonal, False
        try:
            out = self.project(q_new, dq_new, v_new, dv_new)
        finally:
            self.mass_orthogonal = saved
        if near(out[0]):
            raise _FarFromJ
        return out


@exclusive
def step_derivatives(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray | None,
    h: float,
    *,
    integrator: str = "default",
    method: str = DEFAULT_METHOD,
    settings: SolverSettings = DEFAULT_SETTINGS,
    simulation_settings: SimulationSettings = DEFAULT_SIMULATION_SETTINGS,
) -> StepDerivatives:
    r"""Take one integration step of length h and return its derivatives in (q, v, tau).

    The step follows the library's arithmetic (:mod:`closedchain.simulate`), with a
    constant tau over the step:

    * ``"rk4"`` (with its default stabilization, ``stage-projection``): one
      :func:`~closedchain.simulate.fixed.rk4_projected` step: rk4 in the chart about q,
      each of stages 2 to 4 and the end projected onto phi = 0, J v = 0, the velocity
      mass-orthogonally where the method is singular-robust (the default), else with the
      minimum-norm correction; the accelerations by ``method``;
    * ``"default"`` (``"dop853-rk43"``): where the rank indicator of J is at its cap at
      the start, at DOP853's stages 5 and 8 and at the end, the DOP853 step of
      :class:`~closedchain.simulate.dop853_rk43.Dop853Far` (stages unprojected, kkt's
      accelerations for the augmented Lagrangian, the end projected with the minimum-norm
      correction); elsewhere the rk4 step above, as rk43 takes it (a run's rk43 may
      retake it as substeps near a crossing: not here). The step-size control and the
      error estimate are not part of the step.

    Each stage is differentiated in forward mode: the accelerations with
    :func:`forward_dynamics_derivatives` (the exact KKT derivative, at the stage's
    solution), the position projection through each of its Gauss-Newton iterations
    :math:`q \leftarrow q \oplus (-J^+ \phi)` with

    .. math::

        d(J^+ r) = d(J^\top)\, y + J^\top (J J^\top)^{-1}
        \bigl(dr - d(J)\, J^+ r - J\, d(J^\top)\, y\bigr), \qquad y = (J J^\top)^{-1} r,

    (d(J) w and d(J^T) y at fixed w, y from :func:`constraint_derivatives`' rows), the
    minimum-norm velocity projection likewise, and the mass-orthogonal one as the KKT
    system :math:`M (v^+ - v) + J^\top \mu = 0`, :math:`J v^+ = 0` (the limit of the
    augmented-Lagrangian iteration that computes it).

    Args:
        mech: the mechanism; its tree joints must be revolute, prismatic or continuous
            (a free-flyer, spherical or planar joint's chart rate D(x)^-1 v is not
            differentiated).
        q: configuration at the step's start, shape (nq,).
        v: velocity at the step's start, shape (nv,) [rad/s or m/s].
        tau: generalized forces over the step, shape (nv,) [N m or N]; zeros when None.
        h: the step [s], > 0.
        integrator: ``"rk4"``, ``"dop853-rk43"`` or ``"default"`` (the same).
        method: the forward-dynamics method of the run (:data:`closedchain.METHODS`).
        settings: its settings (``SolverSettings``).
        simulation_settings: ``projection_tol``, ``projection_iters``,
            ``project_velocities`` (:class:`closedchain.SimulationSettings`).

    Returns:
        q+, v+ and their derivatives (:class:`StepDerivatives`).

    Raises:
        UnknownChoiceError: an integrator other than :data:`STEP_INTEGRATORS`.
        ClosedChainError: h not a positive number; a joint with a curved configuration
            space.
        SingularConfigurationError: a stage's KKT matrix is singular
            (:func:`forward_dynamics_derivatives`).
    """
    if integrator not in STEP_INTEGRATORS:
        raise UnknownChoiceError("integrator", integrator, STEP_INTEGRATORS)
    check_settings("settings", settings, SolverSettings)
    check_settings("simulation_settings", simulation_settings, SimulationSettings)
    if not (isinstance(h, (int, float)) and math.isfinite(h) and h > 0.0):
        raise ClosedChainError(f"h must be a positive number of seconds, got {h!r}")
    curved = curved_blocks(mech.model)
    if curved:
        names = [mech.coordinate_names[b.start] for b in curved]
        raise ClosedChainError(
            f"{mech.name}: step_derivatives differentiates steps on revolute, prismatic and "
            f"continuous joints only; {', '.join(names)} belong to free-flyer, spherical or "
            "planar joints"
        )
    q = mech.check_q(q, "q")
    v = mech.check_v(v, "v")
    tau = np.zeros(mech.nv) if tau is None else mech.check_v(tau, "tau")
    get_method(method)  # an unknown method is refused before any work
    mass_orthogonal = METHOD_CAPABILITIES[method].singular_robust
    stepper = _Stepper(mech, tau, method, settings, simulation_settings, mass_orthogonal)
    scheme = "rk4-projected"
    out = None
    if integrator != "rk4":
        try:
            out = stepper.dop853(q, v, float(h), FAR_METHODS.get(method, method))
            scheme = "dop853"
        except _FarFromJ:
            out = None
    if out is None:
        out = stepper.rk4_projected(q, v, float(h))
    q_new, dq, v_new, dv = out
    nv = mech.nv
    return StepDerivatives(
        q=q_new,
        v=v_new,
        scheme=scheme,
        h=float(h),
        dq_dq=dq[:, :nv].copy(),
        dq_dv=dq[:, nv : 2 * nv].copy(),
        dq_dtau=dq[:, 2 * nv :].copy(),
        dv_dq=dv[:, :nv].copy(),
        dv_dv=dv[:, nv : 2 * nv].copy(),
        dv_dtau=dv[:, 2 * nv :].copy(),
    )
