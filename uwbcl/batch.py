"""The nightly job: a directory tree of scan archives in, a displacement time series out (docs/outputs.md).

Stages: discover the archives (recursively, skipping the output directory) -> detect the plates of every pass
(cached per pass, in parallel) -> validate and group the passes by rig, cycle and height -> locate the plates
of each cycle -> chain the cycles of each rig into displacements -> write the outputs atomically.

Resumable and incremental: the detections of a pass are cached under OUT/.uwbcl-cache, keyed by the SHA-256
of the file's bytes and a hash of the settings that shape detections. Everything after detection is cheap and
recomputed from all cached passes on every run, so a run that was killed and restarted, or one that only added
new shifts, writes exactly what one uninterrupted run over the same files writes.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import fcntl
import functools
import hashlib
import json
import logging
import multiprocessing
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from . import __version__, archive, chain, outputs, pipeline
from .atomic import write_text_atomic
from .records import (
    BatchError,
    BatchOptions,
    BatchReport,
    CycleResult,
    Detection,
    PassRecord,
    Problem,
    ProcessingSettings,
)

log = logging.getLogger("uwbcl")

CACHE_DIR = ".uwbcl-cache"
CACHE_VERSION = 1  # bump when the cached record changes meaning
LOCK_FILE = ".uwbcl.lock"
PARAMETER_KEYS = ("carrier_frequency_hz", "bandwidth_hz", "sample_rate_hz", "pulse_repetition_frequency_hz",
                  "antenna_aperture_m", "rotation_table_angle_deg", "reference_point_m", "boresight_y_sign")


# ----------------------------------------------------------------------------------------------- per pass
def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of the package's own source (Python and OpenCL): a changed focuser or detector invalidates the cache
    even when the version number did not move (development installs)."""
    root = Path(__file__).resolve().parent
    files = sorted(p for p in root.rglob("*") if p.suffix in (".py", ".cl") and "__pycache__" not in p.parts)
    kernels = root.parent / "kernels"  # editable install: the .cl sources live beside the package
    if kernels.is_dir():
        files += sorted(kernels.glob("*.cl"))
    h = hashlib.sha256()
    for p in files:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def settings_key(settings: ProcessingSettings) -> str:
    """Hash of everything that shapes a pass's detections (not the association, which is recomputed)."""
    shaping = {k: v for k, v in dataclasses.asdict(settings).items() if k != "association"}
    text = json.dumps({"cache_version": CACHE_VERSION, "uwbcl": __version__, "code": code_fingerprint(),
                       "settings": shaping}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def detect_file(path: str, settings: ProcessingSettings) -> dict:
    """Worker: read and focus one archive. Returns {"header": ..., "detections": [...]} or {"error": ...}.

    Runs in a worker process, so it returns plain data and never raises for a bad file.
    """
    try:
        scan = archive.read_pass(path)
    except archive.ArchiveError as e:
        return {"error": f"{e.field}: {e.reason}", "kind": "invalid_archive"}
    except OSError as e:
        return {"error": f"cannot read: {e.strerror or e}", "kind": "unreadable"}
    try:
        detections = pipeline.detect_pass(scan, settings)
    except Exception as e:  # noqa: BLE001 - a numerical failure in one pass must not stop the night's run
        return {"error": f"focusing failed: {type(e).__name__}: {e}", "kind": "processing_failed"}
    header = {
        "rig_id": scan.rig_id, "cycle": int(scan.cycle), "height_m": float(scan.geometry.height_m),
        "pass_start_time": scan.pass_start_time,
        "parameters": {
            "carrier_frequency_hz": scan.radar.carrier_frequency_hz, "bandwidth_hz": scan.radar.bandwidth_hz,
            "sample_rate_hz": scan.radar.sample_rate_hz,
            "pulse_repetition_frequency_hz": scan.radar.pulse_repetition_frequency_hz,
            "antenna_aperture_m": scan.radar.antenna_aperture_m,
            "rotation_table_angle_deg": scan.geometry.rotation_table_angle_deg,
            "reference_point_m": list(scan.geometry.reference_point_m),
            "boresight_y_sign": scan.geometry.boresight_y_sign,
        },
    }
    header["pass_id"] = archive.read_pass_header(path)["pass_id"]
    return {"header": header, "detections": [dataclasses.asdict(d) for d in detections]}


DETECT = detect_file  # the per-pass worker (tests substitute one that crashes)


def _record(file: str, sha: str, entry: dict) -> PassRecord:
    h = entry["header"]
    return PassRecord(file=file, sha256=sha, rig_id=h["rig_id"], cycle=h["cycle"], height_m=h["height_m"],
                      pass_id=h["pass_id"], pass_start_time=h["pass_start_time"], parameters=h["parameters"],
                      detections=tuple(Detection(**d) for d in entry["detections"]))


class PassCache:
    """Detections per (file content, settings) under OUT/.uwbcl-cache/<settings key>/<sha256>.json."""

    def __init__(self, out_dir: Path, settings: ProcessingSettings, enabled: bool = True):
        self.dir = out_dir / CACHE_DIR / settings_key(settings)
        self.enabled = enabled

    def get(self, sha: str) -> dict | None:
        if not self.enabled:
            return None
        path = self.dir / f"{sha}.json"
        try:
            entry = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as e:  # a damaged cache entry is recomputed, never trusted
            log.warning("ignoring damaged cache entry %s: %s", path, e)
            return None
        if entry.get("cache_version") != CACHE_VERSION or entry.get("sha256") != sha:
            return None
        return entry

    def put(self, sha: str, entry: dict) -> None:
        if not self.enabled:
            return
        self.dir.mkdir(parents=True, exist_ok=True)
        # JSON floats round-trip float64 exactly, so a cached pass gives bit-identical results downstream.
        write_text_atomic(self.dir / f"{sha}.json",
                          json.dumps({"cache_version": CACHE_VERSION, "sha256": sha, **entry}, sort_keys=True))


# ----------------------------------------------------------------------------------------------- progress
class Progress:
    """A one-line progress bar on stderr, only on a terminal (a log file gets the log lines instead)."""

    def __init__(self, total: int, enabled: bool | None):
        self.total, self.done, self.failed = total, 0, 0
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.start = time.monotonic()

    def step(self, failed: bool = False) -> None:
        self.done += 1
        self.failed += failed
        if not self.enabled or self.total == 0:
            return
        width = 30
        filled = int(width * self.done / self.total)
        elapsed = time.monotonic() - self.start
        eta = elapsed / self.done * (self.total - self.done)
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} passes"
                         f"{f', {self.failed} failed' if self.failed else ''}, {elapsed:.0f} s, ETA {eta:.0f} s ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self.total:
            sys.stderr.write("\n")
            sys.stderr.flush()


