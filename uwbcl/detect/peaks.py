"""Peaks of a focused image on its pixel grid: the floors, non-maximum suppression and where to search.

A peak is a pixel above both floors (relative to the strongest peak, and to the image's median magnitude, a
robust noise/clutter level), and optionally over its range bin's median by `cfar_db`, inside the region of
interest in R_c, that is the largest pixel of its separation ellipse (`DetectionSettings`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from .. import geometry as geo
from ..focus import backprojection as bp
from ..focus import nlcs
from ..records import DetectionSettings

# Range bins at each end of the NLCS image's window where no peak is sought: the image is periodic in range
# (range FFTs), and so is the interpolant that refines a peak, so near one edge it mixes in the other.
NLCS_RANGE_EDGE_BINS = 2
# Rows kept beyond the separation ellipse's reach at each end of the rail when the NLCS image is cropped: one
# for the 3x3 maximum filter, one to spare, so the crop's edges cannot change any test of a pixel on the rail.
NLCS_CROP_MARGIN_ROWS = 2
# A footprint search of an NLCS image looks this much further along track than the footprint itself: beyond
# the rail's ends one processing squint focuses a target up to ~0.45 m further out than its t_n (the
# focus-position map, detect.calibration), and the detections are checked against the footprint on their
# own t_n afterwards.
NLCS_FOOTPRINT_MARGIN_M = 0.5


def local_peaks(mag: np.ndarray, valid: np.ndarray, pixel_m: tuple[float, float], s: DetectionSettings,
                rc_m: np.ndarray | None = None, floor_mask: np.ndarray | None = None
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
    rc_m : ndarray, shape (n_a, n_r), optional
        Each pixel's closest-approach range (m): the adaptive threshold's bins (`s.cfar_db`); without it,
        the image's columns.
    floor_mask : ndarray of bool, shape (n_a, n_r), optional
        The pixels whose median is the noise level (default `valid`): a footprint search keeps the rail's,
        where the aperture is whole, so its SNRs, floor and adaptive levels are those of a rail search.

    Returns
    -------
    pixels : ndarray of int, shape (n_peaks, 2)
        (row, column) of each peak, strongest first, at most `s.max_targets`.
    floor : float
        The median magnitude over `floor_mask` (0 where it is empty): the noise level of the SNR.
    """
    on_floor = valid if floor_mask is None else floor_mask
    floor = np.median(mag[on_floor]) if on_floor.any() else 0.0
    peak_max = mag[valid].max() if valid.any() else 0.0
    threshold = detection_threshold(peak_max, floor, s)
    candidates = valid & (mag > threshold)
    if s.cfar_db > 0:
        level = range_bin_medians(mag, valid, rc_m, pixel_m[1], floor_mask, at=candidates)
        candidates &= mag > level * 10 ** (s.cfar_db / 20)
    na, nr = (int(s.separation_m / pixel_m[0]), int(s.range_separation_m / pixel_m[1]))
    a, r = np.ogrid[-na:na + 1, -nr:nr + 1]
    footprint = (a * pixel_m[0] / s.separation_m) ** 2 + (r * pixel_m[1] / s.range_separation_m) ** 2 <= 1.0
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


def detection_threshold(peak_max: float, floor: float, s: DetectionSettings) -> float:
    """The smallest |value| a peak may have: `s.relative_floor_db` under the strongest peak and `s.min_snr_db`
    over the noise level `floor` (the median magnitude)."""
    return max(peak_max * 10 ** (s.relative_floor_db / 20), floor * 10 ** (s.min_snr_db / 20))


