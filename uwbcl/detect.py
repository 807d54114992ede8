"""Point-target (bolt plate) detection in a focused pass, sub-cell peak refinement and geometry correction.

Both focusers give an image on (azimuth, r_LRCM) axes. Peaks are found on the pixel grid (local maxima above a
floor relative to the strongest peak and to the image's noise level), refined to sub-cell accuracy on the
underlying band-limited image, and mapped to the target's closest-approach coordinates (x_M, R_c) of the pass:
for NLCS through the inverse of the focus-position map t_f(t_n) (eq. 19 [fix], notes section 8), for
backprojection directly. Close plates bias each other's sub-cell peaks through their point responses' arms, so
each peak is refined again with the other plates' modelled responses removed (docs/method.md section 4).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage, optimize

from .focus import backprojection as bp
from .focus import coefficients as coef
from .focus import nlcs
from .model import ScanPass


@dataclasses.dataclass(frozen=True)
class DetectionSettings:
    relative_floor_db: float = -20.0  # peaks weaker than the strongest by more than this are ignored
    min_snr_db: float = 12.0  # peak over the median image magnitude (a robust noise/clutter level)
    separation_m: float = 0.15  # non-maximum suppression: semi-axis of the ellipse along track
    range_separation_m: float = 0.12  # and in range (beyond the azimuth side-lobes, inside the plate spacing)
    max_targets: int = 64
    # CLEAN-like re-refinements of every peak with the other targets' modelled responses removed (0: off)
    neighbour_cancellation_passes: int = 1
    neighbour_cancellation_tol_m: float = 1e-5  # stop early once no peak moves more than this
    neighbour_gain_degree: int = 8  # Legendre degree of a modelled target's gain along the rail (beam pattern)


@dataclasses.dataclass(frozen=True)
class Detection:
    """One point target seen in one pass, in that pass's closest-approach coordinates."""

    x_m: float  # along-track position X_r of the target
    rc_m: float  # closest-approach slant range from the rail
    t_n_s: float  # P1 azimuth time (crossing of the squinted beam centre)
    r0_m: float  # P1 range at t_n
    image_azimuth_m: float  # where the peak sits in the image (u = v t_f), before geometry correction
    image_range_m: float  # r_LRCM of the peak
    amplitude: float
    snr_db: float


def _local_peaks(mag: np.ndarray, valid: np.ndarray, pixel_m: tuple[float, float], s: DetectionSettings):
    """Pixels above the floors that are the maximum of their separation ellipse (non-maximum suppression)."""
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


def _trig_evaluator(image: np.ndarray, azimuth_band: tuple[float, float] | None = None):
    """Band-limited (trigonometric) interpolation of a 2-D image at fractional indices.

    `azimuth_band` = (lo, hi) in cycles per sample: the image's azimuth spectrum is zero outside it (the NLCS
    azimuth compression zeroes it), so only those spectral rows enter the sums; they hold rounding noise only.
    """
    n, m = image.shape
    spec = (np.fft.fft2(image) / (n * m)).astype(np.complex128)  # once, not per evaluation
    ka = np.fft.fftfreq(n)
    if azimuth_band is not None:
        rows = (ka >= azimuth_band[0]) & (ka <= azimuth_band[1])
        spec, ka = spec[rows], ka[rows]
    ka = ka * 2j * np.pi
    kb = np.fft.fftfreq(m) * 2j * np.pi

    def value(a: float, b: float) -> complex:
        return np.exp(ka * a) @ (spec @ np.exp(kb * b))

    return value


def _nlcs_band(products: nlcs.NlcsProducts) -> tuple[float, float]:
    """The union of the per-bin H8 bands, in cycles per azimuth sample, with a one-sample margin."""
    grid, ac = products.grid, products.compression
    return (float(ac.f_lo_hz.min()) * grid.dt_s - 1.0 / grid.n_azimuth,
            float(ac.f_hi_hz.max()) * grid.dt_s + 1.0 / grid.n_azimuth)


