"""Echo simulator: demodulated baseband echoes of point targets (eq. 2) with a real rail's imperfections.

* Gaussian pulse p(t) = exp(-t^2 / 2 sigma^2), sigma from the -10 dB bandwidth, or the radar's measured
  pulse (`model.pulse_waveform`).
* Optionally a bent rail: per-pulse deviations (dy, dz) of the antenna from the straight rail; the echo uses
  the true antenna position (x, dy, h + dz).
* Two-way main-lobe beam pattern of the 0.14 m aperture, frequency independent (eq. 2's w_a).
* Pulses at a fixed repetition frequency; the carriage speed fluctuates by up to +-speed_jitter (a smooth
  random process), so the rail positions are not uniform. They are logged per pulse, as the encoder does.
* Receiver noise: circular complex Gaussian, SNR defined per raw fast-time sample relative to a unit echo:
  SNR_dB = 10 log10(1 / E|n|^2), where a target of amplitude 1 on boresight gives a peak sample of modulus 1.
* Optionally (`spreading_loss`) the two-way spreading of a real echo, amplitude (R_c / R)^2: 1 at the
  target's closest approach R_c, so the SNR definition stands. Eq. (2) has none; a real radar's echo has it.
"""

from __future__ import annotations

import math

import numpy as np

from . import geometry as geo
from .model import SPEED_OF_LIGHT_M_S, PassGeometry, RadarParameters, ScanPass, pulse_waveform


