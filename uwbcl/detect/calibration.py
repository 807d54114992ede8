"""The NLCS focus-position calibration t_f(t_n) and its inverse (eqs. 18-19, C12, docs/method.md section 2).

NLCS focuses a target that crosses the beam centre at t_n at t_f = t_n + (b/2) t_n^2 + ...: up to 36 mm of
distortion at the aperture ends. The map is calibrated per range bin by simulation: point targets at the
bin's range across the aperture go through the bin's azimuth chain (`Focuser.calibration_spectra`, on the same
backend as the image), each focused peak is located to 1e-10 s (`peak_times`), and t_n(t_f) is a polynomial
fitted through them (`invert_focus_position`, cached per bin in the products), interpolated linearly in range
between the two bins around a peak.
"""

from __future__ import annotations

import math

import numpy as np

from ..focus import nlcs
from ..focus.protocol import Focuser
from ..focus.reference import NUMPY_FOCUSER

# Simulated targets per calibrated range, evenly across the rail's t_a: more than twice the fit's
# coefficients, so the fit is a least-squares one through every part of the aperture.
CALIBRATION_TARGETS = 13
# Beyond the rail's ends (docs/method.md section 4, footprint search) t_f(t_n) is far from the identity (at
# 1 m past the end of paper-sim1's rail a target focuses 0.44 m further out) and ends where the rail sees too
# little of a target: it is simulated every 5 cm from 0.1 m inside the rail's end to 3 m past it, and inverted
# locally about each peak.
BEYOND_STEP_M = 0.05
BEYOND_OVERLAP_M = 0.1
BEYOND_REACH_M = 3.0
# Degree of the t_n(t_f) polynomial: the distortion is a smooth series in t_n (t_n + (b/2) t_n^2 + ...).
CALIBRATION_DEGREE = 5
# Newton on |Y(t)|^2 for each focused peak: stop once every step is shorter than 1e-10 s (well under a
# micrometre along track at the rail's speeds), after at most 30 steps.
PEAK_TIME_TOL_S = 1e-10
PEAK_TIME_MAX_ITER = 30
# Taylor terms of Y about the coarse maximum: the tail beyond is < pi^33 / 33! < 1e-20 of sum |y_f|.
PEAK_TIME_SERIES_ORDER = 32
# The coarse maximum is the largest sample, so the peak is within one sample of it; half a sample per step.
PEAK_TIME_MAX_STEP_SAMPLES = 0.5
# A trial point whose |Y|^2 is lower by less than this relative amount is rounding, not a worse point.
ROUNDING_RTOL = 1e-13


def peak_times(f_hz: np.ndarray, y: np.ndarray, t0_s: np.ndarray, dt_s: float, tol_s: float = PEAK_TIME_TOL_S,
               max_iter: int = PEAK_TIME_MAX_ITER, order: int = PEAK_TIME_SERIES_ORDER) -> np.ndarray:
    """Per column c of y, the t in [t0_c - dt, t0_c + dt] that maximises g(t) = |Y(t)|^2,
    Y(t) = sum_f exp(2 pi i f t) y_f, by Newton's method on all columns at once.

    About t0 (the coarse maximum), Y(t0 + x dt) = sum_p m_p x^p / p! with m_p = sum_f (2 pi i f dt)^p y_f
    exp(2 pi i f t0): for |x| <= 1 the series' tail beyond `order` is below pi^(order+1) / (order+1)! < 1e-20
    of sum |y_f|, so after one pass over y (the m_p) each Newton step costs a few small polynomials. Steps are
    at most dt / 2, a damped ascent step where g is not concave, and a step that lowers g is retried at half
    its length; stops once every step is shorter than tol_s.

    Parameters
    ----------
    f_hz : ndarray, shape (n_f,)
        Azimuth frequencies of the rows of y (Hz), |f dt| <= 1/2.
    y : ndarray, shape (n_f, n_targets), complex
        Focused azimuth spectra, one column per target.
    t0_s : ndarray, shape (n_targets,)
        Coarse maxima (s).
    dt_s : float
        Azimuth sample spacing (s).

    Returns
    -------
    ndarray, shape (n_targets,)
        The focus positions t_f (s).
    """
    p = np.arange(order + 3)
    powers = np.empty((p.size, f_hz.size), dtype=np.complex128)  # (2 pi i f dt)^p
    powers[0] = 1.0
    for k in p[1:]:
        np.multiply(powers[k - 1], 2j * np.pi * dt_s * f_hz, out=powers[k])
    m = powers @ (y * np.exp(2j * np.pi * np.outer(f_hz, t0_s)))  # m_q = dt^q Y^(q)(t0), one row per q
    inv_factorial = 1.0 / np.cumprod(np.maximum(p[:order + 1], 1)).astype(float)

    def local(x):  # g and its first two derivatives in x = (t - t0) / dt
        series = x[None, :] ** p[:order + 1, None] * inv_factorial[:, None]
        y0, y1, y2 = ((m[q:q + order + 1] * series).sum(axis=0) for q in range(3))
        return np.abs(y0) ** 2, 2.0 * (y0.conj() * y1).real, 2.0 * (np.abs(y1) ** 2 + (y0.conj() * y2).real)

    x = np.zeros(np.shape(t0_s))
    g, dg, ddg = local(x)
    radius = np.full(x.shape, PEAK_TIME_MAX_STEP_SAMPLES)
    for _ in range(max_iter):
        concave = ddg < 0
        newton = -dg / np.where(concave, ddg, -1.0)
        step = np.clip(np.where(concave, newton, np.sign(dg) * radius), -radius, radius)
        step = np.clip(x + step, -1.0, 1.0) - x
        active = np.abs(step) >= tol_s / dt_s
        if not active.any():
            break
        g1, dg1, ddg1 = local(x + step)
        ok = active & (g1 >= g * (1.0 - ROUNDING_RTOL))  # not worse beyond rounding
        x = np.where(ok, x + step, x)
        g, dg, ddg = np.where(ok, g1, g), np.where(ok, dg1, dg), np.where(ok, ddg1, ddg)
        radius = np.where(ok, np.minimum(PEAK_TIME_MAX_STEP_SAMPLES, 2.0 * radius),
                          np.where(active, 0.5 * np.abs(step), radius))
    return t0_s + x * dt_s


