r"""Validation against ``pinocchio.constraintDynamics``.

At random assembled states (q on phi = 0, v with J v = 0, random tau) the
accelerations of a closedchain method are compared with Pinocchio's proximal
constrained dynamics on the same mechanism (revolute loops expressed as two
CONTACT_3D points on the axis). The generalized constraint force
:math:`J^\top\lambda` is compared rather than the multipliers, because it does
not depend on how a closure is parameterized; Pinocchio's sign convention is
the opposite of ``M a + h + J^T lam = tau``.

Two things keep the comparison at round-off rather than at the reference's
own error (measured on the UR5 holding a crank, where constraint forces reach
5e3 N and accelerations 1e3 rad/s^2 at the default torques):

* **States on the manifold to round-off.** Our cut-frame rows and Pinocchio's
  point rows define the same manifold but different Jacobians off it: their
  row spaces differ by O(|phi|), so with constraint forces lam the two
  generalized constraint forces differ by about |phi| |lam|. The states are
  assembled to ``max |phi| <= VALIDATION_PHI_TOL`` (the assembly default,
  1e-12, left 7e-13 and so 2e-9 rad/s^2 on the UR5).
* **Pinocchio's answer polished by iterative refinement of its own system.**
  A single ``pinocchio.constraintDynamics`` call is accurate to a few 1e-12 of
  max |a| whatever its ``mu``, ``max_iter`` or the revolute points' spacing:
  its answer violates its own rows by ~5e-12, which a nearly singular
  direction of J (sigma_min ~ 4e-3) turns into 1e-9 rad/s^2 at |a| ~ 1.6e3
  (a 40-digit solve of the same system shows this; see
  tests/test_robots.py). ``REFERENCE_REFINEMENT_STEPS`` steps of
  iterative refinement (Wilkinson) fix this using only Pinocchio's terms:
  residuals :math:`r_d = \tau - \mathrm{rnea}(q, v, a) + J_c^\top\lambda_c`
  and :math:`r_c = J_c a - b_c` (``getConstraintsJacobian`` and the
  constraint right-hand side ``data.primal_rhs_contact``), then the
  correction :math:`\delta a = \delta a_p + \delta a_h` with
  :math:`J_c\,\delta a_p = -r_c` (least squares) and :math:`\delta a_h`
  from ``constraintDynamics`` at v = 0 with generalized force
  :math:`r_d - M\,\delta a_p + g(q)`. The report keeps the deviation from
  the unrefined call too (``max_da_unrefined``).

What is judged: the accelerations in the mass-matrix norm, and :math:`J^\top\lambda`.
Robots with near-massless links (example-parallel-robots' ball joints and
U-joint crosses: eigenvalues of M down to 1.6e-11 kg m^2, condition numbers of
M of 1e6 to 1e8) accelerate at 1e5 to 6e7 rad/s^2 along those links under
torques of the gravity-load scale. There max |a - a_pin| is not determined to
1e-9 by the double-precision problem itself: rounding M, h, J and gamma to
double moves the exact (40-digit) solution by up to 3e-8 rad/s^2 (robot_delta),
a forward error of order eps cond(M) |a| that neither side can beat.
The mass-matrix norm :math:`\|\delta a\|_M = (\delta a^\top M\,\delta a)^{1/2}`
(the norm of Gauss's principle, in which the constrained acceleration is the
M-orthogonal projection of the free one) weighs an error by the inertia that
carries it: rounding the inputs moves the exact solution by 3e-11 to 1e-10 of
:math:`\|a\|_M` (tests/data/yaml_delta_light.urdf, cond(M) = 3e6, |a| up to
6e6 rad/s^2). So the report judges
:math:`\|a - a_\mathrm{pin}\|_M / \max(1, \|a_\mathrm{pin}\|_M)` (absolute below
1, relative above, as the force) against ``tol_a``, with the same value 1e-9,
and keeps max |a - a_pin| as information (``max_da``). On robot_delta the
closedchain KKT solution agrees with the 40-digit solve to 7e-8 rad/s^2 at
|a| = 6e7, Pinocchio's refined one to 6e-4; in the mass-matrix norm the two
differ by 2e-11 of :math:`\|a\|_M` (docs/guide/validation.md).

**Couplings** (``q_j = m q_i + c``: URDF ``<mimic>``, coupling loops, MJCF joint
equalities, SDF gearboxes) have no Pinocchio constraint model, and
``constraintDynamics`` refuses Pinocchio's mimic joints. Their reference is the same
tree with every coupled joint turned into a Pinocchio mimic joint
(``pinocchio.transformJointIntoMimic`` on the built model; the multipliers and
offsets of URDF ``<mimic>`` elements read again from the file, apart from
closedchain's reader): its coordinates are those of the primary
joints, v = G v_r, and its ``crba`` and ``nonLinearEffects`` are the reduced M_r and
h_r (:class:`MimicReference`; Pinocchio 4.1's ``aba`` and ``constraintDynamics``
refuse mimic joints). Without frame loops a_r = M_r^-1 (G^T tau - h_r); with them,
the loops' points (as for ``constraintDynamics``: two on a revolute axis, one for a
spherical joint, three for a weld) give rows J_r a_r + gamma_r = 0 from Pinocchio's
frame Jacobians and classical accelerations on the mimic model, solved in the null
space of J_r. closedchain's accelerations are compared on the primary
coordinates, its generalized constraint force as G^T J^T lam (the couplings' own
forces drop out: J_coupling G = 0), in the mimic model's mass-matrix norm.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from ._locking import exclusive
from .closure import AssemblySettings
from .constraints import PIN_REVOLUTE_POINT_OFFSET, axis_basis
from .dynamics import DEFAULT_SETTINGS, METHODS, SolverSettings, forward_dynamics
from .dynamics.base import mass_matrix, method_name
from .dynamics.pinocchio_method import pinocchio_constrained_dynamics
from .exceptions import (
    AssemblyError,
    InvalidArgumentError,
    ModelFileError,
    SingularConfigurationError,
    UnknownChoiceError,
    ValidationUnavailableError,
    check_settings,
)
from .kinematics import assemble, project_velocity, random_consistent_state, singularity_measures
from .mechanism import Mechanism
from .urdf import COUPLING, MechanismDescription, read_xml

logger = logging.getLogger(__name__)

__all__ = [
    "TOL_ACCELERATION",
    "TOL_FORCE",
    "ValidationReport",
    "validate",
]

#: Default tolerance on the accelerations' deviation in the mass-matrix norm,
#: ||a_ours - a_pin||_M, absolute below 1 and relative to ||a_pin||_M above
#: (module docstring).
TOL_ACCELERATION = 1e-9
#: Default tolerance on the generalized constraint force, absolute below
#: 1 N m and relative to |J^T lam_pin| above.
TOL_FORCE = 1e-8
#: Assembly tolerance of the validation states, max |phi| [m or -] (see the
#: module docstring: the two formulations' Jacobians differ by O(|phi|)).
VALIDATION_PHI_TOL = 1e-14
#: Steps of iterative refinement applied to Pinocchio's answer (module docstring).
REFERENCE_REFINEMENT_STEPS = 1
#: Relative singular-value cut-off of the least-squares correction J_c da_p = -r_c:
#: Pinocchio's rows are redundant (a revolute loop is 6 point rows of rank 5, a
#: planar loop has zero rows), and the round-off in r_c along their near-zero
#: singular directions (~1e-16 of the largest) is not a correction to apply.
REFINEMENT_RCOND = 1e-9
#: Random starts :func:`validate` assembles per state before it walks along the
#: motion instead (:func:`walk_consistent_state`; the shipped mechanisms and
#: example-parallel-robots draw each state within a few starts).
DRAW_ATTEMPTS = 100
#: Steps along the motion between two states of the walk.
WALK_STEPS = 3
#: Standard deviation [rad or m] of one step of the walk (the assembly's Newton
#: steps converge from there on erd:cassie).
WALK_STEP = 0.1
#: Directions tried per step of the walk before it gives up.
WALK_TRIES = 50
#: Smallest singular value of J a drawn state keeps (random_consistent_state's default).
MIN_SIGMA = 1e-3
#: Fraction of the start's sigma_min(J) a walk keeps when the start is below MIN_SIGMA.
WALK_SIGMA_FRACTION = 0.1
#: Largest ``n_samples`` of :func:`validate`: each state is an assembly and two
#: dynamics solves (about 2 ms on the 4-bar, so 1e5 states take some 4 minutes;
#: seconds to minutes per state on the largest models).
MAX_VALIDATION_SAMPLES = 100_000
#: Relative singular-value cut-off of the mimic reference's loop rows J_r (redundant
#: point rows: a revolute loop's 6 rows have rank 5, a planar loop's rank 2 or 3).
MIMIC_RANK_RCOND = 1e-9


@dataclass(frozen=True)
class ValidationReport:
    """Outcome of :func:`validate`.

    Attributes:
        mechanism: mechanism name.
        method: closedchain method compared.
        n_samples: states compared.
        n_singular: states the method refused as singular (not compared).
        seed: random seed.
        max_da: max over states of max |a_ours - a_pin| [rad/s^2] (information:
            not determined to ``tol_a`` where M is ill-conditioned; module docstring).
        max_da_mass_norm: max over states of
            ||a_ours - a_pin||_M / max(1, ||a_pin||_M), with
            ||x||_M = sqrt(x^T M x) (absolute below 1, relative above); judged
            against ``tol_a``.
        max_dforce: max over states of
            max|J^T lam_ours - J^T lam_pin| / max(1, max|J^T lam_pin|) [N m, relative above 1].
        max_constraint_residual: max |J a + gamma| of our accelerations.
        max_pin_constraint_residual: the same for Pinocchio's accelerations
            (after refinement).
        max_da_unrefined: max |a_ours - a_pin| against a single
            ``constraintDynamics`` call, before refinement [rad/s^2]
            (information only: not judged).
        tol_a: tolerance on ``max_da_mass_norm``.
        tol_force: tolerance on ``max_dforce``.
        reference: ``"pinocchio.constraintDynamics"``, or ``"pinocchio mimic joints"``
            for a mechanism with couplings (:class:`MimicReference`: accelerations and
            forces compared on the primary joints' coordinates).
    """

    mechanism: str
    method: str
    n_samples: int
    n_singular: int
    seed: int
    max_da: float
    max_dforce: float
    max_constraint_residual: float
    max_pin_constraint_residual: float
    tol_a: float
    tol_force: float
    max_da_unrefined: float = float("nan")
    max_da_mass_norm: float = float("nan")
    reference: str = "pinocchio.constraintDynamics"

    @property
    def passed(self) -> bool:
        # States are drawn away from singular J, so a refusal is a failure too.
        return bool(
            self.max_da_mass_norm <= self.tol_a
            and self.max_dforce <= self.tol_force
            and self.n_singular == 0
        )

    def as_dict(self) -> dict:
        return {**asdict(self), "passed": self.passed}


#: ``(a, J^T lam)`` from ``pinocchio.constraintDynamics`` in our sign convention
#: (one implementation, shared with the "pinocchio" method).
pinocchio_forward_dynamics = pinocchio_constrained_dynamics


def pinocchio_reference_dynamics(
    mech: Mechanism,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    settings: SolverSettings = DEFAULT_SETTINGS,
    *,
    refinement_steps: int = REFERENCE_REFINEMENT_STEPS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""Return Pinocchio's ``(a, J^T lam)`` polished by iterative refinement, and its raw ``a``.

    See the module docstring for the refinement (only Pinocchio's own terms:
    ``rnea``, ``crba``, ``computeGeneralizedGravity``, its constraint
    Jacobian and right-hand side, and ``constraintDynamics`` for the
    correction).

    Args:
        mech: the mechanism (no prismatic loops).
        q: configuration, shape (nq,).
        v: velocity, shape (nv,).
        tau: generalized forces, shape (nv,) [N m or N].
        settings: the proximal settings (``pinocchio_mu``, ``pinocchio_accuracy``,
            ``pinocchio_max_iter``).
        refinement_steps: refinement steps (0: the single call).

    Returns:
        Refined accelerations, shape (nv,) [rad/s^2 or m/s^2]; refined
        generalized constraint force :math:`J^\top\lambda = -J_c^\top\lambda_c`,
        shape (nv,) [N m or N]; the unrefined accelerations, shape (nv,).
        Non-finite values are returned as they are (the caller checks).
    """
    cms, cds, _, data = mech.pinocchio_constraints()
    model = mech.model
    prox = settings.pinocchio_proximal()
    tau = mech.passive.added_to(tau, q, v)  # Pinocchio has no joint springs or damping
    a = pin.constraintDynamics(model, data, q, v, tau, cms, cds, prox).copy()
    a_raw = a.copy()
    lam = data.lambda_c.copy()
    # (nc, nv) also for nv = 1, which Pinocchio returns as a vector.
    Jc = np.reshape(pin.getConstraintsJacobian(model, data, cms, cds), (-1, model.nv))
    # Right-hand side of Pinocchio's acceleration rows: J_c a = b_c at its solution.
    b = np.array(data.primal_rhs_contact[: lam.size])
    if refinement_steps and lam.size and np.all(np.isfinite(a)) and np.all(np.isfinite(lam)):
        rdata = model.createData()
        M = pin.crba(model, rdata, q)
        M = np.triu(M) + np.triu(M, 1).T
        g = pin.computeGeneralizedGravity(model, rdata, q).copy()
        zero = np.zeros(model.nv)
        for _ in range(refinement_steps):
            r_dyn = tau - pin.rnea(model, rdata, q, v, a) + Jc.T @ lam
            r_con = Jc @ a - b
            da_p = np.linalg.lstsq(Jc, -r_con, rcond=REFINEMENT_RCOND)[0]
            # M da_h + g = (r_dyn - M da_p + g) + J_c^T dlam, with J_c da_h = 0 at v = 0.
            da_h = pin.constraintDynamics(
                model, data, q, zero, r_dyn - M @ da_p + g, cms, cds, prox
            )
            a += da_p
            a += da_h
            lam += data.lambda_c
    force = -(lam @ Jc)
    return a, force, a_raw


@dataclass(frozen=True)
class MimicReference:
    """The mechanism's tree with its couplings as Pinocchio mimic joints (module docstring).

    Attributes:
        model: the mimic model (a copy of the mechanism's tree; every coupled joint but
            one per group of coupled joints is a mimic joint), with a frame at every loop
            point; nq_r, nv_r: its configuration and velocity sizes.
        data: its data.
        q_index: the full configuration's entries of the mimic model's q, shape (nq_r,).
        v_index: the full velocity's entries of the mimic model's v, shape (nv_r,).
        G: v = G v_r, shape (nv, nv_r).
        points: frame ids (predecessor, successor) of every loop point, whose world
            positions coincide when the loop is closed.
    """

    model: pin.Model
    data: pin.Data
    q_index: np.ndarray
    v_index: np.ndarray
    G: np.ndarray
    points: tuple[tuple[int, int], ...]

    def dynamics(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the reduced ``(a_r, f_r, M_r)`` at the full state (q, v) under ``tau``.

        Args:
            q: full configuration, shape (nq,), on the couplings.
            v: full velocity, shape (nv,).
            tau: full generalized force, shape (nv,) [N m or N].

        Returns:
            Accelerations of the primary coordinates, shape (nv_r,); the loops'
            generalized constraint force on them, G^T J^T lam = G^T tau - h_r - M_r a_r,
            shape (nv_r,); the mimic model's mass matrix, shape (nv_r, nv_r).
        """
        model, data = self.model, self.data
        q_r, v_r, tau_r = q[self.q_index], v[self.v_index], self.G.T @ tau
        # M column by column from rnea: Pinocchio 4.1's crba is wrong when a mimic joint
        # hangs below another (erd:cassie's gearbox outputs: 3 % of M), its rnea is not.
        zero = np.zeros(model.nv)
        g = pin.rnea(model, data, q_r, zero, zero).copy()
        M = np.column_stack([pin.rnea(model, data, q_r, zero, e) - g for e in np.eye(model.nv)])
        M = 0.5 * (M + M.T)
        h = pin.nonLinearEffects(model, data, q_r, v_r).copy()
        if not self.points:
            return np.linalg.solve(M, tau_r - h), np.zeros(model.nv), M
        pin.computeJointJacobians(model, data, q_r)
        pin.forwardKinematics(model, data, q_r, v_r, np.zeros(model.nv))
        J = np.vstack(
            [
                pin.getFrameJacobian(model, data, fp, _LWA)[:3]
                - pin.getFrameJacobian(model, data, fs, _LWA)[:3]
                for fp, fs in self.points
            ]
        )
        gamma = np.concatenate(
            [
                pin.getFrameClassicalAcceleration(model, data, fp, _LWA).linear
                - pin.getFrameClassicalAcceleration(model, data, fs, _LWA).linear
                for fp, fs in self.points
            ]
        )
        # J a = -gamma: a = a_p + N z with a_p the minimum-norm solution and N a basis of
        # null(J); N^T (M a + h - tau) = 0 fixes z.
        U, sigma, Vt = np.linalg.svd(J)
        rank = int(np.sum(sigma > MIMIC_RANK_RCOND * sigma[0])) if sigma.size else 0
        a_p = -Vt[:rank].T @ ((U[:, :rank].T @ gamma) / sigma[:rank])
        N = Vt[rank:].T
        z = np.linalg.solve(N.T @ M @ N, N.T @ (tau_r - h - M @ a_p))
        a = a_p + N @ z
        return a, tau_r - h - M @ a, M


#: Reference frame of the mimic reference's point rows.
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


def mimic_reference(mech: Mechanism) -> MimicReference:
    """Return the mechanism's :class:`MimicReference` (built once per mechanism).

    Raises:
        ValidationUnavailableError: a prismatic loop; couplings that fix a joint
            (multiplier 0 from a joint before it in the tree) or close a cycle.
    """
    ref = mech.__dict__.get("_mimic_reference")
    if ref is None or ref[0] is not mech.declared:
        ref = (mech.declared, _build_mimic_reference(mech))
        mech.__dict__["_mimic_reference"] = ref
    return ref[1]


def _coupling_relations(mech: Mechanism) -> dict[int, tuple[int, float, float]]:
    """Return joint j -> (i, m, c) of every coupling q_j = m q_i + c of ``mech``.

    The couplings a URDF file writes as ``<mimic>`` elements are read here again from
    the file (:func:`_file_mimics`), independently of closedchain's reader; the
    others, and those of a model without URDF files (MJCF, SDF), closedchain's.
    """
    model = mech.model
    relations = {
        model.getJointId(spec.joint): (model.getJointId(spec.mimics), spec.multiplier, spec.offset)
        for spec in mech.declared.loops
        if spec.type == COUPLING
    }
    for name, (leader, multiplier, offset) in _file_mimics(mech.description).items():
        if model.existJointName(name) and model.existJointName(leader):
            relations[model.getJointId(name)] = (model.getJointId(leader), multiplier, offset)
    return relations


def _file_mimics(urdf: MechanismDescription) -> dict[str, tuple[str, float, float]]:
    """Return joint -> (mimicked joint, multiplier, offset) of the ``<mimic>`` elements of
    the URDF files a model was read from (its file and its links' files; URDF's
    defaults 1 and 0), read with a plain XML parse; files that are not URDF are passed."""
    out: dict[str, tuple[str, float, float]] = {}
    for path in dict.fromkeys((urdf.path, *urdf.link_files.values())):
        if Path(path).suffix.lower() in (".yaml", ".yml", ".sdf"):
            continue
        try:
            root = read_xml(Path(path))
        except ModelFileError as exc:  # moved or changed since it was loaded
            logger.info("%s: its <mimic> elements are not read again (%s)", path, exc)
            continue
        if root.tag != "robot":  # an MJCF model
            continue
        for joint in root.iter("joint"):
            mimic = joint.find("mimic")
            if mimic is None or joint.get("type") == "fixed":
                continue
            try:
                values = (float(mimic.get("multiplier", 1.0)), float(mimic.get("offset", 0.0)))
            except ValueError as exc:
                logger.info(
                    "%s: <mimic> of joint %r not read again (%s)", path, joint.get("name"), exc
                )
                continue
            out[joint.get("name")] = (mimic.get("joint"), *values)
    return out


def _primaries(mech: Mechanism) -> dict[int, tuple[int, float, float]]:
    """Return every coupled joint k -> (p, s, o) with q_k = s q_p + o and p the first
    joint of its group of coupled joints in the tree (Pinocchio's mimic joints follow the
    joint they mimic)."""
    relations = _coupling_relations(mech)
    root: dict[int, tuple[int, float, float]] = {}

    def resolve(j: int, seen: tuple[int, ...]) -> tuple[int, float, float]:
        if j not in relations:
            return j, 1.0, 0.0
        if j in seen:
            raise ValidationUnavailableError(
                f"{mech.name}: the couplings of joint {mech.model.names[j]!r} close a cycle: "
                "Pinocchio's mimic joints cannot express them"
            )
        i, m, c = relations[j]
        p, s, o = resolve(i, (*seen, j))
        return p, m * s, m * o + c

    for j in relations:
        root[j] = resolve(j, ())
    groups: dict[int, list[int]] = {}
    for k, (p, _, _) in root.items():
        groups.setdefault(p, [p]).append(k)
    out: dict[int, tuple[int, float, float]] = {}
    for p, members in groups.items():
        first = min(members)  # q_p = (q_first - o_f) / s_f
        _, s_f, o_f = root.get(first, (p, 1.0, 0.0))
        if s_f == 0.0:
            raise ValidationUnavailableError(
                f"{mech.name}: a coupling with multiplier 0 fixes joint "
                f"{mech.model.names[first]!r}: Pinocchio's mimic joints cannot express it"
            )
        for k in members:
            if k == first:
                continue
            _, s_k, o_k = root.get(k, (p, 1.0, 0.0))
            out[k] = (first, s_k / s_f, o_k - s_k * o_f / s_f)
    return out


def _build_mimic_reference(mech: Mechanism) -> MimicReference:
    model = mech.model
    mimics = _primaries(mech)
    ref = model
    for k in sorted(mimics):
        p, s, o = mimics[k]
        ref = pin.transformJointIntoMimic(ref, p, k, s, o)
    ref.gravity = model.gravity
    q_index, v_index = [], []
    G = np.zeros((mech.nv, ref.nv))
    for j in range(1, model.njoints):
        jm = model.joints[j]
        if j in mimics:
            continue
        q_index += range(jm.idx_q, jm.idx_q + jm.nq)
        r = ref.joints[j].idx_v
        G[jm.idx_v : jm.idx_v + jm.nv, r : r + jm.nv] = np.eye(jm.nv)
        v_index += range(jm.idx_v, jm.idx_v + jm.nv)
    for k, (p, s, _) in mimics.items():
        G[model.joints[k].idx_v] = s * G[model.joints[p].idx_v]
    points = []
    for spec, (fp, fs) in zip(mech.declared.loops, mech.declared.frame_ids, strict=True):
        if spec.type == COUPLING:
            continue
        if spec.type == "prismatic":
            raise ValidationUnavailableError(
                f"loop {spec.name!r} is prismatic: Pinocchio has no prismatic rigid "
                "constraint model, so it cannot serve as the reference; valid loop types "
                "for validation: revolute, spherical, fixed"
            )
        offsets = [np.zeros(3)]
        if spec.type == "revolute":
            offsets.append(PIN_REVOLUTE_POINT_OFFSET * np.asarray(spec.axis))
        if spec.type == "fixed":
            offsets += [PIN_REVOLUTE_POINT_OFFSET * n for n in axis_basis(np.asarray(spec.axis))]
        for k, offset in enumerate(offsets):
            shift = pin.SE3(np.eye(3), offset)
            ids = []
            for fid, side in ((fp, "p"), (fs, "s")):
                frame = model.frames[fid]
                ids.append(
                    ref.addFrame(
                        pin.Frame(
                            f"{spec.name}.{side}{k}",
                            frame.parentJoint,
                            frame.placement * shift,
                            pin.FrameType.OP_FRAME,
                        )
                    )
                )
            points.append((ids[0], ids[1]))
    return MimicReference(
        model=ref,
        data=ref.createData(),
        q_index=np.array(q_index, dtype=int),
        v_index=np.array(v_index, dtype=int),
        G=G,
        points=tuple(points),
    )


def mass_norm(M: np.ndarray, x: np.ndarray) -> float:
    r"""Return the mass-matrix norm :math:`\|x\|_M = (x^\top M x)^{1/2}`.

    Args:
        M: joint-space mass matrix, symmetric positive definite, shape (nv, nv) [kg m^2 or kg].
        x: accelerations, shape (nv,) [rad/s^2 or m/s^2].

    Returns:
        The norm [kg^(1/2) m/s^2] (round-off below zero read as 0).
    """
    return math.sqrt(max(float(x @ M @ x), 0.0))


def walk_consistent_state(
    mech: Mechanism,
    q: np.ndarray,
    rng: np.random.Generator,
    *,
    assembly: AssemblySettings,
    steps: int = WALK_STEPS,
    step: float = WALK_STEP,
    tries: int = WALK_TRIES,
    min_sigma: float = MIN_SIGMA,
    sigma_fraction: float = WALK_SIGMA_FRACTION,
) -> np.ndarray:
    """Walk ``steps`` random steps along the motion from a closed configuration.

    Each step moves q along a random tangent vector (``project_velocity`` of a
    random v of standard deviation ``step``, so J dq = 0 to first order),
    assembles the result onto phi = 0 and keeps it when it is within the joint
    limits and no nearer a singular J than the start: sigma_min(J) at least
    ``min(min_sigma, sigma_fraction sigma_min(J(q)))`` (a robot standing on
    welded feet, erd:cassie, has sigma_min 7.7e-6 at its reference). A step that
    fails is tried again in another direction.

    Args:
        mech: the mechanism.
        q: a closed configuration (phi(q) = 0), shape (nq,).
        rng: random generator.
        assembly: settings of each step's assembly.
        steps: steps taken.
        step: standard deviation of each step's tangent vector [rad or m].
        tries: directions tried per step before giving up.
        min_sigma: the smallest singular value of J kept when the start is further
            from a singular J (``min_sigma`` of :func:`closedchain.random_consistent_state`).
        sigma_fraction: fraction of the start's sigma_min(J) kept otherwise.

    Returns:
        The configuration reached, shape (nq,), assembled to ``assembly.tol``.

    Raises:
        AssemblyError: ``tries`` directions in a row failed to assemble or left
            the limits or neared a singular J.
    """
    floor = (
        min(min_sigma, sigma_fraction * singularity_measures(mech, q).sigma_min) if mech.nc else 0.0
    )
    for _ in range(steps):
        for _ in range(tries):
            dq = project_velocity(mech, q, step * rng.standard_normal(mech.nv))
            try:
                q_next = mech.wrap_angles(
                    assemble(mech, pin.integrate(mech.model, q, dq), settings=assembly)
                )
            except AssemblyError:
                continue
            if mech.within_limits(q_next) and (
                not mech.nc or singularity_measures(mech, q_next).sigma_min >= floor
            ):
                q = q_next
                break
        else:
            raise AssemblyError(
                f"{mech.name}: the walk along the motion found no consistent state in "
                f"{tries} directions (steps of {step:g} rad or m)",
                residual=float("nan"),
                q=q,
            )
    return q


def _validation_states(
    mech: Mechanism, n_samples: int, seed: int, velocity_scale: float, tau_scale: float | None
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield :func:`validate`'s random states ``(q, v, tau)`` (its arguments' meaning).

    Shapes (nq,), (nv,), (nv,); q assembled to VALIDATION_PHI_TOL, v consistent.
    Each q is drawn by :func:`closedchain.random_consistent_state` (random starts
    assembled) within :data:`DRAW_ATTEMPTS` starts; once that fails (a robot on
    welded feet rarely closes from a random start), this and every later q are
    found by :func:`walk_consistent_state` from the previous state, the first
    walk starting at the closed ``mech.q_ref``.
    """
    rng = np.random.default_rng(seed)
    # Generalized forces on the coordinates of a root joint added by load().
    root_nv = mech.model.joints[1].nv if mech.root_joint is not None else 0
    unactuated_root = tau_scale is None
    if tau_scale is None:
        tau_scale = mech.gravity_torque_scale() or 1.0
    assembly = AssemblySettings(tol=VALIDATION_PHI_TOL)
    walk_from = None
    for _ in range(n_samples):
        if walk_from is None:
            try:
                q, v = random_consistent_state(
                    mech,
                    rng,
                    velocity_scale=velocity_scale,
                    assembly=assembly,
                    max_attempts=DRAW_ATTEMPTS,
                )
            except AssemblyError:
                walk_from = assemble(mech, mech.q_ref, settings=assembly)
        if walk_from is not None:
            q = walk_from = walk_consistent_state(mech, walk_from, rng, assembly=assembly)
            v = project_velocity(mech, q, velocity_scale * rng.standard_normal(mech.nv))
        tau = tau_scale * rng.standard_normal(mech.nv)
        if unactuated_root:
            tau[:root_nv] = 0.0
        yield q, v, tau


@exclusive
def validate(
    mech: Mechanism,
    *,
    n_samples: int = 100,
    seed: int = 0,
    method: str = "kkt",
    tol_a: float = TOL_ACCELERATION,
    tol_force: float = TOL_FORCE,
    settings: SolverSettings = DEFAULT_SETTINGS,
    velocity_scale: float = 1.0,
    tau_scale: float | None = None,
) -> ValidationReport:
    """Compare a method with ``pinocchio.constraintDynamics`` at random consistent states
    (on a mechanism with couplings: with Pinocchio's mimic joints, :class:`MimicReference`).

    Args:
        mech: the mechanism (no prismatic loops: Pinocchio has no reference for them).
        n_samples: number of states.
        seed: random seed.
        method: closedchain method to check.
        tol_a: tolerance on the accelerations' deviation in the mass-matrix
            norm, absolute below 1, relative above (module docstring).
        tol_force: tolerance on the generalized constraint force (absolute
            below 1 N m, relative above).
        settings: solver settings for both sides.
        velocity_scale: std of the random velocities before projection [rad/s].
        tau_scale: std of the random generalized forces [N m]; None: the
            mechanism's gravity load, :meth:`Mechanism.gravity_torque_scale`
            (torques of the order the actuators really apply), on the joints
            only: no actuator pushes the root joint that :func:`load` added, so
            its generalized forces are 0 (a random wrench of the joints'
            scale on the free-floating 4-bar's thin base spun it at 3e4
            rad/s^2, where M has condition 5e4 and no double-precision
            answer is good to 1e-9).

    Returns:
        The report; ``report.passed`` says whether both tolerances hold.

    Raises:
        InvalidArgumentError: ``n_samples`` is not an integer in [1,
            :data:`MAX_VALIDATION_SAMPLES`], or ``seed`` not an integer >= 0.
        UnknownChoiceError: ``method`` is "pinocchio" (the reference itself).
        ValidationUnavailableError: a prismatic loop, or couplings that Pinocchio's mimic
            joints cannot express (:func:`mimic_reference`).
    """
    check_settings("settings", settings, SolverSettings)
    if (
        isinstance(n_samples, bool)
        or not isinstance(n_samples, int | np.integer)
        or not 1 <= n_samples <= MAX_VALIDATION_SAMPLES
    ):
        raise InvalidArgumentError(
            f"n_samples must be an integer in [1, {MAX_VALIDATION_SAMPLES}] (a check on no "
            f"states proves nothing), got {n_samples!r}"
        )
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InvalidArgumentError(
            f"seed must be an integer >= 0 (numpy's generators take no negative seed), got {seed!r}"
        )
    method = method_name(method)
    if method == "pinocchio":
        raise UnknownChoiceError(
            "method to validate against pinocchio.constraintDynamics (it is the reference)",
            method,
            [m for m in METHODS if m != "pinocchio"],
        )
    # raise early for prismatic loops
    mimic = mimic_reference(mech) if mech.declared.couplings else None
    if mimic is None:
        mech.pinocchio_constraints()
    max_da = max_da_m = max_df = max_res = max_pres = max_da_raw = 0.0
    singular = 0
    for q, v, tau in _validation_states(mech, n_samples, seed, velocity_scale, tau_scale):
        try:
            ours = forward_dynamics(mech, q, v, tau, method=method, settings=settings)
        except SingularConfigurationError:
            singular += 1
            continue
        f_ours = ours.generalized_constraint_force()
        if mimic is None:
            a_pin, f_pin, a_raw = pinocchio_reference_dynamics(mech, q, v, tau, settings)
            a_ours, a_pin_full = ours.a, a_pin
            M = mass_matrix(mech, q).M
        else:  # on the primary coordinates (module docstring)
            # Pinocchio has no joint springs or damping: their force goes into its tau.
            a_pin, f_pin, M = mimic.dynamics(q, v, mech.passive.added_to(tau, q, v))
            a_raw, a_ours, a_pin_full = a_pin, ours.a[mimic.v_index], mimic.G @ a_pin
            f_ours = mimic.G.T @ f_ours
        if not (np.all(np.isfinite(a_pin)) and np.all(np.isfinite(f_pin))):
            # A failed reference is a failed comparison, never a skipped one
            # (max() would silently drop a NaN).
            max_da = max_da_m = max_df = max_da_raw = float("inf")
            continue
        max_da = max(max_da, float(np.max(np.abs(a_ours - a_pin))))
        max_da_m = max(max_da_m, mass_norm(M, a_ours - a_pin) / max(1.0, mass_norm(M, a_pin)))
        max_da_raw = max(max_da_raw, float(np.max(np.abs(a_ours - a_raw))))
        scale = max(1.0, float(np.max(np.abs(f_pin))))
        max_df = max(max_df, float(np.max(np.abs(f_ours - f_pin))) / scale)
        max_res = max(max_res, ours.constraint_residual())
        max_pres = max(
            max_pres, float(np.max(np.abs(ours.J @ a_pin_full + ours.gamma), initial=0.0))
        )
    return ValidationReport(
        mechanism=mech.name,
        method=method,
        n_samples=n_samples,
        n_singular=singular,
        seed=seed,
        max_da=max_da,
        max_dforce=max_df,
        max_constraint_residual=max_res,
        max_pin_constraint_residual=max_pres,
        tol_a=tol_a,
        tol_force=tol_force,
        max_da_unrefined=max_da_raw,
        max_da_mass_norm=max_da_m,
        reference="pinocchio mimic joints" if mimic is not None else ValidationReport.reference,
    )
