"""Measure the acquisition front end against the simulated rig on 127.0.0.1 (issue 5's acceptance).

A. accuracy: N cycles x 2 heights acquired over Modbus and processed live, against the simulator's truth, beside
   the same passes generated directly and processed from archive files (same seed, geometry and processing).
B. faults: a run with F injected faults of every kind; every archive written is checked pulse for pulse against
   what the simulated controller produced; counts of passes completed, incomplete-and-re-run, failed, lost.
C. keep-up: a controller in its own process streaming at the UWB module's 612 kbit/s (957 complex int16 samples
   per pulse at 20 Hz, real time) with a 2-second buffer; overflow, buffer backlog and the client's CPU use.

    python scripts/acquisition_study.py [--cycles 10] [--faults 100] [--skip A,B,C]

Prints a report; exit status 1 if an acceptance check fails.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from uwbcl import archive, pipeline
from uwbcl.acquisition.client import AcquireSettings, AcquisitionSession
from uwbcl.acquisition.device import DeviceConfig, LongwallFollower, RigController, RigServer
from uwbcl.acquisition.faults import KINDS, parse_faults
from uwbcl.acquisition.live import LiveProcessor, backend_available, processing_settings
from uwbcl.acquisition.rig import WorldConfig
from uwbcl.displacement import estimate_advance
from uwbcl.model import PassGeometry, ScanPass

LOOPBACK = "127.0.0.1"


def finished_cycles(session: AcquisitionSession) -> int:
    return len(session.report.cycles_complete) + len(session.report.cycles_incomplete)


def run_acquisition(server: RigServer, settings: AcquireSettings, processor=None, enough=None):
    """The session against `server`, the next cycle signalled as soon as the last one is scanned; with
    `enough(session)`, no more signals once it holds, and the session is stopped while it waits."""
    session = AcquisitionSession(settings, processor=processor)

    def cycles_done() -> int:  # -1: never again
        return -1 if enough is not None and enough(session) else finished_cycles(session)

    longwall = LongwallFollower(server, cycles_done, listening=lambda: session.link.requests > 3)
    longwall.start()
    if enough is not None:
        def watch():
            while not session.stop.wait(0.05):
                if enough(session):
                    session.stop.set()
        threading.Thread(target=watch, daemon=True).start()
    t0, c0 = time.monotonic(), time.process_time()
    report = session.run()
    longwall.done.set()
    return report, time.monotonic() - t0, time.process_time() - c0


def audit_archives(report, server: RigServer) -> tuple[int, list[str]]:
    """Archives that hold exactly what the controller produced for their pass; the list of those that do not."""
    audits = {a["token"]: a for a in server.snapshot()["completed_passes"]}
    bad = []
    for path in report.passes_written:
        try:
            token = int(re.search(r"-p(\d+)$", archive.read_pass_header(path)["pass_id"]).group(1))
            a = audits[token]
            scan = archive.read_pass(path)
            iq = np.rint(np.stack([scan.echo.real, scan.echo.imag], axis=-1) / a["scale"])
            same = (a["overflow"] == 0 and scan.n_pulses == a["n_pulses"]
                    and np.array_equal(np.rint(scan.pulse_position_m * 1e6), a["positions_um"])
                    and np.array_equal(np.rint(scan.pulse_time_s * 1e6), a["times_us"])
                    and np.array_equal(iq, a["iq"]))
        except Exception as exc:  # noqa: BLE001 - any failure to verify is a finding
            same, path = False, f"{path} ({exc})"
        if not same:
            bad.append(str(path))
    partial = [str(p) for p in Path(report.passes_written[0]).parents[2].rglob(".*")] if report.passes_written \
        else []
    return len(report.passes_written) - len(bad), bad + partial


# ============================================================================================== A


def study_accuracy(args, out: Path) -> bool:
    print(f"\n== A. {args.cycles} cycles x 2 heights over Modbus, processed live, vs the same passes from files ==")
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, snr_db=args.snr_db, speed_jitter=args.speed_jitter)
    device = RigController(DeviceConfig(world=world, time_scale=args.time_scale, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9))
    proc = processing_settings(args.backend, device.campaign.nominal_web_m)
    if backend_available(proc):
        proc = processing_settings("numpy", device.campaign.nominal_web_m)
    with RigServer(device, LOOPBACK, 0) as server:
        settings = AcquireSettings(host=LOOPBACK, port=server.port, out=str(out / "A-acquired"),
                                   cycles=args.cycles, heights_m=(0.15, 0.30))
        report, wall, cpu = run_acquisition(server, settings, LiveProcessor(proc, max_pending=args.cycles))
        audits = server.snapshot()["completed_passes"]
    n_ok, bad = audit_archives(report, server)
    print(f"acquired {len(report.passes_written)} passes ({n_ok} verified pulse for pulse) in {wall:.1f} s "
          f"(time x{args.time_scale:g}, SNR {args.snr_db} dB, speed jitter {args.speed_jitter:g}; CPU {cpu:.0f} s for rig, "
          f"acquisition and processing in one process); backend "
          f"{proc.backend}; incomplete {len(report.passes_incomplete)}, failed {len(report.passes_failed)}")

    # The same passes, generated directly by the echo simulator (no Modbus, no int16), archived and processed.
    files = out / "A-files"
    for a in audits:
        data = device.campaign.make_pass(a["k"], a["height_m"], a["angle_deg"], a["direction"])
        scan = ScanPass(radar=device.campaign.radar,
                        geometry=PassGeometry(a["height_m"], a["angle_deg"], settings.reference_point_m(-1)),
                        range_window_start_s=data.range_window_start_s, pulse_time_s=data.time_s,
                        pulse_position_m=data.position_m, echo=data.echo, rig_id="sim-rig", cycle=a["cycle"],
                        pass_start_time="2026-11-02T06:00:00Z")
        archive.write_pass(files / archive.default_relative_path(scan), scan, overwrite=True)
    by_cycle: dict[int, list] = {}
    for path in archive.find_pass_files(files):
        s = archive.read_pass(path)
        by_cycle.setdefault(s.cycle, []).append(s)
    located = {c: pipeline.locate_cycle(p, proc) for c, p in sorted(by_cycle.items())}

    rows, ok = [], True
    for r in report.results:
        if r["previous_cycle"] is None:
            continue
        c, c0 = r["cycle"], r["previous_cycle"]
        true = device.campaign.rig_position_m(device.cycle_index(c)) - \
            device.campaign.rig_position_m(device.cycle_index(c0))
        f = estimate_advance(located[c0].plates, located[c].plates, proc.association)
        rows.append((c, np.array([r["retreat_m"], r["creep_m"], r["vertical_m"]]) - true,
                     np.asarray(f.advance_m) - true, r["status"], f.status))
    print(" cycle | live - truth (mm): retreat  creep  vert | files - truth (mm): retreat  creep  vert | status")
    for c, e_live, e_file, s_live, s_file in rows:
        print(f" {c:5d} | {1e3 * e_live[0]:+8.2f} {1e3 * e_live[1]:+6.2f} {1e3 * e_live[2]:+6.1f}          "
              f"| {1e3 * e_file[0]:+8.2f} {1e3 * e_file[1]:+6.2f} {1e3 * e_file[2]:+6.1f}           | "
              f"{s_live}/{s_file}")
    if rows:
        live = np.array([r[1] for r in rows])
        filed = np.array([r[2] for r in rows])
        rms = lambda e: 1e3 * np.sqrt(np.nanmean(e ** 2, axis=0))
        print(f"RMS (mm) retreat/creep/vertical: live {np.round(rms(live), 2)}, files {np.round(rms(filed), 2)}; "
              f"max |live - files| {1e3 * np.nanmax(np.abs(live - filed)):.2f} mm")
        ok = np.all(np.isfinite(live)) and rms(live)[0] <= rms(filed)[0] + 1.0 and rms(live)[1] <= rms(filed)[1] + 1.0
    ok = ok and len(rows) == args.cycles - 1 and not bad and report.ok
    print(f"A: {'PASS' if ok else 'FAIL'} ({len(rows)} displacements)")
    return bool(ok)


# ============================================================================================== B


def study_faults(args, out: Path) -> bool:
    n = args.faults
    print(f"\n== B. {n} injected faults of all kinds ({', '.join(KINDS)}) ==")
    plan = parse_faults(f"every={args.fault_every},limit={n},seed={args.seed},reboot_s=10,slow_s=0.2")
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, snr_db=args.snr_db, speed_jitter=args.speed_jitter)
    device = RigController(DeviceConfig(world=world, time_scale=args.time_scale, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9, reboot_s=10.0))
    with RigServer(device, LOOPBACK, 0, faults=plan) as server:
        settings = AcquireSettings(host=LOOPBACK, port=server.port, out=str(out / "B-faults"), cycles=0,
                                   heights_m=(0.15, 0.30), timeout_s=0.5, reconnect_max_s=1.0, max_attempts=10)
        marks = {}

        def enough(session):  # one more cycle after the last fault, then stop while waiting for the next
            if len(server.faults.injected) >= n and "at" not in marks:
                marks["at"] = finished_cycles(session)
            return "at" in marks and finished_cycles(session) >= marks["at"] + 1

        report, wall, _ = run_acquisition(server, settings, enough=enough)
        injected = server.faults.counts()
    n_ok, bad = audit_archives(report, server)
    scanned = {(c, h) for c in report.cycles_complete + report.cycles_incomplete for h in (150, 300)}
    written = {(archive.read_pass_header(p)["cycle"], round(archive.read_pass_header(p)["height_m"] * 1000))
               for p in report.passes_written}
    failed = {(int(m.group(1)), int(m.group(2))) for m in
              (re.search(r"c(\d+) h(\d+)", f) for f in report.passes_failed) if m}
    lost = scanned - written - failed
    f = report.faults
    print(f"injected: {sum(injected.values())} ({', '.join(f'{k} {v}' for k, v in injected.items())}) in {wall:.0f} s")
    print(f"client saw: {f.no_reply} lost replies, {f.disconnects} dropped connections, {f.exceptions} exception "
          f"replies, {f.corrupt} corrupted replies, {f.reboots} reboots, {f.reconnects} reconnects")
    print(f"passes completed and written: {len(report.passes_written)} ({n_ok} identical to what the controller "
          f"produced, {len(bad)} not); incomplete and re-run: {len(report.passes_incomplete)}; failed after "
          f"{settings.max_attempts} attempts: {len(report.passes_failed)}; lost: {len(lost)}")
    reasons: dict[str, int] = {}
    for line in report.passes_incomplete:
        key = re.sub(r"\d+", "N", line.split(": ", 1)[1])
        reasons[key] = reasons.get(key, 0) + 1
    for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]):
        print(f"   {v:3d} x {k}")
    print(f"cycles: {len(report.cycles_complete)} complete, {len(report.cycles_incomplete)} incomplete, "
          f"{report.cycles_missed} missed")
    ok = sum(injected.values()) == n and not bad and not lost and report.ok
    print(f"B: {'PASS' if ok else 'FAIL'}")
    return ok


# ============================================================================================== C


def study_keepup(args, out: Path) -> bool:
    print("\n== C. keep-up: 612 kbit/s of I/Q (957 samples x 2 x 16 bit x 20 Hz), real time, 2 s buffer ==")
    ok = True
    for scale in args.keepup_scales:
        rate = 957 * 32 * 20 * scale / 1e3
        cmd = [sys.executable, "-m", "uwbcl.cli", "simulate-device", "--port", "0", "--range-samples", "957", "--state", "",
               "--buffer", "40", "--window-regs", "8192", "--time-scale", f"{scale:g}", "--first-cycle-after",
               f"{3 * scale:g}", "--max-cycles", "1", "--seed", str(args.seed)]
        dev = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1", "OPENBLAS_NUM_THREADS": "1"})
        try:
            port = int(re.search(r":(\d+) ", dev.stdout.readline()).group(1))
            settings = AcquireSettings(host=LOOPBACK, port=port, out=str(out / f"C-x{scale:g}"), cycles=1,
                                       heights_m=(0.15, 0.30))
            session = AcquisitionSession(settings)
            k0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            t0 = time.monotonic()
            report = session.run()
            wall = time.monotonic() - t0
            r1 = resource.getrusage(resource.RUSAGE_SELF)
        finally:
            dev.terminate()
            dev.communicate(timeout=20)
        k1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        device_cpu = (k1.ru_utime - k0.ru_utime) + (k1.ru_stime - k0.ru_stime)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        scans = [archive.read_pass_header(p) for p in report.passes_written]
        pulses = sum(s["n_pulses"] for s in scans)
        stream_s = pulses / 20.0 / scale
        print(f"x{scale:g} ({rate:.0f} kbit/s): {len(scans)} passes, {pulses} pulses x 957 samples in {wall:.1f} s; "
              f"incomplete {len(report.passes_incomplete)}; most pulses waiting in the 40-pulse buffer: "
              f"{report.max_backlog_pulses}; client CPU {cpu:.1f} s = {100 * cpu / wall:.0f} % of one core over the "
              f"run ({100 * cpu / max(stream_s, 1e-9):.0f} % of the {stream_s:.0f} s of streaming); max RSS "
              f"{r1.ru_maxrss / 1024:.0f} MiB; rig simulator (its own process) CPU {device_cpu:.1f} s")
        ok = ok and report.ok and len(scans) == 2 and not report.passes_incomplete
    print(f"C: {'PASS' if ok else 'FAIL'}")
    return ok


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycles", type=int, default=10)
    p.add_argument("--faults", type=int, default=100)
    p.add_argument("--fault-every", type=int, default=250, help="requests between faults in study B")
    p.add_argument("--time-scale", type=float, default=20.0, help="device time / real time in A and B")
    p.add_argument("--keepup-scales", type=lambda s: [float(v) for v in s.split(",")], default=[1.0, 4.0],
                   help="time scales of study C (1 = the module's 612 kbit/s)")
    p.add_argument("--snr-db", type=float, default=10.0)
    p.add_argument("--speed-jitter", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", default="", help="processing backend for A (default: the pipeline's, else numpy)")
    p.add_argument("--skip", default="", help="comma-separated studies to skip (A, B, C)")
    p.add_argument("--out", help="work directory (default: a temporary one)")
    args = p.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="uwbcl-acq-study-"))
    skip = {s.strip().upper() for s in args.skip.split(",") if s.strip()}
    print(f"work directory {out}")
    results = []
    for name, fn in (("A", study_accuracy), ("B", study_faults), ("C", study_keepup)):
        if name not in skip:
            results.append(fn(args, out))
    print(f"\noverall: {'PASS' if all(results) else 'FAIL'}")
    return 0 if all(results) else 1


if __name__ == "__main__":
    logging = __import__("logging")
    logging.basicConfig(level=logging.ERROR, format="%(asctime)s %(levelname)s %(message)s")
    sys.exit(main())
