"""Neighbour cancellation: every peak refined again with the other targets' modelled responses removed.

Why: a neighbour's point response (its range-migration arms) tilts the surface a peak is refined on. In sim 2
the plates stand in one along-track column 0.2 m apart in range; E's arms pull D and F by ~0.7 mm in range,
and the short height baseline turns that into ~10 mm of Y and Z (docs/method.md section 4).

One loop (`cancel_neighbours`, CLEAN-like) for both images: each pass models every target's range-compressed
echo at its current position (`bp.point_target_echo`) with per-pulse gains fitted jointly to the pass's
range-compressed echo (`fit_pulse_gains`), then refines each peak on the data minus the other targets' models.
What differs between the images is the model step (`CancellationModel`): where a peak sits (NLCS through the
inverse focus-position calibration), in which domain the models are subtracted (the NLCS image's 2-D spectrum,
focused by the pass's own `Focuser`; the BP range-compressed echo) and how a peak is refined there.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from ..focus import backprojection as bp
from ..focus import nlcs
from ..focus.protocol import Focuser
from ..model import ScanPass
from . import calibration, refine

log = logging.getLogger("uwbcl")

Cell = tuple[float, float, complex]  # a peak: fractional (row, column) indices of the image and its value

# Trust radius (NLCS, Newton) and initial simplex (BP, Nelder-Mead) of the re-refinement, in cells: removing
# the neighbours moves a peak by a fraction of a cell (0.7 mm in sim 2), far less than the first search may.
NLCS_RECANCEL_STEP_CELLS = 0.2
BP_RECANCEL_STEP_CELLS = 0.1
# Least-squares cut-off of the joint gain fit: singular values below 1e-10 of the largest count as zero, so a
# gain component the echoes cannot determine stays zero (lstsq's minimum norm) instead of exploding.
GAIN_FIT_RCOND = 1e-10
# Cap of the gain fit's ridge (eq. N1): a target with no overlap with the echo gets gains ~0, not a NaN.
MAX_GAIN_RIDGE = 1e300
# Half-width of the Legendre variable for a target seen on a single pulse: any positive value keeps it finite.
MIN_GAIN_HALF_WIDTH_M = 1e-9


def fit_pulse_gains(data: np.ndarray, x_rel_m: np.ndarray, echoes: list[tuple[np.ndarray, np.ndarray]],
                    degree: int) -> np.ndarray:
    """Per-pulse complex gains g with data ~ sum_j g_j[k] echo_j[k, :], jointly by least squares.

    Each target's gain is a Legendre series of degree `degree` in rail position over its in-band pulses and
    zero elsewhere: it carries the beam pattern w_a, which one pass cannot model exactly (the beam is
    horizontal, the target's elevation unknown), and smoothness keeps it determined on pulses where two
    targets' delays cross.

    Parameters
    ----------
    data : ndarray, shape (n_pulses, n_t), complex
        The range-compressed echo, pulses in increasing rail position.
    x_rel_m : ndarray, shape (n_pulses,)
        Rail positions relative to the aperture centre (m).
    echoes : list of (ndarray (n_pulses, n_t) complex, ndarray (n_pulses,) bool)
        Each target's unit-gain echo and its in-band pulses, as `bp.point_target_echo` gives them.
    degree : int
        Legendre degree of each gain along the rail.

    Returns
    -------
    ndarray, shape (n_targets, n_pulses), complex128
        The gains (zero on a target's out-of-band pulses).
    """
    n, m = len(echoes), degree + 1
    basis = np.zeros((n, x_rel_m.size, m))
    for j, (_, band) in enumerate(echoes):
        x = x_rel_m[band]
        if x.size:
            mid, half = 0.5 * (x.min() + x.max()), max(0.5 * (x.max() - x.min()), MIN_GAIN_HALF_WIDTH_M)
            basis[j, band] = np.polynomial.legendre.legvander((x - mid) / half, degree)
    normal = np.zeros((n, m, n, m), dtype=np.complex128)
    rhs = np.zeros((n, m), dtype=np.complex128)
    for j, (echo_j, _) in enumerate(echoes):
        rhs[j] = basis[j].T @ np.einsum("kt,kt->k", echo_j.conj(), data)
        for i in range(j, n):
            block = basis[j].T @ (np.einsum("kt,kt->k", echo_j.conj(), echoes[i][0])[:, None] * basis[i])
            normal[j, :, i, :] = block
            normal[i, :, j, :] = block.conj().T
    normal = normal.reshape(n * m, n * m)
    normal[np.diag_indices(n * m)] += np.repeat(_gain_ridge(data, echoes), m)
    series = np.linalg.lstsq(normal, rhs.ravel(), rcond=GAIN_FIT_RCOND)[0].reshape(n, m)
    return np.einsum("jkm,jm->jk", basis, series)


def _gain_ridge(data: np.ndarray, echoes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Per target, the ridge sigma^2 / a_j^2 of its gains' coefficients (eq. N1): a prior N(0, a_j^2) on each,
    a_j the target's matched amplitude |<e_j, d>| / <e_j, e_j> alone, sigma^2 the echo's noise power per
    sample, median |d|^2 / ln 2 (complex Gaussian; most samples hold no echo). Without it two noise peaks a
    few cells apart fitted opposite gains several times the strongest plate's, and each, refined on the data
    minus the other's model, rose from 13 to 31 dB over the floor (SNR 5 dB). A plate well above the noise
    (a_j^2 <e_j, e_j> >> sigma^2) is not changed measurably; a noise-free echo not at all."""
    noise = float(np.median(data.real**2 + data.imag**2)) / math.log(2.0)
    ridge = np.empty(len(echoes))
    for j, (echo_j, _) in enumerate(echoes):
        energy = float(np.sum(echo_j.real**2 + echo_j.imag**2))
        amp2 = abs(np.vdot(echo_j, data)) ** 2 / energy**2 if energy > 0 else 0.0
        ridge[j] = noise / amp2 if amp2 > 0 else (np.inf if noise > 0 else 0.0)
    return np.minimum(ridge, MAX_GAIN_RIDGE)


def fitted_models(model: CancellationModel, u_m: np.ndarray, r_m: np.ndarray, degree: int,
                  gain_map: Callable[[np.ndarray], np.ndarray] | None = None):
    """Each target's model (`model.models`) at (u = v t_n, r_LRCM) (n,) m: its unit-gain echo
    (`bp.point_target_echo`) times the per-pulse gains fitted to the range-compressed echo jointly with the
    others' (`fit_pulse_gains`), mapped by `gain_map` when given (`synthesis.real_gains`)."""
    rc, grid = model.compressed, model.grid
    echoes = [bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u_m[j], r_m[j]) for j in range(len(u_m))]
    gains = fit_pulse_gains(rc.data, rc.x_rel_m, echoes, degree)
    # only the models outlive this call: one echo per target would be n_pulses x n_t each
    return model.models(u_m, r_m, echoes, gain_map(gains) if gain_map is not None else gains)


class CancellationModel(Protocol):
    """The image-specific step of `cancel_neighbours`."""

    grid: nlcs.FocusGrid
    compressed: bp.RangeCompressed  # the range-compressed echo the gains are fitted to
    cell_m: tuple[float, float]  # the image's cell along azimuth and range (m): how far a peak moved

    def positions(self, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u = v t_n, r_LRCM) in m, each (n,), of the targets whose peaks are at the fractional indices
        `at` (n, 2)."""
        ...

    def models(self, u_m: np.ndarray, r_m: np.ndarray, echoes: list[tuple[np.ndarray, np.ndarray]],
               gains: np.ndarray) -> np.ndarray | list[np.ndarray]:
        """Each target's model in the domain its peak is refined on, from its unit-gain matched echo
        and its gains."""
        ...

    def refine_peak(self, at: np.ndarray, i: int, residual, models) -> Cell:
        """Peak i refined from `at[i]` on the data minus the other targets' models: `residual` (the data
        minus every model) plus its own model, `models[i]`."""
        ...

    def residual(self, models):
        """The data minus every target's model."""
        ...


