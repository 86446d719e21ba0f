"""The Trajectory result of a simulation: arrays over time, saved as npz or CSV."""

from __future__ import annotations

import csv
import json
import logging
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ._io import atomic_write, check_npz
from .exceptions import ClosedChainError

__all__ = [
    "SimulationInfo",
    "StopInfo",
    "Trajectory",
]

if TYPE_CHECKING:
    from .mechanism import Mechanism

logger = logging.getLogger(__name__)

_ARRAYS = ("t", "q", "v", "a", "lam", "constraint_residual", "velocity_residual", "energy")
#: Per-sample arrays that may be None (not recorded); an .npz file without them loads.
_OPTIONAL = ("kinetic_energy", "branch", "work")

#: First characters that make a spreadsheet read a cell as a formula (CSV injection,
#: OWASP): a cell starting with one gets a leading apostrophe.
FORMULA_PREFIXES = ("=", "+", "-", "@", "\t", "\r")


def neutralize_formula(cell: str) -> str:
    """Return ``cell`` with a leading ``'`` when a spreadsheet would read it as a formula."""
    return "'" + cell if cell.startswith(FORMULA_PREFIXES) else cell


@dataclass(frozen=True)
class StopInfo:
    """Where and why a simulation stopped early.

    Attributes:
        t: time of the stop [s].
        reason: the error's message (singular configuration, non-finite or
            drifting state).
    """

    t: float
    reason: str


def _field_names(cls) -> frozenset[str]:
    """The dataclass field names of ``cls`` (computed once per class)."""
    names = cls.__dict__.get("_FIELD_NAMES")
    if names is None:
        names = frozenset(f.name for f in fields(cls))
        cls._FIELD_NAMES = names  # a class attribute, not a field (no annotation)
    return names


def energy_scale(energy: np.ndarray, kinetic_energy: np.ndarray | None) -> float:
    """:attr:`Trajectory.energy_scale` of the series ``energy`` and ``kinetic_energy`` [J]."""
    kinetic = 0.0 if kinetic_energy is None else float(np.max(kinetic_energy))
    return max(abs(float(energy[0])), kinetic)


def energy_drift(energy: np.ndarray, kinetic_energy: np.ndarray | None) -> float:
    """:attr:`Trajectory.energy_drift` of the series ``energy`` and ``kinetic_energy``."""
    return energy_balance(energy, kinetic_energy, None)


def energy_balance(
    energy: np.ndarray, kinetic_energy: np.ndarray | None, work: np.ndarray | None
) -> float:
    """:attr:`Trajectory.energy_balance` of the series ``energy``, ``kinetic_energy`` and
    ``work`` (None: no work, W = 0)."""
    deviation = energy - energy[0] if work is None else energy - energy[0] - work
    largest = float(np.max(np.abs(deviation)))
    scale = energy_scale(energy, kinetic_energy)
    if scale == 0.0:
        return 0.0 if largest == 0.0 else float("inf")
    return largest / scale


def _check_names(of: str, target: str, kind: str, names: Sequence[str], valid: Sequence[str]):
    """Raise naming the first difference of two name lists (``kind``: ``"joint"``, ...)."""
    if tuple(names) == tuple(valid):
        return
    k = next(
        (i for i, (a, b) in enumerate(zip(names, valid, strict=False)) if a != b),
        min(len(names), len(valid)),
    )
    ours = repr(names[k]) if k < len(names) else "missing"
    theirs = repr(valid[k]) if k < len(valid) else "missing"
    raise ClosedChainError(
        f"{of} does not fit {target}: its {kind} {k} is {ours}, the mechanism's is {theirs} "
        f"({len(names)} against {len(valid)} {kind}s); give the mechanism it was simulated on"
    )


def _freeze(x):
    """Lists (as JSON gives them back) to tuples, recursively."""
    return tuple(_freeze(e) for e in x) if isinstance(x, (list, tuple)) else x


