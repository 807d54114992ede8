"""The engine's FFT layer: our Stockham azimuth kernels (kernels/fft.cl), VkFFT plans for the rest, and the
start-up self-test of both against numpy (docs/opencl.md, "FFTs")."""

from __future__ import annotations

import numpy as np

from .processing import BufferSpec, OpenclProcessing

SELF_TEST_SHAPE = (64, 48)

# the FFT layer's declared buffers (shapes are functions of the transform, not of the focus grid)
BUFFERS = (
    BufferSpec("fft_scratch", lambda _grid, n, cols: (n, cols), np.complex64,
               doc="the Stockham passes' ping-pong partner of an (n, cols) array"),
    BufferSpec("fft_twiddle", lambda _grid, n: (n,), np.complex64, constant=True,
               doc="exp(-2 pi i k / n), k < n"),
    BufferSpec("selftest", lambda _grid: SELF_TEST_SHAPE, np.complex64, doc="the start-up self-test's data"),
)


def fft_lanes(device) -> int:
    """Columns per work item of the Stockham kernels (fft.cl's FFT_LANES): the device's preferred float vector
    width, 4 to 16 (16 on an AVX-512 CPU, 4 on a GPU, whose preferred width is 1)."""
    width = int(getattr(device, "preferred_vector_width_float", 4) or 4)
    return 16 if width >= 16 else 8 if width >= 8 else 4


def fft_defines(lanes: int) -> dict[str, str]:
    """The `-D` defines that build fft.cl with `lanes` columns per work item."""
    return {"FFT_LANES": str(lanes), f"FFT_LANES_{lanes}": ""}


def is_power_of_two(n: int) -> bool:
    return n > 0 and n & (n - 1) == 0