def focus_position(products: nlcs.NlcsProducts, r_m, t_n_s: np.ndarray, focuser: Focuser = NUMPY_FOCUSER
                   ) -> np.ndarray:
    """t_f(t_n): where the azimuth chain of the bin nearest r focuses targets at t_n (simulated).

    Parameters
    ----------
    products : NlcsProducts
        The pass's focus.
    r_m : float or ndarray, shape (n_r,)
        Range(s) r_LRCM (m).
    t_n_s : ndarray, shape (n_t,)
        Azimuth times of the simulated targets (s).
    focuser : Focuser
        Simulates the targets (`calibration_spectra`); the backend that focused the pass.

    Returns
    -------
    ndarray, shape (n_t,) for a float `r_m`, else (n_r, n_t)
        The focus positions t_f (s).
    """
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    t_n = np.asarray(t_n_s, dtype=float).ravel()
    f, y, coarse = focuser.calibration_spectra(products, r, t_n)
    t_f = peak_times(f, y, coarse, products.grid.dt_s).reshape(r.size, t_n.size)
    return t_f if np.ndim(r_m) else t_f[0]


def bracketing_bins(grid: nlcs.FocusGrid, r_m) -> tuple[np.ndarray, np.ndarray]:
    """The range bin j at or below each r and the fraction w of a bin that r lies above it: r between the
    bins j and j + 1 (clipped to the first and last bins, where w is 0 or 1)."""
    bins = grid.range_bins_m
    if bins.size < 2:
        return np.zeros(np.size(r_m), dtype=int), np.zeros(np.size(r_m))
    pos = (np.atleast_1d(np.asarray(r_m, dtype=float)) - bins[0]) / (bins[1] - bins[0])
    j = np.clip(np.floor(pos), 0, bins.size - 2).astype(int)
    return j, np.clip(pos - j, 0.0, 1.0)


def invert_focus_position(products: nlcs.NlcsProducts, r_m, t_f_s, degree: int = CALIBRATION_DEGREE,
                          focuser: Focuser = NUMPY_FOCUSER):
    """t_n from the focused t_f: per range bin, t_n(t_f) fitted through `CALIBRATION_TARGETS` simulated
    targets at the bin's range across the rail (cached in `products.focus_calibration` under (bin, degree);
    the missing fits are simulated together), and at a range r between two bins the two bins' t_n
    interpolated linearly in r. A peak focused beyond the rail's ends (|t_f| more than half the rail plus
    BEYOND_STEP_M / 2) is inverted on a map simulated past that end (`_beyond_map`, cached under
    (r, degree, side)); NaN where the map does not reach it.

    Why between bins: each bin has its own azimuth chain (per-bin coefficients, C8), so a target focuses at a
    t_f that drifts from bin to bin, and the image between two bins is their interpolation. One bin's map
    (the nearest's) is off by that drift, a sawtooth in the fractional bin (up to +-2 mm along track at 45 deg
    squint), and jumps where the nearest bin changes.

    Parameters
    ----------
    products : NlcsProducts
        The pass's focus; its `focus_calibration` cache is filled.
    r_m : float or ndarray, shape (n,)
        Peak ranges r_LRCM (m).
    t_f_s : float or ndarray, shape (n,)
        Peak focus positions t_f (s), broadcast against `r_m`.
    degree : int
        Degree of the polynomial t_n(t_f).
    focuser : Focuser
        Simulates the calibration targets.

    Returns
    -------
    float, or ndarray of shape (n,) when either input is an array
        t_n (s).
    """
    cache = products.focus_calibration
    grid = products.grid
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    t_f = np.broadcast_to(np.asarray(t_f_s, dtype=float), r.shape)
    half = grid.half_track_s
    outside = np.abs(t_f) > half + 0.5 * BEYOND_STEP_M / grid.speed_m_s  # a rail search's peaks never are
    j, w = bracketing_bins(grid, r)
    upper = np.minimum(j + 1, grid.range_bins_m.size - 1)
    bins = np.unique(np.concatenate([j[~outside], upper[~outside]]))
    missing = [int(b) for b in bins if (int(b), degree) not in cache]
    if missing:
        t_n = np.linspace(-half, half, CALIBRATION_TARGETS)
        for b, t_fit in zip(missing, focus_position(products, grid.range_bins_m[missing], t_n, focuser)):
            cache[(b, degree)] = np.polynomial.polynomial.polyfit(t_fit, t_n, degree)
    sides = [(float(x), degree, 1 if t > 0 else -1) for x, t in zip(r[outside], t_f[outside])]
    for k in dict.fromkeys(k for k in sides if k not in cache):
        cache[k] = _beyond_map(products, k[0], k[2], focuser)
    poly = np.polynomial.polynomial.polyval

    def within(t, lo, hi, wi):
        return (1.0 - wi) * poly(t, cache[(int(lo), degree)]) + wi * poly(t, cache[(int(hi), degree)])

    out = np.array([_invert_beyond(cache[(float(x), degree, 1 if t > 0 else -1)], t, degree) if o
                    else within(t, lo, hi, wi) for x, t, o, lo, hi, wi in zip(r, t_f, outside, j, upper, w)])
    return out if np.ndim(r_m) or np.ndim(t_f_s) else float(out[0])


