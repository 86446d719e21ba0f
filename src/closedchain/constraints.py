r"""Loop-closure constraints: phi(q), J(q) and gamma(q, v) = Jdot(q, v) v.

A loop joint cuts the mechanism between a frame c1 on the predecessor link and
a frame c2 on the successor link (the ``*_origin`` placements of the
``<loop>`` element). With world placements ``oMc1 = (R_p, p_p)`` and
``oMc2 = (R_s, p_s)``, every row is written in frames that move with the
loop, so that a row that is structurally redundant for a planar or spherical
mechanism is the same row in every pose and on every base (turntable, free
flyer). The declared rows of each loop type are

========= ============================================== =========
type      rows                                           count
========= ============================================== =========
revolute  translation in c1 (t1, t2, ta), tilt (r1, r2)  3 + 2
spherical translation in c1 (t1, t2, ta)                 3
fixed     translation (t1, t2, ta), tilt, twist (r3)     3 + 3
prismatic translation across the axis (t1, t2), tilt,    2 + 3
          twist
coupling  q_j - m q_i - c (q)                            1
========= ============================================== =========

where a is the loop axis and (n1, n2, a) a right-handed orthonormal basis of
c1 (:func:`axis_basis`; for a spherical loop, the basis of its ``axis``,
default x); the translation rows are the components of d = p_p - p_s along
n1, n2 and a carried by R_p, the rotation rows the components of the carried
axis R_s a across R_p a (tilt, r1 = (R_p n1).(R_s a), r2 = (R_p n2).(R_s a))
and the twist r3 = (R_p n1).(R_s n2). Every row is one of **two** smooth
scalar functions, with constant unit vectors n, u in c1 and w in c2:

.. math::

    \phi_{t} = (R_p n)^\top (p_p - p_s), \qquad
    \phi_{r} = (R_p u)^\top (R_s w).

:meth:`ConstraintLayer.row_table` lists them per row (function, frames,
vectors): the table a compiled evaluator reads. With frame velocities
``(v, omega)`` and bias accelerations ``(a_b, alpha_b)`` (classical,
world-aligned, at zero joint acceleration), writing ``U = R_p n`` or ``R_p u``
and ``W = R_s w``:

.. math::

    \dot\phi_t = (R_p n)^\top (v_p - v_s) + (U \times d)^\top \omega_p, \qquad
    \gamma_t = \ddot U^\top d + 2 \dot U^\top \dot d + U^\top (a_{b,p} - a_{b,s}),

    \dot\phi_r = (\omega_s - \omega_p)^\top (W \times U), \qquad
    \gamma_r = \ddot U^\top W + 2 \dot U^\top \dot W + U^\top \ddot W,

with :math:`\dot U = \omega_p \times U`, :math:`\ddot U = \alpha_{b,p} \times
U + \omega_p \times (\omega_p \times U)` (and the same for W with the
successor's), expanded in :meth:`ConstraintLayer.evaluate` into dot products.

A coupling loop (``q_j = m q_i + c``, :data:`closedchain.urdf.COUPLING`) has
no frame rows: its one row reads the two joints' coordinates from ``data``
(``data.joints[j].joint_q``, which every kinematics routine fills), its J is
constant (+1 at j, -m at i) and its gamma is zero.

So J is exactly the derivative of phi along ``pin.integrate`` and
gamma = Jdot v exactly: finite differences check both (tests/test_constraints.py).
For the planar 4-bar the two kept rows are the seed's closure
``p_C(coupler) - p_C(rocker)`` (Section 2) expressed in the coupler's cut frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ._arrays import same_array
from .exceptions import ValidationUnavailableError
from .urdf import COUPLING, LoopSpec

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_LOCAL = pin.ReferenceFrame.LOCAL

#: Distance [m] between the two points on the axis that stand for a revolute
#: loop in Pinocchio's CONTACT_3D constraint models (any nonzero value works:
#: it only rescales the multipliers, not J^T lam).
PIN_REVOLUTE_POINT_OFFSET = 0.1

#: With more loops than this holding translation rows, :meth:`ConstraintLayer.evaluate`
#: evaluates every row of every loop at once (numpy over the rows, cost growing with the
#: arithmetic, not with Python calls per loop); with fewer, per loop (numpy's per-call
#: overhead exceeds the arithmetic of a few loops).
BATCH_LOOPS = 4

#: Row function codes of :class:`RowTable`: translation (R_p n).(p_p - p_s).
ROW_TRANSLATION = 0
#: Rotation (R_p u).(R_s w).
ROW_ROTATION = 1
#: Joint coupling q_j - m q_i - c (no frames; not in the compiled core).
ROW_COUPLING = 2
#: Kind of a coupling row in :class:`RowInfo`.
COUPLING_KIND = "q"


_I1 = np.array([1, 2, 0])
_I2 = np.array([2, 0, 1])


def _rotation_gamma(V, A, tr, U, W, UW) -> np.ndarray:
    """gamma of rotation rows u.w = 0 (u = R_p u0, w = R_s w0 in the world): with the
    frames' velocities V and classical bias accelerations A, shape (frames, 6), and the
    rows' table ``tr`` (pred, succ),
    gamma = (alpha_s - alpha_p).(w x u) + (wp.u)(wp.w) + (ws.u)(ws.w)
            - 2 (wp.w)(ws.u) - |wp - ws|^2 (u.w), the triple products expanded."""
    wp, ws = V[tr.pred, 3:], V[tr.succ, 3:]
    pu = np.einsum("ri,ri->r", wp, U)
    pw = np.einsum("ri,ri->r", wp, W)
    su = np.einsum("ri,ri->r", ws, U)
    sw = np.einsum("ri,ri->r", ws, W)
    dw = wp - ws
    return (
        np.einsum("ri,ri->r", _cross(W, U), A[tr.succ, 3:] - A[tr.pred, 3:])
        + pu * pw
        + su * sw
        - 2.0 * pw * su
        - np.einsum("ri,ri->r", dw, dw) * UW
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (k, 3) arrays (or a (3,) vector against (k, 3)).

    numpy.cross spends ~30 us on axis handling; this is the same formula
    without it (``take``: half the time of fancy indexing), for the small arrays of the
    per-evaluation path.
    """
    return a.take(_I1, -1) * b.take(_I2, -1) - a.take(_I2, -1) * b.take(_I1, -1)


