"""One Mechanism shared by a thread pool gives the results of a serial run.

A mechanism keeps state between calls (Pinocchio data, workspaces, memos, the
kept factorization, the compiled core, the row selection); the public functions
hold its lock (closedchain._locking), so concurrent calls take turns. The
reference is the same calls made one after the other on a freshly loaded
mechanism: results do not depend on call history, so they must agree bit for
bit (a wrong interleaving gave relative errors up to 14 before the lock).
"""

from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from conftest import ALL_METHODS, MODELS

import closedchain as cc

#: Threads in the pool (more than the machine's cores: interleavings are what is tested).
THREADS = 4
#: Random consistent states per method.
N_STATES = 60
#: States of each validate call in the pool, and pools run.
VALIDATE_SAMPLES = 5
VALIDATE_ROUNDS = 3
#: Thread switch interval while validate runs in the pool [s] (Python's default: 5e-3).
SWITCH_INTERVAL = 1e-6


def _serial_and_pooled(func, items):
    serial = [func(x) for x in items]
    with ThreadPoolExecutor(THREADS) as pool:
        pooled = list(pool.map(func, items))
    return serial, pooled


@pytest.mark.parametrize("method", (*ALL_METHODS, "augmented-lagrangian", "proximal"))
def test_forward_dynamics_shared_by_threads_equals_serial(method):
    mech = cc.load(MODELS / "agile_eye.urdf")
    rng = np.random.default_rng(7)
    states = [cc.random_consistent_state(mech, rng) for _ in range(N_STATES)]
    tau = np.zeros(mech.nv)

    def accel(state):
        q, v = state
        res = cc.forward_dynamics(mech, q, v, tau, method=method)
        return np.concatenate([res.a, res.lam])

    serial, pooled = _serial_and_pooled(accel, states)
    differing = [
        k for k, (a, b) in enumerate(zip(serial, pooled, strict=True)) if not np.array_equal(a, b)
    ]
    assert not differing, f"{len(differing)} of {N_STATES} calls differ, first at {differing[0]}"


def test_kinematics_and_inverse_dynamics_shared_by_threads_equal_serial():
    mech = cc.load(MODELS / "agile_eye.urdf")
    rng = np.random.default_rng(11)
    states = [cc.random_consistent_state(mech, rng) for _ in range(N_STATES)]

    def terms(state):
        q, v = state
        inv = cc.inverse_dynamics(mech, q, v, np.zeros(mech.mobility))
        return np.concatenate(
            [
                cc.compute_phi(mech, q),
                cc.compute_jacobian(mech, q).ravel(),
                cc.compute_gamma(mech, q, v),
                cc.project_velocity(mech, q, v + 0.1),
                inv.tau,
                inv.lam,
            ]
        )

    serial, pooled = _serial_and_pooled(terms, states)
    assert all(np.array_equal(a, b) for a, b in zip(serial, pooled, strict=True))


def test_validate_shared_by_threads_equals_serial():
    """validate (random states, Pinocchio's reference on the mechanism's own data) in a
    pool: each seed's report is a serial run's. The threads switch every microsecond, so
    that unlocked work interleaves (without validate's lock 30 of 40 reports differed)."""
    previous = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL)
    try:
        mech = cc.load(MODELS / "agile_eye.urdf")

        def report(seed):
            return cc.validate(mech, n_samples=VALIDATE_SAMPLES, seed=seed)

        for _ in range(VALIDATE_ROUNDS):
            serial, pooled = _serial_and_pooled(report, range(2 * THREADS))
            assert serial == pooled
    finally:
        sys.setswitchinterval(previous)


@pytest.mark.parametrize("backend", ("numpy", "compiled"))
def test_simulations_shared_by_threads_equal_serial(backend):
    """Four simulations of one Agile Eye in a pool end where a fresh mechanism's run ends."""
    t_final = 0.2
    reference = cc.load(MODELS / "agile_eye.urdf")
    shared = cc.load(MODELS / "agile_eye.urdf")
    rng = np.random.default_rng(3)
    starts = [cc.random_consistent_state(reference, rng) for _ in range(THREADS)]

    def run(mech, start):
        q0, v0 = start
        traj = cc.simulate(mech, q0, v0, t_final, backend=backend)
        return np.concatenate([traj.q[-1], traj.v[-1]])

    serial = [run(reference, s) for s in starts]
    with ThreadPoolExecutor(THREADS) as pool:
        pooled = list(pool.map(lambda s: run(shared, s), starts))
    for a, b in zip(serial, pooled, strict=True):
        np.testing.assert_array_equal(a, b)


def test_tracking_scene_shared_by_threads_equals_serial():
    """The computed-torque scene: the controller calls inverse dynamics inside the run."""
    from closedchain.control import default_scene

    t_final = 0.1
    reference = cc.load(MODELS / "agile_eye.urdf")
    shared = cc.load(MODELS / "agile_eye.urdf")

    def run(mech):
        scene = default_scene(mech)
        traj = cc.simulate(mech, scene.q0, scene.v0, t_final, tau=scene.tau, backend="numpy")
        return traj.q[-1]

    serial = run(reference)
    with ThreadPoolExecutor(2) as pool:
        pooled = list(pool.map(lambda _: run(shared), range(2)))
    for q in pooled:
        np.testing.assert_array_equal(q, serial)


#: Captures of fd 2 per thread, and loads per thread (4 x 150 loads lost the process's
#: standard error in 2 of 3 runs before the lock).
CAPTURES_PER_THREAD = 2_000
LOADS_PER_THREAD = 25


def test_concurrent_loads_keep_the_process_standard_error(tmp_path):
    """captured_stderr swaps file descriptor 2 (urdfdom's messages); threads that did so at
    once could restore each other's temporary file and leave fd 2 on a deleted file, so
    that every later error vanished. The captures now take turns (STDERR_LOCK)."""
    import os

    from closedchain._io import captured_stderr

    before = os.fstat(2)
    previous = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL)

    def capture(i):
        for _ in range(CAPTURES_PER_THREAD):
            with captured_stderr() as text:
                os.write(2, f"thread {i}\n".encode())
            assert text.text == f"thread {i}\n"  # each capture got its own line, only

    def load(_):
        return [cc.load(MODELS / "fourbar.urdf").nv for _ in range(LOADS_PER_THREAD)]

    try:
        with ThreadPoolExecutor(THREADS) as pool:
            list(pool.map(capture, range(THREADS)))
            assert list(pool.map(load, range(THREADS))) == [[3] * LOADS_PER_THREAD] * THREADS
    finally:
        sys.setswitchinterval(previous)
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
