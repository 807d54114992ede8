"""Command line for the acquisition front end: `uwbcl simulate-device`, `uwbcl acquire`, `uwbcl demo`."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

from ..atomic import file_in_the_way
from ..config import parse_heights
from ..scenarios import SCENARIOS


def add_acquisition_commands(sub) -> None:
    """Add simulate-device, acquire and demo to the `uwbcl` subcommands."""
    d = sub.add_parser("simulate-device", help="serve a simulated rig controller over Modbus TCP",
                       description="A rig controller implementing docs/modbus-register-map.md, fed by the "
                                   "echo simulator. Runs until interrupted.")
    d.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    d.add_argument("--port", type=int, default=5020, help="TCP port; 0 picks a free one (default 5020)")
    _world_options(d)
    _device_options(d)
    d.set_defaults(func=_simulate_device)

    a = sub.add_parser("acquire", help="acquire passes from a rig over Modbus TCP into an archive directory",
                       description="Waits for the longwall cycle signal, scans every configured height, "
                                   "writes each pass atomically (docs/archive-format.md); incomplete passes "
                                   "are re-run.")
    a.add_argument("--host", help="rig controller address (default 127.0.0.1)")
    a.add_argument("--port", type=int, help="Modbus TCP port (default 502)")
    a.add_argument("--unit-id", type=int, help="Modbus unit id (default 1)")
    a.add_argument("--out", help="archive root directory (default ./uwbcl-archive)")
    a.add_argument("--heights", nargs="+", help="rail heights in metres, e.g. 0.15 0.30 or 0.15,0.30")
    a.add_argument("--cycles", type=int, help="stop after this many cycles (default: run until stopped)")
    a.add_argument("--config", help="TOML file with an [acquire] table (command-line flags override it)")
    a.add_argument("--angle", type=float, help="rotation-table angle in degrees (default 30)")
    a.add_argument("--rib-distance", type=float, help="rail-to-rib distance W in metres (default 2.4)")
    a.add_argument("--reference-height", type=float, help="height of the plate row aimed at, m (default 0.3)")
    a.add_argument("--rig-id", help="rig id for the archive (default: the device's)")
    a.add_argument("--timeout", type=float, help="seconds to wait for each Modbus reply (default 1)")
    a.add_argument("--max-attempts", type=int, help="attempts per pass before giving up (default 5)")
    a.add_argument("--process", action="store_true", default=None,
                   help="focus each finished cycle and publish retreat/creep to the result registers")
    a.add_argument("--backend", help="processing backend (default: the pipeline's)")
    a.add_argument("--web-depth", type=float,
                   help="nominal web depth in metres, a prior for plate association")
    a.set_defaults(func=_acquire)

    m = sub.add_parser("demo", help="simulated rig on loopback -> acquire -> process -> retreat/creep table",
                       description="Starts a simulated rig on 127.0.0.1, acquires a few cycles "
                                   "(time-scaled), processes them and prints the measured retreat and creep "
                                   "beside the truth.")
    m.add_argument("--cycles", type=int, default=4, help="cycles to acquire (default 4: 3 displacements)")
    m.add_argument("--out",
                   help="directory for the archives and results (default: a new temporary directory)")
    m.add_argument("--time-scale", type=float, default=20.0, help="device time / real time (default 20)")
    m.add_argument("--faults", default="", help="inject faults, e.g. every=300 (see simulate-device --help)")
    m.add_argument("--backend", help="processing backend (default: the pipeline's, numpy if unavailable)")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--snr-db", type=float, default=20.0)
    m.set_defaults(func=_demo)


def default_state_file(rig_id: str) -> Path:
    """Where `simulate-device` keeps CYCLE_COUNTER and the last BOOT_ID by default:
    $XDG_STATE_HOME/uwbcl/simulate-device-<rig_id>.json ($XDG_STATE_HOME defaults to ~/.local/state)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "uwbcl" / f"simulate-device-{rig_id}.json"


def _world_options(p) -> None:
    p.add_argument("--scenario", choices=sorted(SCENARIOS), default="paper-sim1",
                   help="plate pattern, radar and rail of a paper scenario, repeated along the roadway")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--snr-db", type=float, default=None,
                   help="receiver SNR per raw sample (default: noise-free)")
    p.add_argument("--speed-jitter", type=float, default=0.0,
                   help="carriage speed wander, e.g. 0.1 for +-10%%")
    p.add_argument("--range-samples", type=int, default=None,
                   help="fixed range gate in samples (default: a power of two covering the plates in the "
                        "beam)")
    p.add_argument("--prf", type=float, default=None, help="pulse repetition frequency in Hz (default: 20)")