@dataclass(frozen=True)
class SimulationInfo:
    """What a simulation ran and what it cost (``Trajectory.info``).

    Attributes:
        mechanism: the mechanism's name.
        method: forward-dynamics method.
        integrator: time integrator.
        backend: ``"compiled"`` or ``"numpy"``: what ran.
        backend_fallback: why a compiled request was handed to the numpy
            loops (e.g. a dropped row that opened needs the numpy row
            re-selection), else None.
        stabilization: constraint stabilization.
        dt: fixed step [s] (fixed-step integrators), else None.
        rtol, atol: tolerances (adaptive integrators), else None.
        t_final: requested duration [s].
        joint_names: the mechanism's joint names (``Mechanism.joint_names``);
            empty in trajectories saved before they were recorded.
        model_digest: ``Mechanism.digest()`` of the mechanism simulated, or
            None (saved before it was recorded).
        coordinate_names: one name per coordinate when nq == nv, else None.
        configuration_names: one name per entry of q (nq).
        velocity_names: one name per entry of v (nv).
        independent: names of the independent coordinates at the start.
        repartitions: ``(t, independent names)`` at each re-partition.
        baumgarte: (alpha, beta) gains when the stabilization adds them, else None.
        stopped: where the run stopped early, else None.
        cpu_time: CPU time of the integration [s].
        steps: integration steps taken (accepted steps of an adaptive integrator).
        rejected_steps: steps rejected by the error control (``"rk43"``), else None.
        error_estimate_max: the largest local error estimate of an accepted step,
            relative to the tolerance (at most 1; ``"rk43"``), else None.
        error_estimate_sum: the sum over the accepted steps of their largest local
            position error estimate [rad or m] (``"rk43"``), else None: a first-order
            bound on the accumulated position error that leaves out how the motion
            amplifies earlier errors.
        evaluations: forward-dynamics evaluations.
        row_reselections: ``(t, kept rows, reason)`` at each re-selection of the
            independent constraint rows.
        branch_changes: ``(t_before, t_after, from, to)`` at each change of
            assembly branch (see ``Trajectory.branch``).
        max_constraint_residual: max over time of max |phi(q)|.
        energy_drift: ``Trajectory.energy_drift`` of the run.
        energy_balance: ``Trajectory.energy_balance`` of the run (equal to
            ``energy_drift`` when the run has no tau).
        limit_violations: ``(joint, t_first, value, limit)`` for each joint whose
            coordinate left its URDF ``<limit>`` at a recorded sample: the first
            such time [s], the coordinate there and the limit it passed [rad or m].
        extra: integrator-specific entries (e.g. ``ali3p_alpha``,
            ``newton_iterations``), JSON-serialisable.

    Read-only ``info["steps"]`` / ``info.get("steps")`` access is kept for code
    written against the former dict; new code reads the attributes.
    """

    mechanism: str = ""
    method: str = ""
    integrator: str = ""
    backend: str = ""
    backend_fallback: str | None = None
    stabilization: str = ""
    dt: float | None = None
    rtol: float | None = None
    atol: float | None = None
    t_final: float | None = None
    joint_names: tuple[str, ...] = ()
    model_digest: str | None = None
    coordinate_names: tuple[str, ...] | None = None
    configuration_names: tuple[str, ...] = ()
    velocity_names: tuple[str, ...] = ()
    independent: tuple[str, ...] = ()
    repartitions: tuple = ()
    baumgarte: tuple[float, float] | None = None
    stopped: StopInfo | None = None
    cpu_time: float | None = None
    steps: int | None = None
    rejected_steps: int | None = None
    error_estimate_max: float | None = None
    error_estimate_sum: float | None = None
    evaluations: int | None = None
    row_reselections: tuple = ()
    branch_changes: tuple = ()
    max_constraint_residual: float | None = None
    energy_drift: float | None = None
    energy_balance: float | None = None
    limit_violations: tuple = ()
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SimulationInfo:
        """Build from a mapping (a run's entries, or :meth:`to_dict` read back from JSON).

        Keys that are not fields go to :attr:`extra`.
        """
        names = _field_names(cls)
        kw = {k: v for k, v in d.items() if k in names and k != "extra"}
        extra = {**d.get("extra", {}), **{k: v for k, v in d.items() if k not in names}}
        for k, v in kw.items():
            kw[k] = _freeze(v)
        for k in (
            "joint_names",
            "configuration_names",
            "velocity_names",
            "independent",
            "repartitions",
        ):
            kw[k] = kw.get(k) or ()
        for k in ("branch_changes", "row_reselections", "limit_violations"):
            kw[k] = kw.get(k) or ()
        stopped = kw.get("stopped")
        if isinstance(stopped, Mapping):
            kw["stopped"] = StopInfo(t=float(stopped["t"]), reason=str(stopped["reason"]))
        return cls(**kw, extra=extra)

    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a JSON-serialisable dict (``stopped`` as {t, reason})."""
        return asdict(self) | {"extra": dict(self.extra)}

    def __getitem__(self, key: str) -> Any:
        if key in self.__dataclass_fields__:
            return getattr(self, key)
        return self.extra[key]

    def get(self, key: str, default: Any = None) -> Any:
        """Read access by name (fields, then :attr:`extra`), as on the former dict."""
        try:
            return self[key]
        except KeyError:
            return default


@dataclass(frozen=True)
class Trajectory:
    """A simulated motion.

    Attributes:
        t: times [s], shape (N,).
        q: configurations, shape (N, nq).
        v: velocities, shape (N, nv).
        a: accelerations, shape (N, nv).
        lam: multipliers of the independent rows, shape (N, nc).
        constraint_residual: max |phi(q)| at each time, shape (N,).
        velocity_residual: max |J(q) v| at each time, shape (N,).
        energy: total mechanical energy (kinetic, armature included, + potential of
            gravity and of the joint springs) [J], shape (N,).
        kinetic_energy: kinetic energy [J], shape (N,), or None when not recorded;
            it sets the scale of :attr:`energy_drift`.
        branch: assembly-branch indicator, shape (N,): the sign (+1, -1; 0 when
            singular) of det(J_D) for the mechanism's dependent coordinates
            (``Mechanism.dependent_idx_v``). It changes only where J_D is
            singular: at a change point it says which branch the motion leaves
            on (the 4-bar: open +1 / crossed -1 assembly); ``info.branch_changes``
            lists the changes as [t_before, t_after, from, to]. None when not
            recorded (no loops).
        work: the work of the non-conservative generalized forces since t = 0, the
            actuators' tau and the joint damping D: W(t) = integral of (tau - D v) . v
            dt [J], shape (N,), or None when the run had neither (or was saved before
            it was recorded). Accumulated along the integration
            by a fourth-order rule (``closedchain.simulate.problem.WorkMeter``, which
            states its accuracy).
        info: what the run was and what it cost (:class:`SimulationInfo`); a
            mapping passed here is converted with :meth:`SimulationInfo.from_dict`.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    a: np.ndarray
    lam: np.ndarray
    constraint_residual: np.ndarray
    velocity_residual: np.ndarray
    energy: np.ndarray
    kinetic_energy: np.ndarray | None = None
    branch: np.ndarray | None = None
    work: np.ndarray | None = None
    info: SimulationInfo = field(default_factory=SimulationInfo)

    def __post_init__(self) -> None:
        if not isinstance(self.info, SimulationInfo):
            object.__setattr__(self, "info", SimulationInfo.from_dict(self.info or {}))

    @property
    def energy_scale(self) -> float:
        """max(|E(0)|, max_t T(t)) [J]: the energy the motion holds or exchanges."""
        return energy_scale(self.energy, self.kinetic_energy)

    @property
    def energy_drift(self) -> float:
        r"""Relative energy drift :math:`\max_t |E(t) - E(0)| / E_s`, E_s = :attr:`energy_scale`.

        The kinetic energy enters the scale so that the measure does not hinge
        on where the potential energy's zero is; 0 when E_s = 0 and E is constant.
        """
        return energy_drift(self.energy, self.kinetic_energy)

    @property
    def energy_balance(self) -> float:
        r"""Relative energy balance :math:`\max_t |E(t) - E(0) - W(t)| / E_s`, W = :attr:`work`.

        Zero for an exact solution whatever drives it: the mechanical energy changes by
        the work of tau and of the joint damping alone (the ideal loop joints do none;
        the springs' potential is part of E). Equal to
        :attr:`energy_drift` when :attr:`work` is None (W = 0: no tau).
        """
        return energy_balance(self.energy, self.kinetic_energy, self.work)

    @property
    def max_constraint_residual(self) -> float:
        """max over time of max |phi(q)|."""
        return float(np.max(self.constraint_residual, initial=0.0))

    def check_mechanism(self, mech: Mechanism) -> None:
        """Raise unless this trajectory was simulated on ``mech``.

        The joint names recorded in :attr:`info` must be the mechanism's, and
        so must the model digest (:meth:`Mechanism.digest`): same joints with
        other dimensions, masses, axes or loops are another mechanism. A
        trajectory saved before the digest was recorded is checked by its
        joint names, else its configuration names, with a logged warning; one
        that records neither (built by hand) is not checked.

        Args:
            mech: the mechanism the trajectory is to be drawn or replayed on.

        Raises:
            ClosedChainError: the names differ (the message gives the first
                difference) or the digests differ.
        """
        info = self.info
        of = f"trajectory{' of ' + repr(info.mechanism) if info.mechanism else ''}"
        target = f"mechanism {mech.name!r} ({mech.path})"
        if info.joint_names:
            _check_names(of, target, "joint", info.joint_names, mech.joint_names)
        elif info.configuration_names:
            _check_names(
                of, target, "configuration", info.configuration_names, mech.configuration_names
            )
        else:
            return
        if info.model_digest is None:
            logger.warning(
                "%s records no model digest (saved by an older closedchain): only its names "
                "were checked against %s",
                of,
                target,
            )
            return
        digest = mech.digest()
        if info.model_digest != digest:
            raise ClosedChainError(
                f"{of} was simulated on another model than {target}: same joints, model digest "
                f"{info.model_digest[:12]} != {digest[:12]} (dimensions, masses, axes or loops "
                "differ); give the URDF it was simulated on"
            )

    def save(self, path: str | Path) -> Path:
        """Write the trajectory as ``.npz`` (all arrays, info) or ``.csv`` (t, q, v, residuals,
        E, and the work W of tau when recorded).

        The CSV is written by the csv module: header cells quoted, names that a
        spreadsheet would read as formulas prefixed with ``'`` (see
        :func:`neutralize_formula`), numbers unquoted with all digits.

        The file is written atomically (:func:`closedchain._io.atomic_write`):
        an error leaves a previous file at ``path`` as it was.

        Raises:
            ClosedChainError: the suffix is neither .npz nor .csv.
            OSError: the file cannot be written (its ``filename`` is ``path``).
        """
        path = Path(path)
        if path.suffix == ".npz":
            extra = {k: getattr(self, k) for k in _OPTIONAL if getattr(self, k) is not None}
            with atomic_write(path) as f:
                np.savez_compressed(
                    f,
                    **{k: getattr(self, k) for k in _ARRAYS},
                    **extra,
                    info=json.dumps(self.info.to_dict()),
                )
        elif path.suffix == ".csv":
            names = (
                self.info.configuration_names
                or self.info.coordinate_names
                or [f"q{i}" for i in range(self.q.shape[1])]
            )
            vnames = self.info.velocity_names or [f"v{i}" for i in range(self.v.shape[1])]
            header = (
                ["t"]
                + [f"q:{n}" for n in names]
                + [f"v:{n}" for n in vnames]
                + ["constraint_residual", "velocity_residual", "energy"]
                + ([] if self.work is None else ["work"])
            )
            table = np.column_stack(
                [
                    self.t,
                    self.q,
                    self.v,
                    self.constraint_residual,
                    self.velocity_residual,
                    self.energy,
                    *([] if self.work is None else [self.work]),
                ]
            )
            # csv module, every text cell quoted: names with commas, quotes or
            # newlines keep their column; numbers stay numbers (repr round-trips).
            with atomic_write(path, "w", newline="") as f:
                writer = csv.writer(f, quoting=csv.QUOTE_NONNUMERIC)
                writer.writerow([neutralize_formula(str(h)) for h in header])
                writer.writerows(table.tolist())
        else:
            raise ClosedChainError(
                f"cannot save a trajectory as {path.name!r}; valid suffixes: .npz, .csv"
            )
        return path

    @classmethod
    def load(cls, path: str | Path) -> Trajectory:
        """Read a trajectory written by :meth:`save` as ``.npz``.

        Raises:
            ClosedChainError: not an .npz file, not a regular file, larger than
                :data:`closedchain._io.MAX_NPZ_BYTES` (checked before inflating
                anything), unreadable or truncated, or an
                archive without the trajectory's arrays (the message names the
                file and what is missing) or with inconsistent shapes.
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ClosedChainError(f"{path}: only .npz trajectories can be loaded")
        shapes = check_npz(path, what="trajectory")
        try:
            archive = np.load(path, allow_pickle=False)
            if isinstance(archive, np.ndarray):  # a .npy file renamed
                raise ClosedChainError(
                    f"{path}: not a closedchain trajectory: a single array, not an .npz archive"
                )
            with archive as f:
                missing = [k for k in (*_ARRAYS, "info") if k not in f.files]
                if missing:
                    raise ClosedChainError(
                        f"{path}: not a closedchain trajectory: missing "
                        + ", ".join(missing)
                        + f" (it holds: {', '.join(f.files) or 'nothing'})"
                    )
                keys = [*_ARRAYS, *(k for k in _OPTIONAL if k in f.files)]
                # The rows from the headers, before any array is inflated.
                _check_rows(path, {k: shapes[k] for k in keys if k in shapes})
                arrays = {k: f[k] for k in keys}
                info = json.loads(str(f["info"]))
        except ClosedChainError:
            raise
        except FileNotFoundError as exc:
            raise ClosedChainError(f"{path}: no such file") from exc
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
            raise ClosedChainError(
                f"{path}: not a readable closedchain trajectory (truncated or not an .npz "
                f"archive): {type(exc).__name__}: {exc}"
            ) from exc
        _check_rows(path, {k: a.shape for k, a in arrays.items()})
        if not isinstance(info, dict):
            raise ClosedChainError(
                f"{path}: not a closedchain trajectory: its info is not a JSON object"
            )
        try:
            info = SimulationInfo.from_dict(info)
        except (TypeError, KeyError, ValueError) as exc:
            raise ClosedChainError(
                f"{path}: not a closedchain trajectory: its info is not a simulation's "
                f"({type(exc).__name__}: {exc})"
            ) from exc
        return cls(**arrays, info=info)


def _check_rows(path: Path, shapes: dict[str, tuple[int, ...]]) -> None:
    """Refuse arrays (by shape) that do not all have one row per time of ``t``.

    Raises:
        ClosedChainError: t is not 1-D and non-empty, or another array's first
            dimension differs from len(t) (the message names them).
    """
    t = shapes.get("t")
    if t is None:
        return
    if len(t) != 1 or t[0] < 1:
        raise ClosedChainError(
            f"{path}: not a closedchain trajectory: t has shape {t}; valid: (N,), N >= 1"
        )
    bad = [k for k, s in shapes.items() if len(s) == 0 or s[0] != t[0]]
    if bad:
        raise ClosedChainError(
            f"{path}: not a closedchain trajectory: t has shape {t} and "
            f"{', '.join(bad)} do not have one row per time"
        )


def first_samples(traj: Trajectory, n: int) -> Trajectory:
    """Return the first ``n`` samples of ``traj`` (every per-sample array cut), same info."""
    cut = {k: getattr(traj, k)[:n] for k in (*_ARRAYS, *_OPTIONAL) if getattr(traj, k) is not None}
    return replace(traj, **cut)
