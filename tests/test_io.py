"""Tests of closedchain._io: atomic writes, bounded reads, npz size checks, fd 2 capture."""

from __future__ import annotations

import io
import os
import re
import stat
import zipfile

import numpy as np
import pytest

import closedchain as cc
from closedchain import _io
from closedchain._io import (
    atomic_write,
    captured_stderr,
    check_input_file,
    check_npz,
    read_input_bytes,
    save_figure,
)

#: What a previous output holds before a failed write replaces it.
PREVIOUS = b"previous good content\n"


def leftovers(directory) -> list[str]:
    """Return the names of the temporary files left in ``directory``."""
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# -- atomic_write -----------------------------------------------------------------------------


def test_atomic_write_replaces_the_file_with_umask_permissions(tmp_path):
    path = tmp_path / "out.txt"
    path.write_bytes(PREVIOUS)
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write("new\n")
    assert path.read_text() == "new\n"
    assert leftovers(tmp_path) == []
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask


@pytest.mark.parametrize("exception", [RuntimeError("boom"), KeyboardInterrupt(), SystemExit(3)])
def test_a_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path, exception):
    path = tmp_path / "out.bin"
    path.write_bytes(PREVIOUS)
    with pytest.raises(type(exception)):
        with atomic_write(path) as f:
            f.write(b"half of the new cont")
            raise exception
    assert path.read_bytes() == PREVIOUS
    assert leftovers(tmp_path) == []


def test_an_os_error_names_the_final_path_not_the_temporary(tmp_path):
    path = tmp_path / "out.bin"
    path.write_bytes(PREVIOUS)
    with pytest.raises(OSError, match="No space left") as info:
        with atomic_write(path) as f:
            f.write(b"x")
            raise OSError(28, "No space left on device", f.name)
    assert info.value.filename == str(path)
    assert info.value.errno == 28
    assert path.read_bytes() == PREVIOUS
    assert leftovers(tmp_path) == []


def test_a_directory_in_the_way_is_an_os_error_naming_it(tmp_path):
    path = tmp_path / "out.npz"
    path.mkdir()
    with pytest.raises(IsADirectoryError) as info:
        with atomic_write(path) as f:
            f.write(b"x")
    assert info.value.filename == str(path)
    assert leftovers(tmp_path) == []


def test_a_missing_directory_is_an_os_error_naming_the_file(tmp_path):
    path = tmp_path / "nowhere" / "out.csv"
    with pytest.raises(FileNotFoundError) as info:
        with atomic_write(path):
            pass
    assert info.value.filename == str(path)


def test_trajectory_save_failing_midway_keeps_the_previous_file(
    tmp_path, fourbar_traj, monkeypatch
):
    """The writer raising after part of the rows (a full disk) leaves the previous CSV."""
    path = tmp_path / "t.csv"
    path.write_bytes(PREVIOUS)
    monkeypatch.setattr("csv.writer", _FailingCsvWriter)
    with pytest.raises(OSError, match="No space left") as info:
        fourbar_traj.save(path)
    assert info.value.filename == str(path)
    assert path.read_bytes() == PREVIOUS
    assert leftovers(tmp_path) == []


class _FailingCsvWriter:
    """A csv.writer whose header goes through and whose rows hit a full disk."""

    def __init__(self, f, **kwargs):
        self.f = f

    def writerow(self, row):
        self.f.write(",".join(map(str, row)) + "\n")

    def writerows(self, rows):
        raise OSError(28, "No space left on device")


@pytest.mark.parametrize("suffix", [".png", ".svg", ".pdf"])
def test_save_figure_takes_the_format_from_the_suffix(tmp_path, suffix):
    from matplotlib.figure import Figure

    fig = Figure()
    fig.add_subplot().plot([0, 1], [1, 0])
    path = tmp_path / f"f{suffix}"
    save_figure(fig, path)
    magic = {".png": b"\x89PNG", ".svg": b"<?xml", ".pdf": b"%PDF"}[suffix]
    assert path.read_bytes().startswith(magic)
    assert leftovers(tmp_path) == []


# -- bounded reads ----------------------------------------------------------------------------


def test_a_fifo_is_refused_without_opening_it(tmp_path):
    fifo = tmp_path / "pipe.urdf"
    os.mkfifo(fifo)
    with pytest.raises(
        cc.ModelFileError, match=rf"^{re.escape(str(fifo))}: URDF file is a named pipe"
    ):
        read_input_bytes(fifo, limit=100, what="URDF file", error=cc.ModelFileError)


@pytest.mark.parametrize(
    ("path", "kind"), [("/dev/zero", "a character device"), ("{tmp}", "a directory")]
)
def test_devices_and_directories_are_refused(tmp_path, path, kind):
    path = path.format(tmp=tmp_path)
    with pytest.raises(cc.ClosedChainError, match=rf"^{re.escape(path)}: file is {kind}; valid"):
        check_input_file(path, limit=100)


