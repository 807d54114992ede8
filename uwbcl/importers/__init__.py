"""Import layer: a radar's own recording format -> one common `RawRecording` -> archives (docs/importing.md).

A module that reads one radar's byte stream is a `Reader`: it turns a file into a `RawRecording` (scan times
on the radar's clock, the samples of every complete scan, the fast-time sampling) and knows nothing of rails,
archives or focusing. Everything after that (real RF to complex baseband, pairing with rail positions,
trimming rest periods, building a `ScanPass`) is shared, in `uwbcl.importers.baseband` and
`uwbcl.importers.passes`. Adding a radar (e.g. a Novelda X4 baseband stream) is one more module with a
`Reader`, listed in `uwbcl.importers.registry`.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Protocol

import numpy as np

from ..atomic import open_regular_file
from ..records import ConfigError


class OptionError(ConfigError):
    """An import value (an `ImportOptions` field, or ``speed_m_s`` / ``time_offset_s``) that no archive could
    hold or that does not fit the recording: a usage error (exit 2). ``key`` is the field's name; the command
    line renders it as the flag or the site file's key it came from."""

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(None, key, reason)

    def __reduce__(self):  # args hold (None, key, reason): rebuild from the two this takes
        return (OptionError, (self.key, self.reason))


class RecordingError(ValueError):
    """A radar recording that cannot be read: names the file, the byte offset of the bad record and why."""

    def __init__(self, path: str | os.PathLike[str], offset: int | None, reason: str) -> None:
        super().__init__(str(path), offset, reason)  # all three in args: the exception pickles
        self.path, self.offset, self.reason = str(path), offset, reason

    def __str__(self) -> str:
        where = f"byte {self.offset}: " if self.offset is not None else ""
        return f"{self.path}: {where}{self.reason}"


@dataclasses.dataclass
class RawRecording:
    """Every complete scan of one recording, as the radar delivered it.

    Attributes
    ----------
    samples : ndarray, (n_scans, n_bins)
        Real RF samples (integer ADC counts, e.g. int32) of a radar that samples the RF directly, or complex
        baseband of one that demodulates itself (then ``carrier_frequency_hz`` is its demodulation frequency).
    scan_time_s : ndarray, (n_scans,) float64
        Time of each scan on the radar's own clock (e.g. seconds since boot); strictly increasing.
    bin_period_s : float
        Fast-time sampling period (s of two-way delay per bin).
    scan_start_s : float
        Two-way delay of bin 0 on the radar's delay axis, before any calibrated antenna/cable delay is
        removed.
    source : str
        The file read, for messages.
    radar : str
        Reader name (e.g. "p440").
    n_dropped : int
        Incomplete scans that were dropped (a truncated last scan, lost messages).
    n_repeated : int
        Scans dropped as repeats of the scan before them (same timestamp, counter and samples).
    n_lost : int
        Scans lost whole: numbers the radar's scan counter skips between the complete scans, less the
        incomplete ones dropped (0 for a radar without a counter).
    scan_id : ndarray, (n_scans,) int64
        The radar's scan counter, where it has one (gaps show lost scans).
    carrier_frequency_hz : float or None
        Demodulation frequency of complex samples; None for real RF.
    metadata : dict
        Reader-specific configuration values (plain Python types), kept for provenance.
    """

    samples: np.ndarray
    scan_time_s: np.ndarray
    bin_period_s: float
    scan_start_s: float
    source: str = ""
    radar: str = ""
    n_dropped: int = 0
    n_repeated: int = 0
    n_lost: int = 0
    scan_id: np.ndarray | None = None
    carrier_frequency_hz: float | None = None
    metadata: dict = dataclasses.field(default_factory=dict)

    @property
    def n_scans(self) -> int:
        return int(self.samples.shape[0])

    @property
    def n_bins(self) -> int:
        return int(self.samples.shape[1])

    @property
    def is_real_rf(self) -> bool:
        return not np.iscomplexobj(self.samples)


def open_recording(path: str | os.PathLike[str]):
    """A recording or positions file opened for reading in binary; RecordingError naming it for anything but a
    regular file (a FIFO would block the import, a device never end: `atomic.open_regular_file`)."""
    try:
        return open_regular_file(path)
    except ValueError as exc:
        raise RecordingError(path, None, str(exc)) from None


class Reader(Protocol):
    """One radar's recording format. ``read`` raises `RecordingError` for a file it cannot trust."""

    name: str  # the subcommand word: `uwbcl import <name> FILE`
    description: str

    def read(self, path: str | os.PathLike[str]) -> RawRecording: ...
