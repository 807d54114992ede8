"""The outputs of `uwbcl process` (contract: docs/outputs.md), each written atomically.

displacements.csv / displacements.h5: one row per cycle after a rig's first; targets.csv: every located plate;
errors.csv: every problem; plots/ (on request): time series per rig and focused images per pass.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import importlib.util
import io
import json
import logging
import math
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from . import __version__, archive, pipeline
from .atomic import (
    PARTIAL_SUFFIX,
    csv_bytes,
    fsync_directory,
    open_regular_file,
    read_regular_file,
    write_bytes_atomic,
    write_hdf5_atomic,
    write_text_atomic,
)
from .names import MAX_NAME_LENGTH, safe_name  # noqa: F401  (MAX_NAME_LENGTH: tests)
from .records import TRUSTED_STATUSES, BatchError, CycleResult, OutputError, Problem, SeriesRow
from .utc import parse_utc

log = logging.getLogger("uwbcl")

DISPLACEMENT_COLUMNS = (
    "rig_id", "cycle", "from_cycle", "start_time", "retreat_m", "creep_m", "vertical_m",
    "cumulative_retreat_m", "cumulative_creep_m", "cumulative_vertical_m", "chain", "n_targets", "n_plates",
    "residual_m", "retreat_spread_m", "creep_spread_m", "vertical_spread_m", "runner_up_targets", "status",
    # Added in displacements format 1.1 (docs/outputs.md section 2.1), appended: the order above is fixed.
    "retreat_bound_m", "creep_bound_m", "cumulative_retreat_bound_m", "cumulative_creep_bound_m",
    "association_margin",
    # Added in 1.2: 0 as first issued, 1 when a later cycle resolved the row (the second look); the vertical
    # column's bounds
    "revision", "vertical_bound_m", "cumulative_vertical_bound_m",
    # Added in 1.3: carrier-phase looks that refined the row (eq. M8; 0: the plates' positions alone)
    "phase_looks",
)
TARGET_COLUMNS = (
    "rig_id", "cycle", "plate", "track", "x_m", "y_m", "z_m", "residual_m", "n_passes", "amplitude",
    "matched_plate", "inlier", "x_first_m", "y_first_m", "z_first_m",
    # Added in 1.4: heights where the plate's peak was shared with a neighbour's (eq. L1)
    "n_shared",
)
ERROR_COLUMNS = ("file", "kind", "reason")
H5_FORMAT = "uwbcl-displacements"
H5_FORMAT_VERSION = 1
UNITS = {"_m": "m", "cycle": "1", "from_cycle": "1", "chain": "1", "n_targets": "1", "n_plates": "1",
         "runner_up_targets": "1", "revision": "1", "phase_looks": "1",
         "plate": "1", "track": "1", "n_passes": "1", "n_shared": "1", "matched_plate": "1", "inlier": "1",
         "amplitude": "arb",
         "start_time": "ISO 8601 UTC", "rig_id": "", "status": "",
         "association_margin": "ln(likelihood ratio)"}


def number_text(v: float) -> str:
    """A float as the CSV outputs write it: 6 decimals (micrometres: far below the measurement's resolution,
    stable text), a negative zero as 0.000000 (no sign flip between runs where nothing changed)."""
    text = f"{v:.6f}"
    return text[1:] if text == "-0.000000" else text


def displacement_records(rows: list[SeriesRow]) -> list[dict]:
    """Typed values per displacement row (floats NaN when unknown)."""
    out = []
    for r in rows:
        d = r.displacement
        out.append({
            "rig_id": r.cycle.rig_id, "cycle": r.cycle.cycle, "from_cycle": r.reference.cycle,
            "start_time": r.cycle.start_time,
            "retreat_m": d.retreat_m, "creep_m": d.creep_m, "vertical_m": d.vertical_m,
            "cumulative_retreat_m": float(r.cumulative_m[0]), "cumulative_creep_m": float(r.cumulative_m[1]),
            "cumulative_vertical_m": float(r.cumulative_m[2]), "chain": r.chain,
            "n_targets": d.n_targets, "n_plates": len(r.cycle.plates), "residual_m": d.residual_m,
            "retreat_spread_m": float(d.spread_m[0]), "creep_spread_m": float(d.spread_m[1]),
            "vertical_spread_m": float(d.spread_m[2]), "runner_up_targets": d.runner_up_targets,
            "status": d.status,
            "retreat_bound_m": float(d.bound_m[0]), "creep_bound_m": float(d.bound_m[1]),
            "cumulative_retreat_bound_m": float(r.cumulative_bound_m[0]),
            "cumulative_creep_bound_m": float(r.cumulative_bound_m[1]), "association_margin": float(d.margin),
            "revision": r.revision, "vertical_bound_m": float(d.bound_m[2]),
            "cumulative_vertical_bound_m": float(r.cumulative_bound_m[2]), "phase_looks": d.phase_looks,
        })
    return out


def _text(records: list[dict]) -> list[dict]:
    return [{k: number_text(v) if isinstance(v, float) else v for k, v in rec.items()} for rec in records]


# ------------------------------------------------------------------------------------ revisions across runs
# A row already published is never changed silently: each run compares its rows with the published set's and
# raises `revision` where a row's values changed; a published cycle that is no longer measured (its archives
# removed or no longer usable) stays as a `withdrawn` row (docs/outputs.md section 2.1, "revision").
WITHDRAWN = "withdrawn"
MAX_PREVIOUS_BYTES = 64 << 20  # the published displacements.csv read back (about 200 000 rows)


def _published_rows(out_dir: Path, name: str, what: str, then: str) -> list[dict] | None:
    """The rows (text) of the published set's CSV `name`; None when there is none, or (logged) when it cannot
    be read or parsed."""
    path = out_dir / CURRENT_LINK / name
    try:
        text = read_regular_file(path, MAX_PREVIOUS_BYTES).decode("utf-8")
        return list(csv.DictReader(io.StringIO(text, newline="")))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, csv.Error) as e:  # UnicodeDecodeError is a ValueError
        log.warning("%s: the published %s cannot be read (%s); %s", path, what, e, then)
        return None


def previous_displacements(out_dir: Path) -> dict[tuple[str, int], dict]:
    """The published set's displacements.csv rows (text) by (rig_id, cycle); {} when there is none. A file
    that cannot be read or parsed is logged and taken as none: revisions then start again from the chain's."""
    rows = _published_rows(out_dir, "displacements.csv", "displacements",
                           "revisions are not carried over")
    previous, bad = {}, 0
    for r in rows or []:
        try:
            key = (r["rig_id"], int(r["cycle"]))
            int(r.get("revision") or 0)
        except (KeyError, TypeError, ValueError):
            bad += 1
            continue
        if key[0] is None or r.get("status") is None:
            bad += 1
            continue
        previous[key] = r
    if bad:
        log.warning("%s: %d published rows cannot be read; their revisions are not carried over",
                    out_dir / CURRENT_LINK / "displacements.csv", bad)
    return previous


