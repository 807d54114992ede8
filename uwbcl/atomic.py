"""Atomic output files: write next to the final name, fsync, rename, fsync the directory. A reader, or a
restarted run, never sees half a file, and a failed write leaves the previous version in place. Every file
uwbcl writes goes through `atomic_path` (CSV, HDF5, PNG, JSON cache entries, archives). Small files it reads
back or is given (site files, cache entries) go through `read_regular_file`."""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import os
import stat
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_umask()  # what open() would give; mkstemp's 0600 would hide outputs from other users
PARTIAL_SUFFIX = ".partial"  # temporary files are ".<name>.<random>.partial" beside the final name


def file_in_the_way(directory: Path) -> Path | None:
    """The file that keeps `directory` from being made: it, or a folder above it, exists and is not a
    directory (None: nothing in the way)."""
    for parent in (directory, *directory.parents):
        if parent.exists() and not parent.is_dir():
            return parent
    return None


def fsync_directory(directory: Path) -> None:
    """Make a rename in `directory` durable (POSIX: the rename lives in the directory's own blocks); some
    filesystems cannot open or fsync a directory, which is not an error."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


_APPEARED = "file appeared while writing; not overwritten"


def _publish(tmp: Path, path: Path, overwrite: bool) -> None:
    if overwrite:
        os.replace(tmp, path)
        return
    # link() fails if the target exists, so a file that appeared while we wrote is never clobbered.
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(errno.EEXIST, _APPEARED, str(path)) from None
    except OSError:  # a filesystem without hard links: best-effort check, then rename
        if path.exists():
            raise FileExistsError(errno.EEXIST, _APPEARED, str(path)) from None
        os.replace(tmp, path)
        return
    tmp.unlink()


@contextlib.contextmanager
def atomic_path(path: Path, *, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it is fsynced and renamed over `path` (with
    overwrite=False: published only if `path` does not exist, else FileExistsError), on any error or
    interruption it is removed and `path` keeps its previous content."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=PARTIAL_SUFFIX, dir=path.parent)
    tmp = Path(name)
    os.fchmod(fd, FILE_MODE)
    os.close(fd)
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        _publish(tmp, path, overwrite)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_directory(path.parent)


def write_bytes_atomic(path: Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: Path, text: str) -> None:
    write_bytes_atomic(path, text.encode())


def write_hdf5_atomic(path: Path, fill: Callable[[Any], None]) -> None:
    """An HDF5 output file (format v110, creation order tracked), made in memory by `fill(h5py.File)` and
    written as bytes: a write that fails (disk full, file too large, EIO) is then an OSError from `write`,
    never an HDF5 library error while h5py closes or frees its objects (which can crash the interpreter).
    For outputs that fit in memory (tables, one image); archives are written by `archive.write_pass`."""
    import h5py

    buf = io.BytesIO()
    with h5py.File(buf, "w", libver=("v110", "v110"), track_order=True) as f:
        fill(f)
    write_bytes_atomic(path, buf.getvalue())


def csv_text(columns, rows) -> str:
    """A CSV with a header line, '\\n' line ends, columns in the given order."""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def csv_bytes(columns, rows) -> bytes:
    return csv_text(columns, rows).encode()


def write_csv_atomic(path: Path, columns, rows) -> None:
    write_bytes_atomic(path, csv_bytes(columns, rows))


def open_regular_file(path, *, follow_symlinks: bool = True) -> io.BufferedReader:
    """`path` opened for reading in binary, without blocking and checked before anything is read, so a FIFO
    (which would block) or a device such as /dev/zero (which never ends) is refused, not read; with
    follow_symlinks=False a symbolic link is refused too. OSError when it cannot be opened, ValueError for
    anything but a regular file."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)
    if not follow_symlinks:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    fd = os.open(path, flags)
    try:  # checked on the descriptor: a directory opens, but as a file object it fails naming the descriptor
        regular = stat.S_ISREG(os.fstat(fd).st_mode)
    except OSError:
        os.close(fd)
        raise
    if not regular:
        os.close(fd)
        raise ValueError("not a regular file (a FIFO, a device or a directory); not read")
    return os.fdopen(fd, "rb")


def read_regular_file(path, max_bytes: int, *, follow_symlinks: bool = True) -> bytes:
    """The bytes of a regular file of at most `max_bytes` (`open_regular_file`). OSError when it cannot be
    opened, ValueError for anything but a regular file of at most `max_bytes`."""
    with open_regular_file(path, follow_symlinks=follow_symlinks) as f:
        raw = f.read(max_bytes + 1)
    if len(raw) > max_bytes:
        raise ValueError(f"larger than {max_bytes >> 20} MiB")
    return raw
