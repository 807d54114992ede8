"""Time Domain PulsON 440 scan files: the radar's MRM_SCAN_INFO message stream, read and written.

Layout (all integers big-endian; checked against a real recording, docs/importing.md section 2):

* a 32-byte radar configuration: node_id u32, scan_start i32 (ps), scan_stop i32 (ps), scan_res u16 (bins),
  pii u16, four u16 segment sample counts, four u8 segment integrations, ant_mode u8, tx_gain_ind u8,
  code_channel u8, persist_flag u8;
* then fixed-size 1452-byte records, each one MRM_SCAN_INFO message (type 0xF201) padded with zeros: a 52-byte
  header (message_type u16, message_id u16, node_id u32, timestamp u32 ms since radar boot, four reserved u32,
  scan_start i32 ps, scan_stop i32 ps, scan_res i16, scan_type u8, reserved u8, antenna_id u8,
  operational_mode u8, num_samples_message u16 <= 350, num_samples_total u32, message_index u16,
  num_messages_total u16) followed by num_samples_message i32 samples;
* one scan = num_messages_total consecutive messages with message_index 0, 1, ...; sample k of a scan is real
  RF at two-way delay scan_start + k * T_BIN on the radar's delay axis, T_BIN = scan_res / (512 * 1.024 GHz)
  (61.035 ps for scan_res 32), before the radar's internal antenna/cable delay is removed.

The reader holds one record at a time besides its output (one int32 array sized from the file length), drops
an incomplete scan (a truncated last scan, a lost message) or a repeated one with a log line, puts scans
logged out of time order back in the radar's order, and raises `RecordingError` naming the file and byte
offset of a record it cannot trust (wrong message type, absurd sample counts, a scan configuration that
changes mid-file, a radar clock that goes back).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import struct
from pathlib import Path

import numpy as np

from . import RawRecording, RecordingError, open_recording

log = logging.getLogger("uwbcl")

CONFIG = struct.Struct(">IiiHH4H4B4B")  # 32 bytes
HEADER = struct.Struct(">HHII4IiihBBBBHIHH")  # 52 bytes
RECORD_BYTES = 1452
MRM_SCAN_INFO = 0xF201
MAX_SAMPLES_PER_MESSAGE = (RECORD_BYTES - HEADER.size) // 4  # 350
BIN_CLOCK_HZ = 512 * 1.024e9  # scan_res counts periods of this clock (1.907 ps)
MAX_SAMPLES_PER_SCAN = 1 << 16  # far above any P440 scan window; a larger count is a corrupt header
_TIMESTAMP_WRAP_MS = 1 << 32
# Scans whose timestamps run backwards by at most this are a logger's reordering (UDP delivers out of order)
# and are put back in the radar's time order; a longer step back is a restarted radar clock or two
# recordings in one file, which no order repairs.
MAX_REORDER_MS = 1000
COUNTER_WRAP = 1 << 16  # message_id, the scan counter, is a u16
LISTED_DROPS = 10  # incomplete scans named one by one in the log; the rest are counted in one line
_RECORDS_PER_READ = 4096  # ~6 MB per read: bounded memory whatever the file size

_CONFIG_FIELDS = ("node_id", "scan_start_ps", "scan_stop_ps", "scan_res", "pii")
_SEGMENT_FIELDS = ("segment_samples", "segment_integrations")
_CONFIG_TAIL = ("ant_mode", "tx_gain_ind", "code_channel", "persist_flag")


def bin_period_s(scan_res: int) -> float:
    """Fast-time sample period (two-way delay) of a scan resolution in bins: 32 -> 61.035 ps."""
    return scan_res / BIN_CLOCK_HZ


def _parse_config(raw: bytes) -> dict:
    v = CONFIG.unpack(raw)
    cfg = dict(zip(_CONFIG_FIELDS, v[:5]))
    cfg["segment_samples"] = list(v[5:9])
    cfg["segment_integrations"] = list(v[9:13])
    cfg.update(zip(_CONFIG_TAIL, v[13:17]))
    return cfg


@dataclasses.dataclass
class _Scan:
    """The scan being assembled: its identity (from message 0) and how far it got."""

    message_id: int
    timestamp_ms: int
    n_messages: int
    offset: int  # byte offset of message 0, for messages
    next_index: int = 1
    filled: int = 0


class P440Reader:
    """`uwbcl import p440`: a PulsON 440 scan file (real RF int32, 61 ps bins) -> `RawRecording`."""

    name = "p440"
    description = "Time Domain PulsON 440 scan file (MRM_SCAN_INFO message stream, real RF int32)"

    def read(self, path: str | os.PathLike[str]) -> RawRecording:
        """Every complete scan of ``path``; RecordingError (file, byte offset, reason) for a bad record."""
        path = Path(path)
        f = open_recording(path)
        size = os.fstat(f.fileno()).st_size
        with f:
            head = f.read(CONFIG.size)
            if len(head) < CONFIG.size:
                raise RecordingError(
                    path,
                    0,
                    f"truncated configuration header: {len(head)} of {CONFIG.size} "
                    "bytes (not a PulsON 440 scan file?)",
                )
            cfg = _parse_config(head)
            if cfg["scan_res"] == 0 or cfg["scan_stop_ps"] <= cfg["scan_start_ps"]:
                raise RecordingError(
                    path,
                    0,
                    f"configuration header: scan_res {cfg['scan_res']}, scan window "
                    f"{cfg['scan_start_ps']}..{cfg['scan_stop_ps']} ps is not a scan (not a PulsON 440 scan "
                    "file?)",
                )
            n_records, tail = divmod(size - CONFIG.size, RECORD_BYTES)
            state = _StreamState(path, n_records)
            offset = CONFIG.size
            while True:
                block = f.read(RECORD_BYTES * _RECORDS_PER_READ)
                whole = len(block) // RECORD_BYTES
                for i in range(whole):
                    state.message(block, i * RECORD_BYTES, offset + i * RECORD_BYTES)
                offset += whole * RECORD_BYTES
                if len(block) < RECORD_BYTES * _RECORDS_PER_READ:
                    break
        if tail:
            log.warning(
                "%s: %d trailing bytes at byte %d are a truncated record; dropped", path, tail, offset
            )
        return state.finish(cfg)


READER = P440Reader()


class _StreamState:
    """Assembles scans from messages; owns the output array (allocated once, from the first message)."""

    def __init__(self, path: Path, n_records: int) -> None:
        self.path, self.n_records = path, n_records
        self.rf: np.ndarray | None = None
        self.times_ms: list[int] = []
        self.ids: list[int] = []
        self.offsets: list[int] = []  # byte offset of each complete scan's message 0, for messages
        self.shape: tuple | None = None  # (scan_start, scan_stop, scan_res, n_total, n_messages) of the file
        self.source: tuple[int, int] | None = None  # (node_id, antenna_id) of the file's scans
        self.orphan: int | None = None  # the scan counter of messages skipped for want of their message 0
        self.first_drop = ""  # why the first incomplete scan was dropped (for a file with none complete)
        self.scan: _Scan | None = None
        self.n_complete = 0
        self.n_dropped = 0
        # of them, those between two complete scans (their counter numbers are in a gap), and those since the
        # last complete scan
        self.n_dropped_between = self.n_pending_drops = 0
        self.n_repeated = 0

    def fail(self, offset: int, reason: str) -> None:
        raise RecordingError(self.path, offset, reason)

    def message(self, block: bytes, at: int, offset: int) -> None:
        (
            mtype,
            mid,
            node,
            stamp,
            _r0,
            _r1,
            _r2,
            _r3,
            start,
            stop,
            res,
            _stype,
            _r,
            antenna,
            _op,
            n_msg,
            n_total,
            index,
            n_messages,
        ) = HEADER.unpack_from(block, at)
        if mtype != MRM_SCAN_INFO:
            self.fail(offset, f"message type 0x{mtype:04X} is not MRM_SCAN_INFO (0x{MRM_SCAN_INFO:04X})")
        if not 1 <= n_total <= MAX_SAMPLES_PER_SCAN:
            self.fail(offset, f"num_samples_total {n_total} outside 1..{MAX_SAMPLES_PER_SCAN}")
        if not 1 <= n_msg <= MAX_SAMPLES_PER_MESSAGE:
            self.fail(offset, f"num_samples_message {n_msg} outside 1..{MAX_SAMPLES_PER_MESSAGE}")
        if n_messages != math.ceil(n_total / MAX_SAMPLES_PER_MESSAGE) or index >= n_messages:
            self.fail(
                offset,
                f"message {index} of {n_messages} cannot carry {n_total} samples "
                f"({MAX_SAMPLES_PER_MESSAGE} per message)",
            )
        if res <= 0 or stop <= start:
            self.fail(offset, f"scan_res {res}, scan window {start}..{stop} ps is not a scan")
        self.same_scans(offset, (start, stop, res, n_total, n_messages), (node, antenna))
        scan = self.scan
        if index == 0:
            if scan is not None:
                self.drop(
                    f"scan {scan.message_id} at byte {scan.offset} stops after message "
                    f"{scan.next_index - 1} of {scan.n_messages}"
                )
            scan = self.scan = _Scan(mid, stamp, n_messages, offset)
            self.orphan = None
        elif scan is None or index != scan.next_index or mid != scan.message_id:
            if scan is not None:
                self.drop(
                    f"scan {scan.message_id} at byte {scan.offset} is interrupted at byte {offset} by "
                    f"message {index} of scan {mid}"
                )
                self.orphan = scan.message_id  # its own later messages (one lost between) drop no other scan
            if mid != self.orphan:  # a scan whose message 0 is lost (or came first elsewhere): dropped once
                self.orphan = mid
                self.drop(f"message {index} of scan {mid} at byte {offset} has no message 0")
            self.scan = None
            return
        else:
            scan.next_index += 1
        end = scan.filled + n_msg
        if end > n_total or (index == n_messages - 1 and end != n_total):
            self.fail(offset, f"messages of scan {mid} carry {end} samples, num_samples_total is {n_total}")
        row = self.rf[self.n_complete]
        row[scan.filled : end] = np.frombuffer(block, dtype=">i4", count=n_msg, offset=at + HEADER.size)
        scan.filled = end
        if index == n_messages - 1:
            if self.n_complete:
                self.n_dropped_between += self.n_pending_drops
            self.n_pending_drops = 0
            self.times_ms.append(scan.timestamp_ms)
            self.ids.append(scan.message_id)
            self.offsets.append(scan.offset)
            self.n_complete += 1
            self.scan = None

    def same_scans(self, offset: int, shape: tuple, source: tuple[int, int]) -> None:
        """The first message sets the file's scan configuration and radar (node_id, antenna_id); a message
        with another is a RecordingError at its offset."""
        if self.shape is None:
            self.shape, self.source = shape, source
            # At most one scan per n_messages records: the output never grows.
            self.rf = np.empty((self.n_records // shape[4] + 1, shape[3]), dtype=np.int32)
        elif shape != self.shape:
            self.fail(
                offset,
                f"scan configuration changed mid-file: (scan_start, scan_stop, scan_res, "
                f"num_samples_total, num_messages_total) {shape}, was {self.shape}",
            )
        elif source != self.source:
            # Two radars on one logger, or an alternating-antenna mode (two phase centres, two delays): their
            # scans interleaved are not one aperture.
            self.fail(offset, f"node_id {source[0]}, antenna_id {source[1]}: the file's scans so far came "
                              f"from node_id {self.source[0]}, antenna_id {self.source[1]}; scans of two "
                              "radars or antennas in one file are not one pass (split the file by node and "
                              "antenna)")

    def time_order(self, ms: np.ndarray, rf: np.ndarray) -> np.ndarray | None:
        """The scans to keep, in the radar's time order (None: all of them, as read).

        A scan repeated (same timestamp, counter and samples) is dropped; scans that run back in time by up to
        MAX_REORDER_MS are put back in order; both with a warning. A longer step back, or two different scans
        with one timestamp, is a RecordingError at the later scan's byte offset."""
        steps = np.diff(ms)
        if np.all(steps > 0):
            return None
        keep = np.ones(ms.size, dtype=bool)
        latest = 0  # the scan with the latest time so far
        for i in range(1, ms.size):
            back = int(ms[latest] - ms[i])
            if back < 0:
                latest = i
            elif back == 0 and self.ids[i] == self.ids[latest] and np.array_equal(rf[i], rf[latest]):
                keep[i] = False
                log.warning("%s: scan %d at byte %d repeats the scan at byte %d; dropped", self.path,
                            self.ids[i], self.offsets[i], self.offsets[latest])
            elif back == 0:
                self.fail(self.offsets[i], f"scan {self.ids[i]} has the timestamp of a different scan "
                                           f"(scan {self.ids[latest]} at byte {self.offsets[latest]})")
            elif back > MAX_REORDER_MS:
                self.fail(self.offsets[i], f"the radar clock goes back {back / 1e3:.3f} s from the scan at "
                                           f"byte {self.offsets[latest]} (a restarted radar, or two "
                                           "recordings in one file)")
        kept = np.flatnonzero(keep)
        order = kept[np.argsort(ms[kept], kind="stable")]
        if np.any(np.diff(ms[order]) <= 0):  # a repeat of an earlier, not the latest, scan
            i = int(order[np.flatnonzero(np.diff(ms[order]) <= 0)[0] + 1])
            self.fail(self.offsets[i], f"scan {self.ids[i]} has the timestamp of another scan")
        moved = int(np.sum(order != kept))
        if moved:
            first = int(kept[np.flatnonzero(order != kept)[0]])
            log.warning("%s: %d scans were out of time order (the first at byte %d); put back in the "
                        "radar's order", self.path, moved, self.offsets[first])
        self.n_repeated = int(np.sum(~keep))
        return order

    def drop(self, why: str) -> None:
        self.n_dropped += 1
        self.n_pending_drops += 1
        self.first_drop = self.first_drop or why
        if self.n_dropped <= LISTED_DROPS:
            log.warning("%s: dropped an incomplete scan: %s", self.path, why)

    def finish(self, cfg: dict) -> RawRecording:
        if self.scan is not None:
            s = self.scan
            self.n_dropped += 1
            log.warning(
                "%s: dropped the incomplete last scan (scan %d at byte %d: %d of %d messages)",
                self.path,
                s.message_id,
                s.offset,
                s.next_index,
                s.n_messages,
            )
        if self.n_dropped > LISTED_DROPS:
            log.warning("%s: %d more incomplete scans dropped (not listed)", self.path,
                        self.n_dropped - LISTED_DROPS)
        if self.n_complete == 0:
            why = (f"; {self.n_dropped} incomplete scan(s) dropped, the first because {self.first_drop} (a "
                   "scan is num_messages_total consecutive messages, message_index 0, 1, ..., sharing one "
                   "message_id, the scan counter)" if self.n_dropped else "")
            raise RecordingError(self.path, None, f"no complete scan in the file{why}")
        start, stop, res, n_total, _ = self.shape
        self.check_header(cfg)
        ms = unwrap_timestamps_ms(self.times_ms)
        rf = self.rf[: self.n_complete]
        self.rf = None
        order = self.time_order(ms, rf)
        if order is not None:
            rf, ms = rf[order], ms[order]
            self.ids = [self.ids[i] for i in order]
        metadata = dict(cfg, scan_stop_ps=stop, num_samples_total=n_total)
        steps = np.diff(np.asarray(self.ids, dtype=np.int64)) % COUNTER_WRAP  # u16 message_id, wrapping
        skipped = int(np.sum(steps[(steps > 1) & (steps < COUNTER_WRAP // 2)] - 1))
        astray = int(np.sum((steps == 0) | (steps >= COUNTER_WRAP // 2)))  # a counter stuck or going back
        if astray:
            log.warning("%s: the radar's scan counter (message_id) stays or goes back at %d of %d scans: the "
                        "scans lost whole cannot all be counted", self.path, astray, steps.size)
        return RawRecording(
            samples=rf,
            scan_time_s=ms * 1e-3,
            bin_period_s=bin_period_s(res),
            scan_start_s=start * 1e-12,
            source=str(self.path),
            radar="p440",
            n_dropped=self.n_dropped,
            n_repeated=self.n_repeated,
            # the incomplete scans between complete ones skip counter numbers too
            n_lost=max(0, skipped - self.n_dropped_between),
            scan_id=np.asarray(self.ids, dtype=np.int64),
            metadata=metadata,
        )

    def check_header(self, cfg: dict) -> None:
        """Warnings for a file that contradicts itself where the messages win: a configuration header whose
        scan window differs from the messages' (another firmware, or a header of another recording), and a
        scan window whose length is not num_samples_total bins (scan_start and scan_res place the samples)."""
        start, stop, res, n_total, _ = self.shape
        header = (cfg["scan_start_ps"], cfg["scan_stop_ps"], cfg["scan_res"])
        if header != (start, stop, res):
            log.warning("%s: the configuration header's scan window (scan_start, scan_stop, scan_res) %s "
                        "differs from the messages' %s; the messages' is used", self.path, header,
                        (start, stop, res))
        bins = (stop - start) * 1e-12 / bin_period_s(res)
        if abs(bins - n_total) > 1.0:
            log.warning("%s: the scan window %d..%d ps holds %.1f bins of %.3f ps, the messages carry %d "
                        "samples; the samples are placed from scan_start by scan_res", self.path, start,
                        stop, bins, 1e12 * bin_period_s(res), n_total)


def unwrap_timestamps_ms(stamps) -> np.ndarray:
    """u32 ms-since-boot timestamps (n,) -> int64 ms, unwrapped at the 49.7-day rollover: each step is taken
    modulo 2**32 as a signed 32-bit number (serial-number arithmetic, RFC 1982), so a rollover is a short
    step forward and two swapped scans a short step back, not 49.7 days."""
    ms = np.asarray(stamps, dtype=np.int64)
    if ms.size == 0:
        return ms
    half = _TIMESTAMP_WRAP_MS // 2
    steps = (np.diff(ms) + half) % _TIMESTAMP_WRAP_MS - half
    return ms[0] + np.concatenate([[0], np.cumsum(steps)])


# ----------------------------------------------------------------------------------------------- writing


def write_p440_stream(
    path: str | os.PathLike[str],
    rf: np.ndarray,
    timestamp_ms,
    *,
    scan_start_ps: int,
    scan_res: int = 32,
    node_id: int = 100,
    pii: int = 11,
    partial_last_scan_messages: int = 0,
) -> Path:
    """Write scans in the PulsON 440 scan-file layout (the same bytes `P440Reader` reads).

    Parameters
    ----------
    rf : ndarray, (n_scans, n_bins) integer
        Real RF samples; must fit int32.
    timestamp_ms : array_like, (n_scans,) int
        Radar clock of each scan, ms since boot (written modulo 2**32).
    scan_start_ps : int
        Two-way delay of bin 0 on the radar's axis, ps; scan_stop = scan_start + n_bins * T_BIN.
    partial_last_scan_messages : int
        Append that many messages (fewer than a scan's) of one more scan, as a recording cut off mid-scan.
    """
    rf = np.asarray(rf)
    if rf.ndim != 2 or rf.dtype.kind not in "iu":
        raise ValueError(f"rf must be a 2-D integer array, got {rf.dtype} {rf.shape}")
    if rf.size and (rf.min() < np.iinfo(np.int32).min or rf.max() > np.iinfo(np.int32).max):
        raise ValueError("rf does not fit int32")
    n_scans, n_bins = rf.shape
    stamps = np.asarray(timestamp_ms, dtype=np.int64) % _TIMESTAMP_WRAP_MS
    n_messages = math.ceil(n_bins / MAX_SAMPLES_PER_MESSAGE)
    if not 0 <= partial_last_scan_messages < n_messages:
        raise ValueError(f"partial_last_scan_messages must be in 0..{n_messages - 1}")
    scan_stop_ps = scan_start_ps + round(n_bins * bin_period_s(scan_res) * 1e12)
    config = CONFIG.pack(
        node_id, scan_start_ps, scan_stop_ps, scan_res, pii, 0, 0, 0, 0, 0, 0, 0, 0, 2, 63, 6, 0
    )
    path = Path(path)
    with path.open("wb") as f:
        f.write(config)
        rows = [(k, rf[k], int(stamps[k]), n_messages) for k in range(n_scans)]
        if partial_last_scan_messages:
            last = n_scans - 1 if n_scans else 0
            rows.append((n_scans, rf[last], int(stamps[last]) + 20, partial_last_scan_messages))
        for scan_id, row, stamp, n_write in rows:
            samples = row.astype(">i4")
            for index in range(n_write):
                chunk = samples[index * MAX_SAMPLES_PER_MESSAGE : (index + 1) * MAX_SAMPLES_PER_MESSAGE]
                header = HEADER.pack(
                    MRM_SCAN_INFO,
                    scan_id & 0xFFFF,
                    node_id,
                    stamp,
                    0,
                    0,
                    0,
                    0,
                    scan_start_ps,
                    scan_stop_ps,
                    scan_res,
                    1,
                    3,
                    2,
                    1,
                    chunk.size,
                    n_bins,
                    index,
                    n_messages,
                )
                record = header + chunk.tobytes()
                f.write(record + bytes(RECORD_BYTES - len(record)))
    return path
