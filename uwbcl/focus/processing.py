"""The device spine of the OpenCL engine, in the style of silx's `OpenclProcessing`: context, queue,
program, a kernel table, a buffer table, the device-memory check and optional profiling. Nothing here
knows about radar.

* **Kernel table.** The program is built from `.cl` files with `-D` defines; the `__kernel` signatures of the
  sources are parsed (`parse_kernel_signatures`: argument names, address qualifiers, C types, with the build's
  typedefs resolved, so `real_t` is float or double per build) and every launch names its arguments
  (`launch("nlcs_filter", size, s=..., eta1=..., n_range=...)`). A missing, unknown or wrongly typed
  argument is a `KernelArgumentError` that names the kernel and the argument; scalars are converted to the
  signature's type.
* **Buffer table.** Every device buffer is declared up front (`BufferSpec`: name, shape as a function of the
  focus grid and a few named extents, dtype); buffers are kept between passes per name and shape.
* **Memory.** `check_footprint` adds up the bytes of the buffers a pass will use, from the table, and refuses
  the pass (`DeviceMemoryError`) before anything is allocated if it exceeds the device's global memory or one
  buffer exceeds its largest allocation (`memory_limits`, overridable).
* **Profiling.** With `profile=True` the queue records timestamps; every launch, FFT, upload, fill and
  read-back is recorded under the innermost `stage(...)`; `profile_table()` prints calls, total and mean
  device time.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Callable

import numpy as np

from .. import opencl

log = logging.getLogger("uwbcl")

REAL = "real"  # a BufferSpec dtype: real_t of the build (float64 with fp64 phases, else float32)

# OpenCL C scalar and vector types that kernel arguments use, as numpy dtypes (float2: one complex64)
C_TYPES = {
    "char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16, "int": np.int32,
    "uint": np.uint32, "long": np.int64, "ulong": np.uint64, "float": np.float32, "double": np.float64,
    "float2": np.complex64, "double2": np.complex128,
}
_ADDRESS = {"__global": "global", "global": "global", "__constant": "constant", "constant": "constant",
            "__local": "local", "local": "local", "__private": "private", "private": "private"}
_OTHER_QUALIFIERS = {"const", "restrict", "__restrict", "volatile"}


class KernelArgumentError(TypeError):
    """A launch whose arguments do not match the kernel's signature."""


class DeviceMemoryError(RuntimeError):
    """A pass whose buffers would not fit in the device's memory."""


# ------------------------------------------------------------------------------------------ signatures
@dataclasses.dataclass(frozen=True)
class KernelArg:
    name: str
    address: str  # "global", "constant", "local" or "private" (a scalar passed by value)
    c_type: str  # the C type as resolved through the build's typedefs, e.g. "double", "float2"
    pointer: bool
    const: bool  # a const pointer: the kernel only reads it

    @property
    def dtype(self) -> np.dtype | None:
        t = C_TYPES.get(self.c_type)
        return None if t is None else np.dtype(t)


@dataclasses.dataclass(frozen=True)
class KernelSignature:
    name: str
    args: tuple[KernelArg, ...]

    @property
    def arg_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.args)


def _preprocess(source: str, defines: dict[str, str]) -> str:
    """Comments removed, continued lines joined, #ifdef/#ifndef/#else/#endif resolved against `defines`
    (and the source's own #defines); other directives dropped. Enough for signatures, not a C preprocessor."""
    source = re.sub(r"/\*.*?\*/|//[^\n]*", " ", source, flags=re.DOTALL).replace("\\\n", " ")
    defined = set(defines)
    active = [True]  # one entry per open conditional, and the file level
    out = []
    for line in source.splitlines():
        directive = re.match(r"\s*#\s*(\w+)\s*(\w*)", line)
        if not directive:
            if all(active):
                out.append(line)
            continue
        word, name = directive.groups()
        if word in ("ifdef", "ifndef"):
            active.append((name in defined) == (word == "ifdef"))
        elif word == "else":
            active[-1] = not active[-1]
        elif word == "endif":
            active.pop()
        elif word in ("if", "elif"):
            raise ValueError(f"kernel signatures: '#{word}' is not supported (use #ifdef): {line.strip()}")
        elif all(active) and word == "define":
            defined.add(name)
        elif all(active) and word == "undef":
            defined.discard(name)
    return "\n".join(out)


