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
import logging
import math
import os
from pathlib import Path

import numpy as np

from ..model import PassGeometry, RadarParameters, RawRF, ScanPass
from ..records import ConfigError
from . import RawRecording, RecordingError, baseband

log = logging.getLogger("uwbcl")

MOTION_THRESHOLD_M = 0.002  # a position this far from the first one has moved (about where the echo shows it)
_REST_SCANS = 8  # scans at the start assumed at rest for the radar's motion detector


@dataclasses.dataclass(frozen=True)
class ImportOptions:
    """The archive values a radar recording does not hold (flags, or the [import] table of a site TOML)."""

    height_m: float | None = None  # rail (antenna phase centre) height; default: median z_m of the positions
    rotation_table_angle_deg: float = 0.0
    boresight_y_sign: int = -1
    reference_point_m: tuple[float, float, float] | None = (
        None  # default: on boresight, reference_range_m away
    )
    reference_range_m: float = 3.0
    antenna_aperture_m: float = 0.14
    pulse_repetition_frequency_hz: float | None = None  # default: 1 / median scan interval
    range_delay_s: float = 0.0  # calibrated two-way antenna/cable delay (archive 1.1 /radar@range_delay_s)
    rig_id: str = "rig-1"
    cycle: int = 0
    pass_start_time: str | None = None  # ISO 8601 UTC; default: file modification time minus the duration
    carrier_frequency_hz: float | None = None  # default: the measured -10 dB band centre
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


def read_positions_csv(path: str | os.PathLike[str]) -> Positions:
    """A CSV with a header row naming ``time_s, x_m`` and optionally ``y_m, z_m`` (any order, extra columns
    ignored). RecordingError naming the file and line for a missing column, a non-number or a time that does
    not increase."""
    path = Path(path)
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise RecordingError(path, None, "empty positions file (expected a header: time_s,x_m[,y_m,z_m])")
    header = [h.strip() for h in rows[0]]
    for name in ("time_s", "x_m"):
        if name not in header:
            raise RecordingError(path, None, f"line 1: no column {name!r} (header: {', '.join(header)})")
    cols = {name: header.index(name) for name in ("time_s", "x_m", "y_m", "z_m") if name in header}
    values = {name: [] for name in cols}
    for line, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        for name, i in cols.items():
            try:
                v = float(row[i])
            except (IndexError, ValueError):
                raise RecordingError(
                    path, None, f"line {line}: {name}: not a number: {row[i] if i < len(row) else ''!r}"
                ) from None
            if not math.isfinite(v):
                raise RecordingError(path, None, f"line {line}: {name}: not finite")
            values[name].append(v)
    t = np.asarray(values["time_s"])
    if t.size < 2:
        raise RecordingError(path, None, "fewer than 2 positions")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise RecordingError(path, None, f"line {bad[0] + 3}: time_s does not increase")
    arr = {k: np.asarray(v) for k, v in values.items()}
    return Positions(time_s=t, x_m=arr["x_m"], y_m=arr.get("y_m"), z_m=arr.get("z_m"))


def radar_first_motion_s(recording: RawRecording, factor: float = 5.0) -> float | None:
    """Time (radar clock) of the first scan whose echo departs from the rest echo, or None.

    The first `_REST_SCANS` scans are taken as the rest echo and its scan-to-scan spread as the noise level;
    the first scan from which three in a row differ from the rest echo by more than ``factor`` x that level
    is the first motion (the phases of the scene's echoes change within a fraction of a wavelength).
    """
    x = recording.samples[: min(recording.n_scans, 2000)].astype(np.float64)
    if x.shape[0] <= _REST_SCANS + 3:
        return None
    rest = x[:_REST_SCANS]
    ref = rest.mean(axis=0)
    noise = np.mean((rest - ref) ** 2, axis=1).max()
    e = np.mean((x - ref) ** 2, axis=1)
    moving = e > factor * max(noise, 1e-30)
    run = moving[:-2] & moving[1:-1] & moving[2:]
    hits = np.flatnonzero(run[_REST_SCANS:]) + _REST_SCANS
    return float(recording.scan_time_s[hits[0]]) if hits.size else None


def positions_first_motion_s(positions: Positions) -> float | None:
    moved = np.flatnonzero(np.abs(positions.x_m - positions.x_m[0]) > MOTION_THRESHOLD_M)
    if not moved.size:
        return None
    i = moved[0]
    # Interpolate the crossing: the log may be sparse.
    x0, x1 = abs(positions.x_m[i - 1] - positions.x_m[0]), abs(positions.x_m[i] - positions.x_m[0])
    t0, t1 = positions.time_s[i - 1], positions.time_s[i]
    return float(t0 + (MOTION_THRESHOLD_M - x0) / (x1 - x0) * (t1 - t0)) if i > 0 else float(t0)


