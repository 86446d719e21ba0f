"""Files in and out: bounded reads of input files, atomic writes of output files.

Every file closedchain reads is checked by :func:`check_input_file` before it
is opened (a regular file, not a FIFO that would block or a device without an
end, and no larger than a named limit); every file it writes goes through
:func:`atomic_write`, so that a full disk, a size limit or an interrupt during
the write leaves the previous file as it was and no partial file behind.
"""

from __future__ import annotations

import errno
import math
import os
import secrets
import stat
import sys
import tempfile
import threading
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO

import numpy as np

from .exceptions import ClosedChainError

#: Largest URDF or URDF+ overlay file read [bytes] (the largest model of
#: example-robot-data is below 1 MB; the N-four-bar with N = 40 is 0.1 MB).
MAX_XML_BYTES = 64 * 2**20

#: Largest uncompressed size of an ``.npz`` archive read, summed over its
#: members [bytes]: a trajectory of SimulationSettings.max_outputs = 1e7
#: samples of a 4-bar (t, q, v, residuals, energies: 13 columns) is 1.04e9 bytes.
MAX_NPZ_BYTES = 2**31

#: Largest CSV table read (:func:`closedchain.benchmark.read_rows`) [bytes];
#: the full benchmark writes about 0.1 MB.
MAX_CSV_BYTES = 256 * 2**20

#: Largest mesh file drawn by an animation [bytes]: the page embeds it
#: (base64, a third more); the largest example-robot-data mesh (go1 trunk.dae) is 29 MB.
MAX_MESH_BYTES = 128 * 2**20

#: Largest ``.npy`` header accepted [bytes] (numpy's own default of ``np.load``).
NPY_MAX_HEADER_BYTES = 10_000

#: The first bytes of an ``.npy`` file.
NPY_MAGIC = b"\x93NUMPY"

#: What a path that is not a regular file is, by ``stat`` test (for messages).
_FILE_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)

#: Largest text kept from a C library's stderr (:func:`captured_stderr`) [bytes].
MAX_CAPTURED_STDERR_BYTES = 64 * 2**10

#: Attempts at a fresh temporary name before giving up (names are 64 random bits).
_TEMP_ATTEMPTS = 16


def check_input_file(
    path: str | Path,
    *,
    limit: int,
    what: str = "file",
    error: type[ClosedChainError] = ClosedChainError,
) -> int:
    """Refuse a path that is not a regular file of at most ``limit`` bytes, before opening it.

    A named pipe would block the reader and a device such as ``/dev/zero``
    never ends, so both are refused from ``stat`` alone, as is a file larger
    than the limit (its content is never read).

    Args:
        path: the file (symbolic links are followed).
        limit: largest size accepted [bytes].
        what: what the file is, for the message ("URDF file", "trajectory").
        error: the ClosedChainError subclass raised.

    Returns:
        The file's size [bytes].

    Raises:
        ClosedChainError: (of class ``error``) the file does not exist, cannot
            be examined, is not a regular file, or is larger than ``limit``.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: cannot read {what}: no such file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _FILE_KINDS if test(st.st_mode)), "not a file")
        raise error(f"{path}: {what} is {kind}; valid: a regular file")
    if st.st_size > limit:
        raise error(
            f"{path}: {what} of {st.st_size:.4g} bytes is larger than the limit of "
            f"{limit:.4g} bytes"
        )
    return st.st_size


def read_input_bytes(
    path: str | Path,
    *,
    limit: int,
    what: str = "file",
    error: type[ClosedChainError] = ClosedChainError,
) -> bytes:
    """Return the content of a regular file of at most ``limit`` bytes.

    The file is checked by :func:`check_input_file` and then read with the
    same bound (a file that grows after the check is still refused).

    Raises:
        ClosedChainError: (of class ``error``) see :func:`check_input_file`,
            or the file cannot be read.
    """
    check_input_file(path, limit=limit, what=what, error=error)
    try:
        with open(path, "rb") as f:
            raw = f.read(limit + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror}") from None
    if len(raw) > limit:
        raise error(f"{path}: {what} is larger than the limit of {limit:.4g} bytes")
    return raw


def check_npz(
    path: str | Path,
    *,
    limit: int | None = None,
    what: str = "archive",
    error: type[ClosedChainError] = ClosedChainError,
) -> dict[str, tuple[int, ...]]:
    """Refuse an ``.npz`` archive (or ``.npy`` file) that would take more than ``limit`` bytes.

    The file is checked by :func:`check_input_file`; then, without inflating
    anything, each member's uncompressed size (the zip directory's
    ``file_size``, which also bounds what the zip reader inflates) is summed
    and compared with ``limit``, and each ``.npy`` header's shape times item
    size is compared with the bytes its member (or file) holds: ``np.load``
    allocates the array a header claims before reading it. A file that is
    neither a zip archive nor an ``.npy`` file is left to ``np.load`` to refuse.

    Args:
        path: the file.
        limit: largest total uncompressed size [bytes] (None: :data:`MAX_NPZ_BYTES`).
        what: what the file is, for the message ("trajectory").
        error: the ClosedChainError subclass raised.

    Returns:
        The shape each ``.npy`` member's header declares, by the name
        ``np.load`` gives it (without ``.npy``); empty for an ``.npy`` file or
        what is not a zip archive. A reader checks them before loading.

    Raises:
        ClosedChainError: (of class ``error``) the file is not a regular file
            or is too large, or a member is too large or claims more data than
            it holds. The message names the file and member.
    """
    limit = MAX_NPZ_BYTES if limit is None else limit
    size = check_input_file(path, limit=limit, what=what, error=error)
    shapes: dict[str, tuple[int, ...]] = {}
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                members = archive.infolist()
                total = sum(m.file_size for m in members)
                if total > limit:
                    raise error(
                        f"{path}: {what} inflates to {total:.4g} bytes, more than the limit of "
                        f"{limit:.4g} bytes"
                    )
                for m in members:
                    if m.filename.endswith(".npy"):
                        with archive.open(m) as f:
                            shapes[m.filename.removesuffix(".npy")] = _check_npy_header(
                                f, m.file_size, f"{path}: {what} member {m.filename!r}", error
                            )
        else:
            with open(path, "rb") as f:
                if f.read(len(NPY_MAGIC)) == NPY_MAGIC:
                    f.seek(0)
                    _check_npy_header(f, size, f"{path}: {what}", error)
    except ClosedChainError:
        raise
    except (
        OSError,
        ValueError,
        EOFError,
        NotImplementedError,
        zlib.error,
        zipfile.BadZipFile,
    ) as exc:
        raise error(f"{path}: {what} is unreadable: {type(exc).__name__}: {exc}") from None
    return shapes


def _check_npy_header(f: IO[bytes], size: int, where: str, error) -> tuple[int, ...]:
    """Return the shape of an ``.npy`` stream, refusing a header that claims more than
    its ``size`` bytes."""
    fmt = np.lib.format
    version = fmt.read_magic(f)
    # Versions 2 and 3 share the header layout (3 only allows UTF-8 in field names).
    read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, _, dtype = read_header(f, max_header_size=NPY_MAX_HEADER_BYTES)
    claimed = math.prod(shape) * dtype.itemsize
    if claimed > size:
        raise error(
            f"{where} claims an array of shape {shape} ({claimed:.4g} bytes) in {size} bytes"
        )
    return shape


def _open_temporary(path: Path) -> tuple[int, Path]:
    """Create a new empty file beside ``path``; return its descriptor and path.

    The file is made by ``os.open`` with mode 0o666, so the process umask
    applies as it does to any new file (``tempfile.mkstemp`` would make it 0o600).
    """
    for _ in range(_TEMP_ATTEMPTS):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(path))


@contextmanager
def atomic_write(
    path: str | Path, mode: str = "wb", *, encoding: str | None = None, newline: str | None = None
) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success move it onto ``path``.

    The content is written to a new file in the same directory, flushed to
    disk (``fsync``) and renamed onto ``path`` (``os.replace``, atomic on
    POSIX): readers see the previous file or the complete new one, never a
    part. On any error, KeyboardInterrupt or SystemExit in the block or while
    finishing, the temporary file is removed and ``path`` is left as it was.

    Args:
        path: the file to write (replaced when it exists).
        mode: ``"wb"`` or ``"w"`` (text).
        encoding: text encoding (text mode).
        newline: newline translation (text mode; ``""`` for the csv module).

    Yields:
        The open temporary file.

    Raises:
        OSError: the temporary file cannot be made, written or renamed; the
            error names ``path`` (its ``filename``), not the temporary file.
    """
    path = Path(path)
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write mode must be 'w' or 'wb', got {mode!r}")
    try:
        fd, tmp = _open_temporary(path)
    except OSError as exc:
        raise _naming(exc, path) from exc
    try:
        with os.fdopen(fd, mode, encoding=encoding, newline=newline) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _naming(exc, path) from exc
        raise


