"""Atomic output files: write next to the final name, fsync, rename. A reader, or a restarted run, never sees
half a file, and a failed write leaves the previous version in place. Used for every output uwbcl writes."""

from __future__ import annotations

import csv
import io
import os
import tempfile
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


FILE_MODE = 0o666 & ~_umask()  # what open() would give; mkstemp's 0600 would hide outputs from other users


def write_bytes_atomic(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.fchmod(fd, FILE_MODE)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: Path, text: str) -> None:
    write_bytes_atomic(path, text.encode())


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
