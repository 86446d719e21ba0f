"""Shapes: the URDF ``<visual>`` primitives and meshes, joint markers, bodies."""

from __future__ import annotations

import io
import logging
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pinocchio as pin

from .._io import MAX_MESH_BYTES, check_input_file, read_input_bytes
from ..constraints import axis_basis
from ..exceptions import ClosedChainError, quoted
from ..urdf import COUPLING, WORLD_LINK, _declares_doctype

if TYPE_CHECKING:
    from ..description import TreeDescription
    from ..mechanism import Mechanism

from .settings import (
    DEFAULT_SETTINGS,
    MEGABYTE,
    NATIVE_MESH_FORMATS,
    SCENE_ROOT,
    STICK_AXIS_LENGTH,
    STICK_BALL_RATIO,
    STICK_MIN_LENGTH,
    STICK_RADIUS,
    STICK_RADIUS_RATIO,
    AnimationSettings,
    Body,
    JointMarker,
    MeshData,
    MeshSummary,
    StickSegment,
    VisualShape,
)

logger = logging.getLogger(__name__)


def _meshcat():
    import warnings

    with warnings.catch_warnings():
        # meshcat's server module (imported by meshcat, unused here) imports
        # zmq.eventloop.ioloop, deprecated in pyzmq >= 17.
        warnings.filterwarnings("ignore", category=DeprecationWarning, module="meshcat")
        import meshcat  # lazy: it imports zmq and IPython

    return meshcat


def scene_path(*names: str) -> str:
    """Return the meshcat path of nested URDF names under :data:`SCENE_ROOT`.

    Each name is percent-encoded (``urllib.parse.quote`` with no safe
    characters), so a ``/`` cannot split it and markup characters cannot reach
    the page. Plain names (letters, digits, ``_.-~``) are unchanged.
    """
    return SCENE_ROOT + "".join("/" + urllib.parse.quote(n, safe="") for n in names)


#: ROS packages whose installed share directory is a trusted mesh root:
#: ``package://<name>/sub`` is looked up there, and files under it may be embedded
#: whatever the URDF's directory (they are public data installed with Python
#: packages, so embedding them discloses nothing).
TRUSTED_PACKAGES = ("example-robot-data",)


def _trusted_roots() -> dict[str, Path]:
    """Return package name -> resolved share directory of the installed trusted packages."""
    from ..robots import erd_robots_dir

    try:
        return {TRUSTED_PACKAGES[0]: erd_robots_dir().parent.resolve()}
    except ClosedChainError:  # example-robot-data is not installed
        return {}


def _mesh_candidates(filename: str, urdf_dir: Path, trusted: dict[str, Path]) -> list[Path]:
    """Return the paths a URDF mesh ``filename`` may refer to, in lookup order.

    A plain name is relative to ``urdf_dir`` (or absolute); ``file://`` gives
    a path the same way; ``package://pkg/sub`` is looked up as ``sub`` in
    ``urdf_dir``, then in its parent directories (where ROS packages keep
    their meshes, so that :func:`_resolve_mesh` can name a file it refuses),
    then in the share directory of a trusted package ``pkg``; other schemes
    give nothing.
    """
    scheme, sep, rest = filename.partition("://")
    if not sep:
        return [urdf_dir / filename]
    if scheme == "file":
        return [urdf_dir / urllib.parse.unquote(rest)]
    if scheme == "package":
        package, _, sub = rest.partition("/")
        if not sub:
            return []
        roots = [urdf_dir, *urdf_dir.parents]
        if package in trusted:
            roots.append(trusted[package])
        return [d / sub for d in roots]
    return []


def _resolve_mesh(
    filename: str, urdf_dir: Path, trusted: dict[str, Path]
) -> tuple[Path | None, Path | None]:
    """Return (the mesh file, None), or (None, a file found outside the allowed roots).

    Only files under the URDF's directory or a trusted package's share
    directory (after resolving ``..`` and symbolic links) are drawn, so a URDF
    cannot embed arbitrary local files in the page. ``urdf_dir`` must be
    resolved. (None, None): no file found.
    """
    allowed = (urdf_dir, *trusted.values())
    outside = None
    for candidate in _mesh_candidates(filename, urdf_dir, trusted):
        if not candidate.is_file():
            continue
        found = candidate.resolve()
        if any(found.is_relative_to(root) for root in allowed):
            return found, None
        outside = outside or found
    return None, outside


