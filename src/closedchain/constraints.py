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
successor's), evaluated as written by :meth:`ConstraintLayer.evaluate`.

A coupling loop (``q_j = m q_i + c``, :data:`closedchain.urdf.COUPLING`) has
no frame rows: its one row reads the two joints' coordinates from ``data``
(``data.joints[j].joint_q``, which every kinematics routine fills), its J is
constant (+1 at j, -m at i) and its gamma is zero.

So J is exactly the derivative of phi along ``pin.integrate`` and
gamma = Jdot v exactly: finite differences check both (tests/test_constraints.py).
For the planar 4-bar the two kept rows are the lesson's closure
``p_C(coupler) - p_C(rocker)`` (Section 2) expressed in the coupler's cut frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .exceptions import ValidationUnavailableError
from .pindata import frame_jacobian
from .urdf import COUPLING, LoopSpec

__all__ = [
    "CLOSURE_SIZES",
    "ConstraintLayer",
    "RowInfo",
]

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_LOCAL = pin.ReferenceFrame.LOCAL

#: Distance [m] between the two points on the axis that stand for a revolute
#: loop in Pinocchio's CONTACT_3D constraint models (any nonzero value works:
#: it only rescales the multipliers, not J^T lam).
PIN_REVOLUTE_POINT_OFFSET = 0.1

#: Row function codes of :class:`RowTable`: translation (R_p n).(p_p - p_s).
ROW_TRANSLATION = 0
#: Rotation (R_p u).(R_s w).
ROW_ROTATION = 1
#: Joint coupling q_j - m q_i - c of the parent joints i of c1 and j of c2 (1-dof joints).
ROW_COUPLING = 2
#: Kind of a coupling row in :class:`RowInfo`.
COUPLING_KIND = "q"


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


def _loop_rows(model, data, blk: LoopRows, phi, J, gamma) -> None:
    r"""Fill the rows of one loop with cut frames (the formulas of the module docstring).

    With world placements ``(R_p, p_p)`` of c1 and ``(R_s, p_s)`` of c2, d = p_p - p_s,
    U = R_p n (translation rows) or R_p u (rotation rows), W = R_s w, and the frames'
    velocities (v, omega) and classical bias accelerations (a_b, alpha_b), all
    LOCAL_WORLD_ALIGNED:

    .. math::

        \phi_t = U^\top d, \qquad
        J_t = U^\top (J_{v,p} - J_{v,s}) + (U \times d)^\top J_{\omega,p}, \qquad
        \gamma_t = \ddot U^\top d + 2 \dot U^\top \dot d + U^\top (a_{b,p} - a_{b,s}),

        \phi_r = U^\top W, \qquad
        J_r = (W \times U)^\top (J_{\omega,s} - J_{\omega,p}), \qquad
        \gamma_r = \ddot U^\top W + 2 \dot U^\top \dot W + U^\top \ddot W,

    with :math:`\dot U = \omega_p \times U`, :math:`\ddot U = \alpha_{b,p} \times U +
    \omega_p \times \dot U`, and the same for W with the successor's.
    """
    oMp = pin.updateFramePlacement(model, data, blk.fid_p)
    oMs = pin.updateFramePlacement(model, data, blk.fid_s)
    d = oMp.translation - oMs.translation
    Ut = blk.trans @ oMp.rotation.T  # translation rows: U = R_p n, one row each
    Ur = blk.rot_u @ oMp.rotation.T  # rotation rows: U = R_p u
    Wr = blk.rot_w @ oMs.rotation.T  # W = R_s w
    t = slice(blk.start, blk.start + blk.nt)  # translation rows come first
    r = slice(blk.start + blk.nt, blk.start + blk.n)
    if phi is not None:
        phi[t] = Ut @ d
        phi[r] = np.sum(Ur * Wr, axis=1)
    if J is not None:
        Jp = frame_jacobian(model, data, blk.fid_p, _LWA)
        Js = frame_jacobian(model, data, blk.fid_s, _LWA)
        # (U x d).omega_p = U.(d x omega_p) = U^T [d]x omega_p
        J[t] = Ut @ (Jp[:3] - Js[:3] + pin.skew(d) @ Jp[3:])
        W_x_U = np.array([pin.skew(w) @ u for u, w in zip(Ur, Wr, strict=True)]).reshape(-1, 3)
        J[r] = W_x_U @ (Js[3:] - Jp[3:])
    if gamma is not None:
        vp = pin.getFrameVelocity(model, data, blk.fid_p, _LWA)
        vs = pin.getFrameVelocity(model, data, blk.fid_s, _LWA)
        ap = pin.getFrameClassicalAcceleration(model, data, blk.fid_p, _LWA)
        as_ = pin.getFrameClassicalAcceleration(model, data, blk.fid_s, _LWA)
        Ut_dot = _cross_rows(vp.angular, Ut)
        Ut_ddot = _cross_rows(ap.angular, Ut) + _cross_rows(vp.angular, Ut_dot)
        d_dot = vp.linear - vs.linear
        gamma[t] = Ut_ddot @ d + 2.0 * Ut_dot @ d_dot + Ut @ (ap.linear - as_.linear)
        Ur_dot = _cross_rows(vp.angular, Ur)
        Ur_ddot = _cross_rows(ap.angular, Ur) + _cross_rows(vp.angular, Ur_dot)
        Wr_dot = _cross_rows(vs.angular, Wr)
        Wr_ddot = _cross_rows(as_.angular, Wr) + _cross_rows(vs.angular, Wr_dot)
        gamma[r] = np.sum(Ur_ddot * Wr + 2.0 * Ur_dot * Wr_dot + Ur * Wr_ddot, axis=1)


