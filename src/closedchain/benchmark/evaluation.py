"""Cost of one forward-dynamics evaluation: every registered method beside its peers.

CPU microseconds per call (``time.process_time``; median over repeats of the
mean of ``number`` calls; all entries interleaved repeat by repeat so machine
load hits them alike) at a random consistent state of each mechanism:

* each method in ``closedchain.METHODS`` (its backend from its capabilities);
* ``pinocchio.constraintDynamics`` with the library's settings and with the
  cheapest exact settings (the fewest proximal iterations that still agree
  with ``kkt`` to :data:`EXACT_TOL`);
* MuJoCo's ``mj_forward`` on the exported model (when MuJoCo is installed).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..dynamics import forward_dynamics
from ..dynamics.base import DEFAULT_SETTINGS, METHOD_CAPABILITIES, METHODS, get_method
from ..kinematics import random_consistent_state
from ..mechanism import Mechanism, load

logger = logging.getLogger(__name__)

#: Agreement with kkt that makes pinocchio.constraintDynamics "exact" [rad/s^2].
EXACT_TOL = 1e-9
#: Proximal iteration caps tried for the cheapest exact settings.
MAX_ITER_CANDIDATES = (1, 2, 3, 5, 10, 20, 50)
#: Regularizations tried (mu = 0 fails on redundant rows).
MU_CANDIDATES = (1e-12, 1e-10, 1e-8, 1e-6)

EVALUATION_COLUMNS = ("mechanism", "nv", "nc", "call", "backend", "us", "note")


@dataclass(frozen=True)
class EvaluationSettings:
    """Timing settings: ``number`` calls per repeat, ``repeats`` repeats, state seed."""

    number: int = 2000
    repeats: int = 7
    seed: int = 0


def cpu_us_per_call(fn: Callable[[], object], number: int) -> float:
    """Mean CPU time of ``number`` calls of ``fn`` [us] (``time.process_time``)."""
    t0 = time.process_time()
    for _ in range(number):
        fn()
    return (time.process_time() - t0) / number * 1e6


def cheapest_exact_settings(mech: Mechanism, q, v, tau, a_ref, cms, cds, data):
    """The cheapest ``pin.ProximalSettings`` (fewest iterations first, then the smallest mu) whose
    ``pin.constraintDynamics`` matches ``a_ref`` to ``EXACT_TOL``, and a note saying which;
    ``(None, note)`` when none does."""
    for max_iter in MAX_ITER_CANDIDATES:
        for mu in MU_CANDIDATES:
            prox = pin.ProximalSettings(1e-14, 0.0, mu, max_iter)
            a = pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, prox)
            if np.all(np.isfinite(a)) and np.max(np.abs(a - a_ref)) <= EXACT_TOL:
                return prox, f"mu={mu:.0e}, max_iter={max_iter}"
    return None, "no exact setting found"


def compiled_methods(mech: Mechanism) -> list[tuple[str, object]]:
    """(name, :class:`closedchain.compiled.CompiledDynamics`) of every compiled method
    (empty when the compiled core is not built)."""
    from .. import compiled

    if not compiled.available():
        logger.warning("the compiled core is not built: compiled methods left out")
        return []
    return [
        (name, compiled.compiled_dynamics(mech, name))
        for name in sorted(METHODS)
        if METHOD_CAPABILITIES[name].compiled
    ]


def evaluation_calls(mech: Mechanism, seed: int = 0) -> list[tuple[str, str, Callable, str]]:
    """The timed calls (label, backend, function, note) at one random consistent state."""
    q, v = random_consistent_state(mech, np.random.default_rng(seed))
    tau = np.zeros(mech.nv)
    calls = []
    for name in sorted(METHODS):
        func = get_method(name)
        calls.append(
            (f"method {name}", "numpy", lambda f=func: f(mech, q, v, tau, DEFAULT_SETTINGS), "")
        )
    for name, fd in compiled_methods(mech):
        calls.append(
            (f"method {name}", "compiled", lambda fd=fd: fd.forward(q, v, tau), "from Python")
        )
    cms, cds, _, data = mech.pinocchio_constraints()
    lib = DEFAULT_SETTINGS.pinocchio_proximal()
    calls.append(
        (
            "pin.constraintDynamics (library settings)",
            "C++",
            lambda: pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, lib),
            f"mu={DEFAULT_SETTINGS.pinocchio_mu:.0e}, "
            f"max_iter={DEFAULT_SETTINGS.pinocchio_max_iter}",
        )
    )
    a_ref = forward_dynamics(mech, q, v, tau, method="kkt").a
    prox, note = cheapest_exact_settings(mech, q, v, tau, a_ref, cms, cds, data)
    if prox is not None:
        calls.append(
            (
                "pin.constraintDynamics (cheapest exact)",
                "C++",
                lambda: pin.constraintDynamics(mech.model, data, q, v, tau, cms, cds, prox),
                note,
            )
        )
    mj_forward = mujoco_forward(mech, q, v)
    if mj_forward is not None:
        calls.append(("mujoco.mj_forward (default solref)", "C", mj_forward, "soft constraints"))
    return calls


def mujoco_forward(mech: Mechanism, q, v) -> Callable[[], object] | None:
    """``mujoco.mj_forward`` on the exported model at (q, v), as a call of no argument;
    None (with a warning) when MuJoCo is not installed or cannot load the model."""
    try:
        import mujoco

        from ..export.mjcf import load_mujoco, mujoco_state
    except ImportError:
        logger.warning("MuJoCo not installed: mj_forward left out")
        return None
    try:
        m, d = load_mujoco(mech)
    except ValueError as exc:  # a model MuJoCo refuses
        logger.warning("MuJoCo cannot load %s: %s", mech.name, str(exc).splitlines()[-1])
        return None
    d.qpos[:], d.qvel[:] = mujoco_state(mech, q, v)
    return lambda: mujoco.mj_forward(m, d)


def time_evaluations(
    paths: list[str | Path], settings: EvaluationSettings | None = None
) -> list[dict]:
    """Microseconds per call for each mechanism file (tidy rows, :data:`EVALUATION_COLUMNS`)."""
    settings = settings or EvaluationSettings()
    entries = []
    for path in paths:
        mech = load(path)
        for label, backend, fn, note in evaluation_calls(mech, settings.seed):
            entries.append((mech, label, backend, fn, note, []))
    for _ in range(settings.repeats):
        for *_, fn, _note, runs in entries:
            runs.append(cpu_us_per_call(fn, settings.number))
    return [
        dict(
            mechanism=mech.name,
            nv=mech.nv,
            nc=mech.nc,
            call=label,
            backend=backend,
            us=float(np.median(runs)),
            note=note,
        )
        for mech, label, backend, _fn, note, runs in entries
    ]


def evaluation_markdown(rows: list[dict]) -> str:
    """The per-evaluation table as Markdown."""
    lines = [
        "| mechanism | call | backend | us per call | note |",
        "| --- | --- | --- | --- | --- |",
    ]
    lines += [
        f"| {r['mechanism']} (nv={r['nv']}, nc={r['nc']}) | {r['call']} | {r['backend']} "
        f"| {r['us']:.1f} | {r['note']} |"
        for r in rows
    ]
    return "\n".join(lines) + "\n"