def _maximise(value, a0: float, b0: float, step: float = 0.5) -> tuple[float, float, complex]:
    """Sub-cell maximum of |value| near the fractional index (a0, b0)."""
    res = optimize.minimize(lambda p: -abs(value(p[0], p[1])) ** 2, x0=[a0, b0], method="Nelder-Mead",
                            options={"xatol": 1e-4, "fatol": 1e-12, "initial_simplex":
                                     [[a0, b0], [a0 + step, b0], [a0, b0 + step]]})
    a, b = res.x
    return float(a), float(b), value(a, b)


# --------------------------------------------------------------------------------------------- NLCS
def _bin(obj, j: int):
    """The dataclass with every per-bin array narrowed to bin j (kept 1-D for broadcasting)."""
    return dataclasses.replace(obj, **{f.name: getattr(obj, f.name)[j:j + 1] for f in dataclasses.fields(obj)
                                       if isinstance(getattr(obj, f.name), np.ndarray)})


def focus_position(products: nlcs.NlcsProducts, r_m: float, t_n_s: np.ndarray) -> np.ndarray:
    """t_f(t_n): where the azimuth chain of the bin nearest r focuses targets at t_n (calibrated by simulation)."""
    grid = products.grid
    bins = grid.range_bins_m
    j = int(np.clip(np.rint((r_m - bins[0]) / (bins[1] - bins[0])), 0, bins.size - 1))
    k = _bin(products.coefficients, j)
    ac = _bin(products.compression, j)
    rd = nlcs.az_fft(nlcs.slow_time_point_response(r_m, t_n_s, grid, products.aperture_m))
    y = nlcs.azimuth_compression(nlcs._azimuth_nlcs_chain(rd, k, grid), ac, grid)
    t_grid = grid.t_azimuth_s
    coarse = np.argmax(np.abs(nlcs.az_ifft(y)), axis=0)
    band = (grid.f_azimuth_hz >= ac.f_lo_hz[0]) & (grid.f_azimuth_hz <= ac.f_hi_hz[0])  # H8 is zero elsewhere
    f, y = grid.f_azimuth_hz[band], y[band]
    out = np.empty(y.shape[1])
    for i in range(y.shape[1]):
        col = y[:, i]
        res = optimize.minimize_scalar(lambda t, col=col: -abs(np.exp(2j * np.pi * f * t) @ col),
                                       bounds=(t_grid[coarse[i]] - grid.dt_s, t_grid[coarse[i]] + grid.dt_s),
                                       method="bounded", options={"xatol": 1e-7})
        out[i] = res.x
    return out


def invert_focus_position(products: nlcs.NlcsProducts, r_m: float, t_f_s: float, degree: int = 5) -> float:
    """t_n from the focused t_f: fit t_n(t_f) through simulated targets across the aperture."""
    fit = products.focus_calibration.get((r_m, degree))
    if fit is None:
        grid = products.grid
        half = 0.5 * (grid.n_track - 1) * grid.dt_s
        t_n = np.linspace(-half, half, 13)
        t_f = focus_position(products, r_m, t_n)
        fit = products.focus_calibration[(r_m, degree)] = np.polynomial.polynomial.polyfit(t_f, t_n, degree)
    return float(np.polynomial.polynomial.polyval(t_f_s, fit))


