"""Tests of the Trajectory result: npz and CSV files, and their error paths."""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import re
import zipfile

import numpy as np
import pytest

import closedchain as cc
from closedchain.trajectory import FORMULA_PREFIXES, neutralize_formula

ARRAYS = ("t", "q", "v", "a", "lam", "constraint_residual", "velocity_residual", "energy")


def read_csv(path) -> tuple[list[str], np.ndarray]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], np.array(rows[1:], dtype=float)


# -- npz -----------------------------------------------------------------------------------


def test_npz_round_trip_is_exact(short_traj, tmp_path):
    path = short_traj.save(tmp_path / "t.npz")
    back = cc.Trajectory.load(path)
    for name in ARRAYS:
        assert np.array_equal(getattr(back, name), getattr(short_traj, name)), name
    assert back.info == short_traj.info


@pytest.fixture(scope="module")
def driven_traj(fourbar) -> cc.Trajectory:
    """A run with a constant crank torque: it records the work W of tau."""
    tau = np.array([0.5, 0.0, 0.0])
    return cc.simulate(fourbar, fourbar.q_ref, np.zeros(3), 0.2, dt=1e-2, tau=tau)


def test_work_round_trips_and_files_without_it_still_load(driven_traj, tmp_path):
    """npz keeps W (and the energy balance); an npz written before W was recorded (no
    ``work`` array) loads with work None, whose balance is the drift (W = 0)."""
    assert driven_traj.work is not None
    back = cc.Trajectory.load(driven_traj.save(tmp_path / "t.npz"))
    np.testing.assert_array_equal(back.work, driven_traj.work)
    assert back.energy_balance == driven_traj.energy_balance
    assert back.info.energy_balance == driven_traj.info.energy_balance
    with np.load(tmp_path / "t.npz") as f:
        old = {k: f[k] for k in f.files if k != "work"}
    np.savez(tmp_path / "old.npz", **old)
    legacy = cc.Trajectory.load(tmp_path / "old.npz")
    assert legacy.work is None
    assert legacy.energy_balance == legacy.energy_drift


def test_csv_has_the_work_column_when_recorded(driven_traj, short_traj, tmp_path):
    header, table = read_csv(driven_traj.save(tmp_path / "d.csv"))
    assert header[-1] == "work"
    np.testing.assert_array_equal(table[:, -1], driven_traj.work)
    header, _ = read_csv(short_traj.save(tmp_path / "s.csv"))
    assert header[-1] == "energy"


def test_truncated_npz_names_the_file(short_traj, tmp_path):
    path = short_traj.save(tmp_path / "t.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(
        cc.ClosedChainError, match=rf"^{path}: not a readable closedchain trajectory \(truncated"
    ):
        cc.Trajectory.load(path)


def test_foreign_npz_names_what_is_missing(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, x=np.zeros(3), t=np.zeros(3))
    pattern = (
        rf"^{path}: not a closedchain trajectory: missing q, v, a, lam, constraint_residual, "
        r"velocity_residual, energy, info \(it holds: x, t\)$"
    )
    with pytest.raises(cc.ClosedChainError, match=pattern):
        cc.Trajectory.load(path)


def test_npz_with_a_missing_array_names_it(short_traj, tmp_path):
    full = short_traj.save(tmp_path / "t.npz")
    path = tmp_path / "partial.npz"
    with zipfile.ZipFile(full) as src, zipfile.ZipFile(path, "w") as dst:
        for item in src.namelist():
            if item != "lam.npy":
                dst.writestr(item, src.read(item))
    with pytest.raises(cc.ClosedChainError, match=rf"^{path}: .*missing lam \(it holds: "):
        cc.Trajectory.load(path)


def test_npz_with_inconsistent_rows(short_traj, tmp_path):
    path = tmp_path / "bad.npz"
    arrays = {k: getattr(short_traj, k) for k in ARRAYS}
    arrays["q"] = arrays["q"][:-1]
    np.savez(path, **arrays, info=json.dumps({}))
    with pytest.raises(cc.ClosedChainError, match=r"q do not have one row per time"):
        cc.Trajectory.load(path)


