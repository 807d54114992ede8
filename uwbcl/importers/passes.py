"""A `RawRecording` + rail positions + site values -> one archive pass (`ScanPass`), radar-independent.

* Clock alignment: scan times are on the radar's clock (P440: ms since boot), positions on the logger's. A
  position log time is ``scan_time_s + time_offset_s``; without an offset the two clocks are aligned on the
  first motion (the first position that moved `MOTION_THRESHOLD_M` from the first one, and the first scan
  whose echo departs from the rest echoes, `radar_first_motion_s`).
* Positions are interpolated linearly to the scan times; scans outside the log are dropped (no
  extrapolation).
* Rest periods: the pass is the longest run of scans whose rail position moves strictly one way by more than
  ``min_step_m`` per scan; standing still and turning back at the rail ends are cut off.
* Without positions, a straight constant-speed track over every scan (``speed_m_s``) centred on x = 0:
  for commissioning and tests only.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime as dt
import io
import logging
import math
import os
from pathlib import Path

import numpy as np

from ..archive import MAX_CYCLE, MAX_RAIL_DEVIATION_M
from ..config import MAX_LENGTH_M, MAX_RANGE_DELAY_S, beyond_max_length
from ..geometry import LONG_RAIL_M
from ..model import MIN_WINDOW_RANGE_M, SPEED_OF_LIGHT_M_S, PassGeometry, RadarParameters, RawRF, ScanPass
from ..records import ConfigError
from ..utc import parse_utc
from . import OptionError, RawRecording, RecordingError, baseband, open_recording

log = logging.getLogger("uwbcl")

DEFAULT_REFERENCE_RANGE_M = 3.0  # the scene centre's range when the recording's window holds it
MOTION_THRESHOLD_M = 0.002  # a position this far from the first one has moved (about where the echo shows it)
MAX_SPEED_M_S = 10.0  # --speed-m-s beyond this is no rail carriage (1e308 overflowed the track to NaN)
BANDWIDTH_WARN_FRACTION = 0.2  # a given bandwidth this far off the measured one is warned about
# a given carrier this far (of the measured -10 dB width) from the measured centre is warned about: 0.2 of the
# width (3.7 GHz for a 4.01 GHz centre) split one plate into two 14 mm apart on an independent tester's pass
CARRIER_WARN_FRACTION = 0.1
_REST_SCANS = 8  # scans at the start assumed at rest for the radar's motion detector
_MOTION_SCANS = 2000  # scans searched for the first (last) motion from the start (end)
# the offsets the first and the last motion give (both ends at rest) are warned about beyond this: the echo
# shows a gentle start or stop later than the log's 2 mm (54 ms apart on the synthetic set, whose slow turn
# back at the end stop lags most; up to 0.25 s with a 0.3 m/s^2 ramp or a noisy echo), and a recording started
# after the rail is off by the time the rail had moved
ALIGN_MISMATCH_S = 0.1
END_REST_SPREAD = 4.0  # final scans spread more than this x the first scans': the recording ended moving


@dataclasses.dataclass(frozen=True)
class ImportOptions:
    """The archive values a radar recording does not hold (flags, or the [import] table of a site TOML)."""

    height_m: float | None = None  # rail (antenna phase centre) height; default: median z_m of the positions
    rotation_table_angle_deg: float = 0.0
    boresight_y_sign: int = -1
    reference_point_m: tuple[float, float, float] | None = (
        None  # default: on boresight, reference_range_m away
    )
    # default: DEFAULT_REFERENCE_RANGE_M, or the middle of the recording's delay window when that lies outside
    reference_range_m: float | None = None
    antenna_aperture_m: float = 0.14
    pulse_repetition_frequency_hz: float | None = None  # default: 1 / median scan interval
    range_delay_s: float = 0.0  # calibrated two-way antenna/cable delay (archive 1.1 /radar@range_delay_s)
    rig_id: str = "rig-1"
    cycle: int = 0
    pass_start_time: str | None = None  # ISO 8601 UTC; default: file modification time minus the duration
    carrier_frequency_hz: float | None = None  # default: the measured -10 dB band centre
    # default: the measured -10 dB width; fixed by a site whose heights are imported from separate recordings,
    # whose measured widths differ by about 1 % (a cycle's passes must agree within 1 %)
    bandwidth_hz: float | None = None
    oversampling: float = baseband.DEFAULT_OVERSAMPLING
    decimation: int | None = None  # default: baseband.choose_decimation
    min_step_m: float = 1e-4  # smaller steps per scan count as standing still
    keep_raw_rf: bool = True  # /raw/rf beside the baseband, for provenance
    # "gaussian": the archive models the pulse as the Gaussian of the measured -10 dB band; "measured": the
    # pulse is measured from the reference echo between pulse_window_start_m and pulse_window_stop_m (one-way
    # range on the archive's axis), the direct coupling by default (archive 1.2, docs/importing.md)
    pulse: str = "gaussian"
    pulse_window_start_m: float = 1.5
    pulse_window_stop_m: float = 2.6


OPTION_TYPES = {f.name: f.type for f in dataclasses.fields(ImportOptions)}


@dataclasses.dataclass(frozen=True)
class Positions:
    """A rail position log: time on the logger's clock, X_r (and optionally Y_r, Z_r) of the antenna."""

    time_s: np.ndarray  # (K,) strictly increasing
    x_m: np.ndarray  # (K,)
    y_m: np.ndarray | None = None
    z_m: np.ndarray | None = None
    source: str = ""  # the file read, for messages
    line: np.ndarray | None = None  # (K,) its line number of each position, for messages


