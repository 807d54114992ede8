#!/usr/bin/env python3
"""Seeded fuzz campaign against `uwbcl process`: mutated archives of every hostile kind, one run each.

For each case a valid pass archive is mutated (attributes removed, retyped, NaN or huge; datasets reshaped or
retyped; soft, external and looping links; virtual datasets and external storage; truncations; bit flips;
compression bombs; huge declared shapes; lossy filters; non-regular files) and `uwbcl process` runs over a
tree holding it beside a good cycle. Each case must end in: no traceback, no hang, no file opened outside the
tree (checked with strace), peak memory below a bound, and either a rejection naming the file in errors.csv or
a result equal to the unmutated file's.

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
         "soft_link", "soft_loop", "external_link", "external_passwd", "virtual", "external_storage",
         "truncated", "bit_flips", "bomb", "huge_declared", "lossy_filter", "fifo", "directory", "empty",
         "symlink_loop", "outside_symlink", "broken_symlink")
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


# ---------------------------------------------------------------------------------------- mutations
# Each mutation draws from `rng` in a fixed order, so a seed names the same campaign every time.


def _empty(path: Path, rng: np.random.Generator) -> str:
    path.write_bytes(b"")
    return "empty file"


def _truncate(path: Path, rng: np.random.Generator) -> str:
    data = path.read_bytes()
    n = int(rng.integers(0, len(data)))
    path.write_bytes(data[:n])
    return f"truncated to {n} of {len(data)} bytes"


def _flip_bits(path: Path, rng: np.random.Generator) -> str:
    data = bytearray(path.read_bytes())
    flips = int(rng.integers(1, 9))
    for _ in range(flips):
        i = int(rng.integers(0, len(data)))
        data[i] ^= 1 << int(rng.integers(0, 8))
    path.write_bytes(bytes(data))
    return f"{flips} bits flipped"


def _fifo(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    os.mkfifo(path)
    return "fifo"


def _directory(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    path.mkdir()
    return "directory"


def _symlink_loop(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    os.symlink(path.name, path)
    return "a symbolic link to itself"


def _outside_symlink(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    os.symlink(path.parent.parent / "outside.h5", path)  # a valid archive outside the tree
    return "a symbolic link to an archive outside the tree"


def _broken_symlink(path: Path, rng: np.random.Generator) -> str:
    path.unlink()
    os.symlink("nowhere.h5", path)
    return "a symbolic link to nothing"


# Mutations of the file as a whole, without opening it as HDF5.
FILE_MUTATIONS = {"truncated": _truncate, "bit_flips": _flip_bits, "empty": _empty, "fifo": _fifo,
                  "directory": _directory, "symlink_loop": _symlink_loop, "outside_symlink": _outside_symlink,
                  "broken_symlink": _broken_symlink}


def _remove_attr(obj: h5py.HLObject, name: str, rng: np.random.Generator) -> None:
    del obj.attrs[name]


def _retype_attr(obj: h5py.HLObject, name: str, rng: np.random.Generator) -> None:
    choice = int(rng.integers(0, 4))
    obj.attrs[name] = ["text", 1.5, np.int8(3), np.array([1.0, 2.0])][choice]


def _nonfinite_attr(obj: h5py.HLObject, name: str, rng: np.random.Generator) -> None:
    obj.attrs[name] = [np.nan, np.inf, -np.inf][int(rng.integers(0, 3))]


def _huge_attr(obj: h5py.HLObject, name: str, rng: np.random.Generator) -> None:
    obj.attrs[name] = [1e300, -1e300, np.int64(2**62), np.zeros(5000)][int(rng.integers(0, 4))]


# Mutations of one attribute of a random object; any other "attr*" kind makes it huge.
ATTR_MUTATIONS = {"attr_removed": _remove_attr, "attr_retyped": _retype_attr,
                  "attr_nonfinite": _nonfinite_attr}


def _mutate_attr(objs: list[h5py.HLObject], kind: str, rng: np.random.Generator) -> str:
    obj = objs[int(rng.integers(0, len(objs)))]
    names = list(obj.attrs)
    if not names:
        return "no attribute"
    name = names[int(rng.integers(0, len(names)))]
    where = f"{obj.name}@{name}"
    ATTR_MUTATIONS.get(kind, _huge_attr)(obj, name, rng)
    return f"{kind} {where}"


@dataclasses.dataclass
class _Target:
    """The dataset a mutation replaces, with what is needed to put something else in its place."""

    ds: h5py.Dataset
    datasets: list[h5py.Dataset]
    outside: Path

    def __post_init__(self) -> None:
        self.name, self.attrs = self.ds.name, dict(self.ds.attrs)
        self.parent = self.ds.parent
        self.base = self.name.rsplit("/", 1)[1]

    def link(self, link: h5py.SoftLink | h5py.ExternalLink) -> None:
        del self.parent[self.base]
        self.parent[self.base] = link

    def recreate(self, **kw) -> h5py.Dataset:
        del self.parent[self.base]
        new = self.parent.create_dataset(self.base, **kw)
        for k, v in self.attrs.items():
            new.attrs[k] = v
        return new


def _reshape(t: _Target, rng: np.random.Generator) -> str | None:
    data = t.ds[()]
    t.recreate(data=data.reshape(-1)[: max(1, data.size // 2)])
    return None


def _retype(t: _Target, rng: np.random.Generator) -> str | None:
    data = t.ds[()]
    t.recreate(data=(np.abs(data) if np.iscomplexobj(data) else data).astype(np.int8))
    return None


def _soft_link(t: _Target, rng: np.random.Generator) -> str | None:
    other = t.datasets[(t.datasets.index(t.ds) + 1) % len(t.datasets)].name
    t.link(h5py.SoftLink(other))
    return None


def _soft_loop(t: _Target, rng: np.random.Generator) -> str | None:
    t.link(h5py.SoftLink(t.name))
    return None


def _external_link(t: _Target, rng: np.random.Generator) -> str | None:
    t.link(h5py.ExternalLink(str(t.outside), t.name))
    return None


def _external_passwd(t: _Target, rng: np.random.Generator) -> str | None:
    t.link(h5py.ExternalLink("/etc/passwd", "/x"))
    return None


def _virtual(t: _Target, rng: np.random.Generator) -> str | None:
    shape = t.ds.shape
    layout = h5py.VirtualLayout(shape=shape, dtype=t.ds.dtype)
    layout[...] = h5py.VirtualSource(str(t.outside), t.name, shape=shape)
    del t.parent[t.base]
    new = t.parent.create_virtual_dataset(t.base, layout)
    for k, v in t.attrs.items():
        new.attrs[k] = v
    return None


def _external_storage(t: _Target, rng: np.random.Generator) -> str | None:
    raw = t.outside.with_suffix(".raw")
    t.recreate(shape=t.ds.shape, dtype=t.ds.dtype, external=[(str(raw), 0, h5py.h5f.UNLIMITED)])
    return None


def _bomb(t: _Target, rng: np.random.Generator) -> str | None:
    """Zeros written through gzip: ~32 MB per row in a few kB."""
    rows = int(rng.integers(1, 9))
    t.recreate(shape=(rows, 1 << 22), dtype="c8", chunks=(1, 1 << 20), compression="gzip",
               compression_opts=9)
    row = np.zeros(1 << 22, dtype="c8")
    for i in range(rows):
        t.parent[t.base][i] = row
    return None


def _huge_declared(t: _Target, rng: np.random.Generator) -> str | None:
    t.recreate(shape=(10**6, 10**6), dtype="c8", chunks=(64, 64))
    return None


def _lossy_filter(t: _Target, rng: np.random.Generator) -> str | None:
    data = t.ds[()]
    if data.dtype.kind not in "fi":
        return "not a real dataset: " + t.name
    t.recreate(data=data, scaleoffset=3 if data.dtype.kind == "f" else 0, chunks=data.shape)
    return None


# Mutations of one random dataset; each returns None or, when it could not apply, what happened instead.
DATASET_MUTATIONS = {
    "dataset_reshaped": _reshape, "dataset_retyped": _retype, "soft_link": _soft_link,
    "soft_loop": _soft_loop,
    "external_link": _external_link, "external_passwd": _external_passwd, "virtual": _virtual,
    "external_storage": _external_storage, "bomb": _bomb, "huge_declared": _huge_declared,
    "lossy_filter": _lossy_filter,
}


def _mutate_dataset(objs: list[h5py.HLObject], kind: str, rng: np.random.Generator, outside: Path) -> str:
    datasets = [o for o in objs if isinstance(o, h5py.Dataset)]
    target = _Target(datasets[int(rng.integers(0, len(datasets)))], datasets, outside)
    mutation = DATASET_MUTATIONS.get(kind)
    detail = mutation(target, rng) if mutation else None
    return detail or f"{kind} {target.name}"


def mutate(path: Path, kind: str, rng: np.random.Generator, outside: Path) -> str:
    """Damage the archive at `path` in place the way `kind` says; returns what was done."""
    if kind in FILE_MUTATIONS:
        return FILE_MUTATIONS[kind](path, rng)
    with h5py.File(path, "r+") as f:
        objs = _objects(f)
        if kind.startswith("attr"):
            return _mutate_attr(objs, kind, rng)
        return _mutate_dataset(objs, kind, rng, outside)


def opened_outside(strace_log: Path, allowed: list[Path]) -> list[str]:
    """Paths the run opened that lie under none of `allowed` and are not the interpreter's own files."""
    ok = [str(p.resolve()) for p in allowed]
    inside = tuple(a + "/" for a in ok)  # ".../out/" so that ".../outside.h5" is not taken for ".../out"
    system = ("/usr/", "/lib", "/etc/ld.so", "/proc/", "/sys/", "/dev/", sys.prefix, sys.base_prefix,
              os.path.dirname(os.__file__), str(Path(archive.__file__).resolve().parents[1]),
              "/etc/localtime", "/etc/nsswitch", "/etc/host", "/etc/resolv", "/etc/ssl", "/etc/OpenCL",
              "/root/.cache", "/etc/pocl")
    out = []
    for line in strace_log.read_text(errors="replace").splitlines():
        m = re.search(r'open(?:at)?\((?:AT_FDCWD|\d+), "([^"]+)"', line)
        if not m or "ENOENT" in line:
            continue
        p = m.group(1)
        if p in ok or p.startswith(inside) or p.startswith(system) or not p.startswith("/"):
            continue
        if "O_DIRECTORY" in line or any(a.startswith(p.rstrip("/") + "/") for a in ok):
            continue  # listing a directory (the working directory, a parent of the tree) reads no file
        out.append(p)
    return sorted(set(out))