def _cross_rows(w: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Return w x a for every row a of A, shape (k, 3) (A: shape (k, 3), w: shape (3,))."""
    return A @ pin.skew(w).T


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

    Translation and coupling rows carry w = 0; a coupling row carries
    u = (m, c, 0), its multiplier and offset. See the module docstring for the table.
    """
    a = np.asarray(spec.axis, dtype=float)
    n1, n2 = axis_basis(a)
    zero = np.zeros(3)
    if spec.type == COUPLING:
        return [(COUPLING_KIND, ROW_COUPLING, np.array([spec.multiplier, spec.offset, 0.0]), zero)]
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
    ``(R_s, p_s)`` that of ``frame_s[i]``; ``q_j - m q_i - c`` with ``u_i = (m, c, 0)``
    when ``function[i] == ROW_COUPLING``, i and j the parent joints of the two frames.
    The codes are the compiled core's (src/cpp/constants.hpp, generated).

    Attributes:
        function: row function code, shape (nc,), int.
        frame_p, frame_s: model frame ids of c1 and c2, shape (nc,), int.
        u: n or u in c1, shape (nc, 3), unit vectors; (m, c, 0) of a coupling row.
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


class ConstraintLayer:
    """phi, J and gamma of a set of loops, evaluated from filled Pinocchio data.

    Build it with the loop frames already added to the model; restrict it to
    independent rows with :meth:`restricted`. The ``evaluate`` method reads
    ``data`` and never calls a kinematics algorithm itself, so the caller runs
    each Pinocchio routine once per evaluation:

    * phi needs ``forwardKinematics(q)``,
    * J needs ``computeJointJacobians(q)`` (or ``computeAllTerms``),
    * gamma needs ``forwardKinematics(q, v, 0)`` (or ``computeAllTerms``).
    """

    def __init__(
        self,
        loops: tuple[LoopSpec, ...],
        frame_ids: tuple[tuple[int, int], ...],
        keep: tuple[tuple[int, ...], ...] | None = None,
    ) -> None:
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
        return ConstraintLayer(self.loops, self.frame_ids, tuple(tuple(k) for k in per_loop))

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
    ) -> None:
        """Fill the requested outputs from ``data``, loop by loop.

        Args:
            model: the mechanism's Pinocchio model (with the loop frames).
            data: its data, filled by the kinematics routines listed in the class doc.
            phi: output, shape (nc,), [m] or [-] per row.
            J: output, shape (nc, nv), d phi / d v along ``pin.integrate``.
            gamma: output, shape (nc,), Jdot v.
        """
        for blk in self._active:
            if blk.coupling:
                _coupling_row(model, data, blk, blk.start, phi, J, gamma)
            else:
                _loop_rows(model, data, blk, phi, J, gamma)

    @property
    def couplings(self) -> tuple[LoopSpec, ...]:
        """The loops whose active row is a coupling row (``q_j = m q_i + c``)."""
        return tuple(b.spec for b in self._active if b.coupling)

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
                J1 = frame_jacobian(model, data, blk.fid_p, _LOCAL)
                J2 = frame_jacobian(model, data, blk.fid_s, _LOCAL)
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
                f"loop {spec.name!r} is a joint coupling: Pinocchio's constrained dynamics "
                "has no coupling constraint model (closedchain.validate checks couplings on "
                "Pinocchio's mimic joints instead); valid loop types for "
                "pinocchio.constraintDynamics: revolute, spherical, fixed"
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