def default_jobs(settings: ProcessingSettings) -> int:
    """All cores for numpy. Two for OpenCL, whose engine already uses every core (or a GPU) from one process:
    detection is host code, and a second worker keeps the device busy meanwhile (64 shift passes on 2 cores:
    11.2 s with one worker, 7.5 s with two; docs/opencl.md)."""
    try:
        cores = max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        cores = max(1, os.cpu_count() or 1)
    return cores if settings.backend == "numpy" else min(2, cores)


# ----------------------------------------------------------------------------------------------- grouping
def _params_differ(a: dict, b: dict) -> list[str]:
    out = []
    for k in PARAMETER_KEYS:
        va, vb = np.atleast_1d(np.asarray(a[k], dtype=float)), np.atleast_1d(np.asarray(b[k], dtype=float))
        if va.shape != vb.shape or not np.allclose(va, vb, rtol=1e-9, atol=1e-9):
            out.append(k)
    return out


def group_cycles(records: list[PassRecord], options: BatchOptions) -> tuple[dict, list[Problem]]:
    """(rig, cycle) -> {height_mm: record}, after the checks of a cycle; the problems found on the way."""
    problems: list[Problem] = []
    by_cycle: dict[tuple[str, int], list[PassRecord]] = defaultdict(list)
    for r in records:
        if options.heights_m is not None and not any(abs(r.height_m - h) <= options.height_tolerance_m
                                                     for h in options.heights_m):
            problems.append(Problem(r.file, "unexpected_height",
                                    f"rail height {r.height_m:.4f} m is not one of the configured heights "
                                    f"{', '.join(f'{h:g}' for h in options.heights_m)} m"))
            continue
        by_cycle[(r.rig_id, r.cycle)].append(r)
    cycles = {}
    for (rig, cycle), recs in sorted(by_cycle.items()):
        where = f"rig {rig} cycle {cycle}"
        # Duplicates: the same rig, cycle and height twice.
        by_height: dict[int, list[PassRecord]] = defaultdict(list)
        for r in sorted(recs, key=lambda r: r.file):
            by_height[archive.height_mm(r.height_m)].append(r)
        kept: dict[int, PassRecord] = {}
        for hmm, rs in sorted(by_height.items()):
            if len(rs) == 1:
                kept[hmm] = rs[0]
            elif len({r.sha256 for r in rs}) == 1:
                kept[hmm] = rs[0]
                problems.append(Problem("; ".join(r.file for r in rs), "duplicate_pass",
                                        f"{where} height {hmm} mm: {len(rs)} identical copies; {rs[0].file} used"))
            else:
                problems.append(Problem("; ".join(r.file for r in rs), "duplicate_pass",
                                        f"{where} height {hmm} mm: {len(rs)} different passes; none used"))
        # Parameters the passes of one cycle must share (same rig set-up): keep a strict majority, if any.
        groups: list[list[PassRecord]] = []
        for r in kept.values():
            for g in groups:
                if not _params_differ(g[0].parameters, r.parameters):
                    g.append(r)
                    break
            else:
                groups.append([r])
        if len(groups) > 1:
            groups.sort(key=lambda g: (-len(g), min(r.file for r in g)))
            majority = groups[0] if 2 * len(groups[0]) > len(kept) else None
            for g in groups:
                if g is majority:
                    continue
                ref = (groups[1] if g is groups[0] else groups[0])[0]
                fields = ", ".join(_params_differ(ref.parameters, g[0].parameters))
                for r in g:
                    problems.append(Problem(r.file, "mismatched_parameters",
                                            f"{where}: differs from {ref.file} in {fields}"
                                            + ("" if majority else " (no majority; cycle not used)")))
            if majority is None:
                continue
            kept = {k: r for k, r in kept.items() if any(r is m for m in majority)}
        if len(kept) < 2:
            files = "; ".join(r.file for r in kept.values()) or "; ".join(r.file for r in recs)
            heights = ", ".join(f"{r.height_m:g}" for r in kept.values()) or "none usable"
            problems.append(Problem(files, "single_height",
                                    f"{where}: a cycle needs passes at two or more heights, has {heights} m"))
            continue
        cycles[(rig, cycle)] = kept
    return cycles, problems


