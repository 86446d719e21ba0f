r"""Export a loaded mechanism to MuJoCo's MJCF.

The tree is written from the Pinocchio model (so the MJCF holds exactly what
closedchain simulates): one ``<body>`` per joint, placed by
``model.jointPlacements``, with the joint (revolute -> ``hinge``, continuous ->
``hinge`` without range, prismatic -> ``slide``, spherical -> ``ball``, free
flyer -> ``free``, with the joint's ``armature``, ``damping``, ``stiffness`` and
``springref``: :mod:`closedchain.passive`), its ``<inertial>`` (mass, centre of mass, principal
moments ``diaginertia`` and the principal axes as ``quat``, from
``model.inertias``: links attached by fixed joints are already merged there)
and capsules along the link (from the joint origin to each child joint and
loop point) as collision-free geoms for display. Gravity is
``mech.model.gravity``. Each ``<loop>`` becomes equality constraints between
sites placed at the two halves c1 and c2 of the cut joint:

* ``spherical``: one ``connect`` (c1 and c2 coincide);
* ``revolute``: two ``connect``: c1 = c2 and c1 + L u = c2 + L u on the axis u;
* ``fixed``: one ``weld`` of the two site frames;
* ``coupling``: one ``joint`` equality, ``polycoef`` = (offset, multiplier, 0, 0, 0).

Prismatic loops have no MuJoCo equality and raise.

MuJoCo enforces equalities softly (``solref``, ``solimp``): its accelerations
differ from the exact constrained ones by an amount those parameters set
(measured on the 4-bar at a regular state: ~2e-2 relative with MuJoCo's
defaults, ~3e-6 with :data:`STIFF`; Agile Eye 0.2 and 4e-4;
``tests/test_export.py`` asserts it). Known gap: a ``weld`` (fixed loop)
reproduces the tree and satisfies the closure (zero MuJoCo residual) but its
accelerations differ by ~4 % even with :data:`STIFF` on
``tests/data/fixed_branches.urdf``; not yet understood, so not asserted.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin

from .._io import atomic_write
from .._locking import exclusive
from ..description import UNIVERSAL_SECOND_SUFFIX
from ..exceptions import ClosedChainError, check_settings

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)

#: Distance between the two connect points of a revolute loop along its axis [m].
REVOLUTE_CONNECT_OFFSET = 0.1
#: Radius of the display capsules [m].
CAPSULE_RADIUS = 0.01
#: Shortest link drawn as a capsule [m] (shorter ones get a small sphere).
MIN_CAPSULE_LENGTH = 1e-6
#: Most nested bodies in one piece of MJCF that :func:`load_mujoco` gives MuJoCo's XML
#: parser (400 parse, 600 do not).
XML_DEPTH = 200
#: Name prefix of the pieces :func:`load_mujoco` attaches (removed again).
_PIECE_PREFIX = "closedchain_piece_"
#: Bodies lighter than this get MuJoCo's minimum mass and inertia (massless
#: intermediate links, e.g. Euler-angle gimbals) [kg, kg m^2].
MIN_MASS = 1e-9


@dataclass(frozen=True)
class MjcfSettings:
    """Options of :func:`export_mjcf`.

    Attributes:
        solref: MuJoCo ``solref`` of the loop equalities (time constant [s],
            damping ratio); None keeps MuJoCo's default (0.02 1).
        solimp: MuJoCo ``solimp`` of the loop equalities (dmin, dmax, width
            [m], ...); None keeps MuJoCo's default (0.9 0.95 0.001 0.5 2).
        timestep: ``<option timestep>`` [s].
        integrator: ``<option integrator>`` (Euler, RK4, implicit, implicitfast).
        min_mass: mass given to massless bodies that carry a joint [kg]
            (MuJoCo refuses moving bodies without mass).
    """

    solref: tuple[float, float] | None = None
    solimp: tuple[float, ...] | None = None
    timestep: float = 1e-3
    integrator: str = "Euler"
    min_mass: float = MIN_MASS


#: The defaults, shared (frozen).
DEFAULT_MJCF_SETTINGS = MjcfSettings()

#: Stiff equality settings (tests/test_export.py compares accelerations with them).
STIFF = MjcfSettings(solref=(0.002, 1.0), solimp=(0.9999, 0.9999, 0.001))

_JOINT_KIND = {
    "JointModelRX": ("hinge", (1.0, 0.0, 0.0)),
    "JointModelRY": ("hinge", (0.0, 1.0, 0.0)),
    "JointModelRZ": ("hinge", (0.0, 0.0, 1.0)),
    "JointModelRUBX": ("hinge", (1.0, 0.0, 0.0)),
    "JointModelRUBY": ("hinge", (0.0, 1.0, 0.0)),
    "JointModelRUBZ": ("hinge", (0.0, 0.0, 1.0)),
    "JointModelPX": ("slide", (1.0, 0.0, 0.0)),
    "JointModelPY": ("slide", (0.0, 1.0, 0.0)),
    "JointModelPZ": ("slide", (0.0, 0.0, 1.0)),
    "JointModelSpherical": ("ball", None),
    "JointModelFreeFlyer": ("free", None),
}
_VALID_JOINTS = "revolute, continuous, prismatic (any axis), universal, spherical, free flyer"


def _fmt(x) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.ravel(x))


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    q = pin.Quaternion(np.asarray(R, dtype=float))
    q.normalize()
    return np.array([q.w, q.x, q.y, q.z])


def _passive_xml(mech: Mechanism, j: int, coordinate: int = 0) -> str:
    """The attributes of joint j's passive terms on its ``coordinate``: ``armature``,
    ``damping``, ``stiffness`` and ``springref`` (MuJoCo's names and conventions), where
    nonzero."""
    p, jm = mech.passive, mech.model.joints[j]
    k = jm.idx_v + coordinate
    out = ""
    if p.armature[k]:
        out += f' armature="{_fmt(p.armature[k])}"'
    if p.damping[k]:
        out += f' damping="{_fmt(p.damping[k])}"'
    for s in np.flatnonzero(p.spring_idx_v == k) if jm.nv == 1 else ():
        out += f' stiffness="{_fmt(p.stiffness[s])}" springref="{_fmt(p.reference[s])}"'
    return out


def _joint_xml(mech: Mechanism, j: int) -> str:
    model = mech.model
    jm = model.joints[j]
    short = jm.shortname()
    name = quoteattr(model.names[j])
    if short in _JOINT_KIND:
        kind, axis = _JOINT_KIND[short]
    elif short in ("JointModelRevoluteUnaligned", "JointModelRevoluteUnboundedUnaligned"):
        kind, axis = "hinge", tuple(jm.extract().axis)
    elif short == "JointModelPrismaticUnaligned":
        kind, axis = "slide", tuple(jm.extract().axis)
    elif short == "JointModelUniversal":
        # Two hinges in one body: MuJoCo turns it by Rot(axis1, q1) Rot(axis2, q2), each
        # axis in the body frame, as Pinocchio's universal joint does.
        universal = jm.extract()
        hinges = (
            (model.names[j], universal.axis1, 0),
            (model.names[j] + UNIVERSAL_SECOND_SUFFIX, universal.axis2, 1),
        )
        return "".join(
            f'<joint name={quoteattr(n)} type="hinge" axis="{_fmt(a)}" limited="false"'
            f"{_passive_xml(mech, j, k)}/>"
            for n, a, k in hinges
        )
    else:
        raise ClosedChainError(
            f"joint {model.names[j]!r} of type {short} has no MJCF export; valid joint types: "
            f"{_VALID_JOINTS}"
        )
    passive = _passive_xml(mech, j)
    if kind == "free":
        return (
            f'<joint name={name} type="free"{passive}/>' if passive else f"<freejoint name={name}/>"
        )
    if kind == "ball":
        return f'<joint name={name} type="ball" limited="false"{passive}/>'
    return f'<joint name={name} type="{kind}" axis="{_fmt(axis)}" limited="false"{passive}/>'


def _inertial_xml(model: pin.Model, j: int, min_mass: float) -> str:
    inertia = model.inertias[j]
    mass = float(inertia.mass)
    if mass < min_mass:
        return (
            f'<inertial pos="0 0 0" mass="{min_mass:.17g}" diaginertia="{_fmt([min_mass] * 3)}"/>'
        )
    # Principal axes: I = R diag(d) R^T with R a proper rotation (MuJoCo's quat).
    d, R = np.linalg.eigh(np.asarray(inertia.inertia))
    if np.linalg.det(R) < 0:
        R[:, 0] *= -1.0
    d = np.maximum(d, min_mass * 1e-6)
    return (
        f'<inertial pos="{_fmt(inertia.lever)}" quat="{_fmt(_quat_wxyz(R))}" '
        f'mass="{mass:.17g}" diaginertia="{_fmt(d)}"/>'
    )


def _capsule_xml(p: np.ndarray, radius: float) -> str:
    if np.linalg.norm(p) < MIN_CAPSULE_LENGTH:
        return f'<geom type="sphere" size="{radius:.6g}" contype="0" conaffinity="0" mass="0"/>'
    return (
        f'<geom type="capsule" fromto="0 0 0 {_fmt(p)}" size="{radius:.6g}" '
        'contype="0" conaffinity="0" mass="0"/>'
    )


@exclusive
def export_mjcf(
    mech: Mechanism,
    path: str | Path | None = None,
    *,
    settings: MjcfSettings = DEFAULT_MJCF_SETTINGS,
) -> str:
    """Write ``mech`` as MJCF (tree, inertias, gravity, loops as equality constraints).

    Args:
        mech: the loaded mechanism.
        path: file to write; None: only return the text.
        settings: solver parameters of the equalities and options.

    Returns:
        The MJCF text. A tree deeper than a few hundred bodies (a 600-link chain) nests
        deeper than MuJoCo's XML parser reads; :func:`load_mujoco` loads it in pieces.

    Raises:
        ClosedChainError: a joint or loop type MuJoCo cannot express (prismatic loops).
    """
    check_settings("settings", settings, MjcfSettings)
    parts = _parts(mech, settings)
    text, _ = _document(mech, settings, parts)
    if path is not None:
        with atomic_write(path, "w", encoding="utf-8") as f:
            f.write(text)
        logger.info(
            "wrote %s (%d bodies, %d equalities)",
            path,
            mech.model.njoints - 1,
            len(parts.equalities),
        )
    return text


class _Parts(NamedTuple):
    """What the MJCF of a mechanism is made of (:func:`_parts`).

    Attributes:
        children: the child joints of each joint (0: the world).
        sites: the site elements on each joint's body.
        points: the loop points on each joint's body (drawn as capsules).
        equalities: the equality elements of the loops.
    """

    children: dict[int, list[int]]
    sites: dict[int, list[str]]
    points: dict[int, list[np.ndarray]]
    equalities: list[str]


def _parts(mech: Mechanism, settings: MjcfSettings) -> _Parts:
    """The bodies' children, sites and loop points and the loop equalities of ``mech``.

    Raises:
        ClosedChainError: a prismatic loop (no MuJoCo equality).
    """
    model = mech.model
    layer = mech.declared
    children: dict[int, list[int]] = {j: [] for j in range(model.njoints)}
    for j in range(1, model.njoints):
        children[model.parents[j]].append(j)
    sites: dict[int, list[str]] = {j: [] for j in range(model.njoints)}
    points: dict[int, list[np.ndarray]] = {j: [] for j in range(model.njoints)}
    equalities: list[str] = []
    attrs = ""
    if settings.solref is not None:
        attrs += f' solref="{_fmt(settings.solref)}"'
    if settings.solimp is not None:
        attrs += f' solimp="{_fmt(settings.solimp)}"'
    for spec, (fp, fs) in zip(layer.loops, layer.frame_ids, strict=True):
        if spec.type == "prismatic":
            raise ClosedChainError(
                f"loop {spec.name!r} is prismatic: MuJoCo has no prismatic equality; valid "
                "loop types for MJCF export: revolute, spherical, fixed"
            )
        if spec.type == "coupling":  # q_joint = multiplier q_mimics + offset
            equalities.append(
                f"<joint name={quoteattr(spec.name)} joint1={quoteattr(spec.joint)} "
                f"joint2={quoteattr(spec.mimics)} "
                f'polycoef="{_fmt([spec.offset, spec.multiplier, 0.0, 0.0, 0.0])}"{attrs}/>'
            )
            continue
        ends = []
        for side, fid in (("c1", fp), ("c2", fs)):
            frame = model.frames[fid]
            j, M = frame.parentJoint, frame.placement
            name = f"{spec.name}_{side}"
            sites[j].append(
                f'<site name={quoteattr(name)} pos="{_fmt(M.translation)}" '
                f'quat="{_fmt(_quat_wxyz(M.rotation))}" size="0.005"/>'
            )
            points[j].append(M.translation)
            ends.append((j, M, name))
        if spec.type == "fixed":
            equalities.append(
                f"<weld name={quoteattr(spec.name)} site1={quoteattr(ends[0][2])} "
                f"site2={quoteattr(ends[1][2])}{attrs}/>"
            )
            continue
        equalities.append(
            f"<connect name={quoteattr(spec.name)} site1={quoteattr(ends[0][2])} "
            f"site2={quoteattr(ends[1][2])}{attrs}/>"
        )
        if spec.type == "revolute":
            # The axis u is given in c1; closed, c2 holds the same axis.
            shifted = []
            for j, M, name in ends:
                p = M.translation + M.rotation @ (REVOLUTE_CONNECT_OFFSET * spec.axis)
                sname = f"{name}_axis"
                sites[j].append(f'<site name={quoteattr(sname)} pos="{_fmt(p)}" size="0.005"/>')
                shifted.append(sname)
            equalities.append(
                f"<connect name={quoteattr(spec.name + '_axis')} site1={quoteattr(shifted[0])} "
                f"site2={quoteattr(shifted[1])}{attrs}/>"
            )

    return _Parts(children, sites, points, equalities)


def _document(
    mech: Mechanism,
    settings: MjcfSettings,
    parts: _Parts,
    roots: list[int] | None = None,
    depth: int | None = None,
) -> tuple[str, list[tuple[int, int]]]:
    """The MJCF text of the bodies of ``roots`` and their subtrees (None: the whole
    mechanism, with the world's sites and the equalities), nesting at most ``depth``
    bodies (None: no limit).

    Returns:
        The text and the cuts ``(parent joint, child joint)``: the subtrees left out below
        the depth limit, in depth-first order.
    """
    model = mech.model
    children, sites, points, equalities = parts
    lines: list[str] = []
    cuts: list[tuple[int, int]] = []

    def open_body(j: int, indent: str) -> None:
        M = model.jointPlacements[j]
        lines.append(
            f'{indent}<body name={quoteattr(model.names[j])} pos="{_fmt(M.translation)}" '
            f'quat="{_fmt(_quat_wxyz(M.rotation))}">'
        )
        inner = indent + "  "
        lines.append(inner + _joint_xml(mech, j))
        lines.append(inner + _inertial_xml(model, j, settings.min_mass))
        for c in children[j]:
            lines.append(inner + _capsule_xml(model.jointPlacements[c].translation, CAPSULE_RADIUS))
        for p in points[j]:
            lines.append(inner + _capsule_xml(p, CAPSULE_RADIUS))
        lines.extend(inner + s for s in sites[j])

    # Depth first with an explicit stack (a 1000-link chain nests 1000 bodies, deeper
    # than Python's recursion limit): ("open", j, level) writes body j and stacks its
    # closing tag and then its children, first child on top.
    whole = roots is None
    stack = [("open", c, 1) for c in reversed(children[0] if whole else roots)]
    while stack:
        what, j, level = stack.pop()
        indent = "  " * (level + 1)
        if what == "close":
            lines.append(f"{indent}</body>")
            continue
        open_body(j, indent)
        stack.append(("close", j, level))
        if depth is not None and level == depth:
            cuts.extend((j, c) for c in children[j])
        else:
            stack.extend(("open", c, level + 1) for c in reversed(children[j]))
    g = model.gravity.linear
    text = "\n".join(
        [
            f"<mujoco model={quoteattr(mech.name)}>",
            '  <compiler angle="radian" inertiafromgeom="false"/>',
            f'  <option gravity="{_fmt(g)}" timestep="{settings.timestep:.17g}" '
            f'integrator="{settings.integrator}"/>',
            "  <worldbody>",
            *(["    " + s for s in sites[0]] if whole else []),
            *lines,
            "  </worldbody>",
            *(
                ["  <equality>", *["    " + e for e in equalities], "  </equality>"]
                if whole
                else []
            ),
            "</mujoco>",
            "",
        ]
    )
    return text, cuts


def _require_mujoco():
    try:
        import mujoco
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ClosedChainError(
            "MuJoCo is not installed; install it with `pip install closedchain[bench]` "
            "(or `pip install mujoco`)"
        ) from exc
    return mujoco


@exclusive
def load_mujoco(mech: Mechanism, *, settings: MjcfSettings = DEFAULT_MJCF_SETTINGS):
    """Return ``(mjModel, mjData)`` of the exported mechanism (needs the ``mujoco`` package).

    MuJoCo's XML parser nests a few hundred bodies at most (a 600-link chain does not
    parse): the MJCF of :func:`export_mjcf` is parsed in pieces of at most
    :data:`XML_DEPTH` nested bodies, each piece attached to its parent body with
    ``mujoco.MjSpec`` (``MjsFrame.attach_body``), and compiled once: the model of the
    whole text.
    """
    check_settings("settings", settings, MjcfSettings)
    mujoco = _require_mujoco()
    parts = _parts(mech, settings)
    text, cuts = _document(mech, settings, parts, depth=XML_DEPTH)
    if not cuts:
        model = mujoco.MjModel.from_xml_string(text)
        return model, mujoco.MjData(model)
    spec = mujoco.MjSpec.from_string(text)
    names = mech.model.names
    while cuts:
        parent, child = cuts.pop(0)
        piece, more = _document(mech, settings, parts, [child], XML_DEPTH)
        body = mujoco.MjSpec.from_string(piece).body(names[child])
        # attach_body prefixes every name it copies (an empty prefix warns and writes
        # MUJOCO_LOG.TXT): take the names back, so that the equalities find their sites.
        body = spec.body(names[parent]).add_frame().attach_body(body, _PIECE_PREFIX, "")
        kinds = (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_SITE)
        for element in [body, *(e for kind in kinds for e in body.find_all(kind))]:
            element.name = element.name.removeprefix(_PIECE_PREFIX)
        cuts += more
    model = spec.compile()
    return model, mujoco.MjData(model)


def mujoco_state(mech: Mechanism, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map Pinocchio's (q, v) to MuJoCo's (qpos, qvel) for the exported model.

    Revolute, prismatic, universal (two hinges) and spherical joints keep their entries
    (Pinocchio's quaternion is x, y, z, w, MuJoCo's w, x, y, z); a continuous joint's
    (cos, sin) becomes its angle. Velocities are in the same joint frames.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).

    Returns:
        qpos and qvel of the MJCF written by :func:`export_mjcf`.
    """
    model = mech.model
    qpos: list[float] = []
    for j in range(1, model.njoints):
        jm = model.joints[j]
        qj = q[jm.idx_q : jm.idx_q + jm.nq]
        short = jm.shortname()
        if short.startswith("JointModelRUB") or short == "JointModelRevoluteUnboundedUnaligned":
            qpos.append(math.atan2(qj[1], qj[0]))
        elif short == "JointModelSpherical":
            qpos += [qj[3], qj[0], qj[1], qj[2]]
        elif short == "JointModelFreeFlyer":
            qpos += [*qj[:3], qj[6], qj[3], qj[4], qj[5]]
        else:
            qpos += list(qj)
    return np.array(qpos), np.array(v, dtype=float)
