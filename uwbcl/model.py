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
# Samples nearer than this to the antenna (one-way range; or behind it, once a calibrated delay is removed
# from a window that began before it) hold the antenna's own coupling, never a plate: processing drops them
# (`pipeline.crop_near_field`), since a focus grid has no meaning at or behind zero range.
MIN_WINDOW_RANGE_M = 0.1


@dataclasses.dataclass(frozen=True, eq=False)
class MeasuredPulse:
    """A measured transmit pulse (archive 1.2 ``/radar/pulse_spectrum``): its baseband spectrum P(f) at the
    increasing frequency offsets f from the carrier, normalised to max |P| = 1, phase referred to the pulse's
    delay origin (a target at range R echoes p(t - 2R / c) exp(-j 4 pi f_c R / c), as the Gaussian of eq. 2).
    Between samples P is interpolated linearly in its real and imaginary parts; outside it is 0.
    Equal (and hashed) by value, so a focus grid that carries it stays a cache key."""

    frequency_hz: np.ndarray  # (M,) increasing
    spectrum: np.ndarray  # (M,) complex, max |P| = 1

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, dtype=np.float64)
        p = np.asarray(self.spectrum, dtype=np.complex128)
        if f.ndim != 1 or f.shape != p.shape or f.size < 2 or not (np.diff(f) > 0).all():
            raise ValueError("a measured pulse needs >= 2 increasing frequencies, one spectrum value each")
        peak = np.abs(p).max()
        if not (np.isfinite(f).all() and np.isfinite(p).all() and peak > 0):
            raise ValueError("a measured pulse's frequencies and spectrum must be finite, the spectrum not 0")
        object.__setattr__(self, "frequency_hz", f)
        object.__setattr__(self, "spectrum", p / peak if peak != 1.0 else p)
        object.__setattr__(self, "_tables", {})

    def __eq__(self, other) -> bool:
        return (isinstance(other, MeasuredPulse) and np.array_equal(self.frequency_hz, other.frequency_hz)
                and np.array_equal(self.spectrum, other.spectrum))

    def __hash__(self) -> int:
        return hash((self.frequency_hz.tobytes(), self.spectrum.tobytes()))

    def at(self, f_hz) -> np.ndarray:
        """P(f) at the baseband frequencies f_hz (any shape)."""
        f = np.asarray(f_hz, dtype=np.float64)
        re = np.interp(f, self.frequency_hz, self.spectrum.real, left=0.0, right=0.0)
        im = np.interp(f, self.frequency_hz, self.spectrum.imag, left=0.0, right=0.0)
        return re + 1j * im

    # the waveform's table: steps per period of the band's width (cubic interpolation error ~1e-7 of peak),
    # at most this half-span (a pulse is a few ns long), from at most TABLE_SPECTRUM_SAMPLES of P (a longer
    # spectrum is first interpolated onto that many uniform samples): the table's cost stays bounded
    TABLE_OVERSAMPLING = 32
    TABLE_HALF_SPAN_S = 64e-9
    TABLE_SPECTRUM_SAMPLES = 1024

    def waveform(self, t_s, matched: bool = False) -> np.ndarray:
        """p(t) = int P(f) exp(j 2 pi f t) df / int |P| df at the delays t_s (any shape): the sampled echo of
        a unit target whose zero-phase pulse would peak at 1 (for the Gaussian, exp(-t^2 / 2 sigma^2)). With
        `matched` the pulse after its matched filter conj(P): int |P|^2 exp(j 2 pi f t) df / int |P| df
        (Gaussian: exp(-t^2 / 4 sigma^2) / sqrt(2)). Trapezoid rule over the samples of P, tabulated once
        (`exact_waveform`) over |t| <= 1 / (2 df), df the median spectral step (beyond it the sampled spectrum
        only repeats the pulse: 0 there), demodulated to the band's centre and interpolated by cubic Lagrange
        at TABLE_OVERSAMPLING steps per 1 / bandwidth."""
        f = self.frequency_hz
        source = self
        if f.size > self.TABLE_SPECTRUM_SAMPLES:
            f = np.linspace(f[0], f[-1], self.TABLE_SPECTRUM_SAMPLES)
            source = MeasuredPulse(f, self.at(f))
        f_mid, width = 0.5 * (f[0] + f[-1]), f[-1] - f[0]
        step = 1.0 / (self.TABLE_OVERSAMPLING * width)
        half = min(0.5 / float(np.median(np.diff(f))), self.TABLE_HALF_SPAN_S)
        table = self._tables.get(matched)
        if table is None:
            n = int(np.ceil(half / step))
            tt = np.arange(-n - 2, n + 3) * step
            demodulated = source.exact_waveform(tt, matched) * np.exp(-2j * np.pi * f_mid * tt)
            table = self._tables[matched] = (n + 2, demodulated)
        origin, values = table
        t = np.asarray(t_s, dtype=np.float64)
        x = t / step + origin
        i = np.clip(np.floor(x).astype(np.int64), 1, values.size - 3)
        u = x - i
        q = (values[i - 1] * (-u * (u - 1) * (u - 2) / 6) + values[i] * ((u + 1) * (u - 1) * (u - 2) / 2)
             + values[i + 1] * (-(u + 1) * u * (u - 2) / 2) + values[i + 2] * ((u + 1) * u * (u - 1) / 6))
        return np.where(np.abs(t) <= half, q * np.exp(2j * np.pi * f_mid * t), 0.0)

    def exact_waveform(self, t_s, matched: bool = False, chunk: int = 1 << 16) -> np.ndarray:
        """`waveform` summed directly at every delay (the reference for its table)."""
        f = self.frequency_hz
        w = np.zeros_like(f)
        w[1:] += 0.5 * np.diff(f)
        w[:-1] += 0.5 * np.diff(f)
        p = np.abs(self.spectrum) ** 2 if matched else self.spectrum
        coeff = w * p / np.sum(w * np.abs(self.spectrum))
        t = np.asarray(t_s, dtype=np.float64)
        flat = t.ravel()
        out = np.empty(flat.size, dtype=np.complex128)
        step = max(1, chunk // f.size)
        for a in range(0, flat.size, step):
            out[a:a + step] = np.exp(2j * np.pi * np.outer(flat[a:a + step], f)) @ coeff
        return out.reshape(t.shape)


def gaussian_pulse_spectrum(f_hz, sigma_s: float) -> np.ndarray:
    """P(f) of the Gaussian pulse exp(-t^2 / 2 sigma^2), normalised to P(0) = 1 (eq. 10's H4 is its
    conjugate, the same real function)."""
    return np.exp(-2.0 * (np.pi * sigma_s * np.asarray(f_hz)) ** 2)


def pulse_filter(f_hz, sigma_s: float, measured: MeasuredPulse | None) -> np.ndarray:
    """The range matched filter H4 = conj(P(f)) (eq. 10) at baseband frequencies f_hz: the Gaussian's (real,
    P(0) = 1) or the measured pulse's. One home for every focuser's range compression."""
    if measured is None:
        return gaussian_pulse_spectrum(f_hz, sigma_s)
    return np.conj(measured.at(f_hz))


# Point-response models of the Gaussian pulse are evaluated only where its envelope exceeds this fraction of
# its peak: a smaller sample cannot change a float64 sum that holds the peak (eps 2.2e-16), by a factor 1e4.
GAUSSIAN_SUPPORT_FLOOR = 1e-20


def pulse_support_s(sigma_s: float, measured: MeasuredPulse | None, matched: bool = False) -> float:
    """Half-width (s) of the delays where `pulse_waveform` exceeds GAUSSIAN_SUPPORT_FLOOR of its peak: the
    Gaussian's exp(-(t / w)^2), w = sqrt(2) sigma (2 sigma matched); infinite for a measured pulse."""
    if measured is not None:
        return math.inf
    width = 2.0 * sigma_s if matched else math.sqrt(2.0) * sigma_s
    return width * math.sqrt(-math.log(GAUSSIAN_SUPPORT_FLOOR))


def pulse_waveform(t_s, sigma_s: float, measured: MeasuredPulse | None, matched: bool = False) -> np.ndarray:
    """The echo envelope p(t) of a unit target (eq. 2), or with `matched` the pulse after H4: the Gaussian
    exp(-t^2 / 2 sigma^2) and exp(-t^2 / 4 sigma^2) / sqrt(2), or `MeasuredPulse.waveform`. One home for every
    point-response model (simulator, backprojection's models, detection's cancellation)."""
    if measured is not None:
        return measured.waveform(t_s, matched)
    t = np.asarray(t_s)
    if matched:
        return np.exp(-((t / (2.0 * sigma_s)) ** 2)) / math.sqrt(2.0)
    return np.exp(-0.5 * (t / sigma_s) ** 2)


@dataclasses.dataclass(frozen=True)
class RadarParameters:
    """The radar as configured for a pass (paper Table 1/4/7)."""

    carrier_frequency_hz: float = 4.3e9
    bandwidth_hz: float = 1.7e9  # -10 dB width of the Gaussian pulse spectrum
    sample_rate_hz: float = 4.0e9  # complex (I/Q) fast-time sampling
    pulse_repetition_frequency_hz: float = 20.0
    antenna_aperture_m: float = 0.14
    # None: the Gaussian pulse of the -10 dB bandwidth (eq. 2); else the measured pulse (archive 1.2)
    measured_pulse: MeasuredPulse | None = None

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
    # (N_a,) deviations of the antenna from the straight rail, cross-track (Y_r) and up (Z_r), per pulse
    # (archive 1.2 /pulses/antenna_y_m, antenna_z_m); None: on the rail. Focusing compensates them (C14).
    antenna_y_m: np.ndarray | None = None
    antenna_z_m: np.ndarray | None = None

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
