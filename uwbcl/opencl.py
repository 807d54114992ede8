"""OpenCL platform layer: finding devices, choosing one, loading and building the kernels in `kernels/`.

Nothing here knows about radar; `uwbcl.focus.engine` owns the processing state. Device choice follows
pyopencl's convention: an explicit ``--device`` spec, else the ``PYOPENCL_CTX`` environment variable, else the
first GPU, else the first device of any kind.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

INSTALL_HINT = (
    "no usable OpenCL platform was found. On Debian/Ubuntu install a CPU runtime with "
    "`sudo apt-get install pocl-opencl-icd` (or your GPU vendor's OpenCL driver), "
    "or run `bash scripts/install.sh`; "
    "meanwhile every command works with `--backend numpy`."
)
FFT_HINT = (
    "the OpenCL backend needs pyvkfft (VkFFT): "
    "`sudo apt-get install opencl-headers ocl-icd-opencl-dev g++ && "
    "VKFFT_BACKEND=opencl pip install pyvkfft` (or `bash scripts/install.sh`); "
    "meanwhile use `--backend numpy`."
)


CACHE_HINT = (
    "PoCL (the CPU runtime) offers no device, and fails to build kernels, when it cannot write its kernel "
    "cache: check that POCL_CACHE_DIR (default ~/.cache/pocl, or $XDG_CACHE_HOME/pocl) is writable and not "
    "full"
)


class OpenClUnavailable(RuntimeError):
    """The OpenCL backend cannot run here; the message says what to install."""


def kernel_dir() -> Path:
    """Where the .cl sources are: $UWBCL_KERNEL_DIR, else inside the installed package (wheel), else the
    repository's `kernels/` (editable installs do not expose the force-included folder)."""
    override = os.environ.get("UWBCL_KERNEL_DIR")
    if override:
        return Path(override)
    packaged = Path(__file__).resolve().parent / "kernels"
    if packaged.is_dir() and any(packaged.glob("*.cl")):
        return packaged
    return Path(__file__).resolve().parents[1] / "kernels"


def kernel_source(*names: str) -> str:
    """The named .cl files concatenated (common helpers first), with `#line` markers for compiler messages."""
    parts = []
    for name in names:
        path = kernel_dir() / name
        try:
            text = path.read_text()
        except OSError as exc:
            raise OpenClUnavailable(f"kernel source {path}: {exc.strerror or exc}") from exc
        parts.append(f'#line 1 "{name}"\n{text}')
    return "\n".join(parts)


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - pyopencl is a dependency
        raise OpenClUnavailable(f"pyopencl is not importable ({exc}); " + INSTALL_HINT) from exc
    return cl


@dataclasses.dataclass(frozen=True)
class DeviceInfo:
    spec: str  # "platform:device" indices, as accepted by --device and PYOPENCL_CTX
    platform: str
    name: str
    kind: str
    compute_units: int
    global_memory_bytes: int
    fp64: bool


def device_kind(cl, device_type: int) -> str:
    """GPU, ACCELERATOR or CPU (PoCL reports CPU|DEFAULT, which to_string prints as 'ALL | CPU')."""
    for flag, name in ((cl.device_type.GPU, "GPU"), (cl.device_type.ACCELERATOR, "ACCELERATOR"),
                       (cl.device_type.CPU, "CPU")):
        if device_type & flag:
            return name
    return cl.device_type.to_string(device_type)


def list_devices() -> list[DeviceInfo]:
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:  # LogicError PLATFORM_NOT_FOUND_KHR when no ICD is installed
        raise OpenClUnavailable(INSTALL_HINT) from exc
    out, empty = [], []
    for ip, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:
            devices = []
        if not devices:
            empty.append(platform.name.strip())
        for idev, d in enumerate(devices):
            out.append(DeviceInfo(
                spec=f"{ip}:{idev}", platform=platform.name.strip(), name=d.name.strip(),
                kind=device_kind(cl, d.type), compute_units=d.max_compute_units,
                global_memory_bytes=d.global_mem_size, fp64=bool(d.double_fp_config),
            ))
    if not out and empty:  # installed, yet no device: not a missing driver
        raise OpenClUnavailable(f"the OpenCL platform(s) {', '.join(empty)} offer no device. {CACHE_HINT}; "
                                "meanwhile every command works with `--backend numpy`.")
    if not out:
        raise OpenClUnavailable(INSTALL_HINT)
    return out


def select_device(spec: str | None = None):
    """The pyopencl Device for `spec` ("P:D", "P", or a substring of the device name), PYOPENCL_CTX, or the
    default preference (GPU first)."""
    cl = _cl()
    infos = list_devices()
    platforms = cl.get_platforms()

    def device(info: DeviceInfo):
        ip, idev = (int(i) for i in info.spec.split(":"))
        return platforms[ip].get_devices()[idev]

    spec = spec if spec is not None else os.environ.get("PYOPENCL_CTX") or None
    if spec is None:
        gpus = [i for i in infos if i.kind == "GPU"]
        return device((gpus or infos)[0])
    parts = spec.split(":")
    if all(p.isdigit() for p in parts if p) and parts[0]:
        want = f"{parts[0]}:{parts[1] if len(parts) > 1 and parts[1] else 0}"
        for i in infos:
            if i.spec == want:
                return device(i)
        raise OpenClUnavailable(f"no OpenCL device {spec!r}; `uwbcl devices` lists them")
    matches = [i for i in infos if spec.lower() in f"{i.platform} {i.name}".lower()]
    if not matches:
        raise OpenClUnavailable(f"no OpenCL device matches {spec!r}; `uwbcl devices` lists them")
    return device(matches[0])


def describe_devices() -> str:
    lines = []
    for i in list_devices():
        lines.append(f"{i.spec:>5}  {i.kind:<12} {i.name}  [{i.platform}]  {i.compute_units} CU, "
                     f"{i.global_memory_bytes / 2**30:.1f} GiB, fp64 {'yes' if i.fp64 else 'no'}")
    return "\n".join(lines)
