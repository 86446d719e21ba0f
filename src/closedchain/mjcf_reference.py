r"""MuJoCo's own dynamics of an MJCF model, in closedchain's coordinates.

The reference that the tests and ``scripts/check_mjcf_models.py`` compare
closedchain's reading of an MJCF model with: MuJoCo compiles the same file,
and its arrays are mapped to the Pinocchio model :func:`closedchain.load`
built from it (same joints, by name).

Coordinates: hinges, slides and balls share v and a with Pinocchio (a ball's
angular velocity in the body frame; its quaternion is w, x, y, z in MuJoCo and
x, y, z, w in Pinocchio). A free joint's linear velocity is in the world frame
in MuJoCo and in the body frame in Pinocchio: with R the body's rotation,

.. math::

    \dot p = R v, \qquad \ddot p = R (a + \omega \times v), \qquad
    f_{MuJoCo} = R f.

Two accelerations of MuJoCo at a closed state (q, v) with joint forces tau:

- ``soft``: ``mj_forward`` with every active equality as stiff as MuJoCo allows,
  contacts, limits, friction loss and actuation disabled: MuJoCo's own answer,
  within its softness. MuJoCo's constraint force is
  :math:`f = (A + R)^{-1} (a_{ref} - a_u)` with the regulariser
  :math:`R_{ii} = (1 - d)/d \, \hat A_{ii}`, where the impedance d cannot exceed
  ``mjMAXIMP`` = 0.9999 and :math:`\hat A` is an approximate diagonal of
  :math:`A = J M^{-1} J^T` built from the inverse weights MuJoCo's compiler
  computes at qpos0 (``body_invweight0``, ``dof_invweight0``). ``solimp`` at that
  cap therefore leaves :math:`R \geq 10^{-4} \hat A`, and more where
  :math:`\hat A` overestimates A (it is frozen at qpos0 and treats bodies as
  independent; a weld's rotation rows are scaled by its ``torquescale``, which
  the approximation does not see). By default (``rigid_limit``) the inverse weights
  are scaled by :data:`RIGID_LIMIT_SCALE` as well, which takes R towards 0: the
  equality rows then follow MuJoCo's reference acceleration
  :math:`a_{ref} = -b J v - k r`, near 0 at a closed state with MuJoCo's default
  ``solref`` (:data:`STIFF_SOLREF`; a short time constant would turn the
  residuals of order 1e-12 of a closed state into accelerations), and the solver
  runs to convergence (tolerance 0). Without ``rigid_limit``:
  :data:`CAP_SOLREF`, :data:`STIFF_SOLIMP` and MuJoCo's own diagonal, what
  MuJoCo's stiffest equality gives in a simulation (``refsafe`` off so that
  the time constant is not raised to twice the model's time step).
- ``rigid``: the KKT system built from MuJoCo's own M (``mj_fullM``), bias
  forces ``qfrc_bias`` and equality rows of ``efc_J``, with
  :math:`\dot J v` by fourth-order central differences of ``efc_J`` along v
  (step :data:`JDOT_STEP`), solved through its Schur complement, the Delassus
  matrix by least squares (redundant rows allowed):

.. math::

    \begin{bmatrix} M & J^T \\ J & 0 \end{bmatrix}
    \begin{bmatrix} a \\ -\lambda \end{bmatrix} =
    \begin{bmatrix} \tau - b \\ -\dot J v \end{bmatrix}

Passive terms (armature, damping, stiffness, gravity compensation) are zeroed
in the spec by :func:`rigid_spec` where a comparison wants the rigid tree only.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from .mjcf import _mujoco, _pin_values, compile_mjcf

__all__ = [
    "CAP_SOLREF",
    "JDOT_STEP",
    "RIGID_LIMIT_SCALE",
    "STIFF_SOLIMP",
    "STIFF_SOLREF",
    "MujocoModel",
    "mujoco_accelerations",
    "mujoco_mass_matrix",
    "mujoco_model",
    "pin_configuration",
    "rigid_spec",
    "to_mujoco",
]

#: MuJoCo ``solref`` (time constant [s], damping ratio) of the compared equalities in the
#: rigid limit: MuJoCo's default (the reference acceleration's spring-damper; R sets the
#: stiffness).
STIFF_SOLREF = (0.02, 1.0)

#: MuJoCo ``solref`` of the stiffest equality MuJoCo simulates (without ``rigid_limit``).
CAP_SOLREF = (2e-4, 1.0)

#: MuJoCo ``solimp`` (dmin, dmax, width [m], midpoint, power) of a stiff equality: the
#: impedance at MuJoCo's cap ``mjMAXIMP``.
STIFF_SOLIMP = (0.9999, 0.9999, 0.001, 0.5, 2.0)

#: Factor on MuJoCo's inverse weights at qpos0 (``body_invweight0``, ``dof_invweight0``:
#: its approximate diagonal of J M^-1 J^T) in the rigid limit: R = 1e-4 times it.
#: Smaller factors leave MuJoCo's Newton step ill-conditioned (cond(M + J^T R^-1 J)).
RIGID_LIMIT_SCALE = 1e-8

#: Iterations of MuJoCo's solver in the rigid limit (tolerance 0: it stops when a step
#: no longer improves; Newton takes 1 to 3).
SOLVER_ITERATIONS = 1000

#: Equality rows of MuJoCo's efc_J shorter than this times the longest are zero rows.
ZERO_ROW_RTOL = 1e-9

#: Step [s] of the fourth-order central differences of MuJoCo's efc_J along v.
JDOT_STEP = 1e-4


def rigid_spec(spec) -> None:
    """Zero the passive terms of an ``MjSpec``: armature, damping, stiffness, friction
    loss, gravity compensation (MuJoCo folds armature into M at compile time)."""
    for joint in spec.joints:
        joint.armature = 0.0
        joint.damping = np.zeros_like(np.atleast_1d(joint.damping))
        joint.stiffness = np.zeros_like(np.atleast_1d(joint.stiffness))
        joint.frictionloss = 0.0
    for body in spec.bodies:
        body.gravcomp = 0.0


@dataclass
class MujocoModel:
    """A compiled MJCF model and its map to the Pinocchio model of the same file.

    Attributes:
        mj: the ``MjModel`` (equalities stiff or rigid, contacts, limits, friction loss and
            actuation disabled).
        data: its ``MjData``.
        joints: per MuJoCo joint: (kind, Pinocchio idx_q, idx_v, MuJoCo qposadr, dofadr).
    """

    mj: object
    data: object
    joints: list[tuple[str, int, int, int, int]]


def mujoco_model(
    path: str | Path, model: pin.Model, *, rigid: bool = True, rigid_limit: bool = True
) -> MujocoModel:
    """Compile ``path`` with MuJoCo and map its joints to ``model``'s (by name).

    Args:
        path: the MJCF file closedchain loaded ``model`` from.
        model: the Pinocchio model :func:`closedchain.load` built.
        rigid: zero the passive terms (:func:`rigid_spec`).
        rigid_limit: take MuJoCo's equalities to its rigid limit (the module
            docstring), else leave them at MuJoCo's stiffest simulated setting.
    """
    mujoco = _mujoco()
    _, mj, _ = compile_mjcf(Path(path), spec_edit=rigid_spec if rigid else None)
    mj.eq_solref[:] = STIFF_SOLREF if rigid_limit else CAP_SOLREF
    mj.eq_solimp[:] = STIFF_SOLIMP
    if rigid_limit:
        mj.body_invweight0[:] *= RIGID_LIMIT_SCALE
        mj.dof_invweight0[:] *= RIGID_LIMIT_SCALE
        # The exact diagonal (diagexact) would replace the scaled one.
        mj.opt.enableflags &= ~int(mujoco.mjtEnableBit.mjENBL_DIAGEXACT)
        mj.opt.solver = int(mujoco.mjtSolver.mjSOL_NEWTON)
        mj.opt.tolerance = 0.0
        mj.opt.iterations = SOLVER_ITERATIONS
    D = mujoco.mjtDisableBit
    # REFSAFE would raise solref[0] to twice the model's time step (4e-3 s for 2e-3 s).
    off = (D.mjDSBL_CONTACT, D.mjDSBL_LIMIT, D.mjDSBL_FRICTIONLOSS, D.mjDSBL_ACTUATION)
    for flag in (*off, D.mjDSBL_REFSAFE):
        mj.opt.disableflags |= int(flag)
    kinds = {0: "free", 1: "spherical", 2: "prismatic", 3: "revolute"}
    joints = []
    for j in range(mj.njnt):
        name = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j)
        if not name:
            body = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_BODY, mj.jnt_bodyid[j])
            name = f"{body or f'body{mj.jnt_bodyid[j]}'}_joint{j}"
        pj = model.joints[model.getJointId(name)]
        joints.append(
            (kinds[int(mj.jnt_type[j])], pj.idx_q, pj.idx_v, mj.jnt_qposadr[j], mj.jnt_dofadr[j])
        )
    return MujocoModel(mj, mujoco.MjData(mj), joints)


def to_mujoco(ref: MujocoModel, q, v=None, a=None, tau=None):
    """Return MuJoCo's (qpos, qvel, qacc, qfrc) of Pinocchio's (q, v, a, tau) (module docstring).

    Missing v, a, tau give zeros.
    """
    mj = ref.mj
    qpos, qvel = np.array(mj.qpos0, dtype=float), np.zeros(mj.nv)
    qacc, qfrc = np.zeros(mj.nv), np.zeros(mj.nv)
    v = np.zeros(mj.nv) if v is None else v
    a = np.zeros(mj.nv) if a is None else a
    tau = np.zeros(mj.nv) if tau is None else tau
    for kind, iq, iv, aq, av in ref.joints:
        if kind == "free":
            qpos[aq : aq + 7] = [*q[iq : iq + 3], q[iq + 6], *q[iq + 3 : iq + 6]]
            R = pin.Quaternion(q[iq + 3 : iq + 7]).normalized().matrix()
            lin, ang = v[iv : iv + 3], v[iv + 3 : iv + 6]
            qvel[av : av + 6] = [*(R @ lin), *ang]
            qacc[av : av + 6] = [*(R @ (a[iv : iv + 3] + np.cross(ang, lin))), *a[iv + 3 : iv + 6]]
            qfrc[av : av + 6] = [*(R @ tau[iv : iv + 3]), *tau[iv + 3 : iv + 6]]
        elif kind == "spherical":
            qpos[aq : aq + 4] = [q[iq + 3], *q[iq : iq + 3]]
            for out, x in ((qvel, v), (qacc, a), (qfrc, tau)):
                out[av : av + 3] = x[iv : iv + 3]
        else:
            qpos[aq] = q[iq]
            for out, x in ((qvel, v), (qacc, a), (qfrc, tau)):
                out[av] = x[iv]
    return qpos, qvel, qacc, qfrc


def pin_configuration(ref: MujocoModel, model: pin.Model, qpos) -> np.ndarray:
    """Return Pinocchio's q of a MuJoCo qpos (e.g. ``qpos0`` or a keyframe)."""
    q = pin.neutral(model)
    for kind, iq, _, aq, _ in ref.joints:
        n = {"free": 7, "spherical": 4}.get(kind, 1)
        q[iq : iq + n] = _pin_values(kind, qpos[aq : aq + n])
    return q