def _build_tree(cases: list[Case], good: Path, rng: np.random.Generator, work: Path) -> dict[int, Path]:
    """`work`/tree holding `good` and one mutated copy per case; {case index: its path}."""
    tree = work / "tree"
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
        except Exception as e:  # noqa: BLE001 - h5py may refuse a mutation: the case is the unmutated file
            c.detail = f"mutation not applied ({type(e).__name__})"
        originals[c.index] = path
    return originals


def _broken_rules(proc: subprocess.CompletedProcess, rss_before: int, rss: int, log: Path,
                  work: Path) -> list[str]:
    """The rules the run broke: a traceback, an unexpected exit, too much memory, an open outside the tree."""
    tree, out = work / "tree", work / "out"
    broken = []
    if "Traceback" in proc.stderr:
        broken.append("TRACEBACK")
    if proc.returncode not in (0, 1):
        broken.append(f"EXIT_{proc.returncode}")
    if rss > RSS_LIMIT_KB and rss > rss_before:
        broken.append("MEMORY")
    # Anything opened beyond the tree, OUT_DIR and the interpreter's own files: the outside archive and its
    # raw file beside the tree, /etc/passwd, or any other path a link in an archive may name.
    if log.exists() and opened_outside(log, [tree, out]):
        broken.append("OPENED_OUTSIDE")
    return broken