def _published_h5_targets(out_dir: Path) -> list[dict] | None:
    """The targets table of the published displacements.h5 as targets.csv would write it (text); None when
    there is none or it cannot be read."""
    import h5py

    path = out_dir / CURRENT_LINK / "displacements.h5"
    try:
        with h5py.File(path, "r") as f:
            group = f["targets"]
            columns = {name: group[name][()] for name in TARGET_COLUMNS if name in group}
    except FileNotFoundError:
        return None
    except (OSError, KeyError, ValueError, TypeError) as e:
        log.warning("%s: the published targets cannot be read (%s); their changes do not raise revisions",
                    path, e)
        return None
    n = min((len(v) for v in columns.values()), default=0)
    return [{k: _h5_text(v[i]) for k, v in columns.items()} for i in range(n)]


def _h5_text(value) -> str:
    """A value of displacements.h5 as the CSV writes it."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.floating):
        return number_text(float(value))
    return str(int(value))


def previous_targets(out_dir: Path) -> dict[tuple[str, int], list[dict]] | None:
    """The published set's plates (text) by (rig_id, cycle), in file order: its targets.csv, else the targets
    table of its displacements.h5 (a set written with `targets = false`); None when it has neither or they
    cannot be read (then a cycle's plates cannot be compared: only its row's values are)."""
    rows = _published_rows(out_dir, "targets.csv", "targets", "their changes do not raise revisions")
    if rows is None:
        rows = _published_h5_targets(out_dir)
    if rows is None:
        return None
    by_cycle: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        try:
            by_cycle.setdefault((r["rig_id"], int(r["cycle"])), []).append(r)
        except (KeyError, TypeError, ValueError):
            continue
    return by_cycle


def changed_targets(targets: list[dict], previous: dict[tuple[str, int], list[dict]] | None
                    ) -> set[tuple[str, int]]:
    """The (rig_id, cycle) whose targets.csv rows differ from the published set's (any column both sets have,
    the number of rows, their order): their displacement rows are re-issued (docs/outputs.md section 2.1)."""
    if previous is None:
        return set()
    now: dict[tuple[str, int], list[dict]] = {}
    for r in _text(targets):
        now.setdefault((r["rig_id"], int(r["cycle"])), []).append(r)
    changed = set()
    for key in set(now) | set(previous):
        a, b = now.get(key, []), previous.get(key, [])
        if len(a) != len(b) or any(str(x[k]) != y[k] for x, y in zip(a, b) for k in y if k in x):
            changed.add(key)
    return changed


def _withdrawn(p: dict) -> dict:
    """The tombstone of a published row whose cycle is no longer measured."""
    rec = {c: math.nan for c in DISPLACEMENT_COLUMNS}
    try:
        from_cycle = int(p.get("from_cycle") or -1)
    except ValueError:
        from_cycle = -1
    revision = int(p.get("revision") or 0)
    rec.update(rig_id=p["rig_id"], cycle=int(p["cycle"]), from_cycle=from_cycle,
               start_time=p.get("start_time") or "", chain=-1, n_targets=0, n_plates=0, runner_up_targets=0,
               phase_looks=0, status=WITHDRAWN)
    rec["revision"] = revision if p["status"] == WITHDRAWN else revision + 1
    return rec


def newly_withdrawn(previous: dict[tuple[str, int], dict], rows: list[SeriesRow]) -> list[Problem]:
    """One `withdrawn` problem (errors.csv, exit 1) per rig whose published rows this run withdraws: their
    cycles are no longer measured (an unmounted share, archives removed). Rows already withdrawn are not
    counted again, so the next run over the same archives is quiet."""
    measured = {(r.cycle.rig_id, r.cycle.cycle) for r in rows}
    gone: dict[str, list[int]] = {}
    for (rig, cycle), p in previous.items():
        if p["status"] != WITHDRAWN and (rig, cycle) not in measured:
            gone.setdefault(rig, []).append(cycle)
    problems = []
    for rig, cycles in sorted(gone.items()):
        listed = ", ".join(str(c) for c in sorted(cycles)[:10]) + (", ..." if len(cycles) > 10 else "")
        problems.append(Problem(".", WITHDRAWN, f"rig {rig}: {len(cycles)} published row(s) withdrawn (cycle "
                                f"{listed}): no longer measured, their archives gone or no longer usable; "
                                "kept as `withdrawn` rows until they return"))
    return problems


def carry_revisions(records: list[dict], previous: dict[tuple[str, int], dict],
                    plates_changed: set[tuple[str, int]] = frozenset()) -> list[dict]:
    """`records` (displacement_records) with the revisions of the published set carried over: a row whose
    values (every column both sets have, but `revision`) and whose cycle's plates (`plates_changed`,
    `changed_targets`) are unchanged keeps its revision, a changed one gets the published revision + 1 (at
    least the chain's), and a published row without a record now becomes a `withdrawn` row. Revisions never
    decrease; the rows stay sorted by rig_id (code points), then cycle."""
    if not previous:
        return records
    out = []
    for rec in records:
        p = previous.pop((rec["rig_id"], rec["cycle"]), None)
        if p is not None:
            text = _text([rec])[0]
            published = int(p.get("revision") or 0)
            changed = [k for k, v in p.items() if k in text and k != "revision" and str(text[k]) != v]
            changed += ["targets.csv"] if (rec["rig_id"], rec["cycle"]) in plates_changed else []
            rec = {**rec, "revision": max(published + 1 if changed else published, rec["revision"])}
            if changed:
                log.info("rig %s cycle %d: revision %d: changed since the published set (%s)", rec["rig_id"],
                         rec["cycle"], rec["revision"], ", ".join(changed))
        out.append(rec)
    for (rig, cycle), p in previous.items():
        if p["status"] != WITHDRAWN:
            log.info("rig %s cycle %d: withdrawn: published before, no longer measured (its archives are "
                     "gone or no longer usable)", rig, cycle)
        out.append(_withdrawn(p))
    return sorted(out, key=lambda r: (r["rig_id"], r["cycle"]))


def new_or_revised(rows: list[dict], previous: dict[tuple[str, int], dict]) -> int:
    """How many of the rows as written (text, `write_all`) a reader of the published set `previous`
    (`previous_displacements`) has not seen: new rows, and rows whose revision moved (what a run changed)."""
    def moved(r: dict) -> bool:
        p = previous.get((r["rig_id"], int(r["cycle"])))
        return p is None or int(r["revision"]) > int(p.get("revision") or 0)
    return sum(1 for r in rows if moved(r))


def write_displacements_csv(path: Path, rows: list[SeriesRow]) -> list[dict]:
    """displacements.csv of docs/outputs.md from a chain's rows; returns the rows as written (text)."""
    text = _text(displacement_records(rows))
    write_bytes_atomic(path, csv_bytes(DISPLACEMENT_COLUMNS, text))
    return text


def target_records(rows: list[SeriesRow], cycles: list[CycleResult]) -> list[dict]:
    """Every plate of every cycle, with a track id that follows a physical plate through trusted matches."""
    row_of = {(r.cycle.rig_id, r.cycle.cycle): r for r in rows}
    tracks: dict[tuple[str, int], list[int]] = {}
    next_track: dict[str, int] = {}
    out = []
    for c in sorted(cycles, key=lambda c: (c.rig_id, c.cycle)):
        key = (c.rig_id, c.cycle)
        r = row_of.get(key)
        ids = [-1] * len(c.plates)
        matched = [-1] * len(c.plates)
        trusted = r is not None and r.displacement.status in TRUSTED_STATUSES
        if r is not None:
            for i, j in r.displacement.pairs:
                matched[j] = i
                if trusted:
                    ids[j] = tracks[(c.rig_id, r.reference.cycle)][i]
        for j in range(len(ids)):
            if ids[j] < 0:
                ids[j] = next_track.get(c.rig_id, 0)
                next_track[c.rig_id] = ids[j] + 1
        tracks[key] = ids
        cum = r.cumulative_m if r is not None else np.zeros(3)  # the rig's first cycle is the origin
        for j, p in enumerate(c.plates):
            first = p.position_m + cum
            out.append({
                "rig_id": c.rig_id, "cycle": c.cycle, "plate": j, "track": ids[j],
                "x_m": float(p.position_m[0]), "y_m": float(p.position_m[1]), "z_m": float(p.position_m[2]),
                "residual_m": float(p.residual_m), "n_passes": p.n_passes, "amplitude": float(p.amplitude),
                "matched_plate": matched[j], "inlier": int(matched[j] >= 0),
                "x_first_m": float(first[0]), "y_first_m": float(first[1]), "z_first_m": float(first[2]),
                "n_shared": len(p.shared_heights_m),
            })
    return out


def _unit(name: str) -> str:
    if name in UNITS:
        return UNITS[name]
    return next(u for suffix, u in UNITS.items() if suffix.startswith("_") and name.endswith(suffix))


def write_h5_atomic(path: Path, tables: dict[str, tuple[tuple[str, ...], list[dict]]]) -> None:
    """One group per table, one 1-D dataset per column with a `units` attribute; deterministic bytes."""
    import h5py

    def fill(f) -> None:
        f.attrs["format"] = H5_FORMAT
        f.attrs["format_version"] = np.int64(H5_FORMAT_VERSION)
        f.attrs["created_by"] = f"uwbcl {__version__}"
        for name, (columns, records) in tables.items():
            g = f.create_group(name, track_order=True)
            g.attrs["rows"] = np.int64(len(records))
            for col in columns:
                values = [rec[col] for rec in records]
                unit = _unit(col)
                if col in ("rig_id", "start_time", "status"):
                    data = np.array(values, dtype=h5py.string_dtype())
                elif unit == "1":
                    data = np.array(values, dtype=np.int64)
                else:
                    data = np.array(values, dtype=np.float64)
                ds = g.create_dataset(col, data=data, shape=(len(values),))
                ds.attrs["units"] = unit

    write_hdf5_atomic(path, fill)


SETTINGS_FORMAT = "uwbcl-settings"
SETTINGS_FORMAT_VERSION = 1


def _jsonable(value):
    """Plain JSON data: tuples as lists, a non-finite float as its text ("nan", "inf")."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def settings_text(settings, batch_options) -> str:
    """settings.json (docs/outputs.md section 2): every setting in effect that shapes the outputs, from the
    site file, the flags and the defaults together, so a published set says what produced it."""
    opts = batch_options
    processing = dataclasses.asdict(settings)
    if processing["association"]["prior_advance_m"] is None:  # the window of no prior is used nowhere
        processing["association"]["prior_window_m"] = None
    doc = {"format": SETTINGS_FORMAT, "format_version": SETTINGS_FORMAT_VERSION, "uwbcl": __version__,
           "processing": _jsonable(processing),
           "batch": _jsonable({"heights_m": sorted(opts.heights_m) if opts.heights_m else opts.heights_m,
                               "height_tolerance_m": opts.height_tolerance_m,
                               "max_bridge_cycles": opts.max_bridge_cycles,
                               "follow_symlinks": opts.follow_symlinks,
                               "outputs": dataclasses.asdict(opts.outputs)})}
    return json.dumps(doc, indent=1, sort_keys=True, allow_nan=False) + "\n"


def write_all(out_dir: Path, rows: list[SeriesRow], cycles: list[CycleResult], problems: list[Problem], opts,
              *, groups: dict, in_dir: Path, settings, settings_json: str) -> list[dict]:
    """Every output of a run, published as one set (see `publish`); returns the displacements.csv rows (text).

    Raises OutputError naming the path when a file cannot be written (disk full, permissions): the previous
    complete set stays in place.
    """
    try:
        _adopt_plain_outputs(out_dir)  # first: the old set's generation is then numbered before the new one
        previous = previous_displacements(out_dir)
        published_targets = previous_targets(out_dir) if (opts.targets or opts.hdf5) else None
        gen = new_generation(out_dir)
    except OSError as e:
        raise OutputError(f"cannot write the outputs: {e.filename or out_dir}: {e.strerror or e}; the "
                          "previous outputs are intact") from e
    try:
        targets = target_records(rows, cycles) if (opts.targets or opts.hdf5) else []
        disp = carry_revisions(displacement_records(rows), previous,
                               changed_targets(targets, published_targets))
        disp_text = _text(disp)
        write_bytes_atomic(gen / "displacements.csv", csv_bytes(DISPLACEMENT_COLUMNS, disp_text))
        if opts.targets:
            write_bytes_atomic(gen / "targets.csv", csv_bytes(TARGET_COLUMNS, _text(targets)))
        if opts.hdf5:
            write_h5_atomic(gen / "displacements.h5",
                            {"displacements": (DISPLACEMENT_COLUMNS, disp),
                             "targets": (TARGET_COLUMNS, targets)})
        write_bytes_atomic(gen / "errors.csv",
                           csv_bytes(ERROR_COLUMNS, [dataclasses.asdict(p) for p in problems]))
        write_text_atomic(gen / "settings.json", settings_json)
        if opts.plots:
            plot_time_series(gen / "plots", disp)
        if opts.cycle_images:
            plot_cycle_images(gen / "plots" / "cycles", groups, in_dir, settings,
                              carried_from=out_dir / CURRENT_LINK / "plots" / "cycles")
        publish(out_dir, gen)
    except OSError as e:
        shutil.rmtree(gen, ignore_errors=True)
        where = e.filename or gen
        raise OutputError(f"cannot write the outputs: {where}: {e.strerror or e}; the previous outputs are "
                          "intact") from e
    except BaseException:
        shutil.rmtree(gen, ignore_errors=True)
        raise
    return disp_text


# ----------------------------------------------------------------------------------------------- one set
# The files of a run become visible together: they are written into a new generation directory, and one
# symbolic link, OUT/.uwbcl-current, is switched to it by rename(2), which is atomic. The names users read
# (OUT/displacements.csv, ...) are fixed links through .uwbcl-current, so a kill at any instant leaves
# either the old complete set or the new one (docs/outputs.md, "One set").
GENERATIONS_DIR = ".uwbcl-generations"
CURRENT_LINK = ".uwbcl-current"
OUTPUT_NAMES = ("displacements.csv", "displacements.h5", "targets.csv", "errors.csv", "settings.json",
                "plots")
KEEP_GENERATIONS = 2  # the current set and the one before it (a reader may still be reading it)


def _generation_number(name: str) -> int:
    return int(name[2:]) if name.startswith("g-") and name[2:].isdigit() else -1


def _current_generation(out_dir: Path) -> str | None:
    try:
        return Path(os.readlink(out_dir / CURRENT_LINK)).name
    except OSError:
        return None


def new_generation(out_dir: Path) -> Path:
    """An empty generation directory numbered after every existing one."""
    root = out_dir / GENERATIONS_DIR
    root.mkdir(parents=True, exist_ok=True)
    numbers = [_generation_number(p.name) for p in root.iterdir()]
    gen = root / f"g-{max(numbers, default=0) + 1:06d}"
    gen.mkdir()
    return gen


def _replace_with_link(path: Path, target: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}{PARTIAL_SUFFIX}")
    tmp.unlink(missing_ok=True)
    os.symlink(target, tmp)
    os.replace(tmp, path)


def publish(out_dir: Path, gen: Path) -> None:
    """Make generation `gen` the visible output set of out_dir in one atomic step."""
    _adopt_plain_outputs(out_dir)
    for path in sorted(gen.rglob("*"), reverse=True):  # files, then the directories holding them
        if path.is_dir():
            fsync_directory(path)
    fsync_directory(gen)
    fsync_directory(gen.parent)
    _replace_with_link(out_dir / CURRENT_LINK, f"{GENERATIONS_DIR}/{gen.name}")
    fsync_directory(out_dir)
    for name in OUTPUT_NAMES:
        link = out_dir / name
        if (gen / name).exists():
            if not (link.is_symlink() and os.readlink(link) == f"{CURRENT_LINK}/{name}"):
                _replace_with_link(link, f"{CURRENT_LINK}/{name}")
        elif link.is_symlink():
            link.unlink()
    fsync_directory(out_dir)
    prune_generations(out_dir)


_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _own_plot(name: str) -> bool:
    """A name plots/ of an earlier uwbcl holds: time series, the cycle images, its own temporary files."""
    return (name.startswith("timeseries_") and name.endswith(".png")) or name == "cycles" or (
        name.startswith(".timeseries_") and name.endswith(PARTIAL_SUFFIX))


def _plain_output_is_ours(path: Path, name: str) -> bool:
    """Whether a plain (not linked) OUT/NAME is an output of a uwbcl version without generations: a CSV with
    its header, JSON with its processing settings, an HDF5 file, plots/ of time-series PNGs. Read without
    blocking and only its start: someone else's file is never read whole."""
    try:
        if name == "plots":
            return path.is_dir() and not path.is_symlink() and all(_own_plot(e.name) for e in path.iterdir())
        with open_regular_file(path, follow_symlinks=False) as f:
            head = f.read(1 << 20 if name == "settings.json" else 4096)
    except (OSError, ValueError):  # unreadable: not known to be ours
        return False
    if name.endswith(".csv"):
        first = {"displacements.csv": DISPLACEMENT_COLUMNS, "targets.csv": TARGET_COLUMNS,
                 "errors.csv": ERROR_COLUMNS}[name][:3]
        return head.startswith(",".join(first).encode())
    if name == "settings.json":
        try:
            doc = json.loads(head)
        except ValueError:
            return False
        return isinstance(doc, dict) and "processing" in doc
    if not head.startswith(_HDF5_SIGNATURE):
        return False
    import h5py  # only here: h5py is needed where an HDF5 file is read or written

    try:  # uwbcl's own format attribute (docs/outputs.md section 2.2), not any HDF5 file
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format", "")
        return (fmt.decode("utf-8", "replace") if isinstance(fmt, bytes) else str(fmt)) == H5_FORMAT
    except (OSError, ValueError, TypeError):
        return False


def foreign_entries(out_dir: Path) -> list[str]:
    """What in OUT is in the way of the output set and not uwbcl's, for a refusal before the run (uwbcl
    replaces these names by links, and would otherwise move someone's files into a generation it later
    removes): `.uwbcl-current` that is not a link into `.uwbcl-generations` (nor a directory: a set copied
    with its links dereferenced, adopted), and a plain file or directory at a fixed output name that is not
    an earlier uwbcl's output (`_plain_output_is_ours`)."""
    out = []
    current = out_dir / CURRENT_LINK
    if current.is_symlink():
        target = os.readlink(current)
        resolved = Path(os.path.realpath(current))
        if not (resolved.parent == Path(os.path.realpath(out_dir / GENERATIONS_DIR))
                and _generation_number(resolved.name) >= 0):
            out.append(f"{current}: a symbolic link to {target!r}, not to a generation in {GENERATIONS_DIR}")
    elif current.is_dir():  # a set copied with its links dereferenced: adopted whole, so only uwbcl's in it
        try:
            entries = sorted(current.iterdir())
        except OSError:
            entries = [current]
        out += [f"{e}: not an output of uwbcl, in a copied {CURRENT_LINK}" for e in entries
                if e.name not in OUTPUT_NAMES or not _plain_output_is_ours(e, e.name)]
    elif current.exists():
        out.append(f"{current}: not uwbcl's symbolic link to the published set")
    for name in OUTPUT_NAMES:
        path = out_dir / name
        if path.is_symlink():
            continue  # uwbcl's fixed link (or one uwbcl replaces: a link is never followed to delete)
        if (path.exists() or os.path.lexists(path)) and not _plain_output_is_ours(path, name):
            out.append(f"{path}: not an output of uwbcl, where uwbcl links its {name}")
    return out


def _adopt_plain_outputs(out_dir: Path) -> None:
    """Outputs of a version before generations (plain files): moved into a generation of their own first, so
    that replacing them by links never shows a mixed set."""
    current = out_dir / CURRENT_LINK
    if current.exists() and not current.is_symlink():  # copied with links dereferenced: keep it
        os.rename(current, new_generation(out_dir))
    plain = [n for n in OUTPUT_NAMES if (out_dir / n).exists() and not (out_dir / n).is_symlink()]
    if not plain:
        return
    gen = new_generation(out_dir)
    for name in plain:
        src = out_dir / name
        if src.is_dir():
            shutil.copytree(src, gen / name)
        else:
            shutil.copy2(src, gen / name)
    fsync_directory(gen)
    _replace_with_link(out_dir / CURRENT_LINK, f"{GENERATIONS_DIR}/{gen.name}")
    for name in plain:
        path = out_dir / name
        if path.is_dir():
            shutil.rmtree(path)
        _replace_with_link(path, f"{CURRENT_LINK}/{name}")
    fsync_directory(out_dir)


def prune_generations(out_dir: Path) -> None:
    """Remove generations older than the KEEP_GENERATIONS newest, and any newer than the current one (a run
    killed before it published). Called with the output directory locked."""
    root = out_dir / GENERATIONS_DIR
    if not root.is_dir():
        return
    current = _current_generation(out_dir)
    cur_n = _generation_number(current) if current else -1
    gens = sorted((p for p in root.iterdir() if _generation_number(p.name) >= 0),
                  key=lambda p: _generation_number(p.name))
    keep = {p.name for p in gens if _generation_number(p.name) <= cur_n}
    keep = set(sorted(keep, key=_generation_number)[-KEEP_GENERATIONS:])
    for p in gens:
        if p.name not in keep:
            shutil.rmtree(p, ignore_errors=True)


# ----------------------------------------------------------------------------------------------- plots
MPL_CONFIG_DIR = ".uwbcl-matplotlib"  # matplotlib's config and font cache, inside OUT


def require_matplotlib(out_dir: Path) -> None:
    """BatchError when matplotlib is not installed. Points matplotlib's config and font cache at
    OUT/.uwbcl-matplotlib (unless MPLCONFIGDIR is set): importing it would otherwise write under the user's
    home, outside the output directory. Called before matplotlib is imported, which it does not do itself."""
    if importlib.util.find_spec("matplotlib") is None:
        raise BatchError("plots need matplotlib: pip install 'uwbcl[plot]'")
    if "matplotlib" not in sys.modules:
        os.environ.setdefault("MPLCONFIGDIR", str(Path(out_dir).resolve() / MPL_CONFIG_DIR))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    write_bytes_atomic(path, buf.getvalue())


def plot_time_series(plot_dir: Path, records: list[dict]) -> None:
    """plots/timeseries_<rig>.png: cumulative and per-cycle retreat and creep against time, flags in red."""
    plt = _pyplot()
    by_rig: dict[str, list[dict]] = {}
    for rec in records:
        by_rig.setdefault(rec["rig_id"], []).append(rec)
    for rig, recs in sorted(by_rig.items()):
        t = [parse_utc(r["start_time"]) for r in recs]
        flagged = [r["status"] != "ok" for r in recs]
        fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
        for col, (name, label) in enumerate((("retreat", "retreat"), ("creep", "creep"))):
            cum = np.array([r[f"cumulative_{name}_m"] for r in recs])
            step = np.array([r[f"{name}_m"] for r in recs]) * 1000.0
            axes[0, col].plot(t, cum, ".-", color="C0")
            axes[0, col].set_ylabel(f"cumulative {label} (m)")
            axes[1, col].plot(t, step, ".", color="C0", label="ok")
            bad = np.array(flagged)
            if bad.any():
                axes[1, col].plot(np.array(t, dtype=object)[bad], step[bad], "x", color="C3", label="flagged")
            axes[1, col].set_ylabel(f"{label} per cycle (mm)")
            axes[1, col].legend(loc="best", fontsize=8)
        fig.suptitle(f"{rig}: {len(recs)} displacements, {sum(flagged)} flagged")
        fig.autofmt_xdate()
        fig.tight_layout()
        _save(fig, plot_dir / f"timeseries_{safe_name(rig)}.png")
        plt.close(fig)


IMAGE_INDEX = "images.json"  # plots/cycles/: each image's archive digest and settings


def _image_key(rec, settings) -> str:
    """What a pass's image depends on: the archive's bytes, the settings that shape focusing (not the
    association's) and the detections it marks."""
    marks = [(d.image_azimuth_m, d.image_range_m) for d in rec.detections]
    text = json.dumps({"archive": rec.sha256, "uwbcl": __version__, "settings": settings.shaping(),
                       "marks": marks}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _carried_images(carried_from: Path | None) -> dict[str, str]:
    """The published images' index (relative PNG path -> `_image_key`); {} when there is none or it cannot
    be read (every image is then drawn again)."""
    if carried_from is None:
        return {}
    try:
        index = json.loads(read_regular_file(carried_from / IMAGE_INDEX, MAX_PREVIOUS_BYTES))
    except (OSError, ValueError):
        return {}
    return {k: v for k, v in index.items() if isinstance(k, str) and isinstance(v, str)} \
        if isinstance(index, dict) else {}


def plot_cycle_images(plot_dir: Path, groups: dict, in_dir: Path, settings,
                      carried_from: Path | None = None) -> None:
    """plots/cycles/<rig>/c<cycle>_h<mm>.png: |image| in dB with the detections marked, and
    plots/cycles/images.json indexing them by archive and settings.

    An image of `carried_from` (the published set's plots/cycles) is carried over (hard link: refocusing is
    slow) when its pass's archive and the settings are those it was drawn from; every other image is drawn:
    the pass refocused with the numpy reference (the engine's image is the same within its tolerance), as
    `uwbcl process` focused it. Images of passes no longer in `groups` are not carried.
    """
    settings = dataclasses.replace(settings, backend="numpy")
    published, index, plt = _carried_images(carried_from), {}, None
    for (rig, cycle), recs in sorted(groups.items()):
        for hmm, rec in sorted(recs.items()):
            name = f"{safe_name(rig)}/c{cycle:06d}_h{hmm:04d}.png"
            path, index[name] = plot_dir / name, _image_key(rec, settings)
            if published.get(name) == index[name]:
                path.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(carried_from / name, path)
                    continue
                except FileNotFoundError:
                    pass  # indexed but gone: drawn again
                except OSError:
                    shutil.copy2(carried_from / name, path)
                    continue
            plt = plt or _pyplot()
            scan = archive.read_pass(in_dir / rec.file, settings.limits)
            prod = pipeline.focus_only(scan, settings)
            if settings.algorithm == "bp":
                az, rg = prod.u_axis_m, prod.r_axis_m
            else:
                az, rg = prod.grid.t_azimuth_s * prod.grid.speed_m_s, prod.grid.range_bins_m
            mag = 20 * np.log10(np.abs(prod.image) / np.abs(prod.image).max() + 1e-12)
            fig, ax = plt.subplots(figsize=(7, 5))
            ax.imshow(mag.T, origin="lower", aspect="auto", vmin=-40, vmax=0, cmap="viridis",
                      extent=(az[0], az[-1], rg[0], rg[-1]))
            ax.plot([d.image_azimuth_m for d in rec.detections],
                    [d.image_range_m for d in rec.detections], "o",
                    mfc="none", mec="red", ms=10)
            half = 0.5 * (scan.pulse_position_m.max() - scan.pulse_position_m.min())
            ax.set_xlim(-1.2 * half, 1.2 * half)
            ax.set_xlabel("azimuth v t (m)")
            ax.set_ylabel("range r_LRCM (m)")
            ax.set_title(f"{rig} cycle {cycle} h {hmm} mm: {len(rec.detections)} detections")
            _save(fig, path)
            plt.close(fig)
    write_text_atomic(plot_dir / IMAGE_INDEX, json.dumps(index, indent=1, sort_keys=True) + "\n")
