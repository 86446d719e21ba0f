r"""Reduced coordinates by coordinate partitioning (seed text, Sections 4 and 6).

The velocity coordinates are split into ``mobility`` independent ones, I, and
``nc`` dependent ones, D, such that the square block :math:`J_D` of the
constraint Jacobian is nonsingular. The acceleration constraint
:math:`J_I a_I + J_D a_D + \gamma = 0` then gives every acceleration from the
independent ones,

.. math::

    a = S\, a_I + c, \qquad
    S = \begin{bmatrix} I \\ -J_D^{-1} J_I \end{bmatrix}, \qquad
    c = \begin{bmatrix} 0 \\ -J_D^{-1} \gamma \end{bmatrix},

with the rows of ``S`` and ``c`` laid out in the tree's coordinate order (the
block rows above are the I and D rows). Premultiplying the equations of motion
by :math:`S^\top` removes the multipliers (:math:`J S = 0`) and leaves the
lesson's reduced equations

.. math::

    M_r\, a_I = S^\top \tau - h_r, \qquad M_r = S^\top M S, \qquad
    h_r = S^\top (h + M c),

which is the lesson's :math:`h_r = S^\top (h - M \dot S \dot q_r)` with
:math:`\dot S \dot q_r = -c`. The multipliers are recovered afterwards from the
dependent rows of the equations of motion,
:math:`J_D^\top \lambda = \tau_D - (M a + h)_D`.

:math:`J_D` is LU-factored (``dgetrf``) with a 1-norm condition estimate
(``dgecon``); :math:`J_D` singular is a singularity of the partition (the lesson's
Problem 4), not necessarily of the mechanism: :func:`choose_partition` picks
the best-conditioned dependent set at a configuration by pivoted QR.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import lapack

from ..exceptions import ClosedChainError
from .base import (
    DEFAULT_SETTINGS,
    MASS_HINT,
    MethodCapabilities,
    SolverSettings,
    check_condition,
    compute_terms,
    register,
    singular_error,
    workspace,
)

if TYPE_CHECKING:
    from ..mechanism import Mechanism

_NAME = "reduced"


class _Partition:
    """Index maps and buffers of one partition (made once per partition).

    Attributes:
        ind: independent velocity indices, shape (m,).
        dep: dependent velocity indices, shape (nc,).
        cols: ``[dep, ind]`` then the column ``nv`` of ``[J | gamma]``, shape (nv + 1,).
        S: the map a_I -> a (its I rows hold the constant identity), shape (nv, m).
        c: the acceleration offset (zero on I rows), shape (nv,).
        what: description of J_D for error messages.
    """

    def __init__(self, mech: Mechanism, ind: np.ndarray, dep: np.ndarray) -> None:
        nv, nc = mech.nv, mech.nc
        m = nv - nc
        self.ind = ind
        self.dep = dep
        self.cols = np.concatenate([dep, ind, [nv]]).astype(int)
        self.Jg = np.zeros((nc, nv + 1))  # [J | gamma]
        self.S = np.zeros((nv, m))
        self.S[ind, np.arange(m)] = 1.0
        self.c = np.zeros(nv)
        self.X = np.zeros((nc, m + 1))
        self.MS = np.zeros((nv, m))
        self.Mr = np.zeros((m, m))
        self.f = np.zeros(nv)
        names = ", ".join(mech.coordinate_names[i] for i in dep)
        self.what = f"J_D (constraint-Jacobian columns of the dependent coordinates {names})"
        #: 1-norm condition estimate of J_D at the last call [-].
        self.cond_JD = float("nan")


def _partition(mech: Mechanism, independent_idx_v) -> _Partition:
    ws = workspace(mech)
    cache = ws.method_buffers.setdefault(_NAME, {})
    if independent_idx_v is None:
        key = None
    else:
        key = tuple(int(i) for i in np.asarray(independent_idx_v).ravel())
    part = cache.get(key)
    if part is None:
        if key is None:
            ind, dep = np.asarray(mech.independent_idx_v), np.asarray(mech.dependent_idx_v)
        else:
            ind = np.array(key, dtype=int)
            if (
                len(ind) != mech.mobility
                or len(set(key)) != len(key)
                or not all(0 <= i < mech.nv for i in key)
            ):
                raise ClosedChainError(
                    f"{mech.name}: independent_idx_v = {list(key)} must be {mech.mobility} "
                    f"distinct velocity indices in 0..{mech.nv - 1} (the mobility)"
                )
            dep = np.setdiff1d(np.arange(mech.nv), ind)
        part = cache[key] = _Partition(mech, ind.astype(int), dep.astype(int))
    return part


def choose_partition(mech: Mechanism, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r"""Pick dependent coordinates whose block J_D of J is well conditioned at q.

    Column-pivoted QR of J (Businger-Golub) picks, greedily, the ``nc``
    columns that are farthest from linearly dependent: they become the
    dependent coordinates, the rest are independent. Rank-revealing QR keeps
    :math:`\sigma_{\min}(J_D)` within a modest factor of :math:`\sigma_{\min}(J)`
    in practice; it is not an exhaustive search for the best of all
    :math:`\binom{nv}{nc}` partitions. Meant for re-partitioning (e.g. when
    :func:`reduced_dynamics` raises or :func:`partition_condition` grows), not
    for every evaluation.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).

    Returns:
        ``(independent_idx_v, dependent_idx_v)``, sorted, shapes (mobility,) and (nc,).
    """
    from ..kinematics import compute_jacobian, partition_coordinates

    return partition_coordinates(compute_jacobian(mech, q, backend="numpy"))


def partition_condition(mech: Mechanism, independent_idx_v=None) -> float:
    """Return the 1-norm condition estimate of J_D at the last reduced solve.

    Args:
        mech: the mechanism.
        independent_idx_v: the partition (None: the mechanism's own).

    Returns:
        cond_1(J_D) estimated by LAPACK ``dgecon``; NaN before the first solve.
    """
    return _partition(mech, independent_idx_v).cond_JD


def reduced_dynamics(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    *,
    settings: SolverSettings = DEFAULT_SETTINGS,
    independent_idx_v: np.ndarray | None = None,
    cond_JD_max: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics in reduced coordinates for a given partition.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``cond_max`` bounds cond(J_D) and cond(M_r).
        independent_idx_v: the independent velocity indices, shape (mobility,);
            None: ``mech.independent_idx_v``. A simulator re-partitions with
            :func:`choose_partition` when J_D becomes ill-conditioned.
        cond_JD_max: a separate, usually tighter, bound on cond(J_D) (a
            simulator's re-partition trigger); None: ``settings.cond_max``.

    Returns:
        ``(a, lam)``: accelerations, shape (nv,) [rad/s^2 or m/s^2], and
        multipliers of the independent rows, shape (nc,), with
        ``M a + h + J^T lam = tau``.

    Raises:
        SingularConfigurationError: J_D (names the dependent coordinates and
            cond(J_D)) or M_r is singular or ill-conditioned at q.
        ClosedChainError: ``independent_idx_v`` is not ``mobility`` distinct indices.
    """
    part = _partition(mech, independent_idx_v)
    ws = compute_terms(mech, q, v, settings.baumgarte)
    nv, nc = mech.nv, mech.nc
    m = nv - nc
    M, S, c, f = ws.M, part.S, part.c, part.f
    np.subtract(tau, ws.h, out=f)
    if nc:
        Jg = part.Jg
        Jg[:, :nv] = ws.J
        Jg[:, nv] = ws.gamma
        B = Jg[:, part.cols]  # [J_D | J_I | gamma]
        lu, piv, info = lapack.dgetrf(B[:, :nc])
        if info == 0:
            rcond = lapack.dgecon(lu, lapack.dlange("1", B[:, :nc]))[0]
        else:
            rcond = 0.0
        part.cond_JD = cond = 1.0 / rcond if rcond > 0.0 else float("inf")
        bound = settings.cond_max if cond_JD_max is None else cond_JD_max
        if cond > bound:
            raise singular_error(
                mech,
                q,
                part.what,
                cond,
                bound,
                "this partition cannot describe the motion here (its block J_D is singular): "
                "re-partition with choose_partition(mech, q), or the configuration is a "
                "singularity of the mechanism",
                bound_name="cond_max" if cond_JD_max is None else "cond_JD_max",
            )
        # The explicit inverse (dgetri) and one product instead of dgetrs with
        # several right-hand sides: OpenBLAS threads dgetrs over the right-hand
        # sides, which costs milliseconds per call on a loaded machine.
        JD_inv = lapack.dgetri(lu, piv)[0]
        X = np.dot(JD_inv, B[:, nc:], out=part.X)  # J_D^-1 [J_I | gamma]
        S[part.dep] = -X[:, :m]
        c[part.dep] = -X[:, m]
        f -= M @ c  # tau - h - M c
    if m:
        MS = np.dot(M, S, out=part.MS)
        Mr = np.dot(S.T, MS, out=part.Mr)
        R, info = lapack.dpotrf(Mr, lower=0, clean=0)
        rcond = lapack.dpocon(R, lapack.dlange("1", Mr))[0] if info == 0 else 0.0
        check_condition(
            mech, q, "the reduced mass matrix S^T M S", rcond, info, settings, MASS_HINT
        )
        a_I = lapack.dpotrs(R, f @ S)[0]
        a = S @ a_I
        a += c
        if not nc:
            return a, np.zeros(0)
        f -= MS @ a_I  # tau - h - M a
    else:
        a = c.copy()
    return a, f[part.dep] @ JD_inv  # lam = J_D^-T (tau - h - M a)_D


@register(_NAME, MethodCapabilities(compiled=True))
def reduced(
    mech: Mechanism, q: np.ndarray, v: np.ndarray, tau: np.ndarray, settings: SolverSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Solve the constrained dynamics in the mechanism's reduced coordinates.

    The registered form of :func:`reduced_dynamics` with the partition chosen
    at load (``mech.independent_idx_v``).

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,), on the constraint manifold.
        v: velocity, shape (nv,), with J v = 0.
        tau: generalized forces, shape (nv,) [N m or N].
        settings: ``cond_max`` bounds cond(J_D) and cond(M_r).

    Returns:
        ``(a, lam)`` as :func:`reduced_dynamics`.
    """
    return reduced_dynamics(mech, q, v, tau, settings=settings)
