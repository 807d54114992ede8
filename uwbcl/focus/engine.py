"""The OpenCL focusing engine: the NLCS chain and backprojection of `nlcs.py` / `backprojection.py` on a
device.

Three layers (docs/opencl.md, "Structure"):

* `processing.OpenclProcessing`, the device spine: context, queue, the program built from `PROGRAM_FILES` with
  `-D` defines, the kernel table parsed from the `__kernel` signatures (every launch names its arguments), the
  buffer table `BUFFERS` (shapes as functions of the focus grid), the device-memory check of each pass and
  optional profiling per stage;
* `device_fft.DeviceFft`: our Stockham azimuth FFTs, VkFFT plans for the rest, the start-up self-test;
* `FocusEngine` (here): the NLCS and backprojection orchestration on them.

One engine is reused across passes (buffers and plans are kept per shape, so a batch of same-sized passes
allocates once). Coefficients are computed on the host (`coefficients.py`, a few scalars per range bin); every
phase function is evaluated in the kernels from them (`kernels/*.cl`). Data are complex64 on the device; phase
arguments are evaluated in float64 where the device has fp64 (docs/opencl.md, error budget). The reference
spectra of the exact-reference H8 are computed in complex64; the few bins whose band edge is within rounding
of the fit's threshold are recomputed on the host in float64 (`REFERENCE_EDGE_MARGIN`).

Azimuth arrays live on the device in FFT (natural) order; the numpy reference keeps them centred. The engine
converts at the edges only (writing the resampled track in natural order, fftshift of the read-back image).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time

import numpy as np

from .. import opencl
from ..model import ScanPass
from . import backprojection as bp
from . import coefficients as coef
from . import device_fft, nlcs
from .processing import REAL, BufferSpec, OpenclProcessing, PreparedLaunch

log = logging.getLogger("uwbcl")

PROGRAM_FILES = ("common.cl", "range.cl", "azimuth.cl", "fft.cl", "backprojection.cl")
# |X_ref| closer than this fraction of its bin's peak to the H8 fit's threshold counts as undecided in
# complex64 (measured complex64 error on PoCL: 3e-7 of the peak); such bins are recomputed in float64.
REFERENCE_EDGE_MARGIN = 3e-6
LAGRANGE_TAPS = nlcs.LAGRANGE_ORDER  # taps of the motion-compensation resampling
ROW_STEP = 128  # band buffers' row counts are rounded up to this: their range-FFT plans recur across passes
# An echo's rows (pulses) are rounded up to this, zero rows after the pulses: the pulse count moves with the
# carriage speed from pass to pass, and every new row count of a range FFT is a new VkFFT plan (measured on
# PoCL, 2 cores: ~50 ms with the runtime's kernel cache, 0.6-2 s to compile without; a 41-cycle study rig has
# 19 pulse counts in 76 passes). Zero rows cost a few percent of one range FFT.
PULSE_ROW_STEP = 32
AC_TERMS_BOUND = 9  # H8 polynomial terms at most: the degree-8 exact-reference fit (the series has 5)
BP_UPSAMPLE = 16  # backprojection's range upsampling
NLCS_COEFFICIENTS = ("eta1", "y3", "y4", "q2", "q3", "q4")
POINT_STEP = 1024  # point counts of `backproject_track_points` are rounded up to this: its buffers recur


def _round_up(n: int, step: int) -> int:
    """The smallest multiple of step >= n: buffer extents that recur from pass to pass."""
    return -(-n // step) * step


def padded_rows(n_rows: int, grid: nlcs.FocusGrid) -> int:
    """A band's row count rounded up to ROW_STEP (at most the whole azimuth axis)."""
    return min(_round_up(n_rows, ROW_STEP), grid.n_azimuth)


def pulse_rows(n_pulses: int) -> int:
    """Rows of the device buffers that hold a pass's pulses: n_pulses rounded up to PULSE_ROW_STEP."""
    return _round_up(n_pulses, PULSE_ROW_STEP)


def _with_rows(a: np.ndarray, rows: int) -> np.ndarray:
    """`a` (n, ...) followed by zero rows up to `rows`."""
    if a.shape[0] == rows:
        return a
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[:a.shape[0]] = a
    return out


def _band_shape(grid: nlcs.FocusGrid) -> tuple[int, int]:
    return padded_rows(_doppler_band_rows(grid)[1], grid), grid.n_range


def _full_shape(grid: nlcs.FocusGrid) -> tuple[int, int]:
    return grid.n_azimuth, grid.n_range


def _per_bin(grid: nlcs.FocusGrid) -> tuple[int]:
    return (grid.n_range,)