def _naming(exc: OSError, path: Path) -> OSError:
    """Return an OSError of the same kind whose ``filename`` is ``path``."""
    if exc.errno is None:
        return OSError(f"{path}: {exc}")
    return OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))


def save_figure(fig, path: str | Path, **kwargs) -> None:
    """Write a matplotlib figure atomically, in the format its suffix names.

    Args:
        fig: a ``matplotlib.figure.Figure``.
        path: the image file; its suffix (``.png``, ``.pdf``, ``.svg``, ...)
            gives the format.
        **kwargs: passed to ``fig.savefig`` (``dpi``, ...).
    """
    fmt = Path(path).suffix.lower().removeprefix(".")
    with atomic_write(path) as f:
        fig.savefig(f, format=fmt, **kwargs)


class CapturedText:
    """What :func:`captured_stderr` caught; ``text`` is set when the block ends."""

    text: str = ""


#: Held by whatever in closedchain points file descriptor 2 elsewhere or writes to it
#: (:func:`captured_stderr`, the command line's messages): two threads that swapped fd 2
#: at once could each restore the other's temporary file, leaving the process's standard
#: error on a deleted file. Re-entrant: a capture may nest in the same thread.
STDERR_LOCK = threading.RLock()


@contextmanager
def captured_stderr() -> Iterator[CapturedText]:
    """Catch what C or C++ code writes to file descriptor 2 during the block.

    urdfdom (inside Pinocchio's URDF reader) prints its ``Error:`` lines
    straight to fd 2, where Python's ``sys.stderr`` cannot catch them; the
    caller folds them into its own one-line message instead. The descriptor is
    restored however the block ends, under :data:`STDERR_LOCK` (so concurrent
    captures take turns); at most :data:`MAX_CAPTURED_STDERR_BYTES` are kept.
    What another thread writes to fd 2 without the lock meanwhile is caught too
    (Pinocchio's reader holds the GIL, so only Python code between the swaps can).

    Yields:
        A :class:`CapturedText` whose ``text`` holds the output after the block.
    """
    captured = CapturedText()
    with STDERR_LOCK:
        sys.stderr.flush()
        with tempfile.TemporaryFile() as sink:
            saved = os.dup(2)
            try:
                os.dup2(sink.fileno(), 2)
                yield captured
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                sink.seek(0)
                captured.text = sink.read(MAX_CAPTURED_STDERR_BYTES).decode("utf-8", "replace")
