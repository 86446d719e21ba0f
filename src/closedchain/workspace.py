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

The pictures (:func:`workspace_figure`, :func:`plot_workspace`) draw the mechanism
below the plots as stick figures, the animation's
(:func:`closedchain.visualize.shapes.stick_segments`), at the configurations that tell
the most (the 4-bar's crank-range ends and largest cond(J), a map's most singular grid
points, and the reference), projected on the plane of :func:`view_plane`.
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
    "ViewPlane",
    "plot_workspace",
    "singularity_map",
    "view_plane",
    "workspace_figure",
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
    #: Assembled configuration at each sweep angle, shape (points, nq) (NaN where the
    #: assembly failed).
    q: np.ndarray | None = field(default=None, repr=False)

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
    qs = np.full((points, model.nq), np.nan)
    q = mech.q_ref.copy()
    tip0 = o[b_joint] if crank_j == a_joint else p
    axis = data.oMi[crank_j].rotation @ _joint_axis(model, crank_j)
    for n, th in enumerate(theta):
        rot = pin.exp3(axis * (th - mech.q_ref[idx]))
        tip = o[pivot] + rot @ (tip0 - o[pivot])
        r = float(np.linalg.norm(tip - o[other]))
        closed.append(abs(coupler - rocker) - 1e-12 <= r <= coupler + rocker + 1e-12)
        guess = q.copy()
        guess[idx] = th
        try:
            q = assemble(mech, guess, fixed=[crank_name])
            qs[n] = q
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
        qs,
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
    #: Assembled configuration at each grid point, shape (points, points, nq), indexed
    #: like ``parallel`` (NaN where the assembly failed).
    q: np.ndarray | None = field(default=None, repr=False)


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
    qs = np.full((points, points, mech.model.nq), np.nan)
    for i, yi in enumerate(y):
        q = mech.q_ref.copy()
        for k, xk in enumerate(x):
            guess = q.copy()
            guess[out_idx[0]], guess[out_idx[1]] = xk, yi
            try:
                q = assemble(mech, guess, fixed=list(outputs))
            except AssemblyError:
                continue
            qs[i, k] = q
            par[i, k], ser[i, k] = actuation_sigma_min(
                compute_jacobian(mech, q), mech.actuated_idx_v, output_idx_v=out_idx
            )
    return SingularityMap(outputs, x, y, par, ser, qs)


#: Stick-figure panels of a workspace picture: at most this many configurations.
FIGURE_POSES = 5
#: A joint axis within this angle [rad] of the common axis counts as parallel to it (a
#: planar mechanism), and a view plane whose normal is within it of a world axis is
#: drawn in the other two world axes.
AXIS_TOL = 1e-6
#: Sweep angles closer than this [rad] to one already drawn are not drawn again.
POSE_SEPARATION = math.radians(10.0)
#: Margin around the stick figures, as a fraction of their extent [-].
VIEW_MARGIN = 0.08
#: Colour and marker of each drawn configuration, in order (the maps' markers).
POSE_STYLES = (
    ("tab:red", "o"),
    ("tab:orange", "s"),
    ("magenta", "^"),
    ("tab:cyan", "D"),
    ("tab:brown", "v"),
)
#: Colour of the links fixed to the ground.
GROUND_COLOUR = "0.45"


@dataclass(frozen=True)
class ViewPlane:
    """The plane the stick figures are drawn in.

    Attributes:
        basis: the drawing's horizontal and vertical directions in the world frame,
            orthonormal, shape (2, 3).
        labels: the two axis labels (the world directions) [m].
        how: how the plane was chosen, for the picture.
    """

    basis: np.ndarray
    labels: tuple[str, str]
    how: str


def _direction(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.2f}".replace("-0.00", "0.00") for x in v) + ")"