def detect_nlcs(products: nlcs.NlcsProducts, settings: DetectionSettings = DetectionSettings(),
                scan: ScanPass | None = None, focuser=None) -> list[Detection]:
    """Point targets of an NLCS image. With the pass's echo (`scan`), the peaks are re-refined with the
    neighbours' modelled responses removed (`cancel_neighbours_nlcs`); without it, on the image alone.
    `focuser` (an object with `nlcs_focus`, e.g. the OpenCL engine) focuses the modelled echoes; by default the
    numpy chain does."""
    grid = products.grid
    mag = np.abs(products.image)
    t = grid.t_azimuth_s
    half = 0.5 * (grid.n_track - 1) * grid.dt_s
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    valid = np.zeros(mag.shape, dtype=bool)
    valid[np.abs(t) <= half, 2:-2] = True
    peaks, floor = _local_peaks(mag, valid, (grid.track_spacing_m, dr), settings)
    value = _trig_evaluator(products.image, _nlcs_band(products))
    cells = [_maximise(value, float(i), float(j)) for i, j in peaks]
    if settings.neighbour_cancellation_passes > 0 and len(cells) > 1 and scan is not None:
        cells = cancel_neighbours_nlcs(products, scan, cells, settings.neighbour_cancellation_passes,
                                       settings.neighbour_cancellation_tol_m, settings.neighbour_gain_degree,
                                       focuser)
    out = []
    for a, b, val in cells:
        t_f, r, t_n = _nlcs_peak_time(products, a, b)
        r0 = r - grid.speed_m_s * grid.sin_squint * t_n  # eq. (19) [fix]: r_LC = r_LRCM - v sin(theta_q) t_nc
        out.append(_detection(grid, t_n, r0, grid.speed_m_s * t_f, r, abs(val), floor))
    return out


def _nlcs_peak_time(products: nlcs.NlcsProducts, a: float, b: float) -> tuple[float, float, float]:
    """(t_f, r_LRCM, t_n) of a peak at fractional image indices (a, b)."""
    grid = products.grid
    t_f = (a - grid.n_azimuth // 2) * grid.dt_s
    r = grid.range_bins_m[0] + b * (grid.range_bins_m[1] - grid.range_bins_m[0])
    return t_f, r, invert_focus_position(products, r, t_f)


def nlcs_model_chain(products: nlcs.NlcsProducts, x_rel_m: np.ndarray):
    """echo -> NLCS image: the linear chain of `nlcs.nlcs_focus` for this pass (pulses at x_rel_m), reusing the
    products' coefficients and azimuth compression. The stages after the resampling multiply by filters that
    depend on the grid only, so they are computed once here (applied to ones) and each model costs 6 FFTs."""
    grid, k = products.grid, products.coefficients
    ones = np.ones((grid.n_azimuth, grid.n_range), dtype=np.complex128)
    src = nlcs.secondary_range_compression(ones, grid)
    h5h6 = nlcs.nlcs_filter(nlcs.azimuth_compensation(ones, k.eta1, grid), k, grid)
    h7 = nlcs.nlcs_scaling(ones, k, grid)
    h8 = products.compression.filter(grid.f_azimuth_hz)
    p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)

    def focus(echo: np.ndarray) -> np.ndarray:
        s = nlcs.linear_range_walk_correction(nlcs.range_fft(echo, grid), x_rel_m, grid)
        s = nlcs.extended_nlcs(nlcs.resample_to_uniform_track(s, x_rel_m, grid), p2, grid)
        s = nlcs.range_ifft(nlcs.az_fft(nlcs.pad_azimuth(s, grid)) * src, grid) * h5h6
        return nlcs.az_ifft(nlcs.az_fft(nlcs.az_ifft(s) * h7) * h8)

    return focus


def _focuser_model_chain(products: nlcs.NlcsProducts, scan: ScanPass, x_rel_m: np.ndarray, focuser):
    """echo (pulses at x_rel_m, increasing) -> NLCS image, through `focuser` with the products' own H8."""
    grid = products.grid
    order = np.argsort(scan.pulse_position_m)
    model = dataclasses.replace(scan, pulse_position_m=grid.aperture_centre_m + x_rel_m,
                                pulse_time_s=scan.pulse_time_s[order])

    def focus(echo: np.ndarray) -> np.ndarray:
        return focuser.nlcs_focus(dataclasses.replace(model, echo=echo), grid=grid,
                                  compression=products.compression).image

    return focus


