"""Framing: trajectory checks, resampling, body placements, swept volume, camera."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from ..exceptions import ClosedChainError, format_upper_bound
from ..trajectory import Trajectory

if TYPE_CHECKING:
    from ..mechanism import Mechanism

from ..pindata import new_data
from .settings import (
    DEFAULT_SETTINGS,
    FRAME_EPS,
    MIN_SCENE_RADIUS,
    TIME_EPS,
    AnimationSettings,
    MeshData,
)

logger = logging.getLogger(__name__)


def check_trajectory(mech: Mechanism, trajectory: Trajectory) -> None:
    """Raise ClosedChainError unless the trajectory fits the mechanism and its times increase.

    Fits: q has nq columns, and the trajectory was simulated on this mechanism
    (:meth:`~closedchain.trajectory.Trajectory.check_mechanism`).
    """
    t = np.asarray(trajectory.t, dtype=float)
    q = np.asarray(trajectory.q, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ClosedChainError(f"trajectory.t has shape {t.shape}, expected (N,) with N >= 1")
    if q.shape != (t.size, mech.nq):
        raise ClosedChainError(
            f"trajectory.q has shape {q.shape}, expected ({t.size}, {mech.nq}) for {mech.name}"
        )
    trajectory.check_mechanism(mech)
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ClosedChainError("trajectory.t or trajectory.q contains non-finite values")
    if np.any(np.diff(t) <= TIME_EPS):
        k = int(np.argmax(np.diff(t) <= TIME_EPS))
        raise ClosedChainError(
            f"trajectory times must increase: t[{k}] = {t[k]!r}, t[{k + 1}] = {t[k + 1]!r}"
        )


def resample(
    mech: Mechanism, trajectory: Trajectory, fps: float, *, max_keyframes: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Resample a trajectory at the display rate.

    Keyframes fall at k / fps for k = 0, 1, ... from the first sample, plus one
    at the last sample if it lies between two frames, so the animation lasts
    exactly as long as the trajectory. Configurations between samples are
    interpolated on the configuration Lie group (``pin.interpolate``); a
    keyframe that falls on a sample takes that sample exactly.

    Args:
        mech: the mechanism.
        trajectory: times shape (N,) [s] and configurations shape (N, nq).
        fps: display rate [frames/s].
        max_keyframes: largest K accepted (None: no limit); more is refused
            before any keyframe is computed.

    Returns:
        (times [s] from 0, shape (K,); configurations, shape (K, nq)).

    Raises:
        ClosedChainError: the trajectory does not fit the mechanism, fps is not
            positive, or the keyframes would be more than ``max_keyframes``.
    """
    check_trajectory(mech, trajectory)
    if not (math.isfinite(fps) and fps > 0):
        raise ClosedChainError(f"fps must be a positive number of frames per second, got {fps}")
    t = np.asarray(trajectory.t, dtype=float) - float(trajectory.t[0])
    q = np.asarray(trajectory.q, dtype=float)
    T = float(t[-1])
    frames = T * fps * (1.0 + FRAME_EPS)  # a float: inf when it overflows
    if max_keyframes is not None and not frames + 1 <= max_keyframes:
        raise ClosedChainError(
            f"{fps:g} fps over {T:g} s is {frames + 1:.3g} keyframes, more than "
            f"AnimationSettings.max_keyframes = {max_keyframes:.3g}; valid fps: "
            f"(0, {format_upper_bound((max_keyframes - 1) / T)}]"
        )
    n = int(math.floor(frames)) + 1
    times = np.arange(n, dtype=float) / fps
    if T - times[-1] > TIME_EPS:
        times = np.append(times, T)
    if t.size == 1:
        return times[:1], q[:1].copy()
    idx = np.clip(np.searchsorted(t, times, side="right") - 1, 0, t.size - 2)
    alpha = np.clip((times - t[idx]) / (t[idx + 1] - t[idx]), 0.0, 1.0)
    out = np.empty((times.size, mech.nq))
    for k, (i, a) in enumerate(zip(idx, alpha, strict=True)):
        if a == 0.0:
            out[k] = q[i]
        elif a == 1.0:
            out[k] = q[i + 1]
        else:
            out[k] = pin.interpolate(mech.model, q[i], q[i + 1], float(a))
    return times, out