def read_positions_csv(path: str | os.PathLike[str]) -> Positions:
    """A CSV with a header row naming ``time_s, x_m`` and optionally ``y_m, z_m`` (any order, extra columns
    ignored). RecordingError naming the file and line for a missing column, a non-number or a time that does
    not increase."""
    path = Path(path)
    raw = open_recording(path)
    # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte-order mark, which is not part of the header
    with io.TextIOWrapper(raw, encoding="utf-8-sig", newline="") as f:
        try:
            rows = list(csv.reader(f))
        except (UnicodeDecodeError, csv.Error) as exc:
            raise RecordingError(path, None, f"not a UTF-8 CSV file: {exc}") from None
    if not rows:
        raise RecordingError(path, None, "empty positions file (expected a header: time_s,x_m[,y_m,z_m])")
    header = [h.strip() for h in rows[0]]
    for name in ("time_s", "x_m"):
        if name not in header:
            hint = ("; the columns must be separated by commas" if len(header) == 1 and
                    any(sep in header[0] for sep in ";\t") else "")
            raise RecordingError(path, None,
                                 f"line 1: no column {name!r} (header: {', '.join(header)}){hint}")
    cols = {name: header.index(name) for name in ("time_s", "x_m", "y_m", "z_m") if name in header}
    values = {name: [] for name in cols}
    lines = []
    for line, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        lines.append(line)
        for name, i in cols.items():
            try:
                v = float(row[i])
            except (IndexError, ValueError):
                raise RecordingError(
                    path, None, f"line {line}: {name}: not a number: {row[i] if i < len(row) else ''!r}"
                ) from None
            if not math.isfinite(v):
                raise RecordingError(path, None, f"line {line}: {name}: not finite")
            if name != "time_s" and beyond_max_length(v):
                raise RecordingError(path, None, f"line {line}: {name}: {v!r} m is beyond "
                                     f"+-{MAX_LENGTH_M:g} m (is it in metres?)")
            values[name].append(v)
    t = np.asarray(values["time_s"])
    if t.size < 2:
        raise RecordingError(path, None, "fewer than 2 positions")
    lines = np.asarray(lines)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise RecordingError(path, None, f"line {lines[bad[0] + 1]}: time_s does not increase")
    arr = {k: np.asarray(v) for k, v in values.items()}
    return Positions(time_s=t, x_m=arr["x_m"], y_m=arr.get("y_m"), z_m=arr.get("z_m"), source=str(path),
                     line=lines)


def radar_first_motion_s(recording: RawRecording, factor: float = 5.0) -> float | None:
    """Time (radar clock) of the first scan whose echo departs from the rest echo, or None.

    The first `_REST_SCANS` scans are taken as the rest echo and its scan-to-scan spread as the noise level;
    the first scan from which three in a row differ from the rest echo by more than ``factor`` x that level
    is the first motion (the phases of the scene's echoes change within a fraction of a wavelength).
    """
    k, _ = _echo_departure(recording.samples[: min(recording.n_scans, _MOTION_SCANS)], factor)
    return None if k is None else float(recording.scan_time_s[k])


def radar_last_motion_s(recording: RawRecording, last_scan: int, factor: float = 5.0) -> float | None:
    """Time (radar clock) of the last scan up to `last_scan` whose echo departs from the final rest echo (the
    `_REST_SCANS` scans before it: `radar_first_motion_s` run backwards), or None when those scans are not at
    rest (their spread over END_REST_SPREAD x the first scans': the recording stopped while moving)."""
    n = min(last_scan + 1, _MOTION_SCANS)
    k, end_noise = _echo_departure(recording.samples[last_scan + 1 - n:last_scan + 1][::-1], factor)
    _, start_noise = _echo_departure(recording.samples[:_REST_SCANS], factor)
    if k is None or end_noise > END_REST_SPREAD * max(start_noise, 1e-30):
        return None
    return float(recording.scan_time_s[last_scan - k])


def _echo_departure(samples: np.ndarray, factor: float) -> tuple[int | None, float]:
    """(index of the first scan from which three in a row differ from the mean of the first `_REST_SCANS` by
    more than `factor` x their own spread, or None; that spread)."""
    x = samples.astype(np.float64)
    rest = x[:_REST_SCANS]
    ref = rest.mean(axis=0)
    noise = float(np.mean((rest - ref) ** 2, axis=1).max()) if rest.size else 0.0
    if x.shape[0] <= _REST_SCANS + 3:
        return None, noise
    e = np.mean((x - ref) ** 2, axis=1)
    moving = e > factor * max(noise, 1e-30)
    run = moving[:-2] & moving[1:-1] & moving[2:]
    hits = np.flatnonzero(run[_REST_SCANS:]) + _REST_SCANS
    return (int(hits[0]) if hits.size else None), noise