def view_plane(mech: Mechanism, points: np.ndarray, q: np.ndarray | None = None) -> ViewPlane:
    """Return the plane that shows a mechanism best.

    A planar mechanism (every joint one revolute or prismatic coordinate, the revolute
    axes parallel to a common axis n at ``q``, the prismatic ones normal to it) is drawn
    in the plane normal to n; any other in the plane of the two principal directions of
    ``points`` (the largest two singular values of their centred coordinates). A plane
    whose normal is a world axis (within :data:`AXIS_TOL`) is drawn in the other two world
    axes, in the order x, y, z.

    Args:
        mech: the mechanism.
        points: the points to show (e.g. the stick ends at ``q``), world frame, shape (n, 3) [m].
        q: the configuration the joint axes are read at, shape (nq,) (default ``q_ref``).
    """
    model = mech.model
    q = mech.q_ref if q is None else q
    data = new_data(model)
    pin.forwardKinematics(model, data, q)
    revolute, prismatic, planar = [], [], True
    for j in range(1, model.njoints):
        joint = model.joints[j]
        if joint.nv != 1:
            planar = False
            break
        jdata = joint.createData()
        joint.calc(jdata, q)
        S = np.asarray(jdata.S, dtype=float).ravel()
        rot = data.oMi[j].rotation
        if np.linalg.norm(S[3:]) > 0:
            revolute.append(rot @ S[3:] / np.linalg.norm(S[3:]))
        else:
            prismatic.append(rot @ S[:3] / np.linalg.norm(S[:3]))
    centred = np.asarray(points, dtype=float) - np.mean(points, axis=0)
    principal = np.linalg.svd(centred)[2]
    if planar and revolute:
        n = revolute[0]
        planar = all(np.linalg.norm(np.cross(n, r)) <= AXIS_TOL for r in revolute) and all(
            abs(n @ p) <= AXIS_TOL for p in prismatic
        )
    if planar and revolute:
        how = f"plane normal to the joint axes {_direction(n)}"
        # In-plane: the world axis least along n, then n x it.
        e = np.eye(3)[int(np.argmin(np.abs(n)))]
        u = e - (e @ n) * n
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
    else:
        how = "plane of the principal directions of the joints at q_ref"
        n, u, v = principal[2], principal[0], principal[1]
    k = int(np.argmax(np.abs(n)))
    if abs(n[k]) >= 1.0 - AXIS_TOL:
        i, j = (m for m in range(3) if m != k)
        return ViewPlane(np.eye(3)[[i, j]], (f"world {'xyz'[i]} [m]", f"world {'xyz'[j]} [m]"), how)
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    v = v if v[np.argmax(np.abs(v))] > 0 else -v
    return ViewPlane(np.array([u, v]), (f"{_direction(u)} [m]", f"{_direction(v)} [m]"), how)


def _draw_sticks(ax, mech: Mechanism, sticks, q: np.ndarray, plane: ViewPlane, style, label):
    """Draw the mechanism at q as stick figures; return the 2-D points drawn, shape (n, 2)."""
    from .visualize.settings import STICK_MIN_LENGTH
    from .visualize.shapes import posed_sticks

    colour, marker = style
    P = posed_sticks(mech, q, sticks) @ plane.basis.T  # (n, 2 ends, 2)
    model = mech.model
    ends = []
    for stick, seg in zip(sticks, P, strict=True):
        if stick.length < STICK_MIN_LENGTH:
            continue
        fixed = model.frames[model.getFrameId(stick.link, pin.FrameType.BODY)].parentJoint == 0
        ax.plot(
            seg[:, 0],
            seg[:, 1],
            "-",
            color=GROUND_COLOUR if fixed else colour,
            lw=3.0,
            solid_capstyle="round",
            gid="stick",
        )
        ends.append(seg)
    if not ends:
        return np.zeros((0, 2))
    loops = np.array([seg[1] for stick, seg in zip(sticks, P, strict=True) if stick.loop])
    joints = np.concatenate(ends)
    ax.plot(joints[:, 0], joints[:, 1], "o", ms=5, mfc="white", mec="k", mew=1.0, zorder=3)
    if len(loops):  # the two sides of each cut joint end here: one ring when closed
        ax.plot(loops[:, 0], loops[:, 1], "o", ms=11, mfc="none", mec="k", mew=1.2, zorder=3)
    ax.plot(  # the configuration's marker on the maps, outside the drawing
        0.0, 1.04, marker, color=colour, mec="k", ms=9, transform=ax.transAxes, clip_on=False
    )
    ax.set_title(label, fontsize=9)
    return joints


