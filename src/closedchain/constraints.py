r"""Loop-closure constraints: phi(q), J(q) and gamma(q, v) = Jdot(q, v) v.

A loop joint cuts the mechanism between a frame c1 on the predecessor link and
a frame c2 on the successor link (the ``*_origin`` placements of the
``<loop>`` element). With world placements ``oMc1 = (R_p, p_p)`` and
``oMc2 = (R_s, p_s)`` the declared rows of each loop type are

======== =============================================== =========
type     rows                                            count
======== =============================================== =========
revolute translation d = p_p - p_s (world x, y, z),      3 + 2
         tilt of the axis (n1.a, n2.a)
spherical translation d (world x, y, z)                   3
fixed    translation d, tilt (n1.a, n2.a), twist n1.n2   3 + 3
prismatic d across the axis (n1.d, n2.d), tilt, twist    2 + 3
======== =============================================== =========

where a is the loop axis and (n1, n2, a) a right-handed orthonormal basis, all
given in c1 (predecessor side) and c2 (successor side) and carried to the world
by R_p and R_s. Every row is one of three smooth scalar functions:

.. math::

    \phi_{d,k} = e_k^\top (p_p - p_s), \qquad
    \phi_{t,i} = (R_p n_i)^\top (p_p - p_s), \qquad
    \phi_{r} = (R_p u)^\top (R_s w),

with exact first and second time derivatives (``u``, ``w`` constant unit
vectors in c1 and c2). With frame velocities ``(v, omega)`` and bias
accelerations ``(a_b, alpha_b)`` (classical, world-aligned, at zero joint
acceleration):

.. math::

    \dot\phi_r = (\omega_s - \omega_p)^\top (w \times u), \qquad
    \gamma_r = \ddot u^\top w + 2 \dot u^\top \dot w + u^\top \ddot w,
    \quad \dot u = \omega_p \times u,\;
    \ddot u = \alpha_{b,p} \times u + \omega_p \times (\omega_p \times u),

expanded in :meth:`ConstraintLayer.evaluate` into dot products
(one cross product per loop).

So J is exactly the derivative of phi along ``pin.integrate`` and
gamma = Jdot v exactly: finite differences check both (tests/test_constraints.py).
The translation rows reproduce the textbook 4-bar closure
``p_C(coupler) - p_C(rocker)`` of the seed text, Section 2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .exceptions import ValidationUnavailableError
from .urdf import LoopSpec

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED

#: Distance [m] between the two points on the axis that stand for a revolute
#: loop in Pinocchio's CONTACT_3D constraint models (any nonzero value works:
#: it only rescales the multipliers, not J^T lam).
PIN_REVOLUTE_POINT_OFFSET = 0.1


_I1 = np.array([1, 2, 0])
_I2 = np.array([2, 0, 1])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (k, 3) arrays (or a (3,) vector against (k, 3)).

    numpy.cross spends ~30 us on axis handling; this is the same formula
    without it, for the small arrays of the per-evaluation path.
    """
    return a[..., _I1] * b[..., _I2] - a[..., _I2] * b[..., _I1]


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


@dataclass(frozen=True)
class RowInfo:
    """One declared constraint row.

    Attributes:
        loop: name of its loop.
        kind: ``"x" | "y" | "z"`` (world translation), ``"t1" | "t2"``
            (translation across a prismatic axis), ``"r1" | "r2" | "r3"`` (rotation).
        unit: ``"m"`` or ``"1"`` (dimensionless).
    """

    loop: str
    kind: str
    unit: str

    @property
    def label(self) -> str:
        return f"{self.loop}.{self.kind}"