def positions_first_motion_s(positions: Positions) -> float | None:
    """Logger time at which the positions are first MOTION_THRESHOLD_M from their first value, or None."""
    return _crossing_s(positions.time_s, positions.x_m)


def positions_last_motion_s(positions: Positions, until_s: float, min_rest_s: float) -> float | None:
    """Logger time after which the positions up to `until_s` stay within MOTION_THRESHOLD_M of their last
    value there (backwards `positions_first_motion_s`), or None when they do so for less than min_rest_s (the
    log stopped while moving)."""
    upto = positions.time_s <= until_s
    t = _crossing_s(-positions.time_s[upto][::-1], positions.x_m[upto][::-1])
    if t is None or positions.time_s[upto][-1] + t < min_rest_s:
        return None
    return -t


def _crossing_s(time_s: np.ndarray, x_m: np.ndarray) -> float | None:
    moved = np.flatnonzero(np.abs(x_m - x_m[0]) > MOTION_THRESHOLD_M) if x_m.size else np.zeros(0, int)
    if not moved.size:
        return None
    i = moved[0]
    # Interpolate the crossing: the log may be sparse.
    x0, x1 = abs(x_m[i - 1] - x_m[0]), abs(x_m[i] - x_m[0])
    t0, t1 = time_s[i - 1], time_s[i]
    return float(t0 + (MOTION_THRESHOLD_M - x0) / (x1 - x0) * (t1 - t0)) if i > 0 else float(t0)


def _check_last_motion(recording: RawRecording, positions: Positions, offset_s: float) -> None:
    """The first-motion alignment checked on the last motion of the scans the log covers, where both come to
    rest: a warning when the two offsets differ by more than ALIGN_MISMATCH_S (a recording started after
    the rail, a rest too short to learn the echo from, a gentle ramp or a noisy echo that show the motion
    late, a log of another pass), or when an end is not at rest and nothing can be checked."""
    t = recording.scan_time_s + offset_s
    covered = np.flatnonzero(t <= positions.time_s[-1])
    period_s = float(np.median(np.diff(recording.scan_time_s))) if recording.n_scans > 1 else 0.0
    t_radar = radar_last_motion_s(recording, int(covered[-1])) if covered.size else None
    t_pos = positions_last_motion_s(positions, float(t[covered[-1]]) if covered.size else -math.inf,
                                    _REST_SCANS * period_s)
    if t_radar is None or t_pos is None:
        log.warning("%s: the clocks aligned on the first motion could not be checked on the last one (the "
                    "recording or the log does not end at rest within the time both cover); an error in the "
                    "offset shifts the pass along the rail", recording.source)
        return
    end_s = t_pos - t_radar
    if abs(end_s - offset_s) > ALIGN_MISMATCH_S:
        span_m = float(np.ptp(positions.x_m))
        units = (f" (the log spans {span_m:.1f} m: are its positions in metres?)" if span_m > LONG_RAIL_M
                 else "")
        log.warning("%s: the clocks aligned on the first motion (positions time = scan time %+.3f s, used) "
                    "and on the last one (%+.3f s) are %.0f ms apart: a recording started after the rail, a "
                    "rest shorter than %d scans, a gentle ramp or a noisy echo (the echo shows the motion "
                    "late), or a log of another pass%s; the pass may be shifted along the rail by that time "
                    "x the speed: give --time-offset-s if it is known", recording.source, offset_s, end_s,
                    abs(end_s - offset_s) * 1e3, _REST_SCANS, units)


LATE_LOG_SPEED_FRACTION = 0.5  # a log whose first interval moves this fast (of its median speed) started late


def _check_log_starts_at_rest(recording: RawRecording, positions: Positions) -> None:
    """RecordingError when the positions log is already moving at its first interval (at least
    LATE_LOG_SPEED_FRACTION of its median moving speed): its first motion is then the logger's start, not
    the rail's, and aligning the clocks on it would shift every scan by the time the rail had been moving."""
    v = np.abs(np.diff(positions.x_m)) / np.maximum(np.diff(positions.time_s), 1e-12)
    moving = v[np.abs(np.diff(positions.x_m)) > 0]
    if v.size and moving.size and v[0] >= LATE_LOG_SPEED_FRACTION * float(np.median(moving)):
        raise RecordingError(
            recording.source, None,
            f"cannot align the clocks on the first motion: the positions of {positions.source or 'the log'} "
            f"already move at {v[0]:.3f} m/s over their first interval (the pass's median "
            f"{float(np.median(moving)):.3f} m/s), so the log started after the rail did; give "
            "--time-offset-s, or a log that starts at rest")


def moving_runs(x_m: np.ndarray, min_step_m: float) -> list[slice]:
    """Every run of samples whose position moves strictly one way by > min_step_m each step, in order."""
    dx = np.diff(x_m)
    sign = np.where(dx > min_step_m, 1, np.where(dx < -min_step_m, -1, 0))
    runs, start = [], 0
    for k in range(1, len(sign) + 1):
        if k == len(sign) or sign[k] != sign[start] or sign[k] == 0:
            if sign[start] != 0:
                runs.append(slice(start, k + 1))
            start = k
    return runs