def body_placements(mech: Mechanism, bodies, qs: np.ndarray) -> np.ndarray:
    """Return the world placements of bodies at configurations.

    Args:
        mech: the mechanism.
        bodies: sequence of :class:`Body`.
        qs: configurations, shape (K, nq).

    Returns:
        Homogeneous placements oMf, shape (K, nb, 4, 4) [m].
    """
    data = new_data(mech.model)
    out = np.empty((len(qs), len(bodies), 4, 4))
    for k, q in enumerate(qs):
        pin.framesForwardKinematics(mech.model, data, q)
        for b, body in enumerate(bodies):
            out[k, b] = data.oMf[body.frame_id].homogeneous
    return out


def _local_points(kind: str, dims: tuple[float, ...], mesh: MeshData | None) -> np.ndarray:
    """Return corners of a shape's bounding box in its own frame, shape (8, 3) [m]."""
    if kind == "box":
        h = 0.5 * np.array(dims)
    elif kind == "cylinder":
        h = np.array([dims[0], dims[0], 0.5 * dims[1]])
    elif kind == "sphere":
        h = np.full(3, dims[0])
    else:
        lo, hi = mesh.lower * np.array(dims), mesh.upper * np.array(dims)
        return np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return signs * h


def _swept_points(bodies, visuals, markers, placements, sizes, settings) -> np.ndarray:
    """World points bounding the visuals over sampled keyframes, shape (P, 3) [m]."""
    index = {b.link: i for i, b in enumerate(bodies)}
    K = placements.shape[0]
    ks = np.unique(np.linspace(0, K - 1, min(K, settings.max_bound_samples)).astype(int))
    local: list[tuple[int, np.ndarray]] = []
    for v in visuals:
        if v.link in index:
            pts = _local_points(v.kind, v.dims, v.mesh_data)
            pts = (v.origin[:3, :3] @ pts.T).T + v.origin[:3, 3]
            local.append((index[v.link], pts))
    for m in markers:
        if m.link in index:
            pts = _local_points("sphere", (sizes[(m.kind, m.name)],), None)
            local.append((index[m.link], pts + m.origin[:3, 3]))
    if not local:
        return placements[ks][:, :, :3, 3].reshape(-1, 3)
    out = []
    for b, pts in local:
        M = placements[ks, b]  # (k, 4, 4)
        out.append(np.einsum("kij,pj->kpi", M[:, :3, :3], pts) + M[:, None, :3, 3])
    return np.concatenate([o.reshape(-1, 3) for o in out])


def _bounds(points: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = points.min(axis=0), points.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.max(np.linalg.norm(points - center, axis=1)))
    return center, max(radius, MIN_SCENE_RADIUS)


def frame_camera(points: np.ndarray, settings: AnimationSettings = DEFAULT_SETTINGS):
    """Place the camera so that it frames the given world points.

    The target is the centre of the points' bounding box. The camera looks
    along the principal axis of least extent of the points, which shows the
    most of them (a planar linkage face-on), leaning by ``settings.camera_tilt``
    towards ``settings.view_direction``; when no axis is clearly least
    (smallest extent above ``settings.axis_ratio`` times the middle one) it
    looks along ``view_direction``. The distance makes the bounding sphere fill
    the vertical field of view, times ``settings.camera_margin``.

    Args:
        points: world points [m], shape (P, 3).
        settings: camera settings.

    Returns:
        (camera position, target, bounding-sphere radius): shapes (3,), (3,) [m], float [m].
    """
    center, radius = _bounds(points)
    d0 = np.asarray(settings.view_direction, dtype=float)
    d0 = d0 / np.linalg.norm(d0)
    _, s, Vt = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)
    direction = d0
    if s.size == 3 and s[1] > 0 and s[2] < settings.axis_ratio * s[1]:
        n = Vt[2] if Vt[2] @ d0 >= 0 else -Vt[2]
        lean = d0 - (d0 @ n) * n
        direction = n + settings.camera_tilt * lean
        direction = direction / np.linalg.norm(direction)
    distance = settings.camera_margin * radius / math.sin(math.radians(settings.camera_fov) / 2)
    return center + distance * direction, center, radius


def _nice_step(x: float) -> float:
    """Return the number of the form {1, 2, 5} x 10^k closest (in log) to x > 0."""
    k = math.floor(math.log10(x))
    candidates = [m * 10.0**e for e in (k, k + 1) for m in (1.0, 2.0, 5.0)]
    return min(candidates, key=lambda c: abs(math.log(c / x)))


# -- recording meshcat commands ------------------------------------------------
