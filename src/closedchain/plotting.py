"""Time plots of a Trajectory with matplotlib (headless: no pyplot, no GUI backend).

:func:`plot_trajectory` draws three panels against time: the independent
coordinates, the constraint residuals (log scale), and the energy drift (the energy
balance for a run driven by tau). The
figure is a plain :class:`matplotlib.figure.Figure`, so building and saving it
changes no global matplotlib state (``fig.savefig(path)`` renders with Agg).
:func:`coordinate_series` gives the scalar position of a velocity coordinate
(the angle of a continuous joint, not its cosine); the command line reports
final coordinates with it too.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from .exceptions import ClosedChainError
from .trajectory import Trajectory

__all__ = [
    "coordinate_series",
    "image_formats",
    "plot_trajectory",
]

if TYPE_CHECKING:
    import pinocchio as pin
    from matplotlib.figure import Figure

    from .mechanism import Mechanism

logger = logging.getLogger(__name__)

#: Residuals at or below this are drawn at this floor on the log axis.
RESIDUAL_FLOOR = 1e-17

#: Figure size [in] and resolution [dots/in] of :func:`plot_trajectory`.
FIGSIZE = (8.0, 7.5)
DPI = 100

#: Below this norm [-] of a quaternion's vector part, its rotation vector is
#: taken from the first-order expansion (theta / sin(theta / 2) -> 2 / w).
QUATERNION_SMALL_ANGLE = 1e-12


def image_formats() -> tuple[str, ...]:
    """Return the file suffixes (without the dot) matplotlib can save a figure as."""
    from matplotlib.backend_bases import FigureCanvasBase

    return tuple(sorted(FigureCanvasBase.get_supported_filetypes()))


def _joint_of(model: pin.Model, idx_v: int):
    """Return (joint model, offset of ``idx_v`` in the joint's velocity) of a velocity index."""
    for j in range(1, model.njoints):
        jm = model.joints[j]
        if jm.idx_v <= idx_v < jm.idx_v + jm.nv:
            return jm, idx_v - jm.idx_v
    raise ClosedChainError(f"velocity index {idx_v} out of range 0..{model.nv - 1}")


def _rotation_vector(quat: np.ndarray) -> np.ndarray:
    r"""Return log3 of unit quaternions (x, y, z, w), shape (..., 4) -> (..., 3) [rad].

    .. math:: \theta u = 2 \operatorname{atan2}(|\mathbf{v}|, w)\,\mathbf{v} / |\mathbf{v}|

    with the sign of (v, w) chosen so that w >= 0 (theta in [0, pi]).
    """
    sign = np.where(quat[..., 3:4] < 0.0, -1.0, 1.0)
    vec, w = sign * quat[..., :3], sign[..., 0] * quat[..., 3]
    s = np.linalg.norm(vec, axis=-1)
    small = s < QUATERNION_SMALL_ANGLE
    factor = np.where(
        small, 2.0 / np.where(small, w, 1.0), 2.0 * np.arctan2(s, w) / np.where(small, 1.0, s)
    )
    return factor[..., None] * vec


def _coordinate_unit(model: pin.Model, idx_v: int) -> str:
    """Return the unit of a velocity coordinate's position: ``"m"`` or ``"rad"``."""
    jm, k = _joint_of(model, idx_v)
    kind = jm.shortname().removeprefix("JointModel")
    if kind.startswith(("P", "Translation")):
        return "m"
    if kind == "Planar":
        return "m" if k < 2 else "rad"
    if kind == "FreeFlyer":
        return "m" if k < 3 else "rad"
    return "rad"


def coordinate_series(
    mech_or_model: Mechanism | pin.Model, q, idx_v: int, *, unwrap: bool = False
) -> np.ndarray:
    r"""Return the scalar position of velocity coordinate ``idx_v`` along configurations.

    Velocity coordinates are the ones :attr:`Mechanism.coordinate_names` names.
    Where the joint's configuration is the coordinate itself (nq = nv:
    revolute, prismatic) it is that entry of q. Otherwise:

    - continuous joint, q = (cos theta, sin theta): theta = atan2(sin, cos)
      in (-pi, pi] [rad];
    - planar joint, q = (x, y, cos theta, sin theta): x, y [m] and theta [rad];
    - spherical joint, q a unit quaternion (x, y, z, w): the components of its
      rotation vector log3(R) [rad];
    - free-flyer, q = (p, quaternion): p [m] and the rotation vector [rad].

    Args:
        mech_or_model: the mechanism or its Pinocchio model.
        q: configurations, shape (N, nq) (or one, shape (nq,)).
        idx_v: velocity index of the coordinate, in 0..nv-1.
        unwrap: make the atan2 angles (continuous and planar joints) continuous
            along the configurations (``np.unwrap``) instead of in (-pi, pi].

    Returns:
        The positions, shape (N,) (or a 0-d array for one configuration).

    Raises:
        ClosedChainError: ``idx_v`` is out of range, q has the wrong width, or
            the joint type has no scalar position per velocity coordinate.
    """
    model = getattr(mech_or_model, "model", mech_or_model)
    q = np.asarray(q, dtype=float)
    if q.shape[-1] != model.nq:
        raise ClosedChainError(f"q has {q.shape[-1]} columns, expected nq = {model.nq}")
    jm, k = _joint_of(model, int(idx_v))
    qj = q[..., jm.idx_q : jm.idx_q + jm.nq]
    kind = jm.shortname().removeprefix("JointModel")
    if jm.nq == jm.nv:
        return qj[..., k]
    if jm.nq == 2 and jm.nv == 1:  # continuous joint: (cos, sin)
        theta = np.arctan2(qj[..., 1], qj[..., 0])
        return np.unwrap(theta) if unwrap and theta.ndim else theta
    if kind == "Planar":
        if k < 2:
            return qj[..., k]
        theta = np.arctan2(qj[..., 3], qj[..., 2])
        return np.unwrap(theta) if unwrap and theta.ndim else theta
    if kind == "Spherical":
        return _rotation_vector(qj)[..., k]
    if kind == "FreeFlyer":
        return qj[..., k] if k < 3 else _rotation_vector(qj[..., 3:])[..., k - 3]
    raise ClosedChainError(
        f"velocity coordinate {idx_v} belongs to a {kind} joint, which has no scalar"
        " position per velocity coordinate"
    )


def _angle_series(mech: Mechanism | None, trajectory: Trajectory, idx_v: np.ndarray, names):
    """Yield (label, values) of coordinates given by velocity index."""
    q = np.asarray(trajectory.q, dtype=float)
    if mech is None:  # nq == nv (checked by _coordinates): q holds them directly
        for i, name in zip(idx_v, names, strict=True):
            yield name, q[:, i]
        return
    for i, name in zip(idx_v, names, strict=True):
        try:
            values = coordinate_series(mech, q, int(i), unwrap=True)
        except ClosedChainError:  # e.g. a composite joint
            logger.warning("coordinate %s has no scalar position; not plotted", name)
            continue
        yield f"{name} [{_coordinate_unit(mech.model, int(i))}]", values


def _coordinates(mech: Mechanism | None, trajectory: Trajectory, coordinates):
    """Return (velocity indices, names) of the coordinates to plot."""
    info = trajectory.info
    nq, nv = trajectory.q.shape[1], trajectory.v.shape[1]
    if mech is not None:
        if (nq, nv) != (mech.nq, mech.nv):
            raise ClosedChainError(
                f"trajectory has nq = {nq}, nv = {nv} but mechanism {mech.name!r} has"
                f" nq = {mech.nq}, nv = {mech.nv}"
            )
        trajectory.check_mechanism(mech)
        names = list(mech.coordinate_names)
        if coordinates is None:
            idx = np.asarray(mech.independent_idx_v, dtype=int)
        else:
            idx = mech.coordinate_indices(coordinates)
        return idx, [names[i] for i in idx]
    if nq != nv:
        # Coordinates are velocity coordinates; q holds e.g. (cos, sin) of a
        # continuous joint, so only the joint types can map one to the other.
        raise ClosedChainError(
            f"the trajectory{' of ' + repr(info.mechanism) if info.mechanism else ''}"
            f" has nq = {nq} != nv = {nv}: plotting it needs the mechanism (pass mech=,"
            " or the URDF: closedchain plot TRAJ.npz --urdf FILE)"
        )
    names = info.coordinate_names or info.velocity_names
    names = list(names) if names else [f"q{i}" for i in range(nq)]
    if len(names) != nq:
        raise ClosedChainError(
            f"trajectory info names {len(names)} coordinates but q has {nq} columns"
        )
    wanted = coordinates if coordinates is not None else info.independent or names
    if isinstance(wanted, str):
        wanted = [wanted]
    idx = []
    for w in wanted:
        if isinstance(w, str):
            if w not in names:
                raise ClosedChainError(
                    f"unknown coordinate {w!r}; valid choices: {', '.join(names)}"
                )
            idx.append(names.index(w))
        else:
            i = int(w)
            if not 0 <= i < nv:
                raise ClosedChainError(f"velocity index {i} out of range 0..{nv - 1}")
            idx.append(i)
    return np.asarray(idx, dtype=int), [names[i] for i in idx]


def plot_trajectory(
    trajectory: Trajectory,
    *,
    mech: Mechanism | None = None,
    coordinates=None,
    title: str | None = None,
) -> Figure:
    r"""Return a figure of a trajectory against time.

    Panels, sharing the time axis [s]:

    1. the independent coordinates q_I(t) [rad or m] (or ``coordinates``);
    2. the constraint residual max |phi(q)| and the velocity residual
       max |J(q) v| (log scale; exact zeros drawn at :data:`RESIDUAL_FLOOR`);
    3. the energy drift E(t) - E(0) [J], or, for a run driven by tau (its
       ``trajectory.work`` recorded), the energy balance E(t) - E(0) - W(t), W the
       work of tau: zero for an exact solution whatever drives it.

    Args:
        trajectory: the motion: t shape (N,), q shape (N, nq), residuals and
            energy shape (N,).
        mech: the mechanism; gives the independent coordinates, their names
            and joint types (see :func:`coordinate_series`). Without it they
            come from ``trajectory.info`` (``independent``, ``coordinate_names``)
            when present, else every column of q is drawn; this needs nq = nv
            (no continuous, planar, spherical or free joints), since the
            coordinates are velocity coordinates.
        coordinates: what to draw instead of the independent coordinates: joint
            names (with ``mech``; without it, the names of ``trajectory.info``)
            and integer velocity indices (0..nv-1).
        title: figure title (default: mechanism and run configuration from
            ``trajectory.info``).

    Returns:
        The figure (``fig.savefig("out.png")`` writes it; no display needed).

    Raises:
        ClosedChainError: a coordinate name or index is unknown, the info or
            the mechanism does not match the trajectory (its shape, or it was
            simulated on another mechanism:
            :meth:`~closedchain.trajectory.Trajectory.check_mechanism`), or
            nq != nv and no mechanism is given.
    """
    from matplotlib.figure import Figure

    t = np.asarray(trajectory.t, dtype=float)
    idx, names = _coordinates(mech, trajectory, coordinates)
    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
    ax_q, ax_res, ax_e = fig.subplots(3, 1, sharex=True)

    for label, values in _angle_series(mech, trajectory, idx, names):
        ax_q.plot(t, values, label=label)
    ax_q.set_ylabel("independent coordinates" if coordinates is None else "coordinates")
    if ax_q.lines:
        ax_q.legend(loc="best", fontsize="small")

    if np.asarray(trajectory.lam).ndim == 2 and trajectory.lam.shape[1] == 0:
        # An open chain: no constraint rows, nothing that could drift.
        ax_res.text(
            0.5,
            0.5,
            "no loops: no constraint rows",
            ha="center",
            va="center",
            transform=ax_res.transAxes,
        )
        ax_res.set_yticks([])
    else:
        for values, label in (
            (trajectory.constraint_residual, r"max $|\phi(q)|$ [m, rad]"),
            (trajectory.velocity_residual, r"max $|J(q)\,v|$ [m/s, rad/s]"),
        ):
            values = np.maximum(np.abs(np.asarray(values, dtype=float)), RESIDUAL_FLOOR)
            ax_res.semilogy(t, values, label=label)
        ax_res.legend(loc="best", fontsize="small")
    ax_res.set_ylabel("constraint residuals")
    ax_res.grid(True, which="major", alpha=0.3)

    energy = np.asarray(trajectory.energy, dtype=float)
    drift = energy - energy[0] if energy.size else energy
    if trajectory.work is None:
        ax_e.plot(t, drift, color="C3")
        ax_e.set_ylabel("energy drift\n$E(t) - E(0)$ [J]")
    else:
        ax_e.plot(t, drift - np.asarray(trajectory.work, dtype=float), color="C3")
        ax_e.set_ylabel("energy balance\n" + r"$E - E(0) - \int_0^t \tau \cdot v\,dt$ [J]")
    ax_e.set_xlabel("time [s]")
    ax_e.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3))
    for ax in (ax_q, ax_e):
        ax.grid(True, alpha=0.3)

    if title is None:
        info = trajectory.info
        parts = [
            str(getattr(info, k))
            for k in ("mechanism", "method", "integrator", "stabilization")
            if getattr(info, k)
        ]
        title = " / ".join(parts) if parts else None
    if title:
        fig.suptitle(title)
    return fig