def axis_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return unit vectors (n1, n2) with (n1, n2, axis) right-handed orthonormal.

    Args:
        axis: unit vector, shape (3,).
    """
    e = np.eye(3)[int(np.argmin(np.abs(axis)))]
    n1 = np.cross(axis, e)
    n1 /= np.linalg.norm(n1)
    n2 = np.cross(axis, n1)
    return n1, n2


def _cross3(a: list, b: list) -> list:
    """Cross product of two 3-vectors given as lists of floats (plain Python arithmetic:
    numpy's per-call overhead exceeds the six products)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def support_mask(model: pin.Model, joint: int) -> np.ndarray:
    """Return the velocity columns of the joints supporting ``joint`` (itself included,
    the universe excluded) as a bool mask, shape (nv,): where the joint's frames'
    Jacobians can be nonzero."""
    mask = np.zeros(model.nv, dtype=bool)
    for s in model.supports[joint]:
        if s:
            jm = model.joints[s]
            mask[jm.idx_v : jm.idx_v + jm.nv] = True
    return mask


def _translation_rows(model, data, sl, fp, fs, N, phi, J, gamma) -> None:
    r"""Fill the translation rows ``(R_p n_i).(p_p - p_s)`` of one loop.

    With d = p_p - p_s, (N R_p^T) the rows (R_p n_i)^T, and frame quantities
    world-aligned (LOCAL_WORLD_ALIGNED):

    .. math::

        \phi = N R_p^\top d, \qquad
        J = N R_p^\top \bigl(J_{v,p} - J_{v,s} + [d]_\times J_{\omega,p}\bigr),

        \gamma = N R_p^\top \bigl(a_{b,p} - a_{b,s} + d \times \alpha_{b,p}
        + 2\, \dot d \times \omega_p + (d \times \omega_p) \times \omega_p\bigr),

    the last from :math:`\ddot U^\top d + 2 \dot U^\top \dot d + U^\top \ddot d`
    with :math:`\dot U = \omega_p \times U` (module docstring) and the triple
    product rule :math:`(\omega \times U)^\top x = U^\top (x \times \omega)`.
    """
    oMp = pin.updateFramePlacement(model, data, fp)
    d_arr = oMp.translation - pin.updateFramePlacement(model, data, fs).translation
    NR = N @ oMp.rotation.T  # rows (R_p n_i)^T, world
    if phi is not None:
        phi[sl] = NR @ d_arr
    if J is None and gamma is None:
        return
    d = d_arr.tolist()
    if J is not None:
        Jp = pin.getFrameJacobian(model, data, fp, _LWA)
        Js = pin.getFrameJacobian(model, data, fs, _LWA)
        S = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])  # d x .
        J[sl] = NR @ (Jp[:3] - Js[:3] + S @ Jp[3:])
    if gamma is not None:
        ap = pin.getFrameClassicalAcceleration(model, data, fp, _LWA).vector.tolist()
        as_ = pin.getFrameClassicalAcceleration(model, data, fs, _LWA).linear.tolist()
        vp = pin.getFrameVelocity(model, data, fp, _LWA).vector.tolist()
        vs = pin.getFrameVelocity(model, data, fs, _LWA).linear.tolist()
        w, alpha = vp[3:], ap[3:]
        dd = [vp[0] - vs[0], vp[1] - vs[1], vp[2] - vs[2]]
        c1, c2, c3 = _cross3(d, alpha), _cross3(dd, w), _cross3(_cross3(d, w), w)
        x = [ap[k] - as_[k] + c1[k] + 2.0 * c2[k] + c3[k] for k in range(3)]
        gamma[sl] = NR @ np.array(x)


def _coupling_row(model, data, blk: LoopRows, r: int, phi, J, gamma) -> None:
    r"""Fill row ``r`` of phi, J, gamma with the row ``q_j - m q_i - c`` of a coupling
    loop (joints i, j: the parent joints of its frames c1, c2), reading the
    coordinates ``data`` was filled at:

    .. math::

        \phi = q_j - m q_i - c, \qquad J = e_j^\top - m e_i^\top, \qquad \gamma = 0.
    """
    ji = model.frames[blk.fid_p].parentJoint
    jj = model.frames[blk.fid_s].parentJoint
    m = blk.spec.multiplier
    if phi is not None:
        phi[r] = data.joints[jj].joint_q[0] - m * data.joints[ji].joint_q[0] - blk.spec.offset
    if J is not None:
        J[r] = 0.0
        J[r, model.joints[jj].idx_v] = 1.0
        J[r, model.joints[ji].idx_v] -= m
    if gamma is not None:
        gamma[r] = 0.0