def read_mesh(path: str | Path) -> MeshData:
    """Read a mesh file and check that meshcat's viewer can draw it.

    The file is parsed by trimesh (never fetching what it references): it
    must hold at least one triangle, with finite vertices. STL (binary or
    ASCII), OBJ and DAE (UTF-8 text; a DAE without a DOCTYPE) are embedded as
    they are, other formats trimesh reads as a converted binary STL.

    Args:
        path: the mesh file, at most :data:`closedchain._io.MAX_MESH_BYTES`.

    Returns:
        The data to embed and the mesh's bounding box [mesh units].

    Raises:
        ClosedChainError: the file is not a regular file, is too large, or is
            not a mesh meshcat can draw (the message names the file and why).
    """
    import trimesh

    path = Path(path)
    raw = read_input_bytes(path, limit=MAX_MESH_BYTES, what="mesh file")
    fmt = path.suffix.lower().lstrip(".")
    if fmt == "dae" and _declares_doctype(raw):
        # Entities of a DTD would be expanded by the parsers (ours and the browser's).
        raise ClosedChainError(f"{path}: DAE file declares a DOCTYPE; valid: COLLADA without one")
    if fmt in ("obj", "dae"):
        try:
            raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ClosedChainError(f"{path}: {fmt.upper()} file is not UTF-8 text: {exc}") from None
    try:
        mesh = trimesh.load(io.BytesIO(raw), file_type=fmt, force="mesh")
        faces, vertices = np.asarray(mesh.faces), np.asarray(mesh.vertices, dtype=float)
    except Exception as exc:  # any failure of a third-party reader: not drawable
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ClosedChainError(f"{path}: cannot read mesh: {reason}") from None
    if len(faces) == 0 or len(vertices) == 0:
        raise ClosedChainError(f"{path}: {fmt.upper()} mesh has no triangles")
    if not np.all(np.isfinite(vertices)):
        raise ClosedChainError(f"{path}: mesh has vertices that are not finite")
    if fmt not in NATIVE_MESH_FORMATS:
        raw, fmt = mesh.export(file_type="stl"), "stl"
    return MeshData(fmt, raw, vertices.min(axis=0), vertices.max(axis=0))


#: Joint kinds whose axis is fixed in both links (the axis points of :func:`stick_segments`).
_AXIS_KINDS = ("revolute", "continuous")