def longest_run(runs: list[slice]) -> slice:
    """The longest of `moving_runs` (the first of equals); an empty slice for none."""
    return max(runs, key=lambda r: r.stop - r.start, default=slice(0, 0))


def moving_segment(x_m: np.ndarray, min_step_m: float) -> slice:
    """The longest run of samples whose position moves strictly one way by > min_step_m each step."""
    return longest_run(moving_runs(x_m, min_step_m))


OTHER_PASS_FRACTION = 0.5  # a second run over this fraction of the kept pass's length is another pass


def _warn_other_passes(source: str, x_m: np.ndarray, t_s: np.ndarray, runs: list[slice], kept: slice) -> None:
    """A warning naming each run of the recording (t_s on the positions' clock), besides the one kept, that
    travels at least OTHER_PASS_FRACTION of the kept pass's length: a second pass (another height, the way
    back) that the import leaves out, and how to import it."""
    length = abs(float(x_m[kept.stop - 1] - x_m[kept.start]))
    for r in runs:
        span = float(x_m[r.stop - 1] - x_m[r.start])
        if r != kept and abs(span) >= OTHER_PASS_FRACTION * length:
            log.warning("%s: the recording holds another pass, not imported: %d scans at %.3f-%.3f s on the "
                        "positions' clock, x %+.3f to %+.3f m (the pass kept travels %.3f m); one archive is "
                        "one pass: to import that one, give a positions log that covers only its time",
                        source, r.stop - r.start, t_s[r.start], t_s[r.stop - 1], x_m[r.start],
                        x_m[r.stop - 1], length)


@dataclasses.dataclass
class Track:
    """The rail positions of the scans kept for the pass."""

    scans: np.ndarray  # (N,) indices into the recording
    x_m: np.ndarray  # (N,)
    time_offset_s: float | None  # logger clock - radar clock, when positions were used
    n_outside_log: int = 0
    n_rest: int = 0
    y_m: np.ndarray | None = None
    z_m: np.ndarray | None = None
    positions: Positions | None = None  # the log the track came from, for messages


def track_from_positions(
    recording: RawRecording, positions: Positions, time_offset_s: float | None, min_step_m: float
) -> Track:
    """Scans paired with interpolated positions, rest periods cut (module docstring)."""
    if time_offset_s is None:
        t_pos, t_radar = positions_first_motion_s(positions), radar_first_motion_s(recording)
        if t_pos is None or t_radar is None:
            raise RecordingError(
                recording.source,
                None,
                "cannot align the clocks on the first motion ("
                + ("the positions never move" if t_pos is None else "no motion seen in the echo")
                + "); give --time-offset-s",
            )
        _check_log_starts_at_rest(recording, positions)
        time_offset_s = t_pos - t_radar
        _check_last_motion(recording, positions, time_offset_s)
        log.info("clocks aligned on the first motion: positions time = scan time %+.3f s", time_offset_s)
    t = recording.scan_time_s + time_offset_s
    inside = np.flatnonzero((t >= positions.time_s[0]) & (t <= positions.time_s[-1]))
    if inside.size < 2:
        t0, t1 = recording.scan_time_s[0], recording.scan_time_s[-1]
        raise RecordingError(
            recording.source,
            None,
            f"the positions of {positions.source or 'the log'} ({positions.time_s[0]:.3f}.."
            f"{positions.time_s[-1]:.3f} s) cover {inside.size} scans at a time offset of "
            f"{time_offset_s:.3f} s; the scans run from {t0:.3f} to {t1:.3f} s on the radar's clock "
            f"(positions time = scan time + offset: {positions.time_s[0] - t0:+.3f} s would put the first "
            "scan at the first position); check --time-offset-s",
        )

    def at(v):
        return None if v is None else np.interp(t[inside], positions.time_s, v)

    x = at(positions.x_m)
    runs = moving_runs(x, min_step_m)
    seg = longest_run(runs)
    if seg.stop - seg.start >= 2:
        _warn_other_passes(recording.source, x, t[inside], runs, seg)
    if seg.stop - seg.start < 2:
        raise RecordingError(
            recording.source,
            None,
            f"no moving segment: the positions never move by more than {min_step_m} m per scan",
        )
    y, z = at(positions.y_m), at(positions.z_m)
    return Track(
        scans=inside[seg],
        x_m=x[seg],
        time_offset_s=time_offset_s,
        n_outside_log=recording.n_scans - inside.size,
        n_rest=inside.size - (seg.stop - seg.start),
        y_m=None if y is None else y[seg],
        z_m=None if z is None else z[seg],
        positions=positions,
    )


def check_speed(speed_m_s: float) -> None:
    """OptionError for a constant-speed track's speed (m/s, sign: direction) no rail carriage has."""
    if not (math.isfinite(speed_m_s) and 0 < abs(speed_m_s) <= MAX_SPEED_M_S):
        raise OptionError("speed_m_s", f"must be finite, non-zero and within +-{MAX_SPEED_M_S:g} m/s (a "
                          f"rail carriage), got {speed_m_s}")


