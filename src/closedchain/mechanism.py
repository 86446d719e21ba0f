"""The Mechanism: Pinocchio tree, loops, row selection, coordinates; :func:`load`.

Everything that depends only on the mechanism is done here, once: loop frames
are added to the model, a closed configuration ``q_ref`` is found (within the
joint limits where one exists), the independent constraint rows are selected
over configurations along the motion from it, independent coordinates are
chosen, and Pinocchio constraint models are built for validation.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import threading
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pinocchio as pin
from threadpoolctl import threadpool_limits

from ._invariants import prove_unclosable
from ._locking import exclusive
from .build import build_model, check_size, configuration
from .closure import (
    AssemblySettings,
    LoopClosure,
    RowSelection,
    SelectionSettings,
    assemble_closure,
    layer_jacobian,
    sample_configurations,
    solve_closure,
)
from .constraints import ConstraintLayer, RowInfo
from .exceptions import (
    AssemblyError,
    ClosedChainError,
    InvalidArgumentError,
    LoopClosureError,
    ModelFileError,
    ModelTooLargeError,
    UnknownChoiceError,
    ValidationUnavailableError,
    check_settings,
    quoted,
    shorten,
)
from .mjcf import MJCF_ROOT, read_mjcf
from .passive import PassiveTerms, passive_terms
from .pindata import data_bytes, data_cost_formula, max_nv_for, new_data
from .urdf import WORLD_LINK, MechanismDescription, name_list, parse_urdf, read_xml

__all__ = [
    "DEFAULT_GRAVITY",
    "DEFAULT_LOAD_SETTINGS",
    "LoadSettings",
    "Mechanism",
    "load",
]

logger = logging.getLogger(__name__)

#: Largest accepted deviation from 1 of the norm of a continuous joint's
#: (cos, sin) or a quaternion in a configuration passed to closedchain.
NORMALIZATION_TOL = 1e-9
#: Largest deviation of R^T R from the identity accepted for a rotation matrix given to
#: ``Mechanism.q_from`` (entries; a matrix rounded to 9 digits passes).
ROTATION_TOL = 1e-8

#: Largest |q| [rad or m] of a 1-dof coordinate a configuration may hold: beyond it a
#: double resolves the coordinate more coarsely than 1e-10 (its ulp), so an integrator's
#: steps are lost in round-off (a crank at 1e17 rad does not move at all).
COORDINATE_BOUND = 1e6

#: Root joints :func:`load` can put between the world and the URDF's root link.
ROOT_JOINTS = {None: None, "free": pin.JointModelFreeFlyer, "planar": pin.JointModelPlanar}

#: Standard gravity along world -z [m/s^2].
DEFAULT_GRAVITY = (0.0, 0.0, -9.81)

#: Significant digits of each number in :meth:`Mechanism.digest`: fewer than a
#: double holds, so that a last-bit difference of sin/cos between two machines'
#: math libraries (placements from rpy) leaves the digest as it is.
DIGEST_DIGITS = 12

#: Magnitude [SI] below which a number enters :meth:`Mechanism.digest` as 0
#: (round-off such as cos(pi/2) = 6e-17, and -0.0).
DIGEST_ZERO = 1e-12

#: Largest norm of the gravity vector accepted [m/s^2] (1e5 g, far beyond any
#: physical use): torques, energies and their squares of ordinary models stay
#: finite (--gravity 1e308 overflowed into numpy warnings and NaN).
MAX_GRAVITY_NORM = 1e6


def max_nv(settings: LoadSettings) -> int:
    """Return the largest nv whose Pinocchio ``Data`` fits ``settings.max_data_bytes``."""
    return max_nv_for(settings.max_data_bytes)


@dataclass(frozen=True)
class LoadSettings:
    """Settings of the work :func:`load` does once per mechanism.

    Attributes:
        n_samples: closed configurations the row selection starts walks from:
            q_ref, then random starts (every joint random: base joints take
            random poses) closed by Gauss-Newton.
        max_attempts: random starts tried for them, and for q_ref when none of
            the given starts closes (:func:`load`).
        walk_steps: from each, steps along the motion (null space of J),
            each assembled and added to the samples; with fewer roots, the walk
            goes on until ``n_samples * (1 + walk_steps)`` samples.
        walk_step: length of one such step [rad or m].
        rank_tol: a singular value counts towards the rank of J when it
            exceeds ``rank_tol`` times max(1, the largest singular value).
        cond_JD_max: largest acceptable condition number of J_D when choosing
            independent coordinates.
        prismatic_range: sampling range [m] for unbounded prismatic coordinates.
        seed: seed of the sampling.
        max_data_bytes: largest memory [bytes] one Pinocchio ``Data`` may take
            (:func:`closedchain.pindata.data_bytes`: about 620 nv^2 bytes
            with the compiled core, which leaves out Pinocchio's four nv^3
            second-order tensors; 33 nv^3 without it). 2 GB is nv <= 1796
            (nv <= 392 without the compiled core). A larger tree is refused
            before Pinocchio builds anything.
        mismatch_tol: a model whose loops close only to a least-squares residual
            at most this large [m or rad] (redundant rows that disagree: a rounded
            CAD export) is loaded at the least-squares minimum with a logged
            warning naming the loops; above it, :func:`load` refuses the model.
    """

    n_samples: int = 8
    max_attempts: int = 60
    walk_steps: int = 3
    walk_step: float = 0.3
    rank_tol: float = 1e-8
    cond_JD_max: float = 1e6
    prismatic_range: float = 1.0
    seed: int = 0
    max_data_bytes: float = 2e9
    mismatch_tol: float = 1e-4

    def selection(self) -> SelectionSettings:
        """The row-selection part of these settings."""
        return SelectionSettings(
            n_samples=self.n_samples,
            max_attempts=self.max_attempts,
            walk_steps=self.walk_steps,
            walk_step=self.walk_step,
            rank_tol=self.rank_tol,
            prismatic_range=self.prismatic_range,
            seed=self.seed,
        )


#: The defaults, shared (frozen).
DEFAULT_LOAD_SETTINGS = LoadSettings()


class Mechanism:
    """A closed-chain mechanism: a Pinocchio tree plus independent loop constraints.

    Do not build it directly: use :func:`load`.

    Attributes:
        name: robot name from the model file.
        path: the model file.
        model: Pinocchio model (with one frame per loop side added).
        data: Pinocchio data of closedchain's own computations (use it under
            ``lock``; closedchain's public functions do).
        lock: re-entrant lock that serializes the public functions on this
            mechanism: one Mechanism may be shared between threads, whose calls
            on it then take turns (:mod:`closedchain._locking`).
        description: what the files said: the tree, loops, motors, passive terms
            and scene (:class:`~closedchain.description.MechanismDescription`, whichever
            format was read; formerly ``urdf``, still readable with a deprecation
            warning).
        passive: the joint springs, damping and armature, terms of the dynamics
            (:class:`~closedchain.passive.PassiveTerms`; the armature is also the
            model's ``armature``).
        closure: the loop rows, their independent subset and the coordinate
            partition (:class:`~closedchain.closure.LoopClosure`).
        constraints: the independent rows, the ones every method uses.
        declared: all declared rows (redundant ones included).
        selected_rows: indices of the independent rows in ``declared.declared_rows``.
        nq, nv: configuration and velocity sizes.
        nc: number of independent constraint rows.
        mobility: nv - nc, degrees of freedom of the closed mechanism.
        actuated_joints: joints named by ``<transmission>`` elements, in the order
            they are declared (the URDF's, or ``name_mot``'s for a loops YAML): the
            order of every motor vector (:func:`~closedchain.forward_kinematics`'s
            ``motors``, ``inverse_dynamics(coordinates="actuated")``, ``--torque``).
        actuated_idx_v: their velocity indices in the same order (not sorted), shape
            (na,): ``tau[mech.actuated_idx_v] = motor_torques``.
        independent_idx_v: velocity indices of the independent coordinates, shape (mobility,).
        dependent_idx_v: the others, shape (nc,).
        root_joint: the root joint :func:`load` added (None, ``"free"``, ``"planar"``).
        independent_source: ``"urdf"``, ``"actuated"`` or ``"automatic"``.
        q_ref: an assembled configuration, shape (nq,).
        joint_names: the tree's joint names in tree order (Pinocchio's
            ``model.names`` without the universe; a root joint included).
        coordinate_names: one name per velocity coordinate.
        configuration_names: one name per configuration entry (``joint[k]`` for
            joints with several entries, e.g. a continuous joint's cos, sin).
    """

    def __init__(
        self,
        description: MechanismDescription,
        model: pin.Model,
        closure: LoopClosure,
        gravity: np.ndarray,
        passive: PassiveTerms,
    ) -> None:
        self.description = description
        self.passive = passive
        self.name = description.robot_name
        self.path = description.path
        self.model = model
        #: Re-entrant lock held by every public function working on this mechanism
        #: (:mod:`closedchain._locking`): calls from several threads take turns.
        self.lock = threading.RLock()
        self.data = new_data(model)
        self.closure = closure
        self.gravity = np.array(gravity, dtype=float)
        self.nq, self.nv = model.nq, model.nv
        self.joint_names: tuple[str, ...] = tuple(model.names[1:])
        names = []
        for j in range(1, model.njoints):
            jn = model.names[j]
            nvj = model.joints[j].nv
            names += [jn] if nvj == 1 else [f"{jn}[{k}]" for k in range(nvj)]
        self.coordinate_names: tuple[str, ...] = tuple(names)
        qnames = []
        for j in range(1, model.njoints):
            jn, nqj = model.names[j], model.joints[j].nq
            qnames += [jn] if nqj == 1 else [f"{jn}[{k}]" for k in range(nqj)]
        #: One name per configuration entry (differs from coordinate_names when nq != nv).
        self.configuration_names: tuple[str, ...] = tuple(qnames)
        self.actuated_joints = description.actuated
        # In actuated_joints' order (not coordinate_indices' sorted one): motor vectors
        # index tau and a by it.
        self.actuated_idx_v = np.array(
            [i for name in description.actuated for i in self.joint_indices_v(name)], dtype=int
        )
        self.q_ref = pin.neutral(model)
        self.root_joint: str | None = None
        self._pin_constraints: tuple | None = None
        self._workspace = None  # dynamics.base.Workspace, made on first use
        # A coupling q_j = m q_i + c ties its joints' coordinates, not their angles modulo
        # a turn: wrap_angles leaves them as they are.
        coupled = {
            name for spec in description.loops if spec.joint for name in (spec.joint, spec.mimics)
        }
        self._revolute_idx_q = np.array(
            [
                model.joints[j].idx_q
                for j in range(1, model.njoints)
                if model.joints[j].shortname().startswith("JointModelR")
                and model.joints[j].nq == model.joints[j].nv == 1
                and model.names[j] not in coupled
            ],
            dtype=int,
        )

    # -- rows and partition, owned by the closure ------------------------------
    @property
    def declared(self) -> ConstraintLayer:
        """Every declared row (redundant ones included)."""
        return self.closure.declared

    @property
    def constraints(self) -> ConstraintLayer:
        """The independent rows, the ones every method uses."""
        return self.closure.active

    @property
    def selected_rows(self) -> tuple[int, ...]:
        """Indices of the independent rows in ``declared.declared_rows``."""
        return self.closure.selected_rows

    @property
    def row_selection(self) -> RowSelection:
        """How the independent rows were chosen."""
        return self.closure.selection

    @property
    def independent_idx_v(self) -> np.ndarray:
        return self.closure.independent_idx_v

    @property
    def dependent_idx_v(self) -> np.ndarray:
        return self.closure.dependent_idx_v

    @property
    def independent_source(self) -> str:
        return self.closure.independent_source

    # -- sizes and coordinates -------------------------------------------------
    @property
    def nc(self) -> int:
        return self.constraints.nc

    @property
    def mobility(self) -> int:
        return self.nv - self.nc

    @property
    def rows(self) -> tuple[RowInfo, ...]:
        """The independent rows, in evaluation order."""
        return self.constraints.rows

    def joint_indices_v(self, joint: str) -> np.ndarray:
        """Return the velocity indices of a joint.

        Raises:
            ClosedChainError: unknown joint name (lists the valid ones).
        """
        if not self.model.existJointName(joint):
            raise ClosedChainError(
                f"{self.path}: unknown joint {quoted(joint)}; "
                f"joints: {name_list(self.model.names[1:], keep_order=True)}"
            )
        j = self.model.joints[self.model.getJointId(joint)]
        return np.arange(j.idx_v, j.idx_v + j.nv)

    def coordinate_indices(self, spec: Iterable[str | int] | str) -> np.ndarray:
        """Resolve joint names, velocity indices or a keyword to velocity indices.

        Args:
            spec: ``"actuated"``, ``"independent"``, ``"dependent"``, or an
                iterable of joint names and integer velocity indices.

        Returns:
            Sorted unique velocity indices; for a keyword, that attribute as it is
            (``"actuated"``: :attr:`actuated_idx_v`, in ``actuated_joints``' order).
        """
        if isinstance(spec, str):
            keywords = {
                "actuated": lambda: self.actuated_idx_v,
                "independent": lambda: self.independent_idx_v,
                "dependent": lambda: self.dependent_idx_v,
            }
            if spec in keywords:
                return np.array(keywords[spec](), dtype=int)
            spec = [spec]
        out: list[int] = []
        for item in spec:
            if isinstance(item, str):
                out += list(self.joint_indices_v(item))
            else:
                i = int(item)
                if not 0 <= i < self.nv:
                    raise ClosedChainError(f"velocity index {i} out of range 0..{self.nv - 1}")
                out.append(i)
        return np.unique(np.array(out, dtype=int))

    def q_from(self, values: Mapping[str, object], *, q_start=None) -> np.ndarray:
        """Return a configuration with the named joints at the given values.

        The other joints keep ``q_start``'s values (default :attr:`q_ref`). The result is
        not closed: hand it to :func:`~closedchain.assemble` with ``fixed=`` the joints
        to hold, e.g. ``assemble(mech, mech.q_from({"crank": 0.3}), fixed=["crank"])``.

        Args:
            values: joint name -> value, by joint kind:

                - revolute, prismatic (one entry of q): the angle [rad] or the
                  displacement [m];
                - continuous (q is (cos, sin)): the angle [rad];
                - spherical (q is a unit quaternion x, y, z, w): a rotation matrix,
                  shape (3, 3), a ``pinocchio.Quaternion``, or a quaternion
                  (x, y, z, w), shape (4,), of norm 1;
                - free flyer (q is x, y, z and a quaternion): a ``pinocchio.SE3``
                  or the 7 entries;
                - planar (q is x, y, cos, sin): x [m], y [m], angle [rad];
                - any other kind: its entries of q as they are.
            q_start: configuration the unnamed joints are taken from, shape (nq,).

        Returns:
            The configuration, shape (nq,).

        Raises:
            InvalidArgumentError: an unknown joint (the message lists the joints), or
                a value of the wrong shape, not finite, or not a rotation (naming the
                joint and what it takes).
        """
        q = self.check_q(self.q_ref if q_start is None else q_start, "q_start").copy()
        for name, value in values.items():
            if not isinstance(name, str) or not self.model.existJointName(name):
                raise InvalidArgumentError(
                    f"{self.path}: q_from: unknown joint {name!r}; joints: "
                    f"{', '.join(self.joint_names)}"
                )
            jm = self.model.joints[self.model.getJointId(name)]
            q[jm.idx_q : jm.idx_q + jm.nq] = _joint_configuration(name, jm, value)
        return q

    def check_q(self, q, name: str = "q") -> np.ndarray:
        """Return q as a float array of shape (nq,), or raise naming the argument."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.nq,):
            raise ClosedChainError(f"{name} has shape {q.shape}, expected ({self.nq},)")
        if not np.isfinite(q).all():
            raise ClosedChainError(f"{name} contains non-finite values: {q}")
        if self.nq != self.nv and not pin.isNormalized(self.model, q, NORMALIZATION_TOL):
            # A continuous joint's (cos, sin) or a quaternion off the unit
            # sphere gives Pinocchio a scaled rotation: wrong numbers, silently.
            for j in range(1, self.model.njoints):
                jm = self.model.joints[j]
                if jm.nq != jm.nv:
                    seg = q[jm.idx_q : jm.idx_q + jm.nq]
                    norm = float(np.linalg.norm(seg[-4:] if jm.nq > 4 else seg))
                    if abs(norm - 1.0) > NORMALIZATION_TOL:
                        raise ClosedChainError(
                            f"{name}: the configuration of joint {self.model.names[j]!r} "
                            f"(q[{jm.idx_q}:{jm.idx_q + jm.nq}] = {seg}) has norm {norm:.12g}, "
                            "expected 1 (use pinocchio.normalize)"
                        )
        return q

    def check_v(self, v, name: str = "v") -> np.ndarray:
        """Return v as a float array of shape (nv,), or raise naming the argument."""
        v = np.asarray(v, dtype=float)
        if v.shape != (self.nv,):
            raise ClosedChainError(f"{name} has shape {v.shape}, expected ({self.nv},)")
        if not np.isfinite(v).all():
            raise ClosedChainError(f"{name} contains non-finite values: {v}")
        return v

    def wrap_angles(self, q: np.ndarray) -> np.ndarray:
        """Return q with every revolute angle wrapped into [-pi, pi) (same physical pose).

        The joints a coupling loop ties keep their coordinates (its row holds for
        them, not for their angles modulo a turn).
        """
        q = np.array(q, dtype=float)
        idx = self._revolute_idx_q
        q[idx] = (q[idx] + np.pi) % (2.0 * np.pi) - np.pi
        return q

    def within_limits(self, q: np.ndarray) -> bool:
        """Return whether every 1-dof coordinate of q is within its URDF position limits."""
        lo, hi = self.model.lowerPositionLimit, self.model.upperPositionLimit
        return bool(np.all((q >= lo) | ~np.isfinite(lo)) and np.all((q <= hi) | ~np.isfinite(hi)))

    @exclusive
    def check_limits(
        self, q: np.ndarray, name: str = "q", *, urdf_limits: bool = True, opt_out: str = ""
    ) -> None:
        """Raise InvalidArgumentError when a coordinate of q is outside its joint limits.

        Every 1-dof coordinate is checked against :data:`COORDINATE_BOUND` and, with
        ``urdf_limits``, against its URDF ``<limit>`` where that is finite. The limits
        bound the coordinate, as in URDF, not the pose: a revolute joint with limits
        [-pi, pi] at 3.2 rad is outside them (a joint that turns freely is
        ``continuous``); :meth:`wrap_angles` gives the same pose within one turn.

        Args:
            q: configuration, shape (nq,).
            name: what q is called in the message (an argument or an option).
            urdf_limits: also check the URDF limits (else only the bound).
            opt_out: how to turn the URDF-limit check off, added to its message.
        """
        for j, outside, low, high in self.limit_checks(q[None, :], urdf_limits=urdf_limits):
            if outside[0]:
                value = float(q[self.model.joints[j].idx_q])
                hint = f"; {opt_out}" if opt_out and urdf_limits else ""
                raise InvalidArgumentError(
                    f"{name}: joint {self.model.names[j]!r} is at {value:.6g}, outside its "
                    f"limits [{low:.6g}, {high:.6g}] ({self.path}){hint}"
                )

    def limit_checks(self, qs: np.ndarray, *, urdf_limits: bool = True):
        """Yield ``(joint id, outside, low, high)`` for every 1-dof joint: which of the
        configurations ``qs`` put it outside its limits (low, high) [rad or m], inclusive.

        The rules of :meth:`check_limits`: :data:`COORDINATE_BOUND`, and the finite
        URDF ``<limit>`` with ``urdf_limits``.

        Args:
            qs: configurations, shape (N, nq).
            urdf_limits: also check the URDF limits (else only the bound).

        Yields:
            The joint's id, a bool array of shape (N,), and its limits.
        """
        lo, hi = self.model.lowerPositionLimit, self.model.upperPositionLimit
        for j in range(1, self.model.njoints):
            jm = self.model.joints[j]
            if jm.nq != 1:  # cos/sin pairs, quaternions, free flyers: no limits
                continue
            k = jm.idx_q
            x = qs[:, k]
            low, high = -COORDINATE_BOUND, COORDINATE_BOUND
            if urdf_limits:
                low = max(low, lo[k]) if np.isfinite(lo[k]) else low
                high = min(high, hi[k]) if np.isfinite(hi[k]) else high
            outside = ~((low <= x) & (x <= high))
            yield j, outside, float(low), float(high)

    def gravity_torque_scale(self) -> float:
        """Return the RMS generalized gravity force at ``q_ref`` [N m]: a natural torque scale.

        The coordinates of a root joint added by :func:`load` are left out:
        they carry the whole weight of the mechanism, which no actuator of
        its joints applies (on a free-flying 4-bar it would set the scale
        six times the joints' own loads).
        """
        g = pin.computeGeneralizedGravity(self.model, self.data, self.q_ref)
        if self.root_joint is not None:
            g = g[self.model.joints[1].nv :]
        return float(np.sqrt(np.mean(g**2))) if g.size else 0.0

    def random_configuration(self, rng: np.random.Generator, *, prismatic_range: float = 1.0):
        """Draw a configuration uniformly within joint limits clipped to one turn.

        Args:
            rng: random generator.
            prismatic_range: bound [m] used where a translation is unbounded.

        Returns:
            q, shape (nq,) (not assembled).
        """
        lo = np.array(self.model.lowerPositionLimit, dtype=float)
        hi = np.array(self.model.upperPositionLimit, dtype=float)
        for j in range(1, self.model.njoints):
            jm = self.model.joints[j]
            sl = slice(jm.idx_q, jm.idx_q + jm.nq)
            # Every revolute joint model (RX/RY/RZ, RevoluteUnaligned, RUB*, ...)
            # and only those start with "JointModelR"; a universal joint has two angles.
            name = jm.shortname()
            angles = name.startswith("JointModelR") or name == "JointModelUniversal"
            bound = np.pi if angles else prismatic_range
            if jm.nq != jm.nv:  # continuous, spherical, free flyer: normalize below
                bound = max(bound, 1.0)
            lo[sl] = np.maximum(np.nan_to_num(lo[sl], neginf=-bound), -bound)
            hi[sl] = np.minimum(np.nan_to_num(hi[sl], posinf=bound), bound)
        q = rng.uniform(lo, hi)
        return pin.normalize(self.model, q)

    # -- Pinocchio constraint models (validation reference, "pinocchio" method)
    @exclusive
    def pinocchio_constraints(self):
        """Return ``(models, datas, owners, data)`` of Pinocchio rigid constraints for the loops.

        Built and initialized (``initConstraintDynamics``) once per mechanism,
        with a Pinocchio data of their own. Raises ValidationUnavailableError
        for prismatic loops.
        """
        if self._pin_constraints is None:
            from .constraints import build_pinocchio_constraints

            cms, owners = build_pinocchio_constraints(self.model, self.declared)
            cds = pin.StdVec_RigidConstraintData()
            for cm in cms:
                cds.append(cm.createData())
            pdata = new_data(self.model)
            pin.initConstraintDynamics(self.model, pdata, cms, cds)
            self._pin_constraints = (cms, cds, owners, pdata)
        return self._pin_constraints

    def digest(self) -> str:
        """Return a SHA-256 hex digest of the model a motion of this mechanism depends on.

        It covers, per joint in tree order: name, type, parent, placement in the
        parent joint's frame, motion subspace S at the neutral configuration
        (the axis), the inertia of its body (mass, centre of mass,
        rotational inertia: fixed links folded in) and, where it has any, its
        spring, damping and armature; per loop: name, type,
        links, both origins and axis. Numbers enter rounded to
        :data:`DIGEST_DIGITS` significant digits (below :data:`DIGEST_ZERO`:
        0), so the digest is the same in every process and on every machine
        for the same model, and changes with any dimension, mass or axis.
        It does not depend on the file's path, comments, names of links,
        visuals, actuation or gravity (a load, not the mechanism).
        """

        def numbers(a) -> list[str]:
            return [
                "0" if abs(x) < DIGEST_ZERO else f"{x:.{DIGEST_DIGITS}g}"
                for x in np.ravel(np.asarray(a, dtype=float)).tolist()
            ]

        model, q0 = self.model, pin.neutral(self.model)
        passive = self.passive
        joints = []
        for j in range(1, model.njoints):
            jm, body = model.joints[j], model.inertias[j]
            jdata = jm.createData()
            jm.calc(jdata, q0)
            cols = slice(jm.idx_v, jm.idx_v + jm.nv)
            spring = np.flatnonzero(passive.spring_idx_v == jm.idx_v) if jm.nv == 1 else []
            terms = [
                *passive.stiffness[spring],
                *passive.reference[spring],
                *passive.damping[cols],
                *passive.armature[cols],
            ]
            joints.append(
                [
                    model.names[j],
                    jm.shortname(),
                    int(model.parents[j]),
                    numbers(model.jointPlacements[j].homogeneous[:3]),
                    numbers(jdata.S),
                    numbers([body.mass, *body.lever, *body.inertia.ravel()]),
                ]
                # Springs, damping, armature: only where a joint has one (the other
                # joints' entries stay as they were).
                + ([numbers(terms)] if any(terms) else [])
            )
        loops = [
            [
                spec.name,
                spec.type,
                spec.predecessor,
                spec.successor,
                numbers(spec.predecessor_origin.homogeneous[:3]),
                numbers(spec.successor_origin.homogeneous[:3]),
                numbers(spec.axis),
            ]
            # A coupling's joints and numbers (the other loops' entries stay as they were).
            + (
                [spec.joint, spec.mimics, *numbers([spec.multiplier, spec.offset])]
                if spec.joint
                else []
            )
            for spec in self.description.loops
        ]
        text = json.dumps({"joints": joints, "loops": loops}, separators=(",", ":"))
        return hashlib.sha256(text.encode("utf-8")).hexdigest()

    @exclusive
    def summary(self) -> dict:
        """Return a JSON-serialisable description (what ``closedchain info`` shows)."""
        loops = []
        for spec in self.description.loops:
            declared = [r.kind for r in self.declared.declared_rows if r.loop == spec.name]
            kept = [r.kind for r in self.rows if r.loop == spec.name]
            loops.append(
                {
                    "name": spec.name,
                    "type": spec.type,
                    "predecessor": spec.predecessor_frame or spec.predecessor,
                    "successor": spec.successor_frame or spec.successor,
                    "declared_rows": declared,
                    "independent_rows": kept,
                }
            )
            if spec.joint:  # a coupling q_joint = multiplier q_mimics + offset
                loops[-1].update(
                    joint=spec.joint,
                    mimics=spec.mimics,
                    multiplier=spec.multiplier,
                    offset=spec.offset,
                )
        tree = []
        for j in range(1, self.model.njoints):
            jm = self.model.joints[j]
            tree.append(
                {
                    "joint": self.model.names[j],
                    "type": jm.shortname(),
                    "parent": self.model.names[self.model.parents[j]],
                    "idx_q": jm.idx_q,
                    "idx_v": jm.idx_v,
                }
            )
        try:
            if self.declared.couplings:  # validate's reference: Pinocchio's mimic joints
                from .validation import mimic_reference

                mimic_reference(self)
            else:
                self.pinocchio_constraints()
            pin_ok = True
        except ValidationUnavailableError:
            pin_ok = False
        return {
            "name": self.name,
            "path": str(self.path),
            "nq": self.nq,
            "nv": self.nv,
            "root_joint": self.root_joint,
            "gravity": self.gravity.tolist(),
            "tree": tree,
            "loops": loops,
            "declared_rows": self.declared.nc,
            "independent_rows": self.nc,
            "row_selection": self.row_selection.as_dict(),
            "mobility": self.mobility,
            "actuated": [self.coordinate_names[i] for i in self.actuated_idx_v],
            "independent": [self.coordinate_names[i] for i in self.independent_idx_v],
            "independent_source": self.independent_source,
            "dependent": [self.coordinate_names[i] for i in self.dependent_idx_v],
            "q_ref": self.q_ref.tolist(),
            "pinocchio_reference": pin_ok,
            "inactive_equalities": list(
                () if self.description.tree is None else self.description.tree.inactive
            ),
        }

    @property
    def urdf(self) -> MechanismDescription:
        """Former name of :attr:`description` (deprecated: it holds SDF and MJCF models too)."""
        warnings.warn(
            "Mechanism.urdf is deprecated; use Mechanism.description", DeprecationWarning, 2
        )
        return self.description

    def __repr__(self) -> str:
        return (
            f"Mechanism({self.name!r}, nq={self.nq}, nv={self.nv}, "
            f"loops={len(self.description.loops)}, "
            f"nc={self.nc}/{self.declared.nc}, mobility={self.mobility})"
        )


def _quaternion(name: str, value) -> np.ndarray:
    """A unit quaternion (x, y, z, w) from a rotation matrix, a pinocchio.Quaternion or
    four numbers of norm 1 (``Mechanism.q_from``)."""
    if isinstance(value, pin.Quaternion):
        value = value.coeffs()
    arr = np.asarray(value, dtype=float)
    if arr.shape == (3, 3) and np.isfinite(arr).all():
        if not (np.allclose(arr.T @ arr, np.eye(3), atol=ROTATION_TOL) and np.linalg.det(arr) > 0):
            raise InvalidArgumentError(
                f"q_from: joint {name!r}: the 3x3 matrix is not a rotation (R^T R != I or "
                "det R < 0)"
            )
        return pin.Quaternion(arr).normalized().coeffs()
    if arr.shape == (4,) and np.isfinite(arr).all():
        norm = float(np.linalg.norm(arr))
        if abs(norm - 1.0) > NORMALIZATION_TOL:
            raise InvalidArgumentError(
                f"q_from: joint {name!r}: the quaternion (x, y, z, w) = {arr} has norm "
                f"{norm:.12g}, expected 1"
            )
        return arr
    raise InvalidArgumentError(
        f"q_from: joint {name!r} is spherical: give a rotation matrix (3, 3), a "
        f"pinocchio.Quaternion or a unit quaternion (x, y, z, w), not {value!r}"
    )


def _joint_configuration(name: str, jm, value) -> np.ndarray:
    """The q entries of joint model ``jm`` for a user's value (``Mechanism.q_from``)."""
    kind = jm.shortname()
    if kind == "JointModelSpherical":
        return _quaternion(name, value)
    if kind == "JointModelFreeFlyer" and isinstance(value, pin.SE3):
        return pin.SE3ToXYZQUAT(value)
    if kind == "JointModelFreeFlyer":
        arr = np.asarray(value, dtype=float)
        if arr.shape != (7,):
            raise InvalidArgumentError(
                f"q_from: joint {name!r} is a free flyer: give a pinocchio.SE3 or x, y, z "
                f"and a unit quaternion (x, y, z, w), shape (7,), not shape {arr.shape}"
            )
        return np.concatenate([_finite(name, arr[:3], "x, y, z"), _quaternion(name, arr[3:])])
    if kind == "JointModelPlanar":
        x, y, angle = _finite(name, value, "x [m], y [m], angle [rad]", shape=(3,))
        return np.array([x, y, math.cos(angle), math.sin(angle)])
    if jm.nq == 2 and jm.nv == 1:  # continuous: (cos, sin) of the angle
        (angle,) = _finite(name, value, "an angle [rad]", shape=(1,))
        return np.array([math.cos(angle), math.sin(angle)])
    what = "an angle [rad] or a displacement [m]" if jm.nq == 1 else f"its {jm.nq} entries of q"
    return _finite(name, value, what, shape=(jm.nq,))


def _finite(name: str, value, what: str, *, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """``value`` as a finite float array (of ``shape``), or InvalidArgumentError."""
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"q_from: joint {name!r} takes {what}, not {value!r}") from None
    if shape is not None and arr.shape != shape:
        raise InvalidArgumentError(
            f"q_from: joint {name!r} takes {what} ({shape[0]} number(s)), not {value!r}"
        )
    if not np.isfinite(arr).all():
        raise InvalidArgumentError(f"q_from: joint {name!r}: {value!r} is not finite")
    return arr


def load(
    path: str | Path,
    *,
    root_joint: str | None = None,
    loops: str | Path | None = None,
    gravity: Sequence[float] | None = None,
    settings: LoadSettings = DEFAULT_LOAD_SETTINGS,
    cut_joints: Sequence[str] = (),
    keyframe: str | None = None,
) -> Mechanism:
    """Load a mechanism from a URDF+, SDF or MJCF file (with an optional URDF+ or YAML loops
    overlay), or from example-robot-data.

    Args:
        path: URDF file with optional ``<loop>`` / ``<transmission>`` elements,
            an SDF file (``.sdf``, cut into a tree and loops by
            :mod:`closedchain.sdf`), a MuJoCo MJCF file (root ``<mujoco>``, read by
            :mod:`closedchain.mjcf` through MuJoCo's compiler: ``<equality>``
            connect, weld and joint constraints become loops), or ``erd:<name>``, a model of the
            installed example-robot-data (:data:`closedchain.robots.ERD_MODELS`;
            animations embed its meshes within a budget:
            :attr:`closedchain.visualize.AnimationSettings.mesh_budget_bytes`).
        root_joint: joint between the world and the URDF's root link: None
            (fixed), ``"free"`` (free flyer, 7 entries of q: x, y, z [m] and a
            unit quaternion x, y, z, w; 6 of v in the root link frame) or
            ``"planar"`` (x, y [m], cos, sin of the angle about world z).
        loops: overlay file in URDF+ syntax whose links, joints, loops and
            transmissions are merged into the tree (see :mod:`closedchain.robots`),
            or, with a ``.yaml`` / ``.yml`` suffix, the loops, motors and joint
            conversions of the example-parallel-robots convention (see
            :mod:`closedchain.yaml_loops`).
        gravity: gravity vector in the world frame [m/s^2], shape (3,), of
            norm at most :data:`MAX_GRAVITY_NORM`; None: the file's (MJCF
            ``<option gravity>``), else :data:`DEFAULT_GRAVITY`.
        settings: row-selection settings (defaults: :class:`LoadSettings`).
        cut_joints: SDF only: joints to cut into loops in preference to the
            rule of :mod:`closedchain.sdf` (default: the registry entry's).
        keyframe: MJCF only: the ``<key>`` the assembly starts from (None: the
            first keyframe, else the model's pose at ``qpos0``).

    Returns:
        The mechanism, with independent rows selected and a closed ``q_ref``, within
        the joint limits where a closed configuration within them is found (else a
        logged warning names the joints outside); a model whose redundant rows
        disagree by less than ``settings.mismatch_tol`` loads with a logged warning, and
        so does one whose loops YAML file names more motors than the mobility.

    Raises:
        ModelFileError: invalid file or extension element, or a tree beyond
            ``settings.max_data_bytes`` (refused before any work).
        ClosedChainError: gravity is not 3 finite numbers of norm at most
            :data:`MAX_GRAVITY_NORM`.
        LoopClosureError: a loop provably cannot close (the message names the
            height along a common joint axis that keeps it open), or no start
            closes the loops (the message gives the closure residual reached per loop).
    """
    check_settings("settings", settings, LoadSettings)
    from .robots import merge_overlay, reference_configuration, resolve_model
    from .sdf import is_sdf
    from .yaml_loops import is_loops_yaml

    if root_joint not in ROOT_JOINTS:
        raise UnknownChoiceError("root_joint", root_joint, [str(k) for k in ROOT_JOINTS])
    base, entry = resolve_model(path)
    cut = tuple(cut_joints) or (entry.cut_joints if entry is not None else ())
    # URDF and MJCF are read here once (MJCF through MuJoCo, with its gravity); SDF (into
    # a description: closedchain.sdf) and cuts by merge_overlay.
    robot = None if cut or is_sdf(base) else read_xml(base)
    mjcf, file_gravity = None, None
    if robot is not None and robot.tag == MJCF_ROOT:
        mjcf, file_gravity = read_mjcf(base)
        if loops is not None:
            raise ModelFileError(
                f"{base}: an MJCF model takes its loops from its <equality> elements; "
                "overlays (loops=, --loops) apply to URDF and SDF models"
            )
    elif keyframe is not None:
        raise ModelFileError(f"{base}: keyframe={keyframe!r} is for MJCF models (their <key>s)")
    if gravity is None:
        gravity = DEFAULT_GRAVITY if file_gravity is None else file_gravity
    try:
        if mjcf is not None:
            described = mjcf
            check_size(mjcf.tree, max_nv(settings))
        elif loops is None and entry is None and robot is not None:
            described = parse_urdf(base, element=robot, max_nv=max_nv(settings))
        else:
            described = merge_overlay(
                base,
                loops,
                max_nv=max_nv(settings),
                cut_joints=cut,
                fixed_joints=entry.fixed_joints if entry is not None else (),
                root=robot,
            )
    except ModelTooLargeError as exc:
        raise ModelTooLargeError(
            f"{exc}: one Pinocchio Data takes {data_cost_formula()}, "
            f"{data_bytes(exc.nv):.3g} here, over "
            f"LoadSettings.max_data_bytes = {settings.max_data_bytes:.3g}",
            nv=exc.nv,
            max_nv=exc.max_nv,
        ) from None
    if entry is not None and not entry.springs and described.springs:
        logger.info(
            "%s: its joint springs (%s) are left out, as its registry entry says",
            path,
            ", ".join(s.joint for s in described.springs),
        )
        described = replace(described, springs=())
    gravity = np.asarray(gravity, dtype=float)
    if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
        raise ClosedChainError(f"gravity must be 3 finite numbers [m/s^2], got {gravity}")
    # The largest component first: the norm of 1e308 overflows while squaring.
    if np.max(np.abs(gravity)) > MAX_GRAVITY_NORM or np.linalg.norm(gravity) > MAX_GRAVITY_NORM:
        raise ClosedChainError(
            f"gravity {gravity} m/s^2 is beyond the limit; valid: a norm of at most "
            f"{MAX_GRAVITY_NORM:g} m/s^2 (MAX_GRAVITY_NORM)"
        )
    root = ROOT_JOINTS[root_joint]
    model = build_model(described.tree, None if root is None else root())
    if model.nv == 0:
        raise ModelFileError(
            f"{described.path}: the tree has no movable joint (nv = 0), so there is nothing to "
            "simulate or validate; valid: at least one revolute, continuous, prismatic, "
            "planar or floating <joint>, or root_joint 'free' / 'planar' (--root)"
        )
    model.gravity.linear = gravity
    passive = passive_terms(model, described)  # sets model.armature

    described = _resolve_frame_sides(model, described)
    frame_ids = []
    for spec in described.loops:
        pair = []
        for side, link, origin in (
            ("predecessor", spec.predecessor, spec.predecessor_origin),
            ("successor", spec.successor, spec.successor_origin),
        ):
            if link == WORLD_LINK and not model.existFrame(link, pin.FrameType.BODY):
                parent = 0  # Pinocchio's universe frame: fixed whatever the root joint
            elif not model.existFrame(link, pin.FrameType.BODY):
                raise ModelFileError(
                    f"{spec.where(described.path)}: link {quoted(link)} is not part of the "
                    "kinematic tree"
                )
            else:
                parent = model.getFrameId(link, pin.FrameType.BODY)
            lf = model.frames[parent]
            frame = pin.Frame(
                f"{spec.name}::{side}",
                lf.parentJoint,
                parent,
                lf.placement * origin,
                pin.FrameType.OP_FRAME,
            )
            pair.append(model.addFrame(frame, False))
        if model.frames[pair[0]].parentJoint == model.frames[pair[1]].parentJoint:
            ends = (
                spec.predecessor_frame or spec.predecessor,
                spec.successor_frame or spec.successor,
            )
            raise ModelFileError(
                f"{spec.where(described.path)}: predecessor {quoted(ends[0])} and successor "
                f"{quoted(ends[1])} move with the same joint, so the loop closes nothing"
            )
        frame_ids.append(tuple(pair))

    declared = ConstraintLayer(described.loops, tuple(frame_ids))
    closure = LoopClosure(declared, model.nv, name=described.robot_name)
    mech = Mechanism(described, model, closure, gravity, passive)
    mech.root_joint = root_joint
    starts = []
    if described.scene is not None and described.scene.initial:
        # The default scene's start is a configuration along the motion: sampling from
        # it too finds the generic rank where random starts land near singular ones
        # (the N-four-bar's random assemblies fall onto its flat positions, where every
        # loop loses a row: without it 77 of 80 rows were kept for N = 40).
        scene_q = pin.neutral(model)
        for name, value in described.scene.initial.items():
            scene_q[model.joints[model.getJointId(name)].idx_q] = value
        starts.append(scene_q)
    q_guess = reference_configuration(model, entry)
    if q_guess is None and (mjcf is not None or is_sdf(base)):  # keyframes, else drawn pose
        q_guess = configuration(model, _start_values(described, keyframe))
    _select_rows_and_coordinates(mech, settings, q_guess=q_guess, extra_starts=starts)
    _refuse_massless_subtrees(mech)
    if loops is not None and is_loops_yaml(loops):
        _warn_motors_beyond_mobility(mech, Path(loops))
    logger.info("loaded %r", mech)
    return mech


def _warn_motors_beyond_mobility(mech: Mechanism, loops: Path) -> None:
    """Log a warning where a loops YAML file leaves fewer degrees of freedom than motors.

    The convention's robots have at least as many degrees of freedom as motors
    (``name_mot``); fewer means a loop constrains more than the mechanism does,
    typically a ``6d`` pair (the two frames welded) where a pin between two links
    of a planar loop needs ``3d`` (the points joined): the mechanism loads, with
    motors that fight each other.
    """
    motors = mech.actuated_joints
    if mech.mobility < len(motors):
        logger.warning(
            "%s: mobility %d is less than the %d motors (%s): a loop over-constrains the "
            "mechanism (a 6d pair welds its frames; a pin joint between two links of a "
            "planar loop is 3d)",
            loops,
            mech.mobility,
            len(motors),
            ", ".join(motors),
        )


def _start_values(
    described: MechanismDescription, keyframe: str | None
) -> dict[str, tuple[float, ...]]:
    """Return the joint values an MJCF model's assembly starts from: the named keyframe,
    else the first, else the model's pose at qpos0."""
    keyframes = described.tree.keyframes
    if keyframe is not None and keyframe not in keyframes:
        known = ", ".join(keyframes) if keyframes else "none (the model has no <key>)"
        raise ModelFileError(f"{described.path}: unknown keyframe {keyframe!r}; keyframes: {known}")
    if keyframe is None:
        keyframe = next(iter(keyframes), None)
    if keyframe is None:
        return described.tree.reference_values()
    logger.info("%s: the assembly starts from keyframe %r", described.path, keyframe)
    return keyframes[keyframe]


def _refuse_massless_subtrees(mech: Mechanism) -> None:
    """Refuse a moving subtree that has no mass, no inertia and no loop holding it.

    Its coordinates have no kinetic energy and no constraint: the mass matrix is
    singular in them whatever the method (a loop or coupling that reaches the subtree
    makes its J columns non-zero, and M + alpha J^T J regular, as for a massless link
    of a loop). Only the outermost such subtree is named.

    Raises:
        ModelFileError: names the subtree's first joint and its links.
    """
    model = mech.model
    J = layer_jacobian(model, mech.data, mech.declared, mech.q_ref)
    for j in range(1, model.njoints):  # parents first: the outermost subtree is found
        if model.joints[j].nv == 0:
            continue
        subtree = list(model.subtrees[j])
        if any(
            model.inertias[k].mass != 0.0 or np.any(model.inertias[k].inertia != 0.0)
            for k in subtree
        ):
            continue
        cols = [model.joints[k].idx_v + i for k in subtree for i in range(model.joints[k].nv)]
        if np.any(J[:, cols] != 0.0):
            continue  # a loop or coupling holds it
        links = [
            f.name
            for f in model.frames
            if f.type == pin.FrameType.BODY and f.parentJoint in subtree
        ]
        raise ModelFileError(
            f"{mech.path}: the subtree of joint {quoted(model.names[j])} "
            f"(links {shorten(', '.join(links))}) has no mass and no inertia and no loop "
            "holds it: its motion has no dynamics (the mass matrix is singular); give one "
            "of its links an <inertial> with a positive mass, or make its joint fixed"
        )


def _resolve_frame_sides(model: pin.Model, described: MechanismDescription) -> MechanismDescription:
    """Return ``described`` with every ``<loop>`` side written ``frame=`` made a link and origin.

    A frame f on joint j (any Pinocchio frame of the tree: a link's BODY frame,
    a joint's JOINT or FIXED_JOINT frame, an OP_FRAME) moves with the links on
    j; the side becomes the first such link l (the frame itself if it is a
    link) with origin ``lMf * origin``, where ``lMf = jMl^-1 jMf``. Everything
    downstream (loop frames, drawing, digest) then sees links only.

    Raises:
        ModelFileError: the name is no frame of the tree (lists the frames), names
            several frames at different places, or a frame of the world when the
            tree's own link ``world`` moves with a root joint.
    """
    if not any(spec.predecessor_frame or spec.successor_frame for spec in described.loops):
        return described
    tree_frames = [f.name for f in model.frames]
    loops = []
    for spec in described.loops:
        sides = {}
        for side in ("predecessor", "successor"):
            name = getattr(spec, f"{side}_frame")
            if name is None:
                continue
            where = f"{spec.where(described.path)}: <{side} frame={quoted(name)}>"
            if not model.existFrame(name):
                raise ModelFileError(
                    f"{where} names no frame of the tree; frames: {name_list(tree_frames)}"
                )
            found = [f for f in model.frames if f.name == name]
            frame = found[0]
            if any(
                f.parentJoint != frame.parentJoint or not f.placement.isApprox(frame.placement)
                for f in found[1:]
            ):
                kinds = ", ".join(str(f.type) for f in found)
                raise ModelFileError(
                    f"{where} names {len(found)} frames ({kinds}) at different places; "
                    "valid: link= for the link, or rename the joint"
                )
            bodies = [
                f
                for f in model.frames
                if f.type == pin.FrameType.BODY and f.parentJoint == frame.parentJoint
            ]
            if frame.type == pin.FrameType.BODY:
                link = frame
            elif bodies:
                link = bodies[0]
            elif not model.existFrame(WORLD_LINK, pin.FrameType.BODY):
                link = None  # on the universe: the reserved WORLD_LINK stands for it
            else:
                raise ModelFileError(
                    f"{where} is fixed to the world, and no link is: the tree's link "
                    f"{WORLD_LINK!r} moves with the root joint; valid: a frame of a link"
                )
            origin = getattr(spec, f"{side}_origin")
            lMf = frame.placement if link is None else link.placement.actInv(frame.placement)
            sides[side] = WORLD_LINK if link is None else link.name
            sides[f"{side}_origin"] = lMf * origin
        loops.append(replace(spec, **sides))
    return replace(described, loops=tuple(loops))


def _select_rows_and_coordinates(
    mech: Mechanism,
    settings: LoadSettings,
    *,
    q_guess: np.ndarray | None = None,
    extra_starts: Sequence[np.ndarray] = (),
) -> None:
    """Sample configurations along the motion, select rows, assemble q_ref, partition.

    The samples start from ``q_guess`` (else the neutral configuration), then
    random configurations; the samples from ``extra_starts`` (the default scene's
    start) are added to them for the row selection only.
    """
    if mech.closure.declared.nc == 0:
        return
    # Many small SVDs and least-squares solves: OpenBLAS's threads only spin on them (N-four-bar
    # N = 40 on the shared 2-core machine: 5.2 s CPU with one thread, 67 s with two).
    with threadpool_limits(limits=1, user_api="blas"):
        _select_rows_and_coordinates_serial(mech, settings, q_guess, extra_starts)


def _select_rows_and_coordinates_serial(mech, settings, q_guess, extra_starts) -> None:
    model, data, closure = mech.model, mech.data, mech.closure
    sel = settings.selection()
    q_ref, mismatch = _first_closure(mech, settings, q_guess, extra_starts)
    asm = AssemblySettings(mismatch_tol=settings.mismatch_tol if mismatch else 0.0)

    def draw(rng):
        return mech.random_configuration(rng, prismatic_range=sel.prismatic_range)

    samples, _ = sample_configurations(
        model, data, closure.declared, draw, sel, first=[q_ref], assembly=asm
    )
    if extra_starts:
        # Sampled apart and appended: the random samples stay what they are without the
        # extra starts.
        extra, _ = sample_configurations(
            model,
            data,
            closure.declared,
            draw,
            replace(sel, n_samples=len(extra_starts), max_attempts=len(extra_starts)),
            first=list(extra_starts),
            assembly=asm,
        )
        samples = samples + extra
    closure.select_rows(model, data, samples, rank_tol=settings.rank_tol)
    if mismatch:
        closure.mismatch_tol = settings.mismatch_tol
        # The kept rows are consistent: q_ref closes them exactly (the dynamics' rows).
        try:
            q_ref = solve_closure(
                model, data, closure.active, q_ref, np.arange(mech.nv), AssemblySettings()
            )
        except AssemblyError:
            pass
    mech.q_ref = q_ref
    pin.computeJointJacobians(model, data, mech.q_ref)
    J_ref = np.zeros((mech.nc, mech.nv))
    mech.constraints.evaluate(model, data, J=J_ref)
    marked = (
        mech.coordinate_indices(mech.description.independent)
        if mech.description.independent
        else None
    )
    closure.choose_partition(
        independent=marked,
        actuated=np.sort(mech.actuated_idx_v),
        J_ref=J_ref,
        cond_max=settings.cond_JD_max,
        where=str(mech.path),
        marked_names=mech.description.independent,
    )


def _assembly_starts(mech: Mechanism, q_guess, extra_starts) -> list[np.ndarray]:
    """The starts of q_ref's assembly, in order: the given guess (the SRDF reference
    state), the neutral configuration, the middle of the joint limits where the neutral
    configuration is outside them, the default scene's start."""
    model = mech.model
    neutral = pin.neutral(model)
    mid = neutral.copy()
    lo, hi = model.lowerPositionLimit, model.upperPositionLimit
    for j in range(1, model.njoints):
        k = model.joints[j].idx_q
        if model.joints[j].nq == 1 and not lo[k] <= neutral[k] <= hi[k]:
            mid[k] = 0.5 * (lo[k] + hi[k])
    starts = [] if q_guess is None else [np.asarray(q_guess, dtype=float)]
    starts.append(neutral)
    if not np.array_equal(mid, neutral):
        starts.append(mid)
    return starts + [np.asarray(q, dtype=float) for q in extra_starts]


def _first_closure(mech: Mechanism, settings: LoadSettings, q_guess, extra_starts):
    """Return ``(q_ref, mismatch)``: the configuration the mechanism is loaded in, and
    whether its loops close only by least squares (redundant rows that disagree).

    The starts of :func:`_assembly_starts` are closed by
    :func:`~closedchain.closure.assemble_closure` within the joint limits, then (when
    none closes within them: logged) without; then ``settings.max_attempts`` random
    starts within the limits. A least-squares minimum below ``settings.mismatch_tol``
    is accepted with a logged warning naming the loops.

    Raises:
        LoopClosureError: a loop provably cannot close (names the invariant that
            keeps it open: :func:`~closedchain._invariants.prove_unclosable`), or no
            start closes the loops (names the residual per loop).
    """
    model, data, declared = mech.model, mech.data, mech.closure.declared
    # A proven gap g keeps a 3-vector of the closure residual at norm g or more, so its
    # largest component at g / sqrt(3) or more: below sqrt(3) mismatch_tol the gap may
    # be a rounded CAD export that mismatch_tol accepts, left to the assembly.
    proof = prove_unclosable(model, data, declared, gap_min=math.sqrt(3.0) * settings.mismatch_tol)
    if proof is not None:
        raise LoopClosureError(f"{mech.path}: {proof}; check the loop's type and its joints' types")
    limits = (model.lowerPositionLimit, model.upperPositionLimit)
    free = np.arange(mech.nv)
    asm = AssemblySettings()
    starts = _assembly_starts(mech, q_guess, extra_starts)
    best: AssemblyError | None = None
    outside = None  # the first closure found outside the limits

    def close(q0, bounds):
        nonlocal best
        try:
            return assemble_closure(model, data, declared, q0, free, asm, bounds=bounds)
        except AssemblyError as exc:
            if best is None or exc.residual < best.residual:
                best = exc
            return None

    for bounds in (limits, None):
        for q0 in starts:
            if bounds is None and outside is not None:
                break
            q = close(q0, bounds)
            if q is not None and mech.within_limits(q):
                return q, False
            if q is not None and outside is None:
                outside = q
    rng = np.random.default_rng(settings.seed)
    for _ in range(0 if outside is not None else settings.max_attempts):
        if best is not None and best.residual <= settings.mismatch_tol:
            break
        q = close(mech.random_configuration(rng, prismatic_range=settings.prismatic_range), limits)
        if q is not None:
            if mech.within_limits(q):
                return q, False
            outside = q
            break
    if outside is not None:
        logger.warning(
            "%s: no closed configuration within the joint limits found from %d starts; "
            "q_ref has %s",
            mech.path,
            len(starts),
            _outside_limits(mech, outside),
        )
        return outside, False
    assert best is not None
    pin.forwardKinematics(model, data, best.q)
    per_loop = declared.loop_residuals(model, data)
    if best.residual <= settings.mismatch_tol:
        open_loops = {k: v for k, v in per_loop.items() if v > asm.closure_tol}
        logger.warning(
            "%s: loop(s) %s close only to a least-squares residual of %s [m or rad] "
            "(redundant rows that disagree, such as a rounded CAD export; "
            "LoadSettings.mismatch_tol = %.1e): loaded at the least-squares minimum, "
            "the kept rows closed",
            mech.path,
            ", ".join(open_loops),
            ", ".join(f"{v:.3g}" for v in open_loops.values()),
            settings.mismatch_tol,
        )
        return best.q, True
    worst = ", ".join(f"{k}: {v:.3g}" for k, v in per_loop.items())
    raise LoopClosureError(
        f"{mech.path}: the loop frames cannot be brought together from {len(starts)} starts "
        f"and {settings.max_attempts} random ones; smallest max |phi| reached "
        f"{best.residual:.3g} (per loop: {worst}; the closure residual, m or rad). Check the "
        "<loop> origins and "
        "link lengths."
    )


def _outside_limits(mech: Mechanism, q: np.ndarray) -> str:
    """Name the 1-dof joints of q outside their limits, with value and limits."""
    lo, hi = mech.model.lowerPositionLimit, mech.model.upperPositionLimit
    out = []
    for j in range(1, mech.model.njoints):
        k = mech.model.joints[j].idx_q
        if mech.model.joints[j].nq == 1 and not lo[k] <= q[k] <= hi[k]:
            out.append(f"{mech.model.names[j]} at {q[k]:.6g} outside [{lo[k]:.6g}, {hi[k]:.6g}]")
    return "; ".join(out)