def stick_segments(mech: Mechanism) -> tuple[StickSegment, ...]:
    """Return the sticks of every link's stick figure, link by link in the description's order.

    The one link graph of the stick figures: the animation draws it for links without
    visuals or whose meshes are not drawn (:func:`stick_figure`), the workspace pictures
    for every link (:func:`closedchain.workspace.plot_workspace`). A link's sticks run
    from its joint point to the point of each child joint (in tree order), then to each
    loop frame on it (the two sides of a cut joint, in the loops' order; a coupling has
    no frames), all in the link's frame:

    * a joint's point is its anchor (a URDF joint's origin); a link without a joint (the
      root) starts at its origin;
    * a stick whose two ends coincide (in a spherical mechanism every joint axis passes
      through one centre) joins instead the points at distance R along the two revolute
      axes (a revolute loop's axis at a loop frame), which move with both links: each
      link becomes a chord of the sphere of radius R about the centre, the usual drawing
      of a spherical linkage. R is the median length of the other sticks, else the
      median distance of the bodies' centres of mass from their joint points, else
      :data:`~closedchain.visualize.settings.STICK_AXIS_LENGTH`. A massless link
      without visuals (a virtual link, e.g. of an Euler-angle chain) keeps its
      coinciding ends.

    Every stick is returned, however short; drawings skip those shorter than
    :data:`~closedchain.visualize.settings.STICK_MIN_LENGTH`.

    Args:
        mech: the mechanism (its description's tree and loops).

    Returns:
        tuple of :class:`~closedchain.visualize.settings.StickSegment`.
    """
    tree = mech.description.tree
    zero = np.zeros(3)
    # link -> (its joint's anchor, its revolute axis or None), in the link frame
    own: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    # link -> [(to, loop, end, end's axis direction or None, the axis's point)]
    ends: dict[str, list[tuple[str, bool, np.ndarray, np.ndarray | None]]] = {}
    physical: dict[str, bool] = {}
    order: list[str] = []
    if tree.world_frame:
        order.append(WORLD_LINK)
        own[WORLD_LINK] = (zero, None)
        physical[WORLD_LINK] = bool(tree.world_visuals)
    for body in tree.bodies:
        order.append(body.name)
        anchor, axis = zero, None
        if body.joints:
            joint = body.joints[0]
            anchor = np.asarray(joint.position, dtype=float)
            if len(body.joints) == 1 and joint.kind in _AXIS_KINDS:
                axis = np.asarray(joint.axis, dtype=float)
        own[body.name] = (anchor, axis)
        physical[body.name] = body.inertia.mass > 0 or bool(body.visuals)
        if body.parent is None:  # hangs from Pinocchio's universe, which has no body frame
            continue
        R = body.placement.rotation
        ends.setdefault(body.parent, []).append(
            (
                body.joints[0].name if body.joints else body.fixed_joint or body.name,
                False,
                body.placement.act(anchor),
                None if axis is None else R @ axis,
            )
        )
    for spec in mech.description.loops:
        if spec.type == COUPLING:  # it joins two coordinates, no two frames
            continue
        for link, M in (
            (spec.predecessor, spec.predecessor_origin),
            (spec.successor, spec.successor_origin),
        ):
            axis = M.rotation @ np.asarray(spec.axis, dtype=float)
            ends.setdefault(link, []).append(
                (spec.name, True, M.translation, axis if spec.type == "revolute" else None)
            )
    lengths = [
        float(np.linalg.norm(end - own[link][0]))
        for link, items in ends.items()
        if link in own
        for _, _, end, _ in items
    ]
    lengths = [x for x in lengths if x >= STICK_MIN_LENGTH]
    if not lengths:
        lengths = [
            float(np.linalg.norm(b.inertia.lever - own[b.name][0]))
            for b in tree.bodies
            if b.inertia.mass > 0
        ]
        lengths = [x for x in lengths if x >= STICK_MIN_LENGTH]
    radius = float(np.median(lengths)) if lengths else STICK_AXIS_LENGTH
    out: list[StickSegment] = []
    for link in order:
        start, start_axis = own[link]
        for to, loop, end, end_axis in ends.get(link, []):
            a, b = start, end
            if (
                np.linalg.norm(end - start) < STICK_MIN_LENGTH
                and physical[link]
                and start_axis is not None
                and end_axis is not None
            ):
                a = start + radius * start_axis / np.linalg.norm(start_axis)
                b = end + radius * end_axis / np.linalg.norm(end_axis)
            out.append(
                StickSegment(link, np.array(a, dtype=float), np.array(b, dtype=float), to, loop)
            )
    return tuple(out)


def posed_sticks(
    mech: Mechanism, q: np.ndarray, sticks: tuple[StickSegment, ...] | None = None
) -> np.ndarray:
    """Return the sticks in the world frame at a configuration.

    Args:
        mech: the mechanism.
        q: configuration, shape (nq,) [rad, m].
        sticks: the sticks to place (default: :func:`stick_segments`).

    Returns:
        (start, end) of each stick in the world frame, shape (n, 2, 3) [m].
    """
    from ..pindata import new_data

    model = mech.model
    if sticks is None:
        sticks = stick_segments(mech)
    data = new_data(model)
    pin.framesForwardKinematics(model, data, np.asarray(q, dtype=float))
    out = np.empty((len(sticks), 2, 3))
    fids: dict[str, int] = {}
    for i, stick in enumerate(sticks):
        if stick.link not in fids:
            fids[stick.link] = model.getFrameId(stick.link, pin.FrameType.BODY)
        oMf = data.oMf[fids[stick.link]]
        out[i, 0], out[i, 1] = oMf.act(stick.start), oMf.act(stick.end)
    return out


