"""Scan archive format v1: one HDF5 file per pass along the rail. The contract is docs/archive-format.md.

``write_pass`` writes atomically (a hidden ``.<name>.partial`` next to the target, fsync, rename), so a
reader never sees a half-written file. ``read_pass`` validates everything and reports each problem as an
``ArchiveError`` naming the file and the HDF5 field ("scan.h5: /radar@sample_rate_hz: missing").
``read_pass_header`` reads metadata only, for cheap directory discovery.

The reader is a security boundary (archives come from rigs, USB sticks and network shares): it opens regular
files only, reads nothing but what the file itself holds (soft and external links, virtual datasets and
external raw storage are refused by name), accepts only the standard lossless filters, and checks every
declared shape against `ReadLimits` before any value is read, so a small file cannot declare its way to
gigabytes of memory (a compression bomb decompresses to at most its declared, checked size).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import itertools
import logging
import math
import os
import stat
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NoReturn

import h5py
import numpy as np

from uwbcl.atomic import PARTIAL_SUFFIX, atomic_path
from uwbcl.geometry import describe_gaps, track_gaps
from uwbcl.model import MeasuredPulse, PassGeometry, RadarParameters, RawRF, ScanPass
from uwbcl.names import safe_name
from uwbcl.records import ReadLimits
from uwbcl.utc import parse_utc

FORMAT_NAME = "uwbcl-scan"
FORMAT_VERSION = 1  # major version: bumped only by changes an existing reader would misread
# additions this reader knows (section 5): 1.1 = range_delay_s, /raw/rf; 1.2 = the measured pulse
# (/radar@pulse_shape = "measured", /radar/pulse_frequency_hz, /radar/pulse_spectrum) and the rail deviations
# /pulses/antenna_y_m, /pulses/antenna_z_m
FORMAT_MINOR_VERSION = 2
BANDWIDTH_DEFINITION = "-10 dB"
PULSE_SHAPE = "gaussian"
PULSE_SHAPES = (PULSE_SHAPE, "measured")  # "measured": format 1.2, the pulse in /radar/pulse_spectrum
MAX_PULSE_SPECTRUM_SAMPLES = 65536  # samples of a measured pulse's spectrum (1.2)
MAX_RAIL_DEVIATION_M = 0.5  # |antenna_y_m|, |antenna_z_m| (1.2): beyond, first-order compensation fails
ECHO_DTYPES = ("complex64", "complex128", "int16")
INT16_FULL_SCALE = 32767  # symmetric: -32768 is never written, so +-peak maps to +-32767
FILE_SUFFIX = ".h5"  # what uwbcl writes
# What a scan of a tree reads as an archive (any case): other writers name HDF5 files .hdf5 or .H5, and the
# name is a convenience only (docs/archive-format.md section 1).
READ_SUFFIXES = (".h5", ".hdf5")


def is_archive_name(name: str) -> bool:
    return name.lower().endswith(READ_SUFFIXES)

_LIBVER = ("v110", "v110")  # the h5py wheel bundles HDF5 2.0; "latest" would lock out older readers
_GZIP_LEVEL = 4
_CHUNK_TARGET_BYTES = 1 << 20
_UNITS = {"/pulses/time_s": "s", "/pulses/position_m": "m", "/echo": "arb",
          "/radar/pulse_frequency_hz": "Hz", "/radar/pulse_spectrum": "arb",  # 1.2
          "/pulses/antenna_y_m": "m", "/pulses/antenna_z_m": "m"}  # 1.2
# HDF5 filter id -> name: the standard lossless filters a reader may decode. Anything else (a plugin, szip,
# a filter that needs code we do not ship) is refused rather than handed to a decoder we did not choose.
ALLOWED_FILTERS = {1: "gzip", 2: "shuffle", 3: "fletcher32", 32000: "lzf"}
_MAX_ATTRIBUTE_ELEMENTS = 16  # the largest attribute of the format has 3; anything bigger is not ours

_ROOT_STR = ("format", "rig_id", "pass_id", "pass_start_time", "created_by")
_RADAR_FLOAT = (
    "carrier_frequency_hz",
    "bandwidth_hz",
    "sample_rate_hz",
    "pulse_repetition_frequency_hz",
    "antenna_aperture_m",
    "range_window_start_s",
)
_RADAR_POSITIVE = _RADAR_FLOAT[:5]


class ArchiveError(ValueError):
    """A scan file that cannot be trusted; names the file and the HDF5 field ("/group@attr" or "/dataset")."""

    def __init__(self, path: str | os.PathLike[str], field: str, reason: str) -> None:
        # args hold all three so the exception pickles (multiprocessing workers re-raise it).
        super().__init__(str(path), field, reason)
        self.path, self.field, self.reason = str(path), field, reason

    def __str__(self) -> str:
        return f"{self.path}: {self.field}: {self.reason}"


# ----------------------------------------------------------------------------------------------- naming


def height_mm(height_m: float) -> int:
    return round(float(height_m) * 1000.0)


def default_pass_id(scan: ScanPass) -> str:
    return f"{scan.rig_id}-c{scan.cycle:06d}-h{height_mm(scan.geometry.height_m):04d}"


def default_relative_path(scan: ScanPass) -> Path:
    """``<rig_id>/<YYYY-MM-DD>/<rig_id>_c<cycle:06d>_h<height_mm:04d>.h5``, the date being the UTC pass
    start."""
    day = parse_utc(scan.pass_start_time).date().isoformat()
    rig = safe_name(scan.rig_id)  # a controller's RIG_ID is data, never a path ("../x" stays inside)
    name = f"{rig}_c{scan.cycle:06d}_h{height_mm(scan.geometry.height_m):04d}{FILE_SUFFIX}"
    return Path(rig, day, name)


def find_pass_files(root: str | os.PathLike[str]) -> list[Path]:
    """Finished scan files under ``root``, sorted; hidden files (in-progress ``.partial`` writes) are
    skipped."""
    return walk_pass_files(root).files


def display_name(text: str) -> str:
    """A file name as text that can always be written (UTF-8 CSV, logs): undecodable bytes as \\xNN
    escapes."""
    return os.fsencode(text).decode("utf-8", "backslashreplace")


@dataclasses.dataclass
class TreeWalk:
    """What `walk_pass_files` found: archives to read, and findings that are not archives."""

    files: list[Path]
    problems: list[tuple[str, str, str]]  # (path relative to the root, kind, reason): skipped, reported
    warnings: list[tuple[str, str, str]]  # accepted, but worth a word in the log


def walk_pass_files(root: str | os.PathLike[str], *, skip: tuple[Path, ...] = (),
                    follow_symlinks: bool = False) -> TreeWalk:
    """Every finished archive under `root`, without ever raising for what the tree holds.

    Hidden names are skipped (in-progress `.partial` writes silently, other hidden archives and directories
    reported); undecodable names, unreadable directories, symlink loops, broken links and non-regular files
    are reported; directories in `skip` (the output directory) are not entered. A symlink to an archive inside
    the tree is read (with a warning); one that leaves the tree, and a symlinked directory, only with
    follow_symlinks (then loops are cut by device and inode).
    """
    root = Path(root)
    real_root = os.path.realpath(root)
    skip_ids = set()
    for s in skip:
        with contextlib.suppress(OSError):
            st = os.stat(s)
            skip_ids.add((st.st_dev, st.st_ino))
    walk = TreeWalk([], [], [])
    seen_dirs: set[tuple[int, int]] = set()

    def rel(p: str) -> str:
        return display_name(os.path.relpath(p, root).replace(os.sep, "/"))

    def report(p: str, kind: str, reason: str) -> None:
        walk.problems.append((rel(p), kind, reason))

    stack = [str(root)]
    while stack:
        directory = stack.pop()
        for entry in _list_directory(directory, seen_dirs, skip_ids, report):
            _walk_entry(entry, real_root, follow_symlinks, walk, stack, report, rel)
    walk.files.sort()
    walk.problems.sort()
    walk.warnings.sort()
    return walk


def _list_directory(directory: str, seen_dirs: set[tuple[int, int]], skip_ids: set[tuple[int, int]],
                    report) -> list[os.DirEntry]:
    """The entries of `directory` sorted by name; none for a directory already seen (a loop) or skipped,
    and none, reported, for one that cannot be listed."""
    try:
        st = os.stat(directory)
        if (st.st_dev, st.st_ino) in seen_dirs or (st.st_dev, st.st_ino) in skip_ids:
            return []
        seen_dirs.add((st.st_dev, st.st_ino))
        with os.scandir(directory) as it:
            return sorted(it, key=lambda e: e.name)
    except OSError as e:
        report(directory, "unreadable_directory", f"cannot list: {e.strerror or e}")
        return []


def _walk_entry(entry: os.DirEntry, real_root: str, follow: bool, walk: TreeWalk, stack: list, report,
                rel) -> None:
    """One directory entry: an archive to read, a directory to enter, a finding, or nothing."""
    name = entry.name
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        report(entry.path, "undecodable_name", "the name is not valid UTF-8; rename it to be read")
        return
    if name.startswith("."):
        if name.endswith(PARTIAL_SUFFIX):
            return  # a write in progress (or a dead one): never an archive
        if _is_dir(entry):
            report(entry.path, "hidden_directory", "hidden directories are not searched")
        elif is_archive_name(name):
            report(entry.path, "hidden_file", "hidden files are not read")
        return
    if entry.is_symlink():
        _walk_link(entry, real_root, follow, walk, stack, report, rel)
    elif _is_dir(entry):
        stack.append(entry.path)
    elif is_archive_name(name):
        if entry.is_file(follow_symlinks=False):
            walk.files.append(Path(entry.path))
        else:
            report(entry.path, "not_a_regular_file", "a FIFO, device or socket, not an archive")


def _is_dir(entry: os.DirEntry) -> bool:
    try:
        return entry.is_dir(follow_symlinks=False)
    except OSError:
        return False


def _walk_link(entry: os.DirEntry, real_root: str, follow: bool, walk: TreeWalk, stack: list, report,
               rel) -> None:
    try:
        st = os.stat(entry.path)  # follows the link
    except OSError as e:
        kind = "symlink_loop" if e.errno == errno.ELOOP else "broken_link"
        report(entry.path, kind, f"symbolic link: {e.strerror or e}")
        return
    target = os.path.realpath(entry.path)
    inside = os.path.commonpath([target, real_root]) == real_root
    if stat.S_ISDIR(st.st_mode):
        if follow:
            stack.append(entry.path)
            walk.warnings.append((rel(entry.path), "symlink",
                                  f"a symbolic link to the directory {display_name(target)}, followed "
                                  "(--follow-symlinks): its archives are read through it"))
        else:
            report(entry.path, "directory_link",
                   "a symbolic link to a directory; not followed (--follow-symlinks)")
        return
    if not is_archive_name(entry.name):
        return
    if not stat.S_ISREG(st.st_mode):
        report(entry.path, "not_a_regular_file", "a link to a FIFO, device or socket, not an archive")
    elif inside or follow:
        walk.files.append(Path(entry.path))
        where = "inside the tree" if inside else "outside the tree (--follow-symlinks)"
        walk.warnings.append(
            (rel(entry.path), "symlink", f"a symbolic link to {display_name(target)}, {where}"))
    else:
        report(entry.path, "outside_link", f"a symbolic link to {display_name(target)}, outside the input "
                                           "directory; not read (--follow-symlinks)")


# ----------------------------------------------------------------------------------------------- writing


def write_pass(
    path: str | os.PathLike[str],
    scan: ScanPass,
    *,
    echo_dtype: str = "complex64",
    overwrite: bool = False,
    pass_id: str | None = None,
    created_by: str | None = None,
) -> Path:
    """Write ``scan`` to ``path`` atomically; return the final path.

    echo_dtype: "complex64" (default), "complex128", or "int16" (I/Q counts scaled so the peak component is
    +-32767: error <= scale/2 per component, about 96 dB below the peak). Raises ``FileExistsError`` if
    ``path`` exists and not ``overwrite``, and ``ArchiveError`` if ``scan`` would not read back as valid.
    """
    path = Path(path)
    if echo_dtype not in ECHO_DTYPES:
        raise ValueError(f"echo_dtype must be one of {ECHO_DTYPES}, got {echo_dtype!r}")
    if not overwrite and path.exists():
        raise FileExistsError(errno.EEXIST, "scan file exists (--overwrite, or overwrite=True in Python, "
                              "replaces it)", str(path))

    header = check_scan(scan, path, pass_id=pass_id, created_by=created_by)
    echo = np.asarray(scan.echo)
    time_s = np.asarray(scan.pulse_time_s, dtype=np.float64)
    position_m = np.asarray(scan.pulse_position_m, dtype=np.float64)
    stored, layout, scale = _encode_echo(path, echo, echo_dtype)

    with atomic_path(path, overwrite=overwrite) as partial, h5py.File(partial, "w", libver=_LIBVER) as f:
        _write_header(f, header)
        _write_dataset(f, "/pulses/time_s", time_s)
        _write_dataset(f, "/pulses/position_m", position_m)
        ds = _write_dataset(f, "/echo", stored)
        ds.attrs["layout"] = layout
        ds.attrs["scale"] = np.float64(scale)
        _write_additions(f, path, scan)
    return path


def check_scan(scan: ScanPass, path: Any = "<pass>", *, pass_id: str | None = None,
               created_by: str | None = None) -> dict[str, Any]:
    """ArchiveError (naming `path` and the field) for a pass `write_pass` would refuse: the same checks, run
    before anything is written (`uwbcl acquire` runs them on a pass as the controller described it, so a
    value no archive may hold re-runs the pass instead of stopping at the write). Returns the header."""
    echo = np.asarray(scan.echo)
    if echo.ndim != 2 or not np.iscomplexobj(echo):
        raise ArchiveError(path, "/echo", f"expected a 2-D complex array, got {echo.dtype} {echo.shape}")
    header = _header_from_scan(scan, pass_id, created_by)
    _check_header(path, header)
    _check_pulses(path, np.asarray(scan.pulse_time_s, dtype=np.float64),
                  np.asarray(scan.pulse_position_m, dtype=np.float64), echo.shape[0])
    _check_echo_values(path, echo)
    return header


def _header_from_scan(scan: ScanPass, pass_id: str | None, created_by: str | None) -> dict[str, Any]:
    r, g = scan.radar, scan.geometry
    n_pulses, samples_per_pulse = np.shape(scan.echo)
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "rig_id": scan.rig_id,
        "cycle": int(scan.cycle),
        "pass_id": default_pass_id(scan) if pass_id is None else pass_id,
        "pass_start_time": scan.pass_start_time,
        "created_by": created_by
        or f"uwbcl.archive (h5py {h5py.__version__}, HDF5 {h5py.version.hdf5_version})",
        "carrier_frequency_hz": float(r.carrier_frequency_hz),
        "bandwidth_hz": float(r.bandwidth_hz),
        "bandwidth_definition": BANDWIDTH_DEFINITION,
        "pulse_shape": PULSE_SHAPE if r.measured_pulse is None else "measured",
        "sample_rate_hz": float(r.sample_rate_hz),
        "pulse_repetition_frequency_hz": float(r.pulse_repetition_frequency_hz),
        "antenna_aperture_m": float(r.antenna_aperture_m),
        "range_window_start_s": float(scan.range_window_start_s),
        "samples_per_pulse": int(samples_per_pulse),
        "height_m": float(g.height_m),
        "rotation_table_angle_deg": float(g.rotation_table_angle_deg),
        "reference_point_m": tuple(float(v) for v in g.reference_point_m),
        "boresight_y_sign": int(g.boresight_y_sign),
        "n_pulses": int(n_pulses),
    }


def _decode_echo(raw: np.ndarray, layout: str, scale: float) -> np.ndarray:
    """The complex128 echo of a stored one (`_encode_echo`'s inverse, to its rounding)."""
    echo = np.empty(raw.shape[:2], dtype=np.complex128)
    if layout == "int16_iq":
        echo.real, echo.imag = raw[..., 0], raw[..., 1]
    else:
        echo[...] = raw
    echo *= scale
    return echo


def as_stored(scan: ScanPass, echo_dtype: str = "complex64") -> ScanPass:
    """The pass as `write_pass(..., echo_dtype=echo_dtype)` stores it and `read_pass` gives it back: its echo
    rounded to the stored type. `uwbcl acquire --process` measures this, so that its rows are those `uwbcl
    process` gets from the archives (a complex128 echo rounded differently flipped a few decisions: up to
    1.75 mm in a row's residual over 422 cycles)."""
    stored, layout, scale = _encode_echo(Path(scan.source or "<memory>"), scan.echo, echo_dtype)
    return dataclasses.replace(scan, echo=_decode_echo(stored, layout, scale))


def _encode_echo(path: Path, echo: np.ndarray, echo_dtype: str) -> tuple[np.ndarray, str, float]:
    if echo_dtype != "int16":
        stored = echo.astype(echo_dtype)
        if not np.isfinite(stored).all():  # e.g. |value| > 3.4e38 overflows complex64
            raise ArchiveError(path, "/echo", f"values overflow {echo_dtype}")
        return stored, "complex", 1.0
    peak = float(max(np.abs(echo.real).max(), np.abs(echo.imag).max()))
    scale = peak / INT16_FULL_SCALE if peak > 0 else 1.0
    iq = np.stack([echo.real, echo.imag], axis=-1) / scale
    counts = np.clip(np.rint(iq), -INT16_FULL_SCALE, INT16_FULL_SCALE).astype(np.int16)
    return counts, "int16_iq", scale


def _write_header(f: h5py.File, h: dict[str, Any]) -> None:
    for name in _ROOT_STR:
        f.attrs[name] = h[name]
    f.attrs["format_version"] = np.int64(h["format_version"])
    f.attrs["cycle"] = np.int64(h["cycle"])
    radar = f.create_group("radar")
    for name in _RADAR_FLOAT:
        radar.attrs[name] = np.float64(h[name])
    radar.attrs["bandwidth_definition"] = h["bandwidth_definition"]
    radar.attrs["pulse_shape"] = h["pulse_shape"]
    radar.attrs["samples_per_pulse"] = np.int64(h["samples_per_pulse"])
    geometry = f.create_group("geometry")
    geometry.attrs["height_m"] = np.float64(h["height_m"])
    geometry.attrs["rotation_table_angle_deg"] = np.float64(h["rotation_table_angle_deg"])
    geometry.attrs["reference_point_m"] = np.asarray(h["reference_point_m"], dtype=np.float64)
    geometry.attrs["boresight_y_sign"] = np.int64(h["boresight_y_sign"])


def _write_dataset(f: h5py.File, name: str, data: np.ndarray) -> h5py.Dataset:
    # Chunks of whole rows (~1 MiB) so a reader can pull a pulse range; the Fletcher-32 checksum turns
    # silent corruption of the data into a read error.
    row_bytes = max(1, data[:1].nbytes)
    rows = int(min(data.shape[0], max(1, _CHUNK_TARGET_BYTES // row_bytes)))
    ds = f.create_dataset(
        name,
        data=data,
        chunks=(rows, *data.shape[1:]),
        compression="gzip",
        compression_opts=_GZIP_LEVEL,
        shuffle=True,
        fletcher32=True,
    )
    ds.attrs["units"] = _UNITS[name]
    return ds


# ----------------------------------------------------------------------------------------------- reading


def read_pass_header(path: str | os.PathLike[str], limits: ReadLimits = ReadLimits()) -> dict[str, Any]:
    """Validated metadata of a scan file without reading any dataset's values.

    Keys: the root, /radar and /geometry attributes under their own names (``format`` excepted), plus
    ``n_pulses``, ``echo_layout``, ``echo_scale`` and ``path``. Values are plain Python types.
    """
    with _open(path, limits) as f:
        return _read_header(f, path, limits)


def read_pass(path: str | os.PathLike[str], limits: ReadLimits = ReadLimits()) -> ScanPass:
    """Read and fully validate one scan file; the echo comes back as complex128, ``source`` = str(path).

    Raises ArchiveError (naming the file, the object and the reason) for anything the format does not allow or
    `limits` do not admit, OSError when the file cannot be opened at all.
    """
    with _open(path, limits) as f:
        h = _read_header(f, path, limits)
        time_s = _read_values(f, path, "/pulses/time_s").astype(np.float64)
        position_m = _read_values(f, path, "/pulses/position_m").astype(np.float64)
        raw = _read_values(f, path, "/echo")
        scale = h.pop("echo_scale")
        measured = (_read_measured_pulse(f, path, h["sample_rate_hz"]) if h["pulse_shape"] == "measured"
                    else None)
        deviations = [_read_deviation(f, path, name, h["n_pulses"]) if name in h["rail_deviations"] else None
                      for name in _DEVIATION_DATASETS]
    _check_pulses(path, time_s, position_m, h["n_pulses"])
    gaps = track_gaps(position_m)
    if len(gaps):
        _warn_once("%s: /pulses/position_m: %s", path, describe_gaps(gaps))
    # in place, one complex128 copy beside the stored array: at the limits (2^25 samples) 0.5 GB + the file's
    # 0.25 GB (complex64) or 0.125 GB (int16 I/Q), not twice that
    echo = _decode_echo(raw, h["echo_layout"], scale)
    del raw
    _check_echo_values(path, echo)
    radar = RadarParameters(**{k: h[k] for k in _RADAR_POSITIVE}, measured_pulse=measured)
    geometry = PassGeometry(
        height_m=h["height_m"],
        rotation_table_angle_deg=h["rotation_table_angle_deg"],
        reference_point_m=h["reference_point_m"],
        boresight_y_sign=h["boresight_y_sign"],
    )
    return ScanPass(
        radar=radar,
        geometry=geometry,
        # 1.1: the calibrated delay is removed here, so every focuser uses it unchanged.
        range_window_start_s=h["range_window_start_s"],
        range_delay_s=h["range_delay_s"],
        pulse_time_s=time_s,
        pulse_position_m=position_m,
        echo=echo,
        rig_id=h["rig_id"],
        cycle=h["cycle"],
        pass_start_time=h["pass_start_time"],
        source=str(path),
        antenna_y_m=deviations[0],
        antenna_z_m=deviations[1],
    )


def check_regular_file(path: str | os.PathLike[str], limits: ReadLimits | None = None) -> None:
    """ArchiveError unless `path` (after symlinks) is a regular file: a FIFO would block the reader forever, a
    device could stream without end, a directory is not an archive; with `limits`, nor a file larger than
    limits.max_file_bytes; nor one without the HDF5 signature where HDF5 looks for it
    (`_has_hdf5_signature`)."""
    st = os.stat(path)
    mode = st.st_mode
    if limits is not None and stat.S_ISREG(mode) and st.st_size > limits.max_file_bytes:
        raise ArchiveError(path, "/", f"{st.st_size} bytes, more than the limit of {limits.max_file_bytes} "
                           "(limits.max_file_bytes): not read")
    if not stat.S_ISREG(mode):
        kind = ("a FIFO" if stat.S_ISFIFO(mode) else "a directory" if stat.S_ISDIR(mode) else
                "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "not a regular file")
        raise ArchiveError(path, "/", f"not a regular file ({kind}); only regular files are read")
    if not _has_hdf5_signature(path, st.st_size):
        raise ArchiveError(path, "/", "not an HDF5 file (no HDF5 signature at byte 0, 512, 1024, ...; a "
                           "radar's own recording, e.g. a PulsON 440 .p440 scan file, is converted first: "
                           "`uwbcl import`, docs/importing.md)")


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _has_hdf5_signature(path: str | os.PathLike[str], size: int) -> bool:
    """Whether the HDF5 signature lies where HDF5 looks for it: byte 0, 512, 1024, 2048, ... (after a user
    block). Read before a file is hashed: a large file of anything else costs a few reads, not a pass over it
    (an independent tester's 1.9 GiB of zeros took 18 s to be called not an HDF5 file)."""
    with open(path, "rb") as f:
        offset = 0
        while offset + len(_HDF5_SIGNATURE) <= size:
            f.seek(offset)
            if f.read(len(_HDF5_SIGNATURE)) == _HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else 2 * offset
    return False


@contextlib.contextmanager
def _open(path: str | os.PathLike[str], limits: ReadLimits | None = None) -> Iterator[h5py.File]:
    # A missing or unreadable file is the caller's problem, not the file's: those OSErrors pass through.
    # Everything else h5py raises means "not an HDF5 file" or a damaged one.
    check_regular_file(path, limits)
    try:
        f = h5py.File(path, "r", locking=False)
    except (FileNotFoundError, PermissionError, IsADirectoryError):
        raise
    except OSError as e:
        # HDF5's messages are the only signal; fall back to a generic reason when they change.
        text = str(e)
        if "signature not found" in text:
            reason = ("not an HDF5 file (a radar's own recording, e.g. a PulsON 440 .p440 scan file, is "
                      "converted first: `uwbcl import`, docs/importing.md)")
        elif "truncated" in text:
            reason = "truncated HDF5 file"
        else:
            reason = "unreadable HDF5 file (corrupt?)"
        raise ArchiveError(path, "/", f"{reason}: {text}") from e
    try:
        with f:
            yield f
    except ArchiveError:
        raise
    except (OSError, RuntimeError, KeyError) as e:
        raise ArchiveError(path, "/", f"corrupt HDF5 structure: {e}") from e


def _read_header(f: h5py.File, path: Any, limits: ReadLimits = ReadLimits()) -> dict[str, Any]:
    # Identify the file before anything else, so a foreign or newer file gets one clear message.
    fmt = _str_attr(f, "format", path)
    if fmt != FORMAT_NAME:
        raise ArchiveError(path, "/@format", f"expected {FORMAT_NAME!r}, got {fmt!r}")
    version = _int_attr(f, "format_version", path)
    if version > FORMAT_VERSION:
        raise ArchiveError(
            path,
            "/@format_version",
            f"version {version} is newer than this reader supports ({FORMAT_VERSION}); upgrade uwbcl",
        )
    if version != FORMAT_VERSION:
        raise ArchiveError(path, "/@format_version", f"unknown version {version} (expected {FORMAT_VERSION})")

    h: dict[str, Any] = {"format": fmt, "format_version": version}
    for name in _ROOT_STR[1:]:
        h[name] = _free_text_attr(f, name, path) if name in _FREE_TEXT else _str_attr(f, name, path)
    h["cycle"] = _int_attr(f, "cycle", path)
    radar = _group(f, "radar", path)
    for name in _RADAR_FLOAT:
        h[name] = _float_attr(radar, name, path)
    h["bandwidth_definition"] = _str_attr(radar, "bandwidth_definition", path)
    h["pulse_shape"] = _str_attr(radar, "pulse_shape", path)
    h["samples_per_pulse"] = _int_attr(radar, "samples_per_pulse", path)
    geometry = _group(f, "geometry", path)
    h["height_m"] = _float_attr(geometry, "height_m", path)
    h["rotation_table_angle_deg"] = _float_attr(geometry, "rotation_table_angle_deg", path)
    h["reference_point_m"] = _vector_attr(geometry, "reference_point_m", path, 3)
    h["boresight_y_sign"] = _int_attr(geometry, "boresight_y_sign", path)

    time_ds = _dataset(f, "/pulses/time_s", path)
    position_ds = _dataset(f, "/pulses/position_m", path)
    echo_ds = _dataset(f, "/echo", path)
    _check_size(path, echo_ds, time_ds, position_ds, limits)
    layout = _str_attr(echo_ds, "layout", path)
    h["echo_layout"] = layout
    h["echo_scale"] = _float_attr(echo_ds, "scale", path)
    if not (math.isfinite(h["echo_scale"]) and h["echo_scale"] > 0):
        raise ArchiveError(path, "/echo@scale", f"must be finite and > 0, got {h['echo_scale']}")
    _check_echo_storage(path, echo_ds, layout)
    h["n_pulses"] = int(echo_ds.shape[0])
    if echo_ds.shape[1] != h["samples_per_pulse"]:
        raise ArchiveError(
            path,
            "/radar@samples_per_pulse",
            f"{h['samples_per_pulse']} disagrees with /echo, which has {echo_ds.shape[1]} samples per pulse",
        )
    for ds in (time_ds, position_ds):
        if ds.shape != (h["n_pulses"],):
            raise ArchiveError(
                path, ds.name, f"shape {ds.shape}, expected ({h['n_pulses']},) (one per echo row)"
            )
        if ds.dtype.kind not in "fiu":
            raise ArchiveError(path, ds.name, f"expected a real numeric dtype, got {ds.dtype}")
    _check_header(path, h)
    _read_additions(f, path, h)
    if h["sample_rate_hz"] < h["bandwidth_hz"]:  # complex sampling: fs must hold the -10 dB band
        _warn_once("%s: /radar@sample_rate_hz %.4g Hz is below bandwidth_hz %.4g Hz: the pulse's -10 dB band "
                   "does not fit the complex sampling and aliases (1.41 x bandwidth holds its -20 dB band)",
                   path, h["sample_rate_hz"], h["bandwidth_hz"])
    h.pop("format")
    h["path"] = str(path)
    return h


def _check_size(path: Any, echo: h5py.Dataset, time_ds: h5py.Dataset, position_ds: h5py.Dataset,
                limits: ReadLimits) -> None:
    """Declared sizes against the limits, before a single value is read or decompressed."""
    if echo.ndim < 2:
        raise ArchiveError(path, "/echo", f"expected 2 or 3 dimensions, got shape {echo.shape}")
    n_pulses, n_samples = int(echo.shape[0]), int(echo.shape[1])
    if n_pulses > limits.max_pulses:
        raise ArchiveError(path, "/echo", f"{n_pulses} pulses exceed the limit of {limits.max_pulses} "
                           "(limits.max_pulses)")
    if n_samples > limits.max_samples_per_pulse:
        raise ArchiveError(path, "/echo", f"{n_samples} samples per pulse exceed the limit of "
                           f"{limits.max_samples_per_pulse} (limits.max_samples_per_pulse)")
    if n_pulses * n_samples > limits.max_echo_samples:
        raise ArchiveError(path, "/echo", f"{n_pulses} x {n_samples} = {n_pulses * n_samples} samples "
                           f"exceed the limit of {limits.max_echo_samples} (limits.max_echo_samples)")
    for ds in (time_ds, position_ds):
        if ds.size > limits.max_pulses:
            raise ArchiveError(path, ds.name, f"{ds.size} values exceed the limit of {limits.max_pulses} "
                               "(limits.max_pulses)")


MAX_CYCLE = 2**63 - 1  # the /@cycle attribute is an int64
MIN_REFERENCE_RANGE_M = 1e-3  # the reference point's least distance from the rail's line
# The largest chunk a dataset may have beyond its own size (uncompressed bytes): write_pass's are ~1 MiB.
MAX_CHUNK_BYTES = 64 << 20
# HDF5 keeps a few kB of bookkeeping per chunk a read touches: a 455 kB file whose echo was declared in
# 50,000 chunks of one sample, none written, took 4 GB to read at once (an independent tester). A dataset is
# read CHUNKS_PER_READ chunks at a time, and one stored in more than MAX_CHUNKS (a pass chunked per pulse
# has as many as pulses) is not read at all: its time to read grows with the count too.
CHUNKS_PER_READ = 4096
MAX_CHUNKS = 1 << 20


def _chunk_grid(ds: h5py.Dataset) -> tuple[int, ...]:
    """How many chunks a chunked dataset spans along each axis."""
    return tuple(-(-n // c) for n, c in zip(ds.shape, ds.chunks))


def _check_storage(path: Any, ds: h5py.Dataset) -> None:
    """Data stored in this file, decoded by a standard lossless filter: nothing else is read."""
    if ds.is_virtual:
        raise ArchiveError(path, ds.name, "a virtual dataset (its data live in other files); not read")
    dcpl = ds.id.get_create_plist()
    if dcpl.get_external_count():
        name = dcpl.get_external(0)[0]
        raise ArchiveError(path, ds.name,
                           f"external raw storage in {name!r} (data outside the file); not read")
    if ds.chunks is not None:
        # HDF5 decompresses whole chunks: a chunk larger than its dataset (legal with a larger maxshape) is a
        # compression bomb, gigabytes from a small dataset of a small file
        chunk_bytes = math.prod(ds.chunks) * ds.dtype.itemsize
        data_bytes = ds.size * ds.dtype.itemsize
        if chunk_bytes > max(MAX_CHUNK_BYTES, data_bytes):
            raise ArchiveError(path, ds.name, f"a chunk of {list(ds.chunks)} ({chunk_bytes / 2**20:.1f} MiB) "
                               f"for {data_bytes / 2**20:.3f} MiB of data: a chunk may hold at most "
                               f"{MAX_CHUNK_BYTES >> 20} MiB or the whole dataset; not read")
    for i in range(dcpl.get_nfilters()):
        code, _, _, name = dcpl.get_filter(i)
        if code not in ALLOWED_FILTERS:
            label = name.decode(errors="replace") if isinstance(name, bytes) else str(name)
            raise ArchiveError(path, ds.name, f"HDF5 filter {code} ({label}) is not one of the allowed "
                               f"lossless filters ({', '.join(ALLOWED_FILTERS.values())})")


def _check_echo_storage(path: Any, ds: h5py.Dataset, layout: str) -> None:
    if layout == "complex":
        if ds.dtype.kind != "c" or ds.ndim != 2:
            raise ArchiveError(
                path,
                "/echo",
                f"layout 'complex' needs a 2-D complex (compound r,i) dataset, got {ds.dtype} {ds.shape}",
            )
    elif layout == "int16_iq":
        if ds.dtype.kind != "i" or ds.dtype.itemsize != 2 or ds.ndim != 3 or ds.shape[2] != 2:
            raise ArchiveError(
                path, "/echo", f"layout 'int16_iq' needs int16 of shape (N, M, 2), got {ds.dtype} {ds.shape}"
            )
    else:
        raise ArchiveError(path, "/echo@layout", f"expected 'complex' or 'int16_iq', got {layout!r}")


def _read_values(f: h5py.File, path: Any, name: str) -> np.ndarray:
    try:
        ds = f[name]
        n_chunks = math.prod(_chunk_grid(ds)) if ds.chunks is not None else 1
        if n_chunks > MAX_CHUNKS:
            raise ArchiveError(path, name, f"stored in {n_chunks} chunks of {list(ds.chunks)}, more than "
                               f"{MAX_CHUNKS}: not read (reading costs time and memory per chunk)")
        _check_deflate_chunks(path, ds)
        if n_chunks <= CHUNKS_PER_READ or ds.ndim == 0:
            return ds[()]
        out = np.empty(ds.shape, ds.dtype)  # its size is within the limits checked before
        grid = _chunk_grid(ds)
        # blocks of whole chunks along the first two axes, each spanning at most CHUNKS_PER_READ chunks
        steps = [ds.chunks[k] * max(1, CHUNKS_PER_READ // math.prod(grid[k + 1:]))
                 for k in range(min(2, ds.ndim))]
        for starts in itertools.product(*(range(0, n, step) for n, step in zip(ds.shape, steps))):
            block = tuple(slice(a, a + step) for a, step in zip(starts, steps))
            ds.read_direct(out, block, block)
        return out
    except ArchiveError:
        raise
    except (OSError, RuntimeError, ValueError, TypeError) as e:  # checksum, filter or I/O failure
        raise ArchiveError(path, name, f"cannot read data (corrupt or truncated?): {e}") from e


_DEFLATE, _FLETCHER32 = 1, 3  # HDF5 filter codes (ALLOWED_FILTERS)


def _check_deflate_chunks(path: Any, ds: h5py.Dataset) -> None:
    """ArchiveError for a deflate-compressed chunk, without Fletcher-32, that does not inflate to exactly its
    chunk's size: HDF5 reads a stream that ends early without an error, the rest of the chunk as zeros or as
    whatever its buffer held (different on every read). Only where deflate is the pipeline's last filter (the
    first undone on reading); with Fletcher-32 HDF5 itself refuses damaged chunks."""
    if ds.chunks is None:
        return
    dcpl = ds.id.get_create_plist()
    codes = [dcpl.get_filter(i)[0] for i in range(dcpl.get_nfilters())]
    if not codes or codes[-1] != _DEFLATE or _FLETCHER32 in codes:
        return
    want = math.prod(ds.chunks) * ds.dtype.itemsize
    skipped = 1 << (len(codes) - 1)  # the chunk's filter mask: deflate not applied to it
    offsets: list[tuple[int, ...]] = []
    # one walk of the chunk index (get_chunk_info(i) searches it from the start for each i: 32768 chunks
    # took 30 s, a review)
    ds.id.chunk_iter(lambda info: offsets.append(info.chunk_offset))
    for offset in offsets:
        mask, raw = ds.id.read_direct_chunk(offset)
        if mask & skipped:
            continue
        inflate = zlib.decompressobj()
        try:
            size = len(inflate.decompress(raw, want + 1))
        except zlib.error as e:
            raise ArchiveError(path, ds.name, f"chunk at {list(offset)}: bad compressed data ({e})") from None
        if size != want or not inflate.eof:
            raise ArchiveError(path, ds.name, f"chunk at {list(offset)}: inflates to {size} bytes, not its "
                               f"{want} (a truncated or damaged compressed stream)")


# ----------------------------------------------------------------------------------------------- checks
# Shared by writer and reader, so a file write_pass accepts is exactly a file read_pass accepts.


def _check_header(path: Any, h: dict[str, Any]) -> None:
    def fail(field: str, reason: str) -> NoReturn:
        raise ArchiveError(path, field, reason)

    _check_root_attrs(h, fail)
    _check_radar_attrs(h, fail)
    if h["n_pulses"] < 2:
        fail("/echo", f"needs at least 2 pulses, got {h['n_pulses']}")
    _check_geometry_attrs(h, fail)


def _check_root_attrs(h: dict[str, Any], fail: Callable[[str, str], NoReturn]) -> None:
    for name in _ROOT_STR:
        if not isinstance(h[name], str):
            fail(f"/@{name}", f"expected a string, got {type(h[name]).__name__}")
        if "\x00" in h[name]:  # C readers stop there, and CSV readers choke on it in errors.csv
            fail(f"/@{name}", "contains a NUL character")
    for name in ("rig_id", "pass_id"):
        if not h[name].strip():
            fail(f"/@{name}", "must not be empty")
    try:
        parse_utc(h["pass_start_time"])
    except ValueError as e:
        fail("/@pass_start_time", str(e))
    if not 0 <= h["cycle"] <= MAX_CYCLE:
        fail("/@cycle", f"must be between 0 and {MAX_CYCLE} (int64), got {h['cycle']}")


def _check_radar_attrs(h: dict[str, Any], fail: Callable[[str, str], NoReturn]) -> None:
    for name in _RADAR_FLOAT:
        if not math.isfinite(h[name]):
            fail(f"/radar@{name}", f"must be finite, got {h[name]}")
    for name in _RADAR_POSITIVE:
        if not h[name] > 0:
            fail(f"/radar@{name}", f"must be > 0, got {h[name]}")
    if h["bandwidth_definition"] != BANDWIDTH_DEFINITION:
        fail(
            "/radar@bandwidth_definition",
            f"expected {BANDWIDTH_DEFINITION!r}, got {h['bandwidth_definition']!r}",
        )
    if h["pulse_shape"] not in PULSE_SHAPES:
        fail("/radar@pulse_shape", f"expected one of {', '.join(map(repr, PULSE_SHAPES))}, "
             f"got {h['pulse_shape']!r}")
    if h["samples_per_pulse"] < 1:
        fail("/radar@samples_per_pulse", f"must be >= 1, got {h['samples_per_pulse']}")


def _check_geometry_attrs(h: dict[str, Any], fail: Callable[[str, str], NoReturn]) -> None:
    if not math.isfinite(h["height_m"]):
        fail("/geometry@height_m", f"must be finite, got {h['height_m']}")
    angle = h["rotation_table_angle_deg"]
    if not (math.isfinite(angle) and abs(angle) < 90.0):
        fail("/geometry@rotation_table_angle_deg", f"must be finite and within (-90, 90), got {angle}")
    if len(h["reference_point_m"]) != 3 or not all(math.isfinite(v) for v in h["reference_point_m"]):
        fail("/geometry@reference_point_m", f"must be 3 finite values, got {h['reference_point_m']}")
    _, y, z = h["reference_point_m"]
    if math.isfinite(h["height_m"]) and not math.hypot(y, z - h["height_m"]) >= MIN_REFERENCE_RANGE_M:
        # the scene centre sets the processing squint: one on the rail's own line sets none (a tester's
        # (0, 0, h) divided by zero in the focusing)
        fail("/geometry@reference_point_m", f"must lie at least {MIN_REFERENCE_RANGE_M:g} m from the rail's "
             f"line (Y, Z - height_m), got {h['reference_point_m']}")
    if h["boresight_y_sign"] not in (-1, 1):
        fail("/geometry@boresight_y_sign", f"must be -1 or +1, got {h['boresight_y_sign']}")


def _check_pulses(path: Any, time_s: np.ndarray, position_m: np.ndarray, n_pulses: int) -> None:
    for name, x in (("/pulses/time_s", time_s), ("/pulses/position_m", position_m)):
        if x.shape != (n_pulses,):
            raise ArchiveError(path, name, f"shape {x.shape}, expected ({n_pulses},) (one per echo row)")
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise ArchiveError(path, name, f"NaN or inf at pulse {bad[0]}")
    dt = np.diff(time_s)
    if not (dt > 0).all():
        raise ArchiveError(
            path, "/pulses/time_s", f"not strictly increasing (at pulse {np.argmax(dt <= 0) + 1})"
        )
    # The carriage runs both ways along the rail, so decreasing positions are fine; standing still is not.
    dx = np.diff(position_m)
    if not ((dx > 0).all() or (dx < 0).all()):
        step = np.sign(dx[0]) * dx
        raise ArchiveError(
            path, "/pulses/position_m", f"not strictly monotonic (at pulse {np.argmax(step <= 0) + 1})"
        )


# The largest |I| or |Q| of an echo (after its scale): the focusers work in float32 where the error budget
# allows (max 3.4e38), and a pulse's compression gain (its samples, thousands) must not overflow there. No
# radar comes near it; a file that does was written with a wrong scale.
MAX_ECHO_COMPONENT = 1e30


def _check_echo_values(path: Any, echo: np.ndarray) -> None:
    bad = ~np.isfinite(echo)
    if bad.any():
        pulse, sample = np.argwhere(bad)[0]
        raise ArchiveError(path, "/echo", f"NaN or inf (first at pulse {pulse}, sample {sample})")
    largest = max(float(np.max(echo.real, initial=0.0)), -float(np.min(echo.real, initial=0.0)),
                  float(np.max(echo.imag, initial=0.0)), -float(np.min(echo.imag, initial=0.0)))
    if largest > MAX_ECHO_COMPONENT:
        raise ArchiveError(path, "/echo", f"values up to {largest:.3g} (after the scale): more than "
                           f"{MAX_ECHO_COMPONENT:g}, where float32 focusing would overflow; a wrong scale?")


# ----------------------------------------------------------------------------------------------- attributes


def _resolve(f: h5py.File, name: str, path: Any):
    """The object at `name`, reached through hard links only: a soft link (which may loop or point anywhere
    in the file) or an external link (another file, anywhere on the machine) is refused by name."""
    obj, here = f, ""
    for part in name.strip("/").split("/"):
        here = f"{here}/{part}"
        try:
            link = obj.get(part, getlink=True) if isinstance(obj, h5py.Group) else None
        except (OSError, RuntimeError, KeyError, ValueError) as e:
            raise ArchiveError(path, here, f"unreadable link: {e}") from e
        if link is None:
            return None
        if isinstance(link, h5py.ExternalLink):
            raise ArchiveError(path, here, f"an external link to {link.filename!r}:{link.path!r}; only "
                               "objects stored in the file itself are read")
        if isinstance(link, h5py.SoftLink):
            raise ArchiveError(path, here, f"a soft link to {link.path!r}; only hard links are read")
        if not isinstance(link, h5py.HardLink):
            raise ArchiveError(path, here, f"an unsupported link ({type(link).__name__})")
        try:
            obj = obj[part]
        except (OSError, RuntimeError, KeyError, ValueError) as e:
            raise ArchiveError(path, here, f"unreadable object: {e}") from e
    return obj


def _group(f: h5py.File, name: str, path: Any) -> h5py.Group:
    g = _resolve(f, name, path)
    if not isinstance(g, h5py.Group):
        raise ArchiveError(path, f"/{name}", "missing" if g is None else "not a group")
    return g


def _dataset(f: h5py.File, name: str, path: Any) -> h5py.Dataset:
    ds = _resolve(f, name, path)
    if not isinstance(ds, h5py.Dataset):
        raise ArchiveError(path, name, "missing" if ds is None else "not a dataset")
    _check_storage(path, ds)
    units = _str_attr(ds, "units", path)
    if units != _UNITS[name]:
        raise ArchiveError(path, f"{name}@units", f"expected {_UNITS[name]!r}, got {units!r}")
    return ds


def _raw_attr(obj: h5py.HLObject, name: str, path: Any) -> Any:
    # The object's name (an HDF5 query) is looked up only for a message: a header reads ~30 attributes.
    try:
        n_elements = obj.attrs.get_id(name).shape
    except KeyError:
        raise ArchiveError(path, f"{obj.name}@{name}", "missing") from None
    except (OSError, TypeError, ValueError) as e:
        raise ArchiveError(path, f"{obj.name}@{name}", f"unreadable: {e}") from e
    if n_elements and math.prod(n_elements) > _MAX_ATTRIBUTE_ELEMENTS:
        raise ArchiveError(path, f"{obj.name}@{name}",
                           f"shape {n_elements} is far larger than any attribute of the format")
    try:
        return obj.attrs[name]
    except (OSError, TypeError, ValueError) as e:  # e.g. a datatype h5py cannot map to numpy
        raise ArchiveError(path, f"{obj.name}@{name}", f"unreadable: {e}") from e


def _scalar(obj: h5py.HLObject, name: str, path: Any) -> np.ndarray:
    # 1-element arrays are accepted as scalars: several HDF5 front ends (MATLAB, R) write them that way.
    value = np.asarray(_raw_attr(obj, name, path))
    if value.size != 1 or value.ndim > 1:
        raise ArchiveError(path, f"{obj.name}@{name}", f"expected a scalar, got shape {value.shape}")
    return value.reshape(())


# The longest string attribute (bytes) a pass may carry: ids and names are tens of bytes; a value of megabytes
# is not a name, and every message that quotes it would carry it too.
MAX_STRING_ATTR_BYTES = 4096


def _short_string(value: Any, obj: h5py.HLObject, name: str, path: Any) -> None:
    if isinstance(value, str):
        value = value.encode("utf-8", errors="surrogatepass")
    n = len(value) if isinstance(value, bytes) else 0  # bytes, as stored: not characters
    if n > MAX_STRING_ATTR_BYTES:
        raise ArchiveError(path, f"{obj.name}@{name}", f"a string of {n} bytes, more than the "
                           f"{MAX_STRING_ATTR_BYTES} a string attribute may hold (docs/archive-format.md)")


def _str_attr(obj: h5py.HLObject, name: str, path: Any) -> str:
    return _text(obj, name, path, lenient=False)


# Descriptive text no value depends on: read whatever a writer stored (an empty dataspace, as h5py.Empty
# writes it, is ""; bytes that are not UTF-8, e.g. Latin-1 from a Windows writer, are read with replacement
# characters and a warning) rather than refuse the pass over it.
_FREE_TEXT = ("created_by",)


def _free_text_attr(obj: h5py.HLObject, name: str, path: Any) -> str:
    if isinstance(_raw_attr(obj, name, path), h5py.Empty):
        return ""
    return _text(obj, name, path, lenient=True)


def _text(obj: h5py.HLObject, name: str, path: Any, lenient: bool) -> str:
    """A scalar string attribute, at most MAX_STRING_ATTR_BYTES; bytes that are not UTF-8 refused, or with
    `lenient` read with replacement characters and a warning."""
    value = _scalar(obj, name, path).item()
    _short_string(value, obj, name, path)
    if isinstance(value, bytes):
        try:
            value = value.decode("utf-8")
        except UnicodeDecodeError:
            if not lenient:
                raise ArchiveError(path, f"{obj.name}@{name}", "not valid UTF-8") from None
            value = value.decode("utf-8", errors="replace")
            _warn_once("%s: %s@%s is not UTF-8 text; read with replacement characters (descriptive only)",
                       path, obj.name, name)
    if not isinstance(value, str):
        raise ArchiveError(path, f"{obj.name}@{name}", f"expected a string, got {type(value).__name__}")
    return value


def _int_attr(obj: h5py.HLObject, name: str, path: Any) -> int:
    value = _scalar(obj, name, path)
    if value.dtype.kind not in "iu":
        raise ArchiveError(path, f"{obj.name}@{name}", f"expected an integer, got {value.dtype}")
    return int(value)


def _float_attr(obj: h5py.HLObject, name: str, path: Any) -> float:
    value = _scalar(obj, name, path)
    if value.dtype.kind not in "fiu":
        raise ArchiveError(path, f"{obj.name}@{name}", f"expected a real number, got {value.dtype}")
    return float(value)


def _vector_attr(obj: h5py.HLObject, name: str, path: Any, length: int) -> tuple[float, ...]:
    value = np.asarray(_raw_attr(obj, name, path))
    if value.ndim == 2 and 1 in value.shape and value.size == length:  # a column or row vector (MATLAB's)
        value = value.reshape(-1)
    if value.shape != (length,) or value.dtype.kind not in "fiu":
        raise ArchiveError(
            path, f"{obj.name}@{name}", f"expected {length} real numbers, got {value.dtype} {value.shape}"
        )
    return tuple(float(v) for v in value)


# ------------------------------------------------------------------------------------------- 1.1 additions
# Optional additions of format 1.1 (docs/archive-format.md section 9), kept apart from the 1.0 reader above.
# A file without them is written exactly as 1.0 (no format_minor_version attribute).

log = logging.getLogger("uwbcl")

_RAW_UNITS = "counts"
_KNOWN_ATTRIBUTES = {
    "/radar": {*_RADAR_FLOAT, "bandwidth_definition", "pulse_shape", "samples_per_pulse", "range_delay_s"},
    "/geometry": {"height_m", "rotation_table_angle_deg", "reference_point_m", "boresight_y_sign"},
}
_KNOWN_PULSE_DATASETS = {"time_s", "position_m", "antenna_y_m", "antenna_z_m"}
_DEVIATION_DATASETS = ("/pulses/antenna_y_m", "/pulses/antenna_z_m")
_PULSE_DATASETS = ("/radar/pulse_frequency_hz", "/radar/pulse_spectrum")


def _write_additions(f: h5py.File, path: Path, scan: ScanPass) -> None:
    """range_delay_s (a record of the delay already removed from the window start) and /raw/rf (1.1); the
    measured pulse and the rail deviations (1.2). The minor version is the lowest that has them all."""
    delay = float(scan.range_delay_s)
    if not math.isfinite(delay):
        raise ArchiveError(path, "/radar@range_delay_s", f"must be finite, got {delay}")
    raw = scan.raw_rf
    pulse = scan.radar.measured_pulse
    deviations = {name: np.asarray(d, dtype=np.float64) for name, d in
                  zip(_DEVIATION_DATASETS, (scan.antenna_y_m, scan.antenna_z_m)) if d is not None}
    if pulse is not None:
        _check_measured_pulse(path, pulse.frequency_hz, pulse.spectrum, scan.radar.sample_rate_hz)
    for name, d in deviations.items():
        _check_deviation(path, name, d, scan.n_pulses)
    minor = 2 if pulse is not None or deviations else 1 if delay != 0.0 or raw is not None else 0
    if minor == 0:
        return
    f.attrs["format_minor_version"] = np.int64(minor)
    if pulse is not None:
        _write_dataset(f, "/radar/pulse_frequency_hz", pulse.frequency_hz)
        _write_dataset(f, "/radar/pulse_spectrum", pulse.spectrum)
    for name, d in deviations.items():
        _write_dataset(f, name, d)
    if delay != 0.0:  # provenance only: the stored window start is absolute, as a 1.0 reader expects
        f["radar"].attrs["range_delay_s"] = np.float64(delay)
    if raw is not None:
        _check_raw_rf(path, raw, scan.n_pulses)
        rows = int(min(raw.samples.shape[0], max(1, _CHUNK_TARGET_BYTES // max(1, raw.samples[:1].nbytes))))
        ds = f.create_dataset("/raw/rf", data=np.asarray(raw.samples, dtype=np.int32),
                              chunks=(rows, raw.samples.shape[1]), compression="gzip",
                              compression_opts=_GZIP_LEVEL, shuffle=True, fletcher32=True)
        ds.attrs["units"] = _RAW_UNITS
        ds.attrs["bin_period_s"] = np.float64(raw.bin_period_s)
        ds.attrs["scan_start_s"] = np.float64(raw.scan_start_s)


def _check_raw_rf(path: Any, raw: RawRF, n_pulses: int) -> None:
    samples = np.asarray(raw.samples)
    if samples.ndim != 2 or samples.shape[0] != n_pulses or samples.dtype.kind not in "iu":
        raise ArchiveError(path, "/raw/rf", f"expected integers of shape ({n_pulses}, K), got "
                                            f"{samples.dtype} {samples.shape}")
    if samples.size and (samples.min() < np.iinfo(np.int32).min or samples.max() > np.iinfo(np.int32).max):
        raise ArchiveError(path, "/raw/rf", "values do not fit int32")
    if not (math.isfinite(raw.bin_period_s) and raw.bin_period_s > 0):
        raise ArchiveError(path, "/raw/rf@bin_period_s", f"must be finite and > 0, got {raw.bin_period_s}")
    if not math.isfinite(raw.scan_start_s):
        raise ArchiveError(path, "/raw/rf@scan_start_s", f"must be finite, got {raw.scan_start_s}")


def _read_additions(f: h5py.File, path: Any, h: dict[str, Any]) -> None:
    """format_minor_version and range_delay_s into ``h`` (0 and 0.0 if absent); warns of skipped names."""
    minor = _int_attr(f, "format_minor_version", path) if "format_minor_version" in f.attrs else 0
    if minor < 0:
        raise ArchiveError(path, "/@format_minor_version", f"must be >= 0, got {minor}")
    if minor > FORMAT_MINOR_VERSION:
        _warn_once("%s: format 1.%d is newer than this reader (1.%d): additions it does not know are "
                   "ignored", path, minor, FORMAT_MINOR_VERSION)
    h["format_minor_version"] = minor
    radar = f["radar"]
    delay = _float_attr(radar, "range_delay_s", path) if "range_delay_s" in radar.attrs else 0.0
    if not math.isfinite(delay):
        raise ArchiveError(path, "/radar@range_delay_s", f"must be finite, got {delay}")
    h["range_delay_s"] = delay
    _check_pulse_additions(f, path, h)
    _warn_unknown(f, path)


def _check_pulse_additions(f: h5py.File, path: Any, h: dict[str, Any]) -> None:
    """1.2: the measured pulse's datasets (present with pulse_shape "measured", absent otherwise) and the rail
    deviations, by their declared shapes and types before any value is read; h["rail_deviations"] lists the
    deviation datasets present."""
    if h["pulse_shape"] == "measured":
        sizes = []
        for name, kinds in zip(_PULSE_DATASETS, ("f", "c")):
            ds = _dataset(f, name, path)
            if ds.ndim != 1 or ds.dtype.kind not in kinds:
                raise ArchiveError(path, name, f"expected a 1-D {'real' if kinds == 'f' else 'complex'} "
                                   f"dataset, got {ds.dtype} {ds.shape}")
            if not 2 <= ds.shape[0] <= MAX_PULSE_SPECTRUM_SAMPLES:
                raise ArchiveError(path, name, f"{ds.shape[0]} samples, expected 2 to "
                                   f"{MAX_PULSE_SPECTRUM_SAMPLES}")
            sizes.append(ds.shape[0])
        if sizes[0] != sizes[1]:
            raise ArchiveError(path, _PULSE_DATASETS[1], f"{sizes[1]} samples, but "
                               f"{_PULSE_DATASETS[0]} has {sizes[0]} (one spectrum value per frequency)")
    else:
        for name in _PULSE_DATASETS:
            if _resolve(f, name, path) is not None:
                raise ArchiveError(path, name, f"present, but /radar@pulse_shape is {h['pulse_shape']!r} "
                                   "(a measured pulse needs pulse_shape \"measured\")")
    h["rail_deviations"] = []
    for name in _DEVIATION_DATASETS:
        if _resolve(f, name, path) is None:
            continue
        ds = _dataset(f, name, path)
        if ds.shape != (h["n_pulses"],) or ds.dtype.kind not in "fiu":
            raise ArchiveError(path, name, f"expected real numbers of shape ({h['n_pulses']},) (one per echo "
                               f"row), got {ds.dtype} {ds.shape}")
        h["rail_deviations"].append(name)
    additions = h["rail_deviations"] + (list(_PULSE_DATASETS) if h["pulse_shape"] == "measured" else [])
    if additions and h["format_minor_version"] < 2:
        # a writer that forgot the minor version: the data are the 1.2 additions' all the same, and used
        _warn_once("%s: %s (format 1.2) in a file that declares format 1.%d: used as 1.2 defines them; a "
                   "writer sets format_minor_version = 2", path, ", ".join(additions),
                   h["format_minor_version"])


def _check_measured_pulse(path: Any, f_hz: np.ndarray, spectrum: np.ndarray, sample_rate_hz: float) -> None:
    name_f, name_p = _PULSE_DATASETS
    if f_hz.ndim != 1 or not 2 <= f_hz.size <= MAX_PULSE_SPECTRUM_SAMPLES or spectrum.shape != f_hz.shape:
        raise ArchiveError(path, name_p, f"expected 2 to {MAX_PULSE_SPECTRUM_SAMPLES} samples, one per "
                           f"frequency, got {spectrum.shape} values at {f_hz.shape} frequencies")
    bad = np.flatnonzero(~(np.abs(f_hz) <= sample_rate_hz))
    if bad.size:
        raise ArchiveError(path, name_f, f"{f_hz[bad[0]]} Hz at sample {bad[0]}: must be finite and within "
                           f"+-sample_rate_hz ({sample_rate_hz} Hz) of the carrier")
    if not (np.diff(f_hz) > 0).all():
        raise ArchiveError(path, name_f,
                           f"not strictly increasing (at sample {np.argmax(np.diff(f_hz) <= 0) + 1})")
    bad = np.flatnonzero(~np.isfinite(spectrum))
    if bad.size:
        raise ArchiveError(path, name_p, f"NaN or inf at sample {bad[0]}")
    if not np.any(spectrum != 0):
        raise ArchiveError(path, name_p, "all zero (no pulse)")


def _check_deviation(path: Any, name: str, d: np.ndarray, n_pulses: int) -> None:
    if d.shape != (n_pulses,):
        raise ArchiveError(path, name, f"shape {d.shape}, expected ({n_pulses},) (one per echo row)")
    bad = np.flatnonzero(~np.isfinite(d) | (np.abs(d) > MAX_RAIL_DEVIATION_M))
    if bad.size:
        raise ArchiveError(path, name, f"{d[bad[0]]} m at pulse {bad[0]}: must be finite and within "
                           f"+-{MAX_RAIL_DEVIATION_M} m of the straight rail")


def _read_measured_pulse(f: h5py.File, path: Any, sample_rate_hz: float) -> MeasuredPulse:
    f_hz = np.asarray(_read_values(f, path, _PULSE_DATASETS[0]), dtype=np.float64)
    spectrum = np.asarray(_read_values(f, path, _PULSE_DATASETS[1]), dtype=np.complex128)
    _check_measured_pulse(path, f_hz, spectrum, sample_rate_hz)
    return MeasuredPulse(frequency_hz=f_hz, spectrum=spectrum)


def _read_deviation(f: h5py.File, path: Any, name: str, n_pulses: int) -> np.ndarray:
    d = np.asarray(_read_values(f, path, name), dtype=np.float64)
    _check_deviation(path, name, d, n_pulses)
    return d


_WARNED: dict[str, None] = {}  # the reader's warnings already given in this process (most recent last)
_WARNED_KEPT = 4096


def _warn_once(fmt: str, *args) -> None:
    """A reader's warning about a file, once per process: a file is read more than once in a run (its header,
    its data, the rib registration) and says the same each time (docs/archive-format.md section 5)."""
    text = fmt % args
    if text in _WARNED:
        return
    _WARNED[text] = None
    if len(_WARNED) > _WARNED_KEPT:
        del _WARNED[next(iter(_WARNED))]
    log.warning("%s", text)


def _warn_unknown(f: h5py.File, path: Any) -> None:
    # An unknown name in /radar, /geometry or /pulses may change where targets are (as range_delay_s does for
    # a 1.0 reader): say so instead of ignoring it silently. Elsewhere extras are free-form metadata.
    unknown = [f"{g}@{name}" for g, known in _KNOWN_ATTRIBUTES.items()
               for name in f[g].attrs if name not in known]
    pulses = f.get("pulses")
    if isinstance(pulses, h5py.Group):
        unknown += [f"/pulses/{name}" for name in pulses if name not in _KNOWN_PULSE_DATASETS]
    if unknown:
        _warn_once("%s: ignored (not known to this reader, format 1.%d): %s", path, FORMAT_MINOR_VERSION,
                   ", ".join(sorted(unknown)))


def read_raw_rf(path: str | os.PathLike[str]) -> RawRF | None:
    """The raw real RF kept beside the baseband (format 1.1 ``/raw/rf``), validated; None if there is none."""
    with _open(path) as f:
        n_pulses = int(_dataset(f, "/echo", path).shape[0])
        if "raw" not in f or "rf" not in f["raw"]:
            return None
        ds = f["/raw/rf"]
        if not isinstance(ds, h5py.Dataset) or ds.ndim != 2 or ds.dtype.kind not in "iu":
            raise ArchiveError(path, "/raw/rf", "expected a 2-D integer dataset")
        units = _str_attr(ds, "units", path)
        if units != _RAW_UNITS:
            raise ArchiveError(path, "/raw/rf@units", f"expected {_RAW_UNITS!r}, got {units!r}")
        raw = RawRF(samples=_read_values(f, path, "/raw/rf"),
                    bin_period_s=_float_attr(ds, "bin_period_s", path),
                    scan_start_s=_float_attr(ds, "scan_start_s", path))
    _check_raw_rf(path, raw, n_pulses)
    return raw