def parse_kernel_signatures(source: str, defines: dict[str, str] | None = None) -> dict[str, KernelSignature]:
    """The `__kernel` functions of OpenCL C `source` as built with `defines` (-D NAME=value).

    Parameters
    ----------
    source : the concatenated .cl text.
    defines : the build's -D macros; they select #ifdef branches, hence the typedefs (real_t).

    Returns
    -------
    kernel name -> KernelSignature (arguments in order, C types resolved through simple typedefs).
    """
    text = _preprocess(source, defines or {})
    typedefs = {alias: base for base, alias in re.findall(r"\btypedef\s+(\w+)\s+(\w+)\s*;", text)}

    def resolve(t: str) -> str:
        seen = set()
        while t in typedefs and t not in seen:
            seen.add(t)
            t = typedefs[t]
        return t

    out = {}
    for name, params in re.findall(r"\b(?:__kernel|kernel)\s+void\s+(\w+)\s*\(([^)]*)\)", text):
        args = []
        for param in (p.strip() for p in params.split(",")):
            if not param or param == "void":
                continue
            tokens = re.findall(r"\w+|\*", param)
            address = next((_ADDRESS[t] for t in tokens if t in _ADDRESS), "private")
            words = [t for t in tokens[:-1] if t not in _ADDRESS and t not in _OTHER_QUALIFIERS and t != "*"]
            c_type = " ".join(words)
            c_type = {"unsigned int": "uint", "unsigned char": "uchar", "unsigned short": "ushort",
                      "unsigned long": "ulong"}.get(c_type, c_type)
            pointer = "*" in tokens
            args.append(KernelArg(name=tokens[-1], address=address, c_type=resolve(c_type), pointer=pointer,
                                  const=pointer and "const" in tokens))
        out[name] = KernelSignature(name, tuple(args))
    return out


class _Launcher:
    """One kernel with the conversion plan of its arguments, in signature order (made once per kernel)."""

    __slots__ = ("kernel", "names", "plan", "signature")

    def __init__(self, kernel, signature: KernelSignature):
        self.kernel = kernel
        self.signature = signature
        self.names = frozenset(signature.arg_names)
        self.plan = tuple((a.name, a.pointer, a.dtype) for a in signature.args)

    def values(self, given: dict) -> list:
        """The kernel's arguments in order, from `given` (name -> value), checked and converted."""
        if given.keys() != self.names:
            missing = sorted(self.names - given.keys())
            unknown = sorted(given.keys() - self.names)
            what = "; ".join(s for s in (f"missing {', '.join(missing)}" if missing else "",
                                         f"unknown {', '.join(unknown)}" if unknown else "") if s)
            raise KernelArgumentError(f"kernel {self.signature.name}: {what} "
                                      f"(its arguments: {', '.join(self.signature.arg_names)})")
        out = []
        for name, pointer, dtype in self.plan:
            v = given[name]
            if pointer:
                if (getattr(v, "dtype", None) != dtype or isinstance(v, (np.ndarray, np.generic))
                        or not hasattr(v, "data")):
                    raise self._wrong(name, v)
                out.append(v.data)
            elif dtype is None:
                raise self._wrong(name, v)
            elif dtype.kind in "iu":
                if type(v) is bool or not isinstance(v, (int, np.integer)):
                    raise self._wrong(name, v)
                out.append(dtype.type(v))
            else:
                if not isinstance(v, (float, np.floating)):
                    raise self._wrong(name, v)
                out.append(dtype.type(v))
        return out

    def _wrong(self, name: str, value) -> KernelArgumentError:
        arg = next(a for a in self.signature.args if a.name == name)
        want = f"a device array of {arg.dtype}" if arg.pointer else f"a {arg.dtype} scalar"
        got = (f"an array of {value.dtype}" if hasattr(value, "dtype") and np.ndim(value) > 0
               else f"{type(value).__name__} {value!r}")
        c_type = f"pointer to {arg.c_type}" if arg.pointer else arg.c_type
        return KernelArgumentError(f"kernel {self.signature.name}: argument {name} ({c_type}) wants {want}, "
                                   f"got {got}")