def stick_figure(
    link: str,
    sticks: list[StickSegment],
    rgba: tuple[float, float, float, float],
    *,
    radius: float = STICK_RADIUS,
) -> list[VisualShape]:
    """Return the primitives that stand for a link whose meshes are not drawn.

    A ball at the link's joint point (its origin when it has no stick) and a cylinder
    along each of its sticks (:func:`stick_segments`) of at least
    ``STICK_MIN_LENGTH``: the robot's exact kinematics, without reading any mesh.

    Args:
        link: the link's name.
        sticks: its sticks, in the link frame.
        rgba: colour, (r, g, b, a) in [0, 1] (the colour of its first mesh).
        radius: the cylinders' radius [m] (the ball's is ``STICK_BALL_RATIO`` times it).
    """
    ball = (STICK_BALL_RATIO * radius,)
    centre = np.eye(4)
    if sticks:
        centre[:3, 3] = sticks[0].start
    out = [VisualShape(link, "sphere", ball, centre, rgba)]
    for stick in sticks:
        length = stick.length
        if length < STICK_MIN_LENGTH:
            continue
        # A URDF cylinder runs along its z axis, centred on its origin.
        origin = _frame_with_z((stick.end - stick.start) / length, (stick.start + stick.end) / 2.0)
        out.append(VisualShape(link, "cylinder", (radius, length), origin, rgba))
    return out


def model_stick_radius(sticks: tuple[StickSegment, ...]) -> float:
    """Return the stick radius [m] of links without visuals: ``STICK_RADIUS_RATIO`` times
    the median length of the model's sticks (``STICK_RADIUS`` for a model without any)."""
    lengths = [x for x in (s.length for s in sticks) if x >= STICK_MIN_LENGTH]
    return STICK_RADIUS_RATIO * float(np.median(lengths)) if lengths else STICK_RADIUS


def read_visuals(mech: Mechanism, *, settings: AnimationSettings = DEFAULT_SETTINGS):
    """Return the mechanism's visuals (its description's).

    See :func:`read_scene_visuals`, which also says what of the meshes is embedded.

    Returns:
        tuple of :class:`VisualShape`, in the description's order.
    """
    return read_scene_visuals(mech, settings=settings)[0]


