"""`uwbcl check IN_DIR`: what `uwbcl process` would make of a directory of scan archives, without focusing.

Every archive is read and validated as the batch reads it (docs/archive-format.md), grouped into cycles
with the batch's own rules, and summarised per rig: the cycles and heights found, the radar and the geometry
the files declare, the Doppler-side check of each pass (`geometry.doppler_step_ratio`). For a site engineer
before the first night's run, and for anyone writing archives with their own software.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import statistics
from collections import defaultdict
from pathlib import Path

from . import archive, batch, pipeline
from . import geometry as geo
from .records import BatchOptions, PassRecord, Problem, ProcessingSettings


@dataclasses.dataclass
class PassSummary:
    """What the check keeps of one readable pass (no sample arrays)."""

    record: PassRecord
    n_pulses: int
    rail_m: tuple[float, float]  # first and last pulse position along the rail
    window_m: tuple[float, float]  # one-way range of the first and last sample
    reference_range_m: float  # the reference point's distance from the aperture centre
    doppler_ratio: float | None  # geometry.doppler_step_ratio: about +1 by the format's conventions
    unfocusable: Problem | None = None  # what `uwbcl process` would report before focusing (its plan)


@dataclasses.dataclass
class CheckReport:
    n_files: int
    passes: list[PassSummary]
    problems: list[Problem]  # what `uwbcl process` would report as errors: files or cycles not used
    warnings: list[Problem]  # accepted input worth a look


def summarise_pass(path: Path, name: str, settings: ProcessingSettings) -> PassSummary:
    """Read and validate one archive (ArchiveError, OSError) and keep its summary."""
    scan = archive.read_pass(path, settings.limits)
    header = batch.pass_header(scan, path, settings)
    record = PassRecord(file=name, sha256=batch.file_sha256(path), rig_id=header["rig_id"],
                        cycle=header["cycle"], height_m=header["height_m"], pass_id=header["pass_id"],
                        pass_start_time=header["pass_start_time"],
                        parameters={k: tuple(v) if isinstance(v, list) else v
                                    for k, v in header["parameters"].items()},
                        detections=())
    x = scan.pulse_position_m
    r = scan.range_axis_m
    centre = (0.5 * float(x[0] + x[-1]), 0.0, float(scan.geometry.height_m))
    ratio = geo.doppler_step_ratio(scan.echo, x, scan.geometry.rotation_table_angle_deg,
                                   scan.radar.wavelength_m)
    return PassSummary(record, scan.n_pulses, (float(x[0]), float(x[-1])), (float(r[0]), float(r[-1])),
                       math.dist(centre, scan.geometry.reference_point_m), ratio,
                       plan_problem(scan, name, settings))


def plan_problem(scan, name: str, settings: ProcessingSettings) -> Problem | None:
    """The problem `uwbcl process` would report for this pass before focusing it: the site delay beyond its
    window, a pass too small to focus, or one whose focus grid exceeds the limits (`pipeline.check_plan`)."""
    try:
        pipeline.check_plan(pipeline.apply_range_delay(scan, settings.range_delay_s), settings)
    except ValueError as e:  # LimitExceeded, PassTooSmall, or the site's delay behind the antenna
        failure = batch.focus_failure(e)
        return Problem(name, failure["kind"], failure["error"])
    return None


def check_directory(in_dir: Path, settings: ProcessingSettings | None = None,
                    options: BatchOptions | None = None) -> CheckReport:
    """Read every archive under ``in_dir`` as `uwbcl process` does, one at a time (bounded memory), and group
    them into cycles by its rules. Never raises for what the tree holds."""
    settings = settings or ProcessingSettings()
    options = options or BatchOptions()
    in_dir = Path(in_dir)
    walk = archive.walk_pass_files(in_dir, follow_symlinks=options.follow_symlinks)
    problems = [Problem(*p) for p in walk.problems]
    warnings = [Problem(*w) for w in walk.warnings]
    passes = []
    hung = batch.unreadable_structures(list(walk.files), settings.limits)  # as process: never opened here
    for path in walk.files:
        name = path.relative_to(in_dir).as_posix()
        if path in hung:
            problems.append(Problem(name, "invalid_archive", f"/: {hung[path]}"))
            continue
        try:
            with _reader_warnings() as said:
                passes.append(summarise_pass(path, name, settings))
            warnings += [Problem(name, "reader", text.replace(f"{path}: ", "", 1))
                         for text in dict.fromkeys(said)]  # each once: the header and the data both warn
        except archive.ArchiveError as e:
            problems.append(Problem(name, "invalid_archive", f"{e.field}: {e.reason}"))
        except OSError as e:
            problems.append(Problem(name, "unreadable", f"cannot read: {e.strerror or e}"))
    problems += [p.unfocusable for p in passes if p.unfocusable is not None]
    records = [p.record for p in passes if p.unfocusable is None]  # as in process: such a pass has no record
    linked = frozenset(w.file for w in warnings if w.kind == "symlink")
    _, grouping = batch.group_cycles(records, options, linked)
    problems += grouping
    warnings += batch.suspicious(records)
    for p in passes:
        if p.doppler_ratio is not None and p.doppler_ratio < geo.DOPPLER_WRONG_SIDE_RATIO:
            warnings.append(Problem(p.record.file, "q_sign", geo.doppler_wrong_side_reason(p.doppler_ratio)))
        travel_m = abs(p.rail_m[1] - p.rail_m[0])
        if travel_m > geo.LONG_RAIL_M:
            warnings.append(Problem(p.record.file, "long_rail",
                                    f"the pass travels {travel_m:.1f} m along the rail, more than any "
                                    f"face-end rail ({geo.LONG_RAIL_M:g} m): are its positions in metres?"))
        lo, hi = p.window_m
        if not lo <= p.reference_range_m <= hi:
            warnings.append(Problem(p.record.file, "reference_outside_window",
                                    f"the reference point lies {p.reference_range_m:.2f} m from the aperture "
                                    f"centre, outside the recorded window {lo:.2f}-{hi:.2f} m"))
    warnings += rail_travel_warnings(passes)
    return CheckReport(len(walk.files), passes, problems, warnings)


# A pass whose travel along the rail differs from its rig's median pass by more than this fraction gets a
# `rail_travel` warning: a rig's passes run between the same end stops, so one cut short or one whose
# positions log came from another (slower or faster) pass shows here (indepZs F4: such a log imported
# silently and its cycle came out `prior_conflict` with nothing naming the pass).
RAIL_TRAVEL_WARN_FRACTION = 0.1


def rail_travel_warnings(passes: list[PassSummary]) -> list[Problem]:
    """One `rail_travel` warning per pass whose travel (m) differs from its rig's median pass's by more than
    RAIL_TRAVEL_WARN_FRACTION of it (rigs of three or more passes)."""
    by_rig: dict[str, list[PassSummary]] = defaultdict(list)
    for p in passes:
        by_rig[p.record.rig_id].append(p)
    out = []
    for ps in by_rig.values():
        travel = [abs(p.rail_m[1] - p.rail_m[0]) for p in ps]
        median = statistics.median(travel) if len(ps) >= 3 else 0.0
        for p, t in zip(ps, travel):
            if median > 0 and abs(t - median) > RAIL_TRAVEL_WARN_FRACTION * median:
                out.append(Problem(p.record.file, "rail_travel",
                                   f"the pass travels {t:.2f} m along the rail, its rig's passes "
                                   f"{median:.2f} m (the median): a pass cut short, or positions from "
                                   "another pass or at another speed?"))
    return out


@contextlib.contextmanager
def _reader_warnings():
    """The archive reader's warnings (a newer minor version, attributes it ignores) while reading one file,
    as their texts; they go to the log in `uwbcl process`."""
    said: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            said.append(record.getMessage())

    logger, handler = logging.getLogger("uwbcl"), Keep(logging.WARNING)
    logger.addHandler(handler)
    propagate, logger.propagate = logger.propagate, False
    try:
        yield said
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _span(values, fmt: str, unit: str) -> str:
    lo, hi = min(values), max(values)
    return f"{lo:{fmt}} {unit}" if math.isclose(lo, hi, rel_tol=1e-9, abs_tol=1e-12) else \
        f"{lo:{fmt}}-{hi:{fmt}} {unit}"


def rig_lines(report: CheckReport, options: BatchOptions | None = None) -> list[str]:
    """One paragraph per rig: cycles and heights, radar, geometry, the Doppler check."""
    options = options or BatchOptions()
    by_rig: dict[str, list[PassSummary]] = defaultdict(list)
    for p in report.passes:
        by_rig[p.record.rig_id].append(p)
    groups, _ = batch.group_cycles([p.record for p in report.passes], options)
    out = []
    for rig, ps in sorted(by_rig.items()):
        recs = [p.record for p in ps]
        cycles = sorted({r.cycle for r in recs})
        usable = sorted(c for (g, c) in groups if g == rig)
        heights = defaultdict(int)
        for r in recs:
            heights[archive.height_mm(r.height_m)] += 1
        par = [r.parameters for r in recs]
        lengths = [abs(p.rail_m[1] - p.rail_m[0]) for p in ps]
        forward = sum(p.rail_m[1] > p.rail_m[0] for p in ps)
        ratios = [p.doppler_ratio for p in ps if p.doppler_ratio is not None]
        side = {int(q["boresight_y_sign"]) for q in par}
        gaps = (sorted(set(range(cycles[0], cycles[-1] + 1)) - set(cycles)) if cycles[-1] - cycles[0] < 10**6
                else [])
        missing = (f", none of cycle{'s' if len(gaps) > 1 else ''} "
                   f"{', '.join(map(str, gaps[:10]))}{f' ... ({len(gaps)} in all)' if len(gaps) > 10 else ''}"
                   if gaps else "")
        out += [
            f"rig {rig}: {len(ps)} passes, {len(cycles)} cycles ({cycles[0]}-{cycles[-1]}{missing}), "
            f"{len(usable)} usable (two or more heights that agree)",
            "  heights: " + ", ".join(f"{h / 1000:g} m x {n}" for h, n in sorted(heights.items())),
            f"  radar: carrier {_span([q['carrier_frequency_hz'] / 1e9 for q in par], '.4g', 'GHz')}, "
            f"bandwidth {_span([q['bandwidth_hz'] / 1e9 for q in par], '.4g', 'GHz')}, "
            f"complex rate {_span([q['sample_rate_hz'] / 1e9 for q in par], '.4g', 'GHz')}, "
            f"aperture {_span([q['antenna_aperture_m'] for q in par], '.3g', 'm')}",
            f"  geometry: table angle {_span([q['rotation_table_angle_deg'] for q in par], '.1f', 'deg')}, "
            f"rib on the {'/'.join('+Y' if s > 0 else '-Y' for s in sorted(side))} side, "
            f"rail {_span(lengths, '.2f', 'm')} ({forward} passes towards +X, "
            f"{len(ps) - forward} towards -X), "
            f"{_span([p.n_pulses for p in ps], 'd', 'pulses')}, window "
            f"{min(p.window_m[0] for p in ps):.2f}-{max(p.window_m[1] for p in ps):.2f} m",
            "  Doppler side (about +1 by the format's conventions): "
            + (f"{min(ratios):+.2f} to {max(ratios):+.2f} over {len(ratios)} passes" if ratios else
               "not decided (squint under "
               f"{geo.DOPPLER_CHECK_MIN_SQUINT_DEG:g} deg, a rail step too long for it, too few pulses or "
               "no coherent echo)"),
        ]
    return out