def radix_plan(n: int) -> list[int]:
    """Radices (8, 4, 2) whose product is n, an even number of them where n allows (the ping-pong then ends
    in the input buffer)."""
    m = n.bit_length() - 1
    radices = [8] * (m // 3) + ([4] if m % 3 == 2 else [2] if m % 3 == 1 else [])
    if len(radices) % 2 and 8 in radices:
        radices.remove(8)
        radices += [4, 2]
    return radices


class DeviceFft:
    """In-place complex FFTs along one axis of the device arrays of `proc` (whose program holds fft.cl)."""

    LAUNCH_SETS_KEPT = 64  # Stockham launch sets kept (per buffer and direction); the least recently used go

    def __init__(self, proc: OpenclProcessing, vkfft_app, lanes: int):
        self.proc = proc
        self._vkfft_app = vkfft_app
        self.lanes = lanes  # the FFT_LANES fft.cl was built with
        self._plans: dict = {}  # (shape, axis, dtype) -> VkFFTApp
        self._twiddles: dict = {}  # n -> device table (held here, so the launches that use it stay valid)
        self._launches: dict = {}  # (buffer, scratch, twiddle, shape, inverse) -> [PreparedLaunch]

    def fft(self, arr, axis: int, inverse: bool = False) -> None:
        """In-place complex FFT along one axis (complex64 or complex128); the inverse is normalised by 1/N
        like numpy. Power-of-two complex64 azimuth (axis 0) transforms of 2-D arrays use our Stockham kernels
        (fft.cl), the rest VkFFT."""
        if axis == 0 and arr.ndim == 2 and arr.dtype == np.complex64 and is_power_of_two(arr.shape[0]):
            self.azimuth_fft(arr, inverse)
            return
        key = (arr.shape, axis, arr.dtype)
        app = self._plans.get(key)
        if app is None:
            app = self._plans[key] = self._vkfft_app(arr.shape, arr.dtype, self.proc.queue, ndim=1,
                                                     axes=(axis,), inplace=True, norm=1)
        if self.proc.profiling:  # VkFFT returns no events: time it between two markers
            before = self.proc.marker()
            (app.ifft if inverse else app.fft)(arr, arr)
            label = f"vkfft axis {axis}{' inverse' if inverse else ''}"
            self.proc.record_span(label, before, self.proc.marker())
        else:
            (app.ifft if inverse else app.fft)(arr, arr)

    def azimuth_fft(self, arr, inverse: bool = False) -> None:
        """Stockham FFT along axis 0 (fft.cl), radix 8/4/2 passes ping-ponging through a scratch buffer; the
        pass count is kept even so the result lands back in `arr`. The passes are prepared launches (arguments
        set once per buffer), so a transform costs its launches only (a pass takes ~0.4 ms on a CPU; setting
        nine arguments from Python costs a noticeable part of that)."""
        n, n_cols = arr.shape
        scratch = self.proc.buffer("fft_scratch", None, n=n, cols=n_cols)
        twiddle = self._twiddles.get(n)
        if twiddle is None:
            table = np.exp(-2j * np.pi * np.arange(n) / n)
            twiddle = self._twiddles[n] = self.proc.to_device("fft_twiddle", table, None, n=n)
        key = (arr.data.int_ptr, scratch.data.int_ptr, twiddle.data.int_ptr, arr.shape, bool(inverse))
        launches = self._launches.pop(key, None)
        if launches is None:
            while len(self._launches) >= self.LAUNCH_SETS_KEPT:  # the least recently used set goes
                self.proc.retire(self._launches.pop(next(iter(self._launches))))
            launches = self._azimuth_fft_launches(arr, scratch, twiddle, inverse)
        self._launches[key] = launches  # most recently used last
        for launch in launches:
            self.proc.enqueue(launch)
        if len(launches) % 2:  # an odd number of passes (n = 2 or 4)
            self.proc.copy(arr, scratch)

    def _azimuth_fft_launches(self, arr, scratch, twiddle, inverse: bool) -> list:
        n, n_cols = arr.shape
        radices = radix_plan(n)
        launches, src, dst, ns = [], arr, scratch, 1
        groups = -(-n_cols // self.lanes)  # work items across: the last group may be partial
        for i, radix in enumerate(radices):
            scale = 1.0 / n if inverse and i == len(radices) - 1 else 1.0
            launches.append(self.proc.prepare(f"azimuth_fft_radix{radix}", (groups, n // radix), x=src, y=dst,
                                              twiddle=twiddle, n=n, n_cols=n_cols, ns=ns,
                                              inverse=int(inverse), scale=scale))
            ns *= radix
            src, dst = dst, src
        return launches

    def self_test_failure(self, tol: float = 1e-5, axes: tuple[int, ...] = (0, 1)) -> str:
        """VkFFT is miscompiled by some OpenCL runtimes (e.g. PoCL 7.0-7.1): check it and our own azimuth FFT
        once against numpy, complex64.
        Returns what failed, or "" when the forward and inverse transforms agree to `tol`."""
        rng = np.random.default_rng(0)
        x = rng.standard_normal(SELF_TEST_SHAPE) + 1j * rng.standard_normal(SELF_TEST_SHAPE)
        x = x.astype(np.complex64)

        failure = ""
        for axis in axes:
            d = self.proc.to_device("selftest", x, None)
            self.fft(d, axis)
            ref = np.fft.fft(x.astype(np.complex128), axis=axis)
            err = np.linalg.norm(self.proc.host(d) - ref) / np.linalg.norm(ref)
            self.fft(d, axis, inverse=True)
            err_inv = np.linalg.norm(self.proc.host(d) - x) / np.linalg.norm(x)
            if not (err < tol and err_inv < tol):
                which = "the Stockham azimuth FFT (fft.cl)" if axis == 0 else "VkFFT"
                failure = (f"{which} complex64 self-test failed on {self.proc.device.name.strip()} "
                           f"(axis {axis}: relative error {err:.1e}/{err_inv:.1e})")
                break
        self._plans.clear()
        self.proc.release("selftest")
        return failure
