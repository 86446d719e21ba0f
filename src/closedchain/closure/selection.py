"""Row selection and the run-time row checks: :class:`LoopClosure`.

The algorithm is described in :mod:`closedchain.closure`.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..constraints import ConstraintLayer, RowInfo
from ..exceptions import LoopClosureError, ModelFileError, SingularConfigurationError
from .assembly import SelectionSettings, layer_jacobian, layer_phi
from .partition import PIVOT_TIE_RTOL, partition_coordinates
from .secular import _sigma_min, _sigma_min_with_each_row

logger = logging.getLogger(__name__)

#: Relative margin by which a later candidate row must beat an earlier one in the
#: max-min greedy choice: near ties keep the declared order (deterministic choice).
_TIE_RTOL = 1e-9
#: Up to this many row subsets of the generic rank, the max-min choice is exhaustive.
MAX_EXHAUSTIVE_SUBSETS = 500


@dataclass(frozen=True)
class RowSelection:
    """How the independent rows were chosen (what ``closedchain info`` reports).

    Attributes:
        kept: labels of the kept rows.
        dropped: labels of the declared rows left out.
        rank: generic rank of the declared Jacobian.
        n_samples: configurations examined.
        n_singular: samples whose declared Jacobian had a lower rank (set aside).
        margin: worst case over the regular samples of sigma_min(J_kept) /
            sigma_max(J_declared) (0 < margin <= 1; larger is better).
        reason: ``"load"`` or the re-selection's cause.
    """

    kept: tuple[str, ...]
    dropped: tuple[str, ...]
    rank: int
    n_samples: int
    n_singular: int
    margin: float
    reason: str = "load"

    def as_dict(self) -> dict:
        return {
            "kept": list(self.kept),
            "dropped": list(self.dropped),
            "rank": self.rank,
            "n_samples": self.n_samples,
            "n_singular": self.n_singular,
            "margin": self.margin,
            "reason": self.reason,
        }


@dataclass(frozen=True)
class RowCheckSettings:
    """Tolerances of :meth:`LoopClosure.check_rows`.

    Attributes:
        dropped_tol: a dropped row open by more than this [m or -] ...
        dropped_ratio: ... and by more than ``dropped_ratio`` times the largest
            kept-row residual means the kept rows no longer describe the loop.
        cond_max: a kept Jacobian whose condition number exceeds this while
            the declared rows still have their generic rank, with a condition
            number (of their r largest singular values) below it, means the
            kept rows degenerate where the mechanism does not.
        open_tol: when no re-selection can take in an open dropped row, a
            residual above this [m or -] is an error (below it, the residual
            is only reported: every output's residual covers all declared rows).
    """

    dropped_tol: float = 1e-9
    dropped_ratio: float = 100.0
    cond_max: float = 1e3
    open_tol: float = 1e-6


#: The defaults, shared (frozen).
DEFAULT_ROW_CHECK_SETTINGS = RowCheckSettings()


class LoopClosure:
    """A mechanism's loop rows, their independent subset and its coordinate partition.

    Attributes:
        declared: every declared row.
        active: the kept (independent) rows, the ones every method uses.
        selection: how ``active`` was chosen (:class:`RowSelection`).
        history: every selection made, the load-time one first.
        independent_idx_v: velocity indices of the independent coordinates, shape (mobility,).
        dependent_idx_v: the others, shape (nc,).
        independent_source: ``"urdf"``, ``"actuated"`` or ``"automatic"``.
    """

    def __init__(self, declared: ConstraintLayer, nv: int, *, name: str = "") -> None:
        self.declared = declared
        self.active = declared
        self.nv = nv
        self.name = name
        self.rank = declared.nc
        self.selection = RowSelection(
            tuple(r.label for r in declared.rows), (), declared.nc, 0, 0, 1.0
        )
        self.history: list[RowSelection] = []
        self.independent_idx_v = np.arange(nv)
        self.dependent_idx_v = np.arange(0)
        self.independent_source = "automatic"
        self._Js: list[np.ndarray] = []  # declared J at the regular samples
        self._tol = 0.0
        self._n_singular = 0
        #: Closure residual [m or rad] accepted where the declared rows disagree (a
        #: rounded model loaded with a warning: ``LoadSettings.mismatch_tol``); 0 when
        #: every loop closes exactly.
        self.mismatch_tol = 0.0

    # -- row selection ---------------------------------------------------------------
    @property
    def selected_rows(self) -> tuple[int, ...]:
        """Indices of the kept rows in ``declared.declared_rows``."""
        return self.active.selected

    @property
    def rows(self) -> tuple[RowInfo, ...]:
        return self.active.rows

    def select_rows(
        self,
        model: pin.Model,
        data: pin.Data,
        samples: Sequence[np.ndarray],
        *,
        rank_tol: float,
        margin_min: float = SelectionSettings.margin_min,
    ) -> RowSelection:
        """Choose the independent rows from the declared Jacobian at ``samples``.

        Args:
            model: the mechanism's Pinocchio model (with loop frames).
            data: its data.
            samples: assembled configurations, shape (nq,) each.
            rank_tol: relative rank threshold (see :class:`SelectionSettings`).
            margin_min: below this worst-case margin the choice is logged as weak.

        Returns:
            The selection (also stored in :attr:`selection`).
        """
        Js = [layer_jacobian(model, data, self.declared, q) for q in samples]
        self._tol = rank_tol * max([1.0] + [float(np.linalg.norm(J, 2)) for J in Js])
        return self._select(Js, reason="load", margin_min=margin_min)

    def _select(
        self, Js: list[np.ndarray], *, reason: str, margin_min: float, prefer=()
    ) -> RowSelection:
        tol = self._tol
        ranks = [int(np.sum(np.linalg.svd(J, compute_uv=False) > tol)) for J in Js]
        rank = max(ranks, default=0)
        regular = [J for J, r in zip(Js, ranks, strict=True) if r == rank]
        n_singular = len(Js) - len(regular)
        self._Js = regular
        self._n_singular = n_singular
        keep = self._greedy(regular, rank, prefer)
        scale = [max(float(np.linalg.norm(J, 2)), np.finfo(float).tiny) for J in regular]
        margin = (
            min((_sigma_min(J[keep]) / s for J, s in zip(regular, scale, strict=True)), default=1.0)
            if keep
            else 1.0
        )
        self.rank = rank
        self.active = self.declared.restricted(keep)
        labels = [r.label for r in self.declared.declared_rows]
        self.selection = RowSelection(
            kept=tuple(labels[i] for i in keep),
            dropped=tuple(lb for i, lb in enumerate(labels) if i not in keep),
            rank=rank,
            n_samples=len(Js),
            n_singular=n_singular,
            margin=float(margin),
            reason=reason,
        )
        self.history.append(self.selection)
        log = logger.warning if margin < margin_min else logger.info
        log(
            "%s: kept rows %s of %d declared "
            "(rank %d over %d samples, %d singular; margin %.3g; %s)",
            self.name,
            ", ".join(self.selection.kept),
            self.declared.nc,
            rank,
            len(Js),
            n_singular,
            margin,
            reason,
        )
        return self.selection

    def _greedy(self, Js: list[np.ndarray], rank: int, prefer) -> list[int]:
        """Max-min choice of ``rank`` rows over all ``Js`` (module docstring).

        Exhaustive over every row subset of size ``rank`` when there are at most
        :data:`MAX_EXHAUSTIVE_SUBSETS` of them (a planar or single spatial loop),
        greedy otherwise.
        """
        n = self.declared.nc
        if not prefer and 0 < rank and math.comb(n, rank) <= MAX_EXHAUSTIVE_SUBSETS:
            best_set, best_val = [], -1.0
            for subset in itertools.combinations(range(n), rank):
                val = min(_sigma_min(J[list(subset)]) for J in Js)
                if val > best_val * (1.0 + _TIE_RTOL):
                    best_set, best_val = list(subset), val
            return best_set
        keep: list[int] = []
        # Rows of the previous selection that still have full rank together come first,
        # so a re-selection changes as few rows as it can.
        for i in prefer:
            if len(keep) < rank and all(_sigma_min(J[keep + [i]]) > self._tol for J in Js):
                keep.append(i)
        while len(keep) < rank:
            cand = [i for i in range(self.declared.nc) if i not in keep]
            stack = np.stack(Js)
            vals = np.min(_sigma_min_with_each_row(stack[:, keep], stack[:, cand]), axis=0)
            best, best_val = -1, -1.0
            for i, val in zip(cand, vals, strict=True):
                if val > best_val * (1.0 + _TIE_RTOL):
                    best, best_val = i, float(val)
            keep.append(best)
        return sorted(keep)

    # -- run-time checks -------------------------------------------------------------
    def dropped_row_tol(self, tol: float) -> float:
        """Return the residual [m or -] above which a dropped row counts as open: ``tol``,
        or the disagreement accepted at load (:attr:`mismatch_tol`) when larger (the
        dropped rows of a rounded model stay open by it)."""
        return max(tol, self.mismatch_tol)

    def declared_cond(self, model: pin.Model, data: pin.Data, q: np.ndarray) -> float:
        """Return the condition number of the declared rows' J at q, shape (n_declared, nv),
        over its :attr:`rank` largest singular values (inf when the rank-th is below the
        rank tolerance): above the singular bound the mechanism itself is singular at q."""
        return self._rank_cond(layer_jacobian(model, data, self.declared, q))

    def _rank_cond(self, J: np.ndarray) -> float:
        """Return s_1 / s_rank of J, shape (n_declared, nv) (inf: s_rank below tolerance)."""
        s_all = np.linalg.svd(J, compute_uv=False)
        r = self.rank
        return float(s_all[0] / s_all[r - 1]) if s_all[r - 1] > self._tol else math.inf

    def declared_residuals(self, model: pin.Model, data: pin.Data, q: np.ndarray) -> np.ndarray:
        """Return phi(q) of every declared row, shape (n_declared,) [m or -]."""
        return layer_phi(model, data, self.declared, q)

    def worst_row(self, phi_declared: np.ndarray) -> tuple[str, float]:
        """Return the label and |phi| of the most open declared row."""
        i = int(np.argmax(np.abs(phi_declared)))
        return self.declared.declared_rows[i].label, float(abs(phi_declared[i]))

    def check_rows(
        self,
        model: pin.Model,
        data: pin.Data,
        q: np.ndarray,
        *,
        t: float | None = None,
        kept_cond: float | None = None,
        settings: RowCheckSettings = DEFAULT_ROW_CHECK_SETTINGS,
        phi: np.ndarray | None = None,
    ) -> bool:
        """Check that the kept rows still describe every loop at q; re-select if not.

        The kept rows stop describing the loops when a dropped row is open while
        the kept ones are not (``settings.dropped_tol``, ``dropped_ratio``), or
        when the kept rows' Jacobian degenerates (``kept_cond``, computed by the
        caller, above ``settings.cond_max``) while the declared rows keep their
        generic rank. Then the rows are re-selected with q added to the samples
        (logged, recorded in :attr:`history`).

        Args:
            model: the mechanism's Pinocchio model.
            data: its data (overwritten).
            q: configuration, shape (nq,).
            t: simulation time [s] for messages, if any.
            kept_cond: condition number of the kept rows' J at q, if known.
            settings: tolerances (default :class:`RowCheckSettings`).
            phi: phi(q) of every declared row, shape (n_declared,), if known (the
                compiled core's, ``closedchain.compiled.declared_rows``); else computed.

        Returns:
            True when the rows were re-selected.

        Raises:
            SingularConfigurationError: the declared rows themselves lost rank
                (a singular configuration of the mechanism).
            LoopClosureError: a declared row is open by more than
                ``settings.open_tol`` and no selection of rows of the generic rank
                takes it in (names loop, row, time and residual).
        """
        if self.declared.nc == self.active.nc:
            return False
        when = f" at t = {t:.9g} s" if t is not None else ""
        if phi is None:
            phi = self.declared_residuals(model, data, q)
        sel = np.zeros(self.declared.nc, dtype=bool)
        sel[list(self.selected_rows)] = True
        kept_res = float(np.max(np.abs(phi[sel]), initial=0.0))
        dropped = np.where(sel, 0.0, np.abs(phi))
        drop_res = float(np.max(dropped))
        open_row = drop_res > max(settings.dropped_tol, settings.dropped_ratio * kept_res)
        degenerate = kept_cond is not None and kept_cond > settings.cond_max
        if not (open_row or degenerate):
            return False
        J = layer_jacobian(model, data, self.declared, q)
        r = self.rank
        cond_all = self._rank_cond(J)
        if cond_all > settings.cond_max:
            raise SingularConfigurationError.build(
                self.name,
                f"the constraint Jacobian of the declared loop rows (its {r} largest "
                "singular values)",
                q=q,
                cond=float(cond_all),
                bound=settings.cond_max,
                bound_name="singular_cond",
                state="is close to losing rank",
                hint="a singular configuration of the mechanism",
                t=t,
            )
        worst = self.declared.declared_rows[int(np.argmax(dropped))].label
        reason = (
            f"dropped row {worst} open by {drop_res:.3e} (kept rows {kept_res:.3e}){when}"
            if open_row
            else f"kept rows degenerate (condition number {kept_cond:.3e}){when}"
        )
        # The previous rows describe the loops no more: choose afresh (max-min over the
        # load-time samples and this configuration).
        previous = self.selected_rows
        if tuple(self._greedy(self._Js + [J], r, ())) != previous:
            self._select(self._Js + [J], reason=reason, margin_min=0.0)
            return True
        if open_row and drop_res > settings.open_tol:
            label, res = self.worst_row(phi)
            raise LoopClosureError(
                f"{self.name}{when}: loop row {label} is open by {res:.3e} while the kept rows "
                f"({', '.join(self.selection.kept)}) are closed to {kept_res:.3e}, and no other "
                "choice of independent rows describes the loop here"
            )
        return False

    # -- coordinate partition --------------------------------------------------------
    def choose_partition(
        self,
        *,
        independent: np.ndarray | None,
        actuated: np.ndarray,
        J_ref: np.ndarray,
        cond_max: float,
        where: str = "",
        marked_names: Sequence[str] = (),
    ) -> None:
        """Choose the independent coordinates at load.

        The URDF's ``independent="true"`` joints when given, else the actuated
        joints when they fit (count = mobility, J_D regular at every regular
        sample), else column-pivoted QR of ``J_ref``.

        Args:
            independent: velocity indices marked ``independent="true"`` in the
                URDF, or None.
            actuated: velocity indices of the actuated joints.
            J_ref: kept-row Jacobian at the reference configuration, shape (nc, nv).
            cond_max: largest acceptable cond(J_D) at the regular samples.
            where: the file, for error messages.
            marked_names: the joints marked independent, for error messages.

        Raises:
            ModelFileError: the marked coordinates do not match the mobility or
                leave a singular J_D.
        """
        all_idx = np.arange(self.nv)
        kept = list(self.selected_rows)
        samples = [J[kept] for J in self._Js]
        mobility = self.nv - self.active.nc

        def cond_ok(dep: np.ndarray) -> bool:
            return len(dep) == self.active.nc and all(
                np.linalg.cond(J[:, dep]) < cond_max for J in samples
            )

        if independent is not None:
            dep = np.setdiff1d(all_idx, independent)
            if len(independent) != mobility:
                raise ModelFileError(
                    f"{where}: {len(independent)} coordinates are marked independent="
                    f'"true" ({", ".join(marked_names)}) but the mobility is {mobility}'
                )
            if not cond_ok(dep):
                raise ModelFileError(
                    f'{where}: the joints marked independent="true" '
                    f"({', '.join(marked_names)}) leave a singular J_D "
                    f"(condition number >= {cond_max:.0e} at a sampled configuration)"
                )
            ind, source = independent, "urdf"
        else:
            ind, source = actuated, "actuated"
            dep = np.setdiff1d(all_idx, ind)
            if len(ind) != mobility or not cond_ok(dep):
                ind, dep = partition_coordinates(J_ref)
                source = "automatic"
        self.independent_idx_v = np.asarray(ind, dtype=int)
        self.dependent_idx_v = np.asarray(dep, dtype=int)
        self.independent_source = source

    @staticmethod
    def partition_at(J: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Return the best-conditioned partition for the kept-row Jacobian J.

        Column-pivoted QR (Wehage & Haug), see :func:`kinematics.partition_coordinates`,
        with ties (:data:`PIVOT_TIE_RTOL`) to the lowest index.

        Returns:
            ``(independent_idx_v, dependent_idx_v, cond(J_D))``.
        """
        ind, dep = partition_coordinates(J, PIVOT_TIE_RTOL)
        return ind, dep, float(np.linalg.cond(J[:, dep])) if len(dep) else 1.0