def constant_speed_track(recording: RawRecording, speed_m_s: float) -> Track:
    """Every scan on a straight track at ``speed_m_s`` (sign: direction), centred on x = 0."""
    check_speed(speed_m_s)
    t = recording.scan_time_s
    x = speed_m_s * (t - 0.5 * (t[0] + t[-1]))
    return Track(scans=np.arange(recording.n_scans), x_m=x, time_offset_s=None)


def default_reference_point(x_centre_m: float, options: ImportOptions, height_m: float,
                            range_m: float | None = None) -> tuple:
    """On the boresight at ``range_m`` (default: reference_range_m) from the aperture centre, at rail
    height."""
    th = math.radians(options.rotation_table_angle_deg)
    r = range_m if range_m is not None else options.reference_range_m or DEFAULT_REFERENCE_RANGE_M
    return (x_centre_m + r * math.sin(th), options.boresight_y_sign * r * math.cos(th), height_m)


@dataclasses.dataclass
class ImportResult:
    """One imported pass and what the import measured."""

    scan: ScanPass
    band: baseband.Band
    decimation: int
    track: Track
    notes: list[str] = dataclasses.field(default_factory=list)  # values the import chose, for its summary


def build_pass(
    recording: RawRecording,
    track: Track,
    options: ImportOptions,
    band: baseband.Band | None = None,
    file_mtime_s: float | None = None,
) -> ImportResult:
    """Convert the kept scans to complex baseband and assemble the archive pass (with the raw RF if asked).

    OptionError (a usage error) for a value that does not fit the recording; RecordingError for a recording
    or positions log that cannot make an archive. The cheap checks come before the conversion."""
    if not recording.is_real_rf:
        raise NotImplementedError("complex (already demodulated) recordings: not yet")  # e.g. a Novelda X4
    if track.scans.size < 2:
        raise RecordingError(recording.source, None,
                             f"only {track.scans.size} scan(s) left for the pass, too few to focus")
    window_start_s = _window_start_s(recording, options)
    height = options.height_m
    if height is None:
        check_height_source(options, track.z_m)
        height = float(np.median(track.z_m))
    # the antenna's deviations from the straight rail (archive 1.2, compensated in focusing: method.md C14):
    # y_m is the antenna's Y_r (the straight rail is the X_r axis), z_m - height its height above the rail's
    dy = None if track.y_m is None else np.array(track.y_m, dtype=float)
    dz = None if track.z_m is None else track.z_m - height
    times = recording.scan_time_s[track.scans]
    _check_deviations(track, times, dy, dz, height)
    scans = track.scans  # the kept scans are one run as a rule: a view, not a copy of the recording
    contiguous = bool(np.all(np.diff(scans) == 1))
    rf = recording.samples[scans[0]:scans[-1] + 1] if contiguous else recording.samples[scans]
    if not np.any(rf != rf[:, :1]):
        raise RecordingError(recording.source, None, (
            f"no signal: every kept scan is constant ({int(rf[0, 0]) if rf.dtype.kind in 'iu' else rf[0, 0]} "
            "in every sample), a receiver or antenna that was not connected?"))
    rf_rate_hz = 1.0 / recording.bin_period_s
    band = band or baseband.measure_band(rf, recording.bin_period_s)
    baseband.check_band(rf, rf_rate_hz, band, recording.source)
    carrier = options.carrier_frequency_hz or band.centre_hz
    decimation = options.decimation or baseband.choose_decimation(rf_rate_hz, band, options.oversampling)
    _check_kept_band(band, carrier, decimation, rf_rate_hz)
    try:
        echo, rate = baseband.to_baseband(rf, recording.bin_period_s, recording.scan_start_s, carrier,
                                          decimation)
    except ValueError as exc:  # the kept band leaves 0..Nyquist
        given = [k for k in ("carrier_frequency_hz", "decimation") if getattr(options, k) is not None]
        if given:
            raise OptionError(given[0], str(exc)) from None
        raise RecordingError(recording.source, None, f"cannot convert to baseband: {exc}") from None
    prf = options.pulse_repetition_frequency_hz or 1.0 / float(np.median(np.diff(times)))
    x_centre = 0.5 * float(track.x_m[0] + track.x_m[-1])
    notes = []
    window_m = (0.5 * SPEED_OF_LIGHT_M_S * window_start_s,
                0.5 * SPEED_OF_LIGHT_M_S * (window_start_s + (echo.shape[1] - 1) / rate))
    reference = _reference_point(x_centre, options, height, window_m, notes)
    _warn_undersampled(recording.source, track.x_m, carrier)
    extent_m = abs(float(track.x_m[-1] - track.x_m[0]))
    if extent_m > LONG_RAIL_M:
        log.warning("%s: the pass spans %.1f m along the rail, more than any face-end rail (%g m): %s",
                    track.positions.source if track.positions else recording.source, extent_m, LONG_RAIL_M,
                    "are the positions in metres (x_m)?" if track.positions else "is --speed-m-s in m/s?")
    measured = None
    if options.pulse == "measured":
        measured = baseband.measure_pulse(echo, rate, window_start_s, carrier, options.pulse_window_start_m,
                                          options.pulse_window_stop_m, recording.source)
    bandwidth = options.bandwidth_hz or band.bandwidth_hz
    if abs(carrier - band.centre_hz) > CARRIER_WARN_FRACTION * band.bandwidth_hz:
        log.warning("%s: the carrier given, %.4g Hz, is %.0f MHz from the measured -10 dB centre %.4g Hz "
                    "(%.0f %% of the -10 dB width): the archive's pulse model will not fit the echo, and a "
                    "plate may focus as two (another radar's value?)", recording.source, carrier,
                    abs(carrier - band.centre_hz) / 1e6, band.centre_hz,
                    100 * abs(carrier - band.centre_hz) / band.bandwidth_hz)
    if abs(bandwidth / band.bandwidth_hz - 1.0) > BANDWIDTH_WARN_FRACTION:
        log.warning("%s: the bandwidth given, %.4g Hz, is %.0f %% off the measured -10 dB width %.4g Hz: "
                    "the archive's pulse model will not fit the echo (another radar's value?)",
                    recording.source, bandwidth, 100 * abs(bandwidth / band.bandwidth_hz - 1.0),
                    band.bandwidth_hz)
    radar = RadarParameters(
        carrier_frequency_hz=carrier,
        bandwidth_hz=bandwidth,
        sample_rate_hz=rate,
        pulse_repetition_frequency_hz=prf,
        antenna_aperture_m=options.antenna_aperture_m,
        measured_pulse=measured,
    )
    geometry = PassGeometry(
        height_m=height,
        rotation_table_angle_deg=options.rotation_table_angle_deg,
        reference_point_m=tuple(float(v) for v in reference),
        boresight_y_sign=options.boresight_y_sign,
    )
    raw = None
    if options.keep_raw_rf:
        raw = RawRF(samples=rf, bin_period_s=recording.bin_period_s, scan_start_s=recording.scan_start_s)
    scan = ScanPass(
        radar=radar,
        geometry=geometry,
        range_window_start_s=window_start_s,
        pulse_time_s=times - times[0],
        pulse_position_m=track.x_m,
        echo=echo,
        rig_id=options.rig_id,
        cycle=options.cycle,
        pass_start_time=options.pass_start_time
        or _start_from_mtime(file_mtime_s, recording.scan_time_s[-1] - times[0]),
        source=recording.source,
        range_delay_s=options.range_delay_s,
        raw_rf=raw,
        antenna_y_m=dy,
        antenna_z_m=dz,
    )
    return ImportResult(scan=scan, band=band, decimation=decimation, track=track, notes=notes)


