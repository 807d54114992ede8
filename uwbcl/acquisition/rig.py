"""The world the simulated rig scans: a rib of bolt plates and a face that advances once per cutting cycle.

A paper scenario (`uwbcl.scenarios`) gives the plate pattern, the radar, the rail speed and aperture, the
first rig position and the nominal advance. A production run needs many cycles, so the plate group is repeated
along the roadway (X) with an irregular pitch, and the rig advances by the scenario's web with +-`web_jitter`
variation, a creep that drifts a few millimetres per cycle, and a little vertical noise. Cycle k of a campaign
is the same whatever else is asked of it (each cycle's draws come from a generator seeded by (seed, k)), so
the device, a test and `scripts/acquisition_study.py` agree on the truth.

The echo of a pass comes from `uwbcl.simulate` (eq. 2 with the beam pattern and the rail's speed wander) for
the height and rotation-table angle the client commanded, so the client's steering decides what the radar
sees.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model import SPEED_OF_LIGHT_M_S, PassGeometry, RadarParameters
from ..scenarios import SCENARIOS, Scenario
from ..simulate import gate_samples, rail_motion, seen_ranges_m, simulate_echo

_PLATES, _CYCLE, _PASS = 1, 2, 3  # purposes in the seed sequences


@dataclasses.dataclass(frozen=True)
class WorldConfig:
    scenario: str = "paper-sim1"
    seed: int = 0
    snr_db: float | None = None  # per raw sample, relative to a unit echo (uwbcl.simulate); None: noise-free
    speed_jitter: float = 0.0  # carriage speed wander, fraction of the set speed
    web_jitter: float = 0.05  # advance per cycle varies by +- this fraction of the scenario's
    range_samples: int | None = None  # fixed range gate; None: a power of two covering the plates in the beam
    range_margin_m: float = 1.0
    aperture_length_m: float | None = None  # None: the scenario's
    speed_m_s: float | None = None  # None: the scenario's
    prf_hz: float | None = None  # None: the scenario radar's


@dataclasses.dataclass(frozen=True)
class PassData:
    """One pass as the radar produces it: pulse times from pass start, rail positions, complex echo."""

    time_s: np.ndarray
    position_m: np.ndarray
    echo: np.ndarray  # (N, M) complex128
    range_window_start_s: float
    targets_radar_m: np.ndarray  # the plates in the radar frame during the pass (truth)


class Campaign:
    """Plates and rig positions for cycle index k = 0, 1, 2, ...; see the module docstring."""

    def __init__(self, config: WorldConfig = WorldConfig()):
        if config.scenario not in SCENARIOS:
            raise ValueError(f"unknown scenario {config.scenario!r}; available: "
                             f"{', '.join(sorted(SCENARIOS))}")
        self.config = config
        self.base: Scenario = SCENARIOS[config.scenario]
        radar = self.base.radar
        if config.prf_hz is not None:
            if not (math.isfinite(config.prf_hz) and config.prf_hz > 0):
                raise ValueError(f"prf_hz must be finite and > 0, got {config.prf_hz}")
            radar = dataclasses.replace(radar, pulse_repetition_frequency_hz=float(config.prf_hz))
        self.radar: RadarParameters = radar
        self.speed_m_s = float(config.speed_m_s or self.base.speed_m_s)
        self.aperture_length_m = float(config.aperture_length_m or self.base.aperture_length_m)
        n_intervals = 2 * round(0.5 * self.aperture_length_m / self.speed_m_s
                                * radar.pulse_repetition_frequency_hz)
        self.pulses_per_pass = n_intervals + 1
        self.rail_half_travel_m = 0.5 * n_intervals * self.speed_m_s / radar.pulse_repetition_frequency_hz
        advance = self.base.rig_positions_m[1] - self.base.rig_positions_m[0]
        self.nominal_web_m = float(advance[0])
        self._positions = [np.asarray(self.base.rig_positions_m[0], dtype=float)]
        self._creep_sign = 1.0
        self._plates = np.empty((0, 3))

    # ------------------------------------------------------------------------------------------ the rib

    def plates_roadway_m(self, x_max_m: float) -> np.ndarray:
        """Plates with roadway X below x_max_m: the scenario's group repeated along X at an
        irregular pitch."""
        if len(self._plates) and self._plates[:, 0].max() >= x_max_m:
            return self._plates
        group = np.asarray(self.base.targets_roadway_m, dtype=float)
        span = float(np.ptp(group[:, 0]))
        pitch = span + (span / (len(group) - 1) if span > 0 else 1.25)
        rng = np.random.default_rng([self.config.seed, _PLATES])
        plates, offset = [], 0.0
        while offset + group[:, 0].min() < x_max_m + pitch:
            rough = rng.normal(0.0, [0.0, 0.01, 0.01], size=group.shape) if offset else np.zeros_like(group)
            plates.append(group + [offset, 0.0, 0.0] + rough)
            offset += pitch + rng.uniform(-0.15, 0.15) * min(pitch, 1.0)
        self._plates = np.concatenate(plates)
        return self._plates

    # ------------------------------------------------------------------------------------------ the face

    def rig_position_m(self, k: int) -> np.ndarray:
        """Rig (rail centre at height 0) in the roadway frame at cycle index k."""
        if k < 0:
            raise ValueError(f"cycle index {k} < 0")
        y0 = float(self._positions[0][1])
        while len(self._positions) <= k:
            c = len(self._positions)
            r = np.random.default_rng([self.config.seed, _CYCLE, c])
            prev = self._positions[-1]
            web = self.nominal_web_m * (1.0 + r.uniform(-self.config.web_jitter, self.config.web_jitter))
            if abs(prev[1] + 0.004 * self._creep_sign - y0) > 0.05:
                self._creep_sign = -self._creep_sign  # the conveyor is steered back before it drifts far
            creep = 0.004 * self._creep_sign + r.normal(0.0, 0.0015)
            self._positions.append(prev + np.array([web, creep, r.normal(0.0, 0.002)]))
        return self._positions[k].copy()

    def advance_m(self, k: int) -> np.ndarray:
        """True Delta P = rig(k) - rig(k - 1): retreat, creep, vertical."""
        return self.rig_position_m(k) - self.rig_position_m(k - 1)

    def targets_radar_m(self, k: int) -> np.ndarray:
        rig = self.rig_position_m(k)
        plates = self.plates_roadway_m(rig[0] + 12.0)
        radar = plates - rig
        return radar[np.abs(radar[:, 0]) < 8.0]

    # ------------------------------------------------------------------------------------------ a pass

    def make_pass(self, k: int, height_m: float, table_angle_deg: float, direction: int) -> PassData:
        """The echo the radar records at cycle index k, deterministic in (seed, k, height, direction)."""
        rng = np.random.default_rng([self.config.seed, _PASS, k, round(height_m * 1e6) & 0x7FFFFFFF,
                                     1 if direction > 0 else 0])
        prf = self.radar.pulse_repetition_frequency_hz
        start = -direction * self.rail_half_travel_m
        times, positions = rail_motion(self.pulses_per_pass, prf, self.speed_m_s, start,
                                       self.config.speed_jitter, rng, direction)
        targets = self.targets_radar_m(k)
        geometry = PassGeometry(height_m=height_m, rotation_table_angle_deg=table_angle_deg,
                                reference_point_m=(0.0, -1.0, 0.0))  # not used by the echo model
        t0, n = self._range_gate(positions, targets, geometry)
        echo = simulate_echo(self.radar, geometry, positions, targets, 1.0, t0, n, self.config.snr_db, rng)
        return PassData(times, positions, echo, t0, targets)

    def _range_gate(self, positions_m, targets_m, geometry: PassGeometry) -> tuple[float, int]:
        """Gate from the nearest plate in the beam less the margin; picosecond-exact, as the register
        holds it."""
        ranges = seen_ranges_m(self.radar, positions_m, targets_m, geometry.height_m,
                               geometry.rotation_table_angle_rad, geometry.boresight_y_sign)
        if np.isfinite(ranges).any():
            r_lo = max(0.0, np.nanmin(ranges[:, 0]) - self.config.range_margin_m)
            r_hi = np.nanmax(ranges[:, 1]) + self.config.range_margin_m
        else:  # nothing in the beam: look at the rib anyway
            r_lo, r_hi = 1.0, 1.0 + 128 * self.radar.range_bin_m
        n = int(self.config.range_samples) if self.config.range_samples else gate_samples(r_lo, r_hi,
                                                                                          self.radar.range_bin_m)
        t0 = round(2.0 * r_lo / SPEED_OF_LIGHT_M_S * 1e12) / 1e12
        return t0, n