def _device_options(p) -> None:
    p.add_argument("--time-scale", type=float, default=1.0, help="device seconds per real second (default 1)")
    p.add_argument("--rig-id", default="sim-rig")
    p.add_argument("--initial-cycle", type=int, default=1000,
                   help="cycle counter at the first start, when the state file holds none (default 1000)")
    p.add_argument("--state", default=None,
                   help="file keeping CYCLE_COUNTER and the last BOOT_ID across restarts (default "
                        "$XDG_STATE_HOME/uwbcl/simulate-device-<rig-id>.json, i.e. ~/.local/state/...); '' "
                        "keeps none")
    p.add_argument("--first-seq", type=int, default=1,
                   help="sequence number of the first pulse after each boot (default 1; e.g. 4294967000 to "
                        "exercise the wrap 2^32-1 -> 0)")
    p.add_argument("--first-cycle-after", type=float, default=5.0,
                   help="device seconds to the first cycle signal")
    p.add_argument("--cycle-interval", type=float, default=2700.0,
                   help="device seconds between cycle signals (default 2700 = 45 min)")
    p.add_argument("--max-cycles", type=int, default=None,
                   help="raise the cycle signal this many times, then stop")
    p.add_argument("--buffer", type=int, default=512, help="pulse buffer capacity (default 512)")
    p.add_argument("--window-regs", type=int, default=2048,
                   help="pulse window size in registers (default 2048)")
    p.add_argument("--faults", default="",
                   help="fault injection spec, e.g. 'every=200' or 'drop=0.01,corrupt=0.01'"
                   " (kinds: drop missing slow exception exception02 exception03 exception04 corrupt reboot "
                   "reconfigure overflow absurd short stall counter_back counter_jump; see "
                   "docs/modbus-register-map.md section 11)")


def _device_config(args, world):
    from .device import DeviceConfig

    state = default_state_file(args.rig_id) if args.state is None else (args.state or None)
    return DeviceConfig(world=world, rig_id=args.rig_id, time_scale=args.time_scale,
                        initial_cycle=args.initial_cycle, first_cycle_after_s=args.first_cycle_after,
                        cycle_interval_s=args.cycle_interval, max_cycles=args.max_cycles,
                        buffer_capacity=args.buffer, window_regs=args.window_regs, first_seq=args.first_seq,
                        state_file=str(state) if state else None)


def _simulate_device_argument_error(args: argparse.Namespace) -> str:
    """Why simulate-device's arguments cannot be served (the flag named), or '': a usage error, not a
    traceback from the socket or the simulator."""
    if not 0 <= args.port <= 65535:
        return f"--port {args.port}: must be in 0..65535 (0 picks a free port)"
    if args.prf is not None and not (math.isfinite(args.prf) and args.prf > 0):
        return f"--prf {args.prf:g}: must be a finite number of Hz > 0"
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        return f"--time-scale {args.time_scale:g}: must be a finite number > 0"
    if not (math.isfinite(args.cycle_interval) and args.cycle_interval > 0):
        return f"--cycle-interval {args.cycle_interval:g}: must be a finite number of seconds > 0"
    if not (math.isfinite(args.first_cycle_after) and args.first_cycle_after >= 0):
        return f"--first-cycle-after {args.first_cycle_after:g}: must be a finite number of seconds >= 0"
    if args.max_cycles is not None and args.max_cycles < 1:
        return f"--max-cycles {args.max_cycles}: must be >= 1"
    if not (math.isfinite(args.speed_jitter) and 0 <= args.speed_jitter < 1):
        return f"--speed-jitter {args.speed_jitter:g}: must be in [0, 1) (0.1 for +-10 %)"
    if args.snr_db is not None and not math.isfinite(args.snr_db):
        return f"--snr-db {args.snr_db:g}: must be a finite number of dB"
    if args.range_samples is not None and args.range_samples < 1:
        return f"--range-samples {args.range_samples}: must be >= 1"
    return ""


