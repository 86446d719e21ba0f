r"""Proofs that a loop cannot close: a height along a common joint axis that no joint changes.

A loop closes when its two cut-joint frames c1 and c2 meet (``fixed``: the
placements are equal; ``spherical``: the origins are). Their relative
placement depends only on the joints on the tree path between them, so a loop
that cannot close with every one of those joints free cannot close inside the
mechanism either, whatever the other loops and the joint limits do.

A revolute joint about an axis parallel to a unit vector y, or a prismatic
joint across y, moves every body after it without changing the height
:math:`y \cdot p` of any of its points p, nor the direction y seen from it
(the common ancestor of the loop's two sides is the reference: y is fixed in
it). When every joint of the loop is of that kind ("planar about y"), the
heights of c1 and c2 are the same in every configuration; at the closure they
must be equal. One more joint, the last one before a loop frame (the frame's
own link), may be of another kind:

- a ball joint (spherical) keeps its centre c: a point of the link before it
  (planar: its height is fixed) and of the frame's link, which a ``fixed``
  loop welds to the other side's link (planar: the height of the point welded
  there is fixed too); for a ``spherical`` loop the frame origin stays on the
  sphere about c of radius :math:`\rho = |p - c|`: its height stays in
  :math:`[y \cdot c - \rho, y \cdot c + \rho]`;
- a revolute joint about a unit axis s through c keeps c and s: as for a ball
  (a ``fixed`` loop), plus the angle between y and s (a rotation about y keeps
  it); the origin of a ``spherical`` loop's frame turns on a circle about s,
  whose height stays in :math:`m \pm w` with :math:`d = p - c`,
  :math:`m = y \cdot c + (y \cdot s)(s \cdot d)`,
  :math:`w = |d - (s \cdot d) s| \sqrt{1 - (y \cdot s)^2}`.

All the quantities are evaluated at the neutral configuration (any
configuration gives the same values). :func:`prove_unclosable` returns the
first loop whose two sides' values differ by more than :data:`GAP_MIN` (or the
caller's ``gap_min``), in one line naming the joints, the axis and the two
values. Loops of another type (revolute, prismatic, coupling) and joints of
another kind (free flyer, planar, helical, mimic, ...) are not examined: no
proof is found, none is claimed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from .constraints import ConstraintLayer

#: Two unit axes count as parallel (and a slide direction as across an axis) when
#: the sine (cosine) of their angle is at most this [-]. Axes that are only nearly
#: parallel are left alone: they could reach the closure by turning far.
PARALLEL_TOL = 1e-10

#: A loop is proven open when its two sides' heights [m] (or angles [rad]) differ by
#: more than this: far above the round-off of the forward kinematics, far below any
#: CAD offset.
GAP_MIN = 1e-8

#: Pinocchio joint models that turn about one axis, and that slide along one.
REVOLUTE_JOINTS = frozenset(
    f"JointModel{k}"
    for k in ("RX", "RY", "RZ", "RevoluteUnaligned", "RUBX", "RUBY", "RUBZ")
    + ("RevoluteUnboundedUnaligned",)
)
PRISMATIC_JOINTS = frozenset(f"JointModel{k}" for k in ("PX", "PY", "PZ", "PrismaticUnaligned"))
#: Pinocchio joint models that turn about a point (ball joints).
BALL_JOINTS = frozenset(("JointModelSpherical", "JointModelSphericalZYX"))


@dataclass(frozen=True)
class _Joint:
    """One joint of a loop at the neutral configuration, in world coordinates.

    Attributes:
        name: joint name.
        kind: "revolute", "prismatic", "ball" or "other".
        axis: unit axis (revolute: of rotation; prismatic: of motion), shape (3,).
        point: a point of the axis, or the ball's centre [m], shape (3,).
    """

    name: str
    kind: str
    axis: np.ndarray
    point: np.ndarray

    def planar(self, y: np.ndarray) -> bool:
        """Whether the joint keeps heights along ``y`` and the direction ``y``."""
        if self.kind == "revolute":
            return float(np.linalg.norm(np.cross(self.axis, y))) <= PARALLEL_TOL
        return self.kind == "prismatic" and abs(float(self.axis @ y)) <= PARALLEL_TOL


def _joint(model: pin.Model, data: pin.Data, q: np.ndarray, j: int) -> _Joint:
    """Return joint ``j`` as a :class:`_Joint` (``data`` holds the kinematics at ``q``)."""
    jm, oMi = model.joints[j], data.oMi[j]
    kind = "other"
    axis = np.zeros(3)
    name = jm.shortname()
    if name in REVOLUTE_JOINTS or name in PRISMATIC_JOINTS:
        jdata = jm.createData()
        jm.calc(jdata, q)
        S = np.asarray(jdata.S, dtype=float).ravel()
        kind, local = ("revolute", S[3:6]) if name in REVOLUTE_JOINTS else ("prismatic", S[0:3])
        axis = oMi.rotation @ local / np.linalg.norm(local)
    elif name in BALL_JOINTS:
        kind = "ball"
    return _Joint(model.names[j], kind, axis, oMi.translation.copy())


def _side(model: pin.Model, joint: int, stop: set[int]) -> list[int]:
    """Return the joints from ``joint`` towards the root, up to (without) one of ``stop``."""
    path = []
    while joint not in stop and joint != 0:
        path.append(joint)
        joint = model.parents[joint]
    return path


def _ancestors(model: pin.Model, joint: int) -> set[int]:
    """Return ``joint`` and every joint above it, the universe (0) included."""
    seen = {0}
    while joint:
        seen.add(joint)
        joint = model.parents[joint]
    return seen


def _height_gap(
    y: np.ndarray, end: _Joint | None, loop_type: str, frames: tuple[pin.SE3, pin.SE3]
) -> tuple[float, str] | None:
    """Return (gap, what differs) for one axis ``y``; ``end`` sits before ``frames[0]``.

    Args:
        y: unit common axis, shape (3,), world.
        end: the one joint that is not planar about ``y`` (the last before the
            first frame's link), or None.
        loop_type: "fixed" or "spherical".
        frames: placements of the two loop frames (the end's side first), world.
    """
    oMe, oMo = frames
    if end is None:
        gap = float(y @ (oMe.translation - oMo.translation))
        text = f"the frames' heights along it differ by {abs(gap):.6g} m"
        if loop_type == "fixed":
            ye, yo = oMe.rotation.T @ y, oMo.rotation.T @ y
            angle = math.atan2(np.linalg.norm(np.cross(ye, yo)), float(ye @ yo))
            if angle > abs(gap):
                return angle, f"it points {angle:.6g} rad apart in the two frames"
        return abs(gap), text
    c = end.point
    if loop_type == "fixed":
        # The centre (a point of the axis) as the weld carries it to the other side.
        c_other = oMo.act(oMe.actInv(c))
        gap = float(y @ (c - c_other))
        out = (
            abs(gap),
            f"the centre of joint {end.name!r} is at height {float(y @ c):.6g} m along it on "
            f"its side and {float(y @ c_other):.6g} m through the weld",
        )
        if end.kind == "revolute":
            s_other = oMo.rotation @ oMe.rotation.T @ end.axis
            a1 = math.acos(np.clip(float(y @ end.axis), -1.0, 1.0))
            a2 = math.acos(np.clip(float(y @ s_other), -1.0, 1.0))
            if abs(a1 - a2) > out[0]:
                return abs(a1 - a2), (
                    f"the angle between it and the axis of joint {end.name!r} is {a1:.6g} rad "
                    f"on its side and {a2:.6g} rad through the weld"
                )
        return out
    d = oMe.translation - c
    if end.kind == "ball":
        m, w = float(y @ c), float(np.linalg.norm(d))
    else:
        s = end.axis
        cos = float(y @ s)
        m = float(y @ c) + cos * float(s @ d)
        w = float(np.linalg.norm(d - float(s @ d) * s)) * math.sqrt(max(0.0, 1.0 - cos * cos))
    h = float(y @ oMo.translation)
    return max(0.0, abs(h - m) - w), (
        f"the height of one frame along it stays in [{m - w:.6g}, {m + w:.6g}] m (joint "
        f"{end.name!r}), that of the other at {h:.6g} m"
    )


def prove_unclosable(
    model: pin.Model, data: pin.Data, layer: ConstraintLayer, *, gap_min: float = GAP_MIN
) -> str | None:
    """Return why some loop of ``layer`` can never close, in one line, or None.

    See the module docstring for the argument.

    Args:
        model: the Pinocchio model with the loop frames.
        data: its data (overwritten: the kinematics at the neutral configuration;
            the caller's, as a full ``model.createData()`` of a long chain takes
            nv^3 memory).
        layer: the declared loops.
        gap_min: smallest difference [m or rad] reported (at least :data:`GAP_MIN`).

    Returns:
        ``"loop 'name' (type) cannot close in any configuration: ..."`` for the
        first loop proven open, else None (no proof found; not a proof of closure).
    """
    q = pin.neutral(model)
    pin.framesForwardKinematics(model, data, q)
    for spec, (fp, fs) in zip(layer.loops, layer.frame_ids, strict=True):
        if spec.type not in ("fixed", "spherical"):
            continue
        jp, js = model.frames[fp].parentJoint, model.frames[fs].parentJoint
        common = _ancestors(model, jp) & _ancestors(model, js)
        sides = [
            [_joint(model, data, q, j) for j in _side(model, jp, common)],
            [_joint(model, data, q, j) for j in _side(model, js, common)],
        ]
        joints = sides[0] + sides[1]
        axes: list[np.ndarray] = []
        for jt in joints:
            if jt.kind == "revolute" and not any(
                np.linalg.norm(np.cross(jt.axis, a)) <= PARALLEL_TOL for a in axes
            ):
                axes.append(jt.axis)
        for y in axes:
            for first in (0, 1):
                side, frames = sides[first], (data.oMf[(fp, fs)[first]], data.oMf[(fs, fp)[first]])
                others = [jt for jt in joints if not jt.planar(y)]
                if not others:
                    if first == 1:  # no end joint: one look suffices
                        continue
                    end = None
                elif len(others) == 1 and side and others[0] is side[0]:
                    end = side[0]
                    if end.kind not in ("revolute", "ball"):
                        continue
                else:
                    continue
                gap, what = _height_gap(y, end, spec.type, frames)
                if gap > max(gap_min, GAP_MIN):
                    planar = ", ".join(jt.name for jt in joints if jt is not end)
                    return (
                        f"loop {spec.name!r} ({spec.type}) cannot close in any configuration: "
                        f"joints {planar} turn about (or slide across) the axis "
                        f"[{' '.join(f'{round(v, 4) + 0.0:g}' for v in y)}] (world, neutral "
                        f"configuration), so {what}"
                    )
    return None