@dataclass(frozen=True)
class RowInfo:
    """One declared constraint row.

    Attributes:
        loop: name of its loop.
        kind: ``"t1" | "t2" | "ta"`` (translation along n1, n2, a of c1),
            ``"r1" | "r2"`` (tilt of the axis), ``"r3"`` (twist about it),
            ``"q"`` (a coupling q_j - m q_i - c).
        unit: ``"m"`` or ``"1"`` (dimensionless); a coupling row ``"q"`` (the unit of q_j).
    """

    loop: str
    kind: str
    unit: str

    @property
    def label(self) -> str:
        return f"{self.loop}.{self.kind}"

    @property
    def function(self) -> int:
        """:data:`ROW_TRANSLATION`, :data:`ROW_ROTATION` or :data:`ROW_COUPLING`."""
        if self.kind == COUPLING_KIND:
            return ROW_COUPLING
        return ROW_TRANSLATION if self.unit == "m" else ROW_ROTATION


def declared_row_vectors(spec: LoopSpec) -> list[tuple[str, int, np.ndarray, np.ndarray]]:
    """Return the declared rows of a loop, in order: (kind, function, u or n in c1, w in c2).

    Translation and coupling rows carry w = 0 (a coupling row also u = 0). See the
    module docstring for the table.
    """
    a = np.asarray(spec.axis, dtype=float)
    n1, n2 = axis_basis(a)
    zero = np.zeros(3)
    if spec.type == COUPLING:
        return [(COUPLING_KIND, ROW_COUPLING, zero, zero)]
    rows: list[tuple[str, int, np.ndarray, np.ndarray]] = []
    if spec.type in ("revolute", "spherical", "fixed"):
        rows += [("t1", ROW_TRANSLATION, n1, zero), ("t2", ROW_TRANSLATION, n2, zero)]
        rows += [("ta", ROW_TRANSLATION, a, zero)]
    if spec.type == "prismatic":
        rows += [("t1", ROW_TRANSLATION, n1, zero), ("t2", ROW_TRANSLATION, n2, zero)]
    if spec.type in ("revolute", "fixed", "prismatic"):
        rows += [("r1", ROW_ROTATION, n1, a), ("r2", ROW_ROTATION, n2, a)]
    if spec.type in ("fixed", "prismatic"):
        rows += [("r3", ROW_ROTATION, n1, n2)]
    return rows


class LoopRows:
    """The active rows of one loop and the constant vectors they are built from.

    Attributes:
        spec: the loop as written in the URDF.
        fid_p, fid_s: model frame ids of the cut-joint frames c1 and c2.
        declared_rows: every declared row's RowInfo, in declared order.
        keep: indices of the active rows among the declared ones, increasing.
        trans: unit vectors n in c1 of the active translation rows, shape (nt, 3).
        rot_u, rot_w: the vectors u (in c1) and w (in c2) of the active rotation
            rows (R_p u).(R_s w), shapes (nr, 3).
        rows: the active rows' RowInfo, in evaluation order (= declared order:
            translation, then rotation).
        start: first row of this loop in the layer's output.
    """

    def __init__(self, spec: LoopSpec, fid_p: int, fid_s: int, keep: list[int] | None) -> None:
        self.spec = spec
        self.fid_p = fid_p
        self.fid_s = fid_s
        declared = declared_row_vectors(spec)
        self.n_declared = len(declared)
        units = {ROW_TRANSLATION: "m", ROW_ROTATION: "1", ROW_COUPLING: COUPLING_KIND}
        self.declared_rows = tuple(RowInfo(spec.name, kind, units[f]) for kind, f, _, _ in declared)
        self.keep = tuple(range(len(declared))) if keep is None else tuple(sorted(keep))
        active = [declared[i] for i in self.keep]
        self.rows = tuple(self.declared_rows[i] for i in self.keep)
        self.trans = np.array([u for _, f, u, _ in active if f == ROW_TRANSLATION]).reshape(-1, 3)
        self.rot_u = np.array([u for _, f, u, _ in active if f == ROW_ROTATION]).reshape(-1, 3)
        self.rot_w = np.array([w for _, f, _, w in active if f == ROW_ROTATION]).reshape(-1, 3)
        self.n = len(self.keep)
        self.nt, self.nr = len(self.trans), len(self.rot_u)
        #: Whether the loop's active row is a coupling row (:data:`ROW_COUPLING`).
        self.coupling = spec.type == COUPLING and self.n == 1
        self.start = 0  # first row of this block in the layer, set by ConstraintLayer


@dataclass(frozen=True)
class RowTable:
    """The active rows of a layer as flat per-row arrays (the input of a compiled evaluator).

    Row i is ``(R_p u_i).(p_p - p_s)`` when ``function[i] == ROW_TRANSLATION``
    and ``(R_p u_i).(R_s w_i)`` when ``function[i] == ROW_ROTATION``, with
    ``(R_p, p_p)`` the world placement of model frame ``frame_p[i]`` and
    ``(R_s, p_s)`` that of ``frame_s[i]``.

    Attributes:
        function: row function code, shape (nc,), int.
        frame_p, frame_s: model frame ids of c1 and c2, shape (nc,), int.
        u: n or u in c1, shape (nc, 3), unit vectors.
        w: w in c2, shape (nc, 3) (zeros for translation rows).
        loop: index of the row's loop in the URDF order, shape (nc,), int.
        labels: ``loop.kind`` of every row.
    """

    function: np.ndarray
    frame_p: np.ndarray
    frame_s: np.ndarray
    u: np.ndarray
    w: np.ndarray
    loop: np.ndarray
    labels: tuple[str, ...]