def cancel_neighbours(cells: list[Cell], model: CancellationModel, passes: int, tol_m: float, degree: int,
                      deadline_s: float = math.inf) -> list[Cell]:
    """`cancel_neighbours_with_residual` without the residual."""
    return cancel_neighbours_with_residual(cells, model, passes, tol_m, degree, deadline_s)[0]


def cancel_neighbours_with_residual(cells: list[Cell], model: CancellationModel, passes: int, tol_m: float,
                                    degree: int, deadline_s: float = math.inf) -> tuple[list[Cell], object]:
    """Re-refine every peak on the data with the modelled responses of all the other peaks subtracted.

    Parameters
    ----------
    cells : list of (a, b, value)
        The peaks after the first refinement: fractional (row, column) indices and complex values.
    model : CancellationModel
        The image's model step (`NlcsModel`, `BackprojectionModel`).
    passes : int
        Most passes (each re-models at the positions of the previous one).
    tol_m : float
        Stop early once no peak moved by more than this (m).
    degree : int
        Legendre degree of the fitted gains (`fit_pulse_gains`).
    deadline_s : float
        `time.monotonic()` after which no peak is re-refined (the time budget): the peaks not reached keep
        their previous refinement, the strongest (first) being reached first; no new pass starts after it.

    Returns
    -------
    cells : list of (a, b, value)
        The re-refined peaks, in the order of `cells`.
    residual
        The data minus every model of the last pass (`model.residual`), the models made at the positions that
        pass started from; None when no pass ran.
    """
    residual, previous = None, cells
    for _ in range(passes):
        if time.monotonic() > deadline_s:
            log.warning("neighbour cancellation stopped by its time budget before a pass (%d targets)",
                        len(cells))
            break
        at = np.array([(a, b) for a, b, _ in cells])
        u_m, r_m = model.positions(at)
        lost = ~(np.isfinite(u_m) & np.isfinite(r_m))
        if lost.any():  # a peak refined off the focus-position map (NaN there) keeps its previous place
            cells = [p if off else c for c, p, off in zip(cells, previous, lost)]
            at = np.array([(a, b) for a, b, _ in cells])
            u_m, r_m = model.positions(at)
        models = fitted_models(model, u_m, r_m, degree)
        residual = model.residual(models)
        refined: list[Cell] = []
        for i in range(len(at)):
            if time.monotonic() > deadline_s:
                log.warning("neighbour cancellation stopped by its time budget after %d of %d targets",
                            i, len(at))
                break
            refined.append(model.refine_peak(at, i, residual, models))
        if len(refined) < len(cells):
            return refined + cells[len(refined):], residual
        previous, cells = cells, refined
        moved = np.hypot((np.array([c[0] for c in cells]) - at[:, 0]) * model.cell_m[0],
                         (np.array([c[1] for c in cells]) - at[:, 1]) * model.cell_m[1])
        if moved.max() <= tol_m:
            break
    return cells, residual