def _rejected_names(out: Path) -> dict[str, str]:
    """{file name: error kind} for every file errors.csv names."""
    named = {}
    errors = out / "errors.csv"
    if errors.exists():
        with errors.open(encoding="utf-8") as f:
            for row in csv.DictReader(f):
                for name in row["file"].split("; "):
                    named[name] = row["kind"]
    return named


def _case_outcome(c: Case, path: Path, broken: list[str], named: dict[str, str],
                  good_echo: np.ndarray) -> str:
    """One case's outcome: the rules the run broke, a rejection by name, or whether its values changed."""
    if broken:
        return "+".join(broken)
    if c.name in named:
        return f"rejected:{named[c.name]}"
    if path.is_dir():
        return "rejected:a_directory_not_a_file"  # searched as a directory, never read
    try:
        same = np.array_equal(archive.read_pass(path).echo, good_echo)
    except Exception:  # noqa: BLE001
        same = False
    return "accepted_unchanged" if same else "accepted_changed"


def run_batch(cases: list[Case], good: Path, rng: np.random.Generator, work: Path) -> dict[int, str]:
    """One `uwbcl process` over a tree with `cases` mutated copies of `good`; {case index: outcome}."""
    tree, out = work / "tree", work / "out"
    originals = _build_tree(cases, good, rng, work)
    log = work / "strace.log"
    cmd = [sys.executable, "-m", "uwbcl.cli", "process", str(tree), "--out", str(out), "--backend", "numpy",
           "--jobs", "1", "--no-progress"]
    if shutil.which("strace"):
        cmd = ["strace", "-f", "-qq", "-e", "trace=open,openat", "-o", str(log), *cmd]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True,
                              timeout=TIMEOUT_S * max(1, len(cases) / 20))
    except subprocess.TimeoutExpired:
        return {c.index: "HANG" for c in cases}
    elapsed = time.monotonic() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    broken = _broken_rules(proc, before, rss, log, work)
    named = _rejected_names(out)
    good_echo = archive.read_pass(good).echo
    result = {c.index: _case_outcome(c, originals[c.index], broken, named, good_echo) for c in cases}
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
