"""Location by synthesis: each NLCS peak mapped to the plate position whose modelled image peaks there
(docs/method.md section 4, C12).

The t_f(t_n) calibration (`calibration`) simulates a target in the slow time of one range bin, the nearest,
weighted by the beam's slant-plane pattern. A plate's image differs from that in three ways, each of which
moves its peak by millimetres along track, growing with |t_n|:

* between two range bins the image is an interpolation of bins whose azimuth chains differ (per-bin
  coefficients, C8): a sawtooth of up to +-2 mm in the fractional bin at 45 deg squint;
* the echo's amplitude along the rail (two-way spreading 1/R^2, the horizontal beam of the rotation table)
  weights the equalisation's residual phase differently from the calibration's beam (up to 2.5 mm);
* a plate off the reference range keeps a differential range migration after the bulk SRC (C5), which
  couples range and azimuth in the 2-D peak (up to 2.3 mm along track, 1.2 mm in range).

Together they gave the located plates an along-track error that grows with their position on the rail
(-1.07 mm/m at 45 deg, +0.48 mm/m at 15 deg in the availability study), a scale error that no random-error
bound contains. So each plate is modelled instead: its echo at the calibrated position, with real per-pulse
gains (`real_gains`) from those fitted to the pass's echo (`cancel.fit_pulse_gains`, all plates jointly), is
focused by the pass's own chain and H8 (`Focuser.nlcs_model_spectra`), the model's peak is refined as the
image's, and the position moves by the difference of the two peaks mapped through the calibration T (a
Newton step whose Jacobian is the calibration's):

    t_n <- t_n + T(a, b) - T(a_m, b_m),    r_LRCM <- r_LRCM + r(b) - r(b_m)                          (S1)

Real gains, not the complex ones: a complex gain's phase along the rail absorbs a position error (fitted at a
wrong position, the model reproduces the echo and peaks where the image does, whatever the position).

Where the image's peak is, for a plate with no modelled neighbour near it, is found by matching rather than by
the maximum alone (S1c, `matched_peak`): the data less the other plates' models and the model are each
cross-correlated with the model's main lobe, and the data's match moves the model's peak. Without noise this
is S1; under noise the maximum of a lopsided response (a truncated aperture near the rail's ends) is biased
and scatters with the noise at the peak, the match uses the whole main lobe.
"""

from __future__ import annotations

import math

import numpy as np

from . import calibration, cancel, refine


