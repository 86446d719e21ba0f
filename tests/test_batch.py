"""simulate_batch: a batch on a thread pool gives, member by member, the trajectory of the
same simulate call made alone, bit for bit; a failed member is reported, the others complete.

The reference is independent of the batch machinery: plain ``simulate`` calls one after
the other on the mechanism as loaded. The members run on the worker threads' copies of
the mechanism, through the compiled loops with the GIL released (and taken back for a
Python tau), or through the numpy path under the GIL.
"""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest
from conftest import MODELS

import closedchain as cc
from closedchain.exceptions import BatchError, InvalidArgumentError, UnknownChoiceError

#: Threads of the batches (the machine's 2 cores; more members than threads, so that
#: each thread's copy of the mechanism serves several members in turn).
WORKERS = 2
#: Members of a batch.
N_MEMBERS = 5
#: Horizons [s]: long enough for hundreds of steps, short for the test suite.
FOURBAR_T = 0.5
AGILE_EYE_T = 0.3
#: Output times of the 4-bar runs [s] (dense output and the kept samples).
FOURBAR_T_EVAL = np.linspace(0.0, FOURBAR_T, 11)
#: Speed of the random consistent starts (small: the Agile Eye stays inside its limits).
START_SPEED = 0.3
#: Damping of the Python tau of the callback test [N m s/rad].
DAMPING = 0.05
#: Horizon of the GIL test [s]: a loop of some 0.3 s of CPU, the window in which the main
#: thread must get to run.
SWITCH_TEST_T = 2.0
#: Thread switch interval of the GIL test [s]: longer than the test (no forced switch).
SWITCH_INTERVAL_S = 1000.0
#: The trajectory series compared bit for bit.
SERIES = ("t", "q", "v", "a", "lam")


