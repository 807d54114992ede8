"""Plain data that flows between the layers: radar parameters, pass geometry, one recorded pass.

Everything is SI; names carry units. The radar frame O_r X_r Y_r Z_r has X_r along the rail (direction of
increasing rail position), Z_r up, origin at the rail's centre at height 0. The rib (coal wall) lies on the
side given by ``boresight_y_sign`` (-1: the wall is at negative Y_r, as in the paper's tables).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

SPEED_OF_LIGHT_M_S = 299_792_458.0


@dataclasses.dataclass(frozen=True)
class RadarParameters:
    """The radar as configured for a pass (paper Table 1/4/7)."""

    carrier_frequency_hz: float = 4.3e9
    bandwidth_hz: float = 1.7e9  # -10 dB width of the Gaussian pulse spectrum
    sample_rate_hz: float = 4.0e9  # complex (I/Q) fast-time sampling
    pulse_repetition_frequency_hz: float = 20.0
    antenna_aperture_m: float = 0.14

    @property
    def wavelength_m(self) -> float:
        return SPEED_OF_LIGHT_M_S / self.carrier_frequency_hz

    @property
    def pulse_sigma_s(self) -> float:
        """sigma of p(t) = exp(-t^2 / 2 sigma^2) whose spectrum is 10 dB down at +-B/2."""
        return math.sqrt(math.log(10.0)) / (math.pi * self.bandwidth_hz)

    @property
    def range_bin_m(self) -> float:
        return SPEED_OF_LIGHT_M_S / (2.0 * self.sample_rate_hz)


@dataclasses.dataclass(frozen=True)
class PassGeometry:
    """Where the rail was and where the beam pointed during one pass."""

    height_m: float
    rotation_table_angle_deg: float  # horizontal squint of the boresight from -/+Y_r towards +X_r
    reference_point_m: tuple[float, float, float]  # scene centre T in the radar frame
    boresight_y_sign: int = -1  # side of the rail the rib is on

    @property
    def rotation_table_angle_rad(self) -> float:
        return math.radians(self.rotation_table_angle_deg)


@dataclasses.dataclass
class RawRF:
    """Real RF scans kept beside the baseband for provenance (archive 1.1 ``/raw/rf``), one row per pulse."""

    samples: np.ndarray  # (N_a, K) integer ADC counts; sample k at delay scan_start_s + k bin_period_s
    bin_period_s: float
    scan_start_s: float  # on the radar's delay axis: the calibrated range_delay_s not removed


@dataclasses.dataclass
class ScanPass:
    """One pass along the rail at one height: the raw echo and everything needed to focus it."""

    radar: RadarParameters
    geometry: PassGeometry
    range_window_start_s: float  # absolute two-way delay of fast-time sample 0 (any calibrated delay removed)
    pulse_time_s: np.ndarray  # (N_a,) time of each pulse since pass start
    pulse_position_m: np.ndarray  # (N_a,) rail (X_r) position of the antenna at each pulse
    echo: np.ndarray  # (N_a, N_r) complex baseband, demodulated at the carrier
    rig_id: str = "rig-1"
    cycle: int = 0
    pass_start_time: str = "1970-01-01T00:00:00Z"  # ISO 8601, UTC
    source: str = ""  # file the pass was read from, for error messages
    # the calibrated antenna/cable delay already removed from the window start (record)
    range_delay_s: float = 0.0
    raw_rf: RawRF | None = None  # the radar's real RF, when an importer kept it (archive 1.1)

    @property
    def n_pulses(self) -> int:
        return int(self.echo.shape[0])

    @property
    def samples_per_pulse(self) -> int:
        return int(self.echo.shape[1])

    @property
    def aperture_centre_m(self) -> float:
        """X_r of O_s: the middle of the travelled aperture."""
        return 0.5 * float(self.pulse_position_m[0] + self.pulse_position_m[-1])

    @property
    def mean_speed_m_s(self) -> float:
        x, t = self.pulse_position_m, self.pulse_time_s
        return float((x[-1] - x[0]) / (t[-1] - t[0]))

    @property
    def range_axis_m(self) -> np.ndarray:
        """One-way range of each fast-time sample."""
        t = self.range_window_start_s + np.arange(self.samples_per_pulse) / self.radar.sample_rate_hz
        return 0.5 * SPEED_OF_LIGHT_M_S * t
