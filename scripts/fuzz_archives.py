#!/usr/bin/env python3
"""Seeded fuzz campaign against `uwbcl process`: mutated archives of every hostile kind, one run each.

For each case a valid pass archive is mutated (attributes removed, retyped, NaN or huge; datasets reshaped or
retyped; soft, external and looping links; virtual datasets and external storage; truncations; bit flips;
compression bombs; huge declared shapes; lossy filters; non-regular files) and `uwbcl process` runs over a tree
holding it beside a good cycle. Each case must end in: no traceback, no hang, no file opened outside the tree
(checked with strace), peak memory below a bound, and either a rejection naming the file in errors.csv or a
result equal to the unmutated file's.

    python scripts/fuzz_archives.py --cases 500 --seed 1            # the campaign (a few minutes per 100)
    python scripts/fuzz_archives.py --cases 40 --seed 3 --batch 40  # one run over 40 cases (fast)

Prints the counts by category and by outcome; exits 1 if any case broke a rule. tests/test_fuzz_archives.py
runs a bounded sample of the same generator on every CI run.
"""

from __future__ import annotations

import argparse
import collections
import csv
import dataclasses
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from uwbcl import archive, shift

KINDS = ("attr_removed", "attr_retyped", "attr_nonfinite", "attr_huge", "dataset_reshaped", "dataset_retyped",
         "soft_link", "soft_loop", "external_link", "external_passwd", "virtual", "external_storage", "truncated",
         "bit_flips", "bomb", "huge_declared", "lossy_filter", "fifo", "directory", "empty")
TIMEOUT_S = 120.0
RSS_LIMIT_KB = 1 << 20  # 1 GiB


@dataclasses.dataclass
class Case:
    index: int
    kind: str
    name: str  # file name in the tree
    detail: str = ""


def _objects(f: h5py.File) -> list[h5py.HLObject]:
    out = [f]
    f.visititems(lambda name, obj: out.append(obj))
    return out


