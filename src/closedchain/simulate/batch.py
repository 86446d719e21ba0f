"""Many rollouts at once: :func:`simulate_batch` runs :func:`closedchain.simulate` for a
batch of initial states (and per-member torques) on a thread pool.

Each worker thread integrates on its own copy of the mechanism
(:func:`closedchain._locking.replica`: its own Pinocchio data, compiled core and
buffers), so members never share state and each one's trajectory is bit for bit the
trajectory of the same :func:`~closedchain.simulate` call made alone. The compiled
loops release the GIL while they integrate (src/cpp/gil.hpp) and take it back only to
call into Python (a Python ``tau(t, q, v)``, Ctrl-C checks): compiled members run in
parallel, one per core. Members on the numpy path (a configuration without a compiled
loop, or ``backend="numpy"``) give the same results but take turns on the GIL: a
batch of them runs at the speed of a serial loop.

A member that fails (a start off the manifold, a non-finite state, a singular
position, a tau that raises) does not stop the others: its exception is its outcome
(:class:`BatchResult`, one line per failed member in :meth:`BatchResult.report`).
"""

from __future__ import annotations

import inspect
import logging
import os
import queue
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from .._locking import replica
from ..exceptions import BatchError, InvalidArgumentError, UnknownChoiceError, check_count
from ..trajectory import Trajectory
from .settings import TorqueInput

if TYPE_CHECKING:
    from ..mechanism import Mechanism

logger = logging.getLogger(__name__)

__all__ = ["BatchResult", "Rollout", "simulate_batch"]


@dataclass(frozen=True)
class Rollout:
    """One member of a batch: an initial state and, optionally, its own generalized forces.

    Attributes:
        q0: initial configuration, shape (nq,), on phi = 0.
        v0: initial velocity, shape (nv,), with J v0 = 0.
        tau: this member's ``tau`` (an (nv,) array [N m or N] or a callable
            ``tau(t, q, v)``, as :func:`closedchain.simulate` takes it), replacing the
            batch's; None: the batch's ``tau``.
    """

    q0: np.ndarray
    v0: np.ndarray
    tau: TorqueInput = None


@dataclass(frozen=True)
class BatchResult:
    """The outcome of every member of a :func:`simulate_batch`, in the members' order.

    Attributes:
        outcomes: per member, its :class:`~closedchain.Trajectory`, or the exception
            that stopped it (a :class:`~closedchain.SimulationError` keeps the motion up
            to the stop in ``exc.trajectory``, as from :func:`~closedchain.simulate`).
        workers: threads that ran the batch.
        wall_time: wall-clock time of the whole batch [s].
    """

    outcomes: tuple[Trajectory | Exception, ...]
    workers: int
    wall_time: float

    def __len__(self) -> int:
        return len(self.outcomes)

    def __getitem__(self, index: int) -> Trajectory | Exception:
        return self.outcomes[index]

    @property
    def trajectories(self) -> tuple[Trajectory | None, ...]:
        """Per member, its trajectory, or None where it failed."""
        return tuple(o if isinstance(o, Trajectory) else None for o in self.outcomes)

    @property
    def failed(self) -> dict[int, Exception]:
        """The failed members: index -> the exception that stopped it."""
        return {i: o for i, o in enumerate(self.outcomes) if not isinstance(o, Trajectory)}

    @property
    def ok(self) -> bool:
        """True when every member completed."""
        return not self.failed

    def report(self) -> str:
        """One line per failed member (``member 3: SimulationError: ...``), after a first
        line counting the completed ones."""
        failed = self.failed
        lines = [f"{len(self) - len(failed)} of {len(self)} members completed"]
        for i, exc in failed.items():
            text = str(exc).strip().splitlines()
            lines.append(f"member {i}: {type(exc).__name__}: {text[0] if text else ''}")
        return "\n".join(lines)

    def check(self) -> tuple[Trajectory, ...]:
        """Return every member's trajectory.

        Raises:
            BatchError: a member failed (the message is :meth:`report`; ``exc.failed``
                holds the exceptions by member index).
        """
        failed = self.failed
        if failed:
            raise BatchError(self.report(), failed=failed)
        return self.outcomes  # type: ignore[return-value]


def _simulate_options() -> tuple[str, ...]:
    """The keyword arguments of :func:`closedchain.simulate` a batch passes on (all but
    ``progress``: a member's progress has no meaning in a pool)."""
    from . import simulate

    params = inspect.signature(simulate).parameters.values()
    return tuple(p.name for p in params if p.kind is p.KEYWORD_ONLY and p.name != "progress")