def cancel_neighbours_nlcs(products: nlcs.NlcsProducts, scan: ScanPass, cells: list[tuple[float, float, complex]],
                           passes: int, tol_m: float, degree: int, focuser=None
                           ) -> list[tuple[float, float, complex]]:
    """`cancel_neighbours_bp` for the NLCS image: each target's echo is modelled at its current position with
    gains fitted to the pass's range-compressed echo, focused by the same chain (`nlcs_model_chain`), and each
    peak is re-refined on the image minus the other targets' modelled images."""
    grid = products.grid
    rc = bp.range_compress(scan, grid, upsample=1)  # the gain fit needs no upsampling; same delays as the echo
    focus = (nlcs_model_chain(products, rc.x_rel_m) if focuser is None or focuser is nlcs
             else _focuser_model_chain(products, scan, rc.x_rel_m, focuser))
    band = _nlcs_band(products)
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    for _ in range(passes):
        at = np.array([(a, b) for a, b, _ in cells])
        peaks = [_nlcs_peak_time(products, a, b) for a, b in at]
        u = [grid.speed_m_s * t_n for _, _, t_n in peaks]
        r = [r_lrcm for _, r_lrcm, _ in peaks]
        echoes = [bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u[j], r[j]) for j in range(len(at))]
        gains = fit_pulse_gains(rc.data, rc.x_rel_m, echoes, degree)
        images = [focus(g[:, None] * bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u[j], r[j], matched=False)[0])
                  for j, g in enumerate(gains)]
        residual = products.image - sum(images)
        cells = [_maximise(_trig_evaluator(residual + images[i], band), at[i, 0], at[i, 1], step=0.2)
                 for i in range(len(at))]
        moved = np.hypot((np.array([c[0] for c in cells]) - at[:, 0]) * grid.track_spacing_m,
                         (np.array([c[1] for c in cells]) - at[:, 1]) * dr)
        if moved.max() <= tol_m:
            break
    return cells


def _detection(grid: nlcs.FocusGrid, t_n: float, r0: float, image_az: float, image_r: float, amp: float,
               floor: float) -> Detection:
    x_rel = grid.speed_m_s * t_n + r0 * grid.sin_squint
    return Detection(x_m=grid.aperture_centre_m + x_rel, rc_m=r0 * grid.cos_squint, t_n_s=t_n, r0_m=r0,
                     image_azimuth_m=image_az, image_range_m=image_r, amplitude=amp,
                     snr_db=20 * math.log10(amp / floor) if floor > 0 else math.inf)


# --------------------------------------------------------------------------------------------- backprojection
def detect_bp(products: bp.BackprojectionProducts, settings: DetectionSettings = DetectionSettings()
              ) -> list[Detection]:
    grid = products.grid
    mag = np.abs(products.image)
    du = products.u_axis_m[1] - products.u_axis_m[0]
    dr = products.r_axis_m[1] - products.r_axis_m[0]
    valid = np.ones(mag.shape, dtype=bool)
    valid[[0, -1], :] = valid[:, [0, -1]] = False
    peaks, floor = _local_peaks(mag, valid, (du, dr), settings)
    cells = [_maximise(_bp_evaluator(products, products.compressed), float(i), float(j), step=0.3)
             for i, j in peaks]
    if settings.neighbour_cancellation_passes > 0 and len(cells) > 1:
        cells = cancel_neighbours_bp(products, cells, settings.neighbour_cancellation_passes,
                                     settings.neighbour_cancellation_tol_m, settings.neighbour_gain_degree)
    out = []
    for a, b, val in cells:
        u = products.u_axis_m[0] + a * du
        r = products.r_axis_m[0] + b * dr
        t_n = u / grid.speed_m_s
        out.append(_detection(grid, t_n, r - grid.sin_squint * u, u, r, abs(val), floor))
    return out


def _bp_evaluator(products: bp.BackprojectionProducts, rc: bp.RangeCompressed):
    """The BP sum of range-compressed data `rc` at fractional pixel indices of the products' image."""
    u0, du = products.u_axis_m[0], products.u_axis_m[1] - products.u_axis_m[0]
    r0, dr = products.r_axis_m[0], products.r_axis_m[1] - products.r_axis_m[0]

    def value(a: float, b: float) -> complex:
        return complex(bp.backproject_points(rc, products.grid, u0 + a * du, r0 + b * dr))

    return value