def _beyond_map(products: nlcs.NlcsProducts, r_m: float, sign: int, focuser: Focuser
                ) -> tuple[np.ndarray, np.ndarray]:
    """(t_n, t_f) of simulated targets at range r from inside the rail's `sign` end outwards, every
    BEYOND_STEP_M out to BEYOND_REACH_M past it, cut where t_f stops moving outwards (past it the rail sees
    too little of a target for the chain to focus it: docs/method.md section 4)."""
    grid = products.grid
    v = grid.speed_m_s
    start = grid.half_track_s - BEYOND_OVERLAP_M / v
    steps = np.arange(int(round((BEYOND_REACH_M + BEYOND_OVERLAP_M) / BEYOND_STEP_M)) + 1)
    t_n = sign * (start + (BEYOND_STEP_M / v) * steps)
    t_f = focus_position(products, r_m, t_n, focuser)
    outwards = np.diff(sign * t_f) > 0
    n = t_n.size if outwards.all() else int(np.argmin(outwards)) + 1
    return t_n[:n], t_f[:n]


def _invert_beyond(table: tuple[np.ndarray, np.ndarray], t_f_s: float, degree: int) -> float:
    """t_n of a peak at t_f beyond the rail's end: a polynomial t_n(t_f) through the CALIBRATION_TARGETS
    simulated targets nearest it (`_beyond_map`); NaN where t_f is outside what the map reaches (the peak
    cannot be placed)."""
    t_n, t_f = table
    lo, hi = min(t_f[0], t_f[-1]), max(t_f[0], t_f[-1])
    if t_n.size < degree + 1 or not lo <= t_f_s <= hi:
        return math.nan
    k = int(np.argmin(np.abs(t_f - t_f_s)))
    first = int(np.clip(k - CALIBRATION_TARGETS // 2, 0, max(t_n.size - CALIBRATION_TARGETS, 0)))
    window = slice(first, first + CALIBRATION_TARGETS)
    centre = t_f[k]  # fitted about the nearest target: a well-conditioned local polynomial
    coeffs = np.polynomial.polynomial.polyfit(t_f[window] - centre, t_n[window],
                                              min(degree, t_n[window].size - 1))
    return float(np.polynomial.polynomial.polyval(t_f_s - centre, coeffs))


def peak_track_times(products: nlcs.NlcsProducts, a: np.ndarray, b: np.ndarray,
                     focuser: Focuser = NUMPY_FOCUSER) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_f, r_LRCM, t_n) of NLCS image peaks at fractional indices (a, b): t_f and r from the image's axes
    (row n_azimuth/2 is t_a = 0), t_n through the inverse calibration.

    Parameters
    ----------
    products : NlcsProducts
        The pass's focus; its calibration cache is filled.
    a, b : array_like, shape (n,)
        Fractional azimuth row and range column of each peak.
    focuser : Focuser
        Simulates the calibration targets.

    Returns
    -------
    t_f_s, r_m, t_n_s : ndarrays, shape (n,)
        Seconds, metres, seconds.
    """
    grid = products.grid
    t_f = (np.asarray(a, dtype=float) - grid.n_azimuth // 2) * grid.dt_s
    r = grid.range_bins_m[0] + np.asarray(b, dtype=float) * (grid.range_bins_m[1] - grid.range_bins_m[0])
    return t_f, r, np.atleast_1d(invert_focus_position(products, r, t_f, focuser=focuser))