class _Table:
    """Rows of one kind over all loops: output rows, loop index, frame indices, vectors."""

    def __init__(self, columns: dict[str, list]) -> None:
        self.rows = np.array(columns["rows"], dtype=int)
        self.loop = np.array(columns["loop"], dtype=int)
        self.pred = 2 * self.loop  # index of c1 in the stacked frames
        self.succ = 2 * self.loop + 1
        for key in ("n", "u", "w"):
            if key in columns:
                setattr(self, key, np.array(columns[key], dtype=float).reshape(-1, 3))


class _PlacementMemo:
    """The world placements H, shape (2L, 4, 4), of a batched layer's frames at q."""

    def __init__(self) -> None:
        self.q: np.ndarray | None = None
        self.H: np.ndarray | None = None


class ConstraintLayer:
    """phi, J and gamma of a set of loops, evaluated from filled Pinocchio data.

    Build it with the loop frames already added to the model; restrict it to
    independent rows with :meth:`restricted`. The ``evaluate`` method reads
    ``data`` and never calls a kinematics algorithm itself, so the caller runs
    each Pinocchio routine once per evaluation:

    * phi needs ``forwardKinematics(q)``,
    * J needs ``computeJointJacobians(q)`` (or ``computeAllTerms``),
    * gamma needs ``forwardKinematics(q, v, 0)``, and when :attr:`batched` also
      ``computeJointJacobiansTimeVariation(q, v)`` and ``v`` itself (``computeAllTerms``
      does both).
    """

    def __init__(
        self,
        loops: tuple[LoopSpec, ...],
        frame_ids: tuple[tuple[int, int], ...],
        keep: tuple[tuple[int, ...], ...] | None = None,
        _memos: dict | None = None,
    ) -> None:
        #: Frame-placement memos by frame list, shared with the layers :meth:`restricted`
        #: makes (the same model and loops).
        self._memos: dict[tuple[int, ...], _PlacementMemo] = {} if _memos is None else _memos
        self.loops = loops
        self.frame_ids = frame_ids
        self._blocks = [
            LoopRows(spec, fp, fs, None if keep is None else list(keep[i]))
            for i, (spec, (fp, fs)) in enumerate(zip(loops, frame_ids, strict=True))
        ]
        self.keep = tuple(b.keep for b in self._blocks)
        self.rows: tuple[RowInfo, ...] = tuple(r for b in self._blocks for r in b.rows)
        self.declared_rows: tuple[RowInfo, ...] = tuple(
            r for b in self._blocks for r in b.declared_rows
        )
        #: Indices of the active rows in :attr:`declared_rows`, increasing.
        offsets = np.cumsum([0] + [b.n_declared for b in self._blocks])
        self.selected: tuple[int, ...] = tuple(
            int(off) + i for off, b in zip(offsets, self._blocks, strict=False) for i in b.keep
        )
        self.nc = len(self.rows)
        self._slices = []
        start = 0
        for b in self._blocks:
            b.start = start
            self._slices.append(slice(start, start + b.n))
            start += b.n
        self._active = [b for b in self._blocks if b.n]
        self._build_tables()

    def per_loop(self) -> list[tuple[LoopRows, slice]]:
        """Return each loop's rows and their slice of phi, J, gamma and lam, in URDF order."""
        return list(zip(self._blocks, self._slices, strict=True))

    def restricted(self, rows: list[int] | tuple[int, ...]) -> ConstraintLayer:
        """Return a layer that evaluates only the given declared rows.

        Args:
            rows: indices into :attr:`declared_rows`.
        """
        per_loop: list[list[int]] = [[] for _ in self._blocks]
        offset = 0
        for i, b in enumerate(self._blocks):
            for r in rows:
                if offset <= r < offset + b.n_declared:
                    per_loop[i].append(r - offset)
            offset += b.n_declared
        return ConstraintLayer(
            self.loops, self.frame_ids, tuple(tuple(k) for k in per_loop), _memos=self._memos
        )

    def row_table(self) -> RowTable:
        """Return the active rows as flat per-row arrays (see :class:`RowTable`)."""
        function, fp, fs, us, ws, loop = [], [], [], [], [], []
        for i, b in enumerate(self._blocks):
            vectors = declared_row_vectors(b.spec)
            for k in b.keep:
                _, f, u, w = vectors[k]
                function.append(f)
                fp.append(b.fid_p)
                fs.append(b.fid_s)
                us.append(u)
                ws.append(w)
                loop.append(i)
        return RowTable(
            function=np.array(function, dtype=int),
            frame_p=np.array(fp, dtype=int),
            frame_s=np.array(fs, dtype=int),
            u=np.array(us, dtype=float).reshape(-1, 3),
            w=np.array(ws, dtype=float).reshape(-1, 3),
            loop=np.array(loop, dtype=int),
            labels=tuple(r.label for r in self.rows),
        )

    def evaluate(
        self,
        model: pin.Model,
        data: pin.Data,
        *,
        phi: np.ndarray | None = None,
        J: np.ndarray | None = None,
        gamma: np.ndarray | None = None,
        v: np.ndarray | None = None,
        q: np.ndarray | None = None,
    ) -> None:
        """Fill the requested outputs from ``data``.

        Args:
            model: the mechanism's Pinocchio model (with the loop frames).
            data: its data, filled by the kinematics routines listed in the class doc.
            phi: output, shape (nc,), [m] or [-] per row.
            J: output, shape (nc, nv), d phi / d v along ``pin.integrate``.
            gamma: output, shape (nc,), Jdot v.
            v: the velocity ``data`` was filled at, shape (nv,); required with gamma
                when the layer evaluates all loops at once (:attr:`batched`).
            q: the configuration ``data`` was filled at, if known: a batched layer then
                reuses the frame placements of its last evaluation at the same q (the
                simulator evaluates J and then gamma at each stage's q).
        """
        self._evaluate_frames(model, data, phi, J, gamma, v, q)
        for blk in self._couplings:
            _coupling_row(model, data, blk, blk.start, phi, J, gamma)

    @property
    def couplings(self) -> tuple[LoopSpec, ...]:
        """The loops whose active row is a coupling row (``q_j = m q_i + c``)."""
        return tuple(b.spec for b in self._couplings)

    def _evaluate_frames(self, model, data, phi, J, gamma, v, q) -> None:
        """Fill the rows of the loops with frames (all but the couplings), see evaluate."""
        # Hot path (every dynamics evaluation). Translation rows: per loop, a few
        # 3 x 3 / k x 3 products (see _translation_rows). Rotation rows: all loops at
        # once, a fixed number of batched numpy calls (numpy's per-call overhead,
        # not arithmetic, dominates arrays this small).
        if self._tt is not None:
            if gamma is not None and v is None:
                raise ValueError(
                    "gamma of a layer with many loops needs v (the velocity data was "
                    "filled at); pass v=..."
                )
            self._evaluate_batched(model, data, phi, J, gamma, v, q)
            return
        for sl, fp, fs, N in self._trans:
            _translation_rows(model, data, sl, fp, fs, N, phi, J, gamma)
        tr = self._tr
        if tr is None:
            return
        frames = [pin.updateFramePlacement(model, data, f) for f in self._fids]
        R = np.array([M.rotation for M in frames])  # (2L, 3, 3): c1, c2 of each loop
        U = (R[tr.pred] @ tr.u[:, :, None])[:, :, 0]  # R_p u, world
        W = (R[tr.succ] @ tr.w[:, :, None])[:, :, 0]  # R_s w, world
        UW = np.einsum("ri,ri->r", U, W)
        if phi is not None:
            phi[tr.rows] = UW
        if J is not None:
            Jf = np.array([pin.getFrameJacobian(model, data, f, _LWA) for f in self._fids])
            J[tr.rows] = np.einsum("ri,rin->rn", _cross(W, U), Jf[tr.succ, 3:] - Jf[tr.pred, 3:])
        if gamma is not None:
            A = np.array(
                [pin.getFrameClassicalAcceleration(model, data, f, _LWA).vector for f in self._fids]
            )  # (2L, 6): classical linear, angular; bias (zero joint acceleration)
            V = np.array([pin.getFrameVelocity(model, data, f, _LWA).vector for f in self._fids])
            gamma[tr.rows] = _rotation_gamma(V, A, tr, U, W, UW)

    @property
    def batched(self) -> bool:
        """Whether every row of every loop is evaluated at once (more than
        :data:`BATCH_LOOPS` loops with translation rows; gamma then needs v and the
        joint Jacobians' time variation, see the class doc)."""
        return self._tt is not None

    def _evaluate_batched(self, model, data, phi, J, gamma, v, q) -> None:
        r"""Every row of every loop at once (many loops: numpy over all rows, one pass of
        frame placements), the rows of :func:`_translation_rows` and the rotation rows
        of :meth:`evaluate` (the same functions; J and gamma written differently).

        Translation rows, with U = R_p n (world) and d = p_p - p_s: phi = U.d.

        J from the joint Jacobians (``data.J``: world frame, column k the twist of joint k
        at the world origin) in one product: every row's rate is b_r . (V_p - V_s), with
        V_p, V_s the twists (at the world origin) of the bodies of c1 and c2,
        b_r = (U, p_s x U) for a translation row (from U.(v_p - v_s) + (U x d).omega_p
        with v = v_o + omega x p) and b_r = (0, U x W) for a rotation row; V_f is the sum
        of the columns of the joints supporting frame f, so J = D o (B data.J), D_rk =
        1 / -1 / 0 where joint column k supports c1 only / c2 only / both or neither.
        """
        # One array per frame (R and p in one homogeneous matrix): per-frame Python calls
        # dominate this path.
        memo = self._memo
        if q is not None and same_array(q, memo.q):
            H = memo.H
        else:
            H = np.array(
                [pin.updateFramePlacement(model, data, f).homogeneous for f in self._bfids]
            )
            memo.H, memo.q = H, None if q is None else np.array(q)
        # ``take`` on the contiguous stack: a fraction of fancy indexing's cost here.
        tt, tr = self._tt, self._btr
        Hp = H.take(tt.pred, 0)
        ps = H.take(tt.succ, 0)[:, :3, 3]  # p_s of each translation row
        U = np.einsum("rij,rj->ri", Hp[:, :3, :3], tt.n)
        if tr is not None:
            Ur = np.einsum("rij,rj->ri", H.take(tr.pred, 0)[:, :3, :3], tr.u)
            Wr = np.einsum("rij,rj->ri", H.take(tr.succ, 0)[:, :3, :3], tr.w)
            UW = np.einsum("ri,ri->r", Ur, Wr)
        if phi is not None:
            phi[tt.rows] = np.einsum("ri,ri->r", U, Hp[:, :3, 3] - ps)
            if tr is not None:
                phi[tr.rows] = UW
        if J is not None:
            if tr is None and self._tt_all:  # translation rows only, in table order
                B = np.concatenate([U, _cross(ps, U)], axis=1)
            else:
                B = np.zeros((self.nc, 6))
                B[tt.rows, :3] = U
                B[tt.rows, 3:] = _cross(ps, U)
                if tr is not None:
                    B[tr.rows, 3:] = _cross(Ur, Wr)
            np.multiply(self._support_difference(model), B @ data.J, out=J)
        if gamma is None:
            return
        # gamma = d/dt(b_r) . (V_p - V_s) + b_r . (A_p - A_s), the derivative of the rate
        # b_r . (V_p - V_s) of J above, with the bodies' twists V = data.J (s o v) and
        # bias accelerations A = data.dJ (s o v) at the world origin (s: the frame's
        # support mask; joint accelerations zero). Translation rows: b_r = (U, p_s x U),
        # so b_r . (V_p - V_s) = U . dv, dv = (v_p - v_s) + (w_p - w_s) x p_s the
        # relative velocity at the point p_s, and with dU/dt = w_p x U,
        # dp_s/dt = v_s + w_s x p_s and the triple product rule (w x U) . x = U . (x x w):
        # gamma = U . X, X = dv x w_p + (a_p - a_s) + (alpha_p - alpha_s) x p_s
        # + (w_p - w_s) x dp_s/dt, one X per loop (frames 2 l and 2 l + 1).
        # V and A in one product: S (J v, dJ v per column) with S the 0/1 support masks.
        VA = self._frame_support(model) @ (np.concatenate([data.J, data.dJ]) * v).T
        V, A = VA[:, :6], VA[:, 6:]  # (2L, 6) each: linear, angular
        Vp, Vs = V[0::2], V[1::2]
        dV, dA = Vp - Vs, A[0::2] - A[1::2]
        p = H[1::2, :3, 3]  # p_s of each loop
        n = len(p)
        # Three cross products with p_s at once: dw x p, dalpha x p, w_s x p.
        C1 = _cross(np.concatenate([dV[:, 3:], dA[:, 3:], Vs[:, 3:]]), np.concatenate([p, p, p]))
        dv = dV[:, :3] + C1[:n]
        dps = Vs[:, :3] + C1[2 * n :]
        C2 = _cross(np.concatenate([dv, dV[:, 3:]]), np.concatenate([Vp[:, 3:], dps]))
        X = C2[:n] + C2[n:] + dA[:, :3] + C1[n : 2 * n]
        gamma[tt.rows] = np.einsum("ri,ri->r", U, X.take(tt.loop, 0))
        if tr is not None:  # _rotation_gamma reads the angular parts only
            gamma[tr.rows] = _rotation_gamma(V, A, tr, Ur, Wr, UW)

    def _build_tables(self) -> None:
        """Index tables of the active rows over all loops: per-loop translation blocks,
        one batched table of rotation rows; with more than :data:`BATCH_LOOPS` loops
        holding translation rows, one batched table of them too (every row at once)."""
        self._build_batched_tables()
        self._couplings = [b for b in self._active if b.coupling]
        self._fids: list[int] = []
        self._trans: list[tuple[slice, int, int, np.ndarray]] = []
        rot: dict[str, list] = {"rows": [], "loop": [], "u": [], "w": []}
        active = [b for b in self._active if b.nr]
        for i, blk in enumerate(active):
            self._fids += [blk.fid_p, blk.fid_s]
            r = blk.start + blk.nt  # rotation rows follow the translation rows
            for u, w in zip(blk.rot_u, blk.rot_w, strict=True):
                rot["rows"].append(r)
                rot["loop"].append(i)
                rot["u"].append(u)
                rot["w"].append(w)
                r += 1
        for blk in self._active:
            if blk.nt:
                sl = slice(blk.start, blk.start + blk.nt)
                self._trans.append((sl, blk.fid_p, blk.fid_s, np.array(blk.trans)))
        self._tr = _Table(rot) if rot["rows"] else None

    def _build_batched_tables(self) -> None:
        """Tables of :meth:`_evaluate_batched` (``self._tt`` None: the per-loop path)."""
        self._tt = None
        self._support_model = None  # the model _support_difference was made for
        self._memo = _PlacementMemo()  # placements of _bfids kept by _evaluate_batched
        with_trans = [b for b in self._active if b.nt]
        if not with_trans or len(with_trans) <= BATCH_LOOPS:
            return  # rotation rows alone are batched by the per-loop path already
        self._bfids: list[int] = []
        trans: dict[str, list] = {"rows": [], "loop": [], "n": []}
        rot: dict[str, list] = {"rows": [], "loop": [], "u": [], "w": []}
        for i, blk in enumerate(self._active):
            self._bfids += [blk.fid_p, blk.fid_s]
            for k, n in enumerate(blk.trans):
                trans["rows"].append(blk.start + k)
                trans["loop"].append(i)
                trans["n"].append(n)
            for k, (u, w) in enumerate(zip(blk.rot_u, blk.rot_w, strict=True)):
                rot["rows"].append(blk.start + blk.nt + k)
                rot["loop"].append(i)
                rot["u"].append(u)
                rot["w"].append(w)
        self._tt = _Table(trans)
        self._btr = _Table(rot) if rot["rows"] else None
        # One memo for every layer of these loops with the same frames (the declared rows
        # and the kept ones: the simulator evaluates both at each step's end).
        self._memo = self._memos.setdefault(tuple(self._bfids), self._memo)
        self._memo.q = None
        #: The translation rows are every row, in order (J's rows are then B's as made).
        self._tt_all = bool(np.array_equal(self._tt.rows, np.arange(self.nc)))

    def _frame_support(self, model: pin.Model) -> np.ndarray:
        """Return the support masks of the frames of :meth:`_evaluate_batched` (c1, c2 of
        each loop), shape (2L, nv), float (made once per model)."""
        if self._support_model is not model:
            S = np.array([support_mask(model, model.frames[f].parentJoint) for f in self._bfids])
            self._support = S.astype(float)
            row_loop = np.zeros(self.nc, dtype=int)
            row_loop[self._tt.rows] = self._tt.loop
            if self._btr is not None:
                row_loop[self._btr.rows] = self._btr.loop
            self._support_diff = self._support[2 * row_loop] - self._support[2 * row_loop + 1]
            self._support_model = model
        return self._support

    def _support_difference(self, model: pin.Model) -> np.ndarray:
        """Return D, shape (nc, nv), of :meth:`_evaluate_batched`: per row, 1 on the
        velocity columns of the joints that support c1 but not c2, -1 on those that
        support c2 but not c1, 0 elsewhere (made once per model)."""
        self._frame_support(model)
        return self._support_diff

    def misaligned_loops(self, model: pin.Model, data: pin.Data) -> list[str]:
        """Return the loops whose cut frames satisfy phi = 0 only spuriously.

        The rotation rows ``(R_p u).(R_s w)`` also vanish when c2 is turned by
        180 degrees against c1 (revolute: axis antiparallel; fixed, prismatic:
        a half turn about a basis vector). A continuous motion on phi = 0 never
        crosses between the two sets, so only assembly must rule them out:
        a loop is aligned when the basis vectors it constrains keep a positive
        projection, ``a . R a > 0`` (and ``n1 . R n1 > 0``, ``n2 . R n2 > 0``
        where all three rotations are locked), R = R_p^T R_s. Placements must
        be current.
        """
        bad = []
        for name, fid_p, fid_s, vectors in self.alignment_vectors():
            oMp = pin.updateFramePlacement(model, data, fid_p)
            oMs = pin.updateFramePlacement(model, data, fid_s)
            R = oMp.rotation.T @ oMs.rotation
            if any(float(u @ R @ u) <= 0.0 for u in vectors):
                bad.append(name)
        return bad

    def alignment_vectors(self) -> list[tuple[str, int, int, list[np.ndarray]]]:
        """Return ``(loop name, fid_p, fid_s, vectors)`` of every loop that
        :meth:`misaligned_loops` checks (spherical loops have none): the loop is
        aligned when ``u . R_p^T R_s u > 0`` for each vector u (the compiled core's
        dependent solve checks the same)."""
        out = []
        for blk in self._blocks:
            if blk.spec.type in ("spherical", COUPLING):
                continue
            a = blk.spec.axis
            vectors = [a] if blk.spec.type == "revolute" else [a, *axis_basis(a)]
            out.append((blk.spec.name, blk.fid_p, blk.fid_s, vectors))
        return out

    def loop_residuals(self, model: pin.Model, data: pin.Data) -> dict[str, float]:
        """Return max |e| per loop of its closure residual (:func:`closure_residual`), zero
        exactly where the loop is closed [m or rad] (joint placements must be current)."""
        e, _ = self.closure_residuals(model, data)
        return {
            name: float(np.max(np.abs(e[sl]), initial=0.0)) for name, sl in self.closure_slices()
        }

    def closure_slices(self) -> list[tuple[str, slice]]:
        """Return each loop's name and its slice of :meth:`closure_residuals`, in URDF order."""
        out, start = [], 0
        for blk in self._blocks:
            k = CLOSURE_SIZES[blk.spec.type]
            out.append((blk.spec.name, slice(start, start + k)))
            start += k
        return out

    def closure_residuals(
        self, model: pin.Model, data: pin.Data, *, jacobian: bool = False
    ) -> tuple[np.ndarray, np.ndarray | None]:
        r"""Return the closure residual e of every loop and, optionally, its Jacobian.

        e is zero exactly where every loop is closed (:func:`closure_residual`),
        unlike the rows phi, whose rotation rows also vanish on a 180-degree flip.
        With ``c1Mc2`` the placement of c2 in c1 and LOCAL frame Jacobians J1, J2 of
        c1 and c2, a displacement dq = dv along ``pin.integrate`` moves c1Mc2 to
        ``c1Mc2 exp(xi)`` with

        .. math::

            \xi = \bigl(J_2 - \mathrm{Ad}(c_1M_{c_2}^{-1}) J_1\bigr)\, dv,

        so :math:`E = D\,(J_2 - \mathrm{Ad}(c_1M_{c_2}^{-1}) J_1)` with D the
        derivative of :func:`closure_residual` along xi.

        Args:
            model: the model (with the loop frames).
            data: its data, filled by ``forwardKinematics(q)`` (e) or
                ``computeJointJacobians(q)`` (e and E).
            jacobian: also return E.

        Returns:
            ``(e, E)``: e of every declared loop (all its entries, whichever rows
            are kept), shape (ne,) [m or rad] (:meth:`closure_slices`); E = de/dv,
            shape (ne, nv), or None.
        """
        es, Es = [], []
        for blk in self._blocks:
            if blk.spec.type == COUPLING:  # e is its row phi (zero exactly where closed)
                e, E = np.zeros(1), np.zeros((1, model.nv)) if jacobian else None
                _coupling_row(model, data, blk, 0, e, E, None)
                es.append(e)
                Es.append(E)
                continue
            oMp = pin.updateFramePlacement(model, data, blk.fid_p)
            oMs = pin.updateFramePlacement(model, data, blk.fid_s)
            c1Mc2 = oMp.actInv(oMs)
            e, D = closure_residual(blk.spec, c1Mc2)
            es.append(e)
            if jacobian:
                J1 = pin.getFrameJacobian(model, data, blk.fid_p, _LOCAL)
                J2 = pin.getFrameJacobian(model, data, blk.fid_s, _LOCAL)
                Es.append(D @ (J2 - c1Mc2.inverse().action @ J1))
        e = np.concatenate(es) if es else np.zeros(0)
        if not jacobian:
            return e, None
        return e, np.concatenate(Es) if Es else np.zeros((0, model.nv))


