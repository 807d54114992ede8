"""Command line: `uwbcl simulate` writes archives of a simulated shift, `uwbcl process` measures the advance."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from . import __version__, archive, pipeline
from .scenarios import SCENARIOS


def _simulate(args: argparse.Namespace) -> int:
    scenario = SCENARIOS[args.scenario]
    out = Path(args.out_dir)
    heights = tuple(args.heights) if args.heights else None
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
    settings = pipeline.ProcessingSettings(algorithm=args.algorithm, backend=args.backend, device=args.device,
                                           ac_mode=args.ac_mode)
    if args.backend == "opencl" and not _engine_ready(args.device):
        return 2
    in_dir = Path(args.in_dir)
    if not in_dir.is_dir():
        print(f"uwbcl process: {in_dir}: not a directory", file=sys.stderr)
        return 2
    report = pipeline.process_directory(in_dir, Path(args.out), settings)
    print(f"{len(report.cycles)} cycles located, {len(report.rows)} displacements written to "
          f"{Path(args.out) / 'displacements.csv'}")
    if report.errors:
        print(f"{len(report.errors)} problems, see {Path(args.out) / 'errors.csv'}:", file=sys.stderr)
        for file, reason in report.errors:
            print(f"  {reason}", file=sys.stderr)
        return 1
    return 0


def _engine_ready(device: str | None) -> bool:
    """Start the OpenCL engine before any work, so a missing runtime is one clear message, not a failure per pass."""
    from . import opencl
    from .focus.engine import shared_engine

    try:
        engine = shared_engine(device)
    except opencl.OpenClUnavailable as exc:
        print(f"uwbcl: OpenCL backend unavailable: {exc}", file=sys.stderr)
        return False
    logging.getLogger("uwbcl").info("OpenCL engine on %s (start-up %.2f s)", engine.device.name.strip(),
                                    engine.startup_s)
    return True


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
    s.add_argument("--scenario", choices=sorted(SCENARIOS), default="paper-sim1")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--snr-db", type=float, default=None,
                   help="receiver SNR per raw sample relative to a unit echo (default: no noise)")
    s.add_argument("--speed-jitter", type=float, default=0.0,
                   help="rail speed fluctuation as a fraction of the set speed, e.g. 0.1 for +-10%%")
    s.add_argument("--heights", type=float, nargs="+", help="rail heights in metres (default: the scenario's)")
    s.add_argument("--rig-id", default="sim-rig")
    s.add_argument("--overwrite", action="store_true", help="replace existing archives")
    s.set_defaults(func=_simulate)

    q = sub.add_parser("process", help="focus every pass under IN_DIR and write the displacement time series")
    q.add_argument("in_dir")
    q.add_argument("--out", required=True, help="output directory (displacements.csv, errors.csv)")
    q.add_argument("--backend", choices=pipeline.BACKENDS, default="opencl",
                   help="opencl: the OpenCL engine (default); numpy: the float64 reference")
    q.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' indices or part of its name (`uwbcl devices`); "
                        "default: $PYOPENCL_CTX, else the first GPU, else the first device")
    q.add_argument("--algorithm", choices=pipeline.ALGORITHMS, default="nlcs")
    q.add_argument("--ac-mode", choices=("exact", "series"), default="exact",
                   help="NLCS azimuth compression: exact-reference (default) or the series of eq. 17")
    q.set_defaults(func=_process)

    d = sub.add_parser("devices", help="list the OpenCL platforms and devices (specs for --device)")
    d.set_defaults(func=_devices)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
