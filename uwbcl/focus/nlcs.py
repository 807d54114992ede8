"""The modified NLCS focusing chain (paper section 2.2) as a float64 numpy reference, one function per stage.

Array layout: (azimuth, range) = (pulses, fast-time samples). Range spectra are in numpy FFT order with
absolute delay origins (S(f) = sum s(t) exp(-j 2 pi f t), t = t_r0 + k / f_s). Azimuth arrays on the padded
grid are centred: index N/2 is t_a = 0 (resp. f_a = 0), so transforms are fftshift(fft(ifftshift(.))).

The chain (eq. numbers of the paper; C1..C13: its corrections, docs/method.md section 8):
    range_fft -> linear_range_walk_correction (4, with the logged rail positions) -> resample_to_uniform_track
    -> extended_nlcs (6) -> azimuth_fft -> secondary_range_compression (9-10, C5) -> range_ifft (11)
    -> azimuth_compensation (13) -> nlcs_filter (15: H6) -> azimuth_ifft -> nlcs_scaling (15: H7)
    -> azimuth_fft -> azimuth_compression (17; C10, C11) -> azimuth_ifft
The geometry correction (eqs. 18-19, C12) lives in `FocusedImage.to_track`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import geometry as geo
from ..model import SPEED_OF_LIGHT_M_S, MeasuredPulse, ScanPass, gaussian_pulse_spectrum
from ..model import pulse_filter as _pulse_filter
from ..model import pulse_support_s as _pulse_support_s
from ..model import pulse_waveform as _pulse_waveform
from . import coefficients as coef

C = SPEED_OF_LIGHT_M_S
# The largest |sine of the slant squint| X the chain admits (the band mask of eqs. 9-10, the H8 band): it
# keeps the mask away from end-fire, |X| = 1, where sqrt(1 - X^2) in the reference spectrum's phase (eq. 7
# under P1) has an infinite slope. One home: kernels/range.cl gets it as -DSQUINT_SINE_CAP (the engine's
# build), scipy32 imports it.
SQUINT_SINE_CAP = 0.98


# --------------------------------------------------------------------------------------------- transforms
def az_fft(x: np.ndarray) -> np.ndarray:
    return np.fft.fftshift(np.fft.fft(np.fft.ifftshift(x, axes=0), axis=0), axes=0)


def az_ifft(x: np.ndarray) -> np.ndarray:
    return np.fft.fftshift(np.fft.ifft(np.fft.ifftshift(x, axes=0), axis=0), axes=0)


def spectrum_rows_from_range_doppler(y_rows: np.ndarray, rows: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """fft2(image) / (n m) at the signed azimuth frequency indices `rows`, for the image az_ifft(Y), from
    those rows of Y (shape (..., rows.size, n_range)): detection's band-limited interpolation needs only
    these, and the azimuth IFFT then FFT cancel but for fft(fftshift(z)) = (-1)^k fft(z) (n even)."""
    return spectrum_rows_from_range_spectra(np.fft.fft(y_rows, axis=-1), rows, grid)


def spectrum_rows_from_range_spectra(y_rows_fft: np.ndarray, rows: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """`spectrum_rows_from_range_doppler` for rows already transformed along range."""
    sign = np.where(np.asarray(rows) % 2 == 0, 1.0, -1.0)[:, None]
    return y_rows_fft * (sign / (grid.n_azimuth * grid.n_range))


# --------------------------------------------------------------------------------------------- the grid
@dataclasses.dataclass(frozen=True)
class FocusGrid:
    """The processing frame of one pass: uniform track, padded azimuth grid, range bins, squint."""

    aperture_centre_m: float
    speed_m_s: float  # mean carriage speed; t_a is along-track distance / speed
    track_spacing_m: float  # uniform resampled pulse spacing
    n_track: int  # resampled pulses (odd; the middle one is at the aperture centre)
    n_azimuth: int  # padded azimuth FFT length (even)
    sin_squint: float  # theta_q: slant squint of the reference point (C1)
    reference_range_m: float  # r_ref = |T - O_s|
    range_window_start_s: float
    sample_rate_hz: float
    n_range: int
    carrier_frequency_hz: float
    pulse_sigma_s: float
    doppler_band: tuple[float, float]  # [X_lo, X_hi], support of the sine of the slant squint
    measured_pulse: MeasuredPulse | None = None  # None: the Gaussian of pulse_sigma_s

    def pulse_filter(self, f_hz) -> np.ndarray:
        """H4 = conj(P(f)) at baseband frequencies f_hz (eq. 10): every focuser's range matched filter."""
        return _pulse_filter(f_hz, self.pulse_sigma_s, self.measured_pulse)

    def pulse_waveform(self, t_s, matched: bool = False) -> np.ndarray:
        """The pulse p(t), or after H4 with `matched`: every point-response model's envelope."""
        return _pulse_waveform(t_s, self.pulse_sigma_s, self.measured_pulse, matched)

    def pulse_support_s(self, matched: bool = False) -> float:
        """Half-width (s) outside which `pulse_waveform` is negligible (`model.pulse_support_s`)."""
        return _pulse_support_s(self.pulse_sigma_s, self.measured_pulse, matched)

    @property
    def cos_squint(self) -> float:
        return math.sqrt(1.0 - self.sin_squint**2)

    @property
    def wavelength_m(self) -> float:
        return C / self.carrier_frequency_hz

    @property
    def two_way_wavenumber_rad_m(self) -> float:
        """k = 4 pi f_c / c: the carrier phase per metre of one-way range (eq. 2's exp(-j 4 pi f_c R / c))."""
        return 4.0 * math.pi * self.carrier_frequency_hz / C

    @property
    def dt_s(self) -> float:
        return self.track_spacing_m / self.speed_m_s

    @property
    def t_track_s(self) -> np.ndarray:
        return (np.arange(self.n_track) - (self.n_track - 1) // 2) * self.dt_s

    @property
    def azimuth_df_hz(self) -> float:
        """Azimuth frequency step of the padded grid, 1 / (n_azimuth dt)."""
        return 1.0 / (self.n_azimuth * self.dt_s)

    @property
    def half_track_s(self) -> float:
        """Azimuth time from the aperture centre to either end of the rail (uniform track)."""
        return 0.5 * (self.n_track - 1) * self.dt_s

    @property
    def t_azimuth_s(self) -> np.ndarray:
        return (np.arange(self.n_azimuth) - self.n_azimuth // 2) * self.dt_s

    @property
    def f_azimuth_hz(self) -> np.ndarray:
        return (np.arange(self.n_azimuth) - self.n_azimuth // 2) / (self.n_azimuth * self.dt_s)

    @property
    def f_range_hz(self) -> np.ndarray:
        return np.fft.fftfreq(self.n_range, 1.0 / self.sample_rate_hz)

    @property
    def range_bins_m(self) -> np.ndarray:
        return 0.5 * C * (self.range_window_start_s + np.arange(self.n_range) / self.sample_rate_hz)

    def nearest_bin(self, r_m) -> np.ndarray:
        """Index of the range bin nearest each range r_m (clipped to the window)."""
        bins = self.range_bins_m
        return np.clip(np.rint((np.asarray(r_m) - bins[0]) / (bins[1] - bins[0])), 0,
                       bins.size - 1).astype(int)


# The padded azimuth axis (docs/method.md D5). The data chain's axis spans AZIMUTH_GUARD times the centred
# interval that its signal occupies after H6, over the Doppler band of the range frequencies where the
# compressed pulse's spectrum P^2 is above COMPRESSED_SPECTRUM_FLOOR of its peak (the Gaussian pulse's P from
# `pulse_spectrum`).
AZIMUTH_GUARD = 1.5
COMPRESSED_SPECTRUM_FLOOR = 1e-2


def focus_grid(scan: ScanPass, azimuth_oversampling: float | None = None) -> FocusGrid:
    """The pass's processing frame. The azimuth axis is the shortest power of two that holds the chain's
    signal (D5: `azimuth_half_support_s` with its guard); azimuth_oversampling > 0 instead pads the track to
    that many times its length (the rule before D5: 8)."""
    x = np.sort(scan.pulse_position_m)
    n_track = scan.n_pulses | 1
    length = x[-1] - x[0]
    speed = abs(scan.mean_speed_m_s)
    x_c = scan.aperture_centre_m
    g = scan.geometry
    theta_q = geo.slant_squint_rad(g.reference_point_m, x_c, g.height_m)
    tx, ty, tz = g.reference_point_m
    r_ref = math.sqrt((tx - x_c) ** 2 + ty**2 + (tz - g.height_m) ** 2)
    grid = FocusGrid(
        aperture_centre_m=x_c, speed_m_s=speed, track_spacing_m=length / (n_track - 1), n_track=n_track,
        n_azimuth=0, sin_squint=math.sin(theta_q), reference_range_m=r_ref,
        range_window_start_s=scan.range_window_start_s, sample_rate_hz=scan.radar.sample_rate_hz,
        n_range=scan.samples_per_pulse, carrier_frequency_hz=scan.radar.carrier_frequency_hz,
        pulse_sigma_s=scan.radar.pulse_sigma_s, measured_pulse=scan.radar.measured_pulse,
        doppler_band=geo.slant_doppler_band(g, beam_aperture_m(scan), scan.radar.wavelength_m),
    )
    if azimuth_oversampling:
        n_az = 1 << math.ceil(math.log2(azimuth_oversampling * n_track))
    else:
        n_az = _power_of_two_holding(2.0 * AZIMUTH_GUARD * azimuth_half_support_s(grid), grid)
    return dataclasses.replace(grid, n_azimuth=max(n_az, 2))


def beam_aperture_m(scan: ScanPass) -> float:
    """The aperture (m) the focusing models the pass's beam with (eq. C6b, `geo.processed_aperture_m`)."""
    return geo.processed_aperture_m(scan.radar.antenna_aperture_m, scan.radar.wavelength_m)


def _power_of_two_holding(duration_s: float, grid: FocusGrid) -> int:
    """The shortest power-of-two azimuth axis of at least duration_s and of the whole track."""
    return 1 << math.ceil(math.log2(max(duration_s / grid.dt_s, grid.n_track)))


def h6_group_delay_s(f_hz, k: coef.NlcsCoefficients) -> np.ndarray:
    """-d arg H6 / d(2 pi f_a): the azimuth time H6 (eq. 15) moves the component at f_a by, per bin (D5).
    Shape (f_hz.size, n_bins)."""
    f = np.asarray(f_hz, dtype=float)[:, None]
    return -0.5 * (3.0 * k.y3 * f**2 + 4.0 * k.y4 * f**3)


def max_h6_delay_s(f_lo_hz: float, f_hi_hz: float, k: coef.NlcsCoefficients) -> float:
    """max |h6_group_delay_s| over f_a in [f_lo, f_hi] and every bin: the cubic's extremes are at the ends and
    where its derivative -(3 Y3 f + 6 Y4 f^2) vanishes (f = 0, f = -Y3 / (2 Y4))."""
    with np.errstate(divide="ignore", invalid="ignore"):
        turn = np.where(k.y4 != 0, -k.y3 / (2.0 * k.y4), 0.0)
    turn = np.clip(turn, f_lo_hz, f_hi_hz)
    f = np.stack([np.full_like(turn, f_lo_hz), np.full_like(turn, f_hi_hz), turn])
    return float(np.abs(0.5 * (3.0 * k.y3 * f**2 + 4.0 * k.y4 * f**3)).max())


def _azimuth_frequencies_hz(x_sine, f_abs_hz, grid: FocusGrid) -> np.ndarray:
    """f_a = 2 v F (X - s) / c of slant-squint sines X at absolute frequencies F (broadcast)."""
    return 2.0 * grid.speed_m_s * np.asarray(f_abs_hz) * (np.asarray(x_sine) - grid.sin_squint) / C


def _grid_coefficients(grid: FocusGrid) -> coef.NlcsCoefficients:
    return coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)


def azimuth_half_support_s(grid: FocusGrid) -> float:
    """The largest |t_a| the data chain's signal reaches after H6 (D5): the rail's half length plus the
    largest |H6 group delay| over the Doppler band (eqs. 9-10's mask) at the carrier and at the upper range
    frequency where the compressed pulse's spectrum is COMPRESSED_SPECTRUM_FLOOR of its peak, every bin."""
    lo, hi = grid.doppler_band
    f_r = pulse_frequency_at_hz(math.sqrt(COMPRESSED_SPECTRUM_FLOOR), grid.pulse_sigma_s)
    edges = _azimuth_frequencies_hz(np.array([[max(lo, -SQUINT_SINE_CAP)], [min(hi, SQUINT_SINE_CAP)]]),
                                    [grid.carrier_frequency_hz, grid.carrier_frequency_hz + f_r], grid)
    k = _grid_coefficients(grid)
    return grid.half_track_s + max_h6_delay_s(float(edges.min()), float(edges.max()), k)


def reference_grid(grid: FocusGrid, aperture_m: float) -> FocusGrid:
    """The azimuth axis the whole-beam reference of the exact-reference H8 is computed on (D5): long enough
    that the reference's response after H6 stays inside it (every bin), and a power-of-two multiple of the
    grid's, so its spectrum at the grid's frequencies is every m-th row (`on_grid_frequencies`)."""
    beam = geo.beam_half_width_rad(aperture_m, grid.wavelength_m)
    squint = math.asin(grid.sin_squint)
    x = np.array([max(math.sin(max(squint - beam, -math.pi / 2)), -SQUINT_SINE_CAP),
                  min(math.sin(min(squint + beam, math.pi / 2)), SQUINT_SINE_CAP)])
    k = _grid_coefficients(grid)
    # the reference is a carrier-frequency response; its stationary time at slant squint X (P1, t_n = 0),
    # v t = r (s - X cos(theta_q) / sqrt(1 - X^2)), decreases with X: largest |t| at the main lobe's edges.
    # |t_ref| + |H6 delay| bounds it (triangle inequality): the stationary time alone is only the centre of a
    # component, and the beam's edge components reach past it (measured: 1e-3 of X_ref's peak, 3 s)
    t_ref = np.abs(grid.sin_squint - x * grid.cos_squint / np.sqrt(1.0 - x**2)).max() * k.r_m.max()
    f = _azimuth_frequencies_hz(x, grid.carrier_frequency_hz, grid)
    reach = float(t_ref) / grid.speed_m_s + max_h6_delay_s(float(f.min()), float(f.max()), k)
    return dataclasses.replace(grid, n_azimuth=max(_power_of_two_holding(2.0 * reach, grid), grid.n_azimuth))


def on_grid_frequencies(x: np.ndarray, long_grid: FocusGrid, grid: FocusGrid) -> np.ndarray:
    """Rows of an azimuth spectrum on long_grid (centred or FFT order) at the frequencies of grid: every m-th
    row, m = long_grid.n_azimuth / grid.n_azimuth (both axes centred at index N/2: row 0 maps to row 0)."""
    return x[::long_grid.n_azimuth // grid.n_azimuth]


# --------------------------------------------------------------------------------------------- range stages
def range_fft(echo: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """S1(f_r, t_a) of eq. (3), with the absolute delay origin of the window."""
    return np.fft.fft(echo, axis=1) * np.exp(-2j * np.pi * grid.f_range_hz * grid.range_window_start_s)


def range_ifft(spectrum: np.ndarray, grid: FocusGrid) -> np.ndarray:
    return np.fft.ifft(spectrum * np.exp(2j * np.pi * grid.f_range_hz * grid.range_window_start_s), axis=1)


pulse_spectrum = gaussian_pulse_spectrum  # P(f) of the Gaussian pulse, P(0) = 1 (`FocusGrid.pulse_filter`)


def pulse_frequency_at_hz(level: float, sigma_s: float) -> float:
    """The range frequency |f_r| where `pulse_spectrum` falls to level (0 < level <= 1)."""
    return math.sqrt(0.5 * math.log(1.0 / level)) / (math.pi * sigma_s)


def linear_range_walk_phase(x_rel_m: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """arg H1 = -4 pi (f_c + f_r) v sin(theta_q) t_a / c  (eq. 4), with v t_a the logged rail position."""
    f = grid.carrier_frequency_hz + grid.f_range_hz
    return -4.0 * np.pi * np.outer(x_rel_m, f) * grid.sin_squint / C


def linear_range_walk_correction(s1: np.ndarray, x_rel_m: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """H1 (eq. 4)."""
    return s1 * np.exp(1j * linear_range_walk_phase(x_rel_m, grid))


LAGRANGE_ORDER = 6  # nodes of the motion-compensation resampling: a pass needs at least this many pulses


def lagrange_weights(x_nodes: np.ndarray, x_out: np.ndarray, order: int = LAGRANGE_ORDER):
    """Indices (n_out, order) of `order` consecutive nodes (sorted, increasing) and the Lagrange weights that
    interpolate from them to each x_out (n_out,).

    A gap in the track (`geometry.track_gaps`: pulses lost) is no data: an x_out inside one gets zero weights,
    and a stencil takes no node across one (its taps beyond the gap weigh 0 and the order drops where a run of
    pulses between gaps is shorter than `order`). Interpolating across a gap would extrapolate a polynomial
    over centimetres to decimetres of a signal with several cycles per decimetre: garbage in the image where
    a hole belongs. Without gaps: the plain `order`-point Lagrange stencil, centred where the ends allow.
    """
    n = x_nodes.size
    half = order // 2
    k = np.searchsorted(x_nodes, x_out)  # x_out lies between nodes k - 1 and k
    is_gap = geo.gap_intervals(x_nodes)
    run = np.concatenate([[0], np.cumsum(is_gap)])  # the run of pulses (between gaps) of each node
    first = np.searchsorted(run, np.arange(run[-1] + 1))  # each run's first node
    last = np.append(first[1:] - 1, n - 1)
    own = run[np.clip(k - 1, 0, n - 1)]  # the run of each x_out's left node (of node 0 before the track)
    inside_gap = np.concatenate([[False], is_gap, [False]])[k]
    j = np.clip(np.minimum(k - half, last[own] - order + 1), first[own], None)
    j = np.clip(j, 0, n - order)
    idx = j[:, None] + np.arange(order)[None, :]
    xn = x_nodes[idx]
    tap = run[idx] == own[:, None]  # taps in the x_out's own run
    w = np.ones((x_out.size, order))
    for m in range(order):
        for q in range(order):
            if q != m:
                w[:, m] *= np.where(tap[:, q], (x_out - xn[:, q]) / (xn[:, m] - xn[:, q]), 1.0)
    w = np.where(tap & ~inside_gap[:, None], w, 0.0)
    return idx, w


def resample_to_uniform_track(s: np.ndarray, x_rel_m: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """Motion compensation for rail-speed fluctuation: resample pulses from the logged positions onto the
    uniform track t_a = k dt. After LRWC the signal is slowly varying along the track, so 6-point Lagrange is
    accurate.
    """
    idx, w = lagrange_weights(x_rel_m, grid.t_track_s * grid.speed_m_s)
    return np.einsum("km,kmr->kr", w, s[idx])


def extended_nlcs(s: np.ndarray, p2: np.ndarray | float, grid: FocusGrid) -> np.ndarray:
    """H2 = exp(+j 4 pi (f_c + f_r) p2 t_a^2 / c)  (eq. 6). p2 = 0 on a straight rail under P1 (C3)."""
    if np.all(np.asarray(p2) == 0):
        return s
    f = grid.carrier_frequency_hz + grid.f_range_hz
    t = grid.t_track_s
    return s * np.exp(4j * np.pi * np.outer(p2 * t**2, f) / C)


def pad_azimuth(s: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """Zero-pad the uniform track onto the azimuth FFT grid with t_a = 0 at index N/2."""
    out = np.zeros((grid.n_azimuth, s.shape[1]), dtype=np.complex128)
    start = grid.n_azimuth // 2 - (grid.n_track - 1) // 2
    out[start:start + grid.n_track] = s
    return out


def slant_squint_sine(grid: FocusGrid, f_hz=None) -> np.ndarray:
    """X(f_r, f_a) = sin(theta_q) + c f_a / (2 v F): the slant squint of each 2-D frequency (C4), at the
    absolute frequencies F = f_c + f_r (default, shape (n_azimuth, n_range)) or at the given F."""
    f = grid.carrier_frequency_hz + grid.f_range_hz if f_hz is None else np.atleast_1d(f_hz)
    return grid.sin_squint + C * grid.f_azimuth_hz[:, None] / (2.0 * grid.speed_m_s * f[None, :])


def reference_spectrum_phase(x_sine: np.ndarray, f_hz: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """Exact phi(f_r, f_a) of the reference target (r0 = r_ref, t_n = 0), eq. (7) under P1 (C4)."""
    g = grid.cos_squint * np.sqrt(np.clip(1.0 - x_sine**2, 0.0, None)) + grid.sin_squint * x_sine
    return -4.0 * np.pi * grid.reference_range_m * f_hz / C * g


def secondary_range_compression(s2: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """H3 * H4 (eqs. 9-10, C5-C6): bulk SRC with the reference's exact phase, matched filter, band mask."""
    x = slant_squint_sine(grid)
    f = grid.carrier_frequency_hz + grid.f_range_hz
    x0 = slant_squint_sine(grid, grid.carrier_frequency_hz)
    phi = reference_spectrum_phase(x, f[None, :], grid)
    phi0 = reference_spectrum_phase(x0, grid.carrier_frequency_hz, grid)
    h3 = np.exp(-1j * (phi - phi0 + 4.0 * np.pi * grid.f_range_hz[None, :] * grid.reference_range_m / C))
    lo, hi = grid.doppler_band
    mask = (x >= lo) & (x <= hi) & (np.abs(x) < SQUINT_SINE_CAP)
    h4 = grid.pulse_filter(grid.f_range_hz)  # conj(P): the Gaussian's (real, even) or the measured pulse's
    return s2 * h3 * mask * h4[None, :]


# --------------------------------------------------------------------------------------------- azimuth stages
def azimuth_compensation(s3: np.ndarray, eta1: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """H5 = exp(-j pi eta1 f_a)  (eq. 13), per range bin. eta1 = 0 under P1."""
    if np.all(eta1 == 0):
        return s3
    return s3 * np.exp(-1j * np.pi * np.outer(grid.f_azimuth_hz, eta1))


def nlcs_filter_phase(f_hz: np.ndarray, k: coef.NlcsCoefficients) -> np.ndarray:
    """arg H6 = pi (Y3 f_a^3 + Y4 f_a^4)  (eq. 15), per range bin: shape (f_hz.size, n_bins)."""
    f = np.asarray(f_hz)[:, None]
    return np.pi * (k.y3 * f**3 + k.y4 * f**4)


def nlcs_filter(s: np.ndarray, k: coef.NlcsCoefficients, grid: FocusGrid) -> np.ndarray:
    """H6 (eq. 15)."""
    return s * np.exp(1j * nlcs_filter_phase(grid.f_azimuth_hz, k))


def nlcs_scaling_phase(t_s: np.ndarray, k: coef.NlcsCoefficients) -> np.ndarray:
    """arg H7 = pi (q2 t_a^2 + q3 t_a^3 + q4 t_a^4)  (eq. 15), absolute t_a, per range bin."""
    t = np.asarray(t_s)[:, None]
    return np.pi * (k.q2 * t**2 + k.q3 * t**3 + k.q4 * t**4)


def nlcs_scaling(s: np.ndarray, k: coef.NlcsCoefficients, grid: FocusGrid) -> np.ndarray:
    """H7 (eq. 15)."""
    return s * np.exp(1j * nlcs_scaling_phase(grid.t_azimuth_s, k))


@dataclasses.dataclass(frozen=True)
class AzimuthCompression:
    """H8 per range bin: exp(-j sum_k a_k (f_a / f_scale)^k) inside [f_lo, f_hi], zero outside."""

    poly: np.ndarray  # (n_range, degree + 1), ascending powers of f_a / f_scale
    f_scale_hz: float
    f_lo_hz: np.ndarray  # (n_range,)
    f_hi_hz: np.ndarray

    def phase(self, f_hz: np.ndarray) -> np.ndarray:
        u = np.asarray(f_hz)[:, None] / self.f_scale_hz
        out = np.zeros((u.shape[0], self.poly.shape[0]))
        for a in self.poly.T[::-1]:  # Horner
            out = out * u + a[None, :]
        return out

    def filter(self, f_hz: np.ndarray) -> np.ndarray:
        f = np.asarray(f_hz)[:, None]
        inside = (f >= self.f_lo_hz[None, :]) & (f <= self.f_hi_hz[None, :])
        return np.where(inside, np.exp(-1j * self.phase(f_hz)), 0.0)


def doppler_band_hz(grid: FocusGrid) -> tuple[float, float]:
    """Azimuth frequencies of the beam's slant-squint support at the carrier."""
    lo, hi = grid.doppler_band
    k = 2.0 * grid.speed_m_s / grid.wavelength_m
    return (max(lo, -SQUINT_SINE_CAP) - grid.sin_squint) * k, (min(hi, SQUINT_SINE_CAP) - grid.sin_squint) * k


def series_azimuth_compression(k: coef.NlcsCoefficients, grid: FocusGrid) -> AzimuthCompression:
    """H8 of eq. (17) with the corrected coefficients (C10)."""
    lo, hi = doppler_band_hz(grid)
    n = k.r_m.size
    poly = np.zeros((n, 5))
    poly[:, 2], poly[:, 3], poly[:, 4] = k.ac_c2, k.ac_c3, k.ac_c4
    return AzimuthCompression(poly=poly, f_scale_hz=1.0, f_lo_hz=np.full(n, lo), f_hi_hz=np.full(n, hi))


def slow_time_point_response(r_bin_m, t_n_s, grid: FocusGrid, aperture_m: float, rail_only: bool = True
                             ) -> np.ndarray:
    """Slow-time signal, in range bin r, of a target at azimuth time t_n after LRWC, SRC and RC (C11):
    w(t_a) exp{-j 4 pi / lambda [R(t_a) + v s_q t_a]} with r0 = r - v s_q t_n.  Shape (n_azimuth, n)."""
    r = np.atleast_1d(np.asarray(r_bin_m, dtype=float))[None, :]
    tn = np.atleast_1d(np.asarray(t_n_s, dtype=float))[None, :]
    t = grid.t_azimuth_s[:, None]
    v, s, lam = grid.speed_m_s, grid.sin_squint, grid.wavelength_m
    r0 = r - v * s * tn
    tau = t - tn
    rng = np.sqrt(r0**2 + (v * tau) ** 2 - 2 * r0 * v * tau * s)
    sin_look = (r0 * s - v * tau) / rng
    beam = geo.two_way_beam_gain(np.arcsin(sin_look), math.asin(s), aperture_m, lam)
    gain = beam * ((np.abs(t) <= grid.half_track_s + 1e-12) if rail_only else 1.0)
    seen = gain != 0  # the main lobe covers a fraction of the padded slow time: no phase needed elsewhere
    out = np.zeros(gain.shape, dtype=np.complex128)
    out[seen] = gain[seen] * np.exp(-4j * np.pi / lam * (rng + v * s * t)[seen])
    return out


def _azimuth_nlcs_chain(rd: np.ndarray, k: coef.NlcsCoefficients, grid: FocusGrid) -> np.ndarray:
    """H6 -> IFFT -> H7 -> FFT on range-Doppler columns (one column per bin of `k`)."""
    return az_fft(nlcs_scaling(az_ifft(nlcs_filter(rd, k, grid)), k, grid))


def select_bins(obj, j):
    """The dataclass (NlcsCoefficients, AzimuthCompression) with every per-bin array indexed by j: a subset of
    the bins, or one entry per column of a batch of simulated targets."""
    return dataclasses.replace(obj, **{f.name: getattr(obj, f.name)[j] for f in dataclasses.fields(obj)
                                       if isinstance(getattr(obj, f.name), np.ndarray)})


def reference_spectra(k: coef.NlcsCoefficients, grid: FocusGrid, aperture_m: float) -> np.ndarray:
    """X_ref: the t_n = 0 reference target of each bin of `k` after H6/H7, centred f_a (C11), at the grid's
    frequencies. The reference sees the whole beam (no rail ends): its spectrum is then smooth, and the fit is
    of the stationary-phase law rather than of the Gibbs ripple of one particular truncation. It is computed
    on `reference_grid`, which holds the whole beam's response after H6 (D5)."""
    long = reference_grid(grid, aperture_m)
    ref = az_fft(slow_time_point_response(k.r_m, 0.0, long, aperture_m, rail_only=False))
    return on_grid_frequencies(_azimuth_nlcs_chain(ref, k, long), long, grid)


# The H8 fit keeps the part of each bin's band where |X_ref| exceeds this fraction of its peak.
STRONG_REFERENCE_FRACTION = 1e-2


def exact_reference_azimuth_compression(k: coef.NlcsCoefficients, grid: FocusGrid, aperture_m: float,
                                        degree: int = 8) -> AzimuthCompression:
    """H8 matched to the simulated t_n = 0 reference of each bin after H6/H7 (C11, "exact-reference AC"),
    carried as a polynomial in f_a so a kernel can evaluate it from a few scalars. The carrier phase
    arg X_ref(0) is removed (C11)."""
    return fit_azimuth_compression(reference_spectra(k, grid, aperture_m), k, grid, degree)


def _unwrap_from(p: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Column j of p unwrapped from row start[j] on, bit for bit np.unwrap(p[start[j]:, j]); rows above
    start[j] are left as they are. np.unwrap's arithmetic (its default discont and period), but the mod 2 pi,
    most of its time, only on the steps it corrects (|dp| >= pi)."""
    dd = np.diff(p, axis=0)
    jump = ~(np.abs(dd) < np.pi) & (np.arange(1, p.shape[0])[:, None] > start)
    d = dd[jump]
    ddmod = np.mod(d + np.pi, 2 * np.pi) - np.pi
    ddmod[(ddmod == -np.pi) & (d > 0)] = np.pi
    correction = np.zeros_like(dd)
    correction[jump] = ddmod - d
    out = p.copy()
    out[1:] = p[1:] + correction.cumsum(axis=0)  # zeros before start[j] keep the segment's partial sums exact
    return out


def fit_azimuth_compression(x_ref: np.ndarray, k: coef.NlcsCoefficients, grid: FocusGrid, degree: int = 8
                            ) -> AzimuthCompression:
    """H8 polynomials from the reference spectra X_ref (centred f_a, one column per bin): a weighted fit of
    the unwrapped phase over the strong part of the band. Shared by the numpy chain and the OpenCL engine,
    which computes X_ref on the device."""
    # Vectorised over the bins because every backend calls this once per pass and a loop of np.unwrap +
    # polyfit per bin cost ~25 ms at 128 bins. Per bin it is the loop that tests/test_nlcs.py keeps as the
    # specification: the strong segment [lo, hi] (|X| > STRONG_REFERENCE_FRACTION max|X| within
    # [f_lo, f_hi]) must contain f_a = 0, else the series H8 stays; the phase is np.unwrap'ed along the
    # segment and referred to f_a = 0, and fitted by polyfit's weighted least squares (polyfit's
    # w = sqrt|X| multiplies the residuals: weights |X|).
    f = grid.f_azimuth_hz
    f_scale = 0.5 / grid.dt_s
    n = k.r_m.size
    series = series_azimuth_compression(k, grid)
    poly = np.zeros((n, degree + 1))
    f_lo, f_hi = series.f_lo_hz.copy(), series.f_hi_hz.copy()
    mag = np.abs(x_ref)
    i0 = grid.n_azimuth // 2
    band = np.flatnonzero((f >= f_lo.min()) & (f <= f_hi.max()))  # f increases: one run of rows
    b0 = band[0] if band.size else 0
    strong = ((mag[b0:b0 + band.size] > STRONG_REFERENCE_FRACTION * mag.max(axis=0))
              & (f[band, None] >= f_lo) & (f[band, None] <= f_hi))
    fitted = strong.any(axis=0)  # a bin without strong samples keeps the series too (the loop raised)
    lo = hi = np.zeros(n, dtype=int)
    if fitted.any():
        lo = b0 + np.argmax(strong, axis=0)
        hi = b0 + band.size - 1 - np.argmax(strong[::-1], axis=0)
        fitted &= (lo <= i0) & (i0 <= hi)
    # series powers of f_a -> of f_a / f_scale
    poly[~fitted, :5] = series.poly[~fitted] * f_scale ** np.arange(5)
    bins = np.flatnonzero(fitted)
    if bins.size == 0:
        return AzimuthCompression(poly=poly, f_scale_hz=f_scale, f_lo_hz=f_lo, f_hi_hz=f_hi)
    lo, hi = lo[bins], hi[bins]
    f_lo[bins], f_hi[bins] = f[lo], f[hi]
    # All bins on the union of their segments, a bin's rows outside its own with weight 0. The unwrap starts
    # at each bin's lo: unwrapping from the union's first row instead would only add a multiple of 2 pi,
    # which the reference to f_a = 0 removes, but with rounding (complex64 X_ref: ~3e-5 rad on the paper
    # passes).
    rows = slice(lo.min(), hi.max() + 1)
    cols = slice(None) if bins.size == n else bins
    phase = _unwrap_from(np.angle(x_ref[rows, cols]), lo - rows.start)
    phase -= phase[i0 - rows.start]
    r = np.arange(rows.start, rows.stop)[:, None]
    w = np.where((r >= lo) & (r <= hi), np.sqrt(mag[rows, cols]), 0.0)  # polyfit's w, in X_ref's precision
    b = (w * phase).astype(np.float64)  # polyfit's right-hand side, rounded as polyfit rounds it
    w = w.astype(np.float64)
    # Normal equations for all bins at once, G = V^T diag(w^2) V from one matmul, scaled to unit diagonal
    # (as polyfit scales its columns), then one step of iterative refinement. The scaled weighted Vandermonde
    # has condition ~150 on the paper passes (G: ~2e4); the H8 phase then agrees with polyfit's (SVD) to
    # ~1e-12 rad over the band, as a batched Householder QR's did at ~3x the time. Bins with cond G > 1e10
    # go to polyfit.
    m = degree + 1
    v = np.polynomial.polynomial.polyvander(f[rows] / f_scale, degree)
    g = ((w * w).T @ (v[:, :, None] * v[:, None, :]).reshape(-1, m * m)).reshape(-1, m, m)
    s = np.sqrt(np.diagonal(g, axis1=1, axis2=2))
    s = np.where(s > 0, s, 1.0)
    gs = g / s[:, :, None] / s[:, None, :]
    eig = np.linalg.eigvalsh(gs)
    ok = eig[:, 0] > 1e-10 * eig[:, -1]
    gs[~ok] = np.eye(m)  # solved harmlessly, then replaced
    c = np.linalg.solve(gs, ((w * b).T @ v / s)[:, :, None])[:, :, 0] / s
    c += np.linalg.solve(gs, ((w * (b - w * (v @ c.T))).T @ v / s)[:, :, None])[:, :, 0] / s
    poly[bins] = c
    for i in np.flatnonzero(~ok):  # (nearly) rank deficient, e.g. fewer samples than coefficients
        seg = slice(lo[i] - rows.start, hi[i] + 1 - rows.start)
        poly[bins[i]] = np.polynomial.polynomial.polyfit(v[seg, 1], phase[seg, i], degree,
                                                         w=np.sqrt(mag[lo[i]:hi[i] + 1, bins[i]]))
    return AzimuthCompression(poly=poly, f_scale_hz=f_scale, f_lo_hz=f_lo, f_hi_hz=f_hi)


def azimuth_compression(s: np.ndarray, ac: AzimuthCompression, grid: FocusGrid) -> np.ndarray:
    """H8 (eq. 17; C10, C11)."""
    return s * ac.filter(grid.f_azimuth_hz)


# --------------------------------------------------------------------------------------------- the chain
@dataclasses.dataclass
class NlcsProducts:
    """The focused image on the (t_a, r_LRCM) grid and what the geometry correction needs."""

    image: np.ndarray  # (n_azimuth, n_range)
    grid: FocusGrid
    coefficients: coef.NlcsCoefficients
    compression: AzimuthCompression
    aperture_m: float
    # fft2(image) / (n m) on the rows `spectrum_rows(grid, compression)`, where the focuser had it at hand
    # (detection interpolates the image from it); None: detection computes it from the image
    spectrum: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    # detection's t_n(t_f) calibration fits, keyed by range (they depend on the grid only, not on the image)
    focus_calibration: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)


def spectrum_band(grid: FocusGrid, ac: AzimuthCompression) -> tuple[float, float]:
    """The union of the per-bin H8 bands, in cycles per azimuth sample, with a one-sample margin."""
    return (float(ac.f_lo_hz.min()) * grid.dt_s - 1.0 / grid.n_azimuth,
            float(ac.f_hi_hz.max()) * grid.dt_s + 1.0 / grid.n_azimuth)


def band_rows(n: int, band: tuple[float, float]) -> np.ndarray:
    """Signed frequency indices, ascending, of the rows of an n-point DFT inside `band` (cycles per
    sample)."""
    ka = np.fft.fftfreq(n)
    natural = np.flatnonzero((ka >= band[0]) & (ka <= band[1]))
    return np.sort(np.where(natural < (n + 1) // 2, natural, natural - n))


def spectrum_rows(grid: FocusGrid, ac: AzimuthCompression) -> np.ndarray:
    """Signed azimuth frequency indices, ascending, of the rows that hold a focused image's 2-D spectrum
    (`spectrum_band`): what detection's band-limited interpolation sums."""
    return band_rows(grid.n_azimuth, spectrum_band(grid, ac))


def rail_deviation_range_m(scan: ScanPass) -> np.ndarray | None:
    """Per pulse (scan order), the first-order line-of-sight range change towards the scene reference T
    caused by the antenna's deviations from the straight rail (C14); None on a straight rail."""
    if scan.antenna_y_m is None and scan.antenna_z_m is None:
        return None
    g = scan.geometry
    return geo.line_of_sight_range_change_m(scan.pulse_position_m, scan.antenna_y_m, scan.antenna_z_m,
                                            g.reference_point_m, g.height_m)


def compensate_rail_deviations(echo: np.ndarray, dr_m: np.ndarray, grid: FocusGrid) -> np.ndarray:
    """First-order motion compensation (C14): each pulse's range spectrum times exp(+j 4 pi (f_c + f) dr / c),
    a range shift by -dr with its carrier phase, which moves the scene reference's echo back onto the
    straight rail's range history. Host-side float64 for every backend (via `prepare_track`)."""
    phase = 4.0 * np.pi * np.outer(dr_m, grid.carrier_frequency_hz + grid.f_range_hz) / C
    return np.fft.ifft(np.fft.fft(echo, axis=1) * np.exp(1j * phase), axis=1)


def subtract_background(echo: np.ndarray, mode: str) -> np.ndarray:
    """Background subtraction before focusing (docs/method.md section 4): "none" returns the echo itself;
    "mean" removes each fast-time sample's mean over the pulses, the echoes that stay at one range over the
    pass (the antenna's direct coupling, static clutter). A point target's echo migrates in range over the
    aperture, so its mean, and its loss, is small."""
    if mode == "none":
        return echo
    if mode == "mean":
        return echo - echo.mean(axis=0, keepdims=True)
    raise ValueError(f"unknown background mode {mode!r} (none|mean)")


def condition_pass(scan: ScanPass, background: str) -> ScanPass:
    """The pass with its background removed (`subtract_background`); the pass itself for "none"."""
    if background == "none":
        return scan
    return dataclasses.replace(scan, echo=subtract_background(scan.echo, background))


def prepare_track(scan: ScanPass, grid: FocusGrid) -> tuple[np.ndarray, np.ndarray]:
    """Echo rows in increasing rail position, rail deviations compensated (C14), and positions relative to
    the aperture centre."""
    order = np.argsort(scan.pulse_position_m)
    echo = scan.echo
    dr = rail_deviation_range_m(scan)
    if dr is not None:
        echo = compensate_rail_deviations(echo, dr, grid)
    return echo[order], scan.pulse_position_m[order] - grid.aperture_centre_m


def nlcs_focus(scan: ScanPass, *, ac_mode: str = "exact", grid: FocusGrid | None = None,
               compression: AzimuthCompression | None = None) -> NlcsProducts:
    """Focus one pass with the modified NLCS chain (float64 reference). `compression` reuses an H8 already
    computed for this grid (focusing model echoes of the same pass)."""
    grid = focus_grid(scan) if grid is None else grid
    echo, x_rel = prepare_track(scan, grid)
    k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
    s = range_fft(echo, grid)
    s = linear_range_walk_correction(s, x_rel, grid)
    s = resample_to_uniform_track(s, x_rel, grid)
    s = extended_nlcs(s, coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint), grid)
    s = az_fft(pad_azimuth(s, grid))
    s = secondary_range_compression(s, grid)
    s = range_ifft(s, grid)
    s = azimuth_compensation(s, k.eta1, grid)
    s = _azimuth_nlcs_chain(s, k, grid)
    aperture = beam_aperture_m(scan)
    if compression is not None:
        ac = compression
    elif ac_mode == "exact":
        ac = exact_reference_azimuth_compression(k, grid, aperture)
    elif ac_mode == "series":
        ac = series_azimuth_compression(k, grid)
    else:
        raise ValueError(f"unknown azimuth compression mode {ac_mode!r} (exact|series)")
    s = azimuth_compression(s, ac, grid)
    rows = spectrum_rows(grid, ac)
    return NlcsProducts(image=az_ifft(s), grid=grid, coefficients=k, compression=ac, aperture_m=aperture,
                        spectrum=spectrum_rows_from_range_doppler(s[grid.n_azimuth // 2 + rows], rows, grid))


def nlcs_model_spectra(products: NlcsProducts, x_rel_m: np.ndarray, echoes, rows: np.ndarray) -> np.ndarray:
    """Rows `rows` (signed azimuth indices) of fft2(image) / (n m) of the image each echo (pulses at x_rel_m,
    increasing) focuses to with the products' chain and H8: detection's neighbour models (float64 reference of
    `FocusEngine.nlcs_model_spectra`). The stages after the resampling multiply by filters that depend on the
    grid only, so they are computed once for all echoes; the last azimuth IFFT is not needed."""
    grid, k = products.grid, products.coefficients
    ones = np.ones((grid.n_azimuth, grid.n_range), dtype=np.complex128)
    src = secondary_range_compression(ones, grid)
    h5h6 = nlcs_filter(azimuth_compensation(ones, k.eta1, grid), k, grid)
    h7 = nlcs_scaling(ones, k, grid)
    centred_rows = grid.n_azimuth // 2 + np.asarray(rows)
    h8 = products.compression.filter(grid.f_azimuth_hz[centred_rows])
    p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
    out = []
    for echo in echoes:
        s = linear_range_walk_correction(range_fft(echo, grid), x_rel_m, grid)
        s = extended_nlcs(resample_to_uniform_track(s, x_rel_m, grid), p2, grid)
        s = range_ifft(az_fft(pad_azimuth(s, grid)) * src, grid) * h5h6
        out.append(az_fft(az_ifft(s) * h7)[centred_rows] * h8)
    return spectrum_rows_from_range_doppler(np.array(out), rows, grid)


# Samples of a calibration target's focused image within this fraction of its largest count as tied for the
# coarse maximum: float32 backends round at ~1e-7, and a response with two equal lobes (seen on a real
# PulsON 440 pass, t_n = 0: lobes at +-5 samples) otherwise starts the peak search on either lobe by rounding.
COARSE_TIE_RTOL = 1e-4


def coarse_focus_times(magnitude: np.ndarray, t_s: np.ndarray, t_n_s: np.ndarray) -> np.ndarray:
    """Each calibration target's coarse focus position (s): the time of its image's largest sample; among
    samples within COARSE_TIE_RTOL of it, the one nearest the target's t_n, then the first in `t_s`' order.
    The same choice on every backend, so the sub-sample search (`detect.calibration.peak_times`) refines the
    same lobe.

    Parameters
    ----------
    magnitude : ndarray, shape (n_targets, n_samples)
        |image| of each target along azimuth time.
    t_s : ndarray, shape (n_samples,)
        The samples' azimuth times (s), in the order of `magnitude`'s columns.
    t_n_s : ndarray, shape (n_targets,)
        Each target's t_n (s).
    """
    m = np.asarray(magnitude, dtype=float)
    t, t_n = np.asarray(t_s, dtype=float), np.asarray(t_n_s, dtype=float)
    tied = m >= (1.0 - COARSE_TIE_RTOL) * m.max(axis=1, keepdims=True)
    distance = np.where(tied, np.abs(t[None, :] - t_n[:, None]), np.inf)
    return t[np.argmin(distance, axis=1)]  # argmin: the first of equal distances


def calibration_spectra(products: NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Focused azimuth spectra of simulated point targets, for the t_f(t_n) calibration (eqs. 18-19, C12).

    One target per (r, t_n), each through the azimuth chain (H6, H7, H8) of the range bin nearest its r, as
    `slow_time_point_response` (rail only), `_azimuth_nlcs_chain` and `azimuth_compression` give it, with the
    same numbers, arranged for speed: the point response is evaluated on the rail's rows alone (the rest are
    zero), the FFTs run in their own (unshifted) order and in place, and H6, H7, H8 are computed once per bin
    (H8 on its band only).

    Parameters
    ----------
    products : NlcsProducts
        The pass's focus: its grid, per-bin coefficients and H8.
    r_m : ndarray, shape (n_r,)
        Ranges r_LRCM of the targets (m).
    t_n_s : ndarray, shape (n_t,)
        Azimuth times t_n of the targets (s), the same for every range.

    Returns
    -------
    f_hz : ndarray, shape (n_f,)
        Azimuth frequencies of the rows where H8 is not zero, in FFT (natural) order.
    y : ndarray, shape (n_f, n_r * n_t), complex128
        The focused spectra on those rows, one column per target, r-major (column i * n_t + j is (r_i, t_j)).
    coarse_s : ndarray, shape (n_r * n_t,)
        Each target's coarse focus position t_f (s): the azimuth time of its focused image's largest sample
        (`coarse_focus_times`).
    """
    grid = products.grid
    n = grid.n_azimuth
    j = grid.nearest_bin(r_m)
    bins_used, bin_of_r = np.unique(j, return_inverse=True)
    k, ac = select_bins(products.coefficients, bins_used), select_bins(products.compression, bins_used)
    f = np.fft.ifftshift(grid.f_azimuth_hz)
    band = (f >= ac.f_lo_hz.min()) & (f <= ac.f_hi_hz.max())
    ones = np.ones((n, bins_used.size), dtype=np.complex128)
    h6 = np.fft.ifftshift(nlcs_filter(ones, k, grid), axes=0).T[bin_of_r, None]
    h7 = np.fft.ifftshift(nlcs_scaling(ones, k, grid), axes=0).T[bin_of_r, None]
    h8 = np.zeros((bins_used.size, n), dtype=np.complex128)
    h8[:, band] = ac.filter(f[band]).T
    # the response on a grid of the rail's n_track (odd) + 1 rows: its t_a are the same integers times dt
    half = (grid.n_track + 1) // 2
    rail = slow_time_point_response(np.repeat(r_m, t_n_s.size), np.tile(t_n_s, r_m.size),
                                    dataclasses.replace(grid, n_azimuth=2 * half), products.aperture_m)
    # one contiguous row per target (the FFTs are faster along rows), then r-major
    s = np.zeros((r_m.size * t_n_s.size, n), dtype=np.complex128)
    s[:, :half], s[:, n - half:] = rail[half:].T, rail[:half].T  # ifftshift of the zero-padded response
    by_range = s.reshape(r_m.size, t_n_s.size, n)  # a view: the in-place products below act on s
    np.fft.fft(s, axis=1, out=s)
    by_range *= h6
    np.fft.ifft(s, axis=1, out=s)
    by_range *= h7
    np.fft.fft(s, axis=1, out=s)
    by_range *= h8[bin_of_r, None]
    coarse = coarse_focus_times(np.abs(np.fft.ifft(s, axis=1)), np.fft.ifftshift(grid.t_azimuth_s),
                                np.tile(t_n_s, r_m.size))
    return f[band], s[:, band].T, coarse