def read_scene_visuals(
    mech: Mechanism, *, settings: AnimationSettings = DEFAULT_SETTINGS
) -> tuple[tuple[VisualShape, ...], MeshSummary]:
    """Return the mechanism's visuals (its description's), with meshes within the budget.

    A link without any visual (a URDF with inertials only, common for generated
    and YAML-convention models) is drawn as a :func:`stick_figure` in
    ``settings.default_rgba``: a ball at its origin and a stick to each child joint and
    loop frame on it, of radius :func:`model_stick_radius` (sized from the model).

    The visuals are the description's (:class:`closedchain.description.Visual`,
    in the body's frame; a visual without a colour takes ``settings.default_rgba``):
    a URDF's ``<visual>`` elements (materials resolved by name against the
    robot's top-level ``<material>`` elements by the reader), an MJCF model's
    geoms (mesh files as MuJoCo found them). A URDF's mesh files are looked up
    beside the file that names the link (``MechanismDescription.link_files``: a base URDF
    under an overlay; ``file://`` URLs as paths, ``package://pkg/sub`` as ``sub``
    in that directory and its parents, and in the share directory of the
    packages of :data:`TRUSTED_PACKAGES`, i.e. example-robot-data's meshes for
    ``erd:`` models). Only files under that directory or a trusted package are
    drawn (the page embeds them, so a URDF must not reach other local files).

    In the description's order (the tree, depth first), the meshes of a link are
    embedded when all of them can be read (:func:`read_mesh`) and together fit in
    what the links before left of ``settings.mesh_budget_bytes``. Otherwise the
    link's mesh visuals are replaced by its :func:`stick_figure` (its boxes,
    cylinders and spheres stay): a mesh outside the allowed directories, not
    found, larger than :data:`closedchain._io.MAX_MESH_BYTES` or unreadable is
    named in a warning (file and link); links over the budget are listed in one
    warning.

    Args:
        mech: the mechanism.
        settings: gives the colour of visuals without a material and the mesh budget.

    Returns:
        (visuals in the description's order, what of the meshes is embedded).

    Raises:
        ClosedChainError: ``settings.mesh_budget_bytes`` is negative.
    """
    budget = settings.mesh_budget_bytes
    if not budget >= 0:
        raise ClosedChainError(
            f"AnimationSettings.mesh_budget_bytes = {budget!r}; valid: a number of bytes >= 0"
        )
    links = _description_links(mech.description.tree, settings.default_rgba)
    # Each link's meshes beside the file that names it (a base URDF under an overlay).
    link_files = mech.description.link_files
    trusted = _trusted_roots()
    all_sticks = stick_segments(mech)
    children: dict[str, list[StickSegment]] = {}
    for stick in all_sticks:
        children.setdefault(stick.link, []).append(stick)
    bare_radius = model_stick_radius(all_sticks)
    out: list[VisualShape] = []
    left, n_embedded = budget, 0
    primitive_links: list[str] = []
    over_budget: list[str] = []
    for link_name, items, massive in links:
        shapes: list[VisualShape | None] = []  # None: where the link's meshes are drawn
        meshes: list[tuple[int, object, np.ndarray, tuple]] = []
        for i, (kind, dims, origin, rgba) in enumerate(items):
            if kind != "mesh":
                shapes.append(VisualShape(link_name, kind, dims, origin, rgba))
                continue
            if not meshes:
                shapes.append(None)
            meshes.append((i, dims, origin, rgba))
        drawn: list[VisualShape] = []
        if meshes:
            source = Path(link_files.get(link_name, mech.path))
            where = f"{source}: link {quoted(link_name)}"
            urdf_dir = source.resolve().parent
            fit = _link_meshes(where, link_name, meshes, urdf_dir, trusted, left)
            if isinstance(fit, list):
                drawn = fit
                left -= sum(len(v.mesh_data.data) for v in fit)
                n_embedded += len(fit)
            else:
                if fit is not None:  # the bytes its meshes need
                    over_budget.append(f"{link_name} ({fit / MEGABYTE:.3g} MB)")
                primitive_links.append(link_name)
                drawn = stick_figure(link_name, children.get(link_name, []), meshes[0][3])
        for v in shapes:
            out.extend(drawn if v is None else [v])
        sticks = [x for x in children.get(link_name, []) if x.length >= STICK_MIN_LENGTH]
        if not items and (sticks or massive):
            out.extend(
                stick_figure(
                    link_name,
                    sticks,
                    settings.default_rgba,
                    radius=bare_radius,
                )
            )
    if over_budget:
        logger.warning(
            "%s: meshes over what is left of the budget of %.3g MB "
            "(AnimationSettings.mesh_budget_bytes), drawn as primitives: %s",
            mech.path,
            budget / MEGABYTE,
            ", ".join(over_budget),
        )
    summary = MeshSummary(n_embedded, budget - left, budget, tuple(primitive_links))
    return tuple(out), summary


@dataclass(frozen=True)
class _MeshFile:
    """A mesh visual's file and scale (what :func:`_link_meshes` reads)."""

    filename: str
    scale: tuple[float, ...] | None


def _description_links(description: TreeDescription, default_rgba):
    """Return the bodies as (name, [(kind, dims or mesh file, origin (4, 4), rgba)], has
    mass), in the description's order (the world first when it has visuals of its own)."""
    links = [(b.name, b.visuals, b.inertia.mass > 0) for b in description.bodies]
    if description.world_frame:
        links.insert(0, (WORLD_LINK, description.world_visuals, False))
    out = []
    for name, visuals, massive in links:
        items = []
        for vis in visuals:
            origin = vis.placement.homogeneous
            rgba = tuple(default_rgba) if vis.rgba is None else vis.rgba
            if vis.kind == "mesh":
                items.append(("mesh", _MeshFile(str(vis.mesh_file), vis.dims), origin, rgba))
            else:
                items.append((vis.kind, tuple(vis.dims), origin, rgba))
        out.append((name, items, massive))
    return out


