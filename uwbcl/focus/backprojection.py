"""Time-domain backprojection onto the slant plane: the exact reference focuser (paper section 4.2,
future work).

Pixels live on the same (u = v t_n, r_LRCM) axes as the NLCS image, so detection treats both alike:
r0 = r_LRCM - s_q u, x_M = x_c + u + r0 s_q, R_c = r0 c_q (P1). Each pixel sums the range-compressed echo at
its exact two-way delay over the logged rail positions, with the carrier phase restored, using only pulses
whose slant squint lies in the beam's Doppler band (the same support as the NLCS band mask).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model import SPEED_OF_LIGHT_M_S, ScanPass
from . import nlcs

C = SPEED_OF_LIGHT_M_S


@dataclasses.dataclass(frozen=True)
class RangeCompressed:
    data: np.ndarray  # (n_pulses, n_fine), pulses in increasing rail position
    x_rel_m: np.ndarray  # rail positions relative to the aperture centre
    t0_s: float  # absolute delay of fine sample 0
    dt_s: float  # fine sample spacing

    @property
    def t_s(self) -> np.ndarray:
        """Absolute delay of every fine sample."""
        return self.t0_s + self.dt_s * np.arange(self.data.shape[1])


def range_compress(scan: ScanPass, grid: nlcs.FocusGrid, upsample: int = 16) -> RangeCompressed:
    """Matched filter H4 (eq. 10) and band-limited upsampling of every pulse."""
    echo, x_rel = nlcs.prepare_track(scan, grid)
    n = grid.n_range
    spec = np.fft.fft(echo, axis=1) * grid.pulse_filter(grid.f_range_hz)[None, :]
    padded = np.zeros((echo.shape[0], n * upsample), dtype=np.complex128)
    half = n // 2
    padded[:, :half] = spec[:, :half]
    padded[:, -(n - half):] = spec[:, half:]
    data = np.fft.ifft(padded, axis=1) * upsample
    return RangeCompressed(data, x_rel, grid.range_window_start_s, 1.0 / (grid.sample_rate_hz * upsample))


def pixel_track_coordinates(u_m, r_lrcm_m, grid: nlcs.FocusGrid):
    """(x_M - x_c, R_c) of pixels given on the (u, r_LRCM) axes."""
    r0 = np.asarray(r_lrcm_m) - grid.sin_squint * np.asarray(u_m)
    return np.asarray(u_m) + r0 * grid.sin_squint, r0 * grid.cos_squint


def backproject_points(rc: RangeCompressed, grid: nlcs.FocusGrid, u_m, r_lrcm_m,
                       chunk: int = 4096) -> np.ndarray:
    """Complex BP value at arbitrary (u, r_LRCM) points (any shape)."""
    return backproject_track_points(rc, grid, *pixel_track_coordinates(u_m, r_lrcm_m, grid), chunk=chunk)


def backproject_track_points(rc: RangeCompressed, grid: nlcs.FocusGrid, x_rel_m, rc_m,
                             chunk: int = 4096, counts: bool = False):
    """Complex BP value at points given in track coordinates: along the rail relative to the aperture centre
    (x_M - x_c, m) and closest-approach range R_c (m), any broadcastable shapes. With `counts`, also how many
    pulses each point sums (same shape; the noise of a value is that many samples' noise)."""
    shape = np.broadcast_shapes(np.shape(x_rel_m), np.shape(rc_m))
    x_rel, rc_range = (np.asarray(a, dtype=float).ravel() for a in np.broadcast_arrays(x_rel_m, rc_m))
    out = np.zeros(x_rel.size, dtype=np.complex128)
    n_summed = np.zeros(x_rel.size, dtype=np.int64)
    k = grid.two_way_wavenumber_rad_m
    lo, hi = grid.doppler_band
    n_fine = rc.data.shape[1]
    flat = rc.data.ravel()
    for a in range(0, x_rel.size, chunk):
        xm, rcm = x_rel[a:a + chunk], rc_range[a:a + chunk]
        dx = xm[None, :] - rc.x_rel_m[:, None]  # (pulses, points)
        rng = np.sqrt(dx * dx + rcm[None, :] ** 2)
        in_beam = (dx >= lo * rng) & (dx <= hi * rng)
        pos = (2.0 * rng / C - rc.t0_s) / rc.dt_s
        i = np.floor(pos).astype(np.int64)
        frac = pos - i
        valid = in_beam & (i >= 0) & (i < n_fine - 1)
        i = np.where(valid, i, 0)
        base = np.arange(rc.data.shape[0])[:, None] * n_fine + i
        sample = (1.0 - frac) * flat[base] + frac * flat[base + 1]
        out[a:a + chunk] = np.sum(np.where(valid, sample * np.exp(1j * k * rng), 0.0), axis=0)
        n_summed[a:a + chunk] = np.count_nonzero(valid, axis=0)
    return (out.reshape(shape), n_summed.reshape(shape)) if counts else out.reshape(shape)


def point_target_echo(grid: nlcs.FocusGrid, x_rel_m: np.ndarray, t_s: np.ndarray, u_m: float, r_lrcm_m: float,
                      *, matched: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The echo (n_pulses, n_t) of a point target at (u, r_LRCM) with unit gain on every pulse, seen from the
    rail positions x_rel_m at the absolute delays t_s, and the pulses whose slant squint to it lies in the
    Doppler band (those `backproject_points` sums).

    Per pulse exp(-j 4 pi f_c R / c) p(t - 2R / c), R exact, with p the pulse of eq. (2) (the Gaussian
    exp(-t^2 / 2 sigma^2) or the measured pulse, `FocusGrid.pulse_waveform`), or with `matched` the pulse
    after its matched filter H4 (Gaussian: exp(-t^2 / 4 sigma^2) / sqrt(2)), as `range_compress` gives it.
    The beam gain w_a is the caller's.
    """
    x_rel, rc_range = pixel_track_coordinates(float(u_m), float(r_lrcm_m), grid)
    dx = x_rel - np.asarray(x_rel_m)
    rng = np.sqrt(dx * dx + rc_range**2)
    lo, hi = grid.doppler_band
    in_band = (dx >= lo * rng) & (dx <= hi * rng)
    k = grid.two_way_wavenumber_rad_m
    phase = np.exp(-1j * k * rng)
    t = np.asarray(t_s, dtype=float)
    delay = 2.0 * rng / C
    window = _support_columns(t, delay, grid.pulse_support_s(matched))
    if window is None:
        return phase[:, None] * grid.pulse_waveform(t[None, :] - delay[:, None], matched), in_band
    rows, cols = window  # the same samples, evaluated only where the pulse is not negligible
    out = np.zeros((rng.size, t.size), dtype=np.complex128)
    out[rows, cols] = phase[rows] * grid.pulse_waveform(t[cols] - delay[rows], matched)
    return out, in_band


def _support_columns(t_s: np.ndarray, delay_s: np.ndarray, half_s: float
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """(pulse, sample) indices of the samples of a uniform delay axis t_s within half_s of each pulse's delay
    (None where that does not save work: a measured pulse, a short or non-uniform axis)."""
    n = t_s.size
    if not math.isfinite(half_s) or n < 2:
        return None
    dt = (t_s[-1] - t_s[0]) / (n - 1)
    if not dt > 0:
        return None
    width = int(math.ceil(2.0 * half_s / dt)) + 2
    if 2 * width > n or np.abs(np.diff(t_s) - dt).max() > 1e-9 * dt:
        return None
    first = np.ceil((delay_s - half_s - t_s[0]) / dt).astype(np.int64)
    cols = first[:, None] + np.arange(width)
    rows = np.broadcast_to(np.arange(delay_s.size)[:, None], cols.shape)
    inside = (cols >= 0) & (cols < n)
    return rows[inside], cols[inside]


@dataclasses.dataclass
class BackprojectionProducts:
    image: np.ndarray  # (n_u, n_r)
    u_axis_m: np.ndarray
    r_axis_m: np.ndarray
    grid: nlcs.FocusGrid
    compressed: RangeCompressed


def image_axes(grid: nlcs.FocusGrid, pixel_m: float, range_margin_m: float,
               u_extent_m: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """u (= v t_n) and r_LRCM axes of the BP image: the rail's extent (or `u_extent_m` = (lo, hi), e.g. the
    beam's footprint, on the same pixel lattice), the range window less a margin."""
    half = 0.5 * (grid.n_track - 1) * grid.track_spacing_m
    if u_extent_m is None:
        u_axis = np.arange(-half, half + 1e-9, pixel_m)
    else:  # the rail's lattice extended by whole pixels, so the rail's pixels are the same
        below = math.ceil(max(0.0, -half - u_extent_m[0]) / pixel_m - 1e-9)
        above = math.ceil(max(0.0, u_extent_m[1] - half) / pixel_m - 1e-9)
        u_axis = -half + pixel_m * np.arange(-below, int(np.floor(2 * half / pixel_m + 1e-9)) + 1 + above)
    bins = grid.range_bins_m
    return u_axis, np.arange(bins[0] + range_margin_m, bins[-1] - range_margin_m, pixel_m)


def backprojection_focus(scan: ScanPass, *, pixel_m: float = 0.01, grid: nlcs.FocusGrid | None = None,
                         range_margin_m: float = 0.1, u_extent_m: tuple[float, float] | None = None
                         ) -> BackprojectionProducts:
    """BP image over the scene the pass can image: t_n within the rail (or `u_extent_m`), r_LRCM within the
    range window."""
    grid = nlcs.focus_grid(scan) if grid is None else grid
    rc = range_compress(scan, grid)
    u_axis, r_axis = image_axes(grid, pixel_m, range_margin_m, u_extent_m)
    image = backproject_points(rc, grid, u_axis[:, None], r_axis[None, :])
    return BackprojectionProducts(image=image, u_axis_m=u_axis, r_axis_m=r_axis, grid=grid, compressed=rc)
