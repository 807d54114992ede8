"""Command line: `uwbcl simulate` writes archives of a simulated shift, `uwbcl process` measures the
advance."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import math
import os
import re
import signal
import sys
from pathlib import Path

from .threads import one_blas_thread

# Before numpy loads (the imports below): BLAS on one thread in this process and the workers it starts.
one_blas_thread()

from . import __version__, archive, batch, config, geometry, interrupt, outputs  # noqa: E402
from .atomic import file_in_the_way, write_text_atomic  # noqa: E402
from .importers import OptionError, RecordingError, passes, registry  # noqa: E402
from .pipeline import MIN_FOCUS_PULSES  # noqa: E402
from .records import ALGORITHMS, BACKENDS, BatchError, ConfigError, NothingRead, OutputError  # noqa: E402
from .scenarios import SCENARIOS  # noqa: E402

# a shift's rib and truth are simulated from cycle 0, in time growing with the square (10 s for 10,000)
MAX_SIMULATED_CYCLES = 20_000
MAX_SIMULATED_RIGS = 1000


def _simulate_shift(args: argparse.Namespace) -> int:
    from . import shift

    cfg = shift.ShiftConfig(cycles=args.cycles, rigs=args.rigs, first_cycle=args.first_cycle, seed=args.seed,
                            snr_db=args.snr_db, speed_jitter=args.speed_jitter,
                            **({"heights_m": config.parse_heights(args.heights)} if args.heights else {}),
                            **({"rig_prefix": args.rig_id} if args.rig_id else {}))
    written = shift.write_shift(args.out_dir, cfg, overwrite=args.overwrite,
                                created_by=f"uwbcl {__version__} simulate --scenario shift")
    print(f"wrote {len(written)} passes ({cfg.rigs} rigs, cycles {cfg.first_cycle}-"
          f"{cfg.first_cycle + cfg.cycles - 1}), truth.csv and truth_plates.csv to {args.out_dir}")
    return 0


SIMULATED_RIG_ID = "sim-rig"  # a paper scenario's rig


SHIFT_DEFAULTS = {"cycles": 40, "rigs": 3, "first_cycle": 0}  # `simulate --scenario shift`


def _simulate(args: argparse.Namespace) -> int:
    if blocker := file_in_the_way(Path(args.out_dir)):
        print(f"uwbcl simulate: {args.out_dir}: {blocker} is not a directory", file=sys.stderr)
        return 2
    heights = config.parse_heights(args.heights)
    config.check_heights(heights, "command line", "--heights")
    if heights and len({archive.height_mm(h) for h in heights}) < len(heights):
        raise ConfigError("command line", "--heights", f"two heights within a millimetre, the archives' name "
                          f"unit: {list(heights)}")
    if args.rig_id is not None and not args.rig_id.strip():
        raise ConfigError("command line", "--rig-id", "empty (leave the flag out for the default)")
    if args.rigs is not None and args.rigs > MAX_SIMULATED_RIGS:
        raise ConfigError("command line", "--rigs", f"at most {MAX_SIMULATED_RIGS}, got {args.rigs}")
    given = [k for k in SHIFT_DEFAULTS if getattr(args, k) is not None]
    if args.scenario != "shift" and given:
        raise ConfigError("command line", f"--{given[0].replace('_', '-')}",
                          f"only with --scenario shift ({args.scenario} has its own rig and cycles)")
    for k, v in SHIFT_DEFAULTS.items():
        setattr(args, k, v if getattr(args, k) is None else getattr(args, k))
    if args.first_cycle + args.cycles > MAX_SIMULATED_CYCLES:
        raise ConfigError("command line", "--first-cycle", f"+ --cycles is {args.first_cycle + args.cycles}, "
                          f"more than {MAX_SIMULATED_CYCLES} (the rib and the truth are simulated from "
                          "cycle 0)")
    try:
        return _simulate_shift(args) if args.scenario == "shift" else _simulate_scenario(args)
    except OSError as exc:  # an archive already there (without --overwrite), a full disk
        print(f"uwbcl simulate: {exc.filename or args.out_dir}: {exc.strerror or exc}", file=sys.stderr)
        return 1


def _int_at_least(minimum: int):
    """An argparse type: an integer >= minimum."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value
    return parse


