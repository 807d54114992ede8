"""Command line: `uwbcl simulate` writes archives of a simulated shift, `uwbcl process` measures the advance."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from . import __version__, archive, pipeline
from .scenarios import SCENARIOS


def _heights(values) -> tuple[float, ...] | None:
    """--heights 0.2 0.6 or --heights 0.2,0.6."""
    if not values:
        return None
    return tuple(float(v) for item in values for v in str(item).split(",") if v.strip())


def _simulate_shift(args: argparse.Namespace) -> int:
    from . import shift

    cfg = shift.ShiftConfig(cycles=args.cycles, rigs=args.rigs, first_cycle=args.first_cycle, seed=args.seed,
                            snr_db=args.snr_db, speed_jitter=args.speed_jitter,
                            **({"heights_m": _heights(args.heights)} if args.heights else {}))
    written = shift.write_shift(args.out_dir, cfg, overwrite=args.overwrite,
                                created_by=f"uwbcl {__version__} simulate --scenario shift")
    print(f"wrote {len(written)} passes ({cfg.rigs} rigs, cycles {cfg.first_cycle}-"
          f"{cfg.first_cycle + cfg.cycles - 1}), truth.csv and truth_plates.csv to {args.out_dir}")
    return 0


def _simulate(args: argparse.Namespace) -> int:
    if args.scenario == "shift":
        return _simulate_shift(args)
    scenario = SCENARIOS[args.scenario]
    out = Path(args.out_dir)
    heights = _heights(args.heights)
    passes = scenario.simulate(snr_db=args.snr_db, speed_jitter=args.speed_jitter, seed=args.seed,
                               heights_m=heights, rig_id=args.rig_id)
    written = []
    for scan in passes:
        path = out / archive.default_relative_path(scan)
        archive.write_pass(path, scan, overwrite=args.overwrite, created_by=f"uwbcl {__version__} simulate")
        written.append(str(path.relative_to(out)))
    cycles = range(len(scenario.rig_positions_m))
    truth = {
        "scenario": scenario.name, "seed": args.seed, "snr_db": args.snr_db, "speed_jitter": args.speed_jitter,
        "rig_id": args.rig_id, "heights_m": list(heights or scenario.heights_m),
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
    tmp = out / ".truth.json.partial"
    tmp.write_text(json.dumps(truth, indent=2) + "\n")
    tmp.replace(out / "truth.json")
    print(f"wrote {len(written)} passes and truth.json to {out}")
    return 0


def _process(args: argparse.Namespace) -> int:
    from . import batch, config

    try:
        site = config.load_config(args.config) if args.config else config.SiteConfig()
        site = config.override(
            site, algorithm=args.algorithm, backend=args.backend, device=args.device, ac_mode=args.ac_mode,
            jobs=1 if args.profile else args.jobs, web_depth_m=args.web_depth,
            heights_m=_heights(args.heights),
            prior_window_m=tuple(args.prior_window) if args.prior_window else None,
            cache=False if args.no_cache else None, plots=True if args.plots else None,
            cycle_images=True if args.cycle_images else None)
        settings = site.processing_settings()
    except config.ConfigError as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        return 2
    if settings.backend == "opencl" and not _engine_ready(settings.device, args.profile):
        return 2
    in_dir = Path(args.in_dir)
    if not in_dir.is_dir():
        print(f"uwbcl process: {in_dir}: not a directory", file=sys.stderr)
        return 2
    try:
        report = pipeline.process_directory(in_dir, Path(args.out), settings, site.batch_options(
            progress=False if args.no_progress else None))
    except batch.BatchError as exc:
        print(f"uwbcl process: {exc}", file=sys.stderr)
        return 2
    if args.profile:
        _print_profile(settings)
    flagged = sum(r["status"] != "ok" for r in report.rows)
    print(f"{report.n_passes} passes ({report.n_detected} focused, {report.n_cached} from the cache), "
          f"{len(report.cycles)} cycles located, {len(report.rows)} displacements ({flagged} flagged) "
          f"written to {Path(args.out)}")
    if report.errors:
        print(f"{len(report.errors)} problems, see {Path(args.out) / 'errors.csv'}:", file=sys.stderr)
        for p in report.errors:
            print(f"  {p.file}: {p.reason}", file=sys.stderr)
        return 1
    return 0


def _engine_ready(device: str | None, profile: bool = False) -> bool:
    """Start the OpenCL engine before any work, so a missing runtime is one clear message, not a failure per
    pass (with `profile`, an engine that records every device command: `_print_profile`)."""
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


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="uwbcl", description="UWB SAR measurement of longwall retreat and creep.")
    p.add_argument("--version", action="version", version=f"uwbcl {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write the scan archives of a simulated scenario and its truth.json")
    s.add_argument("out_dir")
    s.add_argument("--scenario", choices=[*sorted(SCENARIOS), "shift"], default="paper-sim1",
                   help="a paper scenario (2 cycles), or 'shift': rigs x cycles of a production shift")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--snr-db", type=float, default=None,
                   help="receiver SNR per raw sample relative to a unit echo (default: no noise)")
    s.add_argument("--speed-jitter", type=float, default=0.0,
                   help="rail speed fluctuation as a fraction of the set speed, e.g. 0.1 for +-10%%")
    s.add_argument("--heights", nargs="+", help="rail heights in metres, e.g. 0.2 0.6 or 0.2,0.6 "
                   "(default: the scenario's; shift: 0.2 0.6)")
    s.add_argument("--cycles", type=int, default=40, help="shift: cutting cycles per rig (default 40)")
    s.add_argument("--rigs", type=int, default=3, help="shift: rigs (default 3)")
    s.add_argument("--first-cycle", type=int, default=0,
                   help="shift: first cycle to write, to append a later shift to an archive tree")
    s.add_argument("--rig-id", default="sim-rig")
    s.add_argument("--overwrite", action="store_true", help="replace existing archives")
    s.set_defaults(func=_simulate)

    q = sub.add_parser("process", help="focus every pass under IN_DIR and write the displacement time series")
    q.add_argument("in_dir")
    q.add_argument("--out", required=True, help="output directory (docs/outputs.md)")
    q.add_argument("--config", help="site configuration, TOML (docs/configuration.md); flags override it")
    q.add_argument("--backend", choices=pipeline.BACKENDS, default=None,
                   help="opencl: the OpenCL engine (default); numpy: the float64 reference")
    q.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' indices or part of its name (`uwbcl devices`); "
                        "default: $PYOPENCL_CTX, else the first GPU, else the first device")
    q.add_argument("--algorithm", choices=pipeline.ALGORITHMS, default=None, help="default nlcs")
    q.add_argument("--ac-mode", choices=("exact", "series"), default=None,
                   help="NLCS azimuth compression: exact-reference (default) or the series of eq. 17")
    q.add_argument("--jobs", type=int, default=None,
                   help="worker processes (default: all cores with numpy, 2 with opencl)")
    q.add_argument("--web-depth", type=float, default=None,
                   help="nominal advance per cycle in metres: the prior that resolves look-alike plates")
    q.add_argument("--prior-window", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="half-widths of the prior window in metres (default 0.4 0.3 0.5)")
    q.add_argument("--heights", nargs="+", help="expected rail heights in metres; passes at others are errors")
    q.add_argument("--plots", action="store_true", help="write plots/timeseries_<rig>.png (needs matplotlib)")
    q.add_argument("--cycle-images", action="store_true",
                   help="write a focused image per pass with the detections marked (slow: refocuses)")
    q.add_argument("--no-cache", action="store_true", help="refocus every pass, ignoring OUT/.uwbcl-cache")
    q.add_argument("--profile", action="store_true",
                   help="opencl: print the device time per focusing stage after the run (runs with --jobs 1)")
    q.add_argument("--no-progress", action="store_true", help="no progress bar even on a terminal")
    q.set_defaults(func=_process)

    d = sub.add_parser("devices", help="list the OpenCL platforms and devices (specs for --device)")
    d.set_defaults(func=_devices)
    from .acquisition.cli import add_acquisition_commands  # simulate-device, acquire, demo

    add_acquisition_commands(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