def mujoco_mass_matrix(ref: MujocoModel, q) -> np.ndarray:
    """Return MuJoCo's mass matrix at Pinocchio's q in Pinocchio's velocity coordinates.

    With v_MuJoCo = T v (a free joint's linear velocity is in the world frame in
    MuJoCo), the kinetic energy gives :math:`M = T^T M_{MuJoCo} T`, shape (nv, nv).
    """
    mujoco = _mujoco()
    nv = ref.mj.nv
    T = np.column_stack([to_mujoco(ref, q, e)[1] for e in np.eye(nv)])
    ref.data.qpos[:] = to_mujoco(ref, q)[0]
    mujoco.mj_forward(ref.mj, ref.data)
    M = np.zeros((nv, nv))
    mujoco.mj_fullM(ref.mj, ref.data, M)
    return T.T @ M @ T


def _equality_jacobian(ref: MujocoModel, qpos, qvel) -> np.ndarray:
    mujoco = _mujoco()
    d = ref.data
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(ref.mj, d)
    rows = np.flatnonzero(d.efc_type[: d.nefc] == int(mujoco.mjtConstraint.mjCNSTR_EQUALITY))
    J = np.zeros((d.nefc, ref.mj.nv))
    if mujoco.mj_isSparse(ref.mj):
        mujoco.mju_sparse2dense(J, d.efc_J, d.efc_J_rownnz, d.efc_J_rowadr, d.efc_J_colind)
    else:
        J = np.array(d.efc_J[: d.nefc * ref.mj.nv]).reshape(d.nefc, ref.mj.nv)
    return J[rows]