def check_height_source(options: ImportOptions, z_m: np.ndarray | None) -> None:
    """OptionError when the rail height is neither given nor in the positions (z_m): checked again before
    the recording is read, which may take a minute."""
    if options.height_m is None and z_m is None:
        raise OptionError("height_m", "required: the rail height is the median z_m of the positions, and "
                                      "there are none")


def _window_start_s(recording: RawRecording, options: ImportOptions) -> float:
    """The archive's window start, the calibrated delay removed; OptionError for a delay that puts it behind
    the antenna (docs/importing.md section 5)."""
    delay = options.range_delay_s
    start = recording.scan_start_s - delay
    end = start + recording.samples.shape[1] * recording.bin_period_s
    if end <= 0 < delay:
        raise OptionError("range_delay_s", (
            f"{delay:.4g} s is more than the recording's whole scan window ({recording.scan_start_s:.4g} to "
            f"{recording.scan_start_s + end - start:.4g} s): it would lie behind the antenna (a P440's delay "
            "is about 10e-9 s; the value is in seconds)"))
    if start < 0 < delay:  # a window that holds the coupling: its part behind the antenna is not processed
        log.info("%s: the window starts %.2f m behind the antenna once the delay is removed (it holds the "
                 "antenna's coupling); processing starts %.2f m in front of it", recording.source,
                 0.5 * SPEED_OF_LIGHT_M_S * -start, MIN_WINDOW_RANGE_M)
    if delay < 0:
        log.warning("%s: range_delay_s %.4g s is negative: the antenna's echo would come before the radar's "
                    "zero delay (a sign mistake?)", recording.source, delay)
    return start


