"""Real RF scans -> complex baseband in the archive's signal model (docs/archive-format.md section 2).

A radar that samples the RF directly (PulsON 440: 16.384 GHz, one real sample per 61 ps bin) gives
x(t) = Re{s(t) exp(j 2 pi f_c t)}; the archive wants s(t), sampled at a complex rate that covers its band.
`to_baseband` does it in one FFT per scan:

1. analytic signal (FFT Hilbert): the positive-frequency half of the zero-padded scan's spectrum, doubled;
2. mix-down at the carrier f_c: the spectrum is read from f_c - fs/2 to f_c + fs/2 and the phase is
   referenced to zero two-way delay on the radar's axis, so that s(t) = a(t) exp(-j 2 pi f_c t) with t the
   absolute delay of each sample (not its index);
3. band-limited decimation: only those bins are kept (an inverse FFT of M = Np / D bins gives every D-th
   sample of the band-limited analytic signal exactly), with a raised-cosine taper over the outer `taper`
   fraction of the kept band so that the time-domain kernel is short and the zero padding absorbs it;
4. scaling: |s| is the RF envelope in the input's units (ADC counts): a tone of amplitude A in the flat
   part of the band comes out with |s| = A.

Conversion error: nil (to rounding) for a signal whose spectrum lies inside the flat part of the kept band,
|f - f_c| <= (1 - taper) fs / 2; what lies outside is attenuated or removed, and the removed part is the
error. Measured (tests/test_p440_import.py), max |error| / peak for a Gaussian-modulated RF pulse of 1.7 GHz
-10 dB bandwidth at 4.3 GHz, demodulated at 4.27 GHz, against its analytic complex envelope: -95 dB at D = 3
(5.46 GHz), -60 dB at D = 4 (4.10 GHz, what `choose_decimation` picks for it), -50 dB at D = 5 (3.28 GHz);
in energy -91, -55 and -43 dB. A tone in the flat band keeps its amplitude within 1e-5. Within about 1 /
(taper fs / 2) of the ends of the scan window a signal that does not start and end at zero is smoothed: the
window edge is a step in the RF, which has no finite band.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from ..model import SPEED_OF_LIGHT_M_S, MeasuredPulse
from . import OptionError, RecordingError

log = logging.getLogger("uwbcl")

DEFAULT_OVERSAMPLING = 2.4  # complex rate / -10 dB bandwidth (the paper: 4.0 GHz for 1.7 GHz)
DEFAULT_TAPER = 0.2  # fraction of the kept band (each side) in the raised-cosine roll-off
_GUARD_BINS = 256  # zero padding beyond the scan window: room for the filter kernel, no wrap-around
_BLOCK_SCANS = 512  # scans transformed at a time: bounded memory for long recordings


@dataclasses.dataclass(frozen=True)
class Band:
    """Where the energy of a recording is, from its mean power spectrum.

    centre_hz is the middle of the -10 dB band (the carrier of the archive's Gaussian model, whose spectrum is
    symmetric about f_c and 10 dB down at f_c +- B/2); peak_hz and centroid_hz are reported for comparison.
    """

    centre_hz: float
    low_hz: float  # outermost frequencies where the smoothed spectrum is at -10 dB of its peak
    high_hz: float
    peak_hz: float
    centroid_hz: float  # power-weighted mean frequency inside [low_hz, high_hz]
    low_20db_hz: float  # the same at -20 dB: how wide the band to keep must be
    high_20db_hz: float

    @property
    def bandwidth_hz(self) -> float:
        return self.high_hz - self.low_hz


def mean_power_spectrum(
    rf: np.ndarray, bin_period_s: float, block: int = _BLOCK_SCANS
) -> tuple[np.ndarray, np.ndarray]:
    """(f_hz (K,), power (K,)): the mean over scans of |rfft|^2 of each Hann-windowed, mean-removed scan."""
    n = rf.shape[1]
    window = np.hanning(n)
    power = np.zeros(n // 2 + 1)
    for i in range(0, rf.shape[0], block):
        x = rf[i : i + block].astype(np.float64)
        x -= x.mean(axis=1, keepdims=True)  # ADC offset: DC, outside any band
        power += (np.abs(np.fft.rfft(x * window, axis=1)) ** 2).sum(axis=0)
    return np.fft.rfftfreq(n, bin_period_s), power / max(1, rf.shape[0])


def _edges(f_hz: np.ndarray, level: np.ndarray, threshold: float) -> tuple[float, float]:
    """Outermost crossings of ``threshold`` (linear interpolation between bins)."""
    above = np.flatnonzero(level >= threshold)
    lo, hi = above[0], above[-1]

    def cross(i_out: int, i_in: int) -> float:
        if i_out < 0 or i_out >= len(f_hz):
            return float(f_hz[i_in])
        a, b = level[i_out], level[i_in]
        return float(f_hz[i_out] + (threshold - a) / (b - a) * (f_hz[i_in] - f_hz[i_out]))

    return cross(lo - 1, lo), cross(hi + 1, hi)


def measure_band(rf: np.ndarray, bin_period_s: float, smooth_hz: float = 50e6) -> Band:
    """The spectrum centre and -10 dB band of real RF scans (n_scans, n_bins).

    The mean power spectrum is smoothed over ``smooth_hz`` (a running mean, in bins) so that the ripple of a
    few strong static echoes does not decide the edges; the edges are the outermost -10 dB crossings.
    """
    f, p = mean_power_spectrum(rf, bin_period_s)
    width = max(1, round(smooth_hz / (f[1] - f[0])))
    p = np.convolve(p, np.ones(width) / width, mode="same")
    peak = int(np.argmax(p))
    db = 10.0 * np.log10(np.maximum(p, 1e-300) / p[peak])
    lo, hi = _edges(f, db, -10.0)
    lo20, hi20 = _edges(f, db, -20.0)
    inside = (f >= lo) & (f <= hi)
    centroid = float((f[inside] * p[inside]).sum() / p[inside].sum())
    return Band(
        centre_hz=0.5 * (lo + hi),
        low_hz=lo,
        high_hz=hi,
        peak_hz=float(f[peak]),
        centroid_hz=centroid,
        low_20db_hz=lo20,
        high_20db_hz=hi20,
    )


def choose_decimation(
    rf_rate_hz: float, band: Band, oversampling: float = DEFAULT_OVERSAMPLING, taper: float = DEFAULT_TAPER
) -> int:
    """The largest integer D whose complex rate rf_rate / D is >= oversampling x the -10 dB bandwidth and
    keeps the whole -20 dB band inside the flat part of the kept band (|f - f_c| <= (1 - taper) rate / 2)."""
    return max(1, math.floor(rf_rate_hz / required_rate_hz(band, oversampling, taper)))


def required_rate_hz(band: Band, oversampling: float = DEFAULT_OVERSAMPLING,
                     taper: float = DEFAULT_TAPER) -> float:
    """The complex rate `choose_decimation` needs for ``band``: oversampling x the -10 dB bandwidth, and the
    -20 dB band inside the flat part of the kept band."""
    half_20 = max(band.centre_hz - band.low_20db_hz, band.high_20db_hz - band.centre_hz)
    return max(oversampling * band.bandwidth_hz, 2.0 * half_20 / (1.0 - taper))


BAND_EDGE_MARGIN_HZ = 50e6  # the -20 dB band must end this far inside 0..Nyquist (the spectrum's smoothing)
SPIKE_FACTOR = 100.0  # a sample this many times the 99.9th percentile of |RF| is named a spike by check_band
SPIKED_SCANS_LISTED = 5


def check_band(rf: np.ndarray, rf_rate_hz: float, band: Band, source: str = "") -> None:
    """RecordingError naming the file for a spectrum no pulse has: one that is not 20 dB down at 0 or at the
    RF Nyquist frequency (within BAND_EDGE_MARGIN_HZ), so that its -20 dB band does not fit between them. A
    corrupt sample or a clipped spike does that (its spectrum is flat); the message gives the largest
    sample. A pulse whose -20 dB band fits is converted even where the complex band `choose_decimation`
    wants reaches past Nyquist (a coarse scan_res): the analytic signal has nothing there."""
    nyquist_hz = rf_rate_hz / 2
    if band.low_20db_hz > BAND_EDGE_MARGIN_HZ and band.high_20db_hz < nyquist_hz - BAND_EDGE_MARGIN_HZ:
        return
    a = np.abs(rf.astype(np.int64) if rf.dtype.kind in "iu" else rf)  # |int32 min| overflows int32
    scan, sample = np.unravel_index(int(np.argmax(a)), a.shape)
    peak, typical = float(a[scan, sample]), float(np.percentile(a, 99.9))
    spiked = np.flatnonzero(np.max(a, axis=1) > SPIKE_FACTOR * max(typical, 1.0))
    if not spiked.size:
        # No spike: a noise floor within 20 dB of the pulse's peak spectrum (a weak echo, a noisy receiver),
        # not a corrupt sample: converted on the measured -10 dB band, said so (an independent tester's pulse
        # at 3000 counts in noise of 100 was refused)
        log.warning("%s: the spectrum is never 20 dB down at an end (-20 dB band %.3f-%.3f GHz, RF Nyquist "
                    "%.3f GHz) and no sample stands out (the largest |sample| %.6g is %.3g x the 99.9th "
                    "percentile): a noise floor within 20 dB of the pulse; converted on the measured -10 dB "
                    "band %.3f-%.3f GHz", source, band.low_20db_hz / 1e9, band.high_20db_hz / 1e9,
                    nyquist_hz / 1e9, peak, peak / max(typical, 1), band.low_hz / 1e9, band.high_hz / 1e9)
        return
    listed = ", ".join(str(i) for i in spiked[:SPIKED_SCANS_LISTED])
    listed += ", ..." if spiked.size > SPIKED_SCANS_LISTED else ""
    raise RecordingError(source, None, (
        f"the measured spectrum is implausibly wide for a radar pulse: -10 dB band {band.low_hz / 1e9:.3f}-"
        f"{band.high_hz / 1e9:.3f} GHz ({band.bandwidth_hz / 1e9:.3f} GHz), -20 dB band "
        f"{band.low_20db_hz / 1e9:.3f}-{band.high_20db_hz / 1e9:.3f} GHz, which does not fit between 0 and "
        f"the RF Nyquist frequency {nyquist_hz / 1e9:.3f} GHz (the spectrum is never 20 dB down at an end). "
        f"A corrupt sample or a clipped spike flattens the spectrum: the largest "
        f"|sample| is {peak:.6g} (scan {scan}, sample {sample}), {peak / max(typical, 1):.3g} x the 99.9th "
        f"percentile {typical:.6g}; {spiked.size} scan(s) hold a sample over {SPIKE_FACTOR:g} x it"
        + (f" (scans {listed})" if spiked.size else "")))


def to_baseband(
    rf: np.ndarray,
    bin_period_s: float,
    scan_start_s: float,
    carrier_hz: float,
    decimation: int,
    taper: float = DEFAULT_TAPER,
    block: int = _BLOCK_SCANS,
) -> tuple[np.ndarray, float]:
    """Complex baseband of real RF scans (the module docstring gives the method and its error).

    Parameters
    ----------
    rf : ndarray, (n_scans, n_bins), real (any integer or float type)
        RF samples; sample k of a scan at two-way delay scan_start_s + k * bin_period_s.
    bin_period_s : float
        RF sample period, s.
    scan_start_s : float
        Delay of RF sample 0 (the mix-down phase is referenced to zero delay).
    carrier_hz : float
        f_c, the demodulation frequency.
    decimation : int
        D: the complex rate is 1 / (D * bin_period_s); output sample m is at delay scan_start_s + m D
        bin_period_s.
    taper : float
        Fraction of each half of the kept band in the raised-cosine roll-off (0: a brick wall).

    Returns
    -------
    echo : ndarray, (n_scans, ceil(n_bins / D)) complex128
        s at scan_start_s + m / sample_rate, in the input's units.
    sample_rate_hz : float
        The complex rate.
    """
    n_scans, n_bins = rf.shape
    if decimation < 1 or not 0.0 <= taper < 1.0:
        raise ValueError(f"decimation must be >= 1 and 0 <= taper < 1, got {decimation}, {taper}")
    rf_rate = 1.0 / bin_period_s
    n_pad = decimation * math.ceil((n_bins + _GUARD_BINS) / decimation)  # Np = D M: every D-th sample exact
    m = n_pad // decimation
    n_out = math.ceil(n_bins / decimation)
    df = rf_rate / n_pad
    k0 = carrier_hz / df  # carrier in (fractional) bins of the padded FFT
    # Kept bins k0 - M/2 .. k0 + M/2 (integer bins; the fractional part of k0 is mixed in the time domain).
    k_lo = math.floor(k0) - m // 2
    bins = k_lo + np.arange(m)
    if not 0 < carrier_hz < rf_rate / 2:
        raise ValueError(f"carrier {carrier_hz:.4g} Hz is not between 0 and the RF Nyquist frequency "
                         f"{rf_rate / 2:.4g} Hz")
    # Kept bins beyond 0..Nyquist (a coarse RF rate) are zero: the analytic signal has nothing there.
    valid = (bins >= 1) & (bins < n_pad // 2)
    f_rel = (bins - k0) * df  # baseband frequency of each kept bin
    half = 0.5 * m * df
    flat = (1.0 - taper) * half
    gain = np.ones(m)
    roll = np.abs(f_rel) > flat
    if taper > 0:
        gain[roll] = 0.5 * (1.0 + np.cos(np.pi * np.clip((np.abs(f_rel[roll]) - flat) / (half - flat), 0, 1)))
    # 2 X(f): the analytic signal's spectrum; / D: ifft over M bins instead of Np.
    gain *= 2.0 / decimation
    # Bin k_lo + i is baseband bin i - shift after the integer mix: roll it to the inverse FFT's order.
    shift = math.floor(k0) - k_lo
    t_out = scan_start_s + np.arange(n_out) * decimation * bin_period_s
    # exp(-j 2 pi f_c t): the integer part of the shift was done on the bins relative to sample 0, so the
    # remaining phase is the fractional carrier over the output samples plus the integer part at scan_start.
    residual = np.exp(
        -2j * np.pi * ((k0 - math.floor(k0)) * df * (t_out - scan_start_s) + carrier_hz * scan_start_s)
    )
    out = np.empty((n_scans, n_out), dtype=np.complex128)
    for i in range(0, n_scans, block):
        x = rf[i : i + block].astype(np.float64)
        spec = np.zeros((x.shape[0], m), dtype=np.complex128)
        spec[:, valid] = np.fft.rfft(x, n=n_pad, axis=1)[:, bins[valid]] * gain[valid]
        z = np.fft.ifft(np.roll(spec, -shift, axis=1), axis=1)[:, :n_out]
        out[i : i + block] = z * residual
    return out, rf_rate / decimation


PULSE_FFT_SAMPLES = 256  # the measured pulse's spectrum: this many samples across the complex band
PULSE_WINDOW_TAPER = 0.25  # raised-cosine fraction of the reference window at each end
PULSE_MIN_SNR = 10.0  # the reference echo's mean over the scans must peak this far (20 dB) above its noise


def measure_pulse(echo: np.ndarray, sample_rate_hz: float, window_start_s: float, carrier_hz: float,
                  start_m: float, stop_m: float, source: str = "") -> MeasuredPulse:
    """The radar's pulse from a stationary reference echo (the direct coupling): the echo's mean over the
    pulses (moving targets average out, the coupling does not), windowed to one-way ranges [start_m, stop_m]
    (raised-cosine ends), its spectrum S(f) with the absolute delay origin (as `nlcs.range_fft`), and the
    delay tau of the window's envelope peak removed: P(f) = S(f) exp(+j 2 pi (f_c + f) tau), so the pulse's
    delay origin is its envelope peak, as the Gaussian's is (docs/importing.md section 4)."""
    c = SPEED_OF_LIGHT_M_S
    t = window_start_s + np.arange(echo.shape[1]) / sample_rate_hz
    r = 0.5 * c * t
    inside = np.flatnonzero((r >= start_m) & (r <= stop_m))
    whose = f"the echo of {source}" if source else "the echo"
    advice = (f"{whose} spans {r[0]:.2f}-{r[-1]:.2f} m (one-way, on the archive's axis): give "
              "--pulse-window-m START STOP around a stationary echo inside it (the direct coupling, where "
              "the scan window holds it), or use --pulse gaussian")
    if inside.size < 4:
        raise OptionError("pulse_window_start_m", f"the pulse's reference window {start_m}-{stop_m} m holds "
                                                  f"{inside.size} samples of the echo; {advice}")
    ref = echo[:, inside]
    s = ref.mean(axis=0)
    # The mean's own noise, from the scan-to-scan spread: a window of noise alone (no echo there) averages to
    # a few times it, and a pulse measured from it would put phantom targets in every image.
    noise = math.sqrt(float(np.mean(ref.var(axis=0))) / ref.shape[0])
    peak_abs = float(np.max(np.abs(s)))
    if peak_abs <= PULSE_MIN_SNR * noise:
        level = f"{20 * math.log10(peak_abs / noise):.1f} dB" if peak_abs > 0 else "nothing"
        raise OptionError("pulse_window_start_m", (
            f"the pulse's reference window {start_m}-{stop_m} m holds no stationary echo: the mean of its "
            f"{ref.shape[0]} scans peaks {level} above that mean's noise "
            f"({20 * math.log10(PULSE_MIN_SNR):.0f} dB needed); {advice}"))
    n = inside.size
    edge = max(1, int(PULSE_WINDOW_TAPER * n))
    w = np.ones(n)
    ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(edge) + 0.5) / edge)
    w[:edge], w[n - edge:] = ramp, ramp[::-1]
    s = s * w
    peak = int(np.argmax(np.abs(s)))
    if np.abs(s[peak]) == 0:
        raise OptionError("pulse_window_start_m",
                          f"no reference echo between {start_m} and {stop_m} m; {advice}")
    # the envelope peak to a fraction of a sample (parabola through the peak's log-magnitude)
    frac = 0.0
    if 0 < peak < n - 1:
        a, b, d = np.log(np.abs(s[peak - 1:peak + 2]) + 1e-300)
        frac = 0.5 * (a - d) / (a - 2 * b + d) if a - 2 * b + d < 0 else 0.0
    tau = t[inside[0]] + (peak + frac) / sample_rate_hz
    m = max(PULSE_FFT_SAMPLES, n)
    f = np.fft.fftshift(np.fft.fftfreq(m, 1.0 / sample_rate_hz))
    spectrum = np.exp(-2j * np.pi * np.outer(f, t[inside])) @ s  # S(f), absolute delay origin
    return MeasuredPulse(f, spectrum * np.exp(2j * np.pi * (carrier_hz + f) * tau))
