"""Peaks of a focused image on its pixel grid: the floors, non-maximum suppression and where to search.

A peak is a pixel above both floors (relative to the strongest peak, and to the image's median magnitude, a
robust noise/clutter level) that is the largest pixel of its separation ellipse (`DetectionSettings`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..focus import backprojection as bp
from ..focus import nlcs
from ..records import DetectionSettings

# Range bins at each end of the NLCS image's window where no peak is sought: the image is periodic in range
# (range FFTs), and so is the interpolant that refines a peak, so near one edge it mixes in the other.
NLCS_RANGE_EDGE_BINS = 2
# Rows kept beyond the separation ellipse's reach at each end of the rail when the NLCS image is cropped: one
# for the 3x3 maximum filter, one to spare, so the crop's edges cannot change any test of a pixel on the rail.
NLCS_CROP_MARGIN_ROWS = 2


def local_peaks(mag: np.ndarray, valid: np.ndarray, pixel_m: tuple[float, float], s: DetectionSettings
                ) -> tuple[np.ndarray, float]:
    """Pixels above the floors that are the maximum of their separation ellipse (non-maximum suppression).

    Parameters
    ----------
    mag : ndarray, shape (n_a, n_r)
        |image|, azimuth along axis 0.
    valid : ndarray of bool, shape (n_a, n_r)
        Where peaks may lie (the floors are taken over these pixels too).
    pixel_m : (float, float)
        Pixel spacing along azimuth and range (m).
    s : DetectionSettings
        Floors (dB), the ellipse's semi-axes (m) and the most peaks kept.

    Returns
    -------
    pixels : ndarray of int, shape (n_peaks, 2)
        (row, column) of each peak, strongest first, at most `s.max_targets`.
    floor : float
        The median magnitude over `valid` (0 where nothing is valid): the noise level of the SNR.
    """
    floor = np.median(mag[valid]) if valid.any() else 0.0
    peak_max = mag[valid].max() if valid.any() else 0.0
    threshold = max(peak_max * 10 ** (s.relative_floor_db / 20), floor * 10 ** (s.min_snr_db / 20))
    na, nr = (int(s.separation_m / pixel_m[0]), int(s.range_separation_m / pixel_m[1]))
    a, r = np.ogrid[-na:na + 1, -nr:nr + 1]
    footprint = (a * pixel_m[0] / s.separation_m) ** 2 + (r * pixel_m[1] / s.range_separation_m) ** 2 <= 1.0
    candidates = valid & (mag > threshold)
    if na >= 1 and nr >= 1 and footprint[na - 1:na + 2, nr - 1:nr + 2].all():
        # The ellipse holds the 3x3 neighbourhood, so its maxima are 3x3 maxima: test the ellipse only there
        # (the same result as the full filter, at a fraction of its cost on a mostly empty image).
        candidates &= mag == ndimage.maximum_filter(mag, size=3, mode="nearest")
        offsets = np.argwhere(footprint) - (na, nr)
        idx = np.argwhere(candidates)
        rows = np.clip(idx[:, None, 0] + offsets[None, :, 0], 0, mag.shape[0] - 1)  # mode="nearest"
        cols = np.clip(idx[:, None, 1] + offsets[None, :, 1], 0, mag.shape[1] - 1)
        keep = mag[idx[:, 0], idx[:, 1]] >= mag[rows, cols].max(axis=1)
        idx = idx[keep]
    else:
        is_max = mag == ndimage.maximum_filter(mag, footprint=footprint, mode="nearest")
        idx = np.argwhere(candidates & is_max)
    order = np.argsort(mag[idx[:, 0], idx[:, 1]], kind="stable")[::-1][: s.max_targets]
    return idx[order], floor


def nlcs_peaks(products: nlcs.NlcsProducts, s: DetectionSettings) -> tuple[np.ndarray, float]:
    """`local_peaks` of an NLCS image, searched along the rail only.

    Targets focus at t_f within the rail's t_a (a few hundred of the padded rows): the image is cropped to
    those rows plus the separation ellipse's reach, beyond which the crop's edges cannot change any test, so
    the peaks and the floor are those of the whole image with the rail's rows valid.

    Parameters
    ----------
    products : NlcsProducts
        The focused pass: `image` (n_azimuth, n_range) on the centred (t_a, r_LRCM) grid.
    s : DetectionSettings
        Floors, the separation ellipse and the most peaks kept.

    Returns
    -------
    pixels : ndarray of int, shape (n_peaks, 2)
        (row, column) in the whole image (row n_azimuth/2 is t_a = 0), strongest first.
    floor : float
        Median |image| over the rail's rows.
    """
    grid = products.grid
    half_s = 0.5 * (grid.n_track - 1) * grid.dt_s
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    on_rail = np.flatnonzero(np.abs(grid.t_azimuth_s) <= half_s)
    reach = int(s.separation_m / grid.track_spacing_m) + NLCS_CROP_MARGIN_ROWS
    top, bottom = max(on_rail[0] - reach, 0), min(on_rail[-1] + reach + 1, grid.n_azimuth)
    mag = np.abs(products.image[top:bottom])
    valid = np.zeros(mag.shape, dtype=bool)
    valid[on_rail - top, NLCS_RANGE_EDGE_BINS:-NLCS_RANGE_EDGE_BINS] = True
    pixels, floor = local_peaks(mag, valid, (grid.track_spacing_m, dr), s)
    return pixels + (top, 0), floor


def bp_peaks(products: bp.BackprojectionProducts, s: DetectionSettings) -> tuple[np.ndarray, float]:
    """`local_peaks` of a backprojection image, its outermost pixels left out (a peak there is the image's
    edge, not a maximum).

    Parameters
    ----------
    products : BackprojectionProducts
        The focused pass: `image` (n_u, n_r) on the axes `u_axis_m`, `r_axis_m` (m).
    s : DetectionSettings
        Floors, the separation ellipse and the most peaks kept.

    Returns
    -------
    pixels : ndarray of int, shape (n_peaks, 2)
        (row, column) of each peak, strongest first.
    floor : float
        Median |image| over the inner pixels.
    """
    mag = np.abs(products.image)
    du = products.u_axis_m[1] - products.u_axis_m[0]
    dr = products.r_axis_m[1] - products.r_axis_m[0]
    valid = np.ones(mag.shape, dtype=bool)
    valid[[0, -1], :] = valid[:, [0, -1]] = False
    return local_peaks(mag, valid, (du, dr), s)