@pytest.mark.parametrize(
    ("name", "content", "pattern"),
    [
        ("missing.npz", None, r"missing.npz: cannot read trajectory: no such file"),
        ("text.npz", b"hello", r"text.npz: not a readable closedchain trajectory"),
        ("t.csv", b"t\n0\n", r"t.csv: only .npz trajectories can be loaded"),
    ],
)
def test_unreadable_files(tmp_path, name, content, pattern):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(cc.ClosedChainError, match=pattern):
        cc.Trajectory.load(path)


def test_single_array_npy_renamed_npz(tmp_path):
    path = tmp_path / "array.npz"
    with path.open("wb") as f:
        np.save(f, np.zeros(3))
    with pytest.raises(
        cc.ClosedChainError, match=r"array.npz: not a closedchain trajectory: a single"
    ):
        cc.Trajectory.load(path)


# -- CSV -----------------------------------------------------------------------------------


def test_csv_is_readable(short_traj, fourbar, tmp_path):
    path = short_traj.save(tmp_path / "t.csv")
    header, table = read_csv(path)
    assert header[0] == "t" and header[-1] == "energy"
    assert [f"q:{n}" for n in fourbar.coordinate_names] == header[1:4]
    assert np.array_equal(table[:, 0], short_traj.t)
    assert np.array_equal(table[:, 1:4], short_traj.q)
    assert np.array_equal(table[:, -1], short_traj.energy)
    # numpy's reader agrees (numbers are plain, unquoted).
    np.testing.assert_array_equal(np.loadtxt(path, delimiter=",", skiprows=1), table)
    with pytest.raises(cc.ClosedChainError, match="valid suffixes"):
        short_traj.save(tmp_path / "t.txt")


#: Joint names a careless or hostile URDF may hold.
HOSTILE_NAMES = ["a,b", 'say "hi"', "two\nlines", '=HYPERLINK("http://x")']


def test_csv_round_trip_with_hostile_names(short_traj, tmp_path):
    info = short_traj.info.to_dict()
    info["configuration_names"] = HOSTILE_NAMES[:3]
    info["velocity_names"] = HOSTILE_NAMES[1:]
    traj = cc.Trajectory(**{k: getattr(short_traj, k) for k in ARRAYS}, info=info)
    header, table = read_csv(traj.save(tmp_path / "t.csv"))
    assert header == [
        "t",
        *(f"q:{n}" for n in HOSTILE_NAMES[:3]),
        *(f"v:{n}" for n in HOSTILE_NAMES[1:]),
        "constraint_residual",
        "velocity_residual",
        "energy",
    ]
    assert table.shape == (len(traj.t), len(header))
    np.testing.assert_array_equal(table[:, 4:7], traj.v)


@pytest.mark.parametrize("prefix", FORMULA_PREFIXES)
def test_formula_prefixes_are_neutralized(prefix):
    assert neutralize_formula(prefix + "SUM(A1)") == "'" + prefix + "SUM(A1)"
    assert neutralize_formula("q:" + prefix) == "q:" + prefix
    assert set(FORMULA_PREFIXES) >= {"=", "+", "-", "@"}


def test_csv_header_cells_starting_a_formula_are_neutralized(short_traj, tmp_path):
    """Header cells are checked whole: a column name that is a formula gets a ``'``."""
    info = short_traj.info.to_dict()
    info["configuration_names"] = ["x", "y", "z"]
    traj = cc.Trajectory(**{k: getattr(short_traj, k) for k in ARRAYS}, info=info)
    path = traj.save(tmp_path / "t.csv")
    text = path.read_text()
    assert text.splitlines()[0].startswith('"t","q:x","q:y","q:z",')
    assert "\n=" not in text and ",=" not in text