def range_bin_medians(mag: np.ndarray, valid: np.ndarray, rc_m: np.ndarray | None, bin_m: float,
                      level_mask: np.ndarray | None = None, at: np.ndarray | None = None) -> np.ndarray:
    """Each pixel's clutter level for the adaptive threshold (`DetectionSettings.cfar_db`): the median of
    `mag` over the valid pixels of its range bin, shape of `mag`.

    The bins are `bin_m` wide in closest-approach range `rc_m` (a squinted image draws an echo at a constant
    delay, such as the antenna's coupling, along a line of constant R_c, not along a column); without
    `rc_m`, the image's columns. A pixel whose bin holds no valid pixel gets 0. With `level_mask` (a footprint
    search's rail pixels) a bin's median is over its pixels in `level_mask` where it has any: past the rail a
    constant-delay stripe fades, and a median taken there too would let the stripe through on the rail.
    With `at` (bool, shape of `mag`) only the bins of those pixels are computed (the same values; the others
    get 0): the threshold needs the level only where a pixel is already over the floors, and sorting every
    bin was ~7 ms of a paper pass's ~200 ms of detection.
    """
    if rc_m is None:
        bins = np.broadcast_to(np.arange(mag.shape[1])[None, :], mag.shape)
    else:  # bins on a fixed lattice in R_c, so a wider search draws the same bins as the rail's
        lowest = math.floor(rc_m[valid].min() / bin_m) * bin_m if valid.any() else 0.0
        bins = np.floor((rc_m - lowest) / bin_m).astype(np.int64)
    b_valid = bins[valid]
    n_bins = int(b_valid.max()) + 1 if b_valid.size else 1
    if n_bins > max(b_valid.size, mag.shape[1]):
        # far more bins than pixels (positions off by orders of magnitude spread R_c over kilometres): the
        # occupied bins renumbered in order, so memory follows the pixels, not the span (same medians)
        occupied = np.unique(b_valid)
        k = np.clip(np.searchsorted(occupied, bins), 0, occupied.size - 1)
        bins = np.where(occupied[k] == bins, k, -1)
        b_valid, n_bins = bins[valid], occupied.size
    if at is not None:  # only the bins holding a valid pixel of `at`
        wanted = np.zeros(n_bins, dtype=bool)
        wanted[bins[at & valid]] = True
        valid = valid & wanted[np.clip(bins, 0, n_bins - 1)]  # the clip only meets invalid pixels
        b_valid = bins[valid]
    medians = _bin_medians(mag[valid], b_valid, n_bins)
    if level_mask is not None:
        level = level_mask & valid
        on_level = _bin_medians(mag[level], bins[level], n_bins)
        has_level = np.bincount(bins[level], minlength=n_bins) > 0
        medians = np.where(has_level, on_level, medians)
    inside = (bins >= 0) & (bins < n_bins)
    return np.where(inside, medians[np.clip(bins, 0, n_bins - 1)], 0.0)


def _bin_medians(values: np.ndarray, b: np.ndarray, n_bins: int) -> np.ndarray:
    """The median of `values` in each bin `b` (0 .. n_bins - 1; 0 for an empty bin), shape (n_bins,)."""
    counts = np.bincount(b, minlength=n_bins)
    ordered = values[np.lexsort((values, b))]  # by bin, then by magnitude within it
    starts = np.cumsum(counts) - counts
    has = counts > 0
    medians = np.zeros(n_bins)
    lo, hi = starts[has] + (counts[has] - 1) // 2, starts[has] + counts[has] // 2
    medians[has] = 0.5 * (ordered[lo] + ordered[hi])
    return medians


def range_of_interest(rc_m: np.ndarray, s: DetectionSettings) -> np.ndarray:
    """Where a closest-approach range is inside the region of interest [min_range_m, max_range_m]
    (max_range_m = 0: no upper bound)."""
    inside = rc_m >= s.min_range_m
    if s.max_range_m > 0:
        inside &= rc_m <= s.max_range_m
    return inside


def nlcs_peaks(products: nlcs.NlcsProducts, s: DetectionSettings,
               footprint: geo.BeamFootprint | None = None) -> tuple[np.ndarray, float]:
    """`local_peaks` of an NLCS image, searched along the rail, or with `footprint` over the rail and the
    beam's footprint (`in_search`).

    Targets focus at t_f within the searched t_a (a few hundred of the padded rows): the image is cropped to
    those rows plus the separation ellipse's reach, beyond which the crop's edges cannot change any test, so
    the peaks and the floor are those of the whole image with the searched pixels valid.

    Parameters
    ----------
    products : NlcsProducts
        The focused pass: `image` (n_azimuth, n_range) on the centred (t_a, r_LRCM) grid.
    s : DetectionSettings
        Floors, the separation ellipse and the most peaks kept.
    footprint : BeamFootprint, optional
        The pass's beam footprint (`geometry.pass_footprint`); None: the rail only.

    Returns
    -------
    pixels : ndarray of int, shape (n_peaks, 2)
        (row, column) in the whole image (row n_azimuth/2 is t_a = 0), strongest first.
    floor : float
        Median |image| over the searched pixels.
    """
    grid = products.grid
    half_s = grid.half_track_s
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    reach = int(s.separation_m / grid.track_spacing_m) + NLCS_CROP_MARGIN_ROWS
    if footprint is None:
        searched = np.flatnonzero(np.abs(grid.t_azimuth_s) <= half_s)
    else:  # rows whose t_a can hold a footprint pixel, short of the image's ends by the crop's reach
        lo_m, hi_m = search_extent_u_m(grid, grid.range_bins_m, footprint)
        lo_m, hi_m = lo_m - NLCS_FOOTPRINT_MARGIN_M, hi_m + NLCS_FOOTPRINT_MARGIN_M
        u = grid.t_azimuth_s * grid.speed_m_s
        searched = np.flatnonzero((u >= lo_m) & (u <= hi_m))
        searched = searched[(searched >= reach) & (searched < grid.n_azimuth - reach)]
    if searched.size == 0:  # no row holds the footprint clear of the image's ends: nothing to find
        return np.zeros((0, 2), dtype=int), 0.0
    top, bottom = max(searched[0] - reach, 0), min(searched[-1] + reach + 1, grid.n_azimuth)
    mag = np.abs(products.image[top:bottom])
    valid = np.zeros(mag.shape, dtype=bool)
    valid[searched - top, NLCS_RANGE_EDGE_BINS:-NLCS_RANGE_EDGE_BINS] = True
    rc, on_rail = None, None
    if footprint is not None or s.min_range_m > 0 or s.max_range_m > 0 or s.cfar_db > 0:
        # R_c with t_n taken as t_a: the focus-position calibration moves a peak by at most a few cm
        t_a = grid.t_azimuth_s[top:bottom, None]
        rc = (grid.range_bins_m[None, :] - grid.speed_m_s * grid.sin_squint * t_a) * grid.cos_squint
        if footprint is not None:
            valid &= in_search(grid, grid.speed_m_s * t_a, grid.range_bins_m[None, :], footprint,
                               NLCS_FOOTPRINT_MARGIN_M)
        valid &= range_of_interest(rc, s)
        if footprint is not None:
            on_rail = valid & (np.abs(t_a) <= half_s)
    pixels, floor = local_peaks(mag, valid, (grid.track_spacing_m, dr), s, rc, on_rail)
    return pixels + (top, 0), floor