def _starts(mech, n, seed):
    """n consistent starts near the reference configuration, small velocities."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        v = cc.project_velocity(mech, mech.q_ref, START_SPEED * rng.standard_normal(mech.nv))
        out.append((mech.q_ref.copy(), v))
    return out


def _assert_identical(batch_traj, serial_traj, member):
    for name in SERIES:
        a, b = getattr(batch_traj, name), getattr(serial_traj, name)
        assert np.array_equal(a, b), f"member {member}: {name} differs from the serial run"


def _serial(mech, members, t_final, **options):
    return [cc.simulate(mech, q0, v0, t_final, **options) for q0, v0 in members]


@pytest.mark.parametrize(
    "model, t_final, options",
    [
        ("fourbar.urdf", FOURBAR_T, {}),
        ("fourbar.urdf", FOURBAR_T, {"integrator": "DOP853", "t_eval": FOURBAR_T_EVAL}),
        ("fourbar.urdf", FOURBAR_T, {"dt": 1e-3, "method": "kkt"}),
        ("agile_eye.urdf", AGILE_EYE_T, {}),
        ("agile_eye.urdf", AGILE_EYE_T, {"integrator": "ali3p", "dt": 2e-3}),
    ],
)
def test_batch_equals_serial_runs_bit_for_bit(model, t_final, options):
    members = _starts(cc.load(MODELS / model), N_MEMBERS, seed=3)
    batch = cc.simulate_batch(cc.load(MODELS / model), members, t_final, workers=WORKERS, **options)
    serial = _serial(cc.load(MODELS / model), members, t_final, **options)
    assert batch.ok, batch.report()
    assert batch.workers == WORKERS
    assert all(t.info.backend == "compiled" for t in batch.trajectories)
    for k, (b, s) in enumerate(zip(batch.check(), serial, strict=True)):
        _assert_identical(b, s, k)


def test_failed_members_are_reported_and_the_others_complete():
    mech = cc.load(MODELS / "agile_eye.urdf")
    good = _starts(mech, 3, seed=5)
    q_off = mech.q_ref + 0.3  # far off phi = 0
    v_nan = good[0][1].copy()
    v_nan[0] = np.nan
    members = [good[0], (q_off, np.zeros(mech.nv)), good[1], (mech.q_ref, v_nan), good[2]]
    batch = cc.simulate_batch(mech, members, AGILE_EYE_T, workers=WORKERS)
    assert sorted(batch.failed) == [1, 3]
    assert all(isinstance(e, cc.ClosedChainError) for e in batch.failed.values())
    serial = _serial(cc.load(MODELS / "agile_eye.urdf"), [good[0], good[1], good[2]], AGILE_EYE_T)
    for k, s in zip((0, 2, 4), serial, strict=True):
        _assert_identical(batch[k], s, k)
    lines = batch.report().splitlines()
    assert lines[0] == "3 of 5 members completed"
    assert [ln.split(":")[0] for ln in lines[1:]] == ["member 1", "member 3"]
    with pytest.raises(BatchError, match="member 1: .*\nmember 3: ") as info:
        batch.check()
    assert sorted(info.value.failed) == [1, 3]


def test_python_tau_per_member_runs_under_the_gil_and_its_error_stays_its_own():
    mech = cc.load(MODELS / "fourbar.urdf")
    starts = _starts(mech, 3, seed=7)

    def damping(t, q, v):
        return -DAMPING * v

    def broken(t, q, v):
        raise ValueError("broken controller")

    constant = np.full(mech.nv, 0.1)
    members = [
        cc.Rollout(*starts[0], tau=damping),
        cc.Rollout(*starts[1], tau=broken),
        cc.Rollout(*starts[2], tau=constant),
        starts[0],  # the batch's tau: none
    ]
    batch = cc.simulate_batch(mech, members, FOURBAR_T, workers=WORKERS)
    assert list(batch.failed) == [1]
    assert isinstance(batch[1], ValueError) and "broken controller" in str(batch[1])
    fresh = cc.load(MODELS / "fourbar.urdf")
    for k, start, tau in ((0, starts[0], damping), (2, starts[2], constant), (3, starts[0], None)):
        _assert_identical(batch[k], cc.simulate(fresh, *start, FOURBAR_T, tau=tau), k)


def test_numpy_path_members_give_the_serial_results():
    mech = cc.load(MODELS / "fourbar.urdf")
    members = _starts(mech, 3, seed=9)
    options = {"backend": "numpy", "dt": 2e-3}
    batch = cc.simulate_batch(mech, members, FOURBAR_T, workers=WORKERS, **options)
    serial = _serial(cc.load(MODELS / "fourbar.urdf"), members, FOURBAR_T, **options)
    assert all(t.info.backend == "numpy" for t in batch.check())
    for k, (b, s) in enumerate(zip(batch, serial, strict=True)):
        _assert_identical(b, s, k)


def test_batch_leaves_the_mechanism_as_it_was():
    mech = cc.load(MODELS / "fourbar.urdf")
    members = _starts(mech, 2, seed=11)
    before = dict(mech.__dict__)
    cc.simulate_batch(mech, members, FOURBAR_T, workers=WORKERS)
    # The workers used copies: no attribute (cache, core, workspace) of mech was touched.
    assert mech.__dict__.keys() == before.keys()
    assert all(mech.__dict__[k] is v for k, v in before.items())
    one = cc.simulate_batch(mech, members[:1], FOURBAR_T, workers=1)  # on mech itself
    fresh = cc.load(MODELS / "fourbar.urdf")
    _assert_identical(one[0], cc.simulate(fresh, *members[0], FOURBAR_T), 0)


def test_bad_batch_arguments_name_the_argument():
    mech = cc.load(MODELS / "fourbar.urdf")
    members = _starts(mech, 1, seed=1)
    with pytest.raises(UnknownChoiceError, match="simulate_batch option 'progres'.*rtol"):
        cc.simulate_batch(mech, members, FOURBAR_T, progres=print)
    with pytest.raises(UnknownChoiceError, match="option 'progress'"):
        cc.simulate_batch(mech, members, FOURBAR_T, progress=print)
    with pytest.raises(InvalidArgumentError, match="member 1 must be a Rollout or a pair"):
        cc.simulate_batch(mech, [members[0], mech.q_ref], FOURBAR_T)
    with pytest.raises(InvalidArgumentError, match="workers"):
        cc.simulate_batch(mech, members, FOURBAR_T, workers=0)


def test_a_compiled_loop_lets_another_thread_run_python():
    """While a compiled loop integrates, the main thread runs Python (the GIL released).

    The thread switch interval is made huge, so a thread holding the GIL never hands it
    over on request: the main thread, woken by the loop's first progress call, can run
    before the loop's last progress call only if the loop has released the GIL (with a
    loop that holds it, the main thread runs after the loop, and the flag seen at the
    last step is unset).
    """
    mech = cc.load(MODELS / "agile_eye.urdf")
    (start,) = _starts(mech, 1, seed=13)
    inside = threading.Event()
    main_ran = []
    seen = []

    def progress(t):  # called by the loop after each step, holding the GIL for the call
        inside.set()
        seen[:] = [bool(main_ran)]  # at the last step: did the main thread run meanwhile?

    def run():
        cc.simulate(mech, *start, SWITCH_TEST_T, progress=progress)

    interval = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        worker = threading.Thread(target=run)
        worker.start()
        inside.wait()
        main_ran.append(True)
        worker.join()
    finally:
        sys.setswitchinterval(interval)
    assert seen == [True]
