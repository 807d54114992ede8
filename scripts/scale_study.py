#!/usr/bin/env python3
"""Scale study: `uwbcl process` on growing batches of shift passes; time per pass and peak memory per size.

    python scripts/scale_study.py                                   # 200 passes (CI-sized)
    python scripts/scale_study.py --sizes 200 1000 5000 20000 --cache-dir ~/uwbcl-scale
    python scripts/scale_study.py --sizes 1000 --backend numpy --jobs 2

The passes are simulated once (`uwbcl simulate --scenario shift`: RIGS rigs, 2 heights, SNR 10 dB,
+-10 % rail speed, one seed) in chunks of CHUNK_CYCLES cycles (`--first-cycle`: later cycles of the same rigs
and rib), 200 passes per chunk, into --cache-dir, and reused by later runs. A size of n passes is a directory
of links to the first n / 200 chunks (processed with --follow-symlinks): the sizes share their archives, and a
larger size is a longer history of the same rigs. Each size is processed once, in a fresh process, with
--no-cache into a fresh output directory; the wall time includes the engine's start-up.

Peak RSS is that of the whole process tree (`uwbcl process` and its workers): sampled with psutil every
0.2 s when psutil is installed (the sum over the tree's processes), else
`resource.getrusage(RUSAGE_CHILDREN)`'s ru_maxrss, which is the largest single process of the tree so far in
the study (workers not added up).

A run's wall time is a fixed start-up (interpreter, workers, engine, FFT plans) plus a cost per pass, so the
time per pass of a small run overstates the cost per pass. The study prints both, and the marginal time per
pass between consecutive sizes, (wall_b - wall_a) / (n_b - n_a), which the start-up cancels from. Verdict:
flat when every marginal time per pass is within 10 % of the first one (with two sizes only: when the two
times per pass are within 10 %); memory is bounded when the largest size's peak RSS is within 25 % of the
smallest size's (a batch keeps only per-pass records, so memory should not grow with the number of passes).

Exit status: 0; 1 if a run failed; 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RIGS = 5
CHUNK_CYCLES = 20
HEIGHTS = 2  # the shift scenario's default heights, 0.2 and 0.6 m
PASSES_PER_CHUNK = RIGS * CHUNK_CYCLES * HEIGHTS
SEED = 5
SNR_DB = 10.0
SPEED_JITTER = 0.1
WEB_DEPTH_M = 0.9  # the shift scenario's nominal advance (docs/opencl.md, CPU-only sites)
FLAT_TOLERANCE = 0.10
RSS_TOLERANCE = 0.25
SAMPLE_PERIOD_S = 0.2


def uwbcl_command() -> list[str]:
    return [sys.executable, "-m", "uwbcl.cli"]


def chunk_dir(cache: Path, chunk: int) -> Path:
    return cache / "chunks" / f"cycles-{chunk * CHUNK_CYCLES:06d}"


def ensure_chunks(cache: Path, n_chunks: int) -> float:
    """Simulate the chunks that are not in the cache yet; seconds spent."""
    t = time.perf_counter()
    for chunk in range(n_chunks):
        target = chunk_dir(cache, chunk)
        if (target / ".complete").exists():
            continue
        shutil.rmtree(target, ignore_errors=True)
        subprocess.run(uwbcl_command() + [
            "simulate", str(target), "--scenario", "shift", "--rigs", str(RIGS),
            "--cycles", str(CHUNK_CYCLES), "--first-cycle", str(chunk * CHUNK_CYCLES), "--seed", str(SEED),
            "--snr-db", str(SNR_DB), "--speed-jitter", str(SPEED_JITTER)],
            check=True, stdout=subprocess.DEVNULL)
        (target / ".complete").touch()
    return time.perf_counter() - t


def size_dir(cache: Path, n_passes: int) -> Path:
    """A directory of links to the first n_passes / PASSES_PER_CHUNK chunks."""
    out = cache / f"size-{n_passes}"
    out.mkdir(parents=True, exist_ok=True)
    for chunk in range(n_passes // PASSES_PER_CHUNK):
        link = out / chunk_dir(cache, chunk).name
        if not link.is_symlink():
            link.symlink_to(chunk_dir(cache, chunk).resolve(), target_is_directory=True)
    return out


class TreeRss:
    """Peak summed RSS of a process and its descendants, sampled in a thread (psutil), in bytes."""

    def __init__(self, pid: int):
        import psutil

        self._psutil = psutil
        self._root = psutil.Process(pid)
        self.peak_bytes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            total = 0
            try:
                procs = [self._root] + self._root.children(recursive=True)
            except self._psutil.Error:
                break
            for p in procs:
                try:
                    total += p.memory_info().rss
                except self._psutil.Error:
                    pass
            self.peak_bytes = max(self.peak_bytes, total)
            self._stop.wait(SAMPLE_PERIOD_S)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def run_size(in_dir: Path, out_dir: Path, args) -> dict:
    """One `uwbcl process` run over in_dir: wall seconds, peak RSS (bytes) and how it was measured."""
    cmd = uwbcl_command() + ["process", str(in_dir), "--out", str(out_dir), "--no-cache", "--no-progress",
                             "--follow-symlinks", "--backend", args.backend, "--web-depth", str(WEB_DEPTH_M)]
    if args.jobs:
        cmd += ["--jobs", str(args.jobs)]
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    sampler = None
    try:
        sampler = TreeRss(proc.pid)
    except ImportError:
        pass
    output, _ = proc.communicate()
    seconds = time.perf_counter() - t
    if sampler is not None:
        sampler.stop()
    children_max = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # kB on Linux
    if sampler is not None and sampler.peak_bytes:
        rss, how = sampler.peak_bytes, "psutil, process tree summed"
    else:
        rss, how = children_max, "getrusage(RUSAGE_CHILDREN), largest process"
    return {"returncode": proc.returncode, "seconds": seconds, "peak_rss_bytes": rss, "rss_method": how,
            "output_tail": output[-2000:]}


def judge(ok: list[dict]) -> dict:
    """Marginal time per pass between consecutive sizes, the start-up estimate, the flat / bounded verdict,
    printed."""
    base = ok[0]
    marginal = [1e3 * (b["seconds"] - a["seconds"]) / (b["passes"] - a["passes"]) for a, b in zip(ok, ok[1:])]
    startup_s = base["seconds"] - base["passes"] * marginal[0] / 1e3
    if len(marginal) >= 2:
        spread = max(abs(m / marginal[0] - 1) for m in marginal)
        what = "marginal time per pass"
    else:
        spread = max(abs(r["ms_per_pass"] / base["ms_per_pass"] - 1) for r in ok)
        what = "time per pass"
    growth = ok[-1]["peak_rss_bytes"] / base["peak_rss_bytes"] - 1
    verdict = {"marginal_ms_per_pass": marginal, "startup_s_estimate": startup_s, "spread": spread,
               "spread_of": what, "flat": spread <= FLAT_TOLERANCE, "rss_growth": growth,
               "rss_bounded": growth <= RSS_TOLERANCE}
    print("marginal ms per pass between sizes: "
          + ", ".join(f"{a['passes']}->{b['passes']}: {m:.1f}" for a, b, m in zip(ok, ok[1:], marginal))
          + f"; start-up about {startup_s:.1f} s")
    print(f"{what} within {100 * spread:.0f} %: {'flat' if verdict['flat'] else 'NOT flat'} "
          f"(tolerance {100 * FLAT_TOLERANCE:.0f} %); peak RSS {100 * growth:+.0f} % from {base['passes']} "
          f"to {ok[-1]['passes']} passes: {'bounded' if verdict['rss_bounded'] else 'NOT bounded'} "
          f"(tolerance {100 * RSS_TOLERANCE:.0f} %); RSS by {base['rss_method']}")
    return verdict


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="+", default=[200],
                   help=f"batch sizes in passes, multiples of {PASSES_PER_CHUNK} (default 200)")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="where the simulated archives are kept between runs (default: a temporary directory, "
                        "removed)")
    p.add_argument("--backend", choices=("opencl", "numpy"), default="opencl")
    p.add_argument("--jobs", type=int, default=None, help="uwbcl process --jobs (default: its own)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the numbers here")
    args = p.parse_args(argv)
    bad = [n for n in args.sizes if n <= 0 or n % PASSES_PER_CHUNK]
    if bad:
        p.error(f"sizes must be positive multiples of {PASSES_PER_CHUNK}: {bad}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    scratch = Path(tempfile.mkdtemp(prefix="uwbcl-scale-"))
    cache = args.cache_dir or scratch / "cache"
    sizes = sorted(set(args.sizes))
    try:
        sim_s = ensure_chunks(cache, max(sizes) // PASSES_PER_CHUNK)
        print(f"== uwbcl scale study: uwbcl process --backend {args.backend}"
              f"{' --jobs ' + str(args.jobs) if args.jobs else ''} on shift passes ==")
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"archives: {cache} ({RIGS} rigs x 2 heights, {max(sizes) // (RIGS * HEIGHTS)} cycles; "
              f"simulated now in {sim_s:.0f} s); load average {load}")
        print(f"{'passes':>7} {'wall s':>8} {'ms/pass':>8} {'peak RSS MiB':>13}  load avg after")
        rows = []
        for n in sizes:
            result = run_size(size_dir(cache, n), scratch / f"out-{n}", args)
            shutil.rmtree(scratch / f"out-{n}", ignore_errors=True)
            result.update(passes=n, ms_per_pass=1e3 * result["seconds"] / n, load_after=os.getloadavg()[0])
            rows.append(result)
            print(f"{n:7d} {result['seconds']:8.1f} {result['ms_per_pass']:8.1f} "
                  f"{result['peak_rss_bytes'] / 2**20:13.0f}  {result['load_after']:.2f}"
                  + ("" if result["returncode"] == 0 else f"  FAILED (exit {result['returncode']})"))
            if result["returncode"] != 0:
                print(result["output_tail"])
        ok = [r for r in rows if r["returncode"] == 0]
        verdict = {}
        if len(ok) >= 2:
            verdict = judge(ok)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"backend": args.backend, "jobs": args.jobs, "rows": rows,
                                             "verdict": verdict}, indent=2) + "\n")
        return 0 if all(r["returncode"] == 0 for r in rows) else 1
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