def _finite_in(low: float, high: float):
    """An argparse type: a finite number in [low, high)."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not (math.isfinite(value) and low <= value < high):
            where = f" in [{low:g}, {high:g})" if math.isfinite(low) or math.isfinite(high) else ""
            raise argparse.ArgumentTypeError(f"must be a finite number{where}, got {text}")
        return value
    return parse


def _simulate_scenario(args: argparse.Namespace) -> int:
    scenario = SCENARIOS[args.scenario]
    out = Path(args.out_dir)
    heights = config.parse_heights(args.heights)
    passes = scenario.simulate(snr_db=args.snr_db, speed_jitter=args.speed_jitter, seed=args.seed,
                               heights_m=heights, rig_id=args.rig_id or SIMULATED_RIG_ID)
    written = []
    for scan in passes:
        path = out / archive.default_relative_path(scan)
        archive.write_pass(path, scan, overwrite=args.overwrite, created_by=f"uwbcl {__version__} simulate")
        written.append(str(path.relative_to(out)))
    cycles = range(len(scenario.rig_positions_m))
    truth = {
        "scenario": scenario.name, "seed": args.seed, "snr_db": args.snr_db,
        "speed_jitter": args.speed_jitter,
        "rig_id": args.rig_id or SIMULATED_RIG_ID, "heights_m": list(heights or scenario.heights_m),
        "target_names": list(scenario.target_names),
        "targets_roadway_m": scenario.targets_roadway_m.tolist(),
        "cycles": [{
            "cycle": c,
            "rig_position_roadway_m": scenario.rig_positions_m[c].tolist(),
            "targets_radar_m": scenario.targets_radar_m(c).tolist(),
            "rotation_table_angle_deg": scenario.rotation_table_angle_deg(c),
            **({"advance_m": scenario.advance_m(c).tolist(),
                "retreat_m": float(scenario.advance_m(c)[0]), "creep_m": float(scenario.advance_m(c)[1]),
                "vertical_m": float(scenario.advance_m(c)[2])} if c > 0 else {}),
        } for c in cycles],
        "files": written,
    }
    write_text_atomic(out / "truth.json", json.dumps(truth, indent=2) + "\n")
    print(f"wrote {len(written)} passes and truth.json to {out}")
    return 0


def _process(args: argparse.Namespace) -> int:
    try:
        site = config.load_config(args.config) if args.config else config.SiteConfig()
        site = config.override(
            site, algorithm=args.algorithm, backend=args.backend, device=args.device, ac_mode=args.ac_mode,
            jobs=1 if args.profile else args.jobs, web_depth_m=args.web_depth,
            heights_m=config.parse_heights(args.heights),
            prior_window_m=tuple(args.prior_window) if args.prior_window else None,
            cache=False if args.no_cache else None, plots=True if args.plots else None,
            cycle_images=True if args.cycle_images else None)
        settings = site.processing_settings()
    except ConfigError as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        return 2
    usage = _scheduler_problem(args)
    if usage:
        print(f"uwbcl process: {usage}", file=sys.stderr)
        return 2
    # On a cluster the workers start the engine (cluster.connect checks them), not this process.
    local_engine = settings.backend == "opencl" and not args.scheduler
    if local_engine and not _engine_ready(settings.device, args.profile):
        return 2
    in_dir, out_dir = Path(args.in_dir), Path(args.out)
    usage = _directories_problem(in_dir, out_dir)
    if usage:
        print(f"uwbcl process: {usage}", file=sys.stderr)
        return 2
    try:
        with _signals_as_interrupts(), contextlib.ExitStack() as stack:
            runner = None
            if args.scheduler:
                from . import cluster

                runner = stack.enter_context(cluster.connect(args.scheduler, settings))
            report = batch.process_directory(in_dir, out_dir, settings, site.batch_options(
                progress=False if args.no_progress else None, follow_symlinks=args.follow_symlinks), runner)
    except BatchError as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        return 2
    except OutputError as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        return 1
    except NothingRead as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        for p in exc.problems:
            print(f"  {p.file}: {p.reason}", file=sys.stderr)
        return 1
    except interrupt.Interrupted as exc:
        print(f"uwbcl process: stopped by {exc.name}; workers stopped, partial work discarded, the previous "
              "outputs are intact", file=sys.stderr)
        return 128 + exc.signum
    if args.profile:
        _print_profile(settings)
    withdrawn = sum(r["status"] == outputs.WITHDRAWN for r in report.rows)
    flagged = sum(r["status"] not in ("ok", outputs.WITHDRAWN) for r in report.rows)
    unread = report.n_passes - report.n_detected - report.n_cached
    extra = "".join([f", {unread} not read or not focused" if unread else "",
                     f", {len(report.warnings)} warnings" if report.warnings else "",
                     f", {report.n_cache_damaged} damaged cache entries recomputed" if report.n_cache_damaged
                     else ""])
    kept = f", {withdrawn} withdrawn rows kept" if withdrawn else ""
    print(f"{report.n_passes} passes ({report.n_detected} focused, {report.n_cached} from the cache{extra}), "
          f"{len(report.cycles)} cycles located, {len(report.rows) - withdrawn} displacements ({flagged} "
          f"flagged{kept}, {report.n_new_or_revised} new or revised) written to {out_dir}")
    if report.errors:
        print(f"{len(report.errors)} problems, see {Path(args.out) / 'errors.csv'}:", file=sys.stderr)
        for p in report.errors:
            print(f"  {p.file}: {p.reason}", file=sys.stderr)
        return 1
    return 0

def _check(args: argparse.Namespace) -> int:
    """`uwbcl check IN_DIR`: exit 0 when every archive is read and every cycle usable, 1 on any problem (each
    printed, as `uwbcl process` would write it to errors.csv), 2 on usage errors."""
    from . import check

    try:
        site = config.load_config(args.config) if args.config else config.SiteConfig()
        site = config.override(site, heights_m=config.parse_heights(args.heights))
        settings = site.processing_settings()
        options = site.batch_options(follow_symlinks=args.follow_symlinks)
    except ConfigError as exc:
        print(f"uwbcl check: {exc}", file=sys.stderr)
        return 2
    in_dir = Path(args.in_dir)
    if not in_dir.is_dir():
        print(f"uwbcl check: {in_dir}: not a directory", file=sys.stderr)
        return 2
    report = check.check_directory(in_dir, settings, options)
    print(f"{in_dir}: {report.n_files} archives, {len(report.passes)} read")
    if not report.n_files and not report.problems:
        print(f"no archives under {in_dir} (files named *.h5 or *.hdf5, docs/archive-format.md section 1)")
        return 1
    for line in check.rig_lines(report, options):
        print(line)
    for title, found in (("warnings", report.warnings), ("problems", report.problems)):
        if found:
            print(f"{len(found)} {title}:")
            for p in found:
                print(f"  {p.kind}: {p.file}: {p.reason}")
    if not report.problems:
        said = f"; {len(report.warnings)} warnings above, worth reading first" if report.warnings else ""
        print(f"no problems: uwbcl process would use every pass{said}")
    if any(w.kind == "q_sign" for w in report.warnings):  # not a problem of the files, but no usable result
        print("q_sign: those rigs' passes will not focus as they are (conjugated data or the table angle's "
              "sign): their rows would all be flagged (docs/archive-format.md section 3)")
    return 1 if report.problems else 0


def _focus(args: argparse.Namespace) -> int:
    """`uwbcl focus ARCHIVE... --out DIR`: exit 2 on usage errors, 1 when an archive cannot be focused."""
    from . import commission, outputs

    try:
        outputs.require_matplotlib(Path(args.out))
        site = config.load_config(args.config) if args.config else config.SiteConfig()
        settings = config.override(site, algorithm=args.algorithm, backend=args.backend).processing_settings()
    except (ConfigError, BatchError) as exc:
        print(f"uwbcl focus: {exc}", file=sys.stderr)
        return 2
    out_dir = Path(args.out)
    if problem := _out_problem(out_dir):
        print(f"uwbcl focus: {problem}", file=sys.stderr)
        return 2
    if settings.backend == "opencl" and not _engine_ready(settings.device):
        return 2
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"uwbcl focus: --out {out_dir}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    paths = [Path(a) for a in args.archives]
    done, failed = [], 0
    for path, png in zip(paths, commission.png_names(paths)):
        try:
            image_h5 = out_dir / f"{Path(png).stem}.image.h5" if args.save_image else None
            result = commission.focus_one(path, out_dir / png, settings, str(path), image_h5)
        except archive.ArchiveError as exc:  # names the file itself
            print(f"uwbcl focus: {exc}", file=sys.stderr)
            failed += 1
            continue
        except ValueError as exc:
            print(f"uwbcl focus: {path}: {exc}", file=sys.stderr)
            failed += 1
            continue
        except OSError as exc:
            print(f"uwbcl focus: {path}: {exc.strerror or exc}", file=sys.stderr)
            failed += 1
            continue
        done.append(result)
        print(result.summary())
    try:
        csv_path = commission.write_detections_csv(out_dir, done)
    except OSError as exc:
        print(f"uwbcl focus: {out_dir}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"{len(done)} passes focused, {sum(len(p.detections) for p in done)} detections: {csv_path} "
          f"and {len(done)} images in {out_dir}" + (f"; {failed} archives failed" if failed else ""))
    return 1 if failed else 0


def _scheduler_problem(args: argparse.Namespace) -> str:
    """Why --scheduler cannot be used with the other flags given ("" when it can)."""
    if not args.scheduler:
        return ""
    if args.jobs is not None:
        return "--jobs and --scheduler: the cluster's workers are the jobs; give one of them"
    if args.profile:
        return "--profile runs the engine in this process; it cannot be used with --scheduler"
    return ""


def _calibrate(args: argparse.Namespace) -> int:
    """`uwbcl calibrate ARCHIVE... --reflector X,Y,Z ...`: exit 2 on usage errors, 1 when an archive cannot be
    read or no reflector is found."""
    import dataclasses

    from . import calibrate

    name = "uwbcl calibrate"
    try:
        reflectors = [calibrate.parse_reflector(r) for r in args.reflector]
        if not (math.isfinite(args.gate_m) and args.gate_m > 0):
            raise ValueError(f"--gate-m must be finite and > 0, got {args.gate_m}")
    except ValueError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    try:
        site = config.load_config(args.config) if args.config else config.SiteConfig()
        if "search" not in site.detection:  # reflectors often stand beyond the rail's ends
            site = dataclasses.replace(site, detection={**site.detection, "search": "footprint"})
        settings = config.override(site, algorithm=args.algorithm, backend=args.backend).processing_settings()
    except ConfigError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    out = Path(args.write_config) if args.write_config else None
    if out is not None and (out.is_dir() or not out.parent.is_dir() or out.is_symlink()
                            or (out.exists() and not out.is_file())):
        why = ("is a directory" if out.is_dir() else f"{out.parent} is not a directory"
               if not out.parent.is_dir() else "is a symbolic link: give the file it names"
               if out.is_symlink() else "is not a regular file (a FIFO or device): give a site file")
        print(f"{name}: --write-config {out}: {why}", file=sys.stderr)
        return 2
    if settings.backend == "opencl" and not _engine_ready(settings.device):
        return 2
    scans = _read_archives(args.archives, settings.limits, name)
    if scans is None:
        return 1
    try:
        result = calibrate.calibrate(scans, reflectors, settings, start_delay_s=site.range_delay_s,
                                     gate_m=args.gate_m)
    except ValueError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 1
    for line in calibrate.report_lines(result, [s.range_delay_s for s in scans]):
        print(line)
    if out is not None:
        try:
            calibrate.write_config(out, Path(args.config) if args.config else None, result.delay_s)
        except ConfigError as exc:
            print(f"{name}: {exc}", file=sys.stderr)
            return 1
        except OSError as exc:
            print(f"{name}: --write-config {out}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"wrote [radar] range_delay_s = {result.delay_s:.6e} to {out}")
    return 0


def _read_archives(paths: list[str], limits, name: str) -> list | None:
    """Every archive read, or None after a message naming each one that cannot be."""
    scans, failed = [], 0
    for path in paths:
        try:
            scans.append(archive.read_pass(path, limits))
        except archive.ArchiveError as exc:  # names the file itself
            print(f"{name}: {exc}", file=sys.stderr)
            failed += 1
        except OSError as exc:
            print(f"{name}: {path}: {exc.strerror or exc}", file=sys.stderr)
            failed += 1
    if failed:
        print(f"{name}: {failed} archives could not be read; nothing calibrated", file=sys.stderr)
        return None
    return scans


def _out_problem(out_dir: Path) -> str:
    """Why --out cannot be a directory ("" when it can): it, or a folder above it, is a file."""
    blocker = file_in_the_way(out_dir)
    return f"--out {out_dir}: {blocker} is not a directory" if blocker else ""


def _directories_problem(in_dir: Path, out_dir: Path) -> str:
    """Why ARCHIVE_DIR and --out cannot be used together ("" when they can)."""
    if not in_dir.is_dir():
        return f"{in_dir}: not a directory"
    if problem := _out_problem(out_dir):
        return problem
    real_in, real_out = in_dir.resolve(), out_dir.resolve()
    if real_in == real_out:
        return f"--out {out_dir} is the archive directory itself; give the outputs a directory of their own"
    if real_out in real_in.parents:
        return f"the archive directory {in_dir} lies inside --out {out_dir}; its archives would be skipped"
    return ""


@contextlib.contextmanager
def _signals_as_interrupts():
    """SIGINT and SIGTERM raise Interrupted in the main thread (`interrupt.request`: remembered too, so one
    that lands in a finalizer is raised again at the batch's next check): the batch stops its workers on the
    way out."""
    def handler(signum, frame):
        interrupt.request(signum)

    interrupt.clear()
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    old_hook, sys.unraisablehook = sys.unraisablehook, interrupt.quiet_unraisable(sys.unraisablehook)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        sys.unraisablehook = old_hook
        interrupt.clear()


def _engine_ready(device: str | None, profile: bool = False) -> bool:
    """Start the OpenCL engine before any work, so a missing runtime is one clear message, not a failure
    per pass."""
    from . import opencl
    from .focus.engine import shared_engine

    try:
        engine = shared_engine(device, profile=profile or None)
    except opencl.OpenClUnavailable as exc:
        print(f"uwbcl: OpenCL backend unavailable: {exc}", file=sys.stderr)
        return False
    logging.getLogger("uwbcl").info("OpenCL engine on %s (start-up %.2f s)", engine.device.name.strip(),
                                    engine.startup_s)
    return True


def _print_profile(settings) -> None:
    """`process --profile`: the shared engine's per-stage device times (it ran every pass: --jobs 1)."""
    if settings.backend != "opencl":
        print("--profile: the numpy backend has no device profile", file=sys.stderr)
        return
    from .focus.engine import shared_engine

    engine = shared_engine(settings.device)
    print(f"device time per stage on {engine.device.name.strip()} "
          "(passes read from the cache are not focused):")
    print(engine.profile_table())


def _devices(args: argparse.Namespace) -> int:
    from . import opencl

    try:
        print(opencl.describe_devices())
    except opencl.OpenClUnavailable as exc:
        print(f"uwbcl devices: {exc}", file=sys.stderr)
        return 2
    return 0


# The flag of each import value (`ImportOptions` fields, and the track's): messages name what the user typed.
_IMPORT_FLAGS = {
    "height_m": "--height-m", "rotation_table_angle_deg": "--table-angle-deg",
    "boresight_y_sign": "--boresight-y-sign", "reference_range_m": "--reference-range-m",
    "reference_point_m": "--reference-point", "antenna_aperture_m": "--aperture-m",
    "pulse_repetition_frequency_hz": "--prf-hz", "range_delay_s": "--range-delay-s", "rig_id": "--rig-id",
    "cycle": "--cycle", "pass_start_time": "--pass-start-time", "carrier_frequency_hz": "--carrier-hz",
    "bandwidth_hz": "--bandwidth-hz", "decimation": "--decimation", "min_step_m": "--min-step-m",
    "keep_raw_rf": "--no-raw-rf",
    "pulse": "--pulse", "pulse_window_start_m": "--pulse-window-m", "pulse_window_stop_m": "--pulse-window-m",
    "speed_m_s": "--speed-m-s", "time_offset_s": "--time-offset-s",
}


def _import_options(args: argparse.Namespace) -> tuple[passes.ImportOptions, dict[str, str]]:
    """[import] of --config, then the flags given; and where each value came from (key -> the flag, or the
    site file's key), for messages. ConfigError for a bad value."""
    values, origin = {}, {}
    if args.config:
        site = config.read_toml(args.config)
        values = passes.options_from_table(site.get("import", {}), args.config)
        origin = {k: f"{args.config}: import.{k}" for k in values}
        if isinstance(site.get("radar"), dict):  # the calibrated delay (`uwbcl calibrate`), checked
            calibrated = config.parse_config({"radar": site["radar"]}, args.config).range_delay_s
            if calibrated is not None and values.setdefault("range_delay_s", calibrated) != calibrated:
                raise ConfigError(args.config, "import.range_delay_s",
                                  f"{values['range_delay_s']!r} differs from radar.range_delay_s "
                                  f"({calibrated!r}); keep one")
            if calibrated is not None and "range_delay_s" not in origin:
                origin["range_delay_s"] = f"{args.config}: radar.range_delay_s"
    flags = {"height_m": args.height_m, "rotation_table_angle_deg": args.table_angle_deg,
             "boresight_y_sign": args.boresight_y_sign, "reference_range_m": args.reference_range_m,
             "reference_point_m": tuple(args.reference_point) if args.reference_point else None,
             "antenna_aperture_m": args.aperture_m, "pulse_repetition_frequency_hz": args.prf_hz,
             "range_delay_s": args.range_delay_s, "rig_id": args.rig_id, "cycle": args.cycle,
             "pass_start_time": args.pass_start_time, "carrier_frequency_hz": args.carrier_hz,
             "bandwidth_hz": args.bandwidth_hz, "decimation": args.decimation,
             "min_step_m": args.min_step_m,
             "keep_raw_rf": False if args.no_raw_rf else None, "pulse": args.pulse,
             "pulse_window_start_m": args.pulse_window_m[0] if args.pulse_window_m else None,
             "pulse_window_stop_m": args.pulse_window_m[1] if args.pulse_window_m else None}
    given = {k: v for k, v in flags.items() if v is not None}
    values.update(given)
    origin.update({k: _IMPORT_FLAGS[k] for k in given})
    return passes.ImportOptions(**values), origin


def _check_import_flags(args: argparse.Namespace, options: passes.ImportOptions) -> None:
    """OptionError for flags that contradict or lack each other, or a bad value (before the file is read)."""
    passes.check_options(options)
    if args.speed_m_s is not None:
        passes.check_speed(args.speed_m_s)
        if options.height_m is None:
            raise OptionError("height_m", "required with --speed-m-s (a constant-speed track has no z_m to "
                                          "take the rail height from)")
    if args.time_offset_s is not None and not math.isfinite(args.time_offset_s):
        raise OptionError("time_offset_s", f"must be finite, got {args.time_offset_s}")


def _import(args: argparse.Namespace) -> int:
    """`uwbcl import <radar> FILE --out DIR`: exit 2 on usage errors (a bad flag value, also one that does not
    fit the recording), 1 on a file that cannot be imported."""
    name = f"uwbcl import {args.reader}"
    if (args.positions is None) == (args.speed_m_s is None):
        print(f"{name}: give exactly one of --positions POS.csv and --speed-m-s V", file=sys.stderr)
        return 2
    if args.time_offset_s is not None and args.positions is None:
        print(f"{name}: --time-offset-s needs --positions", file=sys.stderr)
        return 2
    origin = {}

    def usage(exc: OptionError) -> int:
        print(f"{name}: {origin.get(exc.key, _IMPORT_FLAGS.get(exc.key, exc.key))}: {exc.reason}",
              file=sys.stderr)
        return 2

    try:
        options, origin = _import_options(args)
        _check_import_flags(args, options)
    except OptionError as exc:
        return usage(exc)
    except ConfigError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    source, out = Path(args.scan_file), Path(args.out)
    if problem := _out_problem(out):
        print(f"{name}: {problem}", file=sys.stderr)
        return 2
    made = []  # the directories this import creates, removed again if it fails
    try:
        # the positions first: a missing height is a usage error before a recording of a minute is read
        positions = passes.read_positions_csv(args.positions) if args.positions else None
        if positions is not None:
            passes.check_height_source(options, positions.z_m)
        recording = registry.get_reader(args.reader).read(source)
        if positions is not None:
            track = passes.track_from_positions(recording, positions, args.time_offset_s, options.min_step_m)
        else:
            track = passes.constant_speed_track(recording, args.speed_m_s)
        result = passes.build_pass(recording, track, options, file_mtime_s=source.stat().st_mtime)
        path = out / archive.default_relative_path(result.scan)
        made = [d for d in (path.parent, *path.parent.parents) if not d.exists()]
        archive.write_pass(path, result.scan, overwrite=args.overwrite,
                           created_by=f"uwbcl {__version__} import {args.reader} {source.name}")
    except OptionError as exc:
        _remove_empty(made)
        return usage(exc)
    except (RecordingError, archive.ArchiveError, ValueError) as exc:
        _remove_empty(made)
        print(f"{name}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        _remove_empty(made)
        print(f"{name}: {exc.filename or source}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except BaseException:
        _remove_empty(made)
        raise
    _print_import_summary(source, recording, track, result, options, aligned=args.time_offset_s is None)
    print(f"wrote 1 archive: {path}")
    return 0


def _print_import_summary(source, recording, track, result, options, *, aligned: bool) -> None:
    """What `uwbcl import` says of a recording it converted (docs/importing.md); warnings on stderr.
    `aligned`: the clocks were aligned on the first motion (no --time-offset-s)."""
    band, scan = result.band, result.scan
    repeated = f", {recording.n_repeated} repeated dropped" if recording.n_repeated else ""
    lost = recording.n_lost
    lost_text = f", {lost} lost whole (the radar's scan counter skips them)" if lost else ""
    print(f"{source}: {recording.n_scans + recording.n_repeated} complete scans read, "
          f"{recording.n_dropped} incomplete dropped{repeated}{lost_text}")
    if track.time_offset_s is not None:
        print(f"positions: time offset {track.time_offset_s:+.3f} s; {track.n_outside_log} scans outside "
              f"the log, {track.n_rest} at rest or turning back trimmed")
        if aligned:
            print("warning: the clocks were aligned on the first motion (no --time-offset-s): the echo "
                  "shows the motion a scene-dependent time late, which changes from pass to pass by about a "
                  "scan (an independent tester: 15 ms standard deviation, 3 mm of travel at 0.2 m/s), and "
                  "the bounds do not include it: give --time-offset-s for millimetre displacements "
                  "(docs/importing.md section 4)", file=sys.stderr)
        if track.n_outside_log and aligned:
            print(f"warning: the clocks were aligned on the first motion, which assumes the recording starts "
                  f"at rest; {track.n_outside_log} scans fell outside the positions log: give "
                  "--time-offset-s if it did not start at rest", file=sys.stderr)
    print(f"spectrum: centre {band.centre_hz / 1e9:.3f} GHz, -10 dB band {band.low_hz / 1e9:.3f}-"
          f"{band.high_hz / 1e9:.3f} GHz ({band.bandwidth_hz / 1e9:.3f} GHz), "
          f"peak {band.peak_hz / 1e9:.3f} GHz")
    fixed = [f"{what} {v / 1e9:.4f} GHz" for what, v in (("carrier", options.carrier_frequency_hz),
                                                       ("-10 dB bandwidth", options.bandwidth_hz)) if v]
    if fixed:
        print(f"written: {', '.join(fixed)} (given, not measured)")
    print(f"baseband: {scan.radar.sample_rate_hz / 1e9:.4g} GHz complex (RF / {result.decimation}), "
          f"{scan.samples_per_pulse} samples x {scan.n_pulses} pulses, x {scan.pulse_position_m[0]:+.3f} to "
          f"{scan.pulse_position_m[-1]:+.3f} m")
    for note in result.notes:
        print(note)
    if scan.n_pulses < MIN_FOCUS_PULSES:
        print(f"warning: {scan.n_pulses} pulses: too few to focus (at least {MIN_FOCUS_PULSES}); the archive "
              "is written, but `uwbcl focus`, `check` and `process` will refuse it", file=sys.stderr)
    gaps = geometry.track_gaps(scan.pulse_position_m)
    if len(gaps):
        print(f"warning: {geometry.describe_gaps(gaps)}", file=sys.stderr)
    print(f"pass start: {scan.pass_start_time}" + ("" if options.pass_start_time else
          " (the file's modification time minus the recording's length; --pass-start-time sets it)"))
    if options.range_delay_s == 0.0:
        print("warning: range_delay_s = 0 (uncalibrated): ranges include the radar's internal delay",
              file=sys.stderr)


def _remove_empty(directories: list[Path]) -> None:
    """Remove the directories a failed import created (deepest first), each only if still empty."""
    for d in directories:
        with contextlib.suppress(OSError):
            d.rmdir()


def _add_import_commands(sub) -> None:
    imp = sub.add_parser("import", help="convert a radar's own recording into a scan archive "
                                        "(docs/importing.md)")
    readers = imp.add_subparsers(dest="reader", required=True)
    for reader in registry.READERS.values():
        r = readers.add_parser(reader.name, help=reader.description)
        r.add_argument("scan_file")
        r.add_argument("--out", required=True,
                       help="archive root; the pass goes to its default relative path")
        r.add_argument("--positions", help="rail positions CSV: time_s,x_m[,y_m,z_m] (docs/importing.md)")
        r.add_argument("--time-offset-s", type=float,
                       help="positions time = scan time + this (default: align the first motion)")
        r.add_argument("--speed-m-s", type=float,
                       help="no positions: a straight constant-speed track (commissioning and tests only)")
        r.add_argument("--config", help="site TOML; its [import] table gives defaults for the flags below")
        r.add_argument("--height-m", type=float, help="rail height (default: median z_m of the positions)")
        r.add_argument("--table-angle-deg", type=float, help="rotation table angle (squint), default 0")
        r.add_argument("--boresight-y-sign", type=int, choices=(-1, 1), help="side of the rib, default -1")
        r.add_argument("--reference-point", type=float, nargs=3, metavar=("X", "Y", "Z"),
                       help="scene centre in the radar frame (default: on boresight at --reference-range-m)")
        r.add_argument("--reference-range-m", type=float,
                       help="default 3.0, or the middle of the recording's delay window if 3.0 lies outside")
        r.add_argument("--aperture-m", type=float, help="antenna aperture along the rail, default 0.14")
        r.add_argument("--prf-hz", type=float, help="nominal PRF (default: 1 / median scan interval)")
        r.add_argument("--range-delay-s", type=float,
                       help="calibrated two-way antenna/cable delay in s, within +-1e-6 (default 0: "
                            "uncalibrated); a negative value in exponent form needs '=': "
                            "--range-delay-s=-1e-9")
        r.add_argument("--pulse", choices=("gaussian", "measured"),
                       help="the archive's pulse: the Gaussian of the -10 dB band (default) or measured from "
                            "the reference echo in --pulse-window-m (archive 1.2)")
        r.add_argument("--pulse-window-m", type=float, nargs=2, metavar=("START", "STOP"),
                       help="one-way range window of the pulse's reference echo, the direct coupling "
                            "(default 1.5 2.6)")
        r.add_argument("--rig-id")
        r.add_argument("--cycle", type=int)
        r.add_argument("--pass-start-time", help="ISO 8601 UTC (default: file time minus the recording)")
        r.add_argument("--carrier-hz", type=float, help="mix-down frequency (default: measured band centre)")
        r.add_argument("--bandwidth-hz", type=float,
                       help="the archive's -10 dB bandwidth (default: measured); fix it, as --carrier-hz, "
                            "where a cycle's heights come from separate recordings")
        r.add_argument("--decimation", type=int,
                       help="complex rate = RF rate / this (default: from the band)")
        r.add_argument("--min-step-m", type=float, help="smaller moves per scan are rest (default 1e-4)")
        r.add_argument("--no-raw-rf", action="store_true", help="do not keep /raw/rf beside the baseband")
        r.add_argument("--overwrite", action="store_true", help="replace an existing archive")
        r.set_defaults(func=_import)


class _Parser(argparse.ArgumentParser):
    """argparse's parser, reading a negative number in scientific notation (`--range-delay-s -1e-9`,
    `--pulse-window-m -2e-1 3e-1`) as a value, as it reads -0.2, not as an unknown option."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="uwbcl", description="UWB SAR measurement of longwall retreat and creep.")
    p.add_argument("--version", action="version", version=f"uwbcl {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    s = sub.add_parser("simulate", help="write the scan archives of a simulated scenario and its truth.json")
    s.add_argument("out_dir")
    s.add_argument("--scenario", choices=[*sorted(SCENARIOS), "shift"], default="paper-sim1",
                   help="a paper scenario (2 cycles), or 'shift': rigs x cycles of a production shift")
    s.add_argument("--seed", type=_int_at_least(0), default=0)
    s.add_argument("--snr-db", type=_finite_in(-math.inf, math.inf), default=None,
                   help="receiver SNR per raw sample relative to a unit echo (default: no noise)")
    s.add_argument("--speed-jitter", type=_finite_in(0.0, 1.0), default=0.0,
                   help="rail speed fluctuation as a fraction of the set speed, e.g. 0.1 for +-10%%")
    s.add_argument("--heights", nargs="+", help="rail heights in metres, e.g. 0.2 0.6 or 0.2,0.6 "
                   "(default: the scenario's; shift: 0.2 0.6)")
    s.add_argument("--cycles", type=_int_at_least(1), default=None,
                   help="shift: cutting cycles per rig (default 40)")
    s.add_argument("--rigs", type=_int_at_least(1), default=None, help="shift: rigs (default 3)")
    s.add_argument("--first-cycle", type=_int_at_least(0), default=None,
                   help="shift: first cycle to write, to append a later shift to an archive tree (the rib "
                   f"and truth.csv cover cycles 0 on: first cycle + cycles <= {MAX_SIMULATED_CYCLES})")
    s.add_argument("--rig-id", help=f"the rig's id (default {SIMULATED_RIG_ID}); shift: the prefix of its "
                   "rigs' ids, ID-1, ID-2, ... (default rig)")
    s.add_argument("--overwrite", action="store_true", help="replace existing archives")
    s.set_defaults(func=_simulate)

    q = sub.add_parser("process", help="focus every pass under IN_DIR and write the displacement time series")
    q.add_argument("in_dir")
    q.add_argument("--out", required=True, help="output directory (docs/outputs.md)")
    q.add_argument("--config", help="site configuration, TOML (docs/configuration.md); flags override it")
    q.add_argument("--backend", choices=BACKENDS, default=None,
                   help="opencl: the OpenCL engine (default); numpy: the float64 reference")
    q.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' indices or part of its name (`uwbcl devices`); "
                        "default: $PYOPENCL_CTX, else the first GPU, else the first device")
    q.add_argument("--algorithm", choices=ALGORITHMS, default=None, help="default nlcs")
    q.add_argument("--ac-mode", choices=("exact", "series"), default=None,
                   help="NLCS azimuth compression: exact-reference (default) or the series of eq. 17")
    q.add_argument("--jobs", type=int, default=None,
                   help="worker processes (default: all cores with numpy, 2 with opencl)")
    q.add_argument("--web-depth", type=float, default=None,
                   help="nominal advance per cycle in metres: the prior that resolves look-alike plates")
    q.add_argument("--prior-window", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="half-widths of the web-depth prior's window in metres (default 0.4 0.3 0.5; needs "
                   "a web depth: --web-depth or the site file's)")
    q.add_argument("--heights", nargs="+",
                   help="expected rail heights in metres; passes at others are errors")
    q.add_argument("--plots", action="store_true", help="write plots/timeseries_<rig>.png (needs matplotlib)")
    q.add_argument("--cycle-images", action="store_true",
                   help="write a focused image per pass with the detections marked (slow: refocuses)")
    q.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="focus on a Dask cluster: its scheduler's tcp://HOST:PORT, or local:N for N worker "
                        "processes on this machine (needs uwbcl[cluster]; docs/outputs.md section 5.1)")
    q.add_argument("--no-cache", action="store_true", help="refocus every pass, ignoring OUT/.uwbcl-cache")
    q.add_argument("--profile", action="store_true",
                   help="opencl: print the device time per focusing stage after the run (runs with --jobs 1)")
    q.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    q.add_argument("--follow-symlinks", action="store_true",
                   help="read archives linked from outside ARCHIVE_DIR and enter linked directories")
    q.set_defaults(func=_process)

    c = sub.add_parser("check", help="read and group every archive under IN_DIR as process would, without "
                                     "focusing: per rig the cycles, heights, radar and geometry found, and "
                                     "every problem")
    c.add_argument("in_dir")
    c.add_argument("--config", help="site configuration, TOML: the expected heights and the read limits")
    c.add_argument("--heights", nargs="+",
                   help="expected rail heights in metres; passes at others are errors")
    c.add_argument("--follow-symlinks", action="store_true",
                   help="read archives linked from outside IN_DIR and enter linked directories")
    c.set_defaults(func=_check)

    f = sub.add_parser("focus", help="commissioning: focus single passes, write their images and "
                                     "detections.csv (docs/outputs.md)")
    f.add_argument("archives", nargs="+", metavar="ARCHIVE")
    f.add_argument("--out", required=True, help="output directory: one PNG per pass and detections.csv")
    f.add_argument("--backend", choices=BACKENDS, default=None, help="opencl (default) or numpy")
    f.add_argument("--algorithm", choices=ALGORITHMS, default=None, help="default nlcs")
    f.add_argument("--config", help="site configuration, TOML (docs/configuration.md); flags override it")
    f.add_argument("--save-image", action="store_true",
                   help="also write each pass's complex image and axes as <pass>.image.h5 (docs/outputs.md)")
    f.set_defaults(func=_focus)

    k = sub.add_parser("calibrate", help="the radar's delay offset from passes over surveyed reflectors "
                                         "(docs/outputs.md)")
    k.add_argument("archives", nargs="+", metavar="ARCHIVE")
    k.add_argument("--reflector", action="append", required=True, metavar="X,Y,Z",
                   help="a surveyed reflector in the radar frame, metres; repeat for each")
    k.add_argument("--config", help="site configuration, TOML: detection settings and the start delay "
                                    "([radar] range_delay_s)")
    k.add_argument("--write-config", metavar="OUT.toml",
                   help="write the site file (--config's, else a new one) with [radar] range_delay_s set")
    k.add_argument("--gate-m", type=float, default=0.5,
                   help="a reflector's detection lies this close to its surveyed (x, R_c), m (default 0.5)")
    k.add_argument("--backend", choices=BACKENDS, default=None, help="opencl (default) or numpy")
    k.add_argument("--algorithm", choices=ALGORITHMS, default=None, help="default nlcs")
    k.set_defaults(func=_calibrate)

    _add_import_commands(sub)

    d = sub.add_parser("devices", help="list the OpenCL platforms and devices (specs for --device)")
    d.set_defaults(func=_devices)
    from .acquisition.cli import add_acquisition_commands  # simulate-device, acquire, demo

    add_acquisition_commands(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s")
    try:
        return args.func(args)
    except ConfigError as exc:  # a flag value no subcommand caught: still a usage error, not a traceback
        print(f"uwbcl {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"uwbcl {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # whoever read our output went away (`uwbcl focus ... | head`): stop quietly, as the shell's tools do;
        # stdout to /dev/null so that the interpreter's last flush does not complain again
        with contextlib.suppress(OSError, ValueError, io.UnsupportedOperation):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE


if __name__ == "__main__":
    sys.exit(main())