def _check_deviations(track: Track, scan_time_s: np.ndarray, dy: np.ndarray | None, dz: np.ndarray | None,
                      height_m: float) -> None:
    """RecordingError naming the positions file, column and line of a rail deviation the archive cannot
    hold (before anything is written)."""
    pos = track.positions
    for column, d in (("y_m", dy), ("z_m", dz)):
        bad = np.flatnonzero(np.abs(d) > MAX_RAIL_DEVIATION_M) if d is not None else []
        if not len(bad):
            continue
        limit = (f"beyond the +-{MAX_RAIL_DEVIATION_M} m a rail deviation may have (so are {len(bad)} of the "
                 f"{len(d)} scans kept)")
        if pos is None or pos.line is None or track.time_offset_s is None:
            raise RecordingError(pos.source if pos else "positions", None,
                                 f"{column}: {d[bad[0]]:+.3f} m from the straight rail, {limit}")
        # the logged row behind the first such scan: of the two it lies between, the one further off
        values = pos.y_m if column == "y_m" else pos.z_m - height_m
        i = int(np.searchsorted(pos.time_s, scan_time_s[bad[0]] + track.time_offset_s))
        i = max((min(k, len(values) - 1) for k in (i - 1, i)), key=lambda k: abs(values[k]))
        what = (f"y_m {pos.y_m[i]:+.3f} m is" if column == "y_m" else
                f"z_m {pos.z_m[i]:.3f} m is {values[i]:+.3f} m from the rail height {height_m:.3f} m,")
        raise RecordingError(pos.source, None, (
            f"line {pos.line[i]}: {what} {limit}; y_m is the distance from the straight rail line, z_m the "
            "height (docs/importing.md section 4)"))


def _check_kept_band(band: baseband.Band, carrier_hz: float, decimation: int, rf_rate_hz: float) -> None:
    """OptionError for a given carrier or decimation whose complex band leaves out part of the measured -10 dB
    band (the written pass would model a band its samples alias)."""
    rate = rf_rate_hz / decimation
    if band.low_hz >= carrier_hz - rate / 2 and band.high_hz <= carrier_hz + rate / 2:
        return
    lo_ghz, hi_ghz = (carrier_hz - rate / 2) / 1e9, (carrier_hz + rate / 2) / 1e9
    numbers = (f"the complex band {lo_ghz:.3f}-{hi_ghz:.3f} GHz (carrier {carrier_hz / 1e9:.3f} GHz, rate "
               f"{rate / 1e9:.3f} GHz = RF {rf_rate_hz / 1e9:.3f} GHz / {decimation}) leaves out part of the "
               f"measured -10 dB band {band.low_hz / 1e9:.3f}-"
               f"{band.high_hz / 1e9:.3f} GHz ({band.bandwidth_hz / 1e9:.3f} GHz)")
    # The defaults cover the band (check_band passed): a decimation below the bandwidth or a carrier off the
    # band was given.
    if rate < band.bandwidth_hz:
        most = math.floor(rf_rate_hz / band.bandwidth_hz)
        raise OptionError("decimation", f"{decimation}: {numbers}; the complex rate must be at least the "
                                        f"bandwidth: decimation <= {most}")
    raise OptionError("carrier_frequency_hz", f"{carrier_hz:.6g} Hz: {numbers}; centre the carrier on the "
                                              f"band ({band.centre_hz:.6g} Hz)")


def _reference_point(x_centre_m: float, options: ImportOptions, height_m: float,
                     window_m: tuple[float, float], notes: list[str]) -> tuple:
    """The scene centre: given, or on boresight at reference_range_m (default: DEFAULT_REFERENCE_RANGE_M, or
    the middle of the delay window when that lies outside it, with a note); a warning when a given one lies
    outside the window (the scene centre would be a range the pass never recorded)."""
    lo, hi = window_m
    window = f"the recording's window {lo:.2f}-{hi:.2f} m (one-way range on the archive's axis)"
    if options.reference_point_m is not None:
        r = math.dist((x_centre_m, 0.0, height_m), options.reference_point_m)
        if not lo <= r <= hi:
            log.warning("the reference point %s (--reference-point) lies %.2f m from the aperture centre, "
                        "outside %s", options.reference_point_m, r, window)
        return options.reference_point_m
    r = options.reference_range_m
    if r is None:
        r = DEFAULT_REFERENCE_RANGE_M
        if not lo <= r <= hi:
            r = 0.5 * (lo + hi)
            notes.append(f"reference: on boresight at {r:.2f} m, the middle of {window}; the default "
                         f"{DEFAULT_REFERENCE_RANGE_M} m lies outside it (--reference-range-m sets it)")
    elif not lo <= r <= hi:
        log.warning("the reference range %.2f m (--reference-range-m) lies outside %s", r, window)
    return default_reference_point(x_centre_m, options, height_m, r)


def _warn_undersampled(source: str, x_m: np.ndarray, carrier_hz: float) -> None:
    """A warning when the pulses are further apart along the rail than a quarter wavelength: a beam that sees
    +-90 deg has a two-way Doppler band of 4 v / lambda, sampled without aliasing when dx <= lambda / 4 (the
    processed beam's band, narrower and more so when squinted, may tolerate more: not refused)."""
    spacing_m = float(np.median(np.abs(np.diff(x_m))))
    quarter_m = SPEED_OF_LIGHT_M_S / carrier_hz / 4
    if spacing_m > quarter_m:
        log.warning("%s: the pulses are %.1f mm apart along the rail (median), more than a quarter "
                    "wavelength (%.1f mm at %.3f GHz): the image may alias in azimuth (a beam seeing +-90 "
                    "deg needs lambda / 4; docs/importing.md section 4)",
                    source, 1e3 * spacing_m, 1e3 * quarter_m, carrier_hz / 1e9)


