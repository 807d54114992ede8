"""The backend seam: the `Focuser` protocol that detection and the pipeline call, and the table of stages.

Three backends implement it: the float64 numpy reference (`reference.NumpyFocuser`, delegating to the pure
functions of `nlcs.py` and `backprojection.py`), the float32 scipy baseline (`scipy32.Scipy32Focuser`) and the
OpenCL engine (`engine.FocusEngine`). Detection needs the four methods: the pass's image (NLCS or BP), the
neighbours' modelled images for neighbour cancellation (`nlcs_model_spectra`) and the simulated targets of the
t_f(t_n) calibration (`calibration_spectra`), each focused by the chain that focused the pass.

`STAGES` names every stage of the chains and what implements it in each backend; docs/method.md (section 3,
"Focusers") prints the same table and tests/test_focusers.py holds the two and the code to each other.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from ..model import ScanPass
from .backprojection import BackprojectionProducts, RangeCompressed
from .nlcs import AzimuthCompression, FocusGrid, NlcsProducts


@runtime_checkable
class Focuser(Protocol):
    """What a focusing backend provides. Arrays are numpy on the host; azimuth runs along axis 0."""

    def nlcs_focus(self, scan: ScanPass, *, ac_mode: str = "exact", grid: FocusGrid | None = None,
                   compression: AzimuthCompression | None = None) -> NlcsProducts:
        """Focus one pass with the modified NLCS chain (paper section 2.2, docs/method.md section 2).

        Parameters
        ----------
        scan : ScanPass
            The pass: echo (n_pulses, n_samples) complex, pulse positions (m).
        ac_mode : {"exact", "series"}
            Azimuth compression H8: fitted to a simulated reference target per bin, or the series of eq. 17.
        grid : FocusGrid, optional
            The processing grid; default `nlcs.focus_grid(scan)`.
        compression : AzimuthCompression, optional
            An H8 already computed for this grid (overrides `ac_mode`).

        Returns
        -------
        NlcsProducts
            `image` (n_azimuth, n_range) complex on the centred (t_a, r_LRCM) grid (t_a = 0 at row
            n_azimuth/2), the grid, per-bin coefficients, H8 and, where the backend has it, `spectrum`:
            fft2(image) / (n m) on the rows `nlcs.spectrum_rows(grid, compression)`.
        """
        ...

    def backprojection_focus(self, scan: ScanPass, *, pixel_m: float = 0.01, grid: FocusGrid | None = None,
                             range_margin_m: float = 0.1, u_extent_m: tuple[float, float] | None = None
                             ) -> BackprojectionProducts:
        """Time-domain backprojection of one pass onto the (u = v t_n, r_LRCM) plane (docs/method.md, 3).

        Parameters
        ----------
        scan : ScanPass
            The pass.
        pixel_m : float
            Pixel spacing along both axes (m).
        grid : FocusGrid, optional
            The processing grid; default `nlcs.focus_grid(scan)`.
        range_margin_m : float
            Range left out at each end of the range window (m).
        u_extent_m : (float, float), optional
            The image's u extent (m), e.g. the beam's footprint (`detect.peaks.search_extent_u_m`);
            default the rail's (`backprojection.image_axes`).

        Returns
        -------
        BackprojectionProducts
            `image` (n_u, n_r) complex, axes `u_axis_m` (n_u,) and `r_axis_m` (n_r,) in m, the grid, and the
            range-compressed echo (host copy) that sub-cell refinement backprojects again.
        """
        ...

    def nlcs_model_spectra(self, products: NlcsProducts, x_rel_m: np.ndarray, echoes: Sequence[np.ndarray],
                           rows: np.ndarray) -> np.ndarray:
        """The 2-D spectra of the images model echoes focus to with the products' chain and H8.

        Parameters
        ----------
        products : NlcsProducts
            The pass's focus (grid, coefficients, H8 are reused).
        x_rel_m : ndarray, shape (n_pulses,)
            Rail positions of the pulses relative to the aperture centre (m), increasing.
        echoes : sequence of ndarray, each (n_pulses, n_range) complex
            Raw (not range-compressed) echoes on the pass's pulses and range window.
        rows : ndarray of int, shape (n_rows,)
            Signed azimuth frequency indices, contiguous and ascending (`nlcs.spectrum_rows`).

        Returns
        -------
        ndarray, shape (n_echoes, n_rows, n_range), complex128
            fft2(image) / (n_azimuth n_range) of each echo's image at `rows`, range in FFT order.
        """
        ...

    def calibration_spectra(self, products: NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Focused azimuth spectra of simulated point targets for the t_f(t_n) calibration (eqs. 18-19, C12).

        Parameters
        ----------
        products : NlcsProducts
            The pass's focus.
        r_m : ndarray, shape (n_r,)
            Target ranges r_LRCM (m); each target goes through the chain of the bin nearest its range.
        t_n_s : ndarray, shape (n_t,)
            Target azimuth times t_n (s), the same for every range.

        Returns
        -------
        f_hz : ndarray, shape (n_f,)
            Azimuth frequencies (Hz, FFT order) of the rows where H8 is not zero.
        y : ndarray, shape (n_f, n_r * n_t), complex128
            The focused spectra on those rows, one column per target, r-major.
        coarse_s : ndarray, shape (n_r * n_t,)
            Each target's coarse focus position t_f (s): the time of its focused image's largest sample.
        """
        ...

    def backproject_track_points(self, rc: RangeCompressed, grid: FocusGrid, x_rel_m, rc_m,
                                 counts: bool = False):
        """The BP value of a range-compressed echo at arbitrary points (docs/method.md section 3): what the
        rib registration (eq. R1) and the carrier phases (eq. R5) backproject.

        Parameters
        ----------
        rc : RangeCompressed
            The pass's range-compressed echo (pulses x fine samples) and its pulse positions.
        grid : FocusGrid
            The pass's grid (carrier, Doppler band, aperture centre).
        x_rel_m, rc_m : array_like, broadcastable
            The points along the rail relative to the aperture centre, x - x_c (m), and in closest-approach
            range R_c (m).
        counts : bool
            Also return how many pulses each point sums.

        Returns
        -------
        ndarray, complex128, the broadcast shape (and with `counts` an int64 array of the same shape).
        """
        ...


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage and what implements it in each backend.

    `numpy` and `scipy32` are "module.function" in `uwbcl.focus` (scipy32 names a reference function where it
    reuses the float64 one); `opencl` is "FocusEngine.method" or "file.cl: kernel" in `kernels/`.
    """

    name: str
    numpy: str
    scipy32: str
    opencl: str


STAGES = (
    # the NLCS chain (docs/method.md section 2), in order
    Stage("range_fft", "nlcs.range_fft", "scipy32.range_fft_walk_corrected", "FocusEngine.fft"),
    Stage("linear_range_walk_correction", "nlcs.linear_range_walk_correction",
          "scipy32.range_fft_walk_corrected", "range.cl: range_walk_correction"),
    Stage("resample_to_uniform_track", "nlcs.resample_to_uniform_track", "scipy32.resample_padded",
          "range.cl: resample_to_uniform_track"),
    Stage("extended_nlcs", "nlcs.extended_nlcs", "nlcs.extended_nlcs", "range.cl: resample_to_uniform_track"),
    Stage("azimuth_fft", "nlcs.az_fft", "scipy32._fft", "FocusEngine.fft"),
    Stage("secondary_range_compression", "nlcs.secondary_range_compression",
          "scipy32.secondary_range_compression_rows", "range.cl: secondary_range_compression"),
    Stage("range_ifft", "nlcs.range_ifft", "scipy32._ifft", "FocusEngine.fft"),
    Stage("azimuth_compensation", "nlcs.azimuth_compensation", "scipy32.azimuth_filter_rows",
          "azimuth.cl: nlcs_filter"),
    Stage("nlcs_filter", "nlcs.nlcs_filter", "scipy32.azimuth_filter_rows", "azimuth.cl: nlcs_filter"),
    Stage("nlcs_scaling", "nlcs.nlcs_scaling", "scipy32.nlcs_scaling", "azimuth.cl: nlcs_scaling"),
    Stage("point_response", "nlcs.slow_time_point_response", "scipy32.reference_point_response",
          "azimuth.cl: point_response"),
    Stage("exact_reference_azimuth_compression", "nlcs.exact_reference_azimuth_compression",
          "scipy32.exact_reference_azimuth_compression", "FocusEngine.exact_reference_azimuth_compression"),
    Stage("azimuth_compression", "nlcs.azimuth_compression", "scipy32.azimuth_compression",
          "azimuth.cl: azimuth_compression"),
    Stage("azimuth_ifft", "nlcs.az_ifft", "scipy32._ifft", "FocusEngine.fft"),
    # backprojection (section 3): scipy32 has no float32 version and uses the reference
    Stage("range_compress", "backprojection.range_compress", "backprojection.range_compress",
          "backprojection.cl: pulse_compression_upsample"),
    Stage("backproject", "backprojection.backproject_points", "backprojection.backproject_points",
          "backprojection.cl: backproject"),
    # the Focuser methods (what detection calls)
    Stage("nlcs_focus", "nlcs.nlcs_focus", "scipy32.nlcs_focus_scipy32", "FocusEngine.nlcs_focus"),
    Stage("backprojection_focus", "backprojection.backprojection_focus",
          "backprojection.backprojection_focus", "FocusEngine.backprojection_focus"),
    Stage("nlcs_model_spectra", "nlcs.nlcs_model_spectra", "scipy32.nlcs_model_spectra",
          "FocusEngine.nlcs_model_spectra"),
    Stage("calibration_spectra", "nlcs.calibration_spectra", "nlcs.calibration_spectra",
          "FocusEngine.calibration_spectra"),
    Stage("backproject_track_points", "backprojection.backproject_track_points",
          "backprojection.backproject_track_points", "FocusEngine.backproject_track_points"),
)

FOCUSER_METHODS = ("nlcs_focus", "backprojection_focus", "nlcs_model_spectra", "calibration_spectra",
                   "backproject_track_points")
