r"""Workspace and singularity pictures, from the model alone: where J loses rank, where
the motors stop determining the motion.

Planar 4-bar (one revolute loop, three revolute joints, two of them on the
ground): the link lengths are measured on the assembled model (joint origins
and the loop point at ``q_ref``), classified by Grashof's rule with s, l the
shortest and longest links and p, q the others,

.. math::

    s + l < p + q: \text{Grashof}, \quad s + l = p + q: \text{change point}, \quad
    s + l > p + q: \text{non-Grashof (triple rocker)},

(Grashof: crank-rocker when the input link is the shortest, double-crank when
the ground is, double-rocker otherwise). The crank range follows in closed form
(the distance r from the crank tip to the rocker pivot must lie in [|b - c|,
b + c]) and is checked by assembling the model at each crank angle of a sweep.

Any other mechanism: the smallest singular values over a grid of two *output*
coordinates (the third and following held at their reference value) of

* J_D, the constraint Jacobian's columns of the non-actuated coordinates (the
  actuated partition): zero on *parallel* (type II) singularities, where the
  actuators no longer determine the motion;
* the columns of the non-output coordinates: zero on *serial* (type I)
  singularities, where the output no longer determines the actuators.

Output coordinates default to the joints from the ground to the link that every loop
closes on, when there is one (a parallel mechanism's platform: for
``models/agile_eye.urdf`` its yaw, pitch, roll): the map is then over the task space,
and the serial map says where the platform no longer determines the actuators.
Without such a link (a five-bar: its loop joins two distal links) they are the
independent coordinates (``Mechanism.independent_idx_v``, the actuated ones when they
suffice): the map is over the coordinates that the motion is given in, where the
assembly with them held is unique on a branch. (Before, the fallback was the first
non-actuated joints in tree order: a five-bar's two passive distal joints.) When the
outputs are the actuated coordinates the serial map is the parallel one.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pinocchio as pin

from ._io import save_figure
from ._locking import exclusive
from .exceptions import AssemblyError, ClosedChainError, InvalidArgumentError
from .kinematics import actuation_sigma_min, assemble, compute_jacobian
from .mechanism import COORDINATE_BOUND, Mechanism
from .pindata import new_data

__all__ = [
    "FourBarAnalysis",
    "SingularityMap",
    "analyze_fourbar",
    "default_outputs",
    "plot_workspace",
    "singularity_map",
]

logger = logging.getLogger(__name__)

#: Crank angles of the 4-bar sweep.
SWEEP_POINTS = 721
#: Relative tolerance of the Grashof equality (change point) [-].
GRASHOF_RTOL = 1e-9
#: Half-width of the singularity map around the reference outputs [rad].
SPAN = 1.5
#: Grid points per axis of the singularity map.
MAP_POINTS = 41
#: Largest sweep (points) and map (points per axis: points^2 assemblies) accepted,
#: so that a typo cannot start hours of work.
MAX_SWEEP_POINTS = 100_000
MAX_MAP_POINTS = 201


def _check_points(points, largest: int) -> int:
    if isinstance(points, bool) or not isinstance(points, int | np.integer):
        raise InvalidArgumentError(f"points must be an integer, got {points!r}")
    if not 2 <= points <= largest:
        raise InvalidArgumentError(f"points must be in [2, {largest}], got {points}")
    return int(points)


@dataclass
class FourBarAnalysis:
    """Link lengths [m], Grashof class, crank range and the sweep check."""

    ground: float
    crank: float
    coupler: float
    rocker: float
    grashof: str
    theta: np.ndarray = field(repr=False)
    closed_form: np.ndarray = field(repr=False)
    assembled: np.ndarray = field(repr=False)
    cond: np.ndarray = field(repr=False)
    crank_joint: str = ""

    @property
    def agreement(self) -> float:
        """Fraction of sweep angles where the closed form and the assembly agree."""
        return float(np.mean(self.closed_form == self.assembled))


def _is_planar_fourbar(mech: Mechanism) -> bool:
    m = mech.model
    return (
        len(mech.declared.loops) == 1
        and mech.declared.loops[0].type == "revolute"
        and m.njoints == 4
        and mech.nv == 3
        and mech.mobility == 1
        and sum(1 for j in range(1, 4) if m.parents[j] == 0) == 2
    )


@exclusive
def analyze_fourbar(mech: Mechanism, *, points: int = SWEEP_POINTS) -> FourBarAnalysis:
    """Grashof class and crank range of a planar 4-bar, measured on the model."""
    if not _is_planar_fourbar(mech):
        raise ClosedChainError(
            f"{mech.name} is not a planar 4-bar (one revolute loop, three "
            "revolute joints, two on the ground)"
        )
    points = _check_points(points, MAX_SWEEP_POINTS)
    model, data = mech.model, new_data(mech.model)
    pin.forwardKinematics(model, data, mech.q_ref)
    pin.updateFramePlacements(model, data)
    ground = [j for j in range(1, 4) if model.parents[j] == 0]
    b_joint = next(j for j in range(1, 4) if model.parents[j] != 0)
    a_joint = model.parents[b_joint]
    c_joint = next(j for j in ground if j != a_joint)
    o = {j: data.oMi[j].translation for j in range(1, 4)}
    p = data.oMf[mech.declared.frame_ids[0][0]].translation
    d = float(np.linalg.norm(o[a_joint] - o[c_joint]))
    link1 = float(np.linalg.norm(o[b_joint] - o[a_joint]))
    coupler = float(np.linalg.norm(p - o[b_joint]))
    link3 = float(np.linalg.norm(p - o[c_joint]))
    crank_name = mech.actuated_joints[0] if mech.actuated_joints else model.names[a_joint]
    crank_j = model.getJointId(crank_name)
    crank, rocker = (link1, link3) if crank_j == a_joint else (link3, link1)
    pivot, other = (a_joint, c_joint) if crank_j == a_joint else (c_joint, a_joint)
    lengths = sorted([d, crank, coupler, rocker])
    s, l_ = lengths[0], lengths[-1]
    pq = lengths[1] + lengths[2]
    if abs(s + l_ - pq) <= GRASHOF_RTOL * pq:
        cls = "change point"
    elif s + l_ > pq:
        cls = "non-Grashof (triple rocker)"
    elif math.isclose(s, crank):
        cls = "Grashof crank-rocker"
    elif math.isclose(s, d):
        cls = "Grashof double-crank"
    else:
        cls = "Grashof double-rocker"
    # Closed form: the crank tip at distance r from the other pivot must reach the coupler-
    # rocker dyad: |coupler - rocker| <= r <= coupler + rocker. Angles are the crank joint's
    # coordinate; the ground direction is measured at q_ref.
    idx = mech.coordinate_indices([crank_name])[0]
    theta = np.linspace(-math.pi, math.pi, points)
    closed, assembled, cond = [], [], []
    q = mech.q_ref.copy()
    tip0 = o[b_joint] if crank_j == a_joint else p
    axis = data.oMi[crank_j].rotation @ _joint_axis(model, crank_j)
    for th in theta:
        rot = pin.exp3(axis * (th - mech.q_ref[idx]))
        tip = o[pivot] + rot @ (tip0 - o[pivot])
        r = float(np.linalg.norm(tip - o[other]))
        closed.append(abs(coupler - rocker) - 1e-12 <= r <= coupler + rocker + 1e-12)
        guess = q.copy()
        guess[idx] = th
        try:
            q = assemble(mech, guess, fixed=[crank_name])
            assembled.append(True)
            cond.append(float(np.linalg.cond(compute_jacobian(mech, q))))
        except AssemblyError:
            assembled.append(False)
            cond.append(math.nan)
    return FourBarAnalysis(
        d,
        crank,
        coupler,
        rocker,
        cls,
        theta,
        np.array(closed),
        np.array(assembled),
        np.array(cond),
        crank_name,
    )


def _joint_axis(model: pin.Model, j: int) -> np.ndarray:
    """Axis of revolute joint j in its own frame, shape (3,)."""
    jm = model.joints[j]
    short = jm.shortname()
    if "Unaligned" in short:
        return np.array(jm.extract().axis)
    if short[-1] in "XYZ":
        return np.eye(3)["XYZ".index(short[-1])]
    raise ClosedChainError(f"joint {model.names[j]!r} ({short}) is not a revolute joint")


@dataclass
class SingularityMap:
    """Smallest singular values over a grid of two output coordinates [rad or m]."""

    outputs: tuple[str, ...]
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    parallel: np.ndarray = field(repr=False)  # sigma_min of J_D (actuated partition)
    serial: np.ndarray = field(repr=False)  # sigma_min of the non-output columns


def default_outputs(mech: Mechanism) -> tuple[str, ...]:
    """The output (platform) coordinates: the joints from the ground to the link that every
    loop closes on (e.g. a parallel mechanism's platform), first ``mobility`` of them; without
    such a link, the independent coordinates (``Mechanism.independent_idx_v``)."""
    model = mech.model
    common = None
    for spec in mech.declared.loops:
        links = {spec.predecessor, spec.successor}
        common = links if common is None else common & links
    if common and len(common) == 1:
        link = next(iter(common))
        j = model.frames[model.getFrameId(link)].parentJoint
        chain = []
        while j > 0:
            if model.names[j] not in mech.actuated_joints:
                chain.append(model.names[j])
            j = model.parents[j]
        chain.reverse()
        if len(chain) >= mech.mobility:
            return tuple(chain[: mech.mobility])
    return tuple(mech.coordinate_names[i] for i in mech.independent_idx_v)


@exclusive
def singularity_map(
    mech: Mechanism,
    *,
    outputs: tuple[str, ...] | None = None,
    points: int = MAP_POINTS,
    span: float = SPAN,
) -> SingularityMap:
    """sigma_min of J_D (parallel, type II) and of the output map (serial, type I) over the
    first two output coordinates, each within +- span [rad] of its reference, the others held."""
    points = _check_points(points, MAX_MAP_POINTS)
    if not (math.isfinite(span) and 0 < span <= COORDINATE_BOUND):
        raise InvalidArgumentError(
            f"span must be a positive number [rad] of at most {COORDINATE_BOUND:g} "
            f"(closedchain.mechanism.COORDINATE_BOUND), got {span}"
        )
    outputs = tuple(outputs or default_outputs(mech))
    repeated = sorted({name for name in outputs if outputs.count(name) > 1})
    if repeated:
        raise InvalidArgumentError(
            f"outputs names {', '.join(map(str, repeated))} more than once; valid: distinct joints"
        )
    if len(outputs) < 2:
        raise ClosedChainError(
            f"a singularity map needs two output coordinates, got {outputs}; valid: two of "
            + ", ".join(mech.coordinate_names)
        )
    out_idx = mech.coordinate_indices(list(outputs))
    x0, y0 = mech.q_ref[out_idx[0]], mech.q_ref[out_idx[1]]
    x = np.linspace(x0 - span, x0 + span, points)
    y = np.linspace(y0 - span, y0 + span, points)
    par = np.full((points, points), np.nan)
    ser = np.full((points, points), np.nan)
    for i, yi in enumerate(y):
        q = mech.q_ref.copy()
        for k, xk in enumerate(x):
            guess = q.copy()
            guess[out_idx[0]], guess[out_idx[1]] = xk, yi
            try:
                q = assemble(mech, guess, fixed=list(outputs))
            except AssemblyError:
                continue
            par[i, k], ser[i, k] = actuation_sigma_min(
                compute_jacobian(mech, q), mech.actuated_idx_v, output_idx_v=out_idx
            )
    return SingularityMap(outputs, x, y, par, ser)


def plot_workspace(
    mech: Mechanism,
    path: str | Path,
    *,
    points: int | None = None,
    outputs: tuple[str, ...] | None = None,
    span: float = SPAN,
) -> str:
    """Write the workspace picture of ``mech`` and return a one-line summary."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if _is_planar_fourbar(mech):
        a = analyze_fourbar(mech, points=SWEEP_POINTS if points is None else points)
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        deg = np.degrees(a.theta)
        ax[0].fill_between(
            deg,
            0,
            a.closed_form.astype(float),
            step="mid",
            alpha=0.3,
            label="reachable (closed form)",
        )
        ax[0].plot(deg, a.assembled.astype(float), "k.", ms=2, label="assembled model")
        ax[0].set_ylabel("crank angle reachable")
        ax[0].legend(fontsize=8)
        ax[0].set_title(
            f"{mech.name}: {a.grashof}; ground {a.ground:.3g}, crank {a.crank:.3g},"
            f" coupler {a.coupler:.3g}, rocker {a.rocker:.3g} m"
        )
        ax[1].semilogy(deg, a.cond)
        ax[1].set_ylabel("cond(J)  (toggle / change point: peaks)")
        ax[1].set_xlabel(f"{a.crank_joint} [deg]")
        for axis in ax:
            axis.grid(True, alpha=0.3)
        fig.tight_layout()
        save_figure(fig, path, dpi=110)
        plt.close(fig)
        return (
            f"{a.grashof}: ground {a.ground:.4g}, crank {a.crank:.4g}, coupler "
            f"{a.coupler:.4g}, rocker {a.rocker:.4g} m; crank range "
            f"{a.closed_form.mean() * 360:.0f} deg of 360; closed form and assembly agree "
            f"at {a.agreement:.1%} of {len(a.theta)} angles"
        )
    m = singularity_map(
        mech, outputs=outputs, points=MAP_POINTS if points is None else points, span=span
    )
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.6))
    for axis, data, what in (
        (ax[0], m.parallel, "parallel / type II: sigma_min(J_D)"),
        (ax[1], m.serial, "serial / type I: sigma_min(output map)"),
    ):
        im = axis.pcolormesh(m.x, m.y, np.log10(data), shading="auto", cmap="viridis")
        axis.contour(m.x, m.y, np.log10(data), levels=[-2], colors="r", linewidths=1)
        fig.colorbar(im, ax=axis, label="log10 sigma_min")
        axis.set_title(what, fontsize=10)
        axis.set_xlabel(f"{m.outputs[0]} [rad]")
        axis.set_ylabel(f"{m.outputs[1]} [rad]")
    fig.suptitle(f"{mech.name}: outputs {', '.join(m.outputs)} (others at q_ref); red: 1e-2")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    same = set(m.outputs) == {mech.coordinate_names[i] for i in mech.actuated_idx_v}
    return (
        f"singularity map over {m.outputs[0]}, {m.outputs[1]}: min sigma parallel "
        f"{np.nanmin(m.parallel):.2e}, serial {np.nanmin(m.serial):.2e}"
        + (" (the outputs are the actuated coordinates: serial = parallel)" if same else "")
    )
