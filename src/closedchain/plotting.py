"""Time plots of a Trajectory with matplotlib (headless: no pyplot, no GUI backend).

:func:`plot_trajectory` draws three panels against time: the independent
coordinates, the constraint residuals (log scale), and the energy drift. The
figure is a plain :class:`matplotlib.figure.Figure`, so building and saving it
changes no global matplotlib state (``fig.savefig(path)`` renders with Agg).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from .exceptions import ClosedChainError
from .trajectory import Trajectory

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .mechanism import Mechanism

logger = logging.getLogger(__name__)

#: Residuals at or below this are drawn at this floor on the log axis.
RESIDUAL_FLOOR = 1e-17

#: Figure size [in] and resolution [dots/in] of :func:`plot_trajectory`.
FIGSIZE = (8.0, 7.5)
DPI = 100


def _angle_series(mech: Mechanism | None, trajectory: Trajectory, idx_v: np.ndarray, names):
    """Yield (label, values) of coordinates given by velocity index."""
    q = np.asarray(trajectory.q, dtype=float)
    if mech is None:
        for i, name in zip(idx_v, names, strict=True):
            yield name, q[:, i]
        return
    model = mech.model
    for i in idx_v:
        jm = next(
            model.joints[j]
            for j in range(1, model.njoints)
            if model.joints[j].idx_v <= i < model.joints[j].idx_v + model.joints[j].nv
        )
        name = mech.coordinate_names[i]
        unit = "m" if jm.shortname().removeprefix("JointModel").startswith("P") else "rad"
        if jm.nq == 2 and jm.nv == 1:  # continuous joint: (cos, sin)
            c, s = q[:, jm.idx_q], q[:, jm.idx_q + 1]
            yield f"{name} [rad]", np.unwrap(np.arctan2(s, c))
        elif jm.nq == jm.nv:
            yield f"{name} [{unit}]", q[:, jm.idx_q + (i - jm.idx_v)]
        else:  # spherical / free-flyer: no angle per velocity coordinate
            logger.warning("coordinate %s has no scalar position; not plotted", name)


def _coordinates(mech: Mechanism | None, trajectory: Trajectory, coordinates):
    """Return (velocity indices, names) of the coordinates to plot."""
    info = trajectory.info or {}
    nq = trajectory.q.shape[1]
    if mech is not None:
        names = list(mech.coordinate_names)
        if coordinates is None:
            idx = np.asarray(mech.independent_idx_v, dtype=int)
        else:
            idx = mech.coordinate_indices(coordinates)
        return idx, [names[i] for i in idx]
    names = info.get("coordinate_names") or [f"q{i}" for i in range(nq)]
    if len(names) != nq:
        raise ClosedChainError(
            f"trajectory info names {len(names)} coordinates but q has {nq} columns"
        )
    wanted = coordinates if coordinates is not None else info.get("independent") or names
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
            idx.append(int(w))
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
    3. the energy drift E(t) - E(0) [J].

    Args:
        trajectory: the motion: t shape (N,), q shape (N, nq), residuals and
            energy shape (N,).
        mech: the mechanism; gives the independent coordinates, their names
            and joint types. Without it they come from ``trajectory.info``
            (``independent``, ``coordinate_names``) when present, else every
            column of q is drawn.
        coordinates: joint names or velocity indices to draw instead of the
            independent coordinates.
        title: figure title (default: mechanism and run configuration from
            ``trajectory.info``).

    Returns:
        The figure (``fig.savefig("out.png")`` writes it; no display needed).

    Raises:
        ClosedChainError: a coordinate name is unknown, or the info does not
            match the trajectory.
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

    for values, label in (
        (trajectory.constraint_residual, r"max $|\phi(q)|$ [m, rad]"),
        (trajectory.velocity_residual, r"max $|J(q)\,v|$ [m/s, rad/s]"),
    ):
        values = np.maximum(np.abs(np.asarray(values, dtype=float)), RESIDUAL_FLOOR)
        ax_res.semilogy(t, values, label=label)
    ax_res.set_ylabel("constraint residuals")
    ax_res.legend(loc="best", fontsize="small")
    ax_res.grid(True, which="major", alpha=0.3)

    energy = np.asarray(trajectory.energy, dtype=float)
    drift = energy - energy[0] if energy.size else energy
    ax_e.plot(t, drift, color="C3")
    ax_e.set_ylabel("energy drift\n$E(t) - E(0)$ [J]")
    ax_e.set_xlabel("time [s]")
    ax_e.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3))
    for ax in (ax_q, ax_e):
        ax.grid(True, alpha=0.3)

    if title is None:
        info = trajectory.info or {}
        parts = [
            str(info[k])
            for k in ("mechanism", "method", "integrator", "stabilization")
            if info.get(k)
        ]
        title = " / ".join(parts) if parts else None
    if title:
        fig.suptitle(title)
    return fig