def in_search(grid: nlcs.FocusGrid, u_m: np.ndarray, r_lrcm_m: np.ndarray, footprint: geo.BeamFootprint,
              margin_m: float = 0.0) -> np.ndarray:
    """Where pixels at image azimuth u = v t_n and range r_LRCM (broadcast) are searched with a footprint:
    on the rail at the processing squint (|u| <= half the rail), or inside the footprint at their R_c,
    widened by `margin_m` along track."""
    x_rel, rc = bp.pixel_track_coordinates(u_m, r_lrcm_m, grid)
    lo, hi = footprint.x_rel_bounds_m(rc)
    inside = (x_rel >= lo - margin_m) & (x_rel <= hi + margin_m)
    return (np.abs(u_m) <= grid.half_track_s * grid.speed_m_s) | inside


def search_extent_u_m(grid: nlcs.FocusGrid, r_lrcm_m: np.ndarray, footprint: geo.BeamFootprint | None
                      ) -> tuple[float, float]:
    """Image azimuth u (m) covering the rail and, when given, the footprint at the ranges r_LRCM: the
    footprint's bounds are linear in R_c and u = x_rel - R_c tan(theta_q), so its ends at the nearest and
    farthest R_c bound it."""
    half = grid.half_track_s * grid.speed_m_s
    if footprint is None:
        return -half, half
    tan_q = grid.sin_squint / grid.cos_squint
    lo, hi = -half, half
    for r in (float(np.min(r_lrcm_m)), float(np.max(r_lrcm_m))):
        for u in (-half, half):  # R_c of the window's corners
            _, rc = bp.pixel_track_coordinates(u, r, grid)
            x_lo, x_hi = footprint.x_rel_bounds_m(rc)
            lo, hi = min(lo, float(x_lo - rc * tan_q)), max(hi, float(x_hi - rc * tan_q))
    return lo, hi


def bp_peaks(products: bp.BackprojectionProducts, s: DetectionSettings,
             footprint: geo.BeamFootprint | None = None) -> tuple[np.ndarray, float]:
    """`local_peaks` of a backprojection image over the rail, or with `footprint` over the rail and the
    footprint (`in_search`; the image must reach it: `search_extent_u_m`), its outermost pixels left out (a
    peak there is the image's edge, not a maximum).

    Parameters
    ----------
    products : BackprojectionProducts
        The focused pass: `image` (n_u, n_r) on the axes `u_axis_m`, `r_axis_m` (m).
    s : DetectionSettings
        Floors, the separation ellipse and the most peaks kept.
    footprint : BeamFootprint, optional
        The pass's beam footprint; None: the rail only.

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
    grid = products.grid
    if footprint is None:  # the rail only, whatever the image's extent
        valid &= (np.abs(products.u_axis_m) <= grid.half_track_s * grid.speed_m_s + 1e-9)[:, None]
    else:
        valid &= in_search(grid, products.u_axis_m[:, None], products.r_axis_m[None, :], footprint)
    rc, on_rail = None, None
    if footprint is not None or s.min_range_m > 0 or s.max_range_m > 0 or s.cfar_db > 0:
        rc = (products.r_axis_m[None, :] - grid.sin_squint * products.u_axis_m[:, None]) * grid.cos_squint
        valid &= range_of_interest(rc, s)
    if footprint is not None:  # the noise level of a rail search: its pixels, the rail's inner ones
        rail_rows = np.flatnonzero(np.abs(products.u_axis_m) <= grid.half_track_s * grid.speed_m_s + 1e-9)
        on_rail = np.zeros(mag.shape, dtype=bool)
        on_rail[rail_rows[1:-1]] = valid[rail_rows[1:-1]]
    return local_peaks(mag, valid, (du, dr), s, rc, on_rail)