def _simulate_device(args: argparse.Namespace) -> int:
    from .device import RigController, RigServer
    from .faults import parse_faults
    from .rig import WorldConfig

    if why := _simulate_device_argument_error(args):
        print(f"uwbcl simulate-device: {why}", file=sys.stderr)
        return 2
    try:
        world = WorldConfig(scenario=args.scenario, seed=args.seed, snr_db=args.snr_db,
                            speed_jitter=args.speed_jitter, range_samples=args.range_samples, prf_hz=args.prf)
        config = _device_config(args, world)
        plan = parse_faults(args.faults)
    except ValueError as exc:
        print(f"uwbcl simulate-device: {exc}", file=sys.stderr)
        return 2
    try:
        controller = RigController(config)
    except OSError as exc:
        print(f"uwbcl simulate-device: state file {config.state_file}: {exc}", file=sys.stderr)
        return 2
    server = RigServer(controller, args.host, args.port, faults=plan)

    async def main() -> None:
        task = asyncio.create_task(server.serve())
        while not server._ready.is_set() and not task.done():
            await asyncio.sleep(0.01)
        if task.done():
            task.result()
        print(f"simulated rig {config.rig_id} listening on {server.host}:{server.port} "
              f"(time scale {config.time_scale:g}, faults: {args.faults or 'none'}, state: "
              f"{config.state_file or 'not kept'})", flush=True)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, lambda: asyncio.ensure_future(server._server.shutdown()))
        await task

    try:
        asyncio.run(main())
    except OSError as exc:
        print(f"uwbcl simulate-device: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 2
    counts = server.faults.counts()
    print(f"stopped after {server.faults.requests} requests; faults injected: "
          f"{', '.join(f'{k} {v}' for k, v in counts.items() if v) or 'none'}")
    return 0


@contextlib.contextmanager
def _stop_on_signals(stop: threading.Event):
    """SIGINT/SIGTERM set `stop` (the session finishes cleanly) while inside; the old handlers
    come back after."""
    def handler(signum, _frame):
        if not stop.is_set():  # said once: a second signal (a process group's) changes nothing
            logging.getLogger("uwbcl.acquire").warning("%s received: finishing cleanly",
                                                      signal.Signals(signum).name)
        stop.set()

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _acquire(args: argparse.Namespace) -> int:
    from .client import AcquisitionSession, ConfigError, load_settings
    from .live import LiveProcessor, backend_available, processing_settings

    try:
        settings = load_settings(
            args.config, host=args.host, port=args.port, unit_id=args.unit_id, out=args.out,
            heights_m=parse_heights(args.heights), cycles=args.cycles, rotation_table_angle_deg=args.angle,
            rib_distance_m=args.rib_distance, reference_height_m=args.reference_height, rig_id=args.rig_id,
            timeout_s=args.timeout, max_attempts=args.max_attempts, process=args.process,
            backend=args.backend, web_depth_m=args.web_depth)
    except (ConfigError, ValueError, TypeError) as exc:
        print(f"uwbcl acquire: {exc}", file=sys.stderr)
        return 2
    if blocker := file_in_the_way(Path(settings.out)):
        print(f"uwbcl acquire: archive root {settings.out}: {blocker} is not a directory", file=sys.stderr)
        return 2
    processor = None
    if settings.process:
        proc_settings = processing_settings(settings.backend, settings.web_depth_m)
        reason = backend_available(proc_settings)
        if reason:
            print(f"uwbcl acquire: backend {proc_settings.backend!r} unavailable: {reason} "
                  f"(use --backend numpy)", file=sys.stderr)
            return 2
        processor = LiveProcessor(proc_settings)
    stop = threading.Event()
    with _stop_on_signals(stop):  # until the end: a second signal while ending changes nothing
        report = AcquisitionSession(settings, stop=stop, processor=processor).run()
        _print_summary(report, settings.out)
    return 0 if report.ok else 1


def _print_summary(report, out) -> None:
    f = report.faults
    print(f"{len(report.passes_written)} passes written to {out}; {len(report.passes_incomplete)} incomplete "
          f"attempts (each run again, up to --max-attempts); {len(report.passes_failed)} failed; cycles "
          f"complete {len(report.cycles_complete)}, "
          f"incomplete {len(report.cycles_incomplete)}, missed {report.cycles_missed}")
    print(f"faults seen: {f.no_reply} lost replies, {f.disconnects} dropped connections, {f.exceptions} "
          f"exception replies, {f.corrupt} corrupted replies, {f.reboots} controller reboots ({f.reconnects} "
          f"reconnects)")
    print(f"  {f.refused} refused requests (01/02/03), {f.requests_failed} requests given up, "
          f"{f.absurd_values} absurd values, {f.incompatible_replies} IDENTITY replies of another rig, "
          f"{f.description_changes} IDENTITY/RADAR changes under a pass, "
          f"{f.rig_id_changes} RIG_ID changes, {f.no_progress} watchdog aborts, {f.counter_decreases} "
          f"cycle-counter decreases, {f.names_taken} archives under a unique name, {f.rate_limited} requests "
          f"delayed by the rate bound, {f.heartbeats_unwritten} CLIENT_HEARTBEAT writes not done, "
          f"{f.foreign_acks} acknowledgements of another command")
    for line in report.passes_failed:
        print(f"  failed: {line}", file=sys.stderr)
    if report.error:
        print(f"  error: {report.error}", file=sys.stderr)
    if report.interrupted:
        print("stopped on request; no partial pass was written")


# ============================================================================================== demo


def _demo(args: argparse.Namespace) -> int:
    from .client import AcquireSettings, AcquisitionSession
    from .device import DeviceConfig, LongwallFollower, RigController, RigServer
    from .faults import parse_faults
    from .live import LiveProcessor, backend_available, processing_settings
    from .rig import WorldConfig

    if args.cycles < 2:
        print("uwbcl demo: --cycles must be >= 2 (a displacement needs two cycles)", file=sys.stderr)
        return 2
    if args.out and (blocker := file_in_the_way(Path(args.out))):
        print(f"uwbcl demo: --out {args.out}: {blocker} is not a directory", file=sys.stderr)
        return 2
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="uwbcl-demo-"))
    t_start = time.monotonic()
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, snr_db=args.snr_db, speed_jitter=0.05)
    # The simulated longwall pushes as soon as the rig has scanned a cycle (not on a 45-minute clock).
    device = RigController(DeviceConfig(world=world, time_scale=args.time_scale, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9))
    proc = processing_settings(args.backend or "", device.campaign.nominal_web_m)
    reason = backend_available(proc)
    if reason and not args.backend:
        print(f"(backend {proc.backend!r} unavailable here: {reason.splitlines()[0]}; using numpy)")
        proc = processing_settings("numpy", device.campaign.nominal_web_m)
    elif reason:
        print(f"uwbcl demo: backend {proc.backend!r} unavailable: {reason}", file=sys.stderr)
        return 2
    try:
        plan = parse_faults(args.faults)
    except ValueError as exc:
        print(f"uwbcl demo: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    with _stop_on_signals(stop), RigServer(device, "127.0.0.1", 0, faults=plan) as server:
        print(f"simulated rig on 127.0.0.1:{server.port} (paper-sim1 plates along the roadway, SNR "
              f"{args.snr_db:g} dB, time x{args.time_scale:g}); acquiring {args.cycles} cycles at 0.15 and "
              f"0.30 m with the {proc.backend} backend ...", flush=True)
        settings = AcquireSettings(host="127.0.0.1", port=server.port, out=str(out), cycles=args.cycles,
                                   heights_m=(0.15, 0.30), rotation_table_angle_deg=30.0, rib_distance_m=2.4,
                                   reference_height_m=0.3, timeout_s=1.0, process=True)
        session = AcquisitionSession(settings, stop=stop,
                                     processor=LiveProcessor(proc, max_pending=args.cycles))
        longwall = LongwallFollower(
            server, lambda: len(session.report.cycles_complete) + len(session.report.cycles_incomplete),
            listening=lambda: session.link.requests > 3)
        longwall.start()
        report = session.run()
        longwall.done.set()
    truth_rows = _write_truth(out, device, report)
    _print_table(truth_rows)
    _print_summary(report, out)
    print(f"archives: {out}/{device.config.rig_id}/...  results: {out}/acquire-results.csv  truth: "
          f"{out}/truth.csv  ({time.monotonic() - t_start:.0f} s)")
    measured = [r for r in truth_rows if r["status"] == "ok"]
    return 0 if report.ok and len(measured) == args.cycles - 1 else 1


def _write_truth(out: Path, device, report) -> list[dict]:
    from ..atomic import write_csv_atomic

    rows = []
    for r in report.results:
        if r["previous_cycle"] is None:
            continue
        k, k0 = device.cycle_index(r["cycle"]), device.cycle_index(r["previous_cycle"])
        true = device.campaign.rig_position_m(k) - device.campaign.rig_position_m(k0)
        rows.append({"cycle": r["cycle"], "previous_cycle": r["previous_cycle"], "retreat_m": r["retreat_m"],
                     "true_retreat_m": float(true[0]), "creep_m": r["creep_m"],
                     "true_creep_m": float(true[1]), "vertical_m": r["vertical_m"],
                     "true_vertical_m": float(true[2]), "status": r["status"]})
    cols = ("cycle", "previous_cycle", "retreat_m", "true_retreat_m", "creep_m", "true_creep_m", "vertical_m",
            "true_vertical_m", "status")
    fmt = [{k: (f"{v:.6f}" if isinstance(v, float) else v) for k, v in row.items()} for row in rows]
    write_csv_atomic(out / "truth.csv", cols, fmt)
    return rows


def _print_table(rows: list[dict]) -> None:
    def mm(v):
        return f"{1000 * v:+7.1f}" if math.isfinite(v) else "    n/a"

    print()
    print(" cycle | retreat m  truth m   err mm | creep m    truth m   err mm | status")
    print("-------+-------------------------------+-------------------------------+--------")
    for r in rows:
        print(f" {r['cycle']:5d} | {r['retreat_m']:8.4f}  {r['true_retreat_m']:8.4f} "
              f"{mm(r['retreat_m'] - r['true_retreat_m'])} | {r['creep_m']:8.4f}  {r['true_creep_m']:8.4f} "
              f"{mm(r['creep_m'] - r['true_creep_m'])} | {r['status']}")
    print()