def rail_motion(n_pulses: int, prf_hz: float, speed_m_s: float, start_m: float, speed_jitter: float,
                rng: np.random.Generator, direction: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Pulse times (from pass start) and rail positions of a carriage whose speed wanders by +-speed_jitter.

    The speed is v (1 + speed_jitter u(t)), u a sum of random sinusoids with 1-8 s periods scaled to
    max |u| = 1: a motor controller hunting around its set speed, not white noise.
    """
    t = np.arange(n_pulses) / prf_hz
    if speed_jitter > 0:
        fine = np.linspace(0.0, t[-1], 16 * n_pulses)
        u = np.zeros_like(fine)
        for _ in range(4):
            period = rng.uniform(1.0, 8.0)
            u += rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * fine / period + rng.uniform(0, 2 * np.pi))
        u /= np.max(np.abs(u))
        speed = speed_m_s * (1.0 + speed_jitter * u)
        travelled = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(fine))])
        x = np.interp(t, fine, travelled)
    else:
        x = speed_m_s * t
    return t, start_m + direction * x


BEAM_SEEN_GAIN = 1e-3  # two-way beam gain (-60 dB) above which a pulse counts as seeing a target


def gate_samples(r_lo_m: float, r_hi_m: float, range_bin_m: float, power_of_two: bool = True) -> int:
    """Samples per pulse of a range gate from r_lo_m to r_hi_m (rounded up to a power of two by default)."""
    n = math.ceil((r_hi_m - r_lo_m) / range_bin_m)
    return 1 << (n - 1).bit_length() if power_of_two else n


def seen_ranges_m(radar: RadarParameters, positions_m, targets_m, height_m: float, table_angle_rad: float,
                  boresight_y_sign: int) -> np.ndarray:
    """(n_targets, 2) min and max range of each target over the pulses whose beam sees it (gain above
    BEAM_SEEN_GAIN); NaN for a target no pulse sees. positions_m (n_pulses,) along the rail,
    targets_m (n, 3)."""
    out = np.full((len(targets_m), 2), np.nan)
    for i, t in enumerate(targets_m):
        psi = geo.horizontal_look_angle_rad(positions_m, t, boresight_y_sign)
        seen = geo.two_way_beam_gain(psi, table_angle_rad, radar.antenna_aperture_m,
                                     radar.wavelength_m) > BEAM_SEEN_GAIN
        if seen.any():
            r = geo.range_history_m(positions_m[seen], t, height_m)
            out[i] = r.min(), r.max()
    return out


def range_window(radar: RadarParameters, positions_m, targets_m, height_m: float,
                 margin_m: float = 1.0, power_of_two: bool = True) -> tuple[float, int]:
    """(range_window_start_s, samples_per_pulse) covering every target over the aperture +- margin."""
    ranges = np.concatenate([geo.range_history_m(positions_m, t, height_m) for t in targets_m])
    r_lo = max(0.0, ranges.min() - margin_m)
    r_hi = ranges.max() + margin_m
    t0 = 2.0 * r_lo / SPEED_OF_LIGHT_M_S
    return t0, gate_samples(r_lo, r_hi, radar.range_bin_m, power_of_two)


def simulate_echo(radar: RadarParameters, geometry: PassGeometry, positions_m, targets_m, amplitudes,
                  range_window_start_s: float, samples_per_pulse: int, snr_db: float | None,
                  rng: np.random.Generator, antenna_y_m=None, antenna_z_m=None,
                  spreading_loss: bool = False) -> np.ndarray:
    """s(t_r, t_a) = sum_M A_M w_a p(t_r - 2R/c) exp(-j 4 pi f_c R / c) + n   (eq. 2), R from the true antenna
    position (x, dy, h + dz) when the per-pulse rail deviations antenna_y_m, antenna_z_m are given; A_M times
    (R_c / R)^2 when `spreading_loss`."""
    positions_m = np.asarray(positions_m, dtype=float)
    t_r = range_window_start_s + np.arange(samples_per_pulse) / radar.sample_rate_hz
    sigma = radar.pulse_sigma_s
    k = 4.0 * np.pi * radar.carrier_frequency_hz / SPEED_OF_LIGHT_M_S
    echo = np.zeros((positions_m.size, samples_per_pulse), dtype=np.complex128)
    for target, amplitude in zip(np.atleast_2d(targets_m),
                                 np.broadcast_to(amplitudes, len(np.atleast_2d(targets_m)))):
        r = geo.range_history_m(positions_m, target, geometry.height_m, antenna_y_m, antenna_z_m)
        psi = geo.horizontal_look_angle_rad(positions_m, target, geometry.boresight_y_sign)
        gain = amplitude * geo.two_way_beam_gain(psi, geometry.rotation_table_angle_rad,
                                                 radar.antenna_aperture_m, radar.wavelength_m)
        if spreading_loss:
            gain = gain * (geo.closest_approach_range_m(target, geometry.height_m) / r) ** 2
        seen = gain > 0
        delay = t_r[None, :] - 2.0 * r[seen, None] / SPEED_OF_LIGHT_M_S
        envelope = pulse_waveform(delay, sigma, radar.measured_pulse)
        echo[seen] += (gain[seen] * np.exp(-1j * k * r[seen]))[:, None] * envelope
    if snr_db is not None and np.isfinite(snr_db):
        noise_power = 10.0 ** (-snr_db / 10.0)
        echo += math.sqrt(noise_power / 2.0) * (rng.standard_normal(echo.shape)
                                                + 1j * rng.standard_normal(echo.shape))
    return echo


def simulate_pass(radar: RadarParameters, geometry: PassGeometry, targets_m, *, aperture_length_m: float,
                  speed_m_s: float, aperture_centre_m: float = 0.0, amplitudes=1.0,
                  snr_db: float | None = None, speed_jitter: float = 0.0,
                  rng: np.random.Generator | None = None, rig_id: str = "rig-1", cycle: int = 0,
                  pass_start_time: str = "1970-01-01T00:00:00Z", direction: int = 1,
                  range_margin_m: float = 1.0, rail_deviation=None, spreading_loss: bool = False) -> ScanPass:
    """One pass of the carriage over the nominal aperture, as the rig would record it. `rail_deviation`:
    a bent rail, a function of the rail positions (m) giving the antenna's (dy, dz) deviations (m), recorded
    in the pass (as a surveyed rail would be) and used for the echo. `spreading_loss`: echoes weighted by
    (R_c / R)^2."""
    rng = np.random.default_rng() if rng is None else rng
    # An even number of intervals (odd pulse count) centred on the nominal aperture centre.
    n_intervals = 2 * round(0.5 * aperture_length_m / speed_m_s * radar.pulse_repetition_frequency_hz)
    n_pulses = n_intervals + 1
    start = (aperture_centre_m
             - direction * 0.5 * n_intervals * speed_m_s / radar.pulse_repetition_frequency_hz)
    times, positions = rail_motion(n_pulses, radar.pulse_repetition_frequency_hz, speed_m_s, start,
                                   speed_jitter, rng, direction)
    targets_m = np.atleast_2d(np.asarray(targets_m, dtype=float))
    t0, n_r = range_window(radar, positions, targets_m, geometry.height_m, range_margin_m)
    dy = dz = None
    if rail_deviation is not None:
        dy, dz = (np.asarray(d, dtype=float) * np.ones_like(positions) for d in rail_deviation(positions))
    echo = simulate_echo(radar, geometry, positions, targets_m, amplitudes, t0, n_r, snr_db, rng, dy, dz,
                         spreading_loss)
    return ScanPass(radar=radar, geometry=geometry, range_window_start_s=t0, pulse_time_s=times,
                    pulse_position_m=positions, echo=echo, rig_id=rig_id, cycle=cycle,
                    pass_start_time=pass_start_time, antenna_y_m=dy, antenna_z_m=dz)