def fit_pulse_gains(data: np.ndarray, x_rel_m: np.ndarray, echoes: list[tuple[np.ndarray, np.ndarray]],
                    degree: int) -> np.ndarray:
    """Per-pulse complex gains g (n_targets, n_pulses) with data ~ sum_j g_j[k] echo_j[k, :], jointly by least squares.

    Each target's gain is a Legendre series of degree `degree` in rail position over its in-band pulses and zero
    elsewhere: it carries the beam pattern w_a, which one pass cannot model exactly (the beam is horizontal,
    the target's elevation unknown), and smoothness keeps it determined on pulses where two targets' delays
    cross. `echoes` are (unit-gain echo, in-band pulses) as `bp.point_target_echo` gives them.
    """
    n, m = len(echoes), degree + 1
    basis = np.zeros((n, x_rel_m.size, m))
    for j, (_, band) in enumerate(echoes):
        x = x_rel_m[band]
        if x.size:
            mid, half = 0.5 * (x.min() + x.max()), max(0.5 * (x.max() - x.min()), 1e-9)
            basis[j, band] = np.polynomial.legendre.legvander((x - mid) / half, degree)
    normal = np.zeros((n, m, n, m), dtype=np.complex128)
    rhs = np.zeros((n, m), dtype=np.complex128)
    for j, (echo_j, _) in enumerate(echoes):
        rhs[j] = basis[j].T @ np.einsum("kt,kt->k", echo_j.conj(), data)
        for i in range(j, n):
            block = basis[j].T @ (np.einsum("kt,kt->k", echo_j.conj(), echoes[i][0])[:, None] * basis[i])
            normal[j, :, i, :] = block
            normal[i, :, j, :] = block.conj().T
    series = np.linalg.lstsq(normal.reshape(n * m, n * m), rhs.ravel(), rcond=1e-10)[0].reshape(n, m)
    return np.einsum("jkm,jm->jk", basis, series)


def cancel_neighbours_bp(products: bp.BackprojectionProducts, cells: list[tuple[float, float, complex]],
                         passes: int, tol_m: float, degree: int) -> list[tuple[float, float, complex]]:
    """Re-refine every peak on the data with the modelled responses of all the other peaks subtracted (CLEAN-like).

    Why: a neighbour's point response (its range-migration arms) tilts the surface a peak is refined on. In
    sim 2 the plates stand in one along-track column 0.2 m apart in range; E's arms pull D and F by ~0.7 mm in
    range, and the short height baseline turns that into ~10 mm of Y and Z. Each pass models every target's
    range-compressed echo at its current position (`bp.point_target_echo`, gains by `fit_pulse_gains`), then
    refines each peak on the data minus the other targets' models. `cells` are (a, b, value) at fractional
    pixel indices; stops early once no peak moves by more than tol_m.
    """
    rc, grid = products.compressed, products.grid
    du = products.u_axis_m[1] - products.u_axis_m[0]
    dr = products.r_axis_m[1] - products.r_axis_m[0]
    for _ in range(passes):
        at = np.array([(a, b) for a, b, _ in cells])
        u = products.u_axis_m[0] + at[:, 0] * du
        r = products.r_axis_m[0] + at[:, 1] * dr
        echoes = [bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u[j], r[j]) for j in range(len(at))]
        gains = fit_pulse_gains(rc.data, rc.x_rel_m, echoes, degree)
        models = [e * g[:, None] for g, (e, _) in zip(gains, echoes)]
        del echoes  # one model per target is held: n_pulses x n_fine each
        residual = rc.data - sum(models)
        cells = [_maximise(_bp_evaluator(products, dataclasses.replace(rc, data=residual + models[i])),
                           at[i, 0], at[i, 1], step=0.1) for i in range(len(at))]
        moved = np.hypot((np.array([c[0] for c in cells]) - at[:, 0]) * du,
                         (np.array([c[1] for c in cells]) - at[:, 1]) * dr)
        if moved.max() <= tol_m:
            break
    return cells