def test_csv_names_configuration_entries_when_nq_differs_from_nv(load_mechanism, tmp_path):
    """A continuous joint's two configuration entries get their own CSV column names."""
    mech = load_mechanism("slider_crank")
    traj = cc.simulate(mech, mech.q_ref, np.zeros(mech.nv), 0.01, integrator="rk4", dt=1e-3)
    header, _ = read_csv(traj.save(tmp_path / "t.csv"))
    assert header[1:3] == ["q:crank_joint[0]", "q:crank_joint[1]"]
    assert len([h for h in header if h.startswith("q:")]) == mech.nq


# -- identity: the mechanism a trajectory was simulated on --------------------------------


def test_simulation_records_joint_names_and_model_digest(short_traj, fourbar, tmp_path):
    info = short_traj.info
    assert info.joint_names == ("crank_joint", "coupler_joint", "rocker_joint")
    assert info.joint_names == fourbar.joint_names
    assert info.model_digest == fourbar.digest()
    back = cc.Trajectory.load(short_traj.save(tmp_path / "t.npz")).info
    assert (back.joint_names, back.model_digest) == (info.joint_names, info.model_digest)


def test_check_mechanism_accepts_the_mechanism_it_was_simulated_on(short_traj, fourbar, caplog):
    with caplog.at_level(logging.WARNING):
        short_traj.check_mechanism(fourbar)
    assert caplog.records == []


def test_other_joints_of_the_same_nq_are_refused(short_traj, fourbar_lookalikes):
    other = fourbar_lookalikes["renamed"]
    assert (other.nq, other.nv) == short_traj.q.shape[1:] + short_traj.v.shape[1:]
    with pytest.raises(
        cc.ClosedChainError,
        match=re.escape(
            f"trajectory of 'fourbar' does not fit mechanism 'fourbar' ({other.path}): its joint 2 "
            "is 'rocker_joint', the mechanism's is 'rocker_pivot' (3 against 3 joints)"
        ),
    ):
        short_traj.check_mechanism(other)


def test_missing_joint_is_named(short_traj, fourbar):
    info = dataclasses.replace(short_traj.info, joint_names=short_traj.info.joint_names[:2])
    with pytest.raises(
        cc.ClosedChainError,
        match=r"its joint 2 is missing, the mechanism's is 'rocker_joint' \(2 against 3 joints\)",
    ):
        dataclasses.replace(short_traj, info=info).check_mechanism(fourbar)


def test_same_joints_other_dimensions_are_refused_by_the_digest(short_traj, fourbar_lookalikes):
    other = fourbar_lookalikes["longer_rocker"]
    assert other.joint_names == short_traj.info.joint_names
    with pytest.raises(
        cc.ClosedChainError,
        match=re.escape("trajectory of 'fourbar' was simulated on another model than mechanism ")
        + r".*same joints, model digest [0-9a-f]{12} != [0-9a-f]{12}",
    ):
        short_traj.check_mechanism(other)


@pytest.fixture
def old_npz(short_traj, tmp_path):
    """The trajectory as a closedchain without joint names and digest saved it."""
    path = short_traj.save(tmp_path / "old.npz")
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    info = json.loads(str(arrays.pop("info")))
    del info["joint_names"], info["model_digest"]
    np.savez_compressed(path, **arrays, info=json.dumps(info))
    return path


def test_old_npz_loads_and_is_checked_by_its_configuration_names(
    old_npz, fourbar, fourbar_lookalikes, caplog
):
    old = cc.Trajectory.load(old_npz)
    assert (old.info.joint_names, old.info.model_digest) == ((), None)
    with caplog.at_level(logging.WARNING, logger="closedchain.trajectory"):
        old.check_mechanism(fourbar)
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "records no model digest" in caplog.text
    with pytest.raises(
        cc.ClosedChainError, match=r"its configuration 2 is 'rocker_joint', the mechanism's is"
    ):
        old.check_mechanism(fourbar_lookalikes["renamed"])