@dataclasses.dataclass
class PreparedLaunch:
    """A launch with its arguments set once (named and checked like `launch`); enqueue it with
    `OpenclProcessing.enqueue`. For launches repeated many times with the same buffers (FFT passes)."""

    name: str
    kernel: object
    global_size: tuple[int, ...]


@dataclasses.dataclass
class PendingRead:
    """A read-back queued by `OpenclProcessing.host_async`: a device copy in a staging buffer, read on
    `result()` through `queue` once `copied` has completed; or (queue None) a direct read into `out`, complete
    with `copied` (None: nothing to read)."""

    cl: object
    queue: object  # None: read directly into `out` (large arrays)
    staging: object
    copied: object
    shape: tuple[int, ...]
    dtype: np.dtype
    out: np.ndarray | None = None

    def result(self) -> np.ndarray:
        if self.queue is None:
            if self.copied is not None:
                self.copied.wait()
            return self.out
        out = np.empty(self.shape, self.dtype)
        self.cl.enqueue_copy(self.queue, out, self.staging, wait_for=[self.copied], is_blocking=True)
        return out


# ------------------------------------------------------------------------------------------ buffers
@dataclasses.dataclass(frozen=True)
class BufferSpec:
    """A declared device buffer: `shape(grid, **extents)` (extents: counts the grid does not fix, such as the
    pulses of a pass), its dtype (or REAL), and whether it is `constant` (no kernel writes it: an upload of
    unchanged bytes is skipped)."""

    name: str
    shape: Callable[..., tuple[int, ...]]
    dtype: object
    constant: bool = False
    doc: str = ""


@dataclasses.dataclass(frozen=True)
class DeviceMemory:
    global_bytes: int
    max_alloc_bytes: int


# ------------------------------------------------------------------------------------------ profiling
class _Stage:
    __slots__ = ("name", "owner")

    def __init__(self, owner: OpenclProcessing, name: str):
        self.owner, self.name = owner, name

    def __enter__(self):
        self.owner._stages.append(self.name)
        if self.owner._profile is not None:
            self.owner._profile_calls[self.name] = self.owner._profile_calls.get(self.name, 0) + 1
        return self

    def __exit__(self, *exc):
        self.owner._stages.pop()
        return False


@dataclasses.dataclass(frozen=True)
class StageTiming:
    stage: str
    calls: int  # times the stage ran
    commands: int  # launches, FFTs, copies and fills it queued
    total_ms: float  # device time of those commands

    @property
    def mean_ms(self) -> float:
        return self.total_ms / self.calls if self.calls else 0.0