def mutate(path: Path, kind: str, rng: np.random.Generator, outside: Path) -> str:
    """Damage the archive at `path` in place the way `kind` says; returns what was done."""
    if kind in ("truncated", "bit_flips", "empty"):
        data = bytearray(path.read_bytes())
        if kind == "empty":
            path.write_bytes(b"")
            return "empty file"
        if kind == "truncated":
            n = int(rng.integers(0, len(data)))
            path.write_bytes(bytes(data[:n]))
            return f"truncated to {n} of {len(data)} bytes"
        flips = int(rng.integers(1, 9))
        for _ in range(flips):
            i = int(rng.integers(0, len(data)))
            data[i] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(data))
        return f"{flips} bits flipped"
    if kind in ("fifo", "directory"):
        path.unlink()
        os.mkfifo(path) if kind == "fifo" else path.mkdir()
        return kind
    with h5py.File(path, "r+") as f:
        objs = _objects(f)
        if kind.startswith("attr"):
            obj = objs[int(rng.integers(0, len(objs)))]
            names = list(obj.attrs)
            if not names:
                return "no attribute"
            name = names[int(rng.integers(0, len(names)))]
            where = f"{obj.name}@{name}"
            if kind == "attr_removed":
                del obj.attrs[name]
            elif kind == "attr_retyped":
                choice = int(rng.integers(0, 4))
                obj.attrs[name] = ["text", 1.5, np.int8(3), np.array([1.0, 2.0])][choice]
            elif kind == "attr_nonfinite":
                obj.attrs[name] = [np.nan, np.inf, -np.inf][int(rng.integers(0, 3))]
            else:
                obj.attrs[name] = [1e300, -1e300, np.int64(2**62), np.zeros(5000)][int(rng.integers(0, 4))]
            return f"{kind} {where}"
        datasets = [o for o in objs if isinstance(o, h5py.Dataset)]
        ds = datasets[int(rng.integers(0, len(datasets)))]
        name, attrs = ds.name, dict(ds.attrs)
        parent = ds.parent
        base = name.rsplit("/", 1)[1]

        def recreate(**kw):
            del parent[base]
            new = parent.create_dataset(base, **kw)
            for k, v in attrs.items():
                new.attrs[k] = v

        if kind == "dataset_reshaped":
            data = ds[()]
            recreate(data=data.reshape(-1)[: max(1, data.size // 2)])
        elif kind == "dataset_retyped":
            data = ds[()]
            recreate(data=(np.abs(data) if np.iscomplexobj(data) else data).astype(np.int8))
        elif kind == "soft_link":
            other = datasets[(datasets.index(ds) + 1) % len(datasets)].name
            del parent[base]
            parent[base] = h5py.SoftLink(other)
        elif kind == "soft_loop":
            del parent[base]
            parent[base] = h5py.SoftLink(name)
        elif kind == "external_link":
            del parent[base]
            parent[base] = h5py.ExternalLink(str(outside), name)
        elif kind == "external_passwd":
            del parent[base]
            parent[base] = h5py.ExternalLink("/etc/passwd", "/x")
        elif kind == "virtual":
            shape = ds.shape
            layout = h5py.VirtualLayout(shape=shape, dtype=ds.dtype)
            layout[...] = h5py.VirtualSource(str(outside), name, shape=shape)
            del parent[base]
            new = parent.create_virtual_dataset(base, layout)
            for k, v in attrs.items():
                new.attrs[k] = v
        elif kind == "external_storage":
            raw = outside.with_suffix(".raw")
            recreate(shape=ds.shape, dtype=ds.dtype, external=[(str(raw), 0, h5py.h5f.UNLIMITED)])
        elif kind == "bomb":  # zeros written through gzip: ~32 MB per row in a few kB
            rows = int(rng.integers(1, 9))
            recreate(shape=(rows, 1 << 22), dtype="c8", chunks=(1, 1 << 20), compression="gzip", compression_opts=9)
            row = np.zeros(1 << 22, dtype="c8")
            for i in range(rows):
                parent[base][i] = row
        elif kind == "huge_declared":
            recreate(shape=(10**6, 10**6), dtype="c8", chunks=(64, 64))
        elif kind == "lossy_filter":
            data = ds[()]
            if data.dtype.kind not in "fi":
                return "not a real dataset: " + name
            recreate(data=data, scaleoffset=3 if data.dtype.kind == "f" else 0, chunks=data.shape)
        return f"{kind} {name}"


def opened_outside(strace_log: Path, allowed: list[Path]) -> list[str]:
    """Paths the run opened that lie under none of `allowed` and are not the interpreter's own files."""
    ok = [str(p.resolve()) for p in allowed]
    system = ("/usr/", "/lib", "/etc/ld.so", "/proc/", "/sys/", "/dev/", sys.prefix, sys.base_prefix,
              os.path.dirname(os.__file__), str(Path(archive.__file__).resolve().parents[1]), "/tmp/", "/etc/localtime",
              "/etc/nsswitch", "/etc/host", "/etc/resolv", "/etc/ssl", "/etc/OpenCL", "/root/.cache", "/etc/pocl")
    out = []
    for line in strace_log.read_text(errors="replace").splitlines():
        m = re.search(r'open(?:at)?\((?:AT_FDCWD|\d+), "([^"]+)"', line)
        if not m or "ENOENT" in line:
            continue
        p = m.group(1)
        if p.startswith(tuple(ok)) or p.startswith(system) or not p.startswith("/"):
            continue
        out.append(p)
    return sorted(set(out))


def run_batch(cases: list[Case], good: Path, rng: np.random.Generator, work: Path) -> dict[int, str]:
    """One `uwbcl process` over a tree with `cases` mutated copies of `good`; {case index: outcome}."""
    tree, out = work / "tree", work / "out"
    shutil.rmtree(work, ignore_errors=True)
    tree.mkdir(parents=True)
    outside = work / "outside.h5"
    shutil.copy(good, outside)
    shutil.copy(good, tree / "good.h5")
    originals = {}
    for c in cases:
        path = tree / c.name
        shutil.copy(good, path)
        try:
            c.detail = mutate(path, c.kind, rng, outside)
        except Exception as e:  # noqa: BLE001 - h5py may refuse a mutation: the case is then the unmutated file
            c.detail = f"mutation not applied ({type(e).__name__})"
        originals[c.index] = path
    log = work / "strace.log"
    cmd = [sys.executable, "-m", "uwbcl.cli", "process", str(tree), "--out", str(out), "--backend", "numpy",
           "--jobs", "1", "--no-progress"]
    if shutil.which("strace"):
        cmd = ["strace", "-f", "-qq", "-e", "trace=open,openat", "-o", str(log), *cmd]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S * max(1, len(cases) / 20))
    except subprocess.TimeoutExpired:
        return {c.index: "HANG" for c in cases}
    elapsed = time.monotonic() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    broken = []
    if "Traceback" in proc.stderr:
        broken.append("TRACEBACK")
    if proc.returncode not in (0, 1):
        broken.append(f"EXIT_{proc.returncode}")
    if rss > RSS_LIMIT_KB and rss > before:
        broken.append("MEMORY")
    outside_opens = opened_outside(log, [tree, out, work]) if log.exists() else []
    if any(p == str(outside.resolve()) or p.startswith("/etc/passwd") for p in outside_opens):
        broken.append("OPENED_OUTSIDE")
    named = {}
    errors = out / "errors.csv"
    if errors.exists():
        with errors.open(encoding="utf-8") as f:
            for row in csv.DictReader(f):
                for name in row["file"].split("; "):
                    named[name] = row["kind"]
    good_echo = archive.read_pass(good).echo
    result = {}
    for c in cases:
        if broken:
            result[c.index] = "+".join(broken)
        elif c.name in named:
            result[c.index] = f"rejected:{named[c.name]}"
        elif originals[c.index].is_dir():
            result[c.index] = "rejected:a_directory_not_a_file"  # searched as a directory, never read
        else:
            try:
                same = np.array_equal(archive.read_pass(originals[c.index]).echo, good_echo)
            except Exception:  # noqa: BLE001
                same = False
            result[c.index] = "accepted_unchanged" if same else "accepted_changed"
    print(f"  batch of {len(cases)}: exit {proc.returncode}, {elapsed:.1f} s, peak RSS {rss / 1024:.0f} MiB",
          file=sys.stderr)
    return result


def make_good(work: Path) -> Path:
    """A small valid pass (the first pass of a simulated shift, shortened range gate)."""
    scan = next(iter(shift.simulate_shift(shift.ShiftConfig(rigs=1, cycles=1, seed=1))))
    return archive.write_pass(work / "good-template.h5", scan)


def campaign(n_cases: int, seed: int, batch: int, work: Path) -> tuple[list[Case], dict[int, str]]:
    rng = np.random.default_rng(seed)
    work.mkdir(parents=True, exist_ok=True)
    good = make_good(work)
    cases = [Case(i, KINDS[i % len(KINDS)] if i < len(KINDS) else KINDS[int(rng.integers(0, len(KINDS)))],
                  f"case{i:04d}.h5") for i in range(n_cases)]
    outcome: dict[int, str] = {}
    for start in range(0, n_cases, batch):
        chunk = cases[start:start + batch]
        outcome.update(run_batch(chunk, good, rng, work / "run"))
    return cases, outcome


BROKEN = ("HANG", "TRACEBACK", "MEMORY", "OPENED_OUTSIDE", "EXIT_")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--batch", type=int, default=25, help="cases per `uwbcl process` run")
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="uwbcl-fuzz-"))
    cases, outcome = campaign(args.cases, args.seed, args.batch, work)
    table: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for c in cases:
        o = outcome[c.index]
        table[c.kind]["broken" if o.startswith(BROKEN) else o.split(":")[0]] += 1
    print(f"{len(cases)} cases, seed {args.seed}, strace {'on' if shutil.which('strace') else 'OFF'}")
    print(f"{'kind':18s} {'cases':>5s} {'rejected':>8s} {'unchanged':>9s} {'changed':>7s} {'broken':>6s}")
    for kind in KINDS:
        t = table[kind]
        print(f"{kind:18s} {sum(t.values()):5d} {t['rejected']:8d} {t['accepted_unchanged']:9d} "
              f"{t['accepted_changed']:7d} {t['broken']:6d}")
    broken = [c for c in cases if outcome[c.index].startswith(BROKEN)]
    for c in broken[:20]:
        print(f"BROKEN case {c.index} {c.kind} ({c.detail}): {outcome[c.index]}")
    print(f"total: {sum(1 for c in cases if outcome[c.index].startswith('rejected'))} rejected by name, "
          f"{sum(1 for c in cases if outcome[c.index] == 'accepted_unchanged')} accepted unchanged, "
          f"{sum(1 for c in cases if outcome[c.index] == 'accepted_changed')} accepted with changed values, "
          f"{len(broken)} broke a rule")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
