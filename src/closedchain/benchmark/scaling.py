"""Cost per forward-dynamics evaluation against the size of a mechanism family.

Times one evaluation (the work of one explicit step) of every registered method
and of ``pinocchio.constraintDynamics`` on a family of models of growing size
(e.g. the N-four-bar for N = 1..40), interleaved size by size, and fits the
growth exponent p of cost ~ N^p by least squares on log-log axes.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..dynamics.base import DEFAULT_SETTINGS, METHODS, get_method
from ..kinematics import assemble, project_velocity
from ..mechanism import Mechanism, load
from .evaluation import compiled_methods, cpu_us_per_call

logger = logging.getLogger(__name__)

SCALING_COLUMNS = ("n", "nv", "nc", "method", "backend", "us")
#: Label of Pinocchio's solver in the rows.
PINOCCHIO_CALL = "pin.constraintDynamics"


def time_scaling(
    files: dict[int, str | Path],
    *,
    number: int = 200,
    repeats: int = 5,
    guess: Callable[[Mechanism], np.ndarray] | None = None,
) -> list[dict]:
    """Microseconds per evaluation for each size N -> URDF file (tidy rows).

    Args:
        files: N -> URDF file.
        number: calls per timing repeat.
        repeats: repeats (median).
        guess: ``guess(mech) -> q`` near a regular configuration, assembled with the
            independent coordinates held (default: the model's ``q_ref``).
    """
    entries = []
    for n, path in sorted(files.items()):
        mech = load(path)
        # The assembled reference configuration, moving with unit independent rates
        # (random consistent states are hard to find for long chains).
        q = mech.q_ref.copy()
        if guess is not None:
            q = assemble(mech, guess(mech), fixed="independent")
        v = np.zeros(mech.nv)
        v[mech.independent_idx_v] = 1.0
        v = project_velocity(mech, q, v, fixed="independent")
        tau = np.zeros(mech.nv)
        for name in sorted(METHODS):
            f = get_method(name)
            entries.append(
                (
                    n,
                    mech,
                    name,
                    "numpy",
                    lambda f=f, m=mech, q=q, v=v, t=tau: f(m, q, v, t, DEFAULT_SETTINGS),
                    [],
                )
            )
        for name, fd in compiled_methods(mech):
            entries.append(
                (n, mech, name, "compiled", lambda fd=fd, q=q, v=v, t=tau: fd.forward(q, v, t), [])
            )
        cms, cds, _, data = mech.pinocchio_constraints()
        prox = DEFAULT_SETTINGS.pinocchio_proximal()
        entries.append(
            (
                n,
                mech,
                PINOCCHIO_CALL,
                "C++",
                lambda m=mech, d=data, c=cms, cd=cds, q=q, v=v, t=tau, p=prox: (
                    pin.constraintDynamics(m.model, d, q, v, t, c, cd, p)
                ),
                [],
            )
        )
    for _ in range(repeats):
        for *_, fn, runs in entries:
            try:
                runs.append(cpu_us_per_call(fn, number))
            except Exception as exc:  # a method that cannot handle a size is reported
                logger.warning("scaling: %s", exc)
                runs.append(np.nan)
    return [
        dict(n=n, nv=mech.nv, nc=mech.nc, method=name, backend=backend, us=float(np.median(runs)))
        for n, mech, name, backend, _fn, runs in entries
    ]


def series_label(row: dict) -> str:
    """``method (backend)`` of a scaling row (the method alone when no backend is given)."""
    backend = row.get("backend")
    return f"{row['method']} ({backend})" if backend else row["method"]


def growth_exponents(rows: list[dict]) -> dict[str, float]:
    """Least-squares slope p of log(us) against log(N) per method and backend."""
    out = {}
    for method in sorted({series_label(r) for r in rows}):
        mine = [r for r in rows if series_label(r) == method and np.isfinite(r["us"])]
        if len(mine) >= 2:
            x = np.log([r["n"] for r in mine])
            y = np.log([r["us"] for r in mine])
            out[method] = float(np.polyfit(x, y, 1)[0])
    return out