def mujoco_accelerations(ref: MujocoModel, q, v, tau) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return MuJoCo's (soft qacc, rigid KKT qacc, qvel) at Pinocchio's state (q, v, tau).

    Both accelerations are MuJoCo's (its coordinates: compare with
    :func:`to_mujoco` of closedchain's a); see the module docstring.
    """
    mujoco = _mujoco()
    mj, d = ref.mj, ref.data
    qpos, qvel, _, qfrc = to_mujoco(ref, q, v, tau=tau)
    # J-dot v: fourth-order central differences of the equality rows along the motion
    # (rows scaled by a small torquescale keep the round-off of their unscaled size).
    shifted = {}
    for k in (2, 1, -1, -2):
        qs = qpos.copy()
        mujoco.mj_integratePos(mj, qs, qvel, k * JDOT_STEP)
        shifted[k] = _equality_jacobian(ref, qs, qvel)
    dJ = (-shifted[2] + 8.0 * shifted[1] - 8.0 * shifted[-1] + shifted[-2]) / (12.0 * JDOT_STEP)
    Jdot_v = dJ @ qvel
    J = _equality_jacobian(ref, qpos, qvel)
    d.qfrc_applied[:] = qfrc
    mujoco.mj_forward(mj, d)
    soft = np.array(d.qacc)
    M = np.zeros((mj.nv, mj.nv))
    mujoco.mj_fullM(mj, d, M)
    bias = np.array(d.qfrc_bias)
    d.qfrc_applied[:] = 0.0
    norms = np.linalg.norm(J, axis=1)
    # Rows that vanish (torquescale 0; the out-of-plane row of a planar loop, zero up to
    # round-off) constrain nothing.
    keep = norms > ZERO_ROW_RTOL * np.max(norms, initial=0.0)
    # Unit rows: the same constraint, a KKT matrix as well conditioned as the tree's M
    # (a torquescale of 0.002 scales rotation rows by it).
    J, Jdot_v = J[keep] / norms[keep, None], Jdot_v[keep] / norms[keep]
    # The KKT system by its Schur complement: M is positive definite, the Delassus matrix
    # J M^-1 J^T singular where rows are redundant (least squares keeps the consistent ones),
    # and both stay well scaled whatever the bodies' masses (grippers: 1e-6 kg m^2).
    f = qfrc + np.array(d.qfrc_passive) - bias
    Minv_f, Minv_JT = np.linalg.solve(M, f), np.linalg.solve(M, J.T)
    lam = np.linalg.lstsq(J @ Minv_JT, J @ Minv_f + Jdot_v, rcond=None)[0]
    rigid = Minv_f - Minv_JT @ lam
    return soft, rigid, qvel