COMPLEX64 = np.complex64
# Every device buffer of the engine. Shapes are functions of the focus grid (for per-column arrays such as the
# calibration's, of the grid with n_range = columns) and of the named extents the grid does not fix.
BUFFERS = (
    BufferSpec("echo", lambda g, n_pulses: (n_pulses, g.n_range), COMPLEX64,
               doc="an echo, then its range FFT"),
    BufferSpec("x_rel", lambda g, n_pulses: (n_pulses,), REAL, True, "logged rail positions - centre (m)"),
    BufferSpec("first", lambda g: (g.n_track,), np.int32, True, "first Lagrange tap pulse per track sample"),
    BufferSpec("weights", lambda g, taps: (g.n_track, taps), REAL, True, "Lagrange weights per track sample"),
    BufferSpec("azimuth", _full_shape, COMPLEX64,
               doc="the padded (range-)Doppler array of an echo, FFT order"),
    BufferSpec("doppler_rows", _band_shape, COMPLEX64, doc="the Doppler band's rows of `azimuth`"),
    BufferSpec("filter_src", _band_shape, COMPLEX64, doc="H3 * band mask * H4 * range-IFFT delay, band rows"),
    BufferSpec("filter_h5h6", _band_shape, COMPLEX64, doc="H5 H6 on the band rows"),
    BufferSpec("filter_h7", _full_shape, COMPLEX64, doc="H7, whole azimuth axis"),
    *(BufferSpec(name, _per_bin, REAL, True, "NLCS coefficient per bin") for name in NLCS_COEFFICIENTS),
    BufferSpec("pulse_filter", _per_bin, COMPLEX64, True,
               "measured pulse's H4 = conj(P) per range frequency"),
    BufferSpec("ac_poly", lambda g, n_terms: (g.n_range, n_terms), REAL, True, "H8 polynomial per bin"),
    BufferSpec("ac_first", _per_bin, np.int32, True, "H8 band: first signed azimuth index per bin"),
    BufferSpec("ac_last", _per_bin, np.int32, True, "H8 band: last signed azimuth index per bin"),
    BufferSpec("filter_h8", lambda g, rows: (rows, g.n_range), COMPLEX64,
               doc="H8 on the image spectrum's rows"),
    BufferSpec("h8_rows", lambda g, rows: (padded_rows(rows, g), g.n_range), COMPLEX64,
               doc="image spectrum rows"),
    BufferSpec("model_rows", lambda g, rows: (padded_rows(rows, g), g.n_range), COMPLEX64,
               doc="a neighbour model's spectrum rows"),
    BufferSpec("reference", lambda g, columns, rows: (rows, columns), COMPLEX64,
               doc="the whole-beam reference per bin, on its own azimuth axis of `rows` (D5)"),
    BufferSpec("calibration", lambda g, columns: (g.n_azimuth, columns), COMPLEX64,
               doc="simulated targets per column"),
    *(BufferSpec(f"{name}_{what}", lambda g, columns: (columns,), REAL, True, "per column")
      for name in ("reference", "calibration") for what in ("r", "t_n")),
    BufferSpec("fine", lambda g, n_pulses, upsample: (n_pulses, g.n_range * upsample), COMPLEX64,
               doc="range-compressed, upsampled pulses"),
    BufferSpec("x_rel_f32", lambda g, n_pulses: (n_pulses,), np.float32, True, "x_rel for backprojection"),
    BufferSpec("bp_image", lambda g, n_u, n_r: (n_u, n_r), COMPLEX64, doc="the backprojection image"),
    BufferSpec("points_echo", lambda g, n_pulses, n_fine: (n_pulses, n_fine), COMPLEX64, True,
               "a range-compressed echo backprojected at points (uploaded again only when it changes)"),
    BufferSpec("points_x_pulse", lambda g, n_pulses: (n_pulses,), np.float32, True, "its pulses' x - x_c"),
    BufferSpec("points_x", lambda g, n_points: (n_points,), REAL, doc="points along the rail, x - x_c (m)"),
    BufferSpec("points_rc", lambda g, n_points: (n_points,), REAL, doc="points' closest-approach range (m)"),
    BufferSpec("points_value", lambda g, n_points: (n_points,), COMPLEX64, doc="the BP value per point"),
    BufferSpec("points_count", lambda g, n_points: (n_points,), np.int32, doc="pulses summed per point"),
) + device_fft.BUFFERS

# kernels whose work item handles four neighbouring range bins, pixels or points (common.cl, c4)
FOUR_BIN_KERNELS = frozenset({"nlcs_filter", "nlcs_scaling", "point_response", "range_walk_correction",
                              "azimuth_compression", "secondary_range_compression", "backproject",
                              "backproject_track_points"})


