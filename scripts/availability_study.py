"""Availability study (issue 14): `uwbcl process` on gate-road scenarios generated independently of uwbcl.

The archives are written here with h5py from docs/archive-format.md alone (section 2, the signal model: a
Gaussian pulse, point scatterers, demodulated at f_c), never with uwbcl's simulator. Each scenario is one rig
over N cycles: a rib of bolt plates in 2-3 rows on a 1.0-1.5 m grid with plates missing and centimetres of
roughness, weak rib clutter, an antenna pattern of the real aperture, the rail run in both directions with a
wobbling carriage speed (positions logged per pulse), receiver noise at a given SNR, cycles missed (no files,
or one height only), with and without a web-depth prior. Then `uwbcl process --backend numpy` per scenario
(`--backend opencl`: the engine `uwbcl process` runs by default) and, against the truth, per scenario:

  ok %        rows with status ok / rows written (missed cycles write no row: the next one bridges them)
  RMS, max    error of the ok rows in retreat and creep (mm), over each row's own span from_cycle -> cycle
  cover       fraction of ok rows with |error| <= 3 x bound on both axes (when the outputs have a bound)
  gross       ok rows with an error > 50 mm (confidently wrong): must be 0
  drift       largest |error| of the cumulative retreat / creep (mm) against the truth from the chain's start

    python scripts/availability_study.py --work /tmp/avail --jobs 2            # full: 41 cycles per scenario
    python scripts/availability_study.py --work /tmp/avail-quick --quick       # CI size: 6 cycles
    python scripts/availability_study.py --work /tmp/avail --reuse-detections  # association only (see below)
    python scripts/availability_study.py --work /tmp/avail-random --random 30  # 30 drawn scenarios, 6 cycles

`--replicas N` also runs N more realisations of each named scenario (the same parameters, other seeds: plate
layout, motion and noise) and prints, per scenario, the spread of the cumulative drift, the largest excursion
of a random walk that one realisation estimates poorly.

`--random N` draws N scenarios from the issue's ranges instead (`random_scenario`: squint, rib, heights, SNR,
wobble, grid, rows, missing plates, rib side, radar, int16, a missed cycle), each run with and without a
web-depth prior over a short history (6 cycles: a user's first night), and prints the pooled rows per SNR
class. `--random-web LO HI` draws each scenario's web (advance per cycle) in [LO, HI] m instead of 0.9 m;
`--random-aligned` puts the rows' plates in columns (one bolting ring per column, x within a few cm), where
the rows' responses merge at some heights (docs/method.md section 5, eq. L1).
`--random-acquisition` also draws what the archive format leaves to its writer (`random_acquisition`: the
rail's length, PRF and carriage speed, the sampling rate, the range window, the antenna's aperture down to a
beam whose first null is at endfire, the reference point), which the other studies hold at one value.
The pooled table also counts the withheld (not ok) rows and, in brackets, those whose cycle shares a located
plate with the cycle before it at the true step (within SHARED_PLATE_TOL_M): the rest had nothing in common
with their neighbour, so no association could have linked them (a data limit, not the method's). A second
table splits the draw's rows by geometry class (`geometry_class`): staggered rows, or columns by how many rail
heights resolve their closest pair of rows in range (`rows_resolved_heights`), and short rails.

Archives are cached under WORK/<scenario>/archive (regenerated only when the scenario's parameters change).
`--reuse-detections` copies the per-pass detection cache of the earlier run whose cache was written last
(OUT/.uwbcl-cache) to the current code's cache key before running `uwbcl process`: detections depend only on
the focuser and detector, which this study does not change, so a changed association is measured in seconds
instead of refocusing every pass.
A "-2h" / "-noprior" variant reprocesses its parent's archives with the extra heights excluded (`--heights`)
or without `--web-depth`: the same data, one thing changed.
`--look-errors` also prints how far the located plates' looks (each pass's x and R_c) lie from the truth, by
kind: clean, split from a peak that held two (eq. S2), shared with a neighbour and kept (eq. L1); the
measurement behind eqs. S3 and L3.

Measured results: docs/method.md section 6.1.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime as dt
import json
import math
import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from uwbcl import batch, config
from uwbcl.archive import height_mm
from uwbcl.geometry import closest_approach_range_m
from uwbcl.records import Detection, PassRecord

C_M_S = 299_792_458.0


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    squint_deg: float = 30.0
    rib_m: float = 2.5  # horizontal distance rail -> rib
    heights_m: tuple[float, ...] = (0.2, 0.6)
    snr_db: float = 15.0  # per raw sample, relative to the strongest plate's peak echo
    wobble: float = 0.10  # carriage speed fluctuation, fraction of the nominal speed
    grid_m: float = 1.2  # nominal plate spacing along the rib
    rows_z_m: tuple[float, ...] = (0.6, 1.3)
    missing: float = 0.15  # fraction of plates missing
    side: int = -1  # boresight_y_sign
    web_m: float = 0.9  # nominal retreat per cycle
    carrier_hz: float = 4.3e9
    bandwidth_hz: float = 1.7e9
    int16: bool = False
    missed: tuple[int, ...] = ()  # cycles with no archives
    single_height: tuple[int, ...] = ()  # cycles with only their lowest height's pass
    seed: int = 0
    # the rows' plates in columns (one bolting ring per column, a few cm apart along the rib) instead of each
    # row spaced on its own
    aligned: bool = False
    # the spread of the plates' positions along the rib: each column's plates about their column (a bolting
    # ring), m; and each plate spacing about grid_m, as a fraction (0, 0: an exact grid, every row in line)
    ring_scatter_m: float = 0.03
    grid_jitter: float = 0.15
    # How the passes are acquired and written: choices the archive format leaves to the writer.
    prf_hz: float = 20.0
    speed_m_s: float = 0.25  # nominal carriage speed (the track spacing is speed / PRF)
    rail_m: float = 3.0  # rail travel
    sample_rate_hz: float = 4.0e9  # complex (I/Q) fast-time sampling rate
    window_margin_m: float = 0.4  # range window beyond the nearest and farthest scatterer seen
    aperture_m: float = 0.14  # real antenna aperture along the rail
    reference_z: str = "rows"  # the reference point's Z_r: "rows" (their mean), "zero", "rail" (mean height)
    rail_offset_m: float = 0.0  # X_r of the rail's centre: the format puts it at 0; a writer may not
    echo_scale: float = 1.0  # the echo's arbitrary linear amplitude unit (archive-format section 3)
    # A plate's size: 0 is a point; else a flat square of this side in the rib's plane, 5 x 5 in-phase points,
    # with its bolt's end BOLT_PROUD_M proud of it (docs/method.md section 6.1, "extended plates")
    plate_m: float = 0.0

    def key(self, cycles: int) -> dict:
        key = {**dataclasses.asdict(self), "cycles": cycles, "generator": 1}
        defaults = Scenario(self.name)
        # the scenarios from before these fields keep their archives
        for name in ("aligned", "ring_scatter_m", "grid_jitter", "plate_m", *ACQUISITION):
            if getattr(self, name) == getattr(defaults, name):
                del key[name]
        return key


# The parent scenarios (archives generated) and the variants that reprocess a parent's archives.
SCENARIOS = [
    Scenario("base", missed=(9, 17, 18)),
    Scenario("wide-45deg-4.5m", squint_deg=45.0, rib_m=4.5, heights_m=(0.2, 0.45, 0.7), snr_db=10.0, side=+1,
             grid_m=1.3, missed=(12,), seed=1),
    Scenario("near-15deg-1.5m", squint_deg=15.0, rib_m=1.5, snr_db=20.0, grid_m=1.0, rows_z_m=(0.5, 1.1, 1.7),
             wobble=0.05, seed=2, single_height=(20,)),
    Scenario("snr5-wobble15", squint_deg=25.0, rib_m=3.0, snr_db=5.0, wobble=0.15, grid_m=1.4, seed=3,
             missed=(15, 16, 17)),
    Scenario("dense-3h", squint_deg=35.0, rib_m=2.0, heights_m=(0.2, 0.45, 0.7), snr_db=10.0, grid_m=1.0,
             rows_z_m=(0.5, 1.1, 1.7), missing=0.2, side=+1, carrier_hz=4.0e9, bandwidth_hz=1.4e9, int16=True,
             seed=4, missed=(10,)),
    # The same grid in bolting rings (each column's plates within a few cm in x), as mines bolt: a column's
    # plates lie within a range cell of each other at some heights (eq. L1).
    Scenario("dense-3h-columns", squint_deg=35.0, rib_m=2.0, heights_m=(0.2, 0.45, 0.7), snr_db=10.0,
             grid_m=1.0, rows_z_m=(0.5, 1.1, 1.7), missing=0.2, side=+1, carrier_hz=4.0e9, bandwidth_hz=1.4e9,
             int16=True, seed=6, missed=(10,), aligned=True),
    # And as an exact grid: every column at k x 1.0 m, its plates in line (a generator's regular grid). The
    # row above then gives the right retreat exactly (eq. M3a), and a column further fits as well but for
    # the missing plates and the field of view's ends.
    Scenario("dense-3h-regular", squint_deg=35.0, rib_m=2.0, heights_m=(0.2, 0.45, 0.7), snr_db=10.0,
             grid_m=1.0, rows_z_m=(0.5, 1.1, 1.7), missing=0.2, side=+1, carrier_hz=4.0e9, bandwidth_hz=1.4e9,
             int16=True, seed=7, missed=(10,), aligned=True, ring_scatter_m=0.0, grid_jitter=0.0),
    Scenario("four-heights-snr10", squint_deg=20.0, rib_m=3.5, heights_m=(0.15, 0.35, 0.55, 0.75),
             snr_db=10.0, wobble=0.15, grid_m=1.5, seed=5, missed=(7, 8)),
    # Plates as they are: 150 mm flat squares with a bolt's end, whose apparent point moves with the aspect
    # (docs/method.md section 6.1); and the same world, motion and noise with point plates, its control.
    Scenario("extended-plates", rib_m=2.4, snr_db=10.0, web_m=0.8, seed=8, plate_m=0.15),
    Scenario("extended-plates-point", rib_m=2.4, snr_db=10.0, web_m=0.8, seed=8),
]
VARIANTS = {  # name: (parent, heights to keep or None, web-depth prior?)
    "dense-2h": ("dense-3h", (0.2, 0.7), True),
    "dense-3h-noprior": ("dense-3h", None, False),
    "base-noprior": ("base", None, False),
    "four-heights-2h": ("four-heights-snr10", (0.15, 0.75), True),
    "dense-2h-columns": ("dense-3h-columns", (0.2, 0.7), True),
    "dense-3h-columns-noprior": ("dense-3h-columns", None, False),
    "dense-2h-regular": ("dense-3h-regular", (0.2, 0.7), True),
    "dense-3h-regular-noprior": ("dense-3h-regular", None, False),
}
QUICK = ["base", "dense-3h", "dense-2h", "dense-3h-noprior"]
REPLICA_SEED_STEP = 1000  # `--replicas`: realisation k of a scenario has seed + k x this
DRIFT_LIMIT_MM = 10.0  # issue 14: cumulative drift over 40 cycles
ACQUISITION = ("prf_hz", "speed_m_s", "rail_m", "sample_rate_hz", "window_margin_m", "aperture_m",
               "reference_z", "rail_offset_m", "echo_scale")
PLATE_POINTS = 5  # an extended plate's points along each side
BOLT_PROUD_M, BOLT_AMPLITUDE = 0.03, 0.3  # its bolt's end: how far proud of the plate, amplitude re the plate
RADARS = ((4.3e9, 1.7e9), (4.0e9, 1.4e9), (3.95e9, 1.2e9))  # (carrier, -10 dB bandwidth) of random scenarios


def random_scenario(seed: int, cycles: int, web_range_m: tuple[float, float] | None = None,
                    aligned: bool = False, acquisition: bool = False) -> Scenario:
    """A scenario drawn from issue 14's ranges (`--random`): squint 15-45 deg, rib 1.5-4.5 m, 2-4 heights,
    SNR 5/10/15/20 dB, wobble up to 15 %, a 1.0-1.5 m grid in 2 or 3 rows with 10-25 % of the plates missing,
    either rib side, one of three radars, int16 archives in 30 %, one missed cycle in half of them; the web
    (advance per cycle) 0.9 m, or uniform in `web_range_m` (`--random-web`: drawn last, so the other draws
    of a seed stay those of the fixed-web study); `aligned` (`--random-aligned`) puts the rows' plates in
    columns, the other draws unchanged."""
    r = random.Random(seed)
    heights = np.linspace(r.uniform(0.1, 0.25), r.uniform(0.55, 0.8), r.choice([2, 2, 3, 3, 4]))
    rows = (0.6, 1.3) if r.choice([2, 3]) == 2 else (0.5, 1.1, 1.7)
    carrier, bandwidth = r.choice(RADARS)
    missed = tuple(sorted(r.sample(range(2, cycles), 1))) if r.random() < 0.5 else ()
    scenario = Scenario(f"r{seed}", squint_deg=r.uniform(15, 45), rib_m=r.uniform(1.5, 4.5),
                    heights_m=tuple(round(float(h), 3) for h in heights),
                    snr_db=r.choice([5.0, 10.0, 15.0, 20.0]), wobble=r.uniform(0.0, 0.15),
                    grid_m=r.uniform(1.0, 1.5), rows_z_m=rows, missing=r.uniform(0.1, 0.25),
                    side=r.choice([-1, 1]), carrier_hz=carrier, bandwidth_hz=bandwidth,
                    int16=r.random() < 0.3, missed=missed, seed=seed,
                    web_m=round(r.uniform(*web_range_m), 3) if web_range_m else 0.9, aligned=aligned)
    if not acquisition:
        return scenario
    acquired = random_acquisition(random.Random(f"{seed}-acquisition"), bandwidth)
    return dataclasses.replace(scenario, **acquired)


def random_acquisition(r: random.Random, bandwidth_hz: float) -> dict:
    """The writer's choices the archive format leaves free (`--random-acquisition`): a rail 1.5-4 m long,
    a PRF of 10-50 Hz and a track spacing of 4-25 mm (the carriage speed follows), a complex sampling rate of
    1.5-3 times the -10 dB bandwidth, a range window 0.2-1.5 m beyond the scatterers seen, an antenna aperture
    of 0.05-0.20 m (a broad beam's first null at endfire, C6b) and the reference point at the rows' mean
    height, at Z_r = 0 or at the rails' mean height. Drawn from their own stream, so a seed's scene is the one
    it has without them."""
    prf = r.choice([10.0, 20.0, 40.0, 50.0])
    return {"rail_m": round(r.uniform(1.5, 4.0), 2), "prf_hz": prf,
            "speed_m_s": round(min(0.5, max(0.05, prf * r.uniform(0.004, 0.025))), 3),
            "sample_rate_hz": round(r.uniform(1.5, 3.0) * bandwidth_hz, -6),
            "window_margin_m": round(r.uniform(0.2, 1.5), 2),
            "aperture_m": r.choice([0.05, 0.08, 0.10, 0.14, 0.20]),
            "reference_z": r.choice(["rows", "zero", "rail"])}


# ----------------------------------------------------------------------------------------------- the scene
@dataclasses.dataclass
class Truth:
    rig_m: np.ndarray  # (cycles, 3) rig position in the roadway frame; advance = rig' - rig


def scene(s: Scenario, cycles: int):
    """Plates and clutter in the roadway frame (rib surface at Y = 0), and the rig's positions per cycle."""
    rng = np.random.default_rng([s.seed, 1])
    x_end = s.web_m * 1.15 * cycles + 20.0
    plates, amps = [], []
    if s.aligned:
        columns = [-10.0 + rng.uniform(0, s.grid_m)]
        while columns[-1] < x_end:
            columns.append(columns[-1] + s.grid_m * rng.uniform(1.0 - s.grid_jitter, 1.0 + s.grid_jitter))
        for x in columns:
            for z in s.rows_z_m:
                if rng.uniform() >= s.missing:
                    plates.append((x + rng.normal(0, s.ring_scatter_m), rng.normal(0, 0.02),
                                   z + rng.normal(0, 0.04)))
                    amps.append(rng.uniform(0.6, 1.0))
    else:
        for z in s.rows_z_m:
            x = -10.0 + rng.uniform(0, s.grid_m)
            while x < x_end:
                if rng.uniform() >= s.missing:
                    plates.append((x, rng.normal(0, 0.02), z + rng.normal(0, 0.04)))
                    amps.append(rng.uniform(0.6, 1.0))
                x += s.grid_m * rng.uniform(1.0 - s.grid_jitter, 1.0 + s.grid_jitter)
    n_clutter = int(8 * (x_end + 10))
    clutter = np.column_stack([rng.uniform(-10, x_end, n_clutter), rng.normal(0, 0.03, n_clutter),
                               rng.uniform(0.0, 2.2, n_clutter)])
    clutter_amp = rng.uniform(0.01, 0.05, n_clutter)
    # Motion: web with variation, creep drift + noise + rare jumps, a few mm of floor undulation.
    steps = np.zeros((cycles, 3))
    steps[1:, 0] = np.clip(s.web_m + rng.normal(0, 0.04, cycles - 1), s.web_m - 0.1, s.web_m + 0.1)
    drift = rng.uniform(-0.005, 0.005)
    steps[1:, 1] = drift + rng.normal(0, 0.002, cycles - 1)
    jumps = rng.uniform(size=cycles - 1) < 0.06
    steps[1:, 1] += jumps * rng.choice([-1, 1], cycles - 1) * rng.uniform(0.03, 0.08, cycles - 1)
    steps[1:, 2] = rng.normal(0, 0.003, cycles - 1)
    rig = np.cumsum(steps, axis=0) + np.array([0.0, -s.side * s.rib_m, 0.0])
    return np.array(plates), np.array(amps), clutter, clutter_amp, Truth(rig)


def plate_scatterers(s: Scenario, plates_m: np.ndarray, amps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plates as scatterers (n, 3), (n,): their centres when `s.plate_m` is 0, else each a flat square of
    PLATE_POINTS x PLATE_POINTS in-phase points over the plate in the rib's plane (x, z), together the plate's
    amplitude, and its bolt's end BOLT_PROUD_M towards the roadway at BOLT_AMPLITUDE of it."""
    if s.plate_m <= 0 or not len(plates_m):
        return plates_m, amps
    u = np.linspace(-s.plate_m / 2, s.plate_m / 2, PLATE_POINTS)
    grid = np.array([(dx, 0.0, dz) for dx in u for dz in u])
    bolt = np.array([[0.0, -s.side * BOLT_PROUD_M, 0.0]])
    offsets = np.vstack([grid, bolt])
    weights = np.concatenate([np.full(len(grid), 1.0 / len(grid)), [BOLT_AMPLITUDE]])
    points = (plates_m[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
    return points, (amps[:, None] * weights[None, :]).ravel()


def pass_echo(s: Scenario, rng, scat_m: np.ndarray, amp: np.ndarray, height_m: float, decreasing: bool):
    """Complex baseband echo of one pass (archive-format section 2), positions and times per pulse."""
    prf, v0, rail = s.prf_hz, s.speed_m_s, s.rail_m
    lam = C_M_S / s.carrier_hz
    # Carriage speed: a slow hunting oscillation plus a random walk, positions logged per pulse.
    n_max = int(rail / (v0 * (1 - s.wobble)) * prf) + 2
    t = np.arange(n_max) / prf
    speed = v0 * (1 + s.wobble * (0.7 * np.sin(2 * np.pi * t / rng.uniform(3, 8) + rng.uniform(0, 6.3))
                                  + 0.3 * np.clip(np.cumsum(rng.normal(0, 0.15, n_max)), -1, 1)))
    travelled = np.concatenate([[0.0], np.cumsum(speed[:-1] / prf)])
    n = int(np.searchsorted(travelled, rail, side="right"))
    t, travelled = t[:n], travelled[:n]
    pos = s.rail_offset_m + ((rail / 2 - travelled) if decreasing else (travelled - rail / 2))
    # Antenna: boresight (sin th, s cos th, 0); two-way pattern of a uniform aperture D in azimuth.
    th = math.radians(s.squint_deg)
    bore = np.array([math.sin(th), s.side * math.cos(th), 0.0])
    rel = scat_m[None, :, :] - np.column_stack([pos, np.zeros(n), np.full(n, height_m)])[:, None, :]
    rng_m = np.linalg.norm(rel, axis=2)
    horiz = np.linalg.norm(rel[:, :, :2], axis=2)
    sin_off = np.clip((bore[0] * rel[:, :, 1] - bore[1] * rel[:, :, 0]) / horiz, -1, 1)
    front = (rel[:, :, :2] @ bore[:2]) > 0
    # the real aperture's two-way pattern, times cos(elevation)
    gain = np.where(front, np.sinc(s.aperture_m * sin_off / lam) ** 2, 0.0) * (horiz / rng_m)
    a = amp[None, :] * gain / rng_m**2
    seen = a.max(axis=0) > 0.02 * a.max()
    r_lo, r_hi = rng_m[:, seen].min() - s.window_margin_m, rng_m[:, seen].max() + s.window_margin_m
    fs = s.sample_rate_hz
    m = int(math.ceil((r_hi - r_lo) * 2 / C_M_S * fs / 32)) * 32
    t0 = 2 * r_lo / C_M_S
    tn = t0 + np.arange(m) / fs
    sigma = math.sqrt(math.log(10)) / (math.pi * s.bandwidth_hz)
    echo = np.zeros((n, m), complex)
    strong = a.max(axis=0) > 1e-4 * a.max()
    for i in np.flatnonzero(strong):
        delay = 2 * rng_m[:, i] / C_M_S
        echo += (a[:, i] * np.exp(-4j * np.pi * s.carrier_hz * rng_m[:, i] / C_M_S))[:, None] * \
            np.exp(-((tn[None, :] - delay[:, None]) ** 2) / (2 * sigma**2))
    peak = a.max()  # the strongest scatterer: a point plate (clutter is 20x weaker), an extended plate's bolt
    noise = peak * 10 ** (-s.snr_db / 20)
    echo += noise / math.sqrt(2) * (rng.standard_normal(echo.shape) + 1j * rng.standard_normal(echo.shape))
    return t, pos, s.echo_scale * echo, t0, fs, bore


def write_archive(path: Path, s: Scenario, cycle: int, height_m: float, when: dt.datetime, t, pos, echo, t0,
                  fs, ref_m) -> None:
    """One pass as docs/archive-format.md section 7, published by rename (section 1)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.partial"
    pass_id = f"rig-{s.name}-c{cycle:06d}-h{round(height_m * 1000):04d}"
    with h5py.File(tmp, "w", libver=("v110", "v110")) as f:
        f.attrs.update({"format": "uwbcl-scan", "format_version": np.int64(1), "rig_id": f"rig-{s.name}",
                        "cycle": np.int64(cycle), "pass_id": pass_id,
                        "pass_start_time": when.strftime("%Y-%m-%dT%H:%M:%SZ"),
                        "created_by": "scripts/availability_study.py"})
        f.create_group("radar").attrs.update({
            "carrier_frequency_hz": s.carrier_hz, "bandwidth_hz": s.bandwidth_hz,
            "bandwidth_definition": "-10 dB",
            "pulse_shape": "gaussian", "sample_rate_hz": fs, "pulse_repetition_frequency_hz": s.prf_hz,
            "antenna_aperture_m": s.aperture_m, "range_window_start_s": t0,
            "samples_per_pulse": np.int64(echo.shape[1])})
        f.create_group("geometry").attrs.update({
            "height_m": height_m, "rotation_table_angle_deg": s.squint_deg,
            "reference_point_m": np.asarray(ref_m),
            "boresight_y_sign": np.int64(s.side)})
        f.create_dataset("pulses/time_s", data=t).attrs["units"] = "s"
        f.create_dataset("pulses/position_m", data=pos).attrs["units"] = "m"
        if s.int16:
            scale = float(np.abs(np.stack([echo.real, echo.imag])).max()) / 32767
            iq = np.round(np.stack([echo.real, echo.imag], axis=-1) / scale).astype(np.int16)
            ds = f.create_dataset("echo", data=iq, chunks=True, compression="gzip")
            ds.attrs.update({"units": "arb", "layout": "int16_iq", "scale": scale})
        else:
            ds = f.create_dataset("echo", data=echo.astype(np.complex64), chunks=True, compression="gzip")
            ds.attrs.update({"units": "arb", "layout": "complex", "scale": 1.0})
    os.replace(tmp, path)


def generate(s: Scenario, cycles: int, root: Path) -> Path:
    """Archives of one scenario under root/archive (cached) and root/truth.json."""
    arch, stamp = root / "archive", root / "scenario.json"
    wanted = json.loads(json.dumps(s.key(cycles)))  # tuples as lists, as read back
    if arch.is_dir() and stamp.exists() and json.loads(stamp.read_text()) == wanted:
        return arch
    shutil.rmtree(arch, ignore_errors=True)
    plates, amps, clutter, clutter_amp, truth = scene(s, cycles)
    plates, amps = plate_scatterers(s, plates, amps)
    scat = np.vstack([plates, clutter])
    amp = np.concatenate([amps, clutter_amp])
    start = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.timezone.utc)
    th = math.radians(s.squint_deg)
    t_start = time.perf_counter()
    for c in range(cycles):
        if c in s.missed:
            continue
        radar_frame = scat - truth.rig_m[c]
        near = np.abs(radar_frame[:, 0] - s.rail_offset_m - s.rib_m * math.tan(th)) < 8.0
        heights = s.heights_m[:1] if c in s.single_height else s.heights_m
        for k, h in enumerate(heights):
            rng = np.random.default_rng([s.seed, 2, c, k])
            t, pos, echo, t0, fs, _ = pass_echo(s, rng, radar_frame[near], amp[near], h, (c + k) % 2 == 1)
            ref_z = {"rows": float(np.mean(s.rows_z_m)), "zero": 0.0, "rail": float(np.mean(s.heights_m))}
            ref = (s.rail_offset_m + s.rib_m * math.tan(th), s.side * s.rib_m, ref_z[s.reference_z])
            when = start + dt.timedelta(minutes=40 * c, seconds=40 * k)
            name = f"rig-{s.name}_c{c:06d}_h{round(h * 1000):04d}.h5"
            write_archive(arch / when.strftime("%Y-%m-%d") / name, s, c, h, when, t, pos, echo, t0, fs, ref)
    (root / "truth.json").write_text(json.dumps({"rig_m": truth.rig_m.tolist()}) + "\n")
    stamp.write_text(json.dumps(s.key(cycles)) + "\n")
    print(f"  generated {s.name}: {cycles} cycles in {time.perf_counter() - t_start:.0f} s", flush=True)
    return arch


# ----------------------------------------------------------------------------------------------- process
def run_process(arch: Path, out: Path, s: Scenario, heights, prior: bool, jobs: int, reuse: Path | None,
                config: Path | None, backend: str = "numpy") -> float:
    out.mkdir(parents=True, exist_ok=True)
    if reuse is not None:
        copy_detections(reuse, out, config, backend)
    cmd = [sys.executable, "-m", "uwbcl.cli", "process", str(arch), "--out", str(out), "--backend", backend,
           "--jobs", str(jobs), "--no-progress"]
    if prior:
        cmd += ["--web-depth", str(s.web_m)]
    if heights:
        cmd += ["--heights", *map(str, heights)]
    if config:
        cmd += ["--config", str(config)]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    t = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if r.returncode not in (0, 1) or not (out / "displacements.csv").exists():  # 1: some inputs had problems
        raise SystemExit(f"uwbcl process failed ({r.returncode}) on {arch}:\n{r.stderr[-3000:]}")
    return time.perf_counter() - t


def share_cache(src_out: Path, out: Path, backend: str = "numpy") -> None:
    """A variant reprocessing its parent's archives: the parent's detections under the same (current) cache
    key are exactly what `uwbcl process` would compute again."""
    settings = config.override(config.SiteConfig(), backend=backend).processing_settings()
    key = batch.settings_key(settings)
    src, dst = src_out / batch.CACHE_DIR / key, out / batch.CACHE_DIR / key
    if src.is_dir() and not dst.is_dir():
        shutil.copytree(src, dst)


def newest_run(root: Path) -> Path | None:
    """The run under root whose detection cache was written last (the current detector's), or None."""
    runs = [p for p in root.glob("*/") if (p / batch.CACHE_DIR).is_dir()]
    return max(runs, key=lambda p: ((p / batch.CACHE_DIR).stat().st_mtime, p.name), default=None)


def copy_detections(src_out: Path, out: Path, site: Path | None = None, backend: str = "numpy") -> None:
    """Detections cached by an earlier run (any code version) -> the cache key of the current code and of the
    settings `uwbcl process` runs with (the site file `site`, when given: its detection settings key the
    cache too)."""
    cfg = config.load_config(site) if site is not None else config.SiteConfig()
    settings = config.override(cfg, backend=backend).processing_settings()
    dst = out / batch.CACHE_DIR / batch.settings_key(settings)
    if dst.is_dir():
        return
    srcs = sorted((src_out / batch.CACHE_DIR).glob("*/"), key=lambda p: p.stat().st_mtime)
    if not srcs:
        return
    dst.mkdir(parents=True, exist_ok=True)
    for src in srcs:  # newest last: wins
        for f in src.glob("*.json"):
            shutil.copyfile(f, dst / f.name)


# ----------------------------------------------------------------------------------------------- scoring
# A located plate of one cycle "is" a plate of another when, moved by the true step, it lies within this (m):
# under half the closest plate spacing the study draws (rows 0.6 m apart), over the worst location errors.
SHARED_PLATE_TOL_M = 0.25


def located_plates(out: Path) -> dict[int, np.ndarray]:
    """Each cycle's located plates (n, 3) in the rig frame, from targets.csv."""
    plates: dict[int, list] = {}
    path = out / "targets.csv"
    if path.exists():
        with path.open() as f:
            for r in csv.DictReader(f):
                plates.setdefault(int(r["cycle"]), []).append([float(r[k]) for k in ("x_m", "y_m", "z_m")])
    return {c: np.array(p) for c, p in plates.items()}


def shared_plates(plates: dict[int, np.ndarray], c0: int, c: int, rig_m: np.ndarray) -> int:
    """How many of cycle c0's located plates cycle c located too, at the true step (P' = P - step)."""
    a, b = plates.get(c0), plates.get(c)
    if a is None or b is None or not len(a) or not len(b):
        return 0
    moved = a - (rig_m[c] - rig_m[c0])
    return int((np.linalg.norm(moved[:, None, :] - b[None, :, :], axis=2).min(axis=1)
                < SHARED_PLATE_TOL_M).sum())


def score(out: Path, rig_m: np.ndarray) -> dict:
    with (out / "displacements.csv").open() as f:
        rows = list(csv.DictReader(f))
    ok = [r for r in rows if r["status"] == "ok"]
    err, cover, gross = [], [], 0
    bound_cols = ("retreat_bound_m", "creep_bound_m") if rows and "retreat_bound_m" in rows[0] else None
    for r in ok:
        c, c0 = int(r["cycle"]), int(r["from_cycle"])
        true = rig_m[c] - rig_m[c0]
        e = np.array([float(r["retreat_m"]) - true[0], float(r["creep_m"]) - true[1]])
        err.append(e)
        gross += bool(np.max(np.abs(e)) > 0.05)
        if bound_cols:
            b = np.array([float(r[k]) for k in bound_cols])
            cover.append(bool(np.all(np.abs(e) <= 3 * b)))
    # Cumulative drift: against the truth from the first cycle of each row's chain.
    chain_start: dict[int, int] = {}
    drift, cum_cover = np.zeros(2), []
    for r in rows:
        ch = int(r["chain"])
        if ch not in chain_start:  # chain 0 counts from its first row's from_cycle (docs/outputs.md)
            chain_start[ch] = int(r["from_cycle"]) if ch == 0 else int(r["cycle"])
        cum = np.array([float(r["cumulative_retreat_m"]), float(r["cumulative_creep_m"])])
        if np.all(np.isfinite(cum)):
            c = int(r["cycle"])
            e = cum - (rig_m[c] - rig_m[chain_start[ch]])[:2]
            drift = np.maximum(drift, np.abs(e))
            if "cumulative_retreat_bound_m" in r:
                b = np.array([float(r["cumulative_retreat_bound_m"]), float(r["cumulative_creep_bound_m"])])
                cum_cover.append(bool(np.all(np.abs(e) <= 3 * b)))
    # Withheld rows whose cycle shares a located plate with the cycle before it (at the true step): the data
    # could have linked them. The others had nothing in common with their neighbour: no association can.
    plates = located_plates(out)
    withheld_shared = 0
    for r in rows:
        c = int(r["cycle"])
        withheld_shared += r["status"] != "ok" and shared_plates(plates, int(r["from_cycle"]), c, rig_m) > 0
    err = np.array(err).reshape(-1, 2)
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    return {
        "rows": len(rows), "ok": len(ok), "ok_pct": 100.0 * len(ok) / max(len(rows), 1),
        "rms_mm": (1e3 * np.sqrt(np.mean(err**2, axis=0))).tolist() if len(err) else [math.nan] * 2,
        "max_mm": (1e3 * np.max(np.abs(err), axis=0)).tolist() if len(err) else [math.nan] * 2,
        "cover": (100.0 * np.mean(cover)) if cover else math.nan,
        "cum_cover": (100.0 * np.mean(cum_cover)) if cum_cover else math.nan,
        "gross": gross, "beyond": len(cover) - int(sum(cover)), "withheld_shared": withheld_shared,
        "drift_mm": (1e3 * drift).tolist(), "chains": len(chain_start), "statuses": statuses,
        "statuses_in_order": [r["status"] for r in rows],
    }


LOOK_KINDS = ("clean", "split", "shared")


def look_kind(plate, height_m: float, det: Detection) -> str:
    """A located plate's look: "split" from a peak that held two (eq. S2), "shared" with a neighbour (eq. L1)
    and kept in the fit, else "clean"."""
    if not math.isnan(det.split_separation_m):
        return "split"
    return "shared" if height_m in plate.shared_heights_m else "clean"


def look_errors(s: Scenario, out: Path, cycles: int, site: Path | None = None
                ) -> list[tuple[str, float, float]]:
    """(kind, x error m, R_c error m) of every look of every plate that the run `out` located, from its
    detection cache (the key written last, as `newest_run` picks a run: the current detector's) read and
    located as `uwbcl process` does (`batch.PassCache`, `batch.locate_records`) with the run's settings,
    against the nearest true plate (in x and in R_c at the look's rail height): the measurement behind eqs. S3
    and L3 and the kept shared looks of docs/method.md section 6.1 (`--look-errors`)."""
    cfg = config.load_config(site) if site is not None else config.SiteConfig()
    settings = cfg.processing_settings()
    plates, *_, truth = scene(s, cycles)
    keys = sorted((out / batch.CACHE_DIR).glob("*/"), key=lambda p: (p.stat().st_mtime, p.name))
    cache = batch.PassCache(out, settings)
    cache.dir = keys[-1] if keys else cache.dir
    by_cycle: dict[int, dict[int, PassRecord]] = {}
    for f in sorted(cache.dir.glob("*.json")) if keys else ():
        rec = cache.get(f.name, f.stem)  # entries are named by their archive's sha256
        if rec is not None:
            by_cycle.setdefault(rec.cycle, {})[height_mm(rec.height_m)] = rec
    errors = []
    for c, recs in sorted(by_cycle.items()):
        if len(recs) < 2 or c >= len(truth.rig_m):
            continue
        cyc = batch.locate_records(recs, settings.detection, settings.association.range_sigma_m)
        p_true = plates - truth.rig_m[c]
        for plate in cyc.plates:
            for h, d in plate.looks:
                rc = np.hypot(p_true[:, 1], p_true[:, 2] - h)
                k = int(np.argmin(np.hypot(p_true[:, 0] - d.x_m, rc - d.rc_m)))
                errors.append((look_kind(plate, h, d), d.x_m - p_true[k, 0], d.rc_m - rc[k]))
    return errors


LOOK_ERROR_CUT_M = 0.06  # errors beyond this are another plate's or clutter's peak, not a look's precision


def look_error_table(errors: list[tuple[str, float, float]]) -> str:
    """Per look kind: count, sigma from the median |error| (1.4826 x), RMS of the errors under
    LOOK_ERROR_CUT_M, the 90th percentile (mm, along track / in range)."""
    cut_mm = 1e3 * LOOK_ERROR_CUT_M
    lines = [f"{'look':8s} {'n':>6s}  sigma(MAD) x/R_c mm  RMS<{cut_mm:.0f}mm x/R_c   p90 x/R_c mm"]
    for kind in LOOK_KINDS:
        e = np.abs(np.array([(x, r) for k, x, r in errors if k == kind]).reshape(-1, 2)) * 1e3
        if not len(e):
            continue
        mad = 1.4826 * np.median(e, axis=0)
        rms = [math.sqrt(np.mean(a[a < cut_mm] ** 2)) if (a < cut_mm).any() else math.nan for a in e.T]
        p90 = np.percentile(e, 90, axis=0)
        lines.append(f"{kind:8s} {len(e):6d}  {mad[0]:8.1f}/{mad[1]:<8.1f}  {rms[0]:9.1f}/{rms[1]:<9.1f} "
                     f"{p90[0]:6.1f}/{p90[1]:<6.1f}")
    return "\n".join(lines)


def table(results: dict) -> str:
    head = (f"{'scenario':22s} {'rows':>4s} {'ok%':>6s} {'RMS x/y mm':>11s} {'max x/y mm':>11s} "
            f"{'cover%':>6s} "
            f"{'gross':>5s} {'drift x/y mm':>13s} {'cum cov%':>8s} chains  flagged")
    lines = [head]
    for name, r in results.items():
        flagged = ", ".join(f"{k} {v}" for k, v in sorted(r["statuses"].items()) if k != "ok")
        lines.append(f"{name:22s} {r['rows']:4d} {r['ok_pct']:6.1f} "
                     f"{r['rms_mm'][0]:5.1f}/{r['rms_mm'][1]:<5.1f} "
                     f"{r['max_mm'][0]:5.1f}/{r['max_mm'][1]:<5.1f} {r['cover']:6.1f} {r['gross']:5d} "
                     f"{r['drift_mm'][0]:6.1f}/{r['drift_mm'][1]:<6.1f} {r['cum_cover']:8.1f} "
                     f"{r['chains']:6d}  "
                     f"{flagged}")
    return "\n".join(lines)


def replica(s: Scenario, k: int) -> Scenario:
    """Realisation k of a scenario: k = 0 is itself; k > 0 the same parameters with seed
    s.seed + REPLICA_SEED_STEP k (another plate layout, motion and noise), named after that seed."""
    if k == 0:
        return s
    seed = s.seed + REPLICA_SEED_STEP * k
    return dataclasses.replace(s, name=f"{s.name}-seed{seed}", seed=seed)


def replica_name(name: str, seed: int, k: int) -> str:
    """The output label of realisation k of scenario or variant `name` (its parent's seed `seed`)."""
    return name if k == 0 else f"{name}-seed{seed}"


def replica_summary(results: dict, names: list[str]) -> str:
    """Per scenario over its realisations (`replica_name`: itself and its -seed labels): the cumulative
    drift's median and largest (retreat / creep, mm), how many realisations drift more than DRIFT_LIMIT_MM on
    either axis, and the pooled ok %. The drift is the largest excursion of a random walk (one per
    realisation): one realisation says little."""
    lines = [f"{'scenario':26s} {'n':>2s} {'drift median x/y mm':>20s} {'largest x/y mm':>15s} "
             f"{'> ' + str(DRIFT_LIMIT_MM) + ' mm':>8s} {'ok%':>6s}"]
    for name in names:
        runs = [r for label, r in results.items() if label == name or label.startswith(name + "-seed")]
        drift = np.array([r["drift_mm"] for r in runs]).reshape(-1, 2)
        med, big = np.median(drift, axis=0), np.max(drift, axis=0)
        over = int(np.sum(np.any(drift > DRIFT_LIMIT_MM, axis=1)))
        ok_pct = 100.0 * sum(r["ok"] for r in runs) / max(sum(r["rows"] for r in runs), 1)
        lines.append(f"{name:26s} {len(runs):2d} {med[0]:9.1f}/{med[1]:<10.1f} {big[0]:7.1f}/{big[1]:<7.1f} "
                     f"{over:8d} {ok_pct:6.1f}")
    return "\n".join(lines)


SHORT_RAIL_M = 2.1  # the random draws' class of short rails (docs/method.md section 6.1)


def rows_resolved_heights(s: Scenario) -> int:
    """How many rail heights at least resolve the closest pair of the scenario's bolt rows in range: the
    fewest, over pairs of rows, of the heights at which the pair's closest-approach ranges (plates in one
    column on the rib, eq. 20) differ by at least a range resolution c / 2B. Plates in one column share their
    x, so only range tells them apart: a pair resolved at no height is one peak at every height, located as
    neither (docs/method.md section 6.1)."""
    resolution_m = C_M_S / (2.0 * s.bandwidth_hz)
    fewest = len(s.heights_m)
    for a, za in enumerate(s.rows_z_m):
        for zb in s.rows_z_m[a + 1:]:
            fewest = min(fewest, sum(abs(float(closest_approach_range_m((0.0, s.rib_m, za), h)
                                               - closest_approach_range_m((0.0, s.rib_m, zb), h)))
                                     >= resolution_m for h in s.heights_m))
    return fewest


def geometry_class(s: Scenario) -> str:
    """A random scenario's class for `class_summary`: staggered rows or columns (by `rows_resolved_heights`),
    and the rail's length against SHORT_RAIL_M."""
    if s.aligned:
        n = rows_resolved_heights(s)
        rows = f"columns, resolved at {'>= 2' if n >= 2 else n} h"
    else:
        rows = "rows staggered"
    return f"{rows}, rail {'<' if s.rail_m < SHORT_RAIL_M else '>='} {SHORT_RAIL_M} m"


def class_summary(results: dict, snr_db: dict, classes: dict) -> str:
    """Rows and % ok with / without a prior per geometry class (`geometry_class`, keyed by scenario name) and
    SNR class: where the draw's withheld rows lie."""
    lines = [f"{'geometry class':40s} {'SNR':>7s} {'scen':>4s} {'rows':>4s} {'ok% prior / no prior':>21s}"]
    for cls in sorted(set(classes.values())):
        for label, keep in (("10+ dB", lambda v: v >= 10.0), ("5 dB", lambda v: v < 10.0)):
            names = [n for n, c in classes.items() if c == cls and keep(snr_db.get(n, math.nan))]
            if not names:
                continue
            pct = []
            for suffix in ("", "-noprior"):
                runs = [results[n + suffix] for n in names if n + suffix in results]
                pct.append(100.0 * sum(r["ok"] for r in runs) / max(sum(r["rows"] for r in runs), 1))
            rows = sum(results[n]["rows"] for n in names)
            lines.append(f"{cls:40s} {label:>7s} {len(names):4d} {rows:4d} {pct[0]:10.1f} / {pct[1]:<8.1f}")
    return "\n".join(lines)


def summary(results: dict, snr_db: dict) -> str:
    """Pooled over scenarios, per SNR class and with / without a prior: rows, % ok, ok rows beyond 3 x their
    bound, gross errors, RMS of the ok rows (retreat / creep, mm), and the withheld rows whose cycle shares
    a located plate with the one before it ("shared": the others no association could have linked)."""
    lines = [f"{'class':22s} {'scen':>4s} {'rows':>4s} {'ok%':>6s} {'beyond 3x':>9s} {'gross':>5s} "
             f"{'RMS x/y mm':>11s} {'withheld (shared)':>17s}"]
    for label, keep in (("SNR >= 10 dB", lambda v: v >= 10.0), ("SNR 5 dB", lambda v: v < 10.0)):
        for prior in (True, False):
            names = [n for n in results if keep(snr_db[n]) and n.endswith("-noprior") != prior]
            if not names:
                continue
            ok = sum(results[n]["ok"] for n in names)
            rows = sum(results[n]["rows"] for n in names)
            sq = sum(results[n]["ok"] * np.array(results[n]["rms_mm"]) ** 2
                     for n in names if results[n]["ok"])
            rms = np.sqrt(sq / ok) if ok else np.full(2, math.nan)
            lines.append(f"{label + (', prior' if prior else ', no prior'):22s} {len(names):4d} {rows:4d} "
                         f"{100.0 * ok / max(rows, 1):6.1f} {sum(results[n]['beyond'] for n in names):9d} "
                         f"{sum(results[n]['gross'] for n in names):5d} {rms[0]:5.1f}/{rms[1]:<5.1f} "
                         f"{rows - ok:8d} ({sum(results[n]['withheld_shared'] for n in names)})")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--cycles", type=int, default=None, help="cycles per scenario (default 41, quick 6)")
    ap.add_argument("--quick", action="store_true",
                    help="CI size: 6 cycles, the base and dense scenarios and the dense variants")
    ap.add_argument("--only", nargs="+", help="scenario names (with --random: r<seed>)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--reuse-detections", action="store_true",
                    help="reuse the detections of the previous run in WORK (association changes only), "
                         "whichever backend computed them")
    ap.add_argument("--config", type=Path, default=None, help="site configuration passed to uwbcl process")
    ap.add_argument("--backend", choices=("numpy", "opencl"), default="numpy",
                    help="uwbcl process's backend (default numpy, the float64 reference; opencl is what "
                         "`uwbcl process` runs by default)")
    ap.add_argument("--tag", default="out", help="output directory name per scenario (default: out)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--replicas", type=int, default=0, metavar="N",
                    help="also run N more realisations of each named scenario (`replica`: the same "
                         "parameters, another seed) and print the spread of their drift")
    ap.add_argument("--random", type=int, default=0, metavar="N",
                    help="instead: N scenarios drawn from the issue's ranges (`random_scenario`), each "
                         "with and without a prior (default 6 cycles each)")
    ap.add_argument("--random-seed", type=int, default=300, help="seed of the first random scenario")
    ap.add_argument("--random-aligned", action="store_true",
                    help="with --random: the rows' plates in columns (bolting rings), other draws unchanged")
    ap.add_argument("--random-acquisition", action="store_true",
                    help="with --random: also draw the writer's free choices (`random_acquisition`: rail, "
                         "PRF, speed, sampling rate, range window, antenna aperture, reference point)")
    ap.add_argument("--look-errors", action="store_true",
                    help="also print the errors of the located plates' looks against the truth, by kind "
                         "(clean, split, shared and kept), pooled over the runs with a prior")
    ap.add_argument("--random-web", type=float, nargs=2, default=None, metavar=("LO_M", "HI_M"),
                    help="draw each random scenario's web (advance per cycle, m) uniformly in [LO, HI] "
                         "instead of 0.9 m; the prior runs are told each scenario's web")
    args = ap.parse_args(argv)
    if args.random:
        return run_random(args)
    cycles = args.cycles or (6 if args.quick else 41)
    names = args.only or (QUICK if args.quick else [s.name for s in SCENARIOS] + list(VARIANTS))
    by_name = {s.name: s for s in SCENARIOS}
    results, looks = {}, []
    for name in names:
        parent, heights, prior = VARIANTS.get(name, (name, None, True))
        for k in range(args.replicas + 1):
            s = replica(by_name[parent], k)
            root, label = args.work / s.name, replica_name(name, s.seed, k)
            arch = generate(s, cycles, root)
            rig_m = np.array(json.loads((root / "truth.json").read_text())["rig_m"])
            out = args.work / label / args.tag
            reuse = None
            if args.reuse_detections:
                reuse = newest_run(args.work / label) or newest_run(root)
            if name != parent:
                share_cache(root / args.tag, out, args.backend)
            secs = run_process(arch, out, s, heights, prior, args.jobs, reuse, args.config, args.backend)
            results[label] = score(out, rig_m)
            if args.look_errors and name == parent:  # a variant locates its parent's looks again
                looks += look_errors(s, out, cycles, args.config)
            print(f"  {label}: processed in {secs:.0f} s", flush=True)
    print(table(results))
    if args.look_errors:
        print(look_error_table(looks))
    if args.replicas:
        print(replica_summary(results, names))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


def run_random(args) -> int:
    """`--random N`: short runs of independently drawn scenarios, as a user's first cycles would be."""
    cycles = args.cycles or 6
    results, snr_db, looks, classes = {}, {}, [], {}
    for seed in range(args.random_seed, args.random_seed + args.random):
        if args.only and f"r{seed}" not in args.only:  # the draw's other scenarios are skipped, not redrawn
            continue
        s = random_scenario(seed, cycles, tuple(args.random_web) if args.random_web else None,
                            args.random_aligned, args.random_acquisition)
        root = args.work / s.name
        classes[s.name] = geometry_class(s)
        arch = generate(s, cycles, root)
        rig_m = np.array(json.loads((root / "truth.json").read_text())["rig_m"])
        for prior in (True, False):
            name = s.name if prior else f"{s.name}-noprior"
            out = root / (args.tag if prior else f"{args.tag}-noprior")
            reuse = newest_run(root) if args.reuse_detections else None
            if not prior:
                share_cache(root / args.tag, out, args.backend)
            run_process(arch, out, s, None, prior, args.jobs, reuse, args.config, args.backend)
            results[name], snr_db[name] = score(out, rig_m), s.snr_db
            if args.look_errors and prior:
                looks += look_errors(s, out, cycles, args.config)
        print(f"  {s.name}: squint {s.squint_deg:.0f} deg, rib {s.rib_m:.1f} m, {len(s.heights_m)} heights, "
              f"{s.snr_db:.0f} dB, wobble {100 * s.wobble:.0f} %, "
              f"grid {s.grid_m:.2f} m x {len(s.rows_z_m)} rows, side {s.side:+d}, "
              f"{s.carrier_hz / 1e9:.2f}/{s.bandwidth_hz / 1e9:.1f} GHz, web {s.web_m:.2f} m"
              f"{', int16' if s.int16 else ''}{f', missed {list(s.missed)}' if s.missed else ''}"
              + (f"; rail {s.rail_m} m, {s.prf_hz:.0f} Hz x {s.speed_m_s} m/s, "
                 f"fs {s.sample_rate_hz / 1e9:.2f} GHz, window +{s.window_margin_m} m, "
                 f"aperture {s.aperture_m} m, reference z {s.reference_z}"
                 if args.random_acquisition else ""), flush=True)
    print(table(results))
    print(summary(results, snr_db))
    print(class_summary(results, snr_db, classes))
    if args.look_errors:
        print(look_error_table(looks))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
