"""Acceptance study of issue 4: `uwbcl process` on simulated production shifts.

Phases (all by default):
  clean  simulate RIGS x CYCLES at SNR / speed jitter, process it, compare with truth.csv: per-cycle retreat
         and creep RMS error, the largest error of an unflagged cycle, cumulative drift per rig;
  bad    the same archive plus a dozen bad files (junk, truncated, corrupt, missing dataset / attribute, NaN
         echo, duplicate, single height, mismatched parameters): every good row identical to the clean run,
         every bad file named in errors.csv, exit code non-zero, no input modified;
  kill   kill `uwbcl process` (SIGKILL) at random points three times, restart, and compare the final outputs
         byte for byte with the uninterrupted clean run.

    python scripts/shift_study.py --work /tmp/shift-study --jobs 2
    python scripts/shift_study.py --work /tmp/shift-study --rigs 1 --cycles 10 --phases clean   # quick look

The archives are kept in WORK and reused when their parameters match (WORK/params.json).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

OUTPUTS = ("displacements.csv", "displacements.h5", "targets.csv", "errors.csv")


def uwbcl(*args: str, env_extra: dict | None = None) -> list[str]:
    return [sys.executable, "-m", "uwbcl.cli", *args]


def run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    return subprocess.run(cmd, env=env, capture_output=True, text=True, check=False, **kw)


def simulate(args, work: Path) -> Path:
    clean = work / "archive"
    params = {k: getattr(args, k) for k in ("rigs", "cycles", "seed", "snr_db", "speed_jitter")}
    stamp = work / "params.json"
    if clean.is_dir() and stamp.exists() and json.loads(stamp.read_text()) == params:
        print(f"reusing {clean}")
        return clean
    shutil.rmtree(clean, ignore_errors=True)
    t = time.perf_counter()
    r = run(uwbcl("simulate", str(clean), "--scenario", "shift", "--rigs", str(args.rigs), "--cycles",
                  str(args.cycles), "--seed", str(args.seed), "--snr-db", str(args.snr_db), "--speed-jitter",
                  str(args.speed_jitter)))
    if r.returncode:
        sys.exit(f"simulate failed:\n{r.stderr}")
    print(r.stdout.strip(), f"({time.perf_counter() - t:.0f} s)")
    stamp.write_text(json.dumps(params))
    return clean


def process_cmd(args, archive_dir: Path, out: Path) -> list[str]:
    return uwbcl("process", str(archive_dir), "--out", str(out), "--backend", args.backend, "--jobs",
                 str(args.jobs), "--web-depth", str(args.web_depth), "--no-progress")


def read_csv(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


def evaluate(out: Path, truth_csv: Path) -> dict:
    truth = {(r["rig_id"], int(r["cycle"])): np.array([float(r["rig_x_m"]), float(r["rig_y_m"]),
                                                       float(r["rig_z_m"])]) for r in read_csv(truth_csv)}
    rows = read_csv(out / "displacements.csv")
    errs, ok, trusted = [], [], []
    cum_final = {}
    origin: dict[tuple[str, int], int] = {}  # (rig, chain) -> the cycle its cumulative values count from
    for r in rows:
        rig, c, c0, chain = r["rig_id"], int(r["cycle"]), int(r["from_cycle"]), int(r["chain"])
        est = np.array([float(r["retreat_m"]), float(r["creep_m"]), float(r["vertical_m"])])
        true = truth[(rig, c)] - truth[(rig, c0)]
        errs.append(est - true)
        ok.append(r["status"] == "ok")
        trusted.append(r["status"] in ("ok", "low_confidence"))
        cum = np.array([float(r["cumulative_retreat_m"]), float(r["cumulative_creep_m"])])
        if (rig, chain) not in origin:
            origin[(rig, chain)] = min(k[1] for k in truth if k[0] == rig) if chain == 0 else c
        if np.all(np.isfinite(cum)):
            start = origin[(rig, chain)]
            cum_final[f"{rig} chain {chain}"] = (start, c, cum - (truth[(rig, c)] - truth[(rig, start)])[:2])
    errs = np.array(errs).reshape(-1, 3)
    ok = np.array(ok, dtype=bool)
    trusted = np.array(trusted, dtype=bool)
    finite = np.all(np.isfinite(errs), axis=1)

    def rms(a):
        return float(np.sqrt(np.mean(a**2))) if a.size else math.nan

    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    return {
        "rows": len(rows), "statuses": statuses,
        "rms_ok_mm": [1e3 * rms(errs[ok, a]) for a in range(3)],
        "rms_trusted_mm": [1e3 * rms(errs[trusted, a]) for a in range(3)],
        "rms_all_finite_mm": [1e3 * rms(errs[finite, a]) for a in range(3)],
        "max_abs_ok_mm": [1e3 * float(np.max(np.abs(errs[ok, a]))) if ok.any() else math.nan
                          for a in range(3)],
        "max_abs_flagged_mm": [1e3 * float(np.nanmax(np.abs(errs[~ok & finite, a])))
                               if (~ok & finite).any() else math.nan for a in range(3)],
        "unflagged_over_50mm": int(np.sum(ok & np.any(np.abs(errs[:, :2]) > 0.05, axis=1))),
        "cumulative_drift_mm": {k: (c0, c, [round(1e3 * v, 2) for v in d])
                                for k, (c0, c, d) in cum_final.items()},
    }


def print_eval(title: str, e: dict) -> None:
    print(f"\n== {title}: {e['rows']} displacements, statuses {e['statuses']}")

    def f(v):
        return " / ".join(f"{x:.2f}" for x in v)

    print(f"  RMS error, status ok      (retreat / creep / vertical, mm): {f(e['rms_ok_mm'])}")
    print(f"  RMS error, ok + low_conf. (retreat / creep / vertical, mm): {f(e['rms_trusted_mm'])}")
    print(f"  RMS error, every estimate (retreat / creep / vertical, mm): {f(e['rms_all_finite_mm'])}")
    print(f"  max |error|, status ok    (mm): {f(e['max_abs_ok_mm'])}")
    print(f"  max |error|, flagged      (mm): {f(e['max_abs_flagged_mm'])}")
    print(f"  unflagged rows with a retreat or creep error > 50 mm: {e['unflagged_over_50mm']}")
    for rig, (c0, c, d) in sorted(e["cumulative_drift_mm"].items()):
        print(f"  {rig}: cumulative drift over cycles {c0}-{c} (retreat, creep): {d[0]:+.2f}, {d[1]:+.2f} mm")


def phase_clean(args, work: Path, archive_dir: Path) -> dict:
    out = work / "out-clean"
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    r = run(process_cmd(args, archive_dir, out))
    wall = time.perf_counter() - t
    print(f"\nclean run: exit {r.returncode}, {wall:.0f} s; {r.stdout.strip()}")
    e = evaluate(out, archive_dir / "truth.csv")
    print_eval("clean", e)
    e["wall_s"] = wall
    e["exit"] = r.returncode
    return e


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def make_bad_files(archive_dir: Path, bad_dir: Path) -> list[str]:
    """Copy the archive to bad_dir and add twelve bad files; returns their paths relative to bad_dir."""
    shutil.copytree(archive_dir, bad_dir)
    passes = sorted(p for p in bad_dir.rglob("*.h5"))
    extra = bad_dir / "incoming"
    extra.mkdir()
    bad = []

    def add(name: str, data: bytes | None = None, src: Path | None = None) -> Path:
        path = extra / name
        if src is not None:
            shutil.copyfile(src, path)
        else:
            path.write_bytes(data)
        bad.append(path.relative_to(bad_dir).as_posix())
        return path

    rng = np.random.default_rng(7)
    add("junk.h5", rng.bytes(4096))
    add("notes.h5", b"operator notes: rail jammed at 0.6 m, rerun\n")
    whole = passes[0].read_bytes()
    add("truncated_half.h5", whole[: len(whole) // 2])
    add("truncated_1k.h5", whole[:1024])
    p = add("corrupt_echo.h5", src=passes[1])
    with h5py.File(p, "r") as f:
        offset = f["/echo"].id.get_offset() if f["/echo"].chunks is None else \
            f["/echo"].id.get_chunk_info(0).byte_offset
    data = bytearray(p.read_bytes())
    for k in range(64):
        data[offset + 200 + k] ^= 0xFF
    p.write_bytes(bytes(data))
    p = add("missing_dataset.h5", src=passes[2])
    with h5py.File(p, "r+") as f:
        del f["/pulses/time_s"]
    p = add("missing_attribute.h5", src=passes[3])
    with h5py.File(p, "r+") as f:
        del f["radar"].attrs["sample_rate_hz"]
    p = add("nan_echo.h5", src=passes[4])
    with h5py.File(p, "r+") as f:
        echo = f["/echo"][()]
        echo[10, 20] = np.nan
        f["/echo"][...] = echo
    dup_dir = bad_dir / "copied-twice"
    dup_dir.mkdir()
    shutil.copyfile(passes[5], dup_dir / passes[5].name)
    bad.append((dup_dir / passes[5].name).relative_to(bad_dir).as_posix())
    # A cycle number nobody else uses: one height only, then two passes that disagree on the radar.
    p = add("lonely_height.h5", src=passes[6])
    with h5py.File(p, "r+") as f:
        f.attrs["cycle"] = np.int64(9000)
    for i, src in enumerate(passes[8:10]):
        p = add(f"mismatch_{i}.h5", src=src)
        with h5py.File(p, "r+") as f:
            f.attrs["cycle"] = np.int64(9001)
            if i == 1:
                f["radar"].attrs["carrier_frequency_hz"] = np.float64(4.1e9)
    return bad


def phase_bad(args, work: Path, archive_dir: Path) -> dict:
    bad_dir = work / "archive-bad"
    shutil.rmtree(bad_dir, ignore_errors=True)
    bad = make_bad_files(archive_dir, bad_dir)
    before = {p: sha(p) for p in bad_dir.rglob("*") if p.is_file()}
    out = work / "out-bad"
    shutil.rmtree(out, ignore_errors=True)
    # Reuse the clean run's per-pass cache: the good files are byte-identical, so only the bad ones are new.
    shutil.copytree(work / "out-clean" / ".uwbcl-cache", out / ".uwbcl-cache")
    r = run(process_cmd(args, bad_dir, out))
    after = {p: sha(p) for p in bad_dir.rglob("*") if p.is_file()}
    errors = read_csv(out / "errors.csv")
    named = {f for e in errors for f in e["file"].split("; ")}
    missing = [b for b in bad if b not in named]
    clean_rows = read_csv(work / "out-clean" / "displacements.csv")
    bad_rows = read_csv(out / "displacements.csv")
    same = clean_rows == bad_rows
    same_targets = (work / "out-clean" / "targets.csv").read_bytes() == (out / "targets.csv").read_bytes()
    print(f"\n== bad files: {len(bad)} added; exit code {r.returncode}; {len(errors)} rows in errors.csv")
    for e in errors:
        print(f"  {e['kind']:<22} {e['file']}: {e['reason'][:110]}")
    print(f"  every bad file named in errors.csv: {not missing} {missing or ''}")
    print(f"  displacements.csv identical to the clean run: {same} ({len(bad_rows)} rows); "
          f"targets.csv identical: {same_targets}")
    print(f"  inputs unmodified: {before == after}")
    return {"exit": r.returncode, "all_named": not missing, "identical": same and same_targets,
            "inputs_unmodified": before == after}


def phase_kill(args, work: Path, archive_dir: Path, clean_wall_s: float) -> dict:
    out = work / "out-kill"
    shutil.rmtree(out, ignore_errors=True)
    rnd = random.Random(args.seed + 1)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    kills = []
    for _ in range(3):
        delay = rnd.uniform(0.1, 0.9) * clean_wall_s / 3
        proc = subprocess.Popen(process_cmd(args, archive_dir, out), env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        time.sleep(delay)
        finished = proc.poll() is not None
        if not finished:
            os.killpg(proc.pid, signal.SIGKILL)  # the whole session: the CLI and its worker processes
        proc.wait()
        cached = len(list((out / ".uwbcl-cache").rglob("*.json"))) if (out / ".uwbcl-cache").exists() else 0
        kills.append((round(delay, 1), finished, cached))
        print(f"  killed after {delay:.1f} s (finished before: {finished}); {cached} passes cached")
    r = run(process_cmd(args, archive_dir, out))
    identical = {name: (out / name).read_bytes() == (work / "out-clean" / name).read_bytes()
                 for name in OUTPUTS}
    print(f"\n== kill/restart: kills {kills}; final exit {r.returncode}; byte-identical: {identical}")
    return {"kills": kills, "identical": all(identical.values())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", default="/tmp/uwbcl-shift-study")
    ap.add_argument("--rigs", type=int, default=3)
    ap.add_argument("--cycles", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--snr-db", type=float, default=10.0)
    ap.add_argument("--speed-jitter", type=float, default=0.1)
    ap.add_argument("--web-depth", type=float, default=0.9)
    ap.add_argument("--backend", default="numpy")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--phases", default="clean,bad,kill")
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    phases = args.phases.split(",")
    archive_dir = simulate(args, work)
    results = {}
    results["clean"] = phase_clean(args, work, archive_dir)
    if "bad" in phases:
        results["bad"] = phase_bad(args, work, archive_dir)
    if "kill" in phases:
        results["kill"] = phase_kill(args, work, archive_dir, results["clean"]["wall_s"])
    (work / "results.json").write_text(json.dumps(results, indent=2, default=str))
    print(f"\nresults in {work / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