class FocusEngine(OpenclProcessing):
    """OpenCL implementation of the focusing stages; `nlcs_focus` and `backprojection_focus` return the same
    products as the numpy functions of the same names.

    Parameters
    ----------
    device : a pyopencl Device, or a device spec for `opencl.select_device` (None: the default device).
    fp64_phase : evaluate phase arguments in float64 (default: where the device has fp64).
    profile : record every device command per stage (`profile_table`); off by default (the queue then has no
        profiling overhead).
    fft_lanes : columns per work item of the azimuth FFT kernels, 4, 8 or 16 (default: from the device's
        preferred float vector width, `device_fft.fft_lanes`).
    """

    def __init__(self, device=None, *, fp64_phase: bool | None = None, profile: bool = False,
                 fft_lanes: int | None = None):
        import pyopencl as cl

        try:
            from pyvkfft.opencl import VkFFTApp
        except ImportError as exc:
            raise opencl.OpenClUnavailable(f"pyvkfft is not importable ({exc}); " + opencl.FFT_HINT) from exc
        t0 = time.perf_counter()
        dev = device if isinstance(device, cl.Device) else opencl.select_device(device)
        has_fp64 = bool(dev.double_fp_config)
        if fp64_phase and not has_fp64:
            raise opencl.OpenClUnavailable(f"{dev.name.strip()} has no fp64; use fp64_phase=False")
        self.fp64_phase = has_fp64 if fp64_phase is None else fp64_phase
        if not self.fp64_phase:
            log.warning("%s: phase arguments in float32 (no fp64): NLCS images differ from the float64 "
                        "reference by ~4e-3 and backprojection by ~2e-4, over the 1e-4 budget "
                        "(docs/opencl.md, error budget); a device with fp64 or --backend numpy keeps it",
                        dev.name.strip())
        # repr of a float is its shortest exact form: the kernels compare with the reference's own double
        lanes = device_fft.fft_lanes(dev) if fft_lanes is None else fft_lanes
        if lanes not in (4, 8, 16):
            raise ValueError(f"fft_lanes must be 4, 8 or 16, not {lanes}")
        super().__init__(dev, PROGRAM_FILES, BUFFERS, defines={"SQUINT_SINE_CAP": repr(nlcs.SQUINT_SINE_CAP),
                                                               **device_fft.fft_defines(lanes)},
                         fp64=self.fp64_phase, profile=profile)
        self.ffts = device_fft.DeviceFft(self, VkFFTApp, lanes)
        self._filters: _PassFilters | None = None  # the last grid's filter tables
        self._h8_tables: dict = {}  # name -> (compression, grid, (first, last row), table)
        self._track: tuple | None = None  # (x_rel bytes, grid, first taps, weights) of the last track
        self._echo_chain: _EchoChain | None = None  # the last echo chain's launches, replayed while valid
        self._recording: list | None = None  # steps of the echo chain being recorded
        with self.stage("FFT self-test"):
            failure = self.ffts.self_test_failure()
        if failure:
            raise opencl.OpenClUnavailable(f"{failure}; this OpenCL runtime miscompiles it, "
                                           "use --backend numpy")
        self.startup_s = time.perf_counter() - t0

    def release_kept(self) -> None:
        """`OpenclProcessing.release_kept` and the engine's own: the filter tables, the H8 tables and the
        recorded echo chain hold device arrays too (rebuilt on the next pass that needs them)."""
        super().release_kept()
        self._filters, self._echo_chain = None, None
        self._h8_tables.clear()

    def __repr__(self) -> str:
        return f"FocusEngine({self.device.name.strip()!r}, fp64_phase={self.fp64_phase})"

    # ------------------------------------------------------------------------------------------ plumbing
    def fft(self, arr, axis: int, inverse: bool = False) -> None:
        """In-place complex FFT along one axis (`device_fft.DeviceFft.fft`); numpy's normalisation."""
        self.ffts.fft(arr, axis, inverse)
        if self._recording is not None:
            self._recording.append(functools.partial(self.ffts.fft, arr, axis, inverse))

    def reals(self, name: str, values, grid: nlcs.FocusGrid, **extents):
        """Per-bin coefficients (or positions) in the phase precision, into the declared buffer `name`."""
        return self.to_device(name, np.asarray(values, dtype=float), grid, **extents)

    def _launch(self, name: str, rows: int, cols: int, **args) -> None:
        """Launch kernel `name` by argument name on a (cols, rows) grid (cols / 4 work items across for the
        four-bin kernels)."""
        if name in FOUR_BIN_KERNELS:
            cols = -(-cols // 4)
        if self._recording is None:
            self.launch(name, (cols, rows), **args)
            return
        launch = self.prepare(name, (cols, rows), **args)
        self.enqueue(launch)  # its arguments are set once, for every replay
        self._recording.append(functools.partial(self.enqueue, launch))

    def _nlcs_entries(self, grid: nlcs.FocusGrid, n_pulses: int) -> list:
        """(buffer, extents) of one echo through the chain, with its filter tables and H8 (the footprint)."""
        rows = _doppler_band_rows(grid)[1]  # the image spectrum's rows lie inside the Doppler band's
        pulses = pulse_rows(n_pulses)
        return [("echo", {"n_pulses": pulses}), ("x_rel", {"n_pulses": pulses}), ("first", {}),
                ("weights", {"taps": LAGRANGE_TAPS}), ("azimuth", {}),
                ("fft_scratch", {"n": grid.n_azimuth, "cols": grid.n_range}),
                ("fft_twiddle", {"n": grid.n_azimuth}),
                ("doppler_rows", {}), ("pulse_filter", {}),
                ("filter_src", {}), ("filter_h5h6", {}), ("filter_h7", {}),
                *((name, {}) for name in NLCS_COEFFICIENTS), ("ac_poly", {"n_terms": AC_TERMS_BOUND}),
                ("ac_first", {}), ("ac_last", {}), ("filter_h8", {"rows": rows}), ("h8_rows", {"rows": rows})]

    @staticmethod
    def _reference_entries(grid: nlcs.FocusGrid, aperture_m: float) -> list:
        """(buffer, extents) of the exact-reference spectra, on their own azimuth axis (D5)."""
        n = nlcs.reference_grid(grid, aperture_m).n_azimuth
        columns = {"columns": grid.n_range}
        return [("reference", {**columns, "rows": n}), ("reference_r", columns), ("reference_t_n", columns),
                ("fft_scratch", {"n": n, "cols": grid.n_range}), ("fft_twiddle", {"n": n})]

    def nlcs_footprint(self, grid: nlcs.FocusGrid, n_pulses: int, aperture_m: float) -> int:
        """Device bytes `nlcs_focus` needs for a pass of `n_pulses` pulses on `grid` (from the buffer table;
        the exact-reference spectra for an antenna of aperture_m included)."""
        entries = self._nlcs_entries(grid, n_pulses) + self._reference_entries(grid, aperture_m)
        return sum(self.footprint(grid, entries).values())

    # ------------------------------------------------------------------------------------------ NLCS stages
    def range_walk_correction(self, s, x_rel_m: np.ndarray, grid: nlcs.FocusGrid) -> None:
        """range FFT delay origin (eq. 3) and H1 (eq. 4) in place on a range spectrum (pulses, n_range); the
        rows after len(x_rel_m) (`pulse_rows`' zero rows) get x = 0."""
        self._launch("range_walk_correction", s.shape[0], s.shape[1], s=s,
                     x_rel_m=self._x_rel_rows(x_rel_m, grid, s.shape[0]), n_range=grid.n_range,
                     sample_rate_hz=grid.sample_rate_hz, window_start_s=grid.range_window_start_s,
                     carrier_hz=grid.carrier_frequency_hz, sin_squint=grid.sin_squint)

    def _x_rel_rows(self, x_rel_m: np.ndarray, grid: nlcs.FocusGrid, rows: int):
        """The "x_rel" buffer: pulse positions (m) padded with zeros to `rows`."""
        return self.reals("x_rel", _with_rows(np.asarray(x_rel_m, dtype=float), rows), grid, n_pulses=rows)

    def resample_to_uniform_track(self, s, x_rel_m: np.ndarray, grid: nlcs.FocusGrid, p2_m_s2: float = 0.0):
        """Lagrange resampling onto the uniform track, ENLCS H2 (eq. 6), padding: -> (n_azimuth, n_range),
        FFT order."""
        first, w = self._lagrange_weights(x_rel_m, grid)
        out = self.buffer("azimuth", grid)
        self._launch("resample_to_uniform_track", grid.n_azimuth, grid.n_range, s=s, out=out,
                     first=self.to_device("first", first, grid),
                     weights=self.reals("weights", w, grid, taps=LAGRANGE_TAPS), order=LAGRANGE_TAPS,
                     n_track=grid.n_track, n_azimuth=grid.n_azimuth, n_range=grid.n_range,
                     sample_rate_hz=grid.sample_rate_hz, carrier_hz=grid.carrier_frequency_hz,
                     track_dt_s=grid.dt_s, p2_m_s2=float(p2_m_s2))
        return out

    def _lagrange_weights(self, x_rel_m: np.ndarray, grid: nlcs.FocusGrid) -> tuple[np.ndarray, np.ndarray]:
        """(first tap pulse (n_track,), weights (n_track, taps)) of `nlcs.lagrange_weights` onto the grid's
        uniform track, kept for the last track (every neighbour model of a pass is resampled from the pass's
        own rail positions)."""
        key = np.asarray(x_rel_m, dtype=float).tobytes()
        if self._track is None or self._track[0] != key or self._track[1] != grid:
            idx, w = nlcs.lagrange_weights(x_rel_m, grid.t_track_s * grid.speed_m_s, LAGRANGE_TAPS)
            self._track = (key, grid, idx[:, 0].copy(), w)
        return self._track[2], self._track[3]

    @staticmethod
    def _row_origin(grid: nlcs.FocusGrid, first_row: int | None) -> int:
        """FFT-order position of row 0 of an array of azimuth rows starting at signed index first_row (None: a
        whole spectrum in FFT order)."""
        return 0 if first_row is None else int(first_row) % grid.n_azimuth

    def secondary_range_compression(self, s, grid: nlcs.FocusGrid, first_row: int | None = None) -> None:
        """H3 * band mask * H4 and the range IFFT's delay origin (eqs. 9-11), in place on the 2-D spectrum
        (or on its rows from signed azimuth index first_row on)."""
        lo, hi = grid.doppler_band
        self._launch("secondary_range_compression", s.shape[0], grid.n_range, s=s, n_range=grid.n_range,
                     n_azimuth=grid.n_azimuth, sample_rate_hz=grid.sample_rate_hz,
                     window_start_s=grid.range_window_start_s, carrier_hz=grid.carrier_frequency_hz,
                     azimuth_df_hz=grid.azimuth_df_hz, speed_m_s=grid.speed_m_s, sin_squint=grid.sin_squint,
                     reference_range_m=grid.reference_range_m, pulse_sigma_s=self._kernel_pulse_sigma_s(grid),
                     band_lo=lo, band_hi=hi, row_origin=self._row_origin(grid, first_row))
        self._measured_pulse_filter(s, grid)

    @staticmethod
    def _kernel_pulse_sigma_s(grid: nlcs.FocusGrid) -> float:
        """The kernels' Gaussian H4 width: the grid's, or 0 (H4 = 1) when `_measured_pulse_filter` applies
        the measured pulse's."""
        return grid.pulse_sigma_s if grid.measured_pulse is None else 0.0

    def _measured_pulse_filter(self, s, grid: nlcs.FocusGrid) -> None:
        """With a measured pulse, H4 = conj(P(f_r)) (eq. 10) on every row of a range spectrum s, in place."""
        if grid.measured_pulse is None:
            return
        h4 = self.to_device("pulse_filter", grid.pulse_filter(grid.f_range_hz), grid)
        self._launch("range_gain", s.shape[0], grid.n_range, s=s, h4=h4, n_range=grid.n_range)

    def nlcs_filter(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, *, with_h5: bool = True,
                    first_row: int | None = None) -> None:
        """H5 (eq. 13) and H6 (eq. 15) in place on a range-Doppler array (or band of rows)."""
        eta1 = k.eta1 if with_h5 else np.zeros_like(k.eta1)
        self._launch("nlcs_filter", s.shape[0], grid.n_range, s=s, eta1=self.reals("eta1", eta1, grid),
                     y3=self.reals("y3", k.y3, grid), y4=self.reals("y4", k.y4, grid), n_range=grid.n_range,
                     n_azimuth=grid.n_azimuth, azimuth_df_hz=grid.azimuth_df_hz,
                     row_origin=self._row_origin(grid, first_row))

    def nlcs_scaling(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid) -> None:
        """H7 (eq. 15) in place on a range-time array."""
        self._launch("nlcs_scaling", grid.n_azimuth, grid.n_range, s=s, q2=self.reals("q2", k.q2, grid),
                     q3=self.reals("q3", k.q3, grid), q4=self.reals("q4", k.q4, grid), n_range=grid.n_range,
                     n_azimuth=grid.n_azimuth, azimuth_dt_s=grid.dt_s)

    def azimuth_compression(self, s, ac: nlcs.AzimuthCompression, grid: nlcs.FocusGrid,
                            first_row: int | None = None) -> None:
        """H8 (eq. 17; C10, C11) in place on a range-Doppler array (or band of rows)."""
        # the reference's own test f_lo <= f <= f_hi on the (increasing) centred axis, as index bounds
        f = grid.f_azimuth_hz
        first = np.searchsorted(f, ac.f_lo_hz, side="left") - grid.n_azimuth // 2
        last = np.searchsorted(f, ac.f_hi_hz, side="right") - 1 - grid.n_azimuth // 2  # first > last: empty
        self._launch("azimuth_compression", s.shape[0], grid.n_range, s=s,
                     poly=self.reals("ac_poly", ac.poly, grid, n_terms=ac.poly.shape[1]),
                     n_coeff=ac.poly.shape[1],
                     band_first=self.to_device("ac_first", first, grid),
                     band_last=self.to_device("ac_last", last, grid), n_range=grid.n_range,
                     n_azimuth=grid.n_azimuth, azimuth_df_hz=grid.azimuth_df_hz, f_scale_hz=ac.f_scale_hz,
                     row_origin=self._row_origin(grid, first_row))

    def azimuth_nlcs_chain(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, *, with_h5: bool) -> None:
        """H5/H6 -> azimuth IFFT -> H7 -> azimuth FFT, in place on a range-Doppler array."""
        self.nlcs_filter(s, k, grid, with_h5=with_h5)
        self.fft(s, 0, inverse=True)
        self.nlcs_scaling(s, k, grid)
        self.fft(s, 0)

    def exact_reference_azimuth_compression(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                                            aperture_m: float, degree: int = 8) -> nlcs.AzimuthCompression:
        """As `nlcs.exact_reference_azimuth_compression`, the reference spectra computed on the device."""
        return nlcs.fit_azimuth_compression(self.reference_spectra(k, grid, aperture_m), k, grid, degree)

    def reference_spectra(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float
                          ) -> np.ndarray:
        """X_ref of every bin after H6/H7 (centred f_a, complex128), computed in complex64 on the device.

        The fit picks each bin's segment and band with a hard threshold on |X_ref|, which float32 rounding can
        move by one sample (an image error of 2e-3): the few bins with a band edge within rounding of the
        threshold are recomputed on the host in float64, so the fit decides exactly as the reference does."""
        return self._reference_spectra_result(self._enqueue_reference_spectra(k, grid, aperture_m), k, grid,
                                              aperture_m)

    def _enqueue_reference_spectra(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float):
        """Queue the device part of `reference_spectra` and its read-back: (`PendingRead`, the long grid)."""
        long = nlcs.reference_grid(grid, aperture_m)  # D5: the whole beam's response fits its axis
        h7 = self._pass_filters(grid, k).h7 if long == grid else None
        with self.stage("reference spectra"):
            ref = self.point_response(k.r_m, np.zeros(grid.n_range), long, aperture_m, "reference")
            self.fft(ref, 0)
            self.nlcs_filter(ref, k, long, with_h5=False)
            self.fft(ref, 0, inverse=True)
            if h7 is None:
                self.nlcs_scaling(ref, k, long)
            else:
                self._launch("apply_filter", grid.n_azimuth, grid.n_range, s=ref, filter=h7,
                             n_range=grid.n_range)
            self.fft(ref, 0)
            return self.host_async(ref), long

    def _reference_spectra_result(self, pending, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                                  aperture_m: float) -> np.ndarray:
        read, long = pending
        host = nlcs.on_grid_frequencies(read.result(), long, grid)
        x_ref = np.fft.fftshift(host, axes=0).astype(np.complex128)
        undecided = np.flatnonzero(undecided_band_edges(np.abs(x_ref), grid, REFERENCE_EDGE_MARGIN))
        if undecided.size:
            x_ref[:, undecided] = nlcs.reference_spectra(nlcs.select_bins(k, undecided), grid, aperture_m)
        return x_ref

    def point_response(self, r_m: np.ndarray, t_n_s: np.ndarray, grid: nlcs.FocusGrid, aperture_m: float,
                       name: str, rail_only: bool = False):
        """`nlcs.slow_time_point_response` on the device, one (r, t_n) per column, FFT order, into the buffer
        `name` ("reference" or "calibration")."""
        columns = r_m.size
        rows = {"rows": grid.n_azimuth} if name == "reference" else {}
        out = self.buffer(name, grid, columns=columns, **rows)
        self._launch("point_response", grid.n_azimuth, columns, out=out,
                     r_m=self.reals(f"{name}_r", r_m, grid, columns=columns),
                     t_n_s=self.reals(f"{name}_t_n", t_n_s, grid, columns=columns), n_cols=columns,
                     n_azimuth=grid.n_azimuth, azimuth_dt_s=grid.dt_s, speed_m_s=grid.speed_m_s,
                     sin_squint=grid.sin_squint, wavelength_m=grid.wavelength_m, aperture_m=float(aperture_m),
                     half_track_s=grid.half_track_s if rail_only else -1.0)
        return out

    def calibration_spectra(self, products: nlcs.NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`detect.calibration_spectra` on the device: simulated targets at every (r, t_n) (columns r-major)
        through the azimuth chain of the bin nearest each r.

        Returns
        -------
        f : (n_rows,) azimuth frequencies (Hz) of H8's rows, increasing.
        y : (n_rows, r_m.size * t_n_s.size) the targets' spectra there.
        coarse : (r_m.size * t_n_s.size,) the coarse focus time t_f (s) of each target.
        """
        grid = products.grid
        r_cols = np.repeat(np.asarray(r_m, dtype=float), t_n_s.size)
        t_cols = np.tile(np.asarray(t_n_s, dtype=float), np.size(r_m))
        # widths in steps of 16 (a whole number of FFT lane groups, fft.cl) recur from pass to pass, so the
        # buffer and its FFT launches are reused
        width = _round_up(r_cols.size, 16)
        r_cols = np.concatenate([r_cols, np.repeat(r_cols[-1:], width - r_cols.size)])
        t_cols = np.concatenate([t_cols, np.repeat(t_cols[-1:], width - t_cols.size)])
        j = grid.nearest_bin(r_cols)
        k = nlcs.select_bins(products.coefficients, j)
        ac = nlcs.select_bins(products.compression, j)
        columns = dataclasses.replace(grid, n_range=width)  # the kernels index per-column coefficients
        cols = {"columns": width}
        self.check_footprint("calibration", columns, [
            ("calibration", cols), ("calibration_r", cols), ("calibration_t_n", cols),
            *((name, {}) for name in ("eta1", "y3", "y4", "q2", "q3", "q4", "ac_first", "ac_last")),
            ("ac_poly", {"n_terms": ac.poly.shape[1]}), ("fft_scratch", {"n": grid.n_azimuth, "cols": width}),
            ("fft_twiddle", {"n": grid.n_azimuth})])
        with self.stage("calibration"):
            s = self.point_response(r_cols, t_cols, grid, products.aperture_m, "calibration", rail_only=True)
            self.fft(s, 0)
            self.azimuth_nlcs_chain(s, k, columns, with_h5=False)
            self.azimuth_compression(s, ac, columns)
            f = np.fft.ifftshift(grid.f_azimuth_hz)
            band = (f >= ac.f_lo_hz.min()) & (f <= ac.f_hi_hz.max())
            y = self.host(s).astype(np.complex128)[band]
            self.fft(s, 0, inverse=True)
            coarse = nlcs.coarse_focus_times(np.abs(self.host(s)).T, np.fft.ifftshift(grid.t_azimuth_s),
                                             t_cols)
        n = np.size(r_m) * t_n_s.size
        return f[band], y[:, :n], coarse[:n]

    def nlcs_focus(self, scan: ScanPass, *, ac_mode: str = "exact", grid: nlcs.FocusGrid | None = None,
                   compression: nlcs.AzimuthCompression | None = None) -> nlcs.NlcsProducts:
        """Focus one pass with the modified NLCS chain on the device (mirrors `nlcs.nlcs_focus`).

        Parameters
        ----------
        scan : the pass (echo (n_pulses, n_range), logged rail positions, radar, geometry).
        ac_mode : "exact" (H8 fitted to the exact reference spectra) or "series" (eq. 17).
        grid : the focus grid (default `nlcs.focus_grid(scan)`).
        compression : an H8 already computed for this grid (overrides ac_mode).

        Returns
        -------
        NlcsProducts: image (n_azimuth, n_range) complex64, centred azimuth time by range bin; the spectrum
        rows detection interpolates; grid, coefficients, H8.

        Raises
        ------
        processing.DeviceMemoryError before anything runs if the pass's buffers would not fit the device
        (`nlcs_footprint`)."""
        if ac_mode not in ("exact", "series"):
            raise ValueError(f"unknown azimuth compression mode {ac_mode!r} (exact|series)")
        grid = nlcs.focus_grid(scan) if grid is None else grid
        echo, x_rel = nlcs.prepare_track(scan, grid)
        aperture = nlcs.beam_aperture_m(scan)
        self.check_footprint("nlcs_focus", grid, self._nlcs_entries(grid, echo.shape[0])
                             + self._reference_entries(grid, aperture))
        k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
        p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
        if np.ptp(p2) > 0:
            raise NotImplementedError("the engine applies H2 with one p2 per pass; "
                                      "p2 varies across range here")
        ac = compression or (nlcs.series_azimuth_compression(k, grid) if ac_mode == "series" else None)
        pending = self._enqueue_reference_spectra(k, grid, aperture) if ac is None else None
        # queued behind the reference spectra: the device runs the chain while the host fits H8 to them
        s = self._nlcs_spectrum(echo, x_rel, grid, k, float(p2[0]))
        if ac is None:
            x_ref = self._reference_spectra_result(pending, k, grid, aperture)
            ac = nlcs.fit_azimuth_compression(x_ref, k, grid)
        # H8 on the rows that hold the image's spectrum (zero elsewhere); those rows are also read back, so
        # detection needs no 2-D FFT of the image
        rows = nlcs.spectrum_rows(grid, ac)
        h8 = self._h8_table(ac, grid, int(rows[0]), int(rows[-1]))
        with self.stage("H8 and spectrum rows"):
            band = self.buffer("h8_rows", grid, rows=rows.size)
            origin = self._row_origin(grid, rows[0])
            self._launch("gather_rows", rows.size, grid.n_range, full=s, out=band, filter=h8,
                         row_origin=origin, n_azimuth=grid.n_azimuth, n_range=grid.n_range)
            self._launch("scatter_rows", grid.n_azimuth, grid.n_range, band=band, full=s, row_origin=origin,
                         n_rows=rows.size, n_azimuth=grid.n_azimuth, n_range=grid.n_range)
            spectrum = self._range_spectra(band, rows)
        with self.stage("image"):
            self.fft(s, 0, inverse=True)
            image = np.fft.fftshift(self.host(s), axes=0)
        spectrum = nlcs.spectrum_rows_from_range_spectra(spectrum.result(), rows, grid)
        return nlcs.NlcsProducts(image=image, grid=grid, coefficients=k, compression=ac, aperture_m=aperture,
                                 spectrum=spectrum)

    def _pass_filters(self, grid: nlcs.FocusGrid, k: coef.NlcsCoefficients) -> _PassFilters:
        """The grid-only filters of the chain as device tables, made once per grid by the stage kernels
        (from their scalars, applied to ones) and then applied to every echo of the pass: the image's and
        detection's neighbour models'. SRC and H5/H6 live on the Doppler band's rows only (the band mask
        zeroes the rest), padded to a multiple of ROW_STEP rows so the band's range IFFT plan is reused across
        passes."""
        if self._filters is not None and self._filters.grid == grid:
            return self._filters
        with self.stage("filter tables"):
            first, _ = _doppler_band_rows(grid)
            src = self.buffer("filter_src", grid)
            self.fill(src, 1)
            self.secondary_range_compression(src, grid, first)
            h5h6 = self.buffer("filter_h5h6", grid)
            self.fill(h5h6, 1)
            self.nlcs_filter(h5h6, k, grid, with_h5=True, first_row=first)
            h7 = self.buffer("filter_h7", grid)
            self.fill(h7, 1)
            self.nlcs_scaling(h7, k, grid)
        self._filters = _PassFilters(grid, first, src, h5h6, h7)
        return self._filters

    def _h8_table(self, ac: nlcs.AzimuthCompression, grid: nlcs.FocusGrid, lo: int, hi: int):
        """H8 on the signed azimuth rows lo..hi as a device table (zero outside each bin's band), kept while
        the compression and rows stay the same."""
        cached = self._h8_tables.get("h8")
        if cached is not None and cached[0] is ac and cached[1:3] == (grid, (lo, hi)):
            return cached[3]
        with self.stage("H8 table"):
            table = self.buffer("filter_h8", grid, rows=hi - lo + 1)
            self.fill(table, 1)
            self.azimuth_compression(table, ac, grid, first_row=lo)
        self._h8_tables["h8"] = (ac, grid, (lo, hi), table)
        return table

    def _nlcs_spectrum(self, echo: np.ndarray, x_rel: np.ndarray, grid: nlcs.FocusGrid,
                       k: coef.NlcsCoefficients, p2: float):
        """echo -> the range-Doppler array before H8 (device, whole spectrum in FFT order).

        The chain's launches are recorded with their arguments set (prepared launches) and replayed for the
        next echo on the same track, grid and buffers: a pass's neighbour models differ from its image only in
        the echo, and setting every kernel's arguments again cost more host time than the launches."""
        f = self._pass_filters(grid, k)
        with self.stage("echo chain"):
            rows = pulse_rows(echo.shape[0])
            s = self.to_device("echo", _with_rows(echo, rows), grid, n_pulses=rows)
            first, w = self._lagrange_weights(x_rel, grid)
            # the track's constant tables: uploaded only when their bytes change, so a replay sees them
            tables = (self._x_rel_rows(x_rel, grid, rows),
                      self.to_device("first", first, grid),
                      self.reals("weights", w, grid, taps=LAGRANGE_TAPS))
            out, band = self.buffer("azimuth", grid), self.buffer("doppler_rows", grid)
            arrays = (s, *tables, out, band, f.src, f.h5h6, f.h7)
            chain = self._echo_chain
            if chain is not None and chain.matches(grid, p2, arrays):
                for step in chain.steps:
                    step()
                return out
            if chain is not None:
                self.retire(chain.launches)
            self._echo_chain = None
            self._recording = []
            try:
                self._echo_chain_steps(s, x_rel, grid, f, p2)
                self._echo_chain = _EchoChain(grid, p2, arrays, tuple(self._recording))
            finally:
                self._recording = None
        return out

    def _echo_chain_steps(self, s, x_rel: np.ndarray, grid: nlcs.FocusGrid, f: _PassFilters,
                          p2: float) -> None:
        """The echo chain's stages on the echo's range spectrum `s` (uploaded), into the "azimuth" buffer."""
        self.fft(s, 1)
        self.range_walk_correction(s, x_rel, grid)
        s = self.resample_to_uniform_track(s, x_rel, grid, p2)
        self.fft(s, 0)
        origin = self._row_origin(grid, f.first_row)
        band = self.buffer("doppler_rows", grid)
        n_band = band.shape[0]
        self._launch("gather_rows", n_band, grid.n_range, full=s, out=band, filter=f.src,
                     row_origin=origin, n_azimuth=grid.n_azimuth, n_range=grid.n_range)
        self.fft(band, 1, inverse=True)
        self._launch("apply_filter", n_band, grid.n_range, s=band, filter=f.h5h6, n_range=grid.n_range)
        self._launch("scatter_rows", grid.n_azimuth, grid.n_range, band=band, full=s, row_origin=origin,
                     n_rows=n_band, n_azimuth=grid.n_azimuth, n_range=grid.n_range)
        self.fft(s, 0, inverse=True)
        self._launch("apply_filter", grid.n_azimuth, grid.n_range, s=s, filter=f.h7, n_range=grid.n_range)
        self.fft(s, 0)

    def nlcs_model_spectra(self, products: nlcs.NlcsProducts, x_rel_m: np.ndarray, echoes,
                           rows: np.ndarray) -> np.ndarray:
        """Rows of fft2(image) / (n m) for the image each echo would focus to with the products' chain and H8:
        what detection's neighbour cancellation needs (`detect.image_spectrum_rows`), without the last IFFT or
        the image.

        Parameters
        ----------
        products : the pass's NLCS products (grid, coefficients, H8).
        x_rel_m : (n_pulses,) pulse positions relative to the aperture centre (m), increasing.
        echoes : iterable of (n_pulses, n_range) echoes.
        rows : (n_rows,) contiguous signed azimuth frequency indices in [-n_azimuth/2, n_azimuth/2).

        Returns
        -------
        (n_echoes, n_rows, n_range) complex128.
        """
        grid, k, ac = products.grid, products.coefficients, products.compression
        p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
        n = grid.n_azimuth
        lo, hi = int(rows[0]), int(rows[-1])
        if not np.array_equal(rows, np.arange(lo, hi + 1)) or not -n // 2 <= lo <= hi < n // 2:
            raise ValueError("rows must be contiguous signed azimuth indices in [-n/2, n/2)")
        entries = [e for e in self._nlcs_entries(grid, len(x_rel_m)) if e[0] not in ("filter_h8", "h8_rows")]
        entries += [("filter_h8", {"rows": rows.size}), ("model_rows", {"rows": rows.size})]
        self.check_footprint("nlcs_model_spectra", grid, entries)

        h8 = self._h8_table(ac, grid, lo, hi)
        band = self.buffer("model_rows", grid, rows=rows.size)
        reads = []  # every echo is queued before the first result is waited for
        for echo in echoes:
            s = self._nlcs_spectrum(echo, x_rel_m, grid, k, float(p2[0]))
            with self.stage("model spectrum rows"):
                self._launch("gather_rows", rows.size, grid.n_range, full=s, out=band, filter=h8,
                             row_origin=self._row_origin(grid, lo), n_azimuth=grid.n_azimuth,
                             n_range=grid.n_range)
                reads.append(self._range_spectra(band, rows))
        return np.array([nlcs.spectrum_rows_from_range_spectra(r.result(), rows, grid) for r in reads])

    def _range_spectra(self, band, rows: np.ndarray):
        """The range spectra of `rows` (the first rows.size rows of `band`, transformed along range in place),
        their read-back queued (`PendingRead`): `nlcs.spectrum_rows_from_range_spectra` of its result is
        fft2(image) / (n m) on those rows."""
        self.fft(band, 1)
        return self.host_async(band[:rows.size])

    # -------------------------------------------------------------------------------------- backprojection
    def range_compress(self, scan: ScanPass, grid: nlcs.FocusGrid, upsample: int = BP_UPSAMPLE):
        """H4 and band-limited upsampling of every pulse (mirrors `backprojection.range_compress`); the result
        stays on the device, its host copy is returned for sub-cell refinement."""
        echo, x_rel = nlcs.prepare_track(scan, grid)
        n_fine = grid.n_range * upsample
        with self.stage("range compression (BP)"):
            rows = pulse_rows(echo.shape[0])
            s = self.to_device("echo", _with_rows(echo, rows), grid, n_pulses=rows)
            self.fft(s, 1)
            self._measured_pulse_filter(s, grid)
            fine = self.buffer("fine", grid, n_pulses=rows, upsample=upsample)
            self._launch("pulse_compression_upsample", rows, n_fine, spec=s, fine=fine,
                         n_range=grid.n_range, n_fine=n_fine, sample_rate_hz=grid.sample_rate_hz,
                         pulse_sigma_s=self._kernel_pulse_sigma_s(grid))
            self.fft(fine, 1, inverse=True)
            data = self.host(fine[:echo.shape[0]])
        return fine, bp.RangeCompressed(data, x_rel, grid.range_window_start_s,
                                        1.0 / (grid.sample_rate_hz * upsample))

    def backprojection_focus(self, scan: ScanPass, *, pixel_m: float = 0.01,
                             grid: nlcs.FocusGrid | None = None,
                             range_margin_m: float = 0.1,
                             u_extent_m: tuple[float, float] | None = None) -> bp.BackprojectionProducts:
        """BP image on the device (mirrors `backprojection.backprojection_focus`).

        Parameters
        ----------
        scan : the pass.
        pixel_m : pixel size (m) along both image axes.
        grid : the focus grid (default `nlcs.focus_grid(scan)`).
        range_margin_m : image extent beyond the range window (m).
        u_extent_m : the image's u extent (m); default the rail's (`bp.image_axes`).

        Returns
        -------
        BackprojectionProducts: image (n_u, n_r) complex64 on the (u = v t_n, r_LRCM) axes (m), the
        range-compressed pulses."""
        grid = nlcs.focus_grid(scan) if grid is None else grid
        u_axis, r_axis = bp.image_axes(grid, pixel_m, range_margin_m, u_extent_m)
        pulses = {"n_pulses": pulse_rows(scan.n_pulses)}
        self.check_footprint("backprojection_focus", grid, [
            ("echo", pulses), ("pulse_filter", {}), ("fine", {**pulses, "upsample": BP_UPSAMPLE}),
            ("x_rel_f32", {"n_pulses": scan.n_pulses}),
            ("bp_image", {"n_u": u_axis.size, "n_r": r_axis.size})])
        fine, rc = self.range_compress(scan, grid)
        with self.stage("backprojection"):
            image = self.buffer("bp_image", grid, n_u=u_axis.size, n_r=r_axis.size)
            lo, hi = grid.doppler_band
            x_rel = self.to_device("x_rel_f32", rc.x_rel_m, grid, n_pulses=rc.x_rel_m.size)
            self._launch("backproject", u_axis.size, r_axis.size, rc=fine, x_rel_m=x_rel, image=image,
                         n_pulses=rc.data.shape[0], n_fine=rc.data.shape[1], t0_s=rc.t0_s, fine_dt_s=rc.dt_s,
                         n_u=u_axis.size, n_r=r_axis.size, u0_m=float(u_axis[0]), du_m=pixel_m,
                         r_start_m=float(r_axis[0]), dr_m=pixel_m, sin_squint=grid.sin_squint,
                         carrier_hz=grid.carrier_frequency_hz, band_lo=lo, band_hi=hi)
            data = self.host(image)
        return bp.BackprojectionProducts(image=data, u_axis_m=u_axis, r_axis_m=r_axis, grid=grid,
                                         compressed=rc)

    def backproject_track_points(self, rc: bp.RangeCompressed, grid: nlcs.FocusGrid, x_rel_m, rc_m,
                                 counts: bool = False):
        """`backprojection.backproject_track_points` on the device: the BP value of the range-compressed echo
        rc at points along the rail x_rel_m (x - x_c, m) and in closest-approach range rc_m (m), any
        broadcastable shapes (complex128 on the host, summed in complex64 with `backproject`'s split phase);
        with `counts`, also the number of pulses each point sums (int64). What the rib registration (eq. R1)
        backprojects for every candidate translation."""
        shape = np.broadcast_shapes(np.shape(x_rel_m), np.shape(rc_m))
        x, r = (np.asarray(a, dtype=float).ravel() for a in np.broadcast_arrays(x_rel_m, rc_m))
        n_pulses, n_fine = rc.data.shape
        n_points = _round_up(max(x.size, 1), POINT_STEP)
        pulses, points = {"n_pulses": n_pulses}, {"n_points": n_points}
        self.check_footprint("backproject_track_points", grid, [
            ("points_echo", {**pulses, "n_fine": n_fine}), ("points_x_pulse", pulses),
            *((name, points) for name in ("points_x", "points_rc", "points_value", "points_count"))])
        with self.stage("backprojection at points"):
            value = self.buffer("points_value", grid, **points)
            count = self.buffer("points_count", grid, **points)
            self._launch("backproject_track_points", 1, n_points,
                         rc=self.to_device("points_echo", rc.data, grid, **pulses, n_fine=n_fine),
                         x_rel_m=self.to_device("points_x_pulse", rc.x_rel_m, grid, **pulses),
                         x_m=self.reals("points_x", _with_rows(x, n_points), grid, **points),
                         rc_m=self.reals("points_rc", _with_rows(r, n_points), grid, **points),
                         out=value, counts=count, n_points=x.size, n_pulses=n_pulses, n_fine=n_fine,
                         t0_s=rc.t0_s, fine_dt_s=rc.dt_s, carrier_hz=grid.carrier_frequency_hz,
                         band_lo=grid.doppler_band[0], band_hi=grid.doppler_band[1])
            out = self.host(value[:x.size]).astype(np.complex128).reshape(shape)
            if counts:
                return out, self.host(count[:x.size]).astype(np.int64).reshape(shape)
        return out


@dataclasses.dataclass(frozen=True, eq=False)
class _EchoChain:
    """The recorded launches and FFTs of one echo chain, valid while its grid, p2 and device arrays are the
    same objects (a buffer dropped and made again is a new array: the chain is recorded again). Holding the
    arrays keeps them allocated while their launches may run."""

    grid: nlcs.FocusGrid
    p2: float
    arrays: tuple
    steps: tuple

    @property
    def launches(self) -> list:
        return [step.args[0] for step in self.steps if isinstance(step.args[0], PreparedLaunch)]

    def matches(self, grid: nlcs.FocusGrid, p2: float, arrays: tuple) -> bool:
        return (p2 == self.p2 and (grid is self.grid or grid == self.grid) and len(arrays) == len(self.arrays)
                and all(a is b for a, b in zip(arrays, self.arrays)))


@dataclasses.dataclass(frozen=True, eq=False)
class _PassFilters:
    grid: nlcs.FocusGrid
    first_row: int  # signed azimuth index of row 0 of `src` and `h5h6`
    src: object  # H3 * mask * H4 * delay origin, (band rows, n_range)
    h5h6: object  # (band rows, n_range)
    h7: object  # (n_azimuth, n_range), FFT order


@functools.lru_cache(maxsize=16)  # per grid (frozen, hashable); the buffer table asks for it on every use
def _doppler_band_rows(grid: nlcs.FocusGrid) -> tuple[int, int]:
    """(first signed azimuth index, count) of a run of rows that holds every row where the band mask of
    eqs. (9-10) passes anything. X = sin(theta_q) + c f_a / (2 v F) is monotonic in f_a at each F = f_c + f_r,
    so each range frequency passes the carrier's band (`nlcs.doppler_band_hz`) scaled by F / f_c; their hull,
    one row wider on each side, is taken (the SRC table applies the exact mask inside it)."""
    f_lo, f_hi = nlcs.doppler_band_hz(grid)
    if f_lo > f_hi:
        return 0, 1
    scale = ((grid.carrier_frequency_hz + grid.f_range_hz) / grid.carrier_frequency_hz
             * (grid.n_azimuth * grid.dt_s))
    first = int(np.floor((f_lo * scale).min())) - 1
    last = int(np.ceil((f_hi * scale).max())) + 1
    first, last = max(first, -(grid.n_azimuth // 2)), min(last, grid.n_azimuth // 2 - 1)
    return first, last - first + 1


def undecided_band_edges(mag: np.ndarray, grid: nlcs.FocusGrid, margin: float) -> np.ndarray:
    """Bins (columns of |X_ref|) whose H8 segment ends, as `nlcs.fit_azimuth_compression` picks them, could
    move if every magnitude moved by up to `margin` times the bin's peak."""

    peak = mag.max(axis=0)
    threshold = nlcs.STRONG_REFERENCE_FRACTION * peak
    f_lo, f_hi = nlcs.doppler_band_hz(grid)
    f = grid.f_azimuth_hz[:, None]
    window = (f >= f_lo) & (f <= f_hi)
    surely = window & (mag > threshold + margin * peak)
    maybe = window & (mag > threshold - margin * peak)

    def ends(strong):
        first = np.argmax(strong, axis=0)
        last = strong.shape[0] - 1 - np.argmax(strong[::-1], axis=0)
        return np.where(strong.any(axis=0), first, -1), np.where(strong.any(axis=0), last, -1)

    (a0, a1), (b0, b1) = ends(surely), ends(maybe)
    return (a0 != b0) | (a1 != b1)


_ENGINES: dict = {}


def shared_engine(device: str | None = None, *, profile: bool | None = None) -> FocusEngine:
    """One engine per device spec and process: programs, plans and buffers survive across passes.
    `profile` True/False replaces the process's engine by one with/without profiling if it differs; None
    takes the engine as it is (a new one without profiling if there is none)."""
    key = device or ""
    engine = _ENGINES.get(key)
    if engine is None or (profile is not None and engine.profiling != profile):
        engine = _ENGINES[key] = FocusEngine(device, profile=bool(profile))
    return engine


def warm_start_s(engine: FocusEngine) -> float:
    """Time to build a second engine on the same device (kernel binaries come from the runtime's cache)."""
    t = time.perf_counter()
    FocusEngine(engine.device, fp64_phase=engine.fp64_phase)
    return time.perf_counter() - t

