r"""Read MuJoCo MJCF models through MuJoCo's own compiler.

An MJCF file (root ``<mujoco>``) is compiled by MuJoCo (``mujoco.MjSpec``,
the ``mujoco`` package: ``pip install mujoco`` or closedchain's ``mjcf``
extra), and the tree, loops and passive terms are read from the compiled
``MjModel``. Everything MuJoCo resolves is then MuJoCo's: ``<default>``
classes and ``childclass``, ``<include>`` (confined to the model's folder),
``<frame>``, ``<replicate>``, euler sequences and angle units, inertias
inferred from geoms and meshes, ``autolimits``, joint ``ref``. The result is a
:class:`closedchain.description.TreeDescription` (built into the
Pinocchio model by :func:`closedchain.build.build_model`) inside a
:class:`closedchain.description.MechanismDescription` carrying the loops, actuated joints and
passive terms.

=================================  =============================================
compiled MjModel                   closedchain
=================================  =============================================
bodies (``body_parentid``,         bodies with their placement at ``qpos0``,
``body_pos``/``body_quat``,        mass, centre of mass and inertia; a BODY
``body_mass``, ``body_ipos``,      frame named after each (the world body:
``body_inertia``/``body_iquat``)   :data:`closedchain.urdf.WORLD_LINK`)
``hinge`` / ``slide``              revolute / prismatic joint about
                                   ``jnt_axis`` at ``jnt_pos``; its q is
                                   MuJoCo's qpos (the body sits at its
                                   placement at q = ``ref``); ``jnt_range``
                                   as limits when ``jnt_limited``, else
                                   +-:data:`UNLIMITED_RANGE`
``ball``                           spherical joint (q: quaternion x, y, z, w;
                                   its cone limit is not modelled: logged)
``free``                           free flyer (top-level bodies; q: position,
                                   quaternion x, y, z, w; v in the body frame)
sites                              OP_FRAMEs named after them
``connect`` (bodies or sites)      spherical loop at the anchors of ``eq_data``
``weld`` (bodies or sites)         fixed loop (the compiled ``relpose``: the
                                   pose at qpos0 unless given)
``weld`` ``torquescale="0"``       spherical loop (MuJoCo's rotation rows are
                                   then zero: a point constraint)
``weld``, other ``torquescale``    fixed loop: MuJoCo scales the rotation rows
                                   (Jacobian and residual) by it, which only
                                   weights them in its soft solve; held
                                   rigidly, scaled rows are the same
                                   constraint (logged; MuJoCo's rigid limit
                                   agrees: ``closedchain.mjcf_reference``)
``joint`` (``polycoef``, padded    coupling loop q1 = c1 q2 + c0 + r1 - c1 r2
with zeros by MuJoCo)              (r: the joints' ``ref``, MuJoCo's
                                   polynomial is in q - ref); nonzero c2..c4
                                   or no ``joint2`` refused
inactive equalities                kept out of the loops, listed in the
(``eq_active0`` = 0)               mechanism's summary and a log line
actuators on joints                actuated joints
``jnt_stiffness``/``qpos_spring``  :class:`~closedchain.urdf.JointSpring`
``dof_damping``                    :class:`~closedchain.urdf.JointDamping`
``dof_armature``                   :class:`~closedchain.urdf.JointArmature`
``dof_frictionloss``               not modelled (logged)
``opt.gravity``                    the mechanism's gravity
keyframes                          named starts (the first: the assembly's)
geoms of groups 0 to 2             visuals (what MuJoCo's viewer shows by
                                   default): spheres, boxes, cylinders,
                                   capsules (a cylinder and two spheres),
                                   meshes from their files; others logged
=================================  =============================================

Refused with a message naming the element: tendon and flex equalities, a
``joint`` equality without ``joint2`` or with a nonzero c2..c4, an
``<include>`` outside the model's folder. A mesh file that is missing is left
out with a warning when its body's inertia does not come from it (an
``<inertial>``, or a body fixed to the world), else refused (MuJoCo would
infer the inertia from it); a missing texture file is left out with a warning.
Ignored: ``solref``/``solimp`` (closedchain's constraints are rigid),
contacts, tendons, sensors, cameras, lights. XML is read as safely as the
URDF reader's (no DTD, size-bounded: :func:`closedchain.urdf.read_xml`)
before MuJoCo sees it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pinocchio as pin

from .description import (
    BodyDescription,
    JointDescription,
    SiteDescription,
    TreeDescription,
    Visual,
)
from .exceptions import ModelFileError
from .urdf import (
    COUPLING_MULTIPLIER_MAX,
    COUPLING_OFFSET_MAX,
    WORLD_LINK,
    JointArmature,
    JointDamping,
    JointSpring,
    LoopSpec,
    MechanismDescription,
    read_xml,
)

logger = logging.getLogger(__name__)

#: Root element of an MJCF file.
MJCF_ROOT = "mujoco"

#: Limits [rad or m] given to an unlimited hinge or slide: beyond any motion,
#: within closedchain's bound on coordinates
#: (``closedchain.mechanism.COORDINATE_BOUND``).
UNLIMITED_RANGE = 1e4

#: Geom groups drawn (MuJoCo's viewer shows groups 0, 1 and 2 by default).
DRAWN_GEOM_GROUPS = 3

#: What to install when ``mujoco`` is missing.
INSTALL_HINT = "pip install mujoco (or pip install 'closedchain[mjcf]')"

#: MuJoCo's equality types read (by ``mjtEq`` value).
EQUALITY_KINDS = {0: "connect", 1: "weld", 2: "joint"}

#: MuJoCo's joint types (``mjtJoint`` values) and closedchain's kinds.
JOINT_KINDS = {0: "free", 1: "spherical", 2: "prismatic", 3: "revolute"}

#: Joint types of loops and couplings as written in :attr:`MechanismDescription.joints`.
URDF_JOINT_TYPES = {"free": "floating", "spherical": "spherical"}

_OBJ_SITE = 6
_TRN_JOINTS = (0, 1)  # mjTRN_JOINT, mjTRN_JOINTINPARENT
_GEOM_SPHERE, _GEOM_CAPSULE, _GEOM_CYLINDER, _GEOM_BOX, _GEOM_MESH = 2, 3, 5, 6, 7


def _mujoco():
    try:
        import mujoco
    except ImportError:
        raise ModelFileError(f"reading MJCF needs MuJoCo's compiler: {INSTALL_HINT}") from None
    return mujoco


def is_mjcf(path: Path) -> bool:
    """Return whether a file is MJCF (its root element is ``<mujoco>``), reading it safely."""
    return read_xml(path, what="model file").tag == MJCF_ROOT


def _check_includes(path: Path, folder: Path, seen: set[Path]) -> None:
    """Check an MJCF file and its ``<include>`` files: safe XML, inside ``folder``."""
    root = read_xml(path, what="MJCF file")
    for include in root.iter("include"):
        name = include.get("file")
        target = (path.parent / (name or "")).resolve()
        if not name or not target.is_relative_to(folder):
            raise ModelFileError(
                f"{path}: line {include.sourceline}: <include file={name!r}> is outside the "
                f"model's folder {folder}; valid: a file under it"
            )
        if target not in seen:
            seen.add(target)
            _check_includes(target, folder, seen)


def _quat(wxyz) -> np.ndarray:
    w, x, y, z = (float(c) for c in wxyz)
    return pin.Quaternion(w, x, y, z).normalized().matrix()


def _se3(pos, wxyz) -> pin.SE3:
    return pin.SE3(_quat(wxyz), np.array(pos, dtype=float))


def _pin_values(kind: str, qpos) -> tuple[float, ...]:
    """Return a joint's MuJoCo qpos entries in Pinocchio's convention (quaternion x, y, z, w)."""
    qpos = [float(x) for x in qpos]
    if kind in ("spherical", "free"):
        # MuJoCo normalizes a quaternion of qpos before use (a keyframe's may not be unit).
        k = 0 if kind == "spherical" else 3
        w, x, y, z = np.array(qpos[k : k + 4]) / np.linalg.norm(qpos[k : k + 4])
        return (*qpos[:k], float(x), float(y), float(z), float(w))
    return tuple(qpos)


def compile_mjcf(path: Path, *, spec_edit=None):
    """Compile an MJCF file with MuJoCo; return ``(spec, model, missing)``.

    Missing mesh files are handled as the module docstring says; ``missing`` maps a
    body's name to placeholders of its drawn mesh geoms whose files are missing.

    Args:
        path: the MJCF file.
        spec_edit: a function called with the ``MjSpec`` before compiling (tests
            and the acceptance script zero passive terms this way), or None.

    Raises:
        ModelFileError: MuJoCo is missing (names what to install), unsafe XML, an
            include outside the folder, or MuJoCo's compiler refuses the model.
    """
    mujoco = _mujoco()
    path = Path(path)
    folder = path.resolve().parent
    _check_includes(path.resolve(), folder, {path.resolve()})
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except Exception as exc:  # MuJoCo's parser: ValueError and its own errors
        raise ModelFileError(
            f"{path}: MuJoCo cannot read it: {' '.join(str(exc).split())}"
        ) from None
    _drop_missing_textures(path, spec)
    missing = _drop_missing_meshes(path, spec)
    if spec_edit is not None:
        spec_edit(spec)
    try:
        model = spec.compile()
    except Exception as exc:
        raise ModelFileError(
            f"{path}: MuJoCo cannot compile it: {' '.join(str(exc).split())}"
        ) from None
    return spec, model, missing


def _mesh_path(path: Path, spec, mesh) -> Path:
    meshdir = Path(spec.meshdir or "")
    base = path.parent if not meshdir.is_absolute() else Path()
    return (base / meshdir / mesh.file).resolve()


def _drop_missing_meshes(path: Path, spec) -> dict[str, list[Visual]]:
    """Delete mesh geoms whose files are missing where the body's inertia does not need them.

    Returns:
        body name -> placeholders of its drawn geoms left out (mesh visuals naming the
        missing file: the drawing stands a stick figure in for them and says why).
    """
    mujoco = _mujoco()
    files = {m.name: _mesh_path(path, spec, m) for m in spec.meshes if m.file}
    missing = {name: file for name, file in files.items() if not file.is_file()}
    if not missing:
        return {}
    from_geoms = spec.compiler.inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    placeholders: dict[str, list[Visual]] = {}
    for geom in list(spec.geoms):
        if geom.meshname not in missing:
            continue
        body = geom.parent
        if _moves(spec, body) and (from_geoms or not body.explicitinertial):
            raise ModelFileError(
                f"{path}: mesh file {missing[geom.meshname].name!r} is missing, and MuJoCo "
                f"infers body {body.name!r}'s inertia from it; valid: the file present, or an "
                "<inertial>"
            )
        if geom.group < DRAWN_GEOM_GROUPS:
            rgba = tuple(float(x) for x in geom.rgba)
            placeholder = Visual(
                "mesh", (1.0, 1.0, 1.0), pin.SE3.Identity(), rgba, missing[geom.meshname]
            )
            placeholders.setdefault(body.name or WORLD_LINK, []).append(placeholder)
        spec.delete(geom)
    for mesh in list(spec.meshes):
        if mesh.name in missing:
            spec.delete(mesh)
    logger.warning(
        "%s: mesh files missing (their geoms are not drawn; inertias are the <inertial>s): %s",
        path,
        ", ".join(sorted({f.name for f in missing.values()})),
    )
    return placeholders


def _drop_missing_textures(path: Path, spec) -> None:
    """Delete textures whose files are missing (they only colour the drawing)."""
    texdir = Path(spec.texturedir or "")
    base = path.parent if not texdir.is_absolute() else Path()
    missing = [t for t in spec.textures if t.file and not (base / texdir / t.file).is_file()]
    if not missing:
        return
    names = {t.name for t in missing}
    for material in spec.materials:
        material.textures = ["" if name in names else name for name in material.textures]
    logger.warning(
        "%s: texture files missing (not drawn): %s",
        path,
        ", ".join(sorted(t.file for t in missing)),
    )
    for texture in missing:
        spec.delete(texture)


def _moves(spec, body) -> bool:
    """Return whether a spec body moves (it or an ancestor has a joint)."""
    while body is not None and body.name != spec.worldbody.name:
        if len(body.joints):
            return True
        body = body.parent
    return False


class _Reader:
    """One compiled model read into a description, loops and passive terms."""

    def __init__(self, path: Path, spec, model, missing: dict[str, list[Visual]]) -> None:
        self.mujoco = _mujoco()
        self.path, self.spec, self.m = path, spec, model
        self.missing = missing
        m = model
        self.body_names = [
            self.name(self.mujoco.mjtObj.mjOBJ_BODY, b, "body") for b in range(m.nbody)
        ]
        self.body_names[0] = WORLD_LINK
        self.kinds = [JOINT_KINDS[int(t)] for t in m.jnt_type]
        taken = {self.name(self.mujoco.mjtObj.mjOBJ_JOINT, j, "") for j in range(m.njnt)}
        self.joint_names = []
        for j in range(m.njnt):
            name = self.name(self.mujoco.mjtObj.mjOBJ_JOINT, j, "")
            if not name:
                body = self.body_names[m.jnt_bodyid[j]]
                name = f"{body}_joint{j}"
                while name in taken:
                    name += "_"
            self.joint_names.append(name)
        self.site_names = [
            self.name(self.mujoco.mjtObj.mjOBJ_SITE, s, "site") for s in range(m.nsite)
        ]

    def name(self, objtype, i: int, prefix: str) -> str:
        name = self.mujoco.mj_id2name(self.m, objtype, i)
        return name if name else (f"{prefix}{i}" if prefix else "")

    # -- the tree ------------------------------------------------------------
    def joint(self, j: int) -> JointDescription:
        m, kind = self.m, self.kinds[j]
        adr = m.jnt_qposadr[j]
        nq = {"free": 7, "spherical": 4}.get(kind, 1)
        q0 = _pin_values(kind, m.qpos0[adr : adr + nq])
        lower, upper = -UNLIMITED_RANGE, UNLIMITED_RANGE
        if kind in ("revolute", "prismatic") and m.jnt_limited[j]:
            lower, upper = (float(x) for x in m.jnt_range[j])
        elif kind == "spherical" and m.jnt_limited[j]:
            logger.info(
                "%s: ball joint %r: its cone limit (range %g rad) is not modelled",
                self.path,
                self.joint_names[j],
                float(np.max(m.jnt_range[j])),
            )
        return JointDescription(
            name=self.joint_names[j],
            kind=kind,
            axis=np.array(m.jnt_axis[j], dtype=float),
            position=np.array(m.jnt_pos[j], dtype=float),
            q0=q0,
            lower=lower,
            upper=upper,
        )

    def inertia(self, b: int) -> pin.Inertia:
        m = self.m
        R = _quat(m.body_iquat[b])
        return pin.Inertia(
            float(m.body_mass[b]),
            np.array(m.body_ipos[b], dtype=float),
            R @ np.diag(m.body_inertia[b]) @ R.T,
        )

    def visuals(self, b: int) -> tuple[Visual, ...]:
        m = self.m
        out: list[Visual] = list(self.missing.get(self.body_names[b], ()))
        skipped = []
        for g in np.flatnonzero(m.geom_bodyid == b):
            if m.geom_group[g] >= DRAWN_GEOM_GROUPS:
                continue
            kind, size = int(m.geom_type[g]), m.geom_size[g]
            M = _se3(m.geom_pos[g], m.geom_quat[g])
            mat = m.geom_matid[g]
            rgba = tuple(float(x) for x in (m.mat_rgba[mat] if mat >= 0 else m.geom_rgba[g]))
            if kind == _GEOM_SPHERE:
                out.append(Visual("sphere", (float(size[0]),), M, rgba))
            elif kind == _GEOM_BOX:
                out.append(Visual("box", tuple(2.0 * float(x) for x in size), M, rgba))
            elif kind in (_GEOM_CYLINDER, _GEOM_CAPSULE):
                r, half = float(size[0]), float(size[1])
                out.append(Visual("cylinder", (r, 2.0 * half), M, rgba))
                if kind == _GEOM_CAPSULE:
                    for end in (-half, half):
                        cap = M * pin.SE3(np.eye(3), np.array([0.0, 0.0, end]))
                        out.append(Visual("sphere", (r,), cap, rgba))
            elif kind == _GEOM_MESH:
                mesh = m.geom_dataid[g]
                rel = m.paths[m.mesh_pathadr[mesh] :].split(b"\0", 1)[0].decode()
                file = (self.path.parent / rel).resolve()
                # MuJoCo moved the mesh to its inertial frame and the geom by as much:
                # the file's vertices are drawn in the geom frame times that move's inverse.
                offset = _se3(m.mesh_pos[mesh], m.mesh_quat[mesh])
                scale = tuple(float(x) for x in m.mesh_scale[mesh])
                out.append(Visual("mesh", scale, M * offset.inverse(), rgba, file))
            else:
                skipped.append(str(self.mujoco.mjtGeom(kind).name).removeprefix("mjGEOM_").lower())
        if skipped:
            logger.info(
                "%s: body %r: geoms of type %s are not drawn",
                self.path,
                self.body_names[b],
                ", ".join(sorted(set(skipped))),
            )
        return tuple(out)

    def description(self) -> TreeDescription:
        m = self.m
        bodies = []
        for b in range(1, m.nbody):
            if m.body_mocapid[b] >= 0:
                logger.info("%s: mocap body %r is read as fixed", self.path, self.body_names[b])
            joints = range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
            bodies.append(
                BodyDescription(
                    name=self.body_names[b],
                    parent=self.body_names[m.body_parentid[b]],
                    placement=_se3(m.body_pos[b], m.body_quat[b]),
                    joints=tuple(self.joint(j) for j in joints),
                    inertia=self.inertia(b),
                    visuals=self.visuals(b),
                )
            )
        sites = tuple(
            SiteDescription(
                self.site_names[s],
                self.body_names[m.site_bodyid[s]],
                _se3(m.site_pos[s], m.site_quat[s]),
            )
            for s in range(m.nsite)
        )
        keyframes = {}
        for k in range(m.nkey):
            name = self.name(self.mujoco.mjtObj.mjOBJ_KEY, k, "key")
            keyframes[name] = {
                self.joint_names[j]: _pin_values(
                    self.kinds[j],
                    m.key_qpos[k][m.jnt_qposadr[j] : m.jnt_qposadr[j] + _nq(self.kinds[j])],
                )
                for j in range(m.njnt)
            }
        loops, inactive = self.equalities()
        self.loops = loops
        return TreeDescription(
            name=self.spec.modelname or self.path.stem,
            path=self.path,
            bodies=tuple(bodies),
            world_visuals=self.visuals(0),
            sites=sites,
            keyframes=keyframes,
            inactive=inactive,
        )

    # -- equalities ----------------------------------------------------------
    def end(self, e: int, side: int, local: pin.SE3) -> tuple[str, pin.SE3]:
        """Return (body, frame in the body) of one side of a body or site equality."""
        m = self.m
        obj = (m.eq_obj1id, m.eq_obj2id)[side][e]
        if m.eq_objtype[e] == _OBJ_SITE:
            return self.body_names[m.site_bodyid[obj]], _se3(m.site_pos[obj], m.site_quat[obj])
        return self.body_names[obj], local

    def equalities(self) -> tuple[tuple[LoopSpec, ...], tuple[str, ...]]:
        m = self.m
        loops, inactive = [], []
        names = [self.name(self.mujoco.mjtObj.mjOBJ_EQUALITY, e, "") for e in range(m.neq)]
        for e in range(m.neq):
            kind = EQUALITY_KINDS.get(int(m.eq_type[e]))
            label = str(self.mujoco.mjtEq(int(m.eq_type[e])).name).removeprefix("mjEQ_").lower()
            name = names[e] or f"{label}{e}"
            while not names[e] and name in names:
                name += "_"
            where = f"{self.path}: <equality> <{label} name={name!r}>"
            if kind is None:
                raise ModelFileError(
                    f"{where}: {label} equalities are not read; valid: "
                    f"{', '.join(EQUALITY_KINDS.values())}"
                )
            if not m.eq_active0[e]:
                inactive.append(f"{label} {name}")
                continue
            data = np.array(m.eq_data[e], dtype=float)
            if kind == "joint":
                loops.append(self.coupling(e, name, where, data))
                continue
            if kind == "connect":
                ends = [
                    self.end(e, 0, pin.SE3(np.eye(3), data[0:3])),
                    self.end(e, 1, pin.SE3(np.eye(3), data[3:6])),
                ]
                loop_type = "spherical"
            else:
                ends = [
                    self.end(e, 0, _se3(data[3:6], data[6:10])),
                    self.end(e, 1, pin.SE3(np.eye(3), data[0:3])),
                ]
                torquescale = float(data[10])
                loop_type = "spherical" if torquescale == 0.0 else "fixed"
                if torquescale not in (0.0, 1.0):
                    logger.info(
                        "%s: torquescale=%g weights MuJoCo's soft rotation rows; a rigid weld "
                        "holds the same constraint",
                        where,
                        torquescale,
                    )
            loops.append(
                LoopSpec(
                    name=name,
                    type=loop_type,
                    predecessor=ends[0][0],
                    successor=ends[1][0],
                    predecessor_origin=ends[0][1],
                    successor_origin=ends[1][1],
                    axis=np.array([0.0, 0.0, 1.0]),
                )
            )
        if inactive:
            logger.info(
                "%s: inactive equalities (eq_active0 = 0), kept out of the loops: %s",
                self.path,
                ", ".join(inactive),
            )
        return tuple(loops), tuple(inactive)

    def coupling(self, e: int, name: str, where: str, data: np.ndarray) -> LoopSpec:
        m = self.m
        j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        if j2 < 0:
            raise ModelFileError(
                f"{where}: a joint equality without joint2 locks joint "
                f"{self.joint_names[j1]!r} at a value, which closedchain does not read; "
                "valid: joint1 and joint2"
            )
        if np.any(data[2:5] != 0.0):
            raise ModelFileError(
                f"{where}: polycoef {' '.join(f'{c:g}' for c in data[:5])}: only a linear "
                "coupling q1 = c0 + c1 q2 is read; valid: c2 = c3 = c4 = 0"
            )
        for j in (j1, j2):
            if self.kinds[j] not in ("revolute", "prismatic"):
                name, kind = self.joint_names[j], self.kinds[j]
                raise ModelFileError(f"{where}: joint {name!r} is {kind}; valid: hinge, slide")
        r1, r2 = float(m.qpos0[m.jnt_qposadr[j1]]), float(m.qpos0[m.jnt_qposadr[j2]])
        c0, c1 = float(data[0]), float(data[1])
        offset = c0 + r1 - c1 * r2
        if not abs(c1) <= COUPLING_MULTIPLIER_MAX or not abs(offset) <= COUPLING_OFFSET_MAX:
            raise ModelFileError(
                f"{where}: polycoef c1 = {c1:.6g}, offset {offset:.6g}: beyond the bounds; "
                f"valid: |c1| <= {COUPLING_MULTIPLIER_MAX:g} (COUPLING_MULTIPLIER_MAX) and "
                f"|c0 + ref1 - c1 ref2| <= {COUPLING_OFFSET_MAX:g} (COUPLING_OFFSET_MAX)"
            )
        return LoopSpec(
            name=name,
            type="coupling",
            predecessor=self.body_names[m.jnt_bodyid[j2]],
            successor=self.body_names[m.jnt_bodyid[j1]],
            predecessor_origin=pin.SE3.Identity(),
            successor_origin=pin.SE3.Identity(),
            axis=np.array([0.0, 0.0, 1.0]),
            joint=self.joint_names[j1],
            mimics=self.joint_names[j2],
            multiplier=c1,
            # MuJoCo's polynomial is in q - ref: q1 - r1 = c0 + c1 (q2 - r2).
            offset=offset,
        )

    # -- the rest ------------------------------------------------------------
    def actuated(self) -> tuple[str, ...]:
        m, out, other = self.m, [], []
        for a in range(m.nu):
            if int(m.actuator_trntype[a]) in _TRN_JOINTS:
                joint = self.joint_names[m.actuator_trnid[a][0]]
                if joint not in out:
                    out.append(joint)
            else:
                other.append(self.name(self.mujoco.mjtObj.mjOBJ_ACTUATOR, a, "actuator"))
        if other:
            logger.info(
                "%s: actuators on tendons or sites are not read as actuated joints: %s",
                self.path,
                ", ".join(other),
            )
        return tuple(out)

    def passive(self):
        m = self.m
        springs, dampings, armatures, friction = [], [], [], []
        for j in range(m.njnt):
            name, kind, dof = self.joint_names[j], self.kinds[j], m.jnt_dofadr[j]
            if m.jnt_stiffness[j] > 0.0:
                if kind in ("revolute", "prismatic"):
                    ref = float(m.qpos_spring[m.jnt_qposadr[j]])
                    springs.append(JointSpring(name, float(m.jnt_stiffness[j]), ref))
                else:
                    logger.info(
                        "%s: %s joint %r: its stiffness is not modelled", self.path, kind, name
                    )
            if m.dof_damping[dof] > 0.0:
                dampings.append(JointDamping(name, float(m.dof_damping[dof])))
            if m.dof_armature[dof] > 0.0:
                armatures.append(JointArmature(name, float(m.dof_armature[dof])))
            if m.dof_frictionloss[dof] > 0.0:
                friction.append(name)
        gravcomp = [self.body_names[b] for b in np.flatnonzero(m.body_gravcomp)]
        if gravcomp:
            logger.info(
                "%s: gravity compensation (gravcomp) is not modelled: %s",
                self.path,
                ", ".join(gravcomp),
            )
        if friction:
            logger.info(
                "%s: joint friction loss (frictionloss) is not modelled: %s",
                self.path,
                ", ".join(friction),
            )
        return tuple(springs), tuple(dampings), tuple(armatures)

    def gravity(self) -> np.ndarray:
        m = self.m
        if m.opt.disableflags & int(self.mujoco.mjtDisableBit.mjDSBL_GRAVITY):
            return np.zeros(3)
        return np.array(m.opt.gravity, dtype=float)


def _nq(kind: str) -> int:
    return {"free": 7, "spherical": 4}.get(kind, 1)


def read_mjcf(path: str | Path, *, spec_edit=None) -> tuple[MechanismDescription, np.ndarray]:
    """Read an MJCF file through MuJoCo's compiler (rule: the module docstring).

    Args:
        path: the MJCF file.
        spec_edit: see :func:`compile_mjcf`.

    Returns:
        The model (its ``description`` set, ``xml`` None) and its gravity [m/s^2], shape (3,).

    Raises:
        ModelFileError: see :func:`compile_mjcf`, and the refusals of the module docstring.
    """
    path = Path(path)
    spec, model, missing = compile_mjcf(path, spec_edit=spec_edit)
    reader = _Reader(path, spec, model, missing)
    description = reader.description()
    springs, dampings, armatures = reader.passive()
    joints = {
        j.name: URDF_JOINT_TYPES.get(j.kind, j.kind) for b in description.bodies for j in b.joints
    }
    urdf = MechanismDescription(
        path=path,
        robot_name=description.name,
        links=(WORLD_LINK, *(b.name for b in description.bodies)),
        joints=joints,
        loops=reader.loops,
        actuated=reader.actuated(),
        springs=springs,
        dampings=dampings,
        armatures=armatures,
        tree=description,
    )
    return urdf, reader.gravity()
