#!/usr/bin/env python3
"""Benchmark: the numpy reference, a float32 scipy.fft chain and the OpenCL engine; same inputs, one run.

Legs, one `Focuser` each (uwbcl.focus.protocol; all focus with modified NLCS and exact-reference azimuth
compression; each focuses detection's neighbour models with its own chain (`nlcs_model_spectra`), as
`uwbcl process` does; the rest of detection is shared code):
  numpy    the float64 reference, `--backend numpy` (uwbcl.focus.reference.NumpyFocuser: nlcs.nlcs_focus)
  scipy32  uwbcl.focus.scipy32.Scipy32Focuser (nlcs_focus_scipy32): complex64 data, float64 phases,
           scipy.fft on all cores; what a careful CPU user would write instead of the engine
  opencl   the OpenCL engine, `--backend opencl` (uwbcl.focus.engine.shared_engine(--device))

Workloads
  (a) batch: N paper-sized passes (PAPER_SIM1 and PAPER_SIM2 on alternate rigs, SNR 10 dB, +-10 % carriage
      speed; one rig = 2 cycles x 2 heights = 4 passes) written as scan archives first (untimed); then, per
      leg, end to end: archive read -> focus -> detect (as pipeline.detect_pass, with the echo for neighbour
      cancellation) -> locate -> displacement -> displacements.csv written.
  (b) hires: one pass of 2048 pulses x 1024 range samples (sim 1 geometry, PRF 153.6 Hz so 2048 pulses span
      the 2 m aperture, 16 GHz fast-time sampling and a 2 m range margin for the 1024 samples) focused by each
      leg.
Each leg is warmed up once on every input shape (FFT plans, kernels, caches) before it is timed. The FFT share
is measured in a separate profiling pass over a sample of the batch, with every FFT call timed (OpenCL:
queue.finish() before and after each), so the timed pass is not distorted. The images of the numpy leg are the
oracle: every other leg must agree within ||out - ref|| / ||ref|| < 1e-4 (also checked with --skip-numpy, on a
few passes).

Running it
  On the CPU, as CI does (PoCL, 2 threads):
      POCL_DEVICES=pthread POCL_MAX_PTHREAD_COUNT=2 POCL_CPU_MAX_CU_COUNT=2 python scripts/benchmark.py
  A smoke run (20 passes; the hires pass timed once, without a warm-up run):
      python scripts/benchmark.py --quick
  On a GPU: install the vendor's OpenCL driver (it registers an ICD in /etc/OpenCL/vendors; NVIDIA's comes
  with the driver) and the `opencl` extra (pyvkfft, see README), then pick the device by its "platform:device"
  spec from `uwbcl devices`, or by a substring of its name, with --device or pyopencl's PYOPENCL_CTX:
      uwbcl devices
      python scripts/benchmark.py --device 0:0 --json gpu.json
      PYOPENCL_CTX=0:0 python scripts/benchmark.py --skip-numpy
  With neither, the engine takes the first GPU, else the first OpenCL device.

Threads, printed in the header: BLAS on one thread unless OPENBLAS_NUM_THREADS and its kin are set (as
`uwbcl` itself runs it, `uwbcl.threads`: set before numpy loads, inherited by the pool's workers); numpy's FFT
and elementwise maths run on one thread, scipy.fft uses all cores (workers=-1) in this process and one in a
pool worker, PoCL follows POCL_MAX_PTHREAD_COUNT / POCL_CPU_MAX_CU_COUNT.

Exit status: 0; 1 if a leg failed or an image disagreed with the reference; 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib.metadata
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uwbcl.threads import one_blas_thread  # noqa: E402

one_blas_thread()  # before numpy loads: BLAS as `uwbcl` runs it

import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.fft  # noqa: E402

from uwbcl import archive, batch, chain, detect, opencl, outputs, pipeline, simulate  # noqa: E402
from uwbcl.focus import nlcs, scipy32  # noqa: E402
from uwbcl.focus.protocol import FOCUSER_METHODS, Focuser  # noqa: E402
from uwbcl.focus.reference import NUMPY_FOCUSER  # noqa: E402
from uwbcl.focus.scipy32 import SCIPY32_FOCUSER  # noqa: E402
from uwbcl.model import PassGeometry, RadarParameters, ScanPass  # noqa: E402
from uwbcl.records import ProcessingSettings  # noqa: E402
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2  # noqa: E402

AGREEMENT_TOL = 1e-4  # ||out - ref|| / ||ref|| of complex images (docs/opencl.md, error budget)
PASSES_PER_RIG = 4  # 2 cycles x 2 heights
BATCH_SNR_DB = 10.0
BATCH_SPEED_JITTER = 0.1
HIRES_PULSES = 2048
HIRES_SAMPLES = 1024
HIRES_SAMPLE_RATE_HZ = 16e9
HIRES_RANGE_MARGIN_M = 2.0
PROFILE_SAMPLE = 16  # passes in the FFT profiling pass
ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
            "VECLIB_MAXIMUM_THREADS", "POCL_DEVICES", "POCL_MAX_PTHREAD_COUNT", "POCL_CPU_MAX_CU_COUNT",
            "POCL_CACHE_DIR", "PYOPENCL_CTX", "CUDA_CACHE_PATH")
LEG_NAMES = ("numpy", "scipy32", "opencl")
BACKEND = "backend"  # the stage of the time spent inside a leg's Focuser methods (TimedFocuser)


# --------------------------------------------------------------------------------------------- timing helpers
class Stopwatch:
    """Seconds accumulated per stage."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)

    @contextlib.contextmanager
    def __call__(self, stage: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - t


@dataclasses.dataclass
class FftClock:
    seconds: float = 0.0
    calls: int = 0

    def wrap(self, fn: Callable, sync: Callable | None = None) -> Callable:
        def timed(*args, **kwargs):
            if sync:
                sync()  # work queued before the FFT is not the FFT's
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            if sync:
                sync()
            self.seconds += time.perf_counter() - t
            self.calls += 1
            return out
        return timed


class TimedFocuser:
    """A leg's focuser whose `Focuser` methods add their seconds to `clock`'s BACKEND stage: what the leg's
    own backend costs, against the code every leg shares (archive reading, detection's host maths, locating,
    the CSV). The backend's stage overlaps "focus" and "detect"; it is not part of their sum."""

    def __init__(self, inner: Focuser, clock: Stopwatch):
        self._inner, self._clock = inner, clock

    def __getattr__(self, name: str):
        attr = getattr(self._inner, name)
        if name not in FOCUSER_METHODS:
            return attr

        def timed(*args, **kwargs):
            with self._clock(BACKEND):
                return attr(*args, **kwargs)
        return timed


@contextlib.contextmanager
def patched(owner, names: tuple[str, ...], clock: FftClock, sync: Callable | None = None):
    """Replace owner.<name> by a timed wrapper for the duration; callers look the attribute up at call
    time."""
    own = {n: n in vars(owner) for n in names}  # module functions: own; an engine's method: its class's
    saved = {n: getattr(owner, n) for n in names}
    try:
        for n in names:
            setattr(owner, n, clock.wrap(saved[n], sync))
        yield clock
    finally:
        for n in names:
            if own[n]:
                setattr(owner, n, saved[n])
            else:
                delattr(owner, n)  # drop the instance attribute that shadowed the method


# --------------------------------------------------------------------------------------------- legs
@dataclasses.dataclass
class Leg:
    name: str
    focuser: Focuser  # focuses the pass, detection's neighbour models and its calibration targets
    fft_probe: Callable[[FftClock], contextlib.AbstractContextManager]  # times every FFT call inside

    def focus(self, scan: ScanPass) -> nlcs.NlcsProducts:
        return self.focuser.nlcs_focus(scan, ac_mode="exact")


def make_legs(names: list[str], engine) -> list[Leg]:
    legs = {
        "numpy": Leg("numpy", NUMPY_FOCUSER, lambda c: patched(np.fft, ("fft", "ifft"), c)),
        "scipy32": Leg("scipy32", SCIPY32_FOCUSER, lambda c: patched(scipy.fft, ("fft", "ifft"), c)),
    }
    if engine is not None:
        legs["opencl"] = Leg("opencl", engine, lambda c: patched(engine, ("fft",), c, engine.queue.finish))
    return [legs[n] for n in names if n in legs]


def rel_err(out: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(out - ref) / np.linalg.norm(ref))


# --------------------------------------------------------------------------------------------- inputs
def write_batch(root: Path, n_passes: int) -> list[Path]:
    """n_passes / 4 rigs, sim 1 and sim 2 alternately, each 2 cycles x 2 heights, as scan archives."""
    for i in range(n_passes // PASSES_PER_RIG):
        scenario = (PAPER_SIM1, PAPER_SIM2)[i % 2]
        for scan in scenario.simulate(snr_db=BATCH_SNR_DB, speed_jitter=BATCH_SPEED_JITTER, seed=i,
                                      rig_id=f"{scenario.name}-rig{i:03d}"):
            archive.write_pass(root / archive.default_relative_path(scan), scan)
    return archive.find_pass_files(root)


def hires_pass() -> ScanPass:
    """2048 pulses x 1024 samples: sim 1's first pass, sampled more densely in both directions."""
    sc = PAPER_SIM1
    prf = HIRES_PULSES * sc.speed_m_s / sc.aperture_length_m  # 2048 pulse intervals over the aperture
    radar = dataclasses.replace(RadarParameters(), pulse_repetition_frequency_hz=prf,
                                sample_rate_hz=HIRES_SAMPLE_RATE_HZ)
    geometry = PassGeometry(height_m=sc.heights_m[0], rotation_table_angle_deg=sc.rotation_table_angle_deg(0),
                            reference_point_m=tuple(float(c) for c in sc.reference_point_m(0)))
    scan = simulate.simulate_pass(radar, geometry, sc.targets_radar_m(0),
                                  aperture_length_m=sc.aperture_length_m, speed_m_s=sc.speed_m_s,
                                  snr_db=BATCH_SNR_DB, speed_jitter=BATCH_SPEED_JITTER,
                                  rng=np.random.default_rng(0), range_margin_m=HIRES_RANGE_MARGIN_M,
                                  rig_id="hires")
    n = HIRES_PULSES  # the simulator centres an odd pulse count (2049) on the aperture: drop the last pulse
    scan = dataclasses.replace(scan, pulse_time_s=scan.pulse_time_s[:n],
                               pulse_position_m=scan.pulse_position_m[:n], echo=scan.echo[:n])
    if scan.echo.shape != (HIRES_PULSES, HIRES_SAMPLES):
        raise RuntimeError(f"hires pass came out {scan.echo.shape}, "
                           f"expected ({HIRES_PULSES}, {HIRES_SAMPLES})")
    return scan


# --------------------------------------------------------------------------------------------- the batch
@dataclasses.dataclass
class BatchRun:
    seconds: float
    stages: dict[str, float]
    displacements: dict[tuple[str, int], tuple[np.ndarray, str]]
    n_detections: int
    shapes: Counter
    jobs: int = 1


def run_batch(leg: Leg, files: list[Path], out_csv: Path, settings: ProcessingSettings) -> BatchRun:
    """archive read -> focus -> detect per pass, in this process; locate per cycle; displacement per rig; CSV
    written."""
    clock = Stopwatch()
    results = []
    t0 = time.perf_counter()
    for path in files:
        results.append(_one_pass(leg, path, settings, clock))
    return _finish_batch(results, clock, t0, out_csv, settings)


def _one_pass(leg: Leg, path: Path | str, settings: ProcessingSettings, clock: Stopwatch
              ) -> tuple[ScanPass, list, tuple[int, int]]:
    leg = dataclasses.replace(leg, focuser=TimedFocuser(leg.focuser, clock))
    with clock("read"):
        scan = archive.read_pass(path)
    with clock("focus"):
        products = leg.focus(scan)
    with clock("detect"):  # as pipeline.detect_pass: the echo lets detection model the neighbours
        found = detect.detect_nlcs(products, settings.detection, scan, leg.focuser)
    return scan, found, scan.echo.shape


def pool_pass(path: str, leg_name: str, settings: ProcessingSettings, device: str | None
              ) -> tuple[tuple[ScanPass, list, tuple[int, int]], dict[str, float]]:
    """Worker of batch's process pool (as `uwbcl process --jobs N`): one pass through `leg_name`; the scan
    without its echo (what locating needs), its detections and the stage seconds. A scipy32 worker's FFTs
    run on one thread: the pool's workers are the parallelism."""
    scipy32.WORKERS = 1
    engine = None
    if leg_name == "opencl":
        from uwbcl.focus.engine import shared_engine

        engine = shared_engine(device)
    leg = make_legs([leg_name], engine)[0]
    clock = Stopwatch()
    scan, found, shape = _one_pass(leg, path, settings, clock)
    return (dataclasses.replace(scan, echo=scan.echo[:0]), found, shape), dict(clock.seconds)


def run_batch_pool(leg: Leg, files: list[Path], out_csv: Path, settings: ProcessingSettings, jobs: int,
                   warm_files: list[Path], device: str | None) -> BatchRun:
    """`run_batch` with the passes spread over `jobs` worker processes of batch's pool. The workers are
    started and warmed up (every input shape, `jobs` times) before the clock starts, as the in-process legs
    are; the stage seconds are summed over the workers (CPU-side time, not wall time)."""
    pool = batch._pool(jobs)  # noqa: SLF001 - the pool `uwbcl process --jobs N` focuses with
    try:
        warm = [pool.submit(pool_pass, str(p), leg.name, settings, device) for p in warm_files * jobs]
        for fut in warm:
            fut.result()
        clock = Stopwatch()
        t0 = time.perf_counter()
        futures = [pool.submit(pool_pass, str(p), leg.name, settings, device) for p in files]
        results = []
        for fut in futures:
            result, stages = fut.result()
            for k, v in stages.items():
                clock.seconds[k] += v
            results.append(result)
        return _finish_batch(results, clock, t0, out_csv, settings)
    finally:
        batch._stop_pool(pool)  # noqa: SLF001


def _finish_batch(results: list[tuple[ScanPass, list, tuple[int, int]]], clock: Stopwatch, t0: float,
                  out_csv: Path, settings: ProcessingSettings) -> BatchRun:
    by_cycle: dict[tuple[str, int], list] = defaultdict(list)
    shapes: Counter = Counter()
    n_det = 0
    for scan, found, shape in results:
        shapes[tuple(shape)] += 1
        n_det += len(found)
        by_cycle[(scan.rig_id, scan.cycle)].append((scan, found))
    with clock("locate"):
        cycles = [pipeline.locate_detections([s for s, _ in items], [f for _, f in items])
                  for _, items in sorted(by_cycle.items())]
    with clock("displacement"):
        rows = chain.series(cycles, settings.association)
    with clock("csv"):
        outputs.write_displacements_csv(out_csv, rows)
    seconds = time.perf_counter() - t0
    disp = {(r.cycle.rig_id, r.cycle.cycle): (np.asarray(r.displacement.advance_m, dtype=float),
                                              r.displacement.status) for r in rows}
    return BatchRun(seconds, dict(clock.seconds), disp, n_det, shapes)


def profile_ffts(leg: Leg, scans: list[ScanPass]) -> tuple[float, float, int]:
    """(focus seconds, FFT seconds, FFT calls) over `scans`, every FFT call timed."""
    clock = FftClock()
    t = time.perf_counter()
    with leg.fft_probe(clock):
        for scan in scans:
            leg.focus(scan)
    return time.perf_counter() - t, clock.seconds, clock.calls


# --------------------------------------------------------------------------------------------- report
def header(engine, engine_error: str | None, fresh_cache: str | None) -> dict:
    def version(dist: str) -> str:
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            return "not installed"

    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info = {
        "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
        "pyopencl": version("pyopencl"), "pyvkfft": version("pyvkfft"),
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "cpu_affinity": affinity,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "env": {k: os.environ.get(k) for k in ENV_VARS},
        "scipy_fft_workers": affinity, "fresh_kernel_cache": fresh_cache,
    }
    try:
        import threadpoolctl

        info["threadpools"] = [{k: p[k] for k in ("internal_api", "num_threads", "version")}
                               for p in threadpoolctl.threadpool_info()]
    except ImportError:
        info["threadpools"] = "threadpoolctl not installed"
    if engine is not None:
        dev = engine.device
        info["opencl"] = {
            "device": dev.name.strip(), "platform": dev.platform.name.strip(),
            "kind": opencl.device_kind(engine._cl, dev.type), "compute_units": dev.max_compute_units,
            "global_memory_gib": dev.global_mem_size / 2**30, "fp64_phase": engine.fp64_phase,
            "cold_start_s": engine.startup_s,
        }
    else:
        info["opencl"] = {"error": engine_error}
    return info


def print_header(info: dict) -> None:
    print("== uwbcl benchmark: numpy float64 reference vs float32 scipy.fft vs OpenCL engine ==")
    print(f"python {info['python']}, numpy {info['numpy']}, scipy {info['scipy']}, "
          f"pyopencl {info['pyopencl']}, pyvkfft {info['pyvkfft']}")
    load = info["load_average"]
    print(f"CPU: {info['cpu']}, {info['cpu_count']} logical cores ({info['cpu_affinity']} usable), "
          "load average "
          + (" ".join(f"{x:.2f}" for x in load) if load else "n/a"))
    env = "  ".join(f"{k}={v if v is not None else '(unset)'}" for k, v in info["env"].items())
    print(f"environment: {env}")
    print(f"threads: numpy FFT/elementwise 1; scipy.fft workers=-1 ({info['scipy_fft_workers']}); "
          f"BLAS pools: {info['threadpools']}")
    if not any(info["env"].get(k) for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")):
        print("note: BLAS threads are unset, so BLAS uses every core. Detection's many small "
              "matrix-vector products then slow down badly on a busy machine (2.2 s instead of 0.2 s per "
              "pass measured on a loaded 2-core host); OPENBLAS_NUM_THREADS=1 avoids it. "
              "Nothing is changed here.")
    cl = info["opencl"]
    if "error" in cl:
        print(f"OpenCL: unavailable ({cl['error']})")
    else:
        print(f"OpenCL: {cl['device']} [{cl['platform']}], {cl['kind']}, {cl['compute_units']} CU, "
              f"{cl['global_memory_gib']:.1f} GiB, phases in {'fp64' if cl['fp64_phase'] else 'fp32'}; "
              f"engine start-up cold {cl['cold_start_s']:.2f} s, warm {cl['warm_start_s']:.2f} s"
              + (" (fresh kernel cache)" if info["fresh_kernel_cache"] else
                 " (cold = first engine in this process; the runtime's on-disk kernel cache may be warm)"))


def fmt_share(part: float, total: float) -> str:
    return f"{100 * part / total:5.1f}%" if total > 0 else "   n/a"


def write_json_atomic(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2,
                      default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
            f.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


# --------------------------------------------------------------------------------------------- main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--passes", type=int, default=None,
                   help=f"passes in the batch, a multiple of {PASSES_PER_RIG} (default 200; 20 with --quick)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 20 passes, the hires pass timed without a warm-up run")
    p.add_argument("--device", default=None,
                   help="OpenCL device spec (see `uwbcl devices`); default PYOPENCL_CTX, "
                        "else the first GPU, else the first device")
    p.add_argument("--skip-numpy", action="store_true",
                   help="do not time the numpy leg (its images are still computed for the agreement check "
                        "on a few batch passes, not on the hires pass)")
    p.add_argument("--skip-hires", action="store_true", help="leave out workload (b)")
    p.add_argument("--jobs", type=int, default=batch.cpu_count(),
                   help="worker processes of the numpy and scipy32 legs in the batch, as `uwbcl process "
                        "--jobs N` runs them (batch's pool; each scipy32 worker's FFTs on one thread); "
                        "default: the cores here. 1: in this process, scipy.fft on all cores")
    p.add_argument("--opencl-jobs", type=int,
                   default=batch.default_jobs(ProcessingSettings(backend="opencl")),
                   help="worker processes of the OpenCL leg in the batch, each with its own engine on the "
                        "same device (default: as `uwbcl process --backend opencl` runs it, two workers "
                        "where there are two cores; 1: this process, the engine on every core the runtime "
                        "is given)")
    p.add_argument("--fresh-kernel-cache", action="store_true",
                   help="point PoCL's and CUDA's kernel caches at an empty directory, for a true cold start")
    p.add_argument("--workdir", type=Path, default=None,
                   help="where the archives and CSVs go (kept); default a temporary directory, removed")
    p.add_argument("--json", type=Path, default=None, metavar="OUT",
                   help="write the numbers to this JSON file")
    args = p.parse_args(argv)
    if args.passes is None:
        args.passes = 20 if args.quick else 200
    if args.passes < PASSES_PER_RIG or args.passes % PASSES_PER_RIG:
        p.error(f"--passes must be a positive multiple of {PASSES_PER_RIG} (2 cycles x 2 heights per rig)")
    return args


def start_engine(device: str | None):
    from uwbcl.focus.engine import shared_engine, warm_start_s

    engine = shared_engine(device)
    return engine, warm_start_s(engine)


def main(argv=None) -> int:
    args = parse_args(argv)
    failures: list[str] = []
    scratch = Path(tempfile.mkdtemp(prefix="uwbcl-bench-"))
    if args.fresh_kernel_cache:  # must precede the first OpenCL call of the process
        for var in ("POCL_CACHE_DIR", "CUDA_CACHE_PATH"):
            os.environ[var] = str(scratch / "kernel-cache")
    workdir = args.workdir or scratch
    try:
        engine, engine_error, warm_s = None, None, None
        try:
            engine, warm_s = start_engine(args.device)
        except Exception as exc:  # noqa: BLE001 - no engine: report it, run the CPU legs
            engine_error = str(exc)
            failures.append(f"opencl: {exc}")
        info = header(engine, engine_error,
                      str(scratch / "kernel-cache") if args.fresh_kernel_cache else None)
        if engine is not None:
            info["opencl"]["warm_start_s"] = warm_s
        print_header(info)
        names = [n for n in LEG_NAMES if not (n == "numpy" and args.skip_numpy)]
        legs = make_legs(names, engine)
        report: dict = {"header": info, "passes": args.passes, "quick": args.quick}
        report["batch"] = benchmark_batch(args, legs, workdir, failures)
        if not args.skip_hires:
            report["hires"] = benchmark_hires(args, legs, failures)
        report["failures"] = failures
        if args.json:
            write_json_atomic(args.json, report)
            print(f"\nnumbers written to {args.json}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    if failures:
        print("\nFAILED:\n  " + "\n  ".join(failures))
        return 1
    return 0


def benchmark_batch(args, legs: list[Leg], workdir: Path, failures: list[str]) -> dict:
    settings = ProcessingSettings(algorithm="nlcs", ac_mode="exact")
    t = time.perf_counter()
    files = write_batch(workdir / "archive", args.passes)
    n_rigs = args.passes // PASSES_PER_RIG
    print(f"\n(a) batch: {len(files)} passes ({n_rigs} rigs x 2 cycles x 2 heights, sim 1 and sim 2 "
          f"alternately, SNR {BATCH_SNR_DB:g} dB, speed +-{100 * BATCH_SPEED_JITTER:g} %); archives "
          f"written in {time.perf_counter() - t:.1f} s (untimed)")
    n_warm, agreement = warm_up_legs(legs, files, settings)
    runs = time_batch_runs(args, legs, files, workdir, settings, failures)
    n_sample, fft_frac = fft_fractions(legs, runs, files)
    out = report_batch_legs(runs, len(files), fft_frac, agreement, n_sample)
    out["ratios"], out["focus_only_ratios"] = throughput_ratios(runs)
    out["shared_code"] = shared_code_bound(runs, len(files))
    engine = next((leg.focuser for leg in legs if leg.name == "opencl"), None)
    if engine is not None:
        out["floor"] = report_floor(engine, files, runs, settings)
    print(f"    agreement on {n_warm} passes (one per shape), max ||out - numpy|| / ||numpy||: "
          + ", ".join(f"{k} {v:.1e}" for k, v in agreement.items()))
    for name, err in agreement.items():
        if not err < AGREEMENT_TOL:
            failures.append(f"batch {name}: image error vs numpy {err:.2e} >= {AGREEMENT_TOL:g}")
    out["displacement_vs"], out["displacement_max_abs_diff_mm"] = compare_displacements(runs)
    return out


def shape_samples(files: list[Path]) -> list[Path]:
    """One pass per input shape: the warm-up inputs, and those the images are compared on."""
    by_shape: dict[tuple[int, int], Path] = {}
    for path in files:
        h = archive.read_pass_header(path)
        by_shape.setdefault((h["n_pulses"], h["samples_per_pulse"]), path)
    return list(by_shape.values())


def warm_up_legs(legs: list[Leg], files: list[Path],
                 settings: ProcessingSettings) -> tuple[int, dict[str, float]]:
    """Warm every leg up on one pass per input shape (plans, kernels, caches); (passes used, each leg's
    max image error vs the numpy oracle on them)."""
    warm_scans = [archive.read_pass(p) for p in shape_samples(files)]
    reference = [nlcs.nlcs_focus(s, ac_mode="exact").image for s in warm_scans]  # the oracle (untimed)
    agreement = {}
    for leg in legs:
        images = []
        for scan in warm_scans:  # warm-up: plans, kernels, caches
            products = leg.focus(scan)
            detect.detect_nlcs(products, settings.detection, scan, leg.focuser)
            images.append(products.image)
        agreement[leg.name] = max(rel_err(im, ref) for im, ref in zip(images, reference))
    return len(warm_scans), agreement


def leg_jobs(args, name: str) -> int:
    """Worker processes of a leg: --jobs for the CPU legs, --opencl-jobs for the engine's."""
    return max(1, args.opencl_jobs if name == "opencl" else args.jobs)


def time_batch_runs(args, legs: list[Leg], files: list[Path], workdir: Path, settings: ProcessingSettings,
                    failures: list[str]) -> dict[str, BatchRun]:
    """The timed end-to-end run of each leg, in this process or in batch's worker pool (leg_jobs); a leg that
    fails is reported and left out."""
    runs: dict[str, BatchRun] = {}
    warm_files = shape_samples(files)
    for leg in legs:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        out_csv = workdir / f"out-{leg.name}" / "displacements.csv"
        jobs = leg_jobs(args, leg.name)
        try:
            if jobs > 1:
                runs[leg.name] = run_batch_pool(leg, files, out_csv, settings, jobs, warm_files, args.device)
            else:
                runs[leg.name] = run_batch(leg, files, out_csv, settings)
        except Exception as exc:  # noqa: BLE001 - report the leg, keep the others
            failures.append(f"batch {leg.name}: {type(exc).__name__}: {exc}")
            print(f"  {leg.name}: FAILED ({type(exc).__name__}: {exc})")
            continue
        runs[leg.name].stages["load_average_before"] = load
        runs[leg.name].jobs = jobs
    return runs


def fft_fractions(legs: list[Leg], runs: dict[str, BatchRun],
                  files: list[Path]) -> tuple[int, dict[str, tuple[float, float]]]:
    """(passes profiled, per timed leg (FFT time / focus time, FFT calls per pass)) from a separate profiling
    pass over a sample of the batch."""
    sample = files[:: max(1, len(files) // PROFILE_SAMPLE)][:PROFILE_SAMPLE]
    sample_scans = [archive.read_pass(p) for p in sample]
    fft_frac = {}
    for leg in legs:
        if leg.name in runs:
            focus_s, fft_s, calls = profile_ffts(leg, sample_scans)
            fft_frac[leg.name] = (fft_s / focus_s if focus_s > 0 else float("nan"), calls / len(sample_scans))
    return len(sample_scans), fft_frac


def report_batch_legs(runs: dict[str, BatchRun], n_files: int, fft_frac: dict[str, tuple[float, float]],
                      agreement: dict[str, float], n_sample: int) -> dict:
    """Print each leg's throughput, stage shares and FFT share; the batch's numbers without the ratios and
    displacement comparison."""
    shapes = next(iter(runs.values())).shapes if runs else Counter()
    print("    shapes (pulses x samples): "
          + ", ".join(f"{a}x{b}: {n}" for (a, b), n in sorted(shapes.items())))
    print("    shares of each leg's total time: archive read, focus (of it FFTs, estimated), detect, "
          "locate + displacement + CSV")
    cores = batch.cpu_count()
    print(f"    {'leg':<8} {'jobs':>4} {'ms/pass':>8} {'passes/s':>9} {'/core':>6} {'total s':>8} "
          f"{'read':>7} {'focus':>7} {'(FFT)':>8} {'detect':>7} {'loc+csv':>8}  load avg before")
    out: dict = {"files": n_files, "shapes": {f"{a}x{b}": n for (a, b), n in shapes.items()}, "legs": {},
                 "cores": cores}
    for name, run in runs.items():
        st = run.stages
        total = run.seconds
        rest = st["locate"] + st["displacement"] + st["csv"]
        # a pooled leg's stage seconds are summed over its workers: shares of that sum, not of the wall time
        basis = total if run.jobs == 1 else _summed_stages(st)
        frac, calls = fft_frac.get(name, (float("nan"), 0))
        fft_s = frac * st["focus"]
        print(f"    {name:<8} {run.jobs:4d} {1e3 * total / n_files:8.1f} {n_files / total:9.2f} "
              f"{n_files / total / cores:6.2f} {total:8.1f} {fmt_share(st['read'], basis):>7} "
              f"{fmt_share(st['focus'], basis):>7} {'(' + fmt_share(fft_s, basis).strip() + ')':>8} "
              f"{fmt_share(st['detect'], basis):>7} {fmt_share(rest, basis):>8}  "
              f"{st['load_average_before']:.2f}")
        out["legs"][name] = {
            "jobs": run.jobs, "ms_per_pass": 1e3 * total / n_files,
            "passes_per_s": n_files / total, "passes_per_s_per_core": n_files / total / cores,
            "seconds": total,
            "stage_seconds": {k: v for k, v in st.items() if k not in ("load_average_before", BACKEND)},
            "backend_seconds": st.get(BACKEND, 0.0),
            "load_average_before": st["load_average_before"],
            "fft_fraction_of_focus": frac, "fft_calls_per_pass": calls,
            "fft_seconds_estimate": fft_s, "detections": run.n_detections,
            "max_image_error_vs_numpy": agreement.get(name),
        }
    if any(run.jobs > 1 for run in runs.values()):
        print(f"    ({cores} cores; a leg with jobs > 1 ran in batch's worker pool, its shares are of the "
              "time summed over its workers)")
    print("    FFT share: from a separate profiling pass over "
          f"{n_sample} passes (FFT time / focus time there) x the focus time of the timed pass")
    for name, d in out["legs"].items():
        total = d["seconds"] if d["jobs"] == 1 else sum(d["stage_seconds"].values())
        focus = d["stage_seconds"]["focus"]
        print(f"    {name:<8} FFTs {fmt_share(d['fft_seconds_estimate'], total)}, focusing without FFTs "
              f"{fmt_share(focus - d['fft_seconds_estimate'], total)}, "
              f"the rest {fmt_share(total - focus, total)} "
              f"(FFTs are {100 * d['fft_fraction_of_focus']:.0f}% of focusing, "
              f"{d['fft_calls_per_pass']:.0f} calls per pass)")
    return out


def _summed_stages(stages: dict[str, float]) -> float:
    """Seconds of the disjoint stages (read, focus, detect, locate, displacement, csv), summed."""
    return sum(v for k, v in stages.items() if k not in ("load_average_before", BACKEND))


def shared_code_bound(runs: dict[str, BatchRun], n_files: int) -> dict:
    """Each leg's time inside its backend (`TimedFocuser`) and in the code all legs share, per pass, and the
    largest end-to-end ratio over numpy that a backend taking no time at all could reach with the shared code
    as it is (Amdahl: numpy's ms per pass / the OpenCL leg's shared ms per pass), printed. A pooled leg's
    seconds are summed over its workers: its per-pass shares are divided by its jobs to compare with wall
    time."""
    out: dict = {"legs": {}}
    print("    backend (the leg's Focuser methods) and shared code (read, detection's host maths, locate, "
          "CSV), ms per pass (core time / jobs):")
    for name, run in runs.items():
        backend = run.stages.get(BACKEND, 0.0)
        shared = _summed_stages(run.stages) - backend
        scale = 1e3 / n_files / run.jobs
        out["legs"][name] = {"backend_ms_per_pass": backend * scale, "shared_ms_per_pass": shared * scale}
        print(f"    {name:<8} backend {backend * scale:7.1f}  shared {shared * scale:7.1f}")
    if "numpy" in runs and "opencl" in runs:
        shared = out["legs"]["opencl"]["shared_ms_per_pass"]
        numpy_ms = 1e3 * runs["numpy"].seconds / n_files
        out["opencl_over_numpy_bound"] = numpy_ms / shared if shared > 0 else float("inf")
        print(f"    bound on opencl/numpy with this shared code (a backend that took no time): "
              f"{out['opencl_over_numpy_bound']:.1f}x")
    return out


def throughput_ratios(runs: dict[str, BatchRun]) -> tuple[dict[str, float], dict[str, float]]:
    """End-to-end and focus-only time ratios between the legs that ran, printed."""
    ratios, focus_ratios = {}, {}
    for a, b in (("opencl", "numpy"), ("opencl", "scipy32"), ("scipy32", "numpy")):
        if a in runs and b in runs:
            ratios[f"{a}/{b}"] = runs[b].seconds / runs[a].seconds
            focus_ratios[f"{a}/{b}"] = runs[b].stages["focus"] / runs[a].stages["focus"]
    if ratios:
        print("    end-to-end throughput ratios (>1: the first is faster): "
              + ", ".join(f"{k} {v:.2f}x" for k, v in ratios.items()))
        print("    focusing alone (same timed pass):                    "
              + ", ".join(f"{k} {v:.2f}x" for k, v in focus_ratios.items()))
    return ratios, focus_ratios


def fft_cost(engine, scans: list[ScanPass], settings: ProcessingSettings) -> dict[str, float]:
    """FLOPs and bytes of the engine's FFTs per pass (5 N log2 N per complex FFT of length N; one read and one
    write of the complex64 array per FFT), counted over `scans`: of the pass's focusing alone (`nlcs_focus`,
    its exact-reference spectra included) and of the whole pass (detection's neighbour models and
    calibration too)."""
    count = {"flops": 0.0, "bytes": 0.0}
    fft = engine.fft

    def counted(arr, axis, inverse=False):
        n = arr.shape[axis]
        count["flops"] += 5.0 * n * np.log2(n) * (arr.size // n)
        count["bytes"] += 2.0 * arr.size * 8
        return fft(arr, axis, inverse)

    engine.fft = counted
    try:
        focus = {"flops": 0.0, "bytes": 0.0}
        for scan in scans:
            before = dict(count)
            products = engine.nlcs_focus(scan, ac_mode="exact")
            for k in focus:
                focus[k] += count[k] - before[k]
            detect.detect_nlcs(products, settings.detection, scan, engine)
    finally:
        del engine.fft  # the instance attribute that shadowed the method
    n = len(scans)
    return {"focus_flops": focus["flops"] / n, "focus_bytes": focus["bytes"] / n,
            "pass_flops": count["flops"] / n, "pass_bytes": count["bytes"] / n}


def machine_rates(cores: int) -> dict[str, float]:
    """This CPU's FFT rate (complex64 scipy.fft on every core, 5 N log2 N per FFT; the better of a batch of
    1024-point FFTs, the chain's size, and one 2^20-point FFT) and its memory bandwidth (a 256 MiB copy,
    read + write), best of 5."""
    def best(fn, reps: int) -> float:
        fn()
        times = []
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(reps):
                fn()
            times.append((time.perf_counter() - t) / reps)
        return min(times)

    rng = np.random.default_rng(0)
    batch_fft = (rng.standard_normal((1024, 512)) + 1j).astype(np.complex64)
    big = (rng.standard_normal(1 << 20) + 1j).astype(np.complex64)
    t_batch = best(lambda: scipy.fft.fft(batch_fft, axis=0, workers=cores), 10)
    t_big = best(lambda: scipy.fft.fft(big, workers=cores), 10)
    rate = max(5.0 * 1024 * 10 * 512 / t_batch, 5.0 * (1 << 20) * 20 / t_big)
    a = np.ones(1 << 25, dtype=np.float64)
    b = np.empty_like(a)
    t_copy = best(lambda: np.copyto(b, a), 3)
    return {"fft_flops_per_s": rate, "memory_bytes_per_s": 2.0 * a.nbytes / t_copy}


def report_floor(engine, files: list[Path], runs: dict[str, BatchRun], settings: ProcessingSettings) -> dict:
    """The physical floor of a pass (its FFTs at this CPU's FFT rate, or their bytes at its memory bandwidth,
    whichever is longer) and the OpenCL leg's measured time over it, printed."""
    sample = [archive.read_pass(p) for p in files[:: max(1, len(files) // PROFILE_SAMPLE)][:PROFILE_SAMPLE]]
    cost = fft_cost(engine, sample, settings)
    rates = machine_rates(batch.cpu_count())
    out = {**cost, **rates}
    for what in ("focus", "pass"):
        out[f"{what}_floor_ms"] = 1e3 * max(cost[f"{what}_flops"] / rates["fft_flops_per_s"],
                                            cost[f"{what}_bytes"] / rates["memory_bytes_per_s"])
    mib = 2**20
    print(f"    floor: FFTs per pass {cost['focus_flops'] / 1e6:.0f} MFLOP / {cost['focus_bytes'] / mib:.0f} "
          f"MiB to focus, {cost['pass_flops'] / 1e6:.0f} MFLOP / {cost['pass_bytes'] / mib:.0f} MiB with "
          f"detection's models and calibration; this CPU: {rates['fft_flops_per_s'] / 1e9:.1f} GFLOP/s "
          f"complex64 FFT (scipy.fft, {batch.cpu_count()} cores), "
          f"{rates['memory_bytes_per_s'] / 1e9:.1f} GB/s copy; floor {out['focus_floor_ms']:.1f} ms to "
          f"focus, {out['pass_floor_ms']:.1f} ms per pass")
    run = runs.get("opencl")
    if run is not None:
        n = sum(run.shapes.values())
        out["opencl_ms_per_pass"] = 1e3 * run.seconds / n
        # a pooled leg's focus seconds are summed over its workers, which ran side by side
        out["opencl_focus_ms_per_pass"] = 1e3 * run.stages["focus"] / n / run.jobs
        print(f"    opencl: {out['opencl_ms_per_pass']:.1f} ms per pass end to end = "
              f"{out['opencl_ms_per_pass'] / out['pass_floor_ms']:.1f}x the pass floor; focusing "
              f"{out['opencl_focus_ms_per_pass']:.1f} ms = "
              f"{out['opencl_focus_ms_per_pass'] / out['focus_floor_ms']:.1f}x the focusing floor")
    return out


def compare_displacements(runs: dict[str, BatchRun]) -> tuple[str | None, dict[str, list[float]]]:
    """(the leg compared against: numpy, else scipy32, else None; each other leg's max |displacement
    difference| per component in mm), printed."""
    base = "numpy" if "numpy" in runs else ("scipy32" if "scipy32" in runs else None)
    worst_mm: dict[str, list[float]] = {}
    if base:
        ref = runs[base].displacements
        for name, run in runs.items():
            if name == base:
                continue
            keys = sorted(set(ref) & set(run.displacements))
            diff = np.array([np.abs(run.displacements[k][0] - ref[k][0]) for k in keys]).reshape(-1, 3)
            status_same = sum(run.displacements[k][1] == ref[k][1] for k in keys)
            worst = np.nanmax(diff, axis=0) * 1e3 if diff.size else np.full(3, np.nan)
            worst_mm[name] = worst.tolist()
            print(f"    displacements {name} vs {base}: max |diff| retreat/creep/vertical "
                  f"{worst[0]:.3f} / {worst[1]:.3f} / {worst[2]:.3f} mm over {len(keys)} rigs "
                  f"(of {len(ref)}); same status {status_same}/{len(keys)}; detections {run.n_detections} vs "
                  f"{runs[base].n_detections}")
    return base, worst_mm


def benchmark_hires(args, legs: list[Leg], failures: list[str]) -> dict:
    t = time.perf_counter()
    scan = hires_pass()
    grid = nlcs.focus_grid(scan)
    print(f"\n(b) hires pass: {scan.n_pulses} pulses x {scan.samples_per_pulse} samples (focus grid "
          f"{grid.n_azimuth} x {grid.n_range} with the azimuth padding of D5), simulated in "
          f"{time.perf_counter() - t:.1f} s (untimed); "
          + ("one cold run per leg (--quick)" if args.quick
             else "one warm-up run per leg, then one timed run"))
    seconds, images = {}, {}
    for leg in legs:
        try:
            if not args.quick:
                leg.focus(scan)
            t = time.perf_counter()
            images[leg.name] = leg.focus(scan).image
            seconds[leg.name] = time.perf_counter() - t
        except Exception as exc:  # noqa: BLE001 - report the leg, keep the others
            failures.append(f"hires {leg.name}: {type(exc).__name__}: {exc}")
            print(f"    {leg.name}: FAILED ({type(exc).__name__}: {exc})")
    ref_name = "numpy" if "numpy" in images else None
    out: dict = {"pulses": scan.n_pulses, "samples": scan.samples_per_pulse,
                 "focus_grid": [grid.n_azimuth, grid.n_range], "warm": not args.quick, "legs": {}}
    print(f"    {'leg':<8} {'seconds':>8} {'numpy/leg':>10} "
          f"{'error vs ' + (ref_name or 'numpy (skipped)'):>22}")
    for name, s in seconds.items():
        err = rel_err(images[name], images[ref_name]) if ref_name and name != ref_name else None
        ratio = seconds[ref_name] / s if ref_name else None
        out["legs"][name] = {"seconds": s, "speedup_vs_numpy": ratio, "error_vs_numpy": err}
        print(f"    {name:<8} {s:8.2f} {(f'{ratio:.2f}x' if ratio else 'n/a'):>10} "
              f"{(f'{err:.1e}' if err is not None else '-'):>22}")
        if err is not None and not err < AGREEMENT_TOL:
            failures.append(f"hires {name}: image error vs numpy {err:.2e} >= {AGREEMENT_TOL:g}")
    if "opencl" in seconds and "scipy32" in seconds:
        out["opencl/scipy32"] = seconds["scipy32"] / seconds["opencl"]
        out["opencl_vs_scipy32_error"] = rel_err(images["opencl"], images["scipy32"])
        print(f"    opencl/scipy32 {out['opencl/scipy32']:.2f}x; ||opencl - scipy32|| / ||scipy32|| "
              f"{out['opencl_vs_scipy32_error']:.1e}")
    return out


if __name__ == "__main__":
    sys.exit(main())
