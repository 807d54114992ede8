"""Simulated production shifts: several rigs, many cutting cycles, a rib of look-alike bolt plates (issue 4).

Each rig sits at one face end with its own rib (roadway frame of `scenarios.py`: X along the panel, the rib at
Y = 0, the rig at Y = W > 0, Z up; radar frame = roadway frame shifted by the rig position). Per rig:

* **Bolt plates** in two or three rows (row heights ~0.5/1.1/1.7 m or ~0.6/1.3 m), each row with its own
  irregular spacing of 1.0-1.5 m, some plates missing, a few centimetres of rib roughness in Y and Z, and
  plate reflectivities of 0.6-1.0.
* **Rib clutter**: many weak scatterers (about 8 per metre of rib, amplitudes ~0.01-0.05) over the rib
  surface.
* **Motion per cycle**: a web of nominal depth (0.85-0.95 m per rig) with small variation, clipped to
  0.8-1.0 m; creep as a drift of 2-6 mm per cycle plus 1.5 mm noise, with occasional (8 %) jumps of 50-100 mm;
  a few millimetres of vertical change (floor undulation); a cycle every 20-60 minutes.
* **Rotation table**: before each cycle's passes the rig steers the table at the plate whose bearing it
  believes is closest to `look_angle_deg` (28 deg), or at the rib point on that bearing when no plate is
  within `steer_tolerance_deg`. Its belief is dead reckoning (last position plus the nominal web), so the
  archived reference point is a few centimetres off the plate, as on a real rig. As the rig retreats, the
  plates it looks at change: new plates enter the beam ahead, old ones leave behind it.

Every random draw comes from a generator seeded by (seed, rig, purpose[, cycle]) and plates/clutter are
drawn in a prefix-stable order, so cycle c of rig k is the same whichever `cycles`/`first_cycle` produced it:
a later call with `first_cycle` appends the next shift to an archive tree without changing what is already
there.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from . import archive
from . import geometry as geo
from .atomic import csv_text, write_text_atomic
from .model import SPEED_OF_LIGHT_M_S, PassGeometry, RadarParameters, ScanPass
from .simulate import rail_motion, seen_ranges_m, simulate_echo
from .utc import parse_utc

SHIFT_START = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.timezone.utc)

_PLATES, _CLUTTER, _CYCLE, _RIG = 1, 2, 3, 4  # purposes in the seed sequences


@dataclasses.dataclass(frozen=True)
class ShiftConfig:
    cycles: int = 40
    rigs: int = 3
    first_cycle: int = 0  # write cycles first_cycle .. first_cycle + cycles - 1
    heights_m: tuple[float, ...] = (0.2, 0.6)
    seed: int = 0
    snr_db: float | None = None
    speed_jitter: float = 0.0
    rig_prefix: str = "rig"  # the rigs' ids are <prefix>-1, <prefix>-2, ...
    # A 3 m rail at 0.25 m/s and 20 Hz: 241 pulses, the cost of a paper pass (sim 1: 267), and a 3 m window
    # along the rib, so consecutive cycles still share ~2 m of plates after a 1 m web (2 m would leave ~1 m).
    aperture_length_m: float = 3.0
    speed_m_s: float = 0.25
    range_samples: int = 128  # the gate: 4.8 m of range at 4 GHz
    look_angle_deg: float = 28.0
    steer_tolerance_deg: float = 6.0
    range_margin_m: float = 0.4
    clutter_per_m: float = 8.0
    radar: RadarParameters = dataclasses.field(default_factory=RadarParameters)


@dataclasses.dataclass(frozen=True)
class Rib:
    """What is fixed in the roadway: bolt plates and weak clutter, positions (n, 3) in the roadway frame."""

    plates_m: np.ndarray
    plate_amplitudes: np.ndarray
    clutter_m: np.ndarray
    clutter_amplitudes: np.ndarray


@dataclasses.dataclass(frozen=True)
class CycleTruth:
    rig_id: str
    cycle: int
    start_time: str
    rig_position_m: np.ndarray  # (3,) roadway frame
    advance_m: np.ndarray  # (3,) Delta P from the previous cycle (NaN for cycle 0)
    rotation_table_angle_deg: float
    reference_point_m: np.ndarray  # (3,) radar frame, where the rig believes its reference plate is


def rig_id(rig: int, prefix: str = "rig") -> str:
    return f"{prefix}-{rig + 1}"


def _rng(cfg: ShiftConfig, rig: int, *purpose: int) -> np.random.Generator:
    return np.random.default_rng([cfg.seed, rig, *purpose])


@dataclasses.dataclass(frozen=True)
class _RigModel:
    nominal_web_m: float
    wall_m: float
    creep_rate_m: float  # signed drift per cycle
    row_heights_m: tuple[float, ...]
    start_offset_min: float


def _rig_model(cfg: ShiftConfig, rig: int) -> _RigModel:
    r = _rng(cfg, rig, _RIG)
    nominal = r.uniform(0.85, 0.95)
    wall = r.uniform(2.2, 2.5)
    rate = r.uniform(0.002, 0.006) * r.choice([-1.0, 1.0])
    rows = (0.5, 1.1, 1.7) if r.uniform() < 0.5 else (0.6, 1.3)
    rows = tuple(float(z + r.normal(0.0, 0.03)) for z in rows)
    return _RigModel(float(nominal), float(wall), float(rate), rows, float(r.uniform(0.0, 15.0)))


def rib(cfg: ShiftConfig, rig: int, x_max_m: float) -> Rib:
    """Plates and clutter of a rig's rib from X = -8 m up to x_max_m (prefix-stable in x_max_m)."""
    model = _rig_model(cfg, rig)
    plates, amps = [], []
    for row, z_row in enumerate(model.row_heights_m):
        r = _rng(cfg, rig, _PLATES, row)
        x = -8.0 + r.uniform(0.0, 1.5)
        while x < x_max_m:
            spacing, missing, dy, dz, amp = r.uniform(1.0, 1.5), r.uniform(), r.normal(0, 0.02), \
                r.normal(0, 0.03), r.uniform(0.6, 1.0)
            if missing >= 0.12:
                plates.append((x, dy, z_row + dz))
                amps.append(amp)
            x += spacing
    r = _rng(cfg, rig, _CLUTTER)
    clutter, camps = [], []
    x = -8.0
    while True:
        gap, z, dy, amp = r.exponential(1.0 / cfg.clutter_per_m), r.uniform(0.0, 2.4), r.normal(0, 0.03), \
            r.rayleigh(0.02)
        x += gap
        if x >= x_max_m:
            break
        clutter.append((x, dy, z))
        camps.append(amp)
    order = np.argsort([p[0] for p in plates], kind="stable")
    return Rib(np.array(plates)[order], np.array(amps)[order], np.array(clutter).reshape(-1, 3),
               np.array(camps))