def test_a_file_over_the_limit_is_refused_before_reading(tmp_path):
    path = tmp_path / "big.urdf"
    path.write_bytes(b"x" * 101)
    with pytest.raises(
        cc.ClosedChainError, match=r"big.urdf: file of 101 bytes is larger than the limit of 100"
    ):
        read_input_bytes(path, limit=100)
    assert read_input_bytes(path, limit=101) == b"x" * 101


def test_a_missing_file_says_so(tmp_path):
    with pytest.raises(cc.ClosedChainError, match=r"none.npz: cannot read file: no such file"):
        check_input_file(tmp_path / "none.npz", limit=100)


def npy_bytes(shape: tuple[int, ...], payload: bytes = b"\0" * 16) -> bytes:
    """An .npy header claiming ``shape`` float64, followed by ``payload``."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": "<f8", "fortran_order": False, "shape": shape}
    )
    return buf.getvalue() + payload


def test_an_npz_member_claiming_a_huge_array_is_refused(tmp_path):
    """A 4.5 GB header in a few hundred bytes: refused before np.load allocates it."""
    path = tmp_path / "huge.npz"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("t.npy", npy_bytes((562_500_000,)))
    with pytest.raises(
        cc.ClosedChainError,
        match=r"huge.npz: trajectory member 't.npy' claims an array of shape \(562500000,\) "
        r"\(4.5e\+09 bytes\) in \d+ bytes",
    ):
        cc.Trajectory.load(path)


def test_an_npy_file_claiming_a_huge_array_is_refused(tmp_path):
    path = tmp_path / "renamed.npz"
    path.write_bytes(npy_bytes((10**9, 10)))
    with pytest.raises(cc.ClosedChainError, match=r"renamed.npz: trajectory claims an array"):
        cc.Trajectory.load(path)


def test_an_npz_inflating_past_the_limit_is_refused_before_inflating(tmp_path, monkeypatch):
    """1 MB of zeros compress to 1 kB; with the limit at 0.5 MB nothing is inflated."""
    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        z.writestr("t.npy", npy_bytes((2**17,), b"\0" * 2**20))
    assert path.stat().st_size < 2**12
    monkeypatch.setattr(_io, "MAX_NPZ_BYTES", 2**19)
    with pytest.raises(
        cc.ClosedChainError, match=r"bomb.npz: trajectory inflates to 1.049e\+06 bytes, more than"
    ):
        cc.Trajectory.load(path)


def test_check_npz_passes_a_saved_trajectory(tmp_path, fourbar_traj):
    path = fourbar_traj.save(tmp_path / "t.npz")
    check_npz(path, limit=path.stat().st_size * 100)
    assert cc.Trajectory.load(path).t.shape == fourbar_traj.t.shape


# -- captured_stderr ----------------------------------------------------------------------------


def test_captured_stderr_catches_fd_2_and_restores_it(capfd):
    with captured_stderr() as captured:
        os.write(2, b"Error:   from C++\n")
    os.write(2, b"after\n")
    assert captured.text == "Error:   from C++\n"
    assert capfd.readouterr().err == "after\n"


def test_captured_stderr_restores_fd_2_after_an_exception(capfd):
    with pytest.raises(RuntimeError, match="boom"):
        with captured_stderr() as captured:
            os.write(2, b"partial\n")
            raise RuntimeError("boom")
    os.write(2, b"after\n")
    assert captured.text == "partial\n"
    assert capfd.readouterr().err == "after\n"


def test_an_inconsistent_trajectory_is_refused_before_any_array_is_inflated(
    tmp_path, fourbar_traj, monkeypatch
):
    """All members present, q a deflate bomb with the wrong rows: no array is read."""
    path = tmp_path / "bomb.npz"
    good = tmp_path / "good.npz"
    fourbar_traj.save(good)
    with zipfile.ZipFile(good) as src, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as dst:
        for name in src.namelist():
            if name != "q.npy":
                dst.writestr(name, src.read(name))
        dst.writestr("q.npy", npy_bytes((2**17,), b"\0" * 2**20))
    reads = []
    read_array = np.lib.format.read_array
    monkeypatch.setattr(
        np.lib.format, "read_array", lambda *a, **k: reads.append(1) or read_array(*a, **k)
    )
    with pytest.raises(cc.ClosedChainError, match=r"bomb.npz: .* q do not have one row per time"):
        cc.Trajectory.load(path)
    assert reads == []
    assert cc.Trajectory.load(good).q.shape == fourbar_traj.q.shape
    assert len(reads) >= 8  # the arrays of a good file are read by np.lib.format.read_array