@dataclasses.dataclass(frozen=True, eq=False)
class BackprojectionModel:
    """Models subtracted from the range-compressed echo, which is backprojected again at each peak."""

    products: bp.BackprojectionProducts

    @property
    def grid(self) -> nlcs.FocusGrid:
        return self.products.grid

    @property
    def compressed(self) -> bp.RangeCompressed:
        return self.products.compressed

    @property
    def cell_m(self) -> tuple[float, float]:
        p = self.products
        return p.u_axis_m[1] - p.u_axis_m[0], p.r_axis_m[1] - p.r_axis_m[0]

    def positions(self, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        du, dr = self.cell_m
        return self.products.u_axis_m[0] + at[:, 0] * du, self.products.r_axis_m[0] + at[:, 1] * dr

    def models(self, u_m, r_m, echoes, gains) -> list[np.ndarray]:
        return [e * g[:, None] for g, (e, _) in zip(gains, echoes)]

    def residual(self, models: list[np.ndarray]) -> np.ndarray:
        return self.compressed.data - sum(models)

    def refine_peak(self, at: np.ndarray, i: int, residual: np.ndarray, models: list[np.ndarray]) -> Cell:
        data = dataclasses.replace(self.compressed, data=residual + models[i])
        return refine.maximise_nelder_mead(refine.bp_evaluator(self.products, data), at[i, 0], at[i, 1],
                                           step=BP_RECANCEL_STEP_CELLS)


@dataclasses.dataclass(frozen=True, eq=False)
class NlcsModel:
    """Models focused by the pass's own chain and H8 (`Focuser.nlcs_model_spectra`) and subtracted from the
    image's 2-D spectrum on the rows the band-limited interpolant sums (no image, no last azimuth IFFT)."""

    products: nlcs.NlcsProducts
    focuser: Focuser
    compressed: bp.RangeCompressed
    rows: np.ndarray  # signed azimuth rows of the spectrum (nlcs.spectrum_rows)
    spectrum: np.ndarray  # (rows, n_range): fft2(image) / (n m) on them

    @classmethod
    def of(cls, products: nlcs.NlcsProducts, scan: ScanPass, focuser: Focuser, rows: np.ndarray,
           spectrum: np.ndarray) -> NlcsModel:
        # the gain fit needs no upsampling; the same delays as the echo
        return cls(products, focuser, bp.range_compress(scan, products.grid, upsample=1), rows, spectrum)

    @property
    def grid(self) -> nlcs.FocusGrid:
        return self.products.grid

    @property
    def cell_m(self) -> tuple[float, float]:
        grid = self.products.grid
        return grid.track_spacing_m, grid.range_bins_m[1] - grid.range_bins_m[0]

    def positions(self, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        _, r, t_n = calibration.peak_track_times(self.products, at[:, 0], at[:, 1], self.focuser)
        return self.grid.speed_m_s * t_n, r

    def models(self, u_m, r_m, echoes, gains) -> np.ndarray:
        rc, grid = self.compressed, self.grid
        raw = np.array([g[:, None] * bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u_m[j], r_m[j],
                                                          matched=False)[0] for j, g in enumerate(gains)])
        return self.focuser.nlcs_model_spectra(self.products, rc.x_rel_m, raw, self.rows)

    def residual(self, models: np.ndarray) -> np.ndarray:
        return self.spectrum - models.sum(axis=0)

    def lattice(self, spectrum: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The image of `spectrum` (on `rows`) on the lattice of fractional indices a (n_a,) x b (n_b,)."""
        return refine.TrigInterpolant.from_rows(self.rows, spectrum, self.grid.n_azimuth).lattice(a, b)

    def frequencies(self) -> tuple[np.ndarray, np.ndarray]:
        """The spectrum's azimuth (on `rows`) and range frequencies, cycles per cell (`TrigInterpolant`)."""
        return self.rows / self.grid.n_azimuth, np.fft.fftfreq(self.spectrum.shape[-1])

    def shift_ramp(self, da: float, db: float) -> np.ndarray:
        """The factor that moves an image by (da, db) cells, on its spectrum's rows (exact: band limited)."""
        ka, kb = self.frequencies()
        return np.exp(-2j * np.pi * ka * da)[:, None] * np.exp(-2j * np.pi * kb * db)[None, :]

    def refine_peak(self, at: np.ndarray, i: int, residual: np.ndarray, models: np.ndarray) -> Cell:
        interpolant = refine.TrigInterpolant.from_rows(self.rows, residual + models[i], self.grid.n_azimuth)
        return interpolant.maximise(at[i, 0], at[i, 1], step=NLCS_RECANCEL_STEP_CELLS)
