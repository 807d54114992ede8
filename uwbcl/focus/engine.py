"""The OpenCL focusing engine: the NLCS chain and backprojection of `nlcs.py` / `backprojection.py` on a device.

One `FocusEngine` owns the context, the queue, the compiled program, the FFT plans and the device buffers, and is
reused across passes (buffers and plans are kept per shape, so a batch of same-sized passes allocates once).
Coefficients are computed on the host (`coefficients.py`, a few scalars per range bin); every phase function is
evaluated in the kernels from them (`kernels/*.cl`). Data are complex64 on the device; phase arguments are
evaluated in float64 where the device has fp64 (docs/opencl.md, error budget). With fp64, the reference spectra of
the exact-reference H8 are computed in complex128 by a second build of azimuth.cl (their band edges come from a
hard magnitude threshold that float32 rounding can flip). FFTs are VkFFT through pyvkfft.

Azimuth arrays live on the device in FFT (natural) order; the numpy reference keeps them centred. The engine
converts at the edges only (writing the resampled track in natural order, fftshift of the read-back image).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from .. import opencl
from ..model import ScanPass
from . import backprojection as bp
from . import coefficients as coef
from . import nlcs

PROGRAM_FILES = ("common.cl", "range.cl", "azimuth.cl", "fft.cl", "backprojection.cl")
# |X_ref| closer than this fraction of its bin's peak to the H8 fit's threshold counts as undecided in
# complex64 (measured complex64 error on PoCL: 3e-7 of the peak); such bins are recomputed in float64.
REFERENCE_EDGE_MARGIN = 3e-6


class FocusEngine:
    """OpenCL implementation of the focusing stages; `nlcs_focus` and `backprojection_focus` return the same
    products as the numpy functions of the same names."""

    def __init__(self, device=None, *, fp64_phase: bool | None = None):
        import pyopencl as cl

        try:
            from pyvkfft.opencl import VkFFTApp
        except ImportError as exc:
            raise opencl.OpenClUnavailable(f"pyvkfft is not importable ({exc}); " + opencl.FFT_HINT) from exc
        import pyopencl.array as cla

        self._cl = cl
        self._cl_array = cla
        self._vkfft_app = VkFFTApp
        t0 = time.perf_counter()
        dev = device if isinstance(device, cl.Device) else opencl.select_device(device)
        self.device = dev
        self.context = cl.Context([dev])
        self.queue = cl.CommandQueue(self.context)
        has_fp64 = bool(dev.double_fp_config)
        if fp64_phase and not has_fp64:
            raise opencl.OpenClUnavailable(f"{dev.name.strip()} has no fp64; use fp64_phase=False")
        self.fp64_phase = has_fp64 if fp64_phase is None else fp64_phase
        self.real = np.float64 if self.fp64_phase else np.float32
        options = ["-DUWBCL_FP64"] if self.fp64_phase else []
        source = opencl.kernel_source(*PROGRAM_FILES)
        self.program = cl.Program(self.context, source).build(options=options)
        self.kernels = {k.function_name: k for k in self.program.all_kernels()}  # fetched once
        self._plans: dict = {}
        self._buffers: dict = {}
        self._twiddles: dict = {}
        self._fft_launches: dict = {}  # (buffer, scratch, shape, inverse) -> [(kernel with its arguments, size)]
        self._uploaded: dict = {}  # (name, shape, dtype) -> bytes of the last small upload
        self._filters: _PassFilters | None = None  # the last grid's filter tables
        self._h8_tables: dict = {}  # name -> (compression, grid, (first, last row), table)
        self._in_flight: list = []  # host arrays of uploads not yet known to be complete
        failure = self._fft_self_test_failure(np.complex64, 1e-5, axes=(0, 1))
        if failure:
            raise opencl.OpenClUnavailable(f"{failure}; this OpenCL runtime miscompiles it, use --backend numpy")
        self.startup_s = time.perf_counter() - t0

    # ------------------------------------------------------------------------------------------ plumbing
    def __repr__(self) -> str:
        return f"FocusEngine({self.device.name.strip()!r}, fp64_phase={self.fp64_phase})"

    # shapes kept per buffer name: a batch alternates between a few pass shapes (rigs with other rails)
    SHAPES_PER_BUFFER = 3

    def buffer(self, name: str, shape: tuple[int, ...], dtype=np.complex64):
        """A device array kept between passes, one per name and shape (the name's least recently used shape is
        released beyond SHAPES_PER_BUFFER)."""
        key = (name, tuple(shape), np.dtype(dtype))
        arr = self._buffers.pop(key, None)
        if arr is None:
            same_name = [k for k in self._buffers if k[0] == name]
            for old in same_name[:max(0, len(same_name) - self.SHAPES_PER_BUFFER + 1)]:
                del self._buffers[old]
                self._uploaded.pop(old, None)
            arr = self._cl_array.empty(self.queue, shape, dtype)
        self._buffers[key] = arr  # most recently used last
        return arr

    def to_device(self, name: str, host: np.ndarray, dtype=None, *, constant: bool = False):
        """Upload into the named buffer without waiting for the device: the host copy is kept alive until the
        next read-back (`host`), which on the in-order queue means the copy is done. A `constant` buffer (one
        no kernel writes: coefficients, positions, indices) is not uploaded again while its bytes are
        unchanged (they repeat for every model echo of a pass)."""
        host = np.array(host, dtype=dtype or host.dtype, order="C")  # a private copy: the caller may reuse its own
        arr = self.buffer(name, host.shape, host.dtype)
        key = (name, host.shape, host.dtype)
        data = host.tobytes() if constant else None
        if constant and self._uploaded.get(key) == data:
            return arr
        arr.set(host, async_=True)
        self._in_flight.append(host)
        self._uploaded[key] = data
        return arr

    def host(self, arr) -> np.ndarray:
        """Blocking read-back; every upload queued before it has completed afterwards."""
        out = arr.get()
        self._in_flight.clear()
        return out

    def reals(self, name: str, values) -> object:
        """Per-bin coefficients (or positions) in the phase precision."""
        return self.to_device(name, np.asarray(values, dtype=float), self.real, constant=True)

    def fft(self, arr, axis: int, inverse: bool = False) -> None:
        """In-place complex FFT along one axis (complex64 or complex128); the inverse is normalised by 1/N like
        numpy. Power-of-two complex64 azimuth (axis 0) transforms of 2-D arrays with a multiple of 4 columns use
        our Stockham kernels (fft.cl), the rest VkFFT."""
        if (axis == 0 and arr.ndim == 2 and arr.dtype == np.complex64 and _is_power_of_two(arr.shape[0])
                and arr.shape[1] % 4 == 0):
            self.azimuth_fft(arr, inverse)
            return
        key = (arr.shape, axis, arr.dtype)
        app = self._plans.get(key)
        if app is None:
            app = self._plans[key] = self._vkfft_app(arr.shape, arr.dtype, self.queue, ndim=1, axes=(axis,),
                                                     inplace=True, norm=1)
        (app.ifft if inverse else app.fft)(arr, arr)

    def azimuth_fft(self, arr, inverse: bool = False) -> None:
        """Stockham FFT along axis 0 (fft.cl), radix 8/4/2 passes ping-ponging through a scratch buffer; the
        pass count is kept even so the result lands back in `arr`. The passes' kernels are kept with their
        arguments set, per buffer, so a transform costs its launches only (a pass takes ~0.4 ms on a CPU; setting
        nine arguments from Python costs a noticeable part of that)."""
        scratch = self.buffer("fft_scratch", arr.shape, arr.dtype)
        key = (arr.data.int_ptr, scratch.data.int_ptr, arr.shape, bool(inverse))
        launches = self._fft_launches.get(key)
        if launches is None:
            if len(self._fft_launches) >= 64:  # buffers of passes long gone: bound what is kept
                self._fft_launches.clear()
            launches = self._fft_launches[key] = self._azimuth_fft_launches(arr, scratch, inverse)
        for kernel, size in launches:
            self._cl.enqueue_nd_range_kernel(self.queue, kernel, size, None)
        if len(launches) % 2:  # an odd number of passes (n = 2 or 4)
            self._cl.enqueue_copy(self.queue, arr.data, scratch.data)

    def _azimuth_fft_launches(self, arr, scratch, inverse: bool) -> list:
        n, n_cols = arr.shape
        twiddle = self._twiddles.get((n, arr.dtype))
        if twiddle is None:
            table = np.exp(-2j * np.pi * np.arange(n) / n).astype(arr.dtype)
            twiddle = self._twiddles[(n, arr.dtype)] = self._cl_array.to_device(self.queue, table)
        radices = _radix_plan(n)
        launches, src, dst, ns = [], arr, scratch, 1
        for i, radix in enumerate(radices):
            kernel = self._cl.Kernel(self.program, f"azimuth_fft_radix{radix}")
            scale = 1.0 / n if inverse and i == len(radices) - 1 else 1.0
            kernel.set_args(src.data, dst.data, twiddle.data, np.int32(n), np.int32(n_cols), np.int32(ns),
                            np.int32(inverse), np.float32(scale))
            launches.append((kernel, (n_cols // 4, n // radix)))
            ns *= radix
            src, dst = dst, src
        return launches

    # kernels whose work item handles four neighbouring range bins (common.cl, c4)
    FOUR_BIN_KERNELS = frozenset({"nlcs_filter", "nlcs_scaling", "point_response", "range_walk_correction"})

    def _run(self, name: str, rows: int, cols: int, *args) -> None:
        """Launch kernel `name` on a (cols, rows) grid (cols / 4 work items across for the four-bin kernels);
        Python ints become int32, floats the phase precision."""
        conv = []
        for a in args:
            if isinstance(a, bool):
                raise TypeError("boolean kernel argument")
            if isinstance(a, (int, np.integer)):
                conv.append(np.int32(a))
            elif isinstance(a, (float, np.floating)):
                conv.append(self.real(a))
            else:
                conv.append(a.data if hasattr(a, "data") and not isinstance(a, np.ndarray) else a)
        if name in self.FOUR_BIN_KERNELS:
            cols = -(-cols // 4)
        self.kernels[name](self.queue, (cols, rows), None, *conv)

    def _fft_self_test_failure(self, dtype, tol: float, axes: tuple[int, ...]) -> str:
        """VkFFT is miscompiled by some OpenCL runtimes (e.g. PoCL 7.0-7.1): check it and our own azimuth FFT
        once against numpy.
        Returns what failed, or "" when the forward and inverse transforms agree to `tol`."""
        rng = np.random.default_rng(0)
        x = (rng.standard_normal((64, 48)) + 1j * rng.standard_normal((64, 48))).astype(dtype)
        failure = ""
        for axis in axes:
            d = self.to_device("selftest", x)
            self.fft(d, axis)
            ref = np.fft.fft(x.astype(np.complex128), axis=axis)
            err = np.linalg.norm(self.host(d) - ref) / np.linalg.norm(ref)
            self.fft(d, axis, inverse=True)
            err_inv = np.linalg.norm(self.host(d) - x) / np.linalg.norm(x)
            if not (err < tol and err_inv < tol):
                which = "the Stockham azimuth FFT (fft.cl)" if axis == 0 else "VkFFT"
                failure = (f"{which} {np.dtype(dtype).name} self-test failed on {self.device.name.strip()} "
                           f"(axis {axis}: relative error {err:.1e}/{err_inv:.1e})")
                break
        self._plans.clear()
        self._buffers = {k: v for k, v in self._buffers.items() if k[0] != "selftest"}
        return failure

    # ------------------------------------------------------------------------------------------ NLCS stages
    def range_walk_correction(self, s, x_rel_m: np.ndarray, grid: nlcs.FocusGrid) -> None:
        """range FFT delay origin (eq. 3) and H1 (eq. 4) in place on a range spectrum (pulses, n_range)."""
        self._run("range_walk_correction", s.shape[0], s.shape[1], s, self.reals("x_rel", x_rel_m), grid.n_range,
                  grid.sample_rate_hz, grid.range_window_start_s, grid.carrier_frequency_hz, grid.sin_squint)

    def resample_to_uniform_track(self, s, x_rel_m: np.ndarray, grid: nlcs.FocusGrid, p2_m_s2: float = 0.0):
        """Lagrange resampling onto the uniform track, ENLCS H2, padding: -> (n_azimuth, n_range), FFT order."""
        idx, w = nlcs.lagrange_weights(x_rel_m, grid.t_track_s * grid.speed_m_s)
        out = self.buffer("azimuth", (grid.n_azimuth, grid.n_range))
        self._run("resample_to_uniform_track", grid.n_azimuth, grid.n_range, s, out,
                  self.to_device("first", idx[:, 0].astype(np.int32), constant=True), self.reals("weights", w), w.shape[1],
                  grid.n_track, grid.n_azimuth, grid.n_range, grid.sample_rate_hz, grid.carrier_frequency_hz,
                  grid.dt_s, float(p2_m_s2))
        return out

    @staticmethod
    def _row_origin(grid: nlcs.FocusGrid, first_row: int | None) -> int:
        """FFT-order position of row 0 of an array of azimuth rows starting at signed index first_row (None: a
        whole spectrum in FFT order)."""
        return 0 if first_row is None else int(first_row) % grid.n_azimuth

    def secondary_range_compression(self, s, grid: nlcs.FocusGrid, first_row: int | None = None) -> None:
        """H3 * band mask * H4 and the range IFFT's delay origin (eqs. 9-11), in place on the 2-D spectrum (or on
        its rows from signed azimuth index first_row on)."""
        lo, hi = grid.doppler_band
        self._run("secondary_range_compression", s.shape[0], grid.n_range, s, grid.n_range, grid.n_azimuth,
                  grid.sample_rate_hz, grid.range_window_start_s, grid.carrier_frequency_hz,
                  1.0 / (grid.n_azimuth * grid.dt_s), grid.speed_m_s, grid.sin_squint, grid.reference_range_m,
                  grid.pulse_sigma_s, lo, hi, self._row_origin(grid, first_row))

    def nlcs_filter(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, *, with_h5: bool = True,
                    first_row: int | None = None) -> None:
        """H5 (eq. 13) and H6 (eq. 15) in place on a range-Doppler array (or band of rows)."""
        eta1 = k.eta1 if with_h5 else np.zeros_like(k.eta1)
        self._run("nlcs_filter", s.shape[0], grid.n_range, s, self.reals("eta1", eta1),
                  self.reals("y3", k.y3), self.reals("y4", k.y4), grid.n_range, grid.n_azimuth,
                  1.0 / (grid.n_azimuth * grid.dt_s), self._row_origin(grid, first_row))

    def nlcs_scaling(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid) -> None:
        """H7 (eq. 15) in place on a range-time array."""
        self._run("nlcs_scaling", grid.n_azimuth, grid.n_range, s, self.reals("q2", k.q2), self.reals("q3", k.q3),
                  self.reals("q4", k.q4), grid.n_range, grid.n_azimuth, grid.dt_s)

    def azimuth_compression(self, s, ac: nlcs.AzimuthCompression, grid: nlcs.FocusGrid,
                            first_row: int | None = None) -> None:
        """H8 (eq. 17; C10, C11) in place on a range-Doppler array (or band of rows)."""
        # the reference's own test f_lo <= f <= f_hi on the (increasing) centred axis, as index bounds
        f = grid.f_azimuth_hz
        first = np.searchsorted(f, ac.f_lo_hz, side="left") - grid.n_azimuth // 2
        last = np.searchsorted(f, ac.f_hi_hz, side="right") - 1 - grid.n_azimuth // 2  # first > last: empty
        self._run("azimuth_compression", s.shape[0], grid.n_range, s, self.reals("ac_poly", ac.poly),
                  ac.poly.shape[1], self.to_device("ac_first", first.astype(np.int32), constant=True),
                  self.to_device("ac_last", last.astype(np.int32), constant=True),
                  grid.n_range, grid.n_azimuth, 1.0 / (grid.n_azimuth * grid.dt_s), ac.f_scale_hz,
                  self._row_origin(grid, first_row))

    def azimuth_nlcs_chain(self, s, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, *, with_h5: bool) -> None:
        """H5/H6 -> azimuth IFFT -> H7 -> azimuth FFT, in place on a range-Doppler array."""
        self.nlcs_filter(s, k, grid, with_h5=with_h5)
        self.fft(s, 0, inverse=True)
        self.nlcs_scaling(s, k, grid)
        self.fft(s, 0)

    def exact_reference_azimuth_compression(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                                            aperture_m: float, degree: int = 8) -> nlcs.AzimuthCompression:
        """As `nlcs.exact_reference_azimuth_compression`, with the reference spectra computed on the device."""
        return nlcs.fit_azimuth_compression(self.reference_spectra(k, grid, aperture_m), k, grid, degree)

    def reference_spectra(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float) -> np.ndarray:
        """X_ref of every bin after H6/H7 (centred f_a, complex128), computed in complex64 on the device.

        The fit picks each bin's segment and band with a hard threshold on |X_ref|, which float32 rounding can
        move by one sample (an image error of 2e-3): the few bins with a band edge within rounding of the
        threshold are recomputed on the host in float64, so the fit decides exactly as the reference does."""
        return self._reference_spectra_result(self._enqueue_reference_spectra(k, grid, aperture_m), k, grid,
                                              aperture_m)

    def _enqueue_reference_spectra(self, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid, aperture_m: float):
        """Queue the device part of `reference_spectra` and its read-back; returns (host array, read event)."""
        ref = self.point_response(k.r_m, np.zeros(grid.n_range), grid, aperture_m, "reference")
        self.fft(ref, 0)
        self.nlcs_filter(ref, k, grid, with_h5=False)
        self.fft(ref, 0, inverse=True)
        self._run("apply_filter", grid.n_azimuth, grid.n_range, ref, self._pass_filters(grid, k).h7, grid.n_range)
        self.fft(ref, 0)
        host = np.empty(ref.shape, ref.dtype)
        return host, self._cl.enqueue_copy(self.queue, host, ref.data, is_blocking=False)

    def _reference_spectra_result(self, pending, k: coef.NlcsCoefficients, grid: nlcs.FocusGrid,
                                  aperture_m: float) -> np.ndarray:
        host, read = pending
        read.wait()
        x_ref = np.fft.fftshift(host, axes=0).astype(np.complex128)
        undecided = np.flatnonzero(undecided_band_edges(np.abs(x_ref), grid, REFERENCE_EDGE_MARGIN))
        if undecided.size:
            x_ref[:, undecided] = nlcs.reference_spectra(nlcs.select_bins(k, undecided), grid, aperture_m)
        return x_ref

    def point_response(self, r_m: np.ndarray, t_n_s: np.ndarray, grid: nlcs.FocusGrid, aperture_m: float,
                       name: str, rail_only: bool = False):
        """`nlcs.slow_time_point_response` on the device, one (r, t_n) per column, FFT order; a buffer `name`."""
        out = self.buffer(name, (grid.n_azimuth, r_m.size))
        half_track = 0.5 * (grid.n_track - 1) * grid.dt_s if rail_only else -1.0
        self._run("point_response", grid.n_azimuth, r_m.size, out, self.reals(f"{name}_r", r_m),
                  self.reals(f"{name}_t_n", t_n_s), r_m.size, grid.n_azimuth, grid.dt_s, grid.speed_m_s,
                  grid.sin_squint, grid.wavelength_m, aperture_m, half_track)
        return out

    def calibration_spectra(self, products: nlcs.NlcsProducts, r_m: np.ndarray, t_n_s: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`detect.calibration_spectra` on the device: simulated targets at every (r, t_n) (columns r-major)
        through the azimuth chain of the bin nearest each r -> (f on H8's rows, y there, coarse t_f)."""
        grid = products.grid
        r_cols = np.repeat(np.asarray(r_m, dtype=float), t_n_s.size)
        t_cols = np.tile(np.asarray(t_n_s, dtype=float), np.size(r_m))
        # the azimuth FFT kernels take columns four at a time; widths in steps of 16 recur from pass to pass, so
        # the buffer and its FFT launches are reused
        width = -(-r_cols.size // 16) * 16
        r_cols = np.concatenate([r_cols, np.repeat(r_cols[-1:], width - r_cols.size)])
        t_cols = np.concatenate([t_cols, np.repeat(t_cols[-1:], width - t_cols.size)])
        j = grid.nearest_bin(r_cols)
        k = nlcs.select_bins(products.coefficients, j)
        ac = nlcs.select_bins(products.compression, j)
        columns = dataclasses.replace(grid, n_range=width)  # the kernels index per-column coefficients
        s = self.point_response(r_cols, t_cols, grid, products.aperture_m, "calibration", rail_only=True)
        self.fft(s, 0)
        self.azimuth_nlcs_chain(s, k, columns, with_h5=False)
        self.azimuth_compression(s, ac, columns)
        f = np.fft.ifftshift(grid.f_azimuth_hz)
        band = (f >= ac.f_lo_hz.min()) & (f <= ac.f_hi_hz.max())
        y = self.host(s).astype(np.complex128)[band]
        self.fft(s, 0, inverse=True)
        coarse = np.fft.ifftshift(grid.t_azimuth_s)[np.argmax(np.abs(self.host(s)), axis=0)]
        n = np.size(r_m) * t_n_s.size
        return f[band], y[:, :n], coarse[:n]

    def nlcs_focus(self, scan: ScanPass, *, ac_mode: str = "exact", grid: nlcs.FocusGrid | None = None,
                   compression: nlcs.AzimuthCompression | None = None) -> nlcs.NlcsProducts:
        """Focus one pass with the modified NLCS chain on the device (mirrors `nlcs.nlcs_focus`)."""
        if ac_mode not in ("exact", "series"):
            raise ValueError(f"unknown azimuth compression mode {ac_mode!r} (exact|series)")
        grid = nlcs.focus_grid(scan) if grid is None else grid
        echo, x_rel = nlcs.prepare_track(scan, grid)
        k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
        p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
        if np.ptp(p2) > 0:
            raise NotImplementedError("the engine applies H2 with one p2 per pass; p2 varies across range here")
        aperture = scan.radar.antenna_aperture_m
        ac = compression or (nlcs.series_azimuth_compression(k, grid) if ac_mode == "series" else None)
        pending = self._enqueue_reference_spectra(k, grid, aperture) if ac is None else None
        # queued behind the reference spectra: the device runs the chain while the host fits H8 to them
        s = self._nlcs_spectrum(echo, x_rel, grid, k, float(p2[0]))
        if ac is None:
            ac = nlcs.fit_azimuth_compression(self._reference_spectra_result(pending, k, grid, aperture), k, grid)
        # H8 on the rows that hold the image's spectrum (zero elsewhere); those rows are also read back, so
        # detection needs no 2-D FFT of the image
        rows = nlcs.spectrum_rows(grid, ac)
        band = self._rows_buffer("h8_rows", rows.size, grid)
        origin = self._row_origin(grid, rows[0])
        self._run("gather_rows", rows.size, grid.n_range, s, band,
                  self._h8_table(ac, grid, int(rows[0]), int(rows[-1]), "h8"), origin, grid.n_azimuth, grid.n_range)
        self._run("scatter_rows", grid.n_azimuth, grid.n_range, band, s, origin, rows.size, grid.n_azimuth,
                  grid.n_range)
        spectrum = self._range_spectra(band, rows, grid)
        self.fft(s, 0, inverse=True)
        image = np.fft.fftshift(self.host(s), axes=0)
        return nlcs.NlcsProducts(image=image, grid=grid, coefficients=k, compression=ac, aperture_m=aperture,
                                 spectrum=spectrum)

    def _pass_filters(self, grid: nlcs.FocusGrid, k: coef.NlcsCoefficients) -> _PassFilters:
        """The grid-only filters of the chain as device tables, made once per grid by the stage kernels (from
        their scalars, applied to ones) and then applied to every echo of the pass: the image's and detection's
        neighbour models'. SRC and H5/H6 live on the Doppler band's rows only (the band mask zeroes the rest),
        padded to a multiple of 128 rows so the band's range IFFT plan is reused across passes."""
        if self._filters is not None and self._filters.grid == grid:
            return self._filters
        first, count = _doppler_band_rows(grid)
        count = min(-(-count // 128) * 128, grid.n_azimuth)
        src = self.buffer("filter_src", (count, grid.n_range))
        src.fill(1)
        self.secondary_range_compression(src, grid, first)
        h5h6 = self.buffer("filter_h5h6", (count, grid.n_range))
        h5h6.fill(1)
        self.nlcs_filter(h5h6, k, grid, with_h5=True, first_row=first)
        h7 = self.buffer("filter_h7", (grid.n_azimuth, grid.n_range))
        h7.fill(1)
        self.nlcs_scaling(h7, k, grid)
        self._filters = _PassFilters(grid, first, src, h5h6, h7)
        return self._filters

    def _h8_table(self, ac: nlcs.AzimuthCompression, grid: nlcs.FocusGrid, lo: int, hi: int, name: str):
        """H8 on the signed azimuth rows lo..hi as a device table (zero outside each bin's band), kept under
        `name` while the compression and rows stay the same."""
        cached = self._h8_tables.get(name)
        if cached is not None and cached[0] is ac and cached[1:3] == (grid, (lo, hi)):
            return cached[3]
        table = self.buffer(f"filter_{name}", (hi - lo + 1, grid.n_range))
        table.fill(1)
        self.azimuth_compression(table, ac, grid, first_row=lo)
        self._h8_tables[name] = (ac, grid, (lo, hi), table)
        return table

    def _nlcs_spectrum(self, echo: np.ndarray, x_rel: np.ndarray, grid: nlcs.FocusGrid, k: coef.NlcsCoefficients,
                       p2: float):
        """echo -> the range-Doppler array before H8 (device, whole spectrum in FFT order)."""
        f = self._pass_filters(grid, k)
        s = self.to_device("echo", echo, np.complex64)
        self.fft(s, 1)
        self.range_walk_correction(s, x_rel, grid)
        s = self.resample_to_uniform_track(s, x_rel, grid, p2)
        self.fft(s, 0)
        origin = self._row_origin(grid, f.first_row)
        band = self.buffer("doppler_rows", f.src.shape)
        self._run("gather_rows", band.shape[0], grid.n_range, s, band, f.src, origin, grid.n_azimuth, grid.n_range)
        self.fft(band, 1, inverse=True)
        self._run("apply_filter", band.shape[0], grid.n_range, band, f.h5h6, grid.n_range)
        self._run("scatter_rows", grid.n_azimuth, grid.n_range, band, s, origin, band.shape[0], grid.n_azimuth,
                  grid.n_range)
        self.fft(s, 0, inverse=True)
        self._run("apply_filter", grid.n_azimuth, grid.n_range, s, f.h7, grid.n_range)
        self.fft(s, 0)
        return s

    def nlcs_model_spectra(self, products: nlcs.NlcsProducts, x_rel_m: np.ndarray, echoes,
                           rows: np.ndarray) -> np.ndarray:
        """Rows `rows` (signed azimuth frequency indices, contiguous) of fft2(image) / (n m) for the image each
        echo (pulses at x_rel_m, increasing) would focus to with the products' chain and H8: what detection's
        neighbour cancellation needs (`detect.image_spectrum_rows`), without the last IFFT or the image."""
        grid, k, ac = products.grid, products.coefficients, products.compression
        p2 = coef.enlcs_coefficient(grid.range_bins_m, grid.speed_m_s, grid.sin_squint)
        n = grid.n_azimuth
        lo, hi = int(rows[0]), int(rows[-1])
        if not np.array_equal(rows, np.arange(lo, hi + 1)) or not -n // 2 <= lo <= hi < n // 2:
            raise ValueError("rows must be contiguous signed azimuth indices in [-n/2, n/2)")
        h8 = self._h8_table(ac, grid, lo, hi, "h8")
        band = self._rows_buffer("model_rows", rows.size, grid)
        out = []
        for echo in echoes:
            s = self._nlcs_spectrum(echo, x_rel_m, grid, k, float(p2[0]))
            self._run("gather_rows", rows.size, grid.n_range, s, band, h8, self._row_origin(grid, lo),
                      grid.n_azimuth, grid.n_range)
            out.append(self._range_spectra(band, rows, grid))
        return np.array(out)

    def _rows_buffer(self, name: str, n_rows: int, grid: nlcs.FocusGrid):
        """A buffer for a band of azimuth rows, its row count rounded up to a multiple of 128 so that the range
        FFT plans of `_range_spectra` are reused across passes (the band's width varies a little)."""
        return self.buffer(name, (min(-(-n_rows // 128) * 128, grid.n_azimuth), grid.n_range))

    def _range_spectra(self, band, rows: np.ndarray, grid: nlcs.FocusGrid) -> np.ndarray:
        """fft2(image) / (n m) on `rows` from their range-Doppler values (the first rows.size rows of `band`,
        transformed along range in place)."""
        self.fft(band, 1)
        return nlcs.spectrum_rows_from_range_spectra(self.host(band[:rows.size]), rows, grid)

    # ------------------------------------------------------------------------------------------ backprojection
    def range_compress(self, scan: ScanPass, grid: nlcs.FocusGrid, upsample: int = 16):
        """H4 and band-limited upsampling of every pulse (mirrors `backprojection.range_compress`); the result
        stays on the device, its host copy is returned for sub-cell refinement."""
        echo, x_rel = nlcs.prepare_track(scan, grid)
        n_fine = grid.n_range * upsample
        s = self.to_device("echo", echo, np.complex64)
        self.fft(s, 1)
        fine = self.buffer("fine", (echo.shape[0], n_fine))
        self._run("pulse_compression_upsample", echo.shape[0], n_fine, s, fine, grid.n_range, n_fine,
                  grid.sample_rate_hz, grid.pulse_sigma_s)
        self.fft(fine, 1, inverse=True)
        return fine, bp.RangeCompressed(self.host(fine), x_rel, grid.range_window_start_s,
                                        1.0 / (grid.sample_rate_hz * upsample))

    def backprojection_focus(self, scan: ScanPass, *, pixel_m: float = 0.01, grid: nlcs.FocusGrid | None = None,
                             range_margin_m: float = 0.1) -> bp.BackprojectionProducts:
        """BP image on the device (mirrors `backprojection.backprojection_focus`)."""
        grid = nlcs.focus_grid(scan) if grid is None else grid
        fine, rc = self.range_compress(scan, grid)
        u_axis, r_axis = bp.image_axes(grid, pixel_m, range_margin_m)
        image = self.buffer("bp_image", (u_axis.size, r_axis.size))
        lo, hi = grid.doppler_band
        x_rel = self.to_device("x_rel_f32", rc.x_rel_m, np.float32, constant=True)
        self._run("backproject", u_axis.size, r_axis.size, fine, x_rel, image,
                  rc.data.shape[0], rc.data.shape[1], rc.t0_s, rc.dt_s, u_axis.size, r_axis.size,
                  float(u_axis[0]), pixel_m, float(r_axis[0]), pixel_m, grid.sin_squint,
                  grid.carrier_frequency_hz, lo, hi)
        return bp.BackprojectionProducts(image=self.host(image), u_axis_m=u_axis, r_axis_m=r_axis, grid=grid,
                                         compressed=rc)


@dataclasses.dataclass(frozen=True, eq=False)
class _PassFilters:
    grid: nlcs.FocusGrid
    first_row: int  # signed azimuth index of row 0 of `src` and `h5h6`
    src: object  # H3 * mask * H4 * delay origin, (band rows, n_range)
    h5h6: object  # (band rows, n_range)
    h7: object  # (n_azimuth, n_range), FFT order


def _doppler_band_rows(grid: nlcs.FocusGrid) -> tuple[int, int]:
    """(first signed azimuth index, count) of a run of rows that holds every row where the band mask of
    eqs. (9-10) passes anything. X = sin(theta_q) + c f_a / (2 v F) is monotonic in f_a at each F = f_c + f_r,
    so each range frequency passes the carrier's band (`nlcs.doppler_band_hz`) scaled by F / f_c; their hull,
    one row wider on each side, is taken (the SRC table applies the exact mask inside it)."""
    f_lo, f_hi = nlcs.doppler_band_hz(grid)
    if f_lo > f_hi:
        return 0, 1
    scale = (grid.carrier_frequency_hz + grid.f_range_hz) / grid.carrier_frequency_hz * (grid.n_azimuth * grid.dt_s)
    first = int(np.floor((f_lo * scale).min())) - 1
    last = int(np.ceil((f_hi * scale).max())) + 1
    first, last = max(first, -(grid.n_azimuth // 2)), min(last, grid.n_azimuth // 2 - 1)
    return first, last - first + 1


def undecided_band_edges(mag: np.ndarray, grid: nlcs.FocusGrid, margin: float) -> np.ndarray:
    """Bins (columns of |X_ref|) whose H8 segment ends, as `nlcs.fit_azimuth_compression` picks them, could move if
    every magnitude moved by up to `margin` times the bin's peak."""
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


def _is_power_of_two(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def _radix_plan(n: int) -> list[int]:
    """Radices (8, 4, 2) whose product is n, an even number of them where n allows (the ping-pong then ends
    in the input buffer)."""
    m = n.bit_length() - 1
    radices = [8] * (m // 3) + ([4] if m % 3 == 2 else [2] if m % 3 == 1 else [])
    if len(radices) % 2 and 8 in radices:
        radices.remove(8)
        radices += [4, 2]
    return radices


_ENGINES: dict = {}


def shared_engine(device: str | None = None) -> FocusEngine:
    """One engine per device spec and process: programs, plans and buffers survive across passes."""
    key = device or ""
    if key not in _ENGINES:
        _ENGINES[key] = FocusEngine(device)
    return _ENGINES[key]


def warm_start_s(engine: FocusEngine) -> float:
    """Time to build a second engine on the same device (kernel binaries come from the runtime's cache)."""
    t = time.perf_counter()
    FocusEngine(engine.device, fp64_phase=engine.fp64_phase)
    return time.perf_counter() - t