# ----------------------------------------------------------------------------------------------- cycles
def locate_records(recs: dict[int, PassRecord]) -> CycleResult:
    """The located plates of one cycle from its passes' records (keyed by height in mm)."""
    first = min(recs.values(), key=lambda r: (r.pass_start_time, r.file))
    return chain.locate_cycle(first.rig_id, first.cycle, first.pass_start_time,
                              {r.height_m: r.detections for r in recs.values()},
                              int(first.parameters["boresight_y_sign"]))


# ----------------------------------------------------------------------------------------------- the job
@contextlib.contextmanager
def _exclusive(out_dir: Path):
    """One run per output directory; the lock dies with the process, so a killed run never blocks the next."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / LOCK_FILE).open("a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise BatchError(f"{out_dir}: another uwbcl process is writing here") from None
        # Temporary files of a run that was killed mid-write; nobody else writes here while we hold the lock.
        for stale in [*out_dir.glob(".*.partial"), *(out_dir / CACHE_DIR).rglob(".*.partial")]:
            stale.unlink(missing_ok=True)
        yield


def discover(in_dir: Path, out_dir: Path) -> list[Path]:
    """Archives under in_dir, sorted, minus anything under out_dir (it may live inside the input tree)."""
    out = out_dir.resolve()
    return [p for p in archive.find_pass_files(in_dir) if out not in p.resolve().parents]


def _pool(jobs: int) -> cf.Executor:
    # spawn: each worker starts clean (no inherited OpenCL context, BLAS threads or locks from the parent).
    return cf.ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))


def _run_pool(todo: list[tuple[Path, str, str]], settings: ProcessingSettings, jobs: int, finish) -> list:
    """Focus `todo` in a pool of `jobs` workers; returns the items left unfinished if the pool broke."""
    pool = _pool(jobs)
    done: set[int] = set()
    try:
        futures = {pool.submit(DETECT, str(item[0]), settings): k for k, item in enumerate(todo)}
        for fut in cf.as_completed(futures):
            try:
                entry = fut.result()
            except cf.process.BrokenProcessPool:
                break
            done.add(futures[fut])
            finish(*todo[futures[fut]], entry)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return [item for k, item in enumerate(todo) if k not in done]


def detect_all(files: list[Path], in_dir: Path, settings: ProcessingSettings, cache: PassCache,
               options: BatchOptions) -> tuple[list[PassRecord], list[Problem], set[str]]:
    """Records of every readable archive, from the cache or by focusing; problems of the others; the files
    focused in this run."""
    records: list[PassRecord] = []
    problems: list[Problem] = []
    todo: list[tuple[Path, str, str]] = []
    for path in files:
        rel = path.relative_to(in_dir).as_posix()
        try:
            sha = file_sha256(path)
        except OSError as e:
            log.error("%s: cannot read: %s", path, e.strerror or e)
            problems.append(Problem(rel, "unreadable", f"cannot read: {e.strerror or e}"))
            continue
        entry = cache.get(sha)
        if entry is not None:
            records.append(_record(rel, sha, entry))
        else:
            todo.append((path, rel, sha))
    if records:
        log.info("%d passes from the cache, %d to focus", len(records), len(todo))
    progress = Progress(len(todo), options.progress)
    done = 0

    def finish(path: Path, rel: str, sha: str, entry: dict) -> None:
        nonlocal done
        if "error" in entry:
            log.error("%s: %s", path, entry["error"])
            problems.append(Problem(rel, entry["kind"], entry["error"]))
        else:
            cache.put(sha, entry)
            records.append(_record(rel, sha, entry))
        done += 1
        progress.step(failed="error" in entry)
        if options.on_pass_done is not None:
            options.on_pass_done(done)

    jobs = options.jobs or default_jobs(settings)
    try:
        if jobs <= 1 or len(todo) <= 1:
            for path, rel, sha in todo:
                finish(path, rel, sha, DETECT(str(path), settings))
        else:
            left = _run_pool(todo, settings, min(jobs, len(todo)), finish)
            if left:
                # A worker died (a crash or the out-of-memory killer) and took the pool with it: redo the
                # unfinished passes one per fresh worker, so the one that kills its worker is the one reported.
                log.warning("a worker process died; focusing the %d unfinished passes one at a time", len(left))
                for item in left:
                    if _run_pool([item], settings, 1, finish):
                        finish(*item, {"error": "the worker process died while focusing it (crash or out of "
                                                "memory)", "kind": "processing_failed"})
    finally:
        progress.close()
    return records, problems, {rel for _, rel, _ in todo}


def process_directory(in_dir: Path, out_dir: Path, settings: ProcessingSettings | None = None,
                      options: BatchOptions | None = None) -> BatchReport:
    """Every archive under in_dir -> the outputs of docs/outputs.md in out_dir. Bad input is reported, skipped."""
    settings = settings or ProcessingSettings()
    options = options or BatchOptions()
    in_dir, out_dir = Path(in_dir), Path(out_dir)
    out_opts = options.outputs
    if out_opts.plots or out_opts.cycle_images:
        outputs.require_matplotlib()
    with _exclusive(out_dir):
        files = discover(in_dir, out_dir)
        cache = PassCache(out_dir, settings, options.cache)
        records, problems, focused = detect_all(files, in_dir, settings, cache, options)
        n_detected = len(focused)
        groups, group_problems = group_cycles(records, options)
        problems += group_problems
        for p in group_problems:
            log.error("%s: %s", p.file, p.reason)
        cycles = []
        for (rig, cycle), recs in sorted(groups.items()):
            result = locate_records(recs)
            log.info("rig %s cycle %d: %d plates located from %d heights", rig, cycle, len(result.plates),
                     len(result.heights_m))
            cycles.append(result)
        rows_series = chain.series(cycles, settings.association, options.max_bridge_cycles)
        for r in rows_series:
            if r.displacement.status != "ok":
                log.warning("rig %s cycle %d: %s (%d plates matched, runner-up %d)", r.cycle.rig_id,
                            r.cycle.cycle, r.displacement.status, r.displacement.n_targets,
                            r.displacement.runner_up_targets)
        problems.sort(key=lambda p: (p.file, p.kind, p.reason))
        rows = outputs.write_all(out_dir, rows_series, cycles, problems, out_opts, groups=groups, in_dir=in_dir,
                                 settings=settings)
    n_cached = len(records) - sum(1 for r in records if r.file in focused)
    return BatchReport(rows, problems, cycles, rows_series, len(files), n_detected, n_cached)