def moving_segment(x_m: np.ndarray, min_step_m: float) -> slice:
    """The longest run of samples whose position moves strictly one way by > min_step_m each step."""
    dx = np.diff(x_m)
    sign = np.where(dx > min_step_m, 1, np.where(dx < -min_step_m, -1, 0))
    best, start = (0, 0), 0
    for k in range(1, len(sign) + 1):
        if k == len(sign) or sign[k] != sign[start] or sign[k] == 0:
            if sign[start] != 0 and k - start > best[1] - best[0]:
                best = (start, k)
            start = k
    return slice(best[0], best[1] + 1) if best[1] > best[0] else slice(0, 0)


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
        time_offset_s = t_pos - t_radar
        log.info("clocks aligned on the first motion: positions time = scan time %+.3f s", time_offset_s)
    t = recording.scan_time_s + time_offset_s
    inside = np.flatnonzero((t >= positions.time_s[0]) & (t <= positions.time_s[-1]))
    if inside.size < 2:
        raise RecordingError(
            recording.source,
            None,
            f"the positions ({positions.time_s[0]:.3f}.."
            f"{positions.time_s[-1]:.3f} s) cover {inside.size} scans at a time offset of "
            f"{time_offset_s:.3f} s; check --time-offset-s",
        )

    def at(v):
        return None if v is None else np.interp(t[inside], positions.time_s, v)

    x = at(positions.x_m)
    seg = moving_segment(x, min_step_m)
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
    )


def constant_speed_track(recording: RawRecording, speed_m_s: float) -> Track:
    """Every scan on a straight track at ``speed_m_s`` (sign: direction), centred on x = 0."""
    if not (math.isfinite(speed_m_s) and speed_m_s != 0):
        raise ValueError(f"speed must be finite and non-zero, got {speed_m_s}")
    t = recording.scan_time_s
    x = speed_m_s * (t - 0.5 * (t[0] + t[-1]))
    return Track(scans=np.arange(recording.n_scans), x_m=x, time_offset_s=None)


def default_reference_point(x_centre_m: float, options: ImportOptions, height_m: float) -> tuple:
    """On the boresight at reference_range_m from the aperture centre, at rail height."""
    th = math.radians(options.rotation_table_angle_deg)
    r = options.reference_range_m
    return (x_centre_m + r * math.sin(th), options.boresight_y_sign * r * math.cos(th), height_m)


@dataclasses.dataclass
class ImportResult:
    """One imported pass and what the import measured."""

    scan: ScanPass
    band: baseband.Band
    decimation: int
    track: Track


def build_pass(
    recording: RawRecording,
    track: Track,
    options: ImportOptions,
    band: baseband.Band | None = None,
    file_mtime_s: float | None = None,
) -> ImportResult:
    """Convert the kept scans to complex baseband and assemble the archive pass (with the raw RF if asked)."""
    if not recording.is_real_rf:
        raise NotImplementedError("complex (already demodulated) recordings: not yet")  # e.g. a Novelda X4
    if track.scans.size < 2:
        raise RecordingError(recording.source, None, f"only {track.scans.size} scans left for the pass")
    rf = recording.samples[track.scans]
    band = band or baseband.measure_band(rf, recording.bin_period_s)
    carrier = options.carrier_frequency_hz or band.centre_hz
    decimation = options.decimation or baseband.choose_decimation(
        1.0 / recording.bin_period_s, band, options.oversampling
    )
    echo, rate = baseband.to_baseband(rf, recording.bin_period_s, recording.scan_start_s, carrier, decimation)
    height = options.height_m
    if height is None:
        if track.z_m is None:
            raise RecordingError(recording.source, None, "no rail height: give --height-m (or z_m positions)")
        height = float(np.median(track.z_m))
    # the antenna's deviations from the straight rail (archive 1.2, compensated in focusing: method.md C14):
    # y_m is the antenna's Y_r (the straight rail is the X_r axis), z_m - height its height above the rail's
    dy = None if track.y_m is None else np.array(track.y_m, dtype=float)
    dz = None if track.z_m is None else track.z_m - height
    times = recording.scan_time_s[track.scans]
    prf = options.pulse_repetition_frequency_hz or 1.0 / float(np.median(np.diff(times)))
    x_centre = 0.5 * float(track.x_m[0] + track.x_m[-1])
    reference = options.reference_point_m or default_reference_point(x_centre, options, height)
    window_start_s = recording.scan_start_s - options.range_delay_s
    measured = None
    if options.pulse == "measured":
        measured = baseband.measure_pulse(echo, rate, window_start_s, carrier, options.pulse_window_start_m,
                                          options.pulse_window_stop_m, recording.source)
    radar = RadarParameters(
        carrier_frequency_hz=carrier,
        bandwidth_hz=band.bandwidth_hz,
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
    return ImportResult(scan=scan, band=band, decimation=decimation, track=track)


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


def check_options(options: ImportOptions, path: str | os.PathLike[str] | None = None) -> None:
    """ConfigError for values no archive could hold (checked before any file is read)."""

    def fail(key: str, reason: str) -> None:
        raise ConfigError(path, key, reason)

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
    ):
        value = getattr(options, key)
        if value is not None and not (math.isfinite(value) and value > 0):
            fail(key, f"must be > 0, got {value}")
    if options.decimation is not None and options.decimation < 1:
        fail("decimation", f"must be >= 1, got {options.decimation}")
    if options.pulse not in ("gaussian", "measured"):
        fail("pulse", f"must be 'gaussian' or 'measured', got {options.pulse!r}")
    if not (0 <= options.pulse_window_start_m < options.pulse_window_stop_m < math.inf):
        fail("pulse_window_stop_m", "the reference window needs 0 <= pulse_window_start_m < "
             f"pulse_window_stop_m, got {options.pulse_window_start_m}, {options.pulse_window_stop_m}")
    if not math.isfinite(options.range_delay_s):
        fail("range_delay_s", f"must be finite, got {options.range_delay_s}")