def _start_from_mtime(mtime_s: float | None, before_end_s: float) -> str:
    # The file was last written at its last scan: the pass started before_end_s earlier.
    if mtime_s is None:
        return "1970-01-01T00:00:00Z"
    start = dt.datetime.fromtimestamp(mtime_s - float(before_end_s), tz=dt.timezone.utc)
    return start.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def options_from_table(table: dict, path: str | os.PathLike[str] | None = None) -> dict:
    """ImportOptions values from the ``[import]`` table of a site TOML, checked: ConfigError names the key."""
    if not isinstance(table, dict):
        raise ConfigError(path, "import", "must be a table ([import])")
    out = {}
    for key, value in table.items():
        if key not in OPTION_TYPES:
            raise ConfigError(
                path, f"import.{key}", f"unknown key; expected one of {', '.join(sorted(OPTION_TYPES))}"
            )
        kind = OPTION_TYPES[key]
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if "tuple" in kind:
            ok = (
                isinstance(value, list)
                and len(value) == 3
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
            )
            value = tuple(float(v) for v in value) if ok else value
        elif kind.startswith("bool"):
            ok = isinstance(value, bool)
        elif kind.startswith("int"):
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif kind.startswith("float"):
            ok = number and math.isfinite(value)
            value = float(value) if ok else value
        else:
            ok = isinstance(value, str)
        if not ok:
            raise ConfigError(path, f"import.{key}", f"expected {kind.replace(' | None', '')}, got {value!r}")
        out[key] = value
    return out


def _check_lengths(options: ImportOptions) -> None:
    """OptionError for a length (an option ending in _m) beyond the site file's +-MAX_LENGTH_M (one rule for
    every length, docs/configuration.md)."""
    for f in dataclasses.fields(options):
        value = getattr(options, f.name)
        if f.name.endswith("_m") and beyond_max_length(value):
            raise OptionError(f.name, f"must be within +-{MAX_LENGTH_M:g} m, got {value}")


def check_options(options: ImportOptions) -> None:
    """OptionError (key, reason) for values no archive could hold, checked before any file is read."""

    def fail(key: str, reason: str) -> None:
        raise OptionError(key, reason)

    if options.boresight_y_sign not in (-1, 1):
        fail("boresight_y_sign", f"must be -1 or +1, got {options.boresight_y_sign}")
    if not abs(options.rotation_table_angle_deg) < 90.0:
        fail("rotation_table_angle_deg", f"must be within (-90, 90), got {options.rotation_table_angle_deg}")
    for key in (
        "antenna_aperture_m",
        "reference_range_m",
        "oversampling",
        "min_step_m",
        "pulse_repetition_frequency_hz",
        "carrier_frequency_hz",
        "bandwidth_hz",
    ):
        value = getattr(options, key)
        if value is not None and not (math.isfinite(value) and value > 0):
            fail(key, f"must be > 0, got {value}")
    if options.height_m is not None and not math.isfinite(options.height_m):
        fail("height_m", f"must be finite, got {options.height_m}")
    if options.reference_point_m is not None and not all(map(math.isfinite, options.reference_point_m)):
        fail("reference_point_m", f"must be finite, got {options.reference_point_m}")
    _check_lengths(options)
    if options.decimation is not None and options.decimation < 1:
        fail("decimation", f"must be >= 1, got {options.decimation}")
    if options.pulse not in ("gaussian", "measured"):
        fail("pulse", f"must be 'gaussian' or 'measured', got {options.pulse!r}")
    # A start below 0 m is legal: a calibrated coupling sits within a few cm of 0 m, so its window starts
    # behind the antenna (docs/importing.md section 5).
    if not math.isfinite(options.pulse_window_start_m):
        fail("pulse_window_start_m", f"must be finite, got {options.pulse_window_start_m}")
    if not options.pulse_window_start_m < options.pulse_window_stop_m < math.inf:
        fail("pulse_window_stop_m", "the reference window needs pulse_window_start_m < pulse_window_stop_m "
             f"(finite), got {options.pulse_window_start_m}, {options.pulse_window_stop_m}")
    if not math.isfinite(options.range_delay_s):
        fail("range_delay_s", f"must be finite, got {options.range_delay_s}")
    if not abs(options.range_delay_s) < MAX_RANGE_DELAY_S:  # the site config's bound (config.py)
        fail("range_delay_s", f"must be within +-{MAX_RANGE_DELAY_S:g} s (a larger value is a unit error: ns "
                              f"for s?), got {options.range_delay_s!r}")
    _check_identity(options)


def _check_identity(options: ImportOptions) -> None:
    """OptionError for a pass identity the archive would refuse after the whole conversion."""
    if options.cycle < 0:
        raise OptionError("cycle", f"must be >= 0, got {options.cycle}")
    if options.cycle > MAX_CYCLE:
        raise OptionError("cycle", f"must be at most {MAX_CYCLE} (the archive's int64), got {options.cycle}")
    if not options.rig_id.strip():
        raise OptionError("rig_id", "must not be empty")
    if options.pass_start_time is not None:
        try:
            parse_utc(options.pass_start_time)
        except ValueError as exc:
            raise OptionError("pass_start_time", f"{exc} (e.g. 2026-11-23T06:00:00Z)") from None
