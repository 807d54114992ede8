"""The modified NLCS chain in float32 with scipy.fft: what a careful CPU user would write instead of the
engine.

The stages, coefficients and products are those of `nlcs` (the float64 reference, which documents the chain
and its equation numbers); only the implementation differs:

* data are complex64; every phase is evaluated in float64 (its arguments reach hundreds of radians, beyond
  float32's resolution), reduced modulo 2 pi and applied as complex64 (`cis`); only the data-independent H8
  reference spectra stay complex128 (see `exact_reference_azimuth_compression`);
* FFTs are `scipy.fft` on all cores (`workers=-1`), in place;
* azimuth arrays stay in FFT (natural) order: the resampled track is written wrapped around index 0 and the
  frequency/time axes are permuted instead of the data, so the only shifts are of the final image and of the
  H8 reference spectra the shared fit expects centred;
* the range-Doppler rows outside the beam's Doppler band (zeroed by the band mask of eqs. 9-10) are dropped
  from the SRC, the range IFFT and H5/H6, and those outside H8's support from H8.

Used as the CPU baseline by `scripts/benchmark.py`; `tests/test_scipy32.py` holds it to the reference.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ..model import ScanPass
from . import coefficients as coef
from . import nlcs
from .reference import NumpyFocuser

C = nlcs.C
WORKERS = -1  # scipy.fft threads: all cores
TWO_PI = 2.0 * np.pi


def cis(phase: np.ndarray, dtype=np.complex64) -> np.ndarray:
    """exp(j phase) from a float64 phase, as complex64 unless asked, with no complex128 intermediate.

    For complex64 the phase is reduced to [-pi, pi] in float64 and only then rounded to float32 (error about
    2e-7 rad), where numpy's SIMD cos/sin run about 10x faster than in float64."""
    out = np.empty(np.shape(phase), dtype=dtype)
    if out.dtype == np.complex64:
        phase = (phase - TWO_PI * np.rint(phase * (1.0 / TWO_PI))).astype(np.float32)
    out.real = np.cos(phase)
    out.imag = np.sin(phase)
    return out


def _fft(x: np.ndarray, axis: int) -> np.ndarray:
    return sfft.fft(x, axis=axis, workers=WORKERS, overwrite_x=True)


def _ifft(x: np.ndarray, axis: int) -> np.ndarray:
    return sfft.ifft(x, axis=axis, workers=WORKERS, overwrite_x=True)


def natural_f_azimuth_hz(grid: nlcs.FocusGrid) -> np.ndarray:
    """The reference's f_a values permuted into FFT order (the same floats, so H8's band edges test alike)."""
    return np.fft.ifftshift(grid.f_azimuth_hz)


def natural_t_azimuth_s(grid: nlcs.FocusGrid) -> np.ndarray:
    return np.fft.ifftshift(grid.t_azimuth_s)


def range_fft_walk_corrected(echo: np.ndarray, x_rel_m: np.ndarray, grid: nlcs.FocusGrid) -> np.ndarray:
    """Range FFT with the window's delay origin (eq. 3) and H1 (eq. 4) as one phase."""
    s = _fft(np.array(echo, dtype=np.complex64), 1)
    phase = (-2.0 * np.pi * grid.range_window_start_s) * grid.f_range_hz[None, :] \
        + nlcs.linear_range_walk_phase(x_rel_m, grid)
    s *= cis(phase)
    return s


def resample_padded(s: np.ndarray, x_rel_m: np.ndarray, grid: nlcs.FocusGrid) -> np.ndarray:
    """`nlcs.resample_to_uniform_track` + ENLCS (eq. 6) + `pad_azimuth`, written in FFT order
    (t_a = 0 at 0)."""
    idx, w = nlcs.lagrange_weights(x_rel_m, grid.t_track_s * grid.speed_m_s)
    w = w.astype(np.float32)
    track = w[:, 0, None] * s[idx[:, 0]]
    for m in range(1, w.shape[1]):
        track += w[:, m, None] * s[idx[:, m]]
    p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
    track = nlcs.extended_nlcs(track, p2, grid).astype(np.complex64, copy=False)  # identity under P1
    half = (grid.n_track - 1) // 2
    out = np.zeros((grid.n_azimuth, grid.n_range), dtype=np.complex64)
    out[:grid.n_track - half] = track[half:]  # t_a >= 0
    out[grid.n_azimuth - half:] = track[:half]  # t_a < 0 wraps to the end
    return out