def _link_meshes(where, link, meshes, urdf_dir, trusted, left):
    """Return a link's mesh visuals to embed, or why it is drawn as a stick figure.

    Args:
        where: ``file: link 'name'``, for messages.
        link: the link's name.
        meshes: (visual index, mesh file (``filename``, ``scale``), origin (4, 4), rgba) of
            its mesh visuals.
        urdf_dir: the URDF's directory, resolved.
        trusted: trusted package share directories (see :func:`_trusted_roots`).
        left: what is left of the budget [bytes].

    Returns:
        list of :class:`VisualShape` (all fit), the bytes they need (over the
        budget), or None (a mesh cannot be drawn; a warning says why).
    """
    files = []
    for i, mesh, _, _ in meshes:
        found, outside = _resolve_mesh(mesh.filename, urdf_dir, trusted)
        if outside is not None:
            logger.warning(
                "%s visual %d: mesh file %r (%s) is outside the URDF's directory %s; not drawn",
                where,
                i,
                mesh.filename,
                outside,
                urdf_dir,
            )
            return None
        if found is None:
            logger.warning(
                "%s visual %d: mesh file %r not found; not drawn", where, i, mesh.filename
            )
            return None
        try:  # the page embeds the mesh: bound it (a FIFO is not is_file())
            size = check_input_file(found, limit=MAX_MESH_BYTES, what="mesh file")
        except ClosedChainError as exc:
            logger.warning("%s visual %d: %s; not drawn", where, i, exc)
            return None
        files.append((found, size))
    native = all(f.suffix.lower().lstrip(".") in NATIVE_MESH_FORMATS for f, _ in files)
    if native and sum(size for _, size in files) > left:  # embedded as they are: not read
        return sum(size for _, size in files)
    out = []
    for (i, mesh, origin, rgba), (found, _) in zip(meshes, files, strict=True):
        try:
            data = read_mesh(found)
        except ClosedChainError as exc:
            logger.warning("%s visual %d: %s; not drawn", where, i, exc)
            return None
        scale = mesh.scale
        dims = (1.0, 1.0, 1.0) if scale is None else _floats(np.broadcast_to(scale, 3))
        out.append(VisualShape(link, "mesh", dims, origin, rgba, found, data))
    need = sum(len(v.mesh_data.data) for v in out)
    return out if need <= left else need


def _floats(x) -> tuple[float, ...]:
    return tuple(float(v) for v in np.asarray(x, dtype=float).ravel())


