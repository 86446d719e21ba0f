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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from ._locking import exclusive
from .constraints import ConstraintLayer
from .dynamics import DEFAULT_METHOD, forward_dynamics
from .dynamics.base import DEFAULT_SETTINGS, KKT_HINT, SolverSettings, singular_error
from .dynamics.kkt import estimate_scaled_inverse_norm, kkt_scaling
from .exceptions import check_settings
from .mechanism import Mechanism
from .pindata import frame_jacobian

__all__ = [
    "ConstraintDerivatives",
    "ForwardDynamicsDerivatives",
    "constraint_derivatives",
    "forward_dynamics_derivatives",
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
    return np.cross(x[0], y[0]), pin.skew(x[0]) @ y[1] - pin.skew(y[0]) @ x[1]


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