def _pose_panels(fig, cells, mech: Mechanism, poses) -> ViewPlane:
    """Draw each (label, q) of ``poses`` in its cell with the same view and scale."""
    from .visualize.shapes import posed_sticks, stick_segments

    sticks = stick_segments(mech)
    ends = posed_sticks(mech, mech.q_ref, sticks).reshape(-1, 3)
    plane = view_plane(mech, ends)
    drawn = []
    axes = []
    for k, (label, q) in enumerate(poses):
        ax = fig.add_subplot(cells[k])
        drawn.append(_draw_sticks(ax, mech, sticks, q, plane, POSE_STYLES[k], label))
        axes.append(ax)
    pts = np.concatenate(drawn) if drawn else np.zeros((0, 2))
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (-np.ones(2), np.ones(2))
    pad = VIEW_MARGIN * max(float(np.max(hi - lo)), 1e-3)
    for k, ax in enumerate(axes):
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel(plane.labels[0], fontsize=8)
        ax.set_ylabel(plane.labels[1] if k == 0 else "", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    return plane


def _fourbar_poses(a: FourBarAnalysis, theta_ref: float) -> list[tuple[str, int]]:
    """Return (label, sweep index) of the 4-bar configurations to draw: the reference
    angle, the ends of the crank range, the largest cond(J), then evenly spread angles."""
    ok = np.flatnonzero(a.assembled[:-1])  # the sweep's last angle is its first
    if not len(ok):
        return []
    n = len(a.theta) - 1

    def wrap(x):
        return (x + math.pi) % (2 * math.pi) - math.pi

    chosen: list[tuple[str, int]] = []

    def add(label, i):
        if len(chosen) < FIGURE_POSES and all(
            abs(wrap(a.theta[i] - a.theta[j])) >= POSE_SEPARATION for _, j in chosen
        ):
            chosen.append((label, int(i)))

    add("q_ref", ok[np.argmin(np.abs(wrap(a.theta[ok] - theta_ref)))])
    for i in ok:  # ends of the reachable runs (cyclic)
        if not a.assembled[(i - 1) % n] or not a.assembled[(i + 1) % n]:
            add("limit of the crank range", i)
    finite = ok[np.isfinite(a.cond[ok])]
    if len(finite):
        i = finite[np.argmax(a.cond[finite])]
        add(f"largest cond(J) = {a.cond[i]:.1e}", i)
    while len(chosen) < FIGURE_POSES:  # then the angle farthest from those drawn
        gap = np.min([np.abs(wrap(a.theta[ok] - a.theta[j])) for _, j in chosen], axis=0)
        if gap.max() < POSE_SEPARATION:
            break
        add("", ok[np.argmax(gap)])
    out = []
    for label, i in sorted(chosen, key=lambda c: a.theta[c[1]]):
        angle = f"{math.degrees(a.theta[i]):.0f} deg"
        out.append((f"{angle}: {label}" if label else angle, i))
    return out


def _fourbar_figure(mech: Mechanism, a: FourBarAnalysis):
    import matplotlib.pyplot as plt

    idx = mech.coordinate_indices([a.crank_joint])[0]
    poses = _fourbar_poses(a, float(mech.q_ref[idx]))
    n = max(len(poses), 1)
    fig = plt.figure(figsize=(2.3 * max(n, 4), 7.0), layout="constrained")
    gs = fig.add_gridspec(3, n, height_ratios=[0.8, 1.2, 1.5])
    ax = [fig.add_subplot(gs[0, :])]
    ax.append(fig.add_subplot(gs[1, :], sharex=ax[0]))
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
    ax[0].set_ylabel("crank angle\nreachable")
    ax[0].legend(fontsize=8, loc="center right")
    ax[0].set_title(
        f"{mech.name}: {a.grashof}; ground {a.ground:.3g}, crank {a.crank:.3g},"
        f" coupler {a.coupler:.3g}, rocker {a.rocker:.3g} m"
    )
    ax[1].semilogy(deg, a.cond)
    ax[1].set_ylabel("cond(J)\n(toggle / change point: peaks)")
    ax[1].set_xlabel(f"{a.crank_joint} [deg]")
    for k, (_, i) in enumerate(poses):
        colour, marker = POSE_STYLES[k]
        for axis in ax:
            axis.axvline(deg[i], color=colour, lw=1.0, alpha=0.8)
        ax[1].plot(deg[i], a.cond[i], marker, color=colour, mec="k", ms=8, zorder=3)
    for axis in ax:
        axis.grid(True, alpha=0.3)
    labels = [label for label, _ in poses]
    plane = _pose_panels(fig, [gs[2, k] for k in range(n)], mech, [(lb, a.q[i]) for lb, i in poses])
    fig.get_layout_engine().set(h_pad=0.08)
    angles = ", ".join(label.split(":")[0] for label in labels)
    return fig, plane, angles


def _map_figure(mech: Mechanism, m: SingularityMap):
    import matplotlib.pyplot as plt

    x0, y0 = mech.q_ref[mech.coordinate_indices(list(m.outputs[:2]))]
    poses: list[tuple[str, np.ndarray, float, float]] = [("q_ref", mech.q_ref, x0, y0)]
    cells: dict[tuple[int, int], list[str]] = {}
    for what, data in (("parallel", m.parallel), ("serial", m.serial)):
        if np.isfinite(data).any():
            i, k = np.unravel_index(np.nanargmin(data), data.shape)
            cells.setdefault((int(i), int(k)), []).append(f"{what} {data[i, k]:.1e}")
    for (i, k), what in cells.items():  # one panel where both minima fall on one point
        poses.append((f"smallest sigma: {', '.join(what)}", m.q[i, k], m.x[k], m.y[i]))
    fig = plt.figure(figsize=(11, 8.2), layout="constrained")
    gs = fig.add_gridspec(2, 1, height_ratios=[1.0, 1.0])
    top = gs[0].subgridspec(1, 2)
    bottom = gs[1].subgridspec(1, max(len(poses), 3))
    for col, data, what in (
        (0, m.parallel, "parallel / type II: sigma_min(J_D)"),
        (1, m.serial, "serial / type I: sigma_min(output map)"),
    ):
        axis = fig.add_subplot(top[col])
        im = axis.pcolormesh(m.x, m.y, np.log10(data), shading="auto", cmap="viridis")
        axis.contour(m.x, m.y, np.log10(data), levels=[-2], colors="r", linewidths=1)
        fig.colorbar(im, ax=axis, label="log10 sigma_min")
        axis.set_title(what, fontsize=10)
        axis.set_xlabel(f"{m.outputs[0]} [rad]")
        axis.set_ylabel(f"{m.outputs[1]} [rad]")
        for k, (_, _, x, y) in enumerate(poses):
            colour, marker = POSE_STYLES[k]
            axis.plot(x, y, marker, color=colour, mec="k", ms=9, zorder=3)
    plane = _pose_panels(
        fig,
        [bottom[k] for k in range(len(poses))],
        mech,
        [
            (f"{lb}\n{m.outputs[0]} = {x + 0.0:.2f}, {m.outputs[1]} = {y + 0.0:.2f}", q)
            for lb, q, x, y in poses
        ],
    )
    fig.suptitle(f"{mech.name}: outputs {', '.join(m.outputs)} (others at q_ref); red: 1e-2")
    return fig, plane


def workspace_figure(
    mech: Mechanism,
    *,
    points: int | None = None,
    outputs: tuple[str, ...] | None = None,
    span: float = SPAN,
):
    """Return the workspace picture of ``mech`` (a matplotlib Figure) and a one-line summary.

    A planar 4-bar (:func:`analyze_fourbar`): its reachable crank range and cond(J) over
    the crank angle. Any other mechanism (:func:`singularity_map`): its parallel and
    serial singularity maps. Below, the mechanism itself as stick figures
    (:func:`closedchain.visualize.shapes.stick_segments`: every link a stick from its
    joint to each child joint and loop frame, links fixed to the ground in grey, joints
    as dots, each loop's two sides ending in one ring) at telling configurations, each
    in its colour and marker, marked at the same place on the plots above: the 4-bar at
    the reference crank angle, the ends of its crank range, the largest cond(J) of the
    sweep and angles spread over the range (at most :data:`FIGURE_POSES`, at least
    :data:`POSE_SEPARATION` apart); a map at ``q_ref`` and at its assembled grid points
    of smallest parallel and serial sigma_min. The figures are drawn in the plane of
    :func:`view_plane` (named in the axis labels), at equal aspect.

    Args:
        mech: the mechanism.
        points: crank angles of the 4-bar sweep (default :data:`SWEEP_POINTS`), or grid
            points per axis of the map (default :data:`MAP_POINTS`).
        outputs: the map's output coordinates (default :func:`default_outputs`).
        span: half-width of the map around the reference outputs [rad].

    Returns:
        (figure, summary); close the figure when done (``matplotlib.pyplot.close``).
    """
    if _is_planar_fourbar(mech):
        a = analyze_fourbar(mech, points=SWEEP_POINTS if points is None else points)
        fig, plane, angles = _fourbar_figure(mech, a)
        return fig, (
            f"{a.grashof}: ground {a.ground:.4g}, crank {a.crank:.4g}, coupler "
            f"{a.coupler:.4g}, rocker {a.rocker:.4g} m; crank range "
            f"{a.closed_form.mean() * 360:.0f} deg of 360; closed form and assembly agree "
            f"at {a.agreement:.1%} of {len(a.theta)} angles; drawn at {angles} "
            f"({plane.how})"
        )
    m = singularity_map(
        mech, outputs=outputs, points=MAP_POINTS if points is None else points, span=span
    )
    fig, plane = _map_figure(mech, m)
    same = set(m.outputs) == {mech.coordinate_names[i] for i in mech.actuated_idx_v}
    return fig, (
        f"singularity map over {m.outputs[0]}, {m.outputs[1]}: min sigma parallel "
        f"{np.nanmin(m.parallel):.2e}, serial {np.nanmin(m.serial):.2e}"
        + (" (the outputs are the actuated coordinates: serial = parallel)" if same else "")
        + f"; drawn at q_ref and the most singular grid points ({plane.how})"
    )


def plot_workspace(
    mech: Mechanism,
    path: str | Path,
    *,
    points: int | None = None,
    outputs: tuple[str, ...] | None = None,
    span: float = SPAN,
) -> str:
    """Write the workspace picture of ``mech`` and return a one-line summary.

    The picture is :func:`workspace_figure`'s (coordinate maps above, the mechanism as
    stick figures at telling configurations below), written atomically in the format
    that the suffix of ``path`` names.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, summary = workspace_figure(mech, points=points, outputs=outputs, span=span)
    try:
        save_figure(fig, path, dpi=110)
    finally:
        plt.close(fig)
    return summary