class LoopRows:
    """The active rows of one loop and the constant vectors they are built from.

    Attributes:
        spec: the loop as written in the URDF.
        fid_p, fid_s: model frame ids of the cut-joint frames c1 and c2.
        world: world axes (0, 1, 2) of the translation rows, in row order.
        perp: unit vectors n_i in c1 of the prismatic cross-axis rows, shape (nt, 3).
        rot_u, rot_w: the vectors u (in c1) and w (in c2) of the rotation rows
            (R_p u).(R_s w), shapes (nr, 3).
        rows: the active rows' RowInfo, in evaluation order (world, perp, rot).
        start: first row of this loop in the layer's output.
    """

    def __init__(self, spec: LoopSpec, fid_p: int, fid_s: int, keep: list[int] | None) -> None:
        self.spec = spec
        self.fid_p = fid_p
        self.fid_s = fid_s
        a = spec.axis
        n1, n2 = axis_basis(a)
        world: list[int] = []
        perp: list[np.ndarray] = []
        rot_u: list[np.ndarray] = []
        rot_w: list[np.ndarray] = []
        # Declared rows in a fixed order: translation, then rotation.
        declared: list[tuple[str, object]] = []
        if spec.type in ("revolute", "spherical", "fixed"):
            declared += [("world", 0), ("world", 1), ("world", 2)]
        if spec.type == "prismatic":
            declared += [("perp", n1), ("perp", n2)]
        if spec.type in ("revolute", "fixed", "prismatic"):
            declared += [("rot", (n1, a)), ("rot", (n2, a))]
        if spec.type in ("fixed", "prismatic"):
            declared += [("rot", (n1, n2))]
        self.n_declared = len(declared)
        names = {"world": "xyz", "perp": ("t1", "t2"), "rot": ("r1", "r2", "r3")}
        counters = {"world": 0, "perp": 0, "rot": 0}
        infos = []
        for kind, payload in declared:
            if kind == "world":
                label = names["world"][payload]
            else:
                label = names[kind][counters[kind]]
            counters[kind] += 1
            infos.append(RowInfo(spec.name, label, "1" if kind == "rot" else "m"))
        self.declared_rows = tuple(infos)
        keep = list(range(len(declared))) if keep is None else keep
        for i in keep:
            kind, payload = declared[i]
            if kind == "world":
                world.append(payload)
            elif kind == "perp":
                perp.append(payload)
            else:
                rot_u.append(payload[0])
                rot_w.append(payload[1])
        # Active rows are evaluated grouped by kind; record their order.
        order = (
            [i for i in keep if declared[i][0] == "world"]
            + [i for i in keep if declared[i][0] == "perp"]
            + [i for i in keep if declared[i][0] == "rot"]
        )
        self.rows = tuple(infos[i] for i in order)
        self.world = np.array(world, dtype=int)
        self.perp = np.array(perp).reshape(-1, 3)
        self.rot_u = np.array(rot_u).reshape(-1, 3)
        self.rot_w = np.array(rot_w).reshape(-1, 3)
        self.n = len(keep)
        self.nw, self.nt, self.nr = len(world), len(perp), len(rot_u)
        self.start = 0  # first row of this block in the layer, set by ConstraintLayer


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
        self.keep = keep
        self._blocks = [
            LoopRows(spec, fp, fs, None if keep is None else list(keep[i]))
            for i, (spec, (fp, fs)) in enumerate(zip(loops, frame_ids, strict=True))
        ]
        self.rows: tuple[RowInfo, ...] = tuple(r for b in self._blocks for r in b.rows)
        self.declared_rows: tuple[RowInfo, ...] = tuple(
            r for b in self._blocks for r in b.declared_rows
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

    def row_table(self) -> dict[str, np.ndarray]:
        """Return the active rows as a table, in output order (the compiled core's input).

        Every row is one of three scalar functions (module docstring): ``kind``
        0, translation along ``vec1`` fixed in the world; 1, translation along
        ``vec1`` fixed in c1; 2, rotation ``(R_p vec1).(R_s vec2)``.

        Returns:
            ``kind`` (nc,) int32, ``fid_p`` and ``fid_s`` (nc,) int32 frame ids of
            c1 and c2, ``vec1`` and ``vec2`` (nc, 3).
        """
        kind, fid_p, fid_s, vec1, vec2 = [], [], [], [], []
        zero = np.zeros(3)
        for blk in self._blocks:
            entries = [(0, np.eye(3)[k], zero) for k in blk.world]
            entries += [(1, n, zero) for n in blk.perp]
            entries += [(2, u, w) for u, w in zip(blk.rot_u, blk.rot_w, strict=True)]
            for k, a, b in entries:
                kind.append(k)
                fid_p.append(blk.fid_p)
                fid_s.append(blk.fid_s)
                vec1.append(a)
                vec2.append(b)
        return {
            "kind": np.array(kind, dtype=np.int32),
            "fid_p": np.array(fid_p, dtype=np.int32),
            "fid_s": np.array(fid_s, dtype=np.int32),
            "vec1": np.array(vec1, dtype=float).reshape(-1, 3),
            "vec2": np.array(vec2, dtype=float).reshape(-1, 3),
        }

    def restricted(self, rows: list[int]) -> ConstraintLayer:
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

    def evaluate(
        self,
        model: pin.Model,
        data: pin.Data,
        *,
        phi: np.ndarray | None = None,
        J: np.ndarray | None = None,
        gamma: np.ndarray | None = None,
    ) -> None:
        """Fill the requested outputs from ``data``.

        Args:
            model: the mechanism's Pinocchio model (with the loop frames).
            data: its data, filled by the kinematics routines listed in the class doc.
            phi: output, shape (nc,), [m] or [-] per row.
            J: output, shape (nc, nv), d phi / d v along ``pin.integrate``.
            gamma: output, shape (nc,), Jdot v.
        """
        # Hot path (every dynamics evaluation): all loops at once, a fixed
        # number of batched numpy calls whatever the number of loops (numpy's
        # per-call overhead, not arithmetic, dominates arrays this small).
        # World translation rows: per loop, contiguous, straight from the
        # frame getters (stacking would cost more than it saves here).
        for r0, r1, fp, fs, axes in self._world:
            if phi is not None:
                pp = pin.updateFramePlacement(model, data, fp).translation
                phi[r0:r1] = (pp - pin.updateFramePlacement(model, data, fs).translation)[axes]
            if J is not None:
                Jp = pin.getFrameJacobian(model, data, fp, _LWA)
                J[r0:r1] = (Jp[:3] - pin.getFrameJacobian(model, data, fs, _LWA)[:3])[axes]
            if gamma is not None:
                ap = pin.getFrameClassicalAcceleration(model, data, fp, _LWA).linear
                as_ = pin.getFrameClassicalAcceleration(model, data, fs, _LWA).linear
                gamma[r0:r1] = (ap - as_)[axes]
        tt, tr = self._tt, self._tr
        if tt is None and tr is None:
            return
        frames = [pin.updateFramePlacement(model, data, f) for f in self._fids]
        p = np.array([M.translation for M in frames])
        d = p[0::2] - p[1::2]  # (L, 3) p_p - p_s, world
        R = np.array([M.rotation for M in frames])  # (2L, 3, 3): c1, c2 of each loop
        if tt is not None:
            Ut = (R[tt.pred] @ tt.n[:, :, None])[:, :, 0]  # R_p n_i, world
            dt = d[tt.loop]
        if tr is not None:
            U = (R[tr.pred] @ tr.u[:, :, None])[:, :, 0]  # R_p u, world
            W = (R[tr.succ] @ tr.w[:, :, None])[:, :, 0]  # R_s w, world
            UW = np.einsum("ri,ri->r", U, W)
        if phi is not None:
            if tt is not None:
                phi[tt.rows] = np.einsum("ri,ri->r", Ut, dt)
            if tr is not None:
                phi[tr.rows] = UW
        if J is not None:
            Jf = np.array([pin.getFrameJacobian(model, data, f, _LWA) for f in self._fids])
            if tt is not None:
                J[tt.rows] = np.einsum(
                    "ri,rin->rn", Ut, Jf[tt.pred, :3] - Jf[tt.succ, :3]
                ) + np.einsum("ri,rin->rn", _cross(Ut, dt), Jf[tt.pred, 3:])
            if tr is not None:
                J[tr.rows] = np.einsum(
                    "ri,rin->rn", _cross(W, U), Jf[tr.succ, 3:] - Jf[tr.pred, 3:]
                )
        if gamma is not None:
            A = np.array(
                [pin.getFrameClassicalAcceleration(model, data, f, _LWA).vector for f in self._fids]
            )  # (2L, 6): classical linear, angular; bias (zero joint acceleration)
            V = np.array([pin.getFrameVelocity(model, data, f, _LWA).vector for f in self._fids])
            if tt is not None:
                wp, alp = V[tt.pred, 3:], A[tt.pred, 3:]
                Ud = _cross(wp, Ut)
                Udd = _cross(alp, Ut) + _cross(wp, Ud)
                ddot = V[tt.pred, :3] - V[tt.succ, :3]
                dd = A[tt.pred, :3] - A[tt.succ, :3]
                gamma[tt.rows] = (
                    np.einsum("ri,ri->r", Udd, dt)
                    + np.einsum("ri,ri->r", 2.0 * Ud, ddot)
                    + np.einsum("ri,ri->r", Ut, dd)
                )
            if tr is not None:
                # Triple products expanded (one cross product):
                # gamma_r = (alpha_s - alpha_p).(w x u) + (wp.u)(wp.w) + (ws.u)(ws.w)
                #           - 2 (wp.w)(ws.u) - |wp - ws|^2 (u.w)
                wp, ws = V[tr.pred, 3:], V[tr.succ, 3:]
                pu = np.einsum("ri,ri->r", wp, U)
                pw = np.einsum("ri,ri->r", wp, W)
                su = np.einsum("ri,ri->r", ws, U)
                sw = np.einsum("ri,ri->r", ws, W)
                dw = wp - ws
                gamma[tr.rows] = (
                    np.einsum("ri,ri->r", _cross(W, U), A[tr.succ, 3:] - A[tr.pred, 3:])
                    + pu * pw
                    + su * sw
                    - 2.0 * pw * su
                    - np.einsum("ri,ri->r", dw, dw) * UW
                )

    def _build_tables(self) -> None:
        """Index tables of the active rows, grouped by kind, over all loops."""
        self._fids: list[int] = []
        self._world: list[tuple[int, int, int, int, np.ndarray]] = []
        perp: dict[str, list] = {"rows": [], "loop": [], "n": []}
        rot: dict[str, list] = {"rows": [], "loop": [], "u": [], "w": []}
        for i, blk in enumerate(self._active):
            self._fids += [blk.fid_p, blk.fid_s]
            r = blk.start
            if blk.nw:
                self._world.append((r, r + blk.nw, blk.fid_p, blk.fid_s, blk.world))
                r += blk.nw
            for n in blk.perp:
                perp["rows"].append(r)
                perp["loop"].append(i)
                perp["n"].append(n)
                r += 1
            for u, w in zip(blk.rot_u, blk.rot_w, strict=True):
                rot["rows"].append(r)
                rot["loop"].append(i)
                rot["u"].append(u)
                rot["w"].append(w)
                r += 1
        self._tt = _Table(perp) if perp["rows"] else None
        self._tr = _Table(rot) if rot["rows"] else None

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
        for blk in self._blocks:
            if blk.spec.type == "spherical":
                continue
            oMp = pin.updateFramePlacement(model, data, blk.fid_p)
            oMs = pin.updateFramePlacement(model, data, blk.fid_s)
            R = oMp.rotation.T @ oMs.rotation
            a = blk.spec.axis
            vectors = [a] if blk.spec.type == "revolute" else [a, *axis_basis(a)]
            if any(float(u @ R @ u) <= 0.0 for u in vectors):
                bad.append(blk.spec.name)
        return bad

    def loop_residuals(self, model: pin.Model, data: pin.Data) -> dict[str, float]:
        """Return max |phi| per loop over its active rows (placements must be current)."""
        phi = np.zeros(self.nc)
        self.evaluate(model, data, phi=phi)
        return {
            b.spec.name: float(np.max(np.abs(phi[sl]), initial=0.0))
            for b, sl in zip(self._blocks, self._slices, strict=True)
        }


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