# ------------------------------------------------------------------------------------------ the base
class OpenclProcessing:
    """Context, queue and program of `kernel_files` built with `defines`, the kernel table, the buffer table
    `buffers`, the memory check and (with `profile`) profiling. `real_t` is double with `fp64`, else float."""

    SHAPES_PER_BUFFER = 3  # shapes kept per buffer name: a batch alternates between a few pass shapes
    SPARE_KERNELS_KEPT = 16  # retired kernel objects kept per kernel name for reuse
    STAGING_MAX_BYTES = 4 << 20  # uploads and queued reads up to this size go through a staging buffer

    def __init__(self, device, kernel_files: tuple[str, ...], buffers: tuple[BufferSpec, ...], *,
                 defines: dict[str, str] | None = None, fp64: bool = True, profile: bool = False):
        import pyopencl as cl

        self._cl = cl
        self.device = device
        self.context = cl.Context([device])
        props = cl.command_queue_properties.PROFILING_ENABLE if profile else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self.real = np.float64 if fp64 else np.float32
        self.defines = dict(defines or {})
        if fp64:
            self.defines["UWBCL_FP64"] = ""
        options = [f"-D{k}={v}" if v != "" else f"-D{k}" for k, v in self.defines.items()]
        if not fp64:  # unsuffixed constants as float, as on a device without fp64, also where it has fp64
            options.append("-cl-single-precision-constant")
        source = opencl.kernel_source(*kernel_files)
        try:
            self.program = cl.Program(self.context, source).build(options=options)
        except cl.Error as exc:  # a runtime that cannot compile or cache kernels: one message, no traceback
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            log.debug("kernel build log:\n%s", exc)
            raise opencl.OpenClUnavailable(f"building the kernels on {device.name.strip()} failed ({first}). "
                                           f"{opencl.CACHE_HINT}") from exc
        self.signatures = parse_kernel_signatures(source, self.defines)
        self._launchers = {k.function_name: _Launcher(k, self.signatures[k.function_name])
                           for k in self.program.all_kernels()}
        self._spare_kernels: dict[str, list] = {}  # kernel name -> retired kernel objects (`retire`)
        self.buffer_table = {b.name: b for b in buffers}
        self._buffers: dict = {}  # (name, shape, dtype) -> device array, most recently used last
        self._uploaded: dict = {}  # (name, shape, dtype) -> bytes of the last upload of a constant buffer
        self._read_queue = None  # the second queue of `host_async`'s reads, made on first use
        self._in_flight: list = []  # host arrays of direct uploads not yet known to be complete
        self.memory_limits = DeviceMemory(int(device.global_mem_size), int(device.max_mem_alloc_size))
        self._stages: list[str] = ["(none)"]
        self._profile: list | None = [] if profile else None  # (stage, label, event, end marker or None)
        self._profile_calls: dict[str, int] = {}
        self._profile_totals: dict[tuple[str, str], list] = {}  # (stage, label) -> [commands, ms], folded

    @property
    def profiling(self) -> bool:
        return self._profile is not None

    # ---- kernels
    def launch(self, name: str, global_size: tuple[int, ...], **args):
        """Launch kernel `name` on `global_size` with its arguments by name (device arrays for pointers,
        Python or numpy numbers for scalars, converted to the signature's types); returns the event."""
        launcher = self._launcher(name)
        event = launcher.kernel(self.queue, global_size, None, *launcher.values(args))
        if self._profile is not None:
            self._record(name, event)
        return event

    def prepare(self, name: str, global_size: tuple[int, ...], **args) -> PreparedLaunch:
        """A launch of `name` with its arguments checked and set now, on a kernel object of its own, to be
        enqueued any number of times (`enqueue`). The kernel object is a retired one (`retire`) where there
        is one: making a new one costs ~0.4 ms of host time (pyopencl generates its invoker)."""
        launcher = self._launcher(name)
        spare = self._spare_kernels.get(name)
        kernel = spare.pop() if spare else self._cl.Kernel(self.program, name)
        for i, value in enumerate(launcher.values(args)):
            kernel.set_arg(i, value)
        return PreparedLaunch(name, kernel, tuple(global_size))

    def retire(self, launches) -> None:
        """Prepared launches that will not be enqueued again: their kernel objects serve later `prepare`s (a
        command already queued keeps the arguments it was enqueued with)."""
        for launch in launches:
            spare = self._spare_kernels.setdefault(launch.name, [])
            if len(spare) < self.SPARE_KERNELS_KEPT:
                spare.append(launch.kernel)

    def _launcher(self, name: str) -> _Launcher:
        launcher = self._launchers.get(name)
        if launcher is None:
            raise KernelArgumentError(f"no kernel {name!r} in the program "
                                      f"(kernels: {', '.join(self._launchers)})")
        return launcher

    def enqueue(self, launch: PreparedLaunch):
        event = self._cl.enqueue_nd_range_kernel(self.queue, launch.kernel, launch.global_size, None)
        if self._profile is not None:
            self._record(launch.name, event)
        return event

    # ---- buffers
    def buffer_shape(self, name: str, grid, **extents) -> tuple[tuple[int, ...], np.dtype]:
        """(shape, dtype) of the declared buffer `name` for `grid` and `extents`."""
        spec = self.buffer_table.get(name)
        if spec is None:
            raise KeyError(f"buffer {name!r} is not declared (declared: {', '.join(self.buffer_table)})")
        try:
            shape = tuple(int(n) for n in spec.shape(grid, **extents))
        except TypeError as exc:
            raise TypeError(f"buffer {name!r}: {exc}") from exc
        return shape, np.dtype(self.real if spec.dtype == REAL else spec.dtype)

    def buffer(self, name: str, grid, **extents):
        """The device array `name` for this grid and extents, kept between passes (the name's least recently
        used shape is released beyond SHAPES_PER_BUFFER)."""
        shape, dtype = self.buffer_shape(name, grid, **extents)
        return self._array(name, shape, dtype)

    def _array(self, name: str, shape: tuple[int, ...], dtype: np.dtype):
        key = (name, shape, dtype)
        arr = self._buffers.pop(key, None)
        if arr is None:
            same_name = [k for k in self._buffers if k[0] == name]
            for old in same_name[:max(0, len(same_name) - self.SHAPES_PER_BUFFER + 1)]:
                del self._buffers[old]
                self._uploaded.pop(old, None)
            arr = self._cl_array().empty(self.queue, shape, dtype)
        self._buffers[key] = arr  # most recently used last
        return arr

    def _cl_array(self):
        import pyopencl.array as cla

        return cla

    def to_device(self, name: str, host, grid, **extents):
        """Upload `host` into the declared buffer `name` (it must have the declared shape; it is converted to
        the declared dtype) without waiting for the device. A constant buffer is not uploaded again while its
        bytes are unchanged.

        The bytes go into a new buffer created with them (CL_MEM_COPY_HOST_PTR), which a buffer-to-buffer
        copy on the queue then moves into `name`: PoCL's clEnqueueWriteBuffer from host memory returns only
        once the device has finished everything queued before it, even when asked not to block (measured:
        a 1 KB write behind 0.7 s of queued kernels returned after 0.7 s, on this queue or another), so a
        plain write made every upload a host-device synchronisation. The staging buffer is released here;
        the runtime keeps it until the copy that uses it has run (OpenCL's retain rules). Arrays above
        STAGING_MAX_BYTES are written directly (a fresh staging buffer of that size costs more in page faults
        than the wait: a 16 MB echo 1.3 -> 45 ms); their host copy is kept until the next read-back."""
        shape, dtype = self.buffer_shape(name, grid, **extents)
        host = np.array(host, dtype=dtype, order="C")  # a private copy: the caller may reuse its own
        if host.shape != shape:
            raise ValueError(f"buffer {name!r}: host array of shape {host.shape}, declared {shape} here")
        arr = self._array(name, shape, dtype)
        key = (name, shape, dtype)
        constant = self.buffer_table[name].constant
        data = host.tobytes() if constant else None
        if constant and self._uploaded.get(key) == data:
            return arr
        if host.nbytes > self.STAGING_MAX_BYTES:
            self._record("upload", self._cl.enqueue_copy(self.queue, arr.data, host, is_blocking=False))
            self._in_flight.append(host)
        elif host.nbytes:
            staging = self._cl.Buffer(self.context, self._cl.mem_flags.READ_ONLY
                                      | self._cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
            self._record("upload", self._cl.enqueue_copy(self.queue, arr.data, staging))
        self._uploaded[key] = data
        return arr

    def host(self, arr) -> np.ndarray:
        """Blocking read-back (of a device array or a leading-axis slice of one)."""
        out = np.empty(arr.shape, arr.dtype)
        event = self._cl.enqueue_copy(self.queue, out, arr.base_data, src_offset=arr.offset, is_blocking=True)
        self._record("read-back", event)
        self._in_flight.clear()  # the queue is in order: every upload queued before this has completed
        return out

    def host_async(self, arr) -> PendingRead:
        """Queue a read-back of `arr` without waiting; `.result()` waits for it alone, not for what was queued
        after it. The array is copied on the device into a staging buffer in queue order; the read from the
        staging buffer goes through a second queue that waits on that copy only. (A non-blocking
        clEnqueueReadBuffer on the in-order queue would do, but PoCL's returns only once everything queued
        before it has run, and the result would then wait for the work queued after it too.) Arrays above
        STAGING_MAX_BYTES are read directly, without blocking (see `to_device`)."""
        if arr.nbytes == 0:
            empty = np.empty(arr.shape, arr.dtype)
            return PendingRead(self._cl, None, None, None, arr.shape, arr.dtype, empty)
        if arr.nbytes > self.STAGING_MAX_BYTES:
            out = np.empty(arr.shape, arr.dtype)
            event = self._cl.enqueue_copy(self.queue, out, arr.base_data, src_offset=arr.offset,
                                          is_blocking=False)
            self._record("read-back", event)
            return PendingRead(self._cl, None, None, event, arr.shape, arr.dtype, out)
        staging = self._cl.Buffer(self.context, self._cl.mem_flags.READ_WRITE, arr.nbytes)
        copy = self._cl.enqueue_copy(self.queue, staging, arr.base_data, src_offset=arr.offset,
                                     byte_count=arr.nbytes)
        self._record("read-back", copy)
        if self._read_queue is None:
            self._read_queue = self._cl.CommandQueue(self.context)
        return PendingRead(self._cl, self._read_queue, staging, copy, arr.shape, arr.dtype)

    def fill(self, arr, value) -> None:
        """Set every element of `arr` to `value` (of the array's dtype) with a fill command, not a kernel."""
        event = self._cl.enqueue_fill_buffer(self.queue, arr.data, arr.dtype.type(value), 0, arr.nbytes)
        self._record("fill", event)

    def copy(self, dst, src) -> None:
        self._record("copy", self._cl.enqueue_copy(self.queue, dst.data, src.data))

    def release(self, name: str) -> None:
        """Forget every kept shape of buffer `name`."""
        for key in [k for k in self._buffers if k[0] == name]:
            del self._buffers[key]
            self._uploaded.pop(key, None)

    # ---- memory
    def footprint(self, grid, entries) -> dict[str, int]:
        """Bytes of each buffer of `entries` ((name, extents) pairs) for `grid`, from the buffer table."""
        out = {}
        for name, extents in entries:
            shape, dtype = self.buffer_shape(name, grid, **extents)
            out[f"{name}{list(shape)}"] = math.prod(shape) * dtype.itemsize
        return out

    def check_footprint(self, what: str, grid, entries) -> int:
        """Refuse (DeviceMemoryError) a pass whose buffers `entries` would not fit in `memory_limits`, before
        anything is allocated; release the kept buffers of other shapes if only they stand in the way.
        Returns the pass's bytes. (VkFFT's own work buffers and the runtime's overhead are not counted.)"""
        sizes = self.footprint(grid, entries)
        need = sum(sizes.values())
        limits = self.memory_limits
        largest = max(sizes, key=sizes.get)
        if sizes[largest] > limits.max_alloc_bytes:
            raise DeviceMemoryError(
                f"{what}: buffer {largest} needs {sizes[largest] / 2**20:.1f} MiB, more than the "
                f"{limits.max_alloc_bytes / 2**20:.1f} MiB {self.device.name.strip()} allocates at once")
        if need > limits.global_bytes:
            raise DeviceMemoryError(
                f"{what}: its buffers need {need / 2**20:.1f} MiB, more than the "
                f"{limits.global_bytes / 2**20:.1f} MiB of {self.device.name.strip()} "
                f"(largest {largest}: {sizes[largest] / 2**20:.1f} MiB)")
        held = sum(a.nbytes for a in self._buffers.values())
        if need + held > limits.global_bytes:
            self.release_kept()
        return need

    def release_kept(self) -> None:
        """Drop every device array kept between passes, so a pass that fits alone can allocate: the buffer
        table's here; a subclass drops whatever else it keeps (cached tables, recorded launches)."""
        self._buffers.clear()
        self._uploaded.clear()

    # ---- profiling
    def stage(self, name: str) -> _Stage:
        """Context manager: device commands queued inside are profiled under `name` (the innermost stage)."""
        return _Stage(self, name)

    PROFILE_EVENTS_KEPT = 20000  # recorded events are folded into totals beyond this (a long batch)

    def _record(self, label: str, event, end_event=None) -> None:
        if self._profile is not None:
            self._profile.append((self._stages[-1], label, event, end_event))
            if len(self._profile) > self.PROFILE_EVENTS_KEPT:
                self._fold_profile()

    def marker(self):
        """A marker event (for timing commands whose events a library does not return, such as VkFFT's)."""
        return self._cl.enqueue_marker(self.queue)

    def record_span(self, label: str, before, after) -> None:
        """Profile the commands queued between markers `before` and `after` as one command `label`."""
        self._record(label, before, after)

    def reset_profile(self) -> None:
        if self._profile is not None:
            self._profile.clear()
            self._profile_calls.clear()
            self._profile_totals.clear()

    def _fold_profile(self) -> None:
        """Add the device time of every recorded command to the totals per (stage, label) and drop the events
        (waits for the queue)."""
        self.queue.finish()
        for stage, label, event, end in self._profile:
            if end is None:
                ns = event.profile.end - event.profile.start
            else:  # between two markers: from the end of the first to the end of the second
                ns = end.profile.end - event.profile.end
            row = self._profile_totals.setdefault((stage, label), [0, 0.0])
            row[0] += 1
            row[1] += ns * 1e-6
        self._profile.clear()

    def profile_summary(self, by: str = "stage") -> list[StageTiming]:
        """Per stage (by="stage") or per kernel/command (by="command"): calls, commands and device ms."""
        if self._profile is None:
            raise RuntimeError("profiling is off: construct the engine with profile=True")
        self._fold_profile()
        rows: dict[str, list] = {}
        for (stage, label), (n, ms) in self._profile_totals.items():
            row = rows.setdefault(stage if by == "stage" else label, [0, 0.0])
            row[0] += n
            row[1] += ms
        return [StageTiming(k, self._profile_calls.get(k, 0) if by == "stage" else n, n, ms)
                for k, (n, ms) in rows.items()]

    def profile_table(self) -> str:
        """The per-stage summary as a text table (stages in the order they first ran), then per command."""
        lines = [f"{'stage':<28} {'calls':>6} {'commands':>9} {'total ms':>10} {'mean ms':>9}"]
        for t in self.profile_summary("stage"):
            lines.append(f"{t.stage:<28} {t.calls:>6} {t.commands:>9} {t.total_ms:>10.1f} {t.mean_ms:>9.2f}")
        lines += ["", f"{'command':<28} {'calls':>6} {'total ms':>10} {'mean ms':>9}"]
        for t in sorted(self.profile_summary("command"), key=lambda t: -t.total_ms):
            lines.append(f"{t.stage:<28} {t.calls:>6} {t.total_ms:>10.1f} {t.mean_ms:>9.3f}")
        return "\n".join(lines)