def locate(cells: list[cancel.Cell], model: cancel.NlcsModel, passes: int, tol_m: float, degree: int,
           split: set[int] = frozenset()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_f, r_LRCM, t_n) of the plates at NLCS image peaks `cells`, corrected by synthesis (S1).

    Parameters
    ----------
    cells : list of (a, b, value)
        The refined image peaks: fractional (row, column) indices and complex values.
    model : cancel.NlcsModel
        The pass's models: its focus, focuser, range-compressed echo and spectrum rows.
    passes : int
        Most Newton steps (S1); 0 gives the calibration's positions.
    tol_m : float
        Stop once no plate moved by more than this (m) along track or in range.
    degree : int
        Legendre degree of the fitted gains (`cancel.fit_pulse_gains`).
    split : set of int
        The plates of split peaks (S2): their image peaks come from the pair's joint fit, and each is moved
        by its own peak against its model's (S1); every other plate by the matched peak (S1c,
        `matched_peak`).

    Returns
    -------
    t_f_s, r_m, t_n_s : ndarrays, shape (n,)
        The image peaks' focus times (s), and each plate's r_LRCM (m) and t_n (s).
    """
    products, grid = model.products, model.grid
    at = np.array([(a, b) for a, b, _ in cells], dtype=float).reshape(-1, 2)
    t_f, r_image, t_n_image = calibration.peak_track_times(products, at[:, 0], at[:, 1], model.focuser)
    r, t_n = r_image.copy(), t_n_image.copy()
    alone = isolated(model, at)  # the image peaks do not move between the passes
    for _ in range(passes if len(cells) else 0):
        u = grid.speed_m_s * t_n
        models = cancel.fitted_models(model, u, r, degree, real_gains)
        peak = np.array([_model_peak(model, models[j], at[j]) for j in range(len(cells))])
        found = np.isfinite(peak[:, 0])  # a plate whose model has no peak keeps its last position
        if not found.any():
            break
        _, r_model, t_n_model = calibration.peak_track_times(products, peak[found, 0], peak[found, 1],
                                                             model.focuser)
        seen = np.array([matched_peak(model, models, j, peak[j], at[j])
                         if found[j] and alone[j] and j not in split else at[j] for j in range(len(cells))])
        _, r_seen, t_n_seen = calibration.peak_track_times(products, seen[found, 0], seen[found, 1],
                                                           model.focuser)
        step_t = np.zeros_like(t_n)
        step_r = np.zeros_like(r)
        step_t[found] = t_n_seen - t_n_model
        step_r[found] = r_seen - r_model
        t_n += step_t
        r += step_r
        if np.max(np.hypot(grid.speed_m_s * step_t, step_r)) <= tol_m:
            break
    return t_f, r, t_n


def real_gains(gains: np.ndarray) -> np.ndarray:
    """The real weighting of each modelled plate along the rail (n_plates, n_pulses): each fitted gain's part
    in phase with the plate's mean gain phase (phases averaged with weights |g|), Re(g exp(-j phi)).

    Not |g|: the noise in a fitted gain is zero-mean, so its real part is unbiased, but |g| is biased upwards
    where the gain is small (the beam's edges), which widened the weighting and moved noisy plates along track
    with their position on the rail (dense-3h, SNR 10 dB, single passes: +0.52 mm/m with |g|, -0.35 mm/m with
    the real part and -0.33 mm/m with the calibration alone, each +-0.25 mm/m).
    """
    phase = np.angle(np.sum(gains * np.abs(gains), axis=-1, keepdims=True))
    return np.real(gains * np.exp(-1j * phase))


def _model_peak(model: cancel.NlcsModel, spectrum: np.ndarray, start: np.ndarray) -> tuple[float, float]:
    """The model's image peak (fractional row, column), refined from the image's peak; NaN where the model is
    zero (no gain fitted)."""
    interpolant = refine.TrigInterpolant.from_rows(model.rows, spectrum, model.grid.n_azimuth)
    a, b, value = interpolant.maximise(float(start[0]), float(start[1]))
    if not (abs(value) > 0 and np.isfinite(a) and np.isfinite(b)):
        return np.nan, np.nan
    return a, b


# S1c's template: the model's image under a Gaussian window about its peak, standard deviations along track
# and in range (m): its main lobe (3 dB widths ~70 / ~100 mm), not its range-migration arms and far side
# lobes, where the other plates' residuals and the clutter lie. PATCH_SIGMAS of them either side
# are evaluated.
MATCH_WINDOW_M = (0.05, 0.05)
PATCH_SIGMAS = 3.0


def matched_peak(model: cancel.NlcsModel, models: np.ndarray, j: int, model_peak: np.ndarray,
                 start: np.ndarray) -> np.ndarray:
    """Where plate j's image lies (fractional row, column), located as its model's is, by the shift that best
    matches each to one template: the model's peak moved by the difference of the two matches (S1c).

    The image's own maximum is biased under noise wherever the plate's response is asymmetric (a truncated
    aperture near the rail's ends, NLCS's residual phase): noise added to a lopsided peak moves its maximum,
    and it scatters with the noise at the peak alone. The template is the model's main lobe
    (`MATCH_WINDOW_M`); the data less the other plates' models and the model itself are each cross-correlated
    with it, sum X^ conj(T^) e^{2 pi i k d}, and the data's match moves against the model's: without noise the
    two are the same and the position is S1's; with noise the match uses the whole main lobe. `start` is the
    image's peak: the data's search starts from its offset to the model's."""
    template = _template_spectrum(model, models[j], model_peak)
    residual = model.spectrum - models.sum(axis=0) + models[j]
    shift = []
    for spectrum, a0, b0 in ((residual, start[0] - model_peak[0], start[1] - model_peak[1]),
                             (models[j], 0.0, 0.0)):
        correlation = refine.TrigInterpolant.from_rows(model.rows, spectrum * np.conj(template),
                                                       model.grid.n_azimuth)
        da, db, value = correlation.maximise(float(a0), float(b0))
        if not (abs(value) > 0 and np.isfinite(da) and np.isfinite(db)):
            return np.asarray(start, dtype=float)
        shift.append((da, db))
    return np.asarray(model_peak, dtype=float) + np.subtract(shift[0], shift[1])


def isolated(model: cancel.NlcsModel, at: np.ndarray) -> np.ndarray:
    """(n,) bool: the plates at image peaks `at` (n, 2) with no other modelled plate's peak within twice the
    template's patch (PATCH_SIGMAS x MATCH_WINDOW_M either side, along track and in range): S1c matches only
    those. Near a neighbour the main lobe holds the neighbour's model error, which the peak alone (S1) does
    not feel as much (measured on the availability study's columns: drift 4.2 -> 7.4 mm with S1c on every
    plate, docs/method.md section 4)."""
    reach = 2.0 * PATCH_SIGMAS * _window_cells(model)
    apart = np.abs(at[:, None, :] - at[None, :, :]) / reach
    near = np.all(apart < 1.0, axis=2)
    np.fill_diagonal(near, False)
    return ~near.any(axis=1)


def _window_cells(model: cancel.NlcsModel) -> np.ndarray:
    """MATCH_WINDOW_M in the image's cells (along track, in range)."""
    return np.asarray(MATCH_WINDOW_M) / np.abs(np.asarray(model.cell_m, dtype=float))


def _template_spectrum(model: cancel.NlcsModel, spectrum: np.ndarray, peak: np.ndarray) -> np.ndarray:
    """The spectrum (on `model.rows`) of the image `spectrum` under a Gaussian window (`MATCH_WINDOW_M`) about
    `peak`, from the image on the integer cells of a patch PATCH_SIGMAS windows either side."""
    n, m = model.grid.n_azimuth, spectrum.shape[-1]
    sa, sb = _window_cells(model)
    a = np.arange(math.floor(peak[0] - PATCH_SIGMAS * sa), math.ceil(peak[0] + PATCH_SIGMAS * sa) + 1)
    b = np.arange(math.floor(peak[1] - PATCH_SIGMAS * sb), math.ceil(peak[1] + PATCH_SIGMAS * sb) + 1)
    interpolant = refine.TrigInterpolant.from_rows(model.rows, spectrum, n)
    image = interpolant.lattice(a.astype(float), b.astype(float))
    window = np.exp(-0.5 * (((a - peak[0]) / sa)[:, None] ** 2 + ((b - peak[1]) / sb)[None, :] ** 2))
    ka, kb = model.rows * (1.0 / n), np.fft.fftfreq(m)
    return (np.exp(-2j * np.pi * np.outer(ka, a)) @ (image * window) @ np.exp(-2j * np.pi * np.outer(b, kb))
            / (n * m))
