"""Point-target (bolt plate) detection in a focused pass, sub-cell peak refinement and geometry correction.

Both focusers give an image on (azimuth, r_LRCM) axes. Peaks are found on the pixel grid (local maxima above a
floor relative to the strongest peak and to the image's noise level), refined to sub-cell accuracy on the
underlying band-limited image, and mapped to the target's closest-approach coordinates (x_M, R_c) of the pass:
for NLCS through the inverse of the focus-position map t_f(t_n) (eq. 19 corrected, docs/method.md C12), for
backprojection directly. Close plates bias each other's sub-cell peaks through their point responses' arms, so
each peak is refined again with the other plates' modelled responses removed (docs/method.md section 4).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage, optimize

from .focus import backprojection as bp
from .focus import nlcs
from .model import ScanPass
from .records import Detection, DetectionSettings


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


@dataclasses.dataclass(frozen=True, eq=False)
class TrigInterpolant:
    """Band-limited (trigonometric) interpolation of a 2-D image at fractional indices (a, b):

        V(a, b) = sum_k sum_l coeffs[k, l] exp(2 pi i (ka_k a + kb_l b)),

    the inverse DFT evaluated off the grid. `coeffs` is the image's 2-D DFT / (n m) on the kept azimuth rows,
    `ka` their frequencies (np.fft.fftfreq(n)[rows]) and `kb` np.fft.fftfreq(m), in cycles per sample. Built from
    an image (`from_image`) or from spectra computed elsewhere (e.g. on an OpenCL device): nothing here needs the
    image itself.
    """

    coeffs: np.ndarray  # (rows, m) complex
    ka: np.ndarray  # (rows,)
    kb: np.ndarray  # (m,)

    @classmethod
    def from_image(cls, image: np.ndarray, azimuth_band: tuple[float, float] | None = None) -> TrigInterpolant:
        """`azimuth_band` = (lo, hi) in cycles per sample: the image's azimuth spectrum is zero outside it (the
        NLCS azimuth compression zeroes it), so only those spectral rows are kept; the others hold rounding
        noise only."""
        n = image.shape[0]
        rows = nlcs.band_rows(n, azimuth_band if azimuth_band is not None else (-1.0, 1.0))
        return cls.from_rows(rows, image_spectrum_rows(image, rows), n)

    @classmethod
    def from_rows(cls, rows: np.ndarray, coeffs: np.ndarray, n: int) -> TrigInterpolant:
        """From `coeffs` = fft2(image) / (n m) at the signed azimuth rows `rows` of an n-row image."""
        return cls(np.ascontiguousarray(coeffs, dtype=np.complex128), rows * (1.0 / n),
                   np.fft.fftfreq(coeffs.shape[-1]))

    def value(self, a: float, b: float) -> complex:
        return complex(np.exp(2j * np.pi * self.ka * a) @ (self.coeffs @ np.exp(2j * np.pi * self.kb * b)))

    def _local(self, a: float, b: float) -> tuple[complex, float, np.ndarray, np.ndarray]:
        """V, g = |V|^2 and the gradient and Hessian of g at (a, b). The derivatives of V are the same sums with
        coeffs[k, l] (2 pi i ka_k)^p (2 pi i kb_l)^q: one mat-mul of coeffs with e_b, w_b e_b, w_b^2 e_b, then
        one 3 x 3 contraction with e_a, w_a e_a, w_a^2 e_a gives d^(p+q) V / da^p db^q for p, q <= 2."""
        wa, wb = 2j * np.pi * self.ka, 2j * np.pi * self.kb
        eb = np.exp(wb * b)
        ea = np.exp(wa * a)
        u = self.coeffs @ np.stack([eb, wb * eb, wb * wb * eb], axis=1)  # (rows, 3)
        d = np.stack([ea, wa * ea, wa * wa * ea]) @ u  # d[p, q] = d^p/da^p d^q/db^q V
        v = d[0, 0]
        dv = np.array([d[1, 0], d[0, 1]])
        ddv = np.array([[d[2, 0], d[1, 1]], [d[1, 1], d[0, 2]]])
        # g = V V*: dg = 2 Re(V* dV), d2g = 2 Re(dV* dV^T + V* d2V)
        grad = 2.0 * (v.conjugate() * dv).real
        hess = 2.0 * (np.outer(dv.conjugate(), dv) + v.conjugate() * ddv).real
        return complex(v), float(abs(v) ** 2), grad, hess

    def maximise(self, a0: float, b0: float, step: float = 0.5, tol: float = 1e-6, max_iter: int = 20
                 ) -> tuple[float, float, complex]:
        """Sub-cell maximum of |V|^2 near (a0, b0) by Newton's method with the analytic gradient and Hessian.

        Trust region of radius <= `step` cells: a Newton step where the Hessian is negative definite, a damped
        steepest-ascent step elsewhere; a step that lowers |V|^2 is retried at half the radius. Stops after a
        step shorter than `tol` cells. Returns (a, b, V(a, b)).
        """
        x = np.array([a0, b0], dtype=float)
        v, g, grad, hess = self._local(*x)
        radius = step
        for _ in range(max_iter):
            det = hess[0, 0] * hess[1, 1] - hess[0, 1] ** 2
            if hess[0, 0] < 0 and det > 0:  # negative definite
                s = np.array([hess[0, 1] * grad[1] - hess[1, 1] * grad[0],
                              hess[0, 1] * grad[0] - hess[0, 0] * grad[1]]) / det  # -H^-1 grad
            else:
                norm = np.hypot(*grad)
                s = grad * (radius / norm) if norm > 0 else np.zeros(2)
            length = float(np.hypot(*s))
            if length > radius:
                s, length = s * (radius / length), radius
            if length < tol:  # converged: take the last, tiny step (its error is of order length^2)
                x += s
                v = self.value(*x)
                break
            v1, g1, grad1, hess1 = self._local(*(x + s))
            if g1 < g * (1.0 - 1e-13):  # worse beyond rounding: shrink the region and retry
                radius = 0.5 * length
                continue
            x += s
            v, g, grad, hess = v1, g1, grad1, hess1
            radius = min(step, 2.0 * radius)
        return float(x[0]), float(x[1]), v


def image_spectrum_rows(image: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """fft2(image) / (n m) at the signed azimuth rows `rows` (the range FFT only on those rows)."""
    n, m = image.shape
    return np.fft.fft(np.fft.fft(image, axis=0)[rows % n], axis=1) / (n * m)


def _maximise(value, a0: float, b0: float, step: float = 0.5) -> tuple[float, float, complex]:
    """Sub-cell maximum of |value| near the fractional index (a0, b0), derivative-free (Nelder-Mead): for the
    backprojection sum, which has no spectral form (the NLCS image uses `TrigInterpolant.maximise`)."""
    res = optimize.minimize(lambda p: -abs(value(p[0], p[1])) ** 2, x0=[a0, b0], method="Nelder-Mead",
                            options={"xatol": 1e-4, "fatol": 1e-12, "initial_simplex":
                                     [[a0, b0], [a0 + step, b0], [a0, b0 + step]]})
    a, b = res.x
    return float(a), float(b), value(a, b)


# --------------------------------------------------------------------------------------------- NLCS
def _peak_times(f_hz: np.ndarray, y: np.ndarray, t0_s: np.ndarray, dt_s: float, tol_s: float = 1e-10,
                max_iter: int = 30, order: int = 32) -> np.ndarray:
    """Per column c of y (rows at azimuth frequencies f_hz, |f dt| <= 1/2), the t in [t0_c - dt, t0_c + dt] that
    maximises g(t) = |Y(t)|^2, Y(t) = sum_f exp(2 pi i f t) y_f, by Newton's method on all columns at once.

    About t0 (the coarse maximum), Y(t0 + x dt) = sum_p m_p x^p / p! with m_p = sum_f (2 pi i f dt)^p y_f
    exp(2 pi i f t0): for |x| <= 1 the series' tail beyond `order` is below pi^(order+1) / (order+1)! < 1e-20
    of sum |y_f|, so after one pass over y (the m_p) each Newton step costs a few small polynomials. Steps are
    at most dt / 2, a damped ascent step where g is not concave, and a step that lowers g is retried at half
    its length; stops once every step is shorter than tol_s."""
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
    radius = np.full(x.shape, 0.5)
    for _ in range(max_iter):
        concave = ddg < 0
        newton = -dg / np.where(concave, ddg, -1.0)
        step = np.clip(np.where(concave, newton, np.sign(dg) * radius), -radius, radius)
        step = np.clip(x + step, -1.0, 1.0) - x
        active = np.abs(step) >= tol_s / dt_s
        if not active.any():
            break
        g1, dg1, ddg1 = local(x + step)
        ok = active & (g1 >= g * (1.0 - 1e-13))  # not worse beyond rounding
        x = np.where(ok, x + step, x)
        g, dg, ddg = np.where(ok, g1, g), np.where(ok, dg1, dg), np.where(ok, ddg1, ddg)
        radius = np.where(ok, np.minimum(0.5, 2.0 * radius), np.where(active, 0.5 * np.abs(step), radius))
    return t0_s + x * dt_s


def calibration_spectra(products: nlcs.NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Focused azimuth spectra of simulated targets at every (r, t_n) (columns r-major), each through the azimuth
    chain of the bin nearest its r: (f, y, coarse) with y on the rows f where H8 is not zero and the coarse t_f
    (grid maximum) of each column.

    The chain of `nlcs.slow_time_point_response` (rail only), `nlcs._azimuth_nlcs_chain` and
    `nlcs.azimuth_compression`, with the same numbers, arranged for speed: the point response is evaluated on
    the rail's rows alone (the rest are zero), the FFTs run in their own (unshifted) order and in place, and H6,
    H7, H8 are computed once per bin (H8 on its band only)."""
    grid = products.grid
    n = grid.n_azimuth
    j = grid.nearest_bin(r_m)
    bins_used, bin_of_r = np.unique(j, return_inverse=True)
    k, ac = nlcs.select_bins(products.coefficients, bins_used), nlcs.select_bins(products.compression, bins_used)
    f = np.fft.ifftshift(grid.f_azimuth_hz)
    band = (f >= ac.f_lo_hz.min()) & (f <= ac.f_hi_hz.max())
    ones = np.ones((n, bins_used.size), dtype=np.complex128)
    h6 = np.fft.ifftshift(nlcs.nlcs_filter(ones, k, grid), axes=0).T[bin_of_r, None]
    h7 = np.fft.ifftshift(nlcs.nlcs_scaling(ones, k, grid), axes=0).T[bin_of_r, None]
    h8 = np.zeros((bins_used.size, n), dtype=np.complex128)
    h8[:, band] = ac.filter(f[band]).T
    # the response on a grid of the rail's n_track (odd) + 1 rows: its t_a are the same integers times dt
    half = (grid.n_track + 1) // 2
    rail = nlcs.slow_time_point_response(np.repeat(r_m, t_n_s.size), np.tile(t_n_s, r_m.size),
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
    coarse = np.fft.ifftshift(grid.t_azimuth_s)[np.argmax(np.abs(np.fft.ifft(s, axis=1)), axis=1)]
    return f[band], s[:, band].T, coarse


def focus_position(products: nlcs.NlcsProducts, r_m, t_n_s: np.ndarray, focuser=None) -> np.ndarray:
    """t_f(t_n): where the azimuth chain of the bin nearest r focuses targets at t_n (calibrated by simulation).

    `r_m` a float: one t_f per t_n. An array of ranges: one row of t_f per range, all simulated at once. The
    simulation runs on `focuser.calibration_spectra` where the focuser has one (the OpenCL engine), else here."""
    r = np.atleast_1d(np.asarray(r_m, dtype=float))
    t_n = np.asarray(t_n_s, dtype=float).ravel()
    f, y, coarse = getattr(focuser, "calibration_spectra", calibration_spectra)(products, r, t_n)
    t_f = _peak_times(f, y, coarse, products.grid.dt_s).reshape(r.size, t_n.size)
    return t_f if np.ndim(r_m) else t_f[0]


def invert_focus_position(products: nlcs.NlcsProducts, r_m, t_f_s, degree: int = 5, focuser=None):
    """t_n from the focused t_f: fit t_n(t_f) through simulated targets across the aperture, per range (cached
    in products.focus_calibration). Arrays of (r, t_f) give an array of t_n; the missing fits are simulated
    together."""
    cache = products.focus_calibration
    r = [float(x) for x in np.atleast_1d(r_m)]
    missing = list(dict.fromkeys(x for x in r if (x, degree) not in cache))
    if missing:
        grid = products.grid
        half = 0.5 * (grid.n_track - 1) * grid.dt_s
        t_n = np.linspace(-half, half, 13)
        for x, t_f in zip(missing, focus_position(products, np.array(missing), t_n, focuser)):
            cache[(x, degree)] = np.polynomial.polynomial.polyfit(t_f, t_n, degree)
    t_f = np.broadcast_to(np.asarray(t_f_s, dtype=float), (len(r),))
    out = np.array([np.polynomial.polynomial.polyval(t, cache[(x, degree)]) for x, t in zip(r, t_f)])
    return out if np.ndim(r_m) or np.ndim(t_f_s) else float(out[0])


def detect_nlcs(products: nlcs.NlcsProducts, settings: DetectionSettings = DetectionSettings(),
                scan: ScanPass | None = None, focuser=None) -> list[Detection]:
    """Point targets of an NLCS image. With the pass's echo (`scan`), the peaks are re-refined with the
    neighbours' modelled responses removed (`cancel_neighbours_nlcs`); without it, on the image alone.
    `focuser` (an object with `nlcs_model_spectra`: the OpenCL engine, `uwbcl.focus.scipy32`) focuses the
    modelled echoes; by default the numpy chain (`nlcs.nlcs_model_spectra`) does."""
    grid = products.grid
    t = grid.t_azimuth_s
    half = 0.5 * (grid.n_track - 1) * grid.dt_s
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    # Peaks are sought along the rail only (a few hundred of the padded rows): crop to those rows plus the
    # separation ellipse's reach, beyond which the crop's edges cannot change any test.
    on_rail = np.flatnonzero(np.abs(t) <= half)
    reach = int(settings.separation_m / grid.track_spacing_m) + 2
    top, bottom = max(on_rail[0] - reach, 0), min(on_rail[-1] + reach + 1, grid.n_azimuth)
    mag = np.abs(products.image[top:bottom])
    valid = np.zeros(mag.shape, dtype=bool)
    valid[on_rail - top, 2:-2] = True
    peaks, floor = _local_peaks(mag, valid, (grid.track_spacing_m, dr), settings)
    peaks = peaks + (top, 0)
    rows = nlcs.spectrum_rows(products.grid, products.compression)
    spectrum = products.spectrum if products.spectrum is not None else image_spectrum_rows(products.image, rows)
    interpolant = TrigInterpolant.from_rows(rows, spectrum, products.grid.n_azimuth)
    cells = [interpolant.maximise(float(i), float(j)) for i, j in peaks]
    if settings.neighbour_cancellation_passes > 0 and len(cells) > 1 and scan is not None:
        cells = cancel_neighbours_nlcs(products, scan, cells, settings.neighbour_cancellation_passes,
                                       settings.neighbour_cancellation_tol_m, settings.neighbour_gain_degree,
                                       focuser, (rows, spectrum))
    if not cells:
        return []
    t_f, r, t_n = _nlcs_peak_times(products, [c[0] for c in cells], [c[1] for c in cells], focuser)
    r0 = r - grid.speed_m_s * grid.sin_squint * t_n  # eq. (19), C12: r_LC = r_LRCM - v sin(theta_q) t_nc
    return [_detection(grid, float(t_n[i]), float(r0[i]), grid.speed_m_s * float(t_f[i]), float(r[i]), abs(val),
                       floor) for i, (_, _, val) in enumerate(cells)]


def _nlcs_peak_times(products: nlcs.NlcsProducts, a: np.ndarray, b: np.ndarray, focuser=None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_f, r_LRCM, t_n) of peaks at fractional image indices (a, b)."""
    grid = products.grid
    t_f = (np.asarray(a, dtype=float) - grid.n_azimuth // 2) * grid.dt_s
    r = grid.range_bins_m[0] + np.asarray(b, dtype=float) * (grid.range_bins_m[1] - grid.range_bins_m[0])
    return t_f, r, np.atleast_1d(invert_focus_position(products, r, t_f, focuser=focuser))


def cancel_neighbours_nlcs(products: nlcs.NlcsProducts, scan: ScanPass, cells: list[tuple[float, float, complex]],
                           passes: int, tol_m: float, degree: int, focuser=None,
                           spectrum: tuple[np.ndarray, np.ndarray] | None = None
                           ) -> list[tuple[float, float, complex]]:
    """`cancel_neighbours_bp` for the NLCS image: each target's echo is modelled at its current position with
    gains fitted to the pass's range-compressed echo and focused by the pass's own chain and H8; each peak is
    re-refined on the image minus the other targets' modelled images. The refinement only needs the band rows
    of each image's 2-D spectrum, which `focuser.nlcs_model_spectra` gives without the last azimuth IFFT;
    `spectrum` = (signed rows, fft2(image) / (n m) on them) of the pass's image, if already computed."""
    grid = products.grid
    focuser = nlcs if focuser is None else focuser
    rows, image_spectrum = spectrum if spectrum is not None else (nlcs.spectrum_rows(grid, products.compression), None)
    if image_spectrum is None:
        image_spectrum = image_spectrum_rows(products.image, rows)
    rc = bp.range_compress(scan, grid, upsample=1)  # the gain fit needs no upsampling; same delays as the echo
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    for _ in range(passes):
        at = np.array([(a, b) for a, b, _ in cells])
        _, r, t_n = _nlcs_peak_times(products, at[:, 0], at[:, 1], focuser)
        u = grid.speed_m_s * t_n
        echoes = [bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u[j], r[j]) for j in range(len(at))]
        gains = fit_pulse_gains(rc.data, rc.x_rel_m, echoes, degree)
        raw = np.array([g[:, None] * bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u[j], r[j], matched=False)[0]
                        for j, g in enumerate(gains)])
        models = focuser.nlcs_model_spectra(products, rc.x_rel_m, raw, rows)
        residual = image_spectrum - models.sum(axis=0)
        cells = [TrigInterpolant.from_rows(rows, residual + models[i], grid.n_azimuth)
                 .maximise(at[i, 0], at[i, 1], step=0.2) for i in range(len(at))]
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
