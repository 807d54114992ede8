#!/usr/bin/env python3
"""Throughput of `uwbcl process --scheduler local:N` against the local `--jobs N` run on the same passes.

Passes: a simulated production shift (`uwbcl simulate --scenario shift`: 4 rigs x PASSES/8 cycles x 2
heights), written once into WORK and reused. Legs, each a fresh Python process running `uwbcl process` as the
command line does (batch.process_directory, the cache off, a new output directory):
  local  --jobs N: N spawned worker processes (each starts its own focuser)
  dask   --scheduler local:N: a LocalCluster of N single-threaded workers started by uwbcl, the workers
         checked and their focusers started (cluster.connect), then the run, then the cluster closed
The legs alternate (local, dask, then dask, local, ...) ROUNDS times per backend, so a machine whose load
drifts loads both alike; the ratios are taken within a round. Reported per leg: the whole run (the process's
own start excluded), the cluster's start-up and close, the run itself, and the steady throughput (passes per
second between the first and the last pass done). The dask leg also times empty tasks through the same client
(the scheduler's own cost per task) and says how many passes went into each task. Every leg's outputs must be
byte-identical to the first local leg's (exit 1 otherwise).

    POCL_DEVICES=pthread POCL_MAX_PTHREAD_COUNT=2 POCL_CPU_MAX_CU_COUNT=2 \\
        python scripts/cluster_study.py --work /tmp/cluster-study --passes 64 --backends numpy,opencl
    python scripts/cluster_study.py --passes 16 --backends numpy --rounds 1       # a quick look
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

OUTPUTS = ("displacements.csv", "displacements.h5", "targets.csv", "errors.csv")
EMPTY_TASKS = 200


def write_passes(work: Path, n_passes: int) -> Path:
    """WORK/in-N: the shift's archives, written once."""
    from uwbcl import shift

    src = work / f"in-{n_passes}"
    if (src / "truth.csv").exists():
        return src
    if src.exists():
        shutil.rmtree(src)
    shift.write_shift(src, shift.ShiftConfig(rigs=4, cycles=n_passes // 8, seed=11))
    return src


def run_leg(leg: str, backend: str, workers: int, src: Path, out: Path) -> dict:
    """In this process: one `uwbcl process` run; its timings."""
    from uwbcl import batch, cluster
    from uwbcl.records import AssociationSettings, BatchOptions, ProcessingSettings

    settings = ProcessingSettings(backend=backend,
                                  association=AssociationSettings(prior_advance_m=(0.9, 0.0, 0.0)))
    done_at: list[float] = []
    options = BatchOptions(jobs=workers if leg == "local" else None, cache=False, progress=False,
                           on_pass_done=lambda n: done_at.append(time.perf_counter()))
    t0 = time.perf_counter()
    timing: dict = {}
    if leg == "local":
        t1 = time.perf_counter()
        report = batch.process_directory(src, out, settings, options)
        t2 = t3 = time.perf_counter()
    else:
        with cluster.connect(f"local:{workers}", settings) as runner:
            t1 = time.perf_counter()
            report = batch.process_directory(src, out, settings, options, runner)
            t2 = time.perf_counter()
            timing.update(empty_task_ms(runner), passes_per_task=cluster.passes_per_task(
                report.n_detected, runner.n_threads()))
        t3 = time.perf_counter()
    first = max(k for k, t in enumerate(done_at) if t <= done_at[0] + 0.01)  # the passes of the first task
    span_s = done_at[-1] - done_at[first]
    steady = (len(done_at) - 1 - first) / span_s if span_s > 0 else float("nan")
    return {"leg": leg, "backend": backend, "passes": report.n_detected, "errors": len(report.errors),
            "total_s": t3 - t0, "startup_s": t1 - t0, "run_s": t2 - t1, "close_s": t3 - t2,
            "steady_passes_per_s": steady, **timing}


def empty_task_ms(runner) -> dict:
    """The scheduler's own cost: EMPTY_TASKS tasks that focus nothing, through the run's client, one by one
    in flight per worker thread as the run submits them (all at once)."""
    from distributed import as_completed

    from uwbcl import cluster

    t = time.perf_counter()
    futures = [runner.client.submit(cluster.detect_passes, [], None, runner.fingerprint, pure=False)
               for _ in range(EMPTY_TASKS)]
    for _ in as_completed(futures, loop=runner.client.loop):
        pass
    return {"empty_task_ms": (time.perf_counter() - t) / EMPTY_TASKS * 1e3}


def leg_subprocess(leg: str, backend: str, workers: int, src: Path, out: Path) -> dict:
    """One leg in a fresh Python process (nothing warm from an earlier leg)."""
    if out.exists():
        shutil.rmtree(out)
    cmd = [sys.executable, __file__, "--leg", leg, "--backends", backend, "--workers", str(workers),
           "--src", str(src), "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{leg}/{backend} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def outputs_of(out: Path) -> dict[str, bytes]:
    return {name: (out / name).read_bytes() for name in OUTPUTS}


def print_leg(r: dict) -> None:
    extra = (f", startup {r['startup_s']:.2f} s, close {r['close_s']:.2f} s, "
             f"{r['passes_per_task']} passes/task, empty task {r['empty_task_ms']:.2f} ms"
             if r["leg"] == "dask" else "")
    print(f"  {r['leg']:5s} total {r['total_s']:6.2f} s  run {r['run_s']:6.2f} s  "
          f"{r['passes'] / r['total_s']:5.2f} passes/s overall, {r['steady_passes_per_s']:5.2f} steady"
          + extra)


def study(args) -> int:
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    src = write_passes(work, args.passes)
    print(f"{args.passes} shift passes in {src}; {args.workers} workers; cores here: {os.cpu_count()}, "
          f"load {os.getloadavg()[0]:.1f}; POCL_MAX_PTHREAD_COUNT={os.environ.get('POCL_MAX_PTHREAD_COUNT')}")
    results, failures = [], []
    for backend in args.backends.split(","):
        reference = None
        for k in range(args.rounds):
            order = ("local", "dask") if k % 2 == 0 else ("dask", "local")
            legs = {}
            print(f"{backend} round {k + 1} ({' then '.join(order)}), load {os.getloadavg()[0]:.1f}:")
            for leg in order:
                out = work / f"out-{backend}-{leg}"
                r = legs[leg] = leg_subprocess(leg, backend, args.workers, src, out)
                print_leg(r)
                got = outputs_of(out)
                reference = reference or got
                if got != reference:
                    failures.append(f"{backend} round {k + 1} {leg}: outputs differ from the first local run")
            ratio_total = legs["local"]["total_s"] / legs["dask"]["total_s"]
            ratio_run = legs["local"]["run_s"] / legs["dask"]["run_s"]
            ratio_steady = legs["dask"]["steady_passes_per_s"] / legs["local"]["steady_passes_per_s"]
            print(f"  dask/local throughput: {ratio_total:.3f} whole run, {ratio_run:.3f} run without the "
                  f"cluster's start and close, {ratio_steady:.3f} steady")
            results.append({"backend": backend, "round": k + 1, "legs": legs, "ratio_total": ratio_total,
                            "ratio_run": ratio_run, "ratio_steady": ratio_steady})
    if args.json:
        Path(args.json).write_text(json.dumps({"passes": args.passes, "workers": args.workers,
                                               "results": results}, indent=2) + "\n")
    for f in failures:
        print(f"FAIL: {f}", file=sys.stderr)
    return 1 if failures else 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default="/tmp/uwbcl-cluster-study",
                   help="archives and outputs (the archives are reused)")
    p.add_argument("--passes", type=int, default=64, help="shift passes, a multiple of 8 (default 64)")
    p.add_argument("--backends", default="numpy,opencl")
    p.add_argument("--workers", type=int, default=2, help="--jobs N and local:N (default 2)")
    p.add_argument("--rounds", type=int, default=2, help="alternating local/dask rounds per backend")
    p.add_argument("--json", help="write the results here")
    p.add_argument("--leg", choices=("local", "dask"), help=argparse.SUPPRESS)
    p.add_argument("--src", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.passes < 8 or args.passes % 8:
        p.error("--passes must be a positive multiple of 8")
    if args.leg:
        print(json.dumps(run_leg(args.leg, args.backends, args.workers, Path(args.src), Path(args.out))))
        return 0
    return study(args)


if __name__ == "__main__":
    sys.exit(main())
