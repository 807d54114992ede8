"""Drained pulse records -> a validated ScanPass -> an archive file (docs/archive-format.md), or a clear
reason why the pass is incomplete. Memory is bounded before anything is allocated: a device claiming absurd
sizes is refused, and a pass that delivers more pulses than it announced is cut off.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from .. import __version__, archive
from ..model import PassGeometry, RadarParameters, ScanPass
from ..records import ReadLimits
from ..utc import format_utc
from . import registers as R


class PassIncomplete(Exception):
    """The pass lost, duplicated or could not trust pulses: it must not be written as whole; re-run it."""


class AbsurdValue(PassIncomplete):
    """A PASS or RADAR value this client will not use (sizes over its limits, ...): the pass fails and is
    re-run (fault ABSURD_VALUE); one absurd reply never stops acquisition."""


class DeviceRefused(Exception):
    """The controller is not a compatible rig (MAGIC, MAP_MAJOR, WINDOW_ADDRESS; fault INCOMPATIBLE), or the
    configuration does not fit it (CONFIGURATION): acquisition stops."""


# What one pass holds while it is finished, per sample: its int16 I/Q as drained (4 B) and its echo as
# archived and kept until written, complex64 (8 B), the type `archive.write_pass` stores by default.
PASS_BYTES_PER_SAMPLE = 4 + 8
ECHO_DTYPE = np.complex64


@dataclasses.dataclass(frozen=True)
class Limits:
    max_samples_per_pulse: int = 8192
    max_pulses_per_pass: int = 100_000
    max_pass_bytes: int = 512 * 2**20  # memory one pass holds (PASS_BYTES_PER_SAMPLE a sample)
    # pulses x samples: no more than every archive reader accepts by default, so no pass is acquired only to
    # be refused by the nightly run (docs/configuration.md [limits])
    max_echo_samples: int = ReadLimits.max_echo_samples


def check_radar(radar: dict, limits: Limits) -> None:
    """Refuse a RADAR block this client cannot use safely: DeviceRefused for a map it does not speak,
    AbsurdValue for values no pass can be run with (re-read and re-tried, never a stop on one reply)."""
    if radar["WINDOW_ADDRESS"] != R.WINDOW_ADDRESS:
        raise DeviceRefused(f"RADAR.WINDOW_ADDRESS = {radar['WINDOW_ADDRESS']}: map 1.x puts it at "
                            f"{R.WINDOW_ADDRESS}")
    for name in ("CARRIER_FREQUENCY", "BANDWIDTH", "SAMPLE_RATE", "PRF", "ANTENNA_APERTURE", "NOMINAL_SPEED"):
        if not radar[name] > 0:
            raise AbsurdValue(f"RADAR.{name} = {radar[name]}: must be > 0")
    if radar["BORESIGHT_Y_SIGN"] not in (-1, 1):
        raise AbsurdValue(f"RADAR.BORESIGHT_Y_SIGN = {radar['BORESIGHT_Y_SIGN']}: must be -1 or +1")
    if not R.WINDOW_HEADER.length + R.record_regs(1) <= radar["WINDOW_REGS"] <= 65536 - R.WINDOW_ADDRESS:
        raise AbsurdValue(f"RADAR.WINDOW_REGS = {radar['WINDOW_REGS']}: outside the window's address space")
    if radar["BUFFER_CAPACITY"] < 1:
        raise AbsurdValue("RADAR.BUFFER_CAPACITY = 0")


def radar_parameters(radar: dict) -> RadarParameters:
    return RadarParameters(carrier_frequency_hz=radar["CARRIER_FREQUENCY"], bandwidth_hz=radar["BANDWIDTH"],
                           sample_rate_hz=radar["SAMPLE_RATE"], pulse_repetition_frequency_hz=radar["PRF"],
                           antenna_aperture_m=radar["ANTENNA_APERTURE"])


class PassAssembler:
    """Collects the records of one pass in order; any gap, repeat, foreign or damaged pulse ends
    it incomplete."""

    def __init__(self, descriptor: dict, radar: dict, limits: Limits):
        m, n = int(descriptor["SAMPLES_PER_PULSE"]), int(descriptor["PULSES_PLANNED"])
        if not 1 <= m <= limits.max_samples_per_pulse:
            raise AbsurdValue(f"PASS.SAMPLES_PER_PULSE = {m}: outside 1..{limits.max_samples_per_pulse}")
        if radar["MAX_SAMPLES_PER_PULSE"] and m > radar["MAX_SAMPLES_PER_PULSE"]:
            raise AbsurdValue(f"PASS.SAMPLES_PER_PULSE = {m}: more than RADAR.MAX_SAMPLES_PER_PULSE = "
                              f"{radar['MAX_SAMPLES_PER_PULSE']}")
        if R.WINDOW_HEADER.length + R.record_regs(m) > radar["WINDOW_REGS"]:
            raise AbsurdValue(f"PASS.SAMPLES_PER_PULSE = {m}: a record does not fit RADAR.WINDOW_REGS")
        if not 2 <= n <= limits.max_pulses_per_pass:
            raise AbsurdValue(f"PASS.PULSES_PLANNED = {n}: outside 2..{limits.max_pulses_per_pass}")
        if n * m > limits.max_echo_samples:
            raise AbsurdValue(f"PASS: {n} pulses x {m} samples, more than the {limits.max_echo_samples} an "
                              "archive may hold (limits.max_echo_samples)")
        if n * m * PASS_BYTES_PER_SAMPLE > limits.max_pass_bytes:
            need_mib = n * m * PASS_BYTES_PER_SAMPLE / 2**20
            raise AbsurdValue(f"PASS: {n} pulses x {m} samples need {need_mib:.0f} MiB, more than the "
                              f"{limits.max_pass_bytes / 2**20:.0f} MiB limit")
        scale = descriptor["AMPLITUDE_SCALE"]
        if not (math.isfinite(scale) and scale > 0):
            raise AbsurdValue(f"PASS.AMPLITUDE_SCALE = {scale}: must be a finite number > 0")
        if descriptor["DIRECTION"] not in (-1, 1):
            raise AbsurdValue(f"PASS.DIRECTION = {descriptor['DIRECTION']}: must be +1 or -1")
        self.descriptor = descriptor
        self.samples_per_pulse = m
        self.planned = n
        self.token = descriptor["TOKEN"]
        self.next_seq = descriptor["FIRST_SEQ"]
        self.time_s = np.empty(n)
        self.position_m = np.empty(n)
        self.iq = np.empty((n, m, 2), dtype=np.int16)
        self.count = 0
        self.last_seen = False

    @property
    def last_seq(self) -> int:
        """The last sequence number stored (modulo 2^32: FIRST_SEQ - 1 before any)."""
        return R.seq_add(self.next_seq, -1)

    def add(self, seq, time_s, position_m, flags, iq) -> None:
        """Append consecutive records (arrays from registers.decode_records); PassIncomplete on any defect."""
        for i in range(len(seq)):
            if seq[i] != self.next_seq:  # compared modulo 2^32 (map 6: 0 follows 2^32 - 1)
                if R.seq_diff(seq[i], self.next_seq) < 0:
                    raise PassIncomplete(f"pulse seq {seq[i]} repeated (expected {self.next_seq})")
                raise PassIncomplete(f"pulses lost: seq {self.next_seq}-{R.seq_add(seq[i], -1)} missing")
            if self.last_seen:
                raise PassIncomplete(f"pulse seq {seq[i]} after the pass's LAST pulse")
            if self.count >= self.planned:
                raise PassIncomplete(f"more pulses than the {self.planned} the device planned")
            if (self.count == 0) != bool(flags[i] & R.RecordFlag.FIRST):
                raise PassIncomplete(f"pulse seq {seq[i]}: FIRST flag "
                                     f"{'missing' if self.count == 0 else 'repeated'}")
            k = self.count
            if k and not time_s[i] > self.time_s[k - 1]:
                raise PassIncomplete(f"pulse seq {seq[i]}: time {time_s[i]:.6f} s not after the previous "
                                     f"pulse")
            self.time_s[k], self.position_m[k], self.iq[k] = time_s[i], position_m[i], iq[i]
            self.count += 1
            self.next_seq = R.seq_add(self.next_seq, 1)
            self.last_seen = bool(flags[i] & R.RecordFlag.LAST)

    def finish(self, descriptor: dict) -> None:
        """The pass as the device reports it at the end must match what arrived, pulse for pulse."""
        d0 = self.descriptor
        for name in ("TOKEN", "CYCLE", "FIRST_SEQ", "PULSES_PLANNED", "RANGE_WINDOW_START",
                     "SAMPLES_PER_PULSE", "AMPLITUDE_SCALE", "HEIGHT", "TABLE_ANGLE", "START_TIME",
                     "DIRECTION"):
            if descriptor[name] != d0[name]:
                raise PassIncomplete(f"PASS.{name} changed during the pass "
                                     f"({d0[name]} -> {descriptor[name]})")
        if descriptor["PASS_STATE"] != R.PassState.COMPLETE:
            raise PassIncomplete(f"pass ended in state {R.enum_name(R.PassState, descriptor['PASS_STATE'])}")
        if descriptor["OVERFLOW_COUNT"]:
            raise PassIncomplete(f"device buffer overflowed: {descriptor['OVERFLOW_COUNT']} pulses dropped")
        if descriptor["PULSES_PRODUCED"] != self.count or not self.last_seen:
            raise PassIncomplete(f"{self.count} pulses received, device produced "
                                 f"{descriptor['PULSES_PRODUCED']}")
        if self.count != self.planned:  # map 1.1, 4.4: a COMPLETE pass produced every pulse it planned
            raise PassIncomplete(f"PULSES_PRODUCED {self.count} != PULSES_PLANNED {self.planned}: incomplete")
        steps = np.diff(self.position_m[:self.count])
        if not (np.all(steps > 0) or np.all(steps < 0)):
            raise PassIncomplete("rail positions not strictly monotonic (encoder fault)")
        if np.sign(steps[0]) != descriptor["DIRECTION"]:  # one of the two is wrong, and nothing says which
            raise PassIncomplete(f"PASS.DIRECTION is {descriptor['DIRECTION']:+d} but the positions run "
                                 f"{'up' if steps[0] > 0 else 'down'} (encoder sign or controller fault)")

    def scan_pass(self, radar: dict, *, rig_id: str, reference_point_m, cycle: int) -> ScanPass:
        """The archived pass; `reference_point_m` is the scene centre relative to the aperture centre x_c (the
        mid-point of the pass's first and last positions), placed at x_c + its x (docs/archive-format.md
        section 3): a rail whose X_r is not centred on 0 keeps the squint the table was set to."""
        d, n = self.descriptor, self.count
        x_c = 0.5 * float(self.position_m[0] + self.position_m[n - 1])
        reference_point_m = (x_c + float(reference_point_m[0]), *reference_point_m[1:])
        # As archived (ECHO_DTYPE): a pass kept in memory while the disk refuses it holds half a complex128's
        # bytes. Scaled in float64 a block of pulses at a time, then rounded once: the values write_pass
        # stores from a complex128 echo, to the bit, without a whole-pass float64 temporary.
        echo = np.empty((n, self.samples_per_pulse), dtype=ECHO_DTYPE)
        scale = float(d["AMPLITUDE_SCALE"])
        step = max(1, 2**20 // self.samples_per_pulse)
        with np.errstate(over="ignore"):  # an echo beyond complex64 is inf: refused by check_scan below
            for k in range(0, n, step):
                echo.real[k:k + step] = self.iq[k:min(k + step, n), :, 0] * scale
                echo.imag[k:k + step] = self.iq[k:min(k + step, n), :, 1] * scale
        try:
            start_time = format_utc(d["START_TIME"])
        except (OverflowError, OSError, ValueError) as exc:
            raise AbsurdValue(f"PASS.START_TIME = {d['START_TIME']}: not a date ({exc})") from None
        geometry = PassGeometry(height_m=d["HEIGHT"], rotation_table_angle_deg=d["TABLE_ANGLE"],
                                reference_point_m=tuple(float(v) for v in reference_point_m),
                                boresight_y_sign=int(radar["BORESIGHT_Y_SIGN"]))
        scan = ScanPass(radar=radar_parameters(radar), geometry=geometry,
                        range_window_start_s=d["RANGE_WINDOW_START"], pulse_time_s=self.time_s[:n].copy(),
                        pulse_position_m=self.position_m[:n].copy(), echo=echo, rig_id=rig_id, cycle=cycle,
                        pass_start_time=start_time)
        try:  # a value no archive may hold (TABLE_ANGLE at 90 deg, an echo past 1e30) fails the pass, re-run
            archive.check_scan(scan, "PASS")
        except archive.ArchiveError as exc:
            raise AbsurdValue(f"the pass cannot be archived: {exc.field}: {exc.reason}") from None
        return scan


def write_scan(out_dir: Path, scan: ScanPass, pass_id: str, unique: str, plain: bool = True) -> Path:
    """Write the pass atomically under its archive path. If that name is taken (a cycle counter that went
    back, a pass acquired twice), or not `plain` (a cycle number scanned again in this session: every pass of
    the second scan named apart), the name gets `_<unique>` (the controller's boot id and pass token), then
    `_2`, `_3`, ...: a whole pass is never dropped for its name, and never overwrites another."""
    path = Path(out_dir) / archive.default_relative_path(scan)
    candidates = [path] if plain else []
    candidates.append(path.with_name(f"{path.stem}_{unique}{path.suffix}"))
    candidates += [path.with_name(f"{path.stem}_{unique}_{k}{path.suffix}") for k in range(2, 1000)]
    for candidate in candidates:
        try:
            return archive.write_pass(candidate, scan, pass_id=pass_id,
                                      created_by=f"uwbcl {__version__} acquire")
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: 1000 passes under this name")