def _frame_with_z(axis: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Return a (4, 4) frame at ``origin`` [m] whose z axis is the unit ``axis``."""
    n1, n2 = axis_basis(axis)
    T = np.eye(4)
    T[:3, :3] = np.column_stack((n1, n2, axis))
    T[:3, 3] = origin
    return T


def _find_pin(cylinders, axis: np.ndarray, tol: float) -> tuple[float, float] | None:
    """Return (offset along the axis [m], radius [m]) of the largest coaxial cylinder.

    Args:
        cylinders: (placement in the joint frame (4, 4), radius [m], length [m]).
        axis: joint axis in the joint frame, unit, shape (3,).
        tol: angle tolerance [rad] and relative offset tolerance [-].
    """
    best = None
    for T, radius, length in cylinders:
        c, z = T[:3, 3], T[:3, 2]
        off_axis = np.linalg.norm(c - (c @ axis) * axis)
        if np.linalg.norm(np.cross(z, axis)) <= tol and off_axis <= tol * max(length, radius):
            if best is None or radius > best[1]:
                best = (float(c @ axis), float(radius))
    return best


def _cylinders(visuals, link: str, jMl: np.ndarray):
    return [
        (jMl @ v.origin, v.dims[0], v.dims[1])
        for v in visuals
        if v.link == link and v.kind == "cylinder"
    ]


def joint_markers(
    mech: Mechanism, visuals=(), *, settings: AnimationSettings = DEFAULT_SETTINGS
) -> tuple[JointMarker, ...]:
    """Return the markers of the actuated joints and the loop joints.

    A loop marker is carried by the predecessor link, an actuated-joint marker
    by the joint's child link. Its z axis is the joint axis. It sits on the
    joint's pin when one of the two links has a cylinder visual coaxial with
    the joint (the largest such), otherwise at the joint origin (which for a
    spherical mechanism is the common centre).

    Args:
        mech: the mechanism.
        visuals: the URDF visuals (see :func:`read_visuals`), searched for pins.
        settings: gives the coaxiality tolerance.
    """
    model = mech.model
    q_neutral = pin.neutral(model)
    tol = settings.coaxial_tol
    out: list[JointMarker] = []
    for name in mech.actuated_joints:
        jid = model.getJointId(name)
        # URDF: the child link's frame is the joint frame; Pinocchio links the
        # JOINT frame to its parent link's BODY frame and the child's to it.
        fj = model.getFrameId(name, pin.FrameType.JOINT)
        child = next(
            (f for f in model.frames if f.parentFrame == fj and f.type == pin.FrameType.BODY),
            None,
        )
        if child is None:
            continue
        axis, shape = _joint_axis(model.joints[jid], q_neutral)
        jMc = child.placement.homogeneous
        cylinders = _cylinders(visuals, child.name, jMc)
        parent = model.frames[model.frames[fj].parentFrame]
        if parent.type == pin.FrameType.BODY:
            # Parent link in the joint frame at q = 0 (a revolute joint only turns
            # about the axis, which keeps coaxial cylinders coaxial).
            jMp = model.jointPlacements[jid].inverse() * parent.placement
            cylinders += _cylinders(visuals, parent.name, jMp.homogeneous)
        pin_ = _find_pin(cylinders, axis, tol) if shape == "ring" else None
        offset, pin_radius = pin_ if pin_ else (0.0, 0.0)
        cMj = np.linalg.inv(jMc)
        origin = cMj @ _frame_with_z(axis, offset * axis)
        out.append(JointMarker("actuated", name, child.name, origin, shape, pin_radius))
    for spec in mech.description.loops:
        if spec.type == COUPLING:  # it joins two coordinates, no two frames: no marker
            continue
        shape = "ring" if spec.type in ("revolute", "prismatic") else "ball"
        # In the cut-joint frames c1 and c2 the axis has the same coordinates
        # (closed, they differ by a motion along or about the axis).
        cylinders = []
        for link, M in (
            (spec.predecessor, spec.predecessor_origin),
            (spec.successor, spec.successor_origin),
        ):
            cylinders += _cylinders(visuals, link, M.inverse().homogeneous)
        pin_ = _find_pin(cylinders, spec.axis, tol) if shape == "ring" else None
        offset, pin_radius = pin_ if pin_ else (0.0, 0.0)
        origin = spec.predecessor_origin.homogeneous @ _frame_with_z(spec.axis, offset * spec.axis)
        out.append(JointMarker("loop", spec.name, spec.predecessor, origin, shape, pin_radius))
    return tuple(out)


def _joint_axis(joint, q_neutral: np.ndarray) -> tuple[np.ndarray, str]:
    """Return (unit axis in the joint frame, marker shape) of a Pinocchio joint model.

    The axis of a 1-dof joint is read from its motion subspace S (shape (6, 1):
    linear, angular): the angular part for a revolute joint (aligned,
    unaligned, unbounded), the linear part for a prismatic one. Other joints
    get a ball marker.
    """
    if joint.nv != 1:
        return np.array([0.0, 0.0, 1.0]), "ball"
    jdata = joint.createData()
    joint.calc(jdata, q_neutral)
    S = np.asarray(jdata.S, dtype=float).ravel()
    axis = S[3:] if np.linalg.norm(S[3:]) > 0 else S[:3]
    return axis / np.linalg.norm(axis), "ring"


def _bodies(mech: Mechanism, links: list[str], root: str) -> tuple[Body, ...]:
    model = mech.model
    bodies = []
    for link in links:
        if not model.existFrame(link, pin.FrameType.BODY):
            logger.warning("%s: link %r is not in the Pinocchio model; not drawn", mech.path, link)
            continue
        fid = model.getFrameId(link, pin.FrameType.BODY)
        moving = model.frames[fid].parentJoint != 0
        bodies.append(Body(link, fid, scene_path(root, link), moving))
    return tuple(bodies)


# -- the motion ----------------------------------------------------------------
