r"""Exact references of benchmark scenarios, and the on-disk cache of numerical ones.

Exact references replace "the most accurate configuration confirmed by a second one"
where the motion is known in closed form up to a quadrature. Each is computed twice,
in double precision and with mpmath at :data:`MP_DIGITS` digits; the agreement of the
two is the reference's confirmation.

``nfourbar-parallelogram``
    The IFToMM A02 N-four-bar (``scripts/make_nfourbar.py``: 2N + 1 uniform rods of
    mass m and length L in a vertical plane) started with every crank vertical and
    turning at ``OMEGA0``: all cranks keep one angle theta and the couplers translate
    (the derivation is in ``tests/nfourbar_reference.py``). With phi = pi/2 - theta
    the angle turned, energy gives

    .. math::

        \dot\phi^2 = \omega_0^2 + k (1 - \cos\phi), \quad k = 2 g c / I, \quad
        I = (N + 1) \frac{m L^2}{3} + N m L^2, \quad c = (N + 1) \frac{m L}{2} + N m L,

    so t(phi) is a quadrature, inverted on the comparison grid by Newton's method
    (dt/dphi = 1 / phidot). Cranks hold theta, couplers (relative to their crank)
    -theta. The model's N, m, L and g are read from the loaded mechanism and its
    energy is checked against the closed form before the reference is used.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin

from .._io import MAX_XML_BYTES, atomic_write, check_npz, read_input_bytes
from ..exceptions import ClosedChainError

logger = logging.getLogger(__name__)

#: Digits of the mpmath confirmation.
MP_DIGITS = 30
#: Absolute tolerance of the double-precision quadratures [s] and Newton steps [rad].
QUAD_TOL = 1e-14
#: Newton iterations at most per grid point.
NEWTON_MAX_ITER = 50
#: The model must reproduce the closed-form energy to this (relative) before use.
MODEL_ENERGY_RTOL = 1e-10


def _nfourbar_constants(mech, q0, v0) -> tuple[int, float, float]:
    """Return (N, k [1/s^2], omega0 [rad/s]) read from the model, checked against the
    closed-form energy at (q0, v0)."""
    model = mech.model
    n = (mech.nv - 1) // 2
    if mech.nv != 2 * n + 1 or mech.mobility != 1:
        raise ClosedChainError(
            f"{mech.name}: the parallelogram reference needs 2N + 1 joints and mobility 1"
        )
    masses = [model.inertias[j].mass for j in range(1, model.njoints)]
    m = masses[0]
    if max(abs(x - m) for x in masses) > 1e-12 * m:
        raise ClosedChainError(f"{mech.name}: the parallelogram reference needs equal rods")
    length = 2.0 * float(np.linalg.norm(model.inertias[1].lever))
    g = float(np.linalg.norm(model.gravity.linear))
    inertia = (n + 1) * m * length**2 / 3.0 + n * m * length**2
    c = (n + 1) * m * length / 2.0 + n * m * length
    theta0, omega0 = float(q0[0]), float(v0[0])
    data = model.createData()
    e_model = pin.computeKineticEnergy(model, data, q0, v0) + pin.computePotentialEnergy(
        model, data, q0
    )
    e_closed = 0.5 * inertia * omega0**2 + g * c * math.sin(theta0)
    if abs(e_model - e_closed) > MODEL_ENERGY_RTOL * max(abs(e_closed), 1.0):
        raise ClosedChainError(
            f"{mech.name}: energy {e_model:.15g} J differs from the parallelogram closed form "
            f"{e_closed:.15g} J; the exact reference does not describe this model"
        )
    if abs(theta0 - math.pi / 2) > 1e-12:
        raise ClosedChainError(f"{mech.name}: the parallelogram reference starts at theta = pi/2")
    return n, 2.0 * g * c / inertia, omega0


def _to_q(mech, q0, theta: np.ndarray) -> np.ndarray:
    sign = np.where(np.asarray(q0) > 0, 1.0, -1.0)  # cranks +theta, couplers -theta
    return theta[:, None] * sign[None, :]


def nfourbar_parallelogram(mech, q0, v0, t_grid: np.ndarray) -> np.ndarray:
    """Crank angles by scipy quadrature and Newton (double precision); q on the grid."""
    import scipy.integrate

    _, k, omega0 = _nfourbar_constants(mech, q0, v0)
    w2 = omega0**2

    def rate(p: float) -> float:
        return math.sqrt(w2 + k * (1.0 - math.cos(p)))

    phis = np.zeros(len(t_grid))
    phi, t_phi = 0.0, 0.0  # T(phi) at the last grid point
    for i, t in enumerate(t_grid):
        if i == 0:
            continue
        p = phi + (t - t_grid[i - 1]) * rate(phi)
        for _ in range(NEWTON_MAX_ITER):
            tp = (
                t_phi
                + scipy.integrate.quad(
                    lambda s: 1.0 / rate(s), phi, p, epsabs=QUAD_TOL, epsrel=1e-13, limit=200
                )[0]
            )
            step = (tp - t) * rate(p)
            p -= step
            if abs(step) <= QUAD_TOL:
                break
        t_phi += scipy.integrate.quad(
            lambda s: 1.0 / rate(s), phi, p, epsabs=QUAD_TOL, epsrel=1e-13, limit=200
        )[0]
        phi = p
        phis[i] = phi
    return _to_q(mech, q0, math.pi / 2 - phis)


def nfourbar_parallelogram_mp(mech, q0, v0, t_grid: np.ndarray) -> np.ndarray:
    """The same reference with mpmath at :data:`MP_DIGITS` digits (the confirmation)."""
    import mpmath as mp

    _, k, omega0 = _nfourbar_constants(mech, q0, v0)
    with mp.workdps(MP_DIGITS):
        kk, w2 = mp.mpf(k), mp.mpf(omega0) ** 2

        def rate(p):
            return mp.sqrt(w2 + kk * (1 - mp.cos(p)))

        phis = [mp.mpf(0)]
        phi, t_phi = mp.mpf(0), mp.mpf(0)
        for i in range(1, len(t_grid)):
            t = mp.mpf(float(t_grid[i]))
            p = phi + (t - mp.mpf(float(t_grid[i - 1]))) * rate(phi)
            for _ in range(NEWTON_MAX_ITER):
                step = (t_phi + mp.quad(lambda s: 1 / rate(s), [phi, p]) - t) * rate(p)
                p -= step
                if abs(step) < mp.mpf(10) ** (-(MP_DIGITS - 5)):
                    break
            t_phi += mp.quad(lambda s: 1 / rate(s), [phi, p])
            phi = p
            phis.append(phi)
        theta = np.array([float(mp.pi / 2 - x) for x in phis])
    return _to_q(mech, q0, theta)


#: name -> (reference, confirmation): ``f(mech, q0, v0, t_grid) -> q``, shape (len(t_grid), nq).
EXACT_REFERENCES: dict[str, tuple[Callable, Callable]] = {
    "nfourbar-parallelogram": (nfourbar_parallelogram, nfourbar_parallelogram_mp),
}


# -- on-disk cache of references ------------------------------------------------------


#: Sources that cannot change a reference's numbers (reporting, charts, other commands).
_NOT_IN_KEY = (
    "cli.py",
    "plotting.py",
    "workspace.py",
    "visualize/",
    "export/",
    "benchmark/__init__.py",
    "benchmark/analysis.py",
    "benchmark/evaluation.py",
    "benchmark/plots.py",
    "benchmark/runner.py",
    "benchmark/scaling.py",
    "benchmark/stability.py",
)


def code_version() -> str:
    """A digest of closedchain's sources that compute a reference (the cache key's code
    part: simulation, dynamics, constraints, the compiled core, the scenarios and exact
    references): a reference is recomputed whenever that code changes."""
    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    paths = sorted(root.rglob("*.py")) + sorted(root.glob("_core*"))
    for path in paths:
        rel = path.relative_to(root).as_posix()
        if rel.startswith(_NOT_IN_KEY):
            continue
        h.update(rel.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def cache_key(job: dict, scenario) -> str:
    """Digest of a reference job: its configuration, the scenario, the horizon and the code."""
    model_bytes = b""
    for name in (scenario.urdf, scenario.loops):
        if name and not name.startswith("erd:"):
            path = Path(job["models_dir"]) / name
            if path.exists():
                model_bytes += read_input_bytes(path, limit=MAX_XML_BYTES, what="model file")
    text = repr(
        (
            job["family"],
            job["solver"],
            job["backend"],
            job["settings"],
            sorted(job["kwargs"].items()),
            scenario,
            job["quick"],
        )
    )
    h = hashlib.sha256(text.encode() + model_bytes + code_version().encode())
    return h.hexdigest()[:24]


def cache_load(cache_dir: str | Path | None, key: str) -> dict | None:
    """The cached result of a reference job (None when absent or unreadable)."""
    if cache_dir is None:
        return None
    path = Path(cache_dir) / f"{key}.npz"
    if not path.exists():
        return None
    try:
        check_npz(path, what="reference cache file")
        with np.load(path, allow_pickle=False) as z:
            return dict(q=z["q"], v=z["v"], cpu_s=float(z["cpu_s"]), status="ok", message="cached")
    except (OSError, ValueError, KeyError, ClosedChainError) as exc:
        logger.warning("reference cache %s unreadable (%s): recomputing", path, exc)
        return None


def cache_store(cache_dir: str | Path | None, key: str, result: dict) -> None:
    """Store a successful reference job's states and CPU seconds."""
    if cache_dir is None or result.get("status") != "ok":
        return
    path = Path(cache_dir)
    path.mkdir(parents=True, exist_ok=True)
    with atomic_write(path / f"{key}.npz") as f:
        np.savez(f, q=result["q"], v=result["v"], cpu_s=result["cpu_s"])