def _format_time(t: dt.datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def cycle_truths(cfg: ShiftConfig, rig: int, rib_: Rib | None = None) -> list[CycleTruth]:
    """The rig's motion and table steering for cycles 0 .. first_cycle + cycles - 1."""
    model = _rig_model(cfg, rig)
    n = cfg.first_cycle + cfg.cycles
    rib_ = rib_ if rib_ is not None else rib(cfg, rig, _x_max(cfg, n))
    rig_pos = np.array([0.0, model.wall_m, 0.0])
    rate = model.creep_rate_m
    when = SHIFT_START + dt.timedelta(minutes=model.start_offset_min)
    out = []
    for c in range(n):
        r = _rng(cfg, rig, _CYCLE, c)
        web = float(np.clip(model.nominal_web_m + r.normal(0.0, 0.025), 0.8, 1.0))
        jump = r.uniform() < 0.08
        jump_m = r.uniform(0.05, 0.10) * (1.0 if r.uniform() < 0.75 else -1.0)
        creep_noise = r.normal(0.0, 0.0015)
        vertical = r.normal(0.0, 0.003)
        gap_min = r.uniform(20.0, 60.0)
        if c == 0:
            advance = np.full(3, np.nan)
            believed = rig_pos.copy()
        else:
            # Creep drifts one way until the rig is pushed too close to / far from the rib, then back.
            if not 1.9 <= rig_pos[1] + rate <= 2.8:
                rate = -rate
            creep = rate + creep_noise + (jump_m * math.copysign(1.0, rate) if jump else 0.0)
            advance = np.array([web, creep, vertical])
            believed = rig_pos + np.array([model.nominal_web_m, 0.0, 0.0])  # dead reckoning
            rig_pos = rig_pos + advance
            when += dt.timedelta(minutes=gap_min)
        # Steer at the plate whose believed bearing is nearest the set look angle; with none within
        # +-steer_tolerance_deg of it, at the rib point on that bearing (low-row height): the table stays in a
        # band where the whole beam falls on the rib ahead.
        believed_radar = rib_.plates_m - believed
        bearing = np.degrees(np.arctan2(believed_radar[:, 0], -believed_radar[:, 1]))
        k = int(np.argmin(np.abs(bearing - cfg.look_angle_deg)))
        if abs(bearing[k] - cfg.look_angle_deg) <= cfg.steer_tolerance_deg:
            ref = believed_radar[k].copy()  # not a view: it would keep the whole rib's array of this cycle
        else:
            wall = float(np.median(-believed_radar[:, 1]))
            ref = np.array([wall * math.tan(math.radians(cfg.look_angle_deg)), -wall, model.row_heights_m[0]])
        angle = geo.rotation_table_angle_for(ref, 0.0)
        out.append(CycleTruth(rig_id(rig, cfg.rig_prefix), c, _format_time(when), rig_pos.copy(), advance,
                              angle, ref))
    return out


def _x_max(cfg: ShiftConfig, n_cycles: int) -> float:
    return 1.0 * n_cycles + 12.0  # the rig advances at most 1 m per cycle; the beam reaches < 8 m ahead


def simulate_gated_pass(cfg: ShiftConfig, geometry: PassGeometry, targets_radar_m: np.ndarray,
                        amplitudes: np.ndarray, rng: np.random.Generator, *, direction: int, rig: str,
                        cycle: int, start_time: str) -> ScanPass:
    """One pass recorded through a fixed range gate of `range_samples` samples, as the radar does.

    The gate opens `range_margin_m` before the nearest echo in the beam; scatterers whose echo would run past
    the gate's end (less the margin) are left out rather than cut, so no truncated responses enter the image.
    """
    radar = cfg.radar
    prf = radar.pulse_repetition_frequency_hz
    n_intervals = 2 * round(0.5 * cfg.aperture_length_m / cfg.speed_m_s * prf)
    start = -direction * 0.5 * n_intervals * cfg.speed_m_s / prf
    times, positions = rail_motion(n_intervals + 1, prf, cfg.speed_m_s, start, cfg.speed_jitter, rng,
                                   direction)
    ranges = seen_ranges_m(radar, positions, targets_radar_m, geometry.height_m,
                           math.radians(geometry.rotation_table_angle_deg), -1)
    seen = np.isfinite(ranges[:, 0])
    r_lo = np.nanmin(ranges[:, 0]) - cfg.range_margin_m
    r_hi = r_lo + cfg.range_samples * radar.range_bin_m - cfg.range_margin_m
    keep = seen & (ranges[:, 1] <= r_hi)
    t0 = 2.0 * max(r_lo, 0.0) / SPEED_OF_LIGHT_M_S
    echo = simulate_echo(radar, geometry, positions, targets_radar_m[keep], amplitudes[keep], t0,
                         cfg.range_samples, cfg.snr_db, rng)
    return ScanPass(radar=radar, geometry=geometry, range_window_start_s=t0, pulse_time_s=times,
                    pulse_position_m=positions, echo=echo, rig_id=rig, cycle=cycle,
                    pass_start_time=start_time)


def simulate_shift(cfg: ShiftConfig) -> Iterator[ScanPass]:
    """Every pass of cycles first_cycle .. first_cycle + cycles - 1 of every rig, in (rig, cycle, height)
    order."""
    n = cfg.first_cycle + cfg.cycles
    for rig in range(cfg.rigs):
        rib_ = rib(cfg, rig, _x_max(cfg, n))
        targets = np.vstack([rib_.plates_m, rib_.clutter_m])
        amplitudes = np.concatenate([rib_.plate_amplitudes, rib_.clutter_amplitudes])
        for truth in cycle_truths(cfg, rig, rib_)[cfg.first_cycle:]:
            radar_frame = targets - truth.rig_position_m
            near = np.abs(radar_frame[:, 0]) < 10.0  # a cheap cut before the per-pulse beam test
            start = parse_utc(truth.start_time)
            for i, h in enumerate(cfg.heights_m):
                g = PassGeometry(height_m=float(h), rotation_table_angle_deg=truth.rotation_table_angle_deg,
                                 reference_point_m=tuple(float(v) for v in truth.reference_point_m))
                # The carriage runs out at the first height and back at the next, as on a real rail.
                yield simulate_gated_pass(
                    cfg, g, radar_frame[near], amplitudes[near], _rng(cfg, rig, _CYCLE, truth.cycle, 1 + i),
                    direction=1 if i % 2 == 0 else -1, rig=truth.rig_id, cycle=truth.cycle,
                    start_time=_format_time(start + dt.timedelta(seconds=45 * i)))


TRUTH_COLUMNS = ("rig_id", "cycle", "start_time", "retreat_m", "creep_m", "vertical_m",
                 "cumulative_retreat_m", "cumulative_creep_m", "cumulative_vertical_m", "rig_x_m", "rig_y_m",
                 "rig_z_m", "rotation_table_angle_deg")


def truth_rows(cfg: ShiftConfig) -> list[dict]:
    """truth.csv: one row per rig and cycle; the displacement columns are empty for cycle 0."""
    rows = []
    for rig in range(cfg.rigs):
        truths = cycle_truths(cfg, rig)
        origin = truths[0].rig_position_m
        for t in truths:
            cum = t.rig_position_m - origin
            first = t.cycle == 0
            rows.append({
                "rig_id": t.rig_id, "cycle": t.cycle, "start_time": t.start_time,
                **{k: "" if first else f"{v:.6f}" for k, v in zip(("retreat_m", "creep_m", "vertical_m"),
                                                                  t.advance_m)},
                **{k: f"{v:.6f}" for k, v in zip(("cumulative_retreat_m", "cumulative_creep_m",
                                                   "cumulative_vertical_m"), cum)},
                **{k: f"{v:.6f}" for k, v in zip(("rig_x_m", "rig_y_m", "rig_z_m"), t.rig_position_m)},
                "rotation_table_angle_deg": f"{t.rotation_table_angle_deg:.6f}",
            })
    return rows


PLATE_COLUMNS = ("rig_id", "plate", "x_m", "y_m", "z_m", "amplitude")


def plate_rows(cfg: ShiftConfig) -> list[dict]:
    """truth_plates.csv: every bolt plate of every rig's rib, roadway frame."""
    rows = []
    for rig in range(cfg.rigs):
        r = rib(cfg, rig, _x_max(cfg, cfg.first_cycle + cfg.cycles))
        for i, (p, a) in enumerate(zip(r.plates_m, r.plate_amplitudes)):
            rows.append({"rig_id": rig_id(rig, cfg.rig_prefix), "plate": i, "x_m": f"{p[0]:.6f}",
                         "y_m": f"{p[1]:.6f}", "z_m": f"{p[2]:.6f}", "amplitude": f"{a:.6f}"})
    return rows


def write_shift(out_dir, cfg: ShiftConfig, *, overwrite: bool = False, created_by: str = "uwbcl simulate"
                ) -> list[str]:
    """Archive every pass of `cfg` under out_dir (archive.default_relative_path) plus truth.csv and
    truth_plates.csv (covering cycles 0 .. first_cycle + cycles - 1); returns the archives' relative paths."""
    out = Path(out_dir)
    written = []
    for scan in simulate_shift(cfg):
        path = out / archive.default_relative_path(scan)
        archive.write_pass(path, scan, overwrite=overwrite, created_by=created_by)
        written.append(path.relative_to(out).as_posix())
    write_text_atomic(out / "truth.csv", csv_text(TRUTH_COLUMNS, truth_rows(cfg)))
    write_text_atomic(out / "truth_plates.csv", csv_text(PLATE_COLUMNS, plate_rows(cfg)))
    return written