def _rollouts(members: Sequence) -> list[Rollout]:
    """``members`` as rollouts: each a :class:`Rollout` or a pair (q0, v0)."""
    out = []
    for i, member in enumerate(members):
        if isinstance(member, Rollout):
            out.append(member)
        elif isinstance(member, (tuple, list)) and len(member) == 2:
            out.append(Rollout(*member))
        else:
            raise InvalidArgumentError(
                f"simulate_batch: member {i} must be a Rollout or a pair (q0, v0), got "
                f"{type(member).__name__}"
            )
    return out


def _check_workers(workers: int | None, n_members: int) -> int:
    """Threads of a batch of ``n_members``: ``workers`` (default: one per core), at most
    one per member."""
    if workers is None:
        workers = os.cpu_count() or 1
    else:
        workers = check_count("workers", workers, "threads of the batch")
    return max(1, min(workers, n_members))


def simulate_batch(
    mech: Mechanism,
    members: Sequence[Rollout | tuple[np.ndarray, np.ndarray]],
    t_final: float,
    *,
    workers: int | None = None,
    **options,
) -> BatchResult:
    """Integrate a batch of initial states (and per-member torques) on a thread pool.

    Every member runs ``simulate(mech, q0, v0, t_final, **options)`` with its own
    ``tau`` when it has one, on its worker's copy of ``mech``: each outcome equals that
    call made alone, bit for bit. Compiled loops run in parallel (the GIL released);
    numpy-path members take turns (module docstring). ``info.cpu_time`` of each
    trajectory is the process's CPU time over its run: with several workers it counts
    the other members' too (the batch's ``wall_time`` is the measure of a batch).

    Args:
        mech: the mechanism (not modified: the workers use copies).
        members: per member a :class:`Rollout` or a pair (q0, v0): q0 of shape (nq,),
            v0 of shape (nv,).
        t_final: duration of every member [s].
        workers: threads (default: one per core); at most one per member; 1 runs the
            members one after the other on ``mech`` itself, in the calling thread.
        **options: keyword arguments of :func:`closedchain.simulate` (``method``,
            ``integrator``, ``dt``, ``rtol``, ``atol``, ``stabilization``, ``tau``,
            ``t_eval``, ``settings``, ``solver_settings``, ``backend``), the same for
            every member (not ``progress``).

    Returns:
        One outcome per member, in order: its trajectory or the exception that stopped
        it (:class:`BatchResult`; ``result.check()`` returns the trajectories or raises
        naming the failed members).

    Raises:
        UnknownChoiceError: an option that :func:`closedchain.simulate` does not take.
        InvalidArgumentError: a member that is neither a Rollout nor a pair, or
            ``workers`` not a positive integer.
    """
    valid = _simulate_options()
    for name in options:
        if name not in valid:
            raise UnknownChoiceError("simulate_batch option", name, valid)
    rollouts = _rollouts(members)
    n_workers = _check_workers(workers, len(rollouts))
    wall0 = time.perf_counter()
    if n_workers == 1:
        outcomes = [_run(mech, r, t_final, options) for r in rollouts]
    else:
        outcomes = _run_pool(mech, rollouts, t_final, options, n_workers)
    result = BatchResult(tuple(outcomes), n_workers, time.perf_counter() - wall0)
    logger.info(
        "%s: batch of %d on %d threads in %.3f s: %s",
        mech.name,
        len(result),
        n_workers,
        result.wall_time,
        result.report().replace("\n", "; "),
    )
    return result


def _run(mech: Mechanism, rollout: Rollout, t_final: float, options: dict):
    """One member's trajectory, or the exception that stopped it."""
    from . import simulate

    kwargs = options if rollout.tau is None else {**options, "tau": rollout.tau}
    try:
        return simulate(mech, rollout.q0, rollout.v0, t_final, **kwargs)
    except Exception as exc:  # a member's failure is its outcome, not the batch's
        return exc


def _run_pool(
    mech: Mechanism, rollouts: list[Rollout], t_final: float, options: dict, n_workers: int
) -> list:
    """The outcomes of ``rollouts`` on ``n_workers`` threads, each on its own copy of
    ``mech``. Ctrl-C cancels the members not started; the running ones finish."""
    idle: queue.SimpleQueue = queue.SimpleQueue()
    for _ in range(n_workers):
        idle.put(replica(mech))

    def task(rollout: Rollout):
        twin = idle.get()  # one copy per running member: n_workers copies, n_workers threads
        try:
            return _run(twin, rollout, t_final, options)
        finally:
            idle.put(twin)

    # The members are the parallel work: BLAS threads would only contend with them (and
    # one limit held around the pool leaves no run's own limit to restore out of order).
    with (
        threadpool_limits(limits=1, user_api="blas"),
        ThreadPoolExecutor(n_workers, thread_name_prefix="closedchain-batch") as pool,
    ):
        futures = [pool.submit(task, r) for r in rollouts]
        try:
            return [f.result() for f in futures]
        except BaseException:
            for f in futures:
                f.cancel()
            raise