def doppler_band_rows(grid: nlcs.FocusGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows (FFT order) where the band mask of eqs. (9-10) passes anything, their X(f_r, f_a) and mask."""
    x = np.fft.ifftshift(nlcs.slant_squint_sine(grid), axes=0)
    lo, hi = grid.doppler_band
    mask = (x >= lo) & (x <= hi) & (np.abs(x) < nlcs.SQUINT_SINE_CAP)
    rows = np.flatnonzero(mask.any(axis=1))
    return rows, x[rows], mask[rows]


def secondary_range_compression_rows(s_rows: np.ndarray, rows: np.ndarray, x: np.ndarray, mask: np.ndarray,
                                     grid: nlcs.FocusGrid) -> np.ndarray:
    """H3 * mask * H4 (eqs. 9-10) with the range IFFT's delay origin (eq. 11), on the band rows only."""
    f_r = grid.f_range_hz
    x0 = np.fft.ifftshift(nlcs.slant_squint_sine(grid, grid.carrier_frequency_hz), axes=0)[rows]
    phi = nlcs.reference_spectrum_phase(x, (grid.carrier_frequency_hz + f_r)[None, :], grid)
    phi0 = nlcs.reference_spectrum_phase(x0, grid.carrier_frequency_hz, grid)
    phase = -(phi - phi0) + (2.0 * np.pi * (grid.range_window_start_s
                                            - 2.0 * grid.reference_range_m / C)) * f_r
    h4 = grid.pulse_filter(f_r)
    gain = (mask * h4[None, :]).astype(np.float32 if grid.measured_pulse is None else np.complex64)
    s_rows *= cis(phase)
    s_rows *= gain
    return s_rows


def azimuth_filter_rows(s_rows: np.ndarray, rows: np.ndarray, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                        with_h5: bool = True) -> np.ndarray:
    """H5 (eq. 13, skipped when eta1 = 0 as under P1) and H6 (eq. 15) on the given range-Doppler rows."""
    f = natural_f_azimuth_hz(grid)[rows]
    phase = nlcs.nlcs_filter_phase(f, k)
    if with_h5 and np.any(k.eta1 != 0):
        phase -= np.pi * f[:, None] * k.eta1
    s_rows *= cis(phase, s_rows.dtype)
    return s_rows


def nlcs_scaling(s: np.ndarray, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid) -> np.ndarray:
    """H7 (eq. 15) on a range-time array in FFT order."""
    s *= cis(nlcs.nlcs_scaling_phase(natural_t_azimuth_s(grid), k), s.dtype)
    return s


def azimuth_nlcs_chain(rd_rows: np.ndarray, rows: np.ndarray, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                       with_h5: bool = True) -> np.ndarray:
    """H5/H6 on the rows that carry signal -> azimuth IFFT -> H7 -> azimuth FFT; full array in FFT order."""
    full = np.zeros((grid.n_azimuth, rd_rows.shape[1]), dtype=rd_rows.dtype)
    full[rows] = azimuth_filter_rows(rd_rows, rows, k, grid, with_h5)
    return _fft(nlcs_scaling(_ifft(full, 0), k, grid), 0)


def reference_point_response(k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float,
                             dtype=np.complex128) -> np.ndarray:
    """`nlcs.slow_time_point_response(r_bins, 0, grid, aperture, rail_only=False)` in FFT order."""
    response = nlcs.slow_time_point_response(k.r_m, 0.0, grid, aperture_m, rail_only=False)
    return np.fft.ifftshift(response, axes=0).astype(dtype, copy=False)


def exact_reference_azimuth_compression(k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float
                                        ) -> nlcs.AzimuthCompression:
    """As `nlcs.exact_reference_azimuth_compression`. The reference spectra stay complex128: the fit keeps
    the samples above a hard 1e-2 magnitude threshold, so float32 rounding can move a bin's band edge by one
    sample and change that bin's H8 (seen: 2e-3 relative image error)."""
    long = nlcs.reference_grid(grid, aperture_m)  # D5: the whole beam's response fits its axis
    ref = _fft(reference_point_response(k, long, aperture_m, np.complex128), 0)
    x_ref = azimuth_nlcs_chain(ref, np.arange(long.n_azimuth), k, long, with_h5=False)
    return nlcs.fit_azimuth_compression(np.fft.fftshift(nlcs.on_grid_frequencies(x_ref, long, grid), axes=0),
                                        k, grid)


def azimuth_compression(s: np.ndarray, ac: nlcs.AzimuthCompression, grid: nlcs.FocusGrid) -> np.ndarray:
    """H8 (eq. 17; C10, C11) in FFT order, evaluated only on the rows inside some bin's [f_lo, f_hi]."""
    f = natural_f_azimuth_hz(grid)
    rows = np.flatnonzero((f >= ac.f_lo_hz.min()) & (f <= ac.f_hi_hz.max()))
    fr = f[rows]
    inside = (fr[:, None] >= ac.f_lo_hz[None, :]) & (fr[:, None] <= ac.f_hi_hz[None, :])
    h8 = cis(-ac.phase(fr))
    h8 *= inside
    out = np.zeros_like(s)
    out[rows] = s[rows] * h8
    return out


def _compressed_spectrum(echo: np.ndarray, x_rel: np.ndarray, grid: nlcs.FocusGrid, k: coef.NlcsCoefficients,
                         ac: nlcs.AzimuthCompression) -> np.ndarray:
    """echo -> the range-Doppler array after H8 (FFT order): the chain up to its last IFFT."""
    s = range_fft_walk_corrected(echo, x_rel, grid)
    s = _fft(resample_padded(s, x_rel, grid), 0)
    rows, x, mask = doppler_band_rows(grid)
    s_rows = secondary_range_compression_rows(s[rows], rows, x, mask, grid)
    s = azimuth_nlcs_chain(_ifft(s_rows, 1), rows, k, grid, with_h5=True)
    return azimuth_compression(s, ac, grid)


def nlcs_focus_scipy32(scan: ScanPass, ac_mode: str = "exact", grid: nlcs.FocusGrid | None = None,
                       compression: nlcs.AzimuthCompression | None = None) -> nlcs.NlcsProducts:
    """Focus one pass with the modified NLCS chain in float32 (same products as `nlcs.nlcs_focus`, whose
    parameters these are; `compression` reuses an H8 already computed for this grid)."""
    if ac_mode not in ("exact", "series"):
        raise ValueError(f"unknown azimuth compression mode {ac_mode!r} (exact|series)")
    grid = nlcs.focus_grid(scan) if grid is None else grid
    echo, x_rel = nlcs.prepare_track(scan, grid)
    k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
    aperture = nlcs.beam_aperture_m(scan)
    if compression is not None:
        ac = compression
    else:
        ac = (exact_reference_azimuth_compression(k, grid, aperture) if ac_mode == "exact"
              else nlcs.series_azimuth_compression(k, grid))
    image = np.fft.fftshift(_ifft(_compressed_spectrum(echo, x_rel, grid, k, ac), 0), axes=0)
    return nlcs.NlcsProducts(image=image, grid=grid, coefficients=k, compression=ac, aperture_m=aperture)


def nlcs_model_spectra(products: nlcs.NlcsProducts, x_rel_m: np.ndarray, echoes,
                       rows: np.ndarray) -> np.ndarray:
    """As `FocusEngine.nlcs_model_spectra`: rows `rows` (signed azimuth indices) of fft2(image) / (n m) of
    each model echo's image, from the range-Doppler array after H8 (no last IFFT)."""
    grid, k, ac = products.grid, products.coefficients, products.compression
    y = np.array([_compressed_spectrum(e, x_rel_m, grid, k, ac)[np.asarray(rows) % grid.n_azimuth]
                  for e in echoes])
    return nlcs.spectrum_rows_from_range_doppler(y, rows, grid)


class Scipy32Focuser(NumpyFocuser):
    """`Focuser` of the float32 scipy baseline: the NLCS image and the neighbour models by this module's
    chain.

    Backprojection, its track points and the calibration targets have no float32 version here: they are the
    float64 reference's (`NumpyFocuser`'s methods), as they were before this class when detection fell back to
    the reference for what the module lacked."""

    def __repr__(self) -> str:
        return "Scipy32Focuser()"

    def nlcs_focus(self, scan: ScanPass, *, ac_mode: str = "exact", grid: nlcs.FocusGrid | None = None,
                   compression: nlcs.AzimuthCompression | None = None) -> nlcs.NlcsProducts:
        """`nlcs_focus_scipy32` (see `Focuser.nlcs_focus`)."""
        return nlcs_focus_scipy32(scan, ac_mode=ac_mode, grid=grid, compression=compression)

    def nlcs_model_spectra(self, products: nlcs.NlcsProducts, x_rel_m: np.ndarray, echoes,
                           rows: np.ndarray) -> np.ndarray:
        """This module's `nlcs_model_spectra` (see `Focuser.nlcs_model_spectra`)."""
        return nlcs_model_spectra(products, x_rel_m, echoes, rows)


SCIPY32_FOCUSER = Scipy32Focuser()