#: Entries of :func:`closure_residual` per loop type.
CLOSURE_SIZES = {"fixed": 6, "spherical": 3, "revolute": 6, "prismatic": 5, COUPLING: 1}


def closure_residual(spec: LoopSpec, c1Mc2: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
    r"""Return a loop's closure residual e, zero exactly where the loop is closed, and de/dxi.

    With ``c1Mc2 = (R, p)`` the placement of c2 in c1, a the loop axis and
    (n1, n2, a) its basis (:func:`axis_basis`):

    ========= ======================================== =====
    type      e                                        size
    ========= ======================================== =====
    fixed     log6(c1Mc2) (translation, rotation)      6
    spherical p                                        3
    revolute  p, R a - a                               3 + 3
    prismatic n1.p, n2.p, log3(R)                      2 + 3
    ========= ======================================== =====

    (A coupling loop's e is its row q_j - m q_i - c: :meth:`ConstraintLayer.closure_residuals`.)

    The revolute loop's rotation part is the chord between the axis and its
    image: smooth everywhere, zero only when the axes coincide, of length
    2 sin(theta / 2) for a tilt theta (2 on the 180-degree flip, where the rows
    phi vanish). log3 and log6 have their cut at a half turn, as far from the
    closure as can be. The rows phi are a local chart of the same set: at a
    closure, e and phi vanish together.

    Args:
        spec: the loop (its type and axis, in c1).
        c1Mc2: placement of the successor's cut frame c2 in the predecessor's c1.

    Returns:
        ``(e, D)``: e, shape (k,) [m or rad] (k from :data:`CLOSURE_SIZES`), and D,
        shape (k, 6), the derivative of e along ``c1Mc2 exp(xi)`` at xi = 0 (xi:
        linear, angular).
    """
    R, p = c1Mc2.rotation, c1Mc2.translation
    if spec.type == "fixed":
        return pin.log6(c1Mc2).vector, pin.Jlog6(c1Mc2)
    D = np.zeros((CLOSURE_SIZES[spec.type], 6))
    if spec.type == "spherical":
        D[:, :3] = R
        return p.copy(), D
    a = np.asarray(spec.axis, dtype=float)
    if spec.type == "revolute":
        D[:3, :3] = R
        D[3:, 3:] = -R @ pin.skew(a)  # d(R a) = R (dw x a)
        return np.concatenate([p, R @ a - a]), D
    n = np.array(axis_basis(a))  # prismatic: translation across the axis
    D[:2, :3] = n @ R
    D[2:, 3:] = pin.Jlog3(R)
    return np.concatenate([n @ p, pin.log3(R)]), D


def build_pinocchio_constraints(
    model: pin.Model, layer: ConstraintLayer
) -> tuple[pin.StdVec_RigidConstraintModel, list[str]]:
    """Express every loop as Pinocchio rigid constraint models.

    revolute: two CONTACT_3D points on the axis (6 rows, rank 5, Pinocchio
    upstream issue #2729 has no 5-D cut); spherical: one CONTACT_3D; fixed:
    CONTACT_6D.

    Args:
        model: model holding the loop frames.
        layer: the constraint layer (its loops and frame ids).

    Returns:
        The constraint models and, per model, the loop it stands for.

    Raises:
        ValidationUnavailableError: a prismatic loop (Pinocchio has no
            prismatic constraint model).
    """
    cms = pin.StdVec_RigidConstraintModel()
    owners: list[str] = []
    for spec, (fp, fs) in zip(layer.loops, layer.frame_ids, strict=True):
        frame_p, frame_s = model.frames[fp], model.frames[fs]
        j1, M1 = frame_p.parentJoint, frame_p.placement
        j2, M2 = frame_s.parentJoint, frame_s.placement
        if spec.type == COUPLING:
            raise ValidationUnavailableError(
                f"loop {spec.name!r} is a joint coupling: Pinocchio has no coupling "
                "constraint model, so there is no Pinocchio reference for coupling rows; "
                "valid loop types for validation: revolute, spherical, fixed"
            )
        if spec.type == "prismatic":
            raise ValidationUnavailableError(
                f"loop {spec.name!r} is prismatic: Pinocchio has no prismatic rigid "
                "constraint model, so it cannot serve as the reference; valid loop types "
                "for validation: revolute, spherical, fixed"
            )
        if spec.type == "fixed":
            cms.append(_rcm(pin.ContactType.CONTACT_6D, model, j1, M1, j2, M2, spec.name))
            owners.append(spec.name)
            continue
        cms.append(_rcm(pin.ContactType.CONTACT_3D, model, j1, M1, j2, M2, spec.name))
        owners.append(spec.name)
        if spec.type == "revolute":
            shift = pin.SE3(np.eye(3), PIN_REVOLUTE_POINT_OFFSET * spec.axis)
            cms.append(
                _rcm(pin.ContactType.CONTACT_3D, model, j1, M1 * shift, j2, M2 * shift, spec.name)
            )
            owners.append(spec.name)
    return cms, owners


def _rcm(ctype, model, j1, M1, j2, M2, name):
    cm = pin.RigidConstraintModel(ctype, model, j1, M1, j2, M2, pin.ReferenceFrame.LOCAL)
    cm.name = name
    return cm
