"""Measure the acquisition front end against the simulated rig on 127.0.0.1 (issue 5's acceptance).

A. accuracy: N cycles x 2 heights acquired over Modbus and processed live, against the simulator's truth,
   beside the same passes generated directly and processed from archive files (same seed, geometry and
   processing).
B. faults: a run with F injected faults of every kind; every archive written is checked pulse for pulse
   against what the simulated controller produced; counts of passes completed, incomplete-and-re-run, failed,
   lost.
C. keep-up: a controller in its own process streaming at the UWB module's 612 kbit/s (957 complex int16
   samples per pulse at 20 Hz, real time) with a 2-second buffer; overflow, buffer backlog and the client's
   CPU use.
D. issue 12's campaign: a seeded schedule of faults of every kind of uwbcl/acquisition/faults.py (lost, late
   and dropped replies, 04/06, spurious 02/03/04, damaged replies, reboots, reboots with a new SAMPLE_RATE and
   RIG_ID, overflows, absurd PASS values, passes cut short (PULSES_PRODUCED < PULSES_PLANNED), a stalled radar
   (the no-progress watchdog), a cycle counter that goes back or jumps), with pulse sequence numbers that
   wrap 2^32 - 1 -> 0 after every boot and a cycle counter that wraps too. Checks: no stop of the service,
   no whole pass lost, every archive's metadata and data what the controller used for that pass, every
   incomplete pass re-run (or its cycle left because the face moved on), counts by fault kind.

    python scripts/acquisition_study.py [--cycles 10] [--faults 100] [--campaign-faults 165] [--skip A,B,C,D]

Prints a report; exit status 1 if an acceptance check fails.
"""

from __future__ import annotations

import argparse
import collections
import itertools
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

from uwbcl import archive, chain, pipeline
from uwbcl.acquisition.client import AcquireSettings, AcquisitionSession
from uwbcl.acquisition.device import DeviceConfig, LongwallFollower, RigController, RigServer
from uwbcl.acquisition.faults import KINDS, parse_faults
from uwbcl.acquisition.live import LiveProcessor, backend_available, processing_settings
from uwbcl.acquisition.registers import SEQ_MODULUS
from uwbcl.acquisition.rig import WorldConfig
from uwbcl.model import PassGeometry, ScanPass

LOOPBACK = "127.0.0.1"


def finished_cycles(session: AcquisitionSession) -> int:
    return len(session.report.cycles_complete) + len(session.report.cycles_incomplete)


def run_acquisition(server: RigServer, settings: AcquireSettings, processor=None, enough=None,
                    by_value=False):
    """The session against `server`, the next cycle signalled as soon as the last one is scanned; with
    `enough(session)`, no more signals once it holds, and the session is stopped while it waits. by_value: the
    last one is scanned when the session's last finished cycle is the counter's value (a counter that faults
    move back and forth is not counted in signals)."""
    session = AcquisitionSession(settings, processor=processor)
    seen = {"complete": 0, "incomplete": 0, "last": None}

    def last_finished():
        for key, cycles in (("complete", session.report.cycles_complete),
                            ("incomplete", session.report.cycles_incomplete)):
            if len(cycles) != seen[key]:
                seen[key], seen["last"] = len(cycles), cycles[-1]
        return seen["last"]

    def cycles_done() -> int:  # -1: never again
        if enough is not None and enough(session):
            return -1
        if by_value:
            c = server.controller
            last = last_finished()
            return c.cycles_raised if last is None or last == c.cycle_counter else -1
        return finished_cycles(session)

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
    """Archives that hold exactly what the controller produced for their pass; the list of those
    that do not."""
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
    partial = ([str(p) for p in Path(report.passes_written[0]).parents[2].rglob(".*")]
               if report.passes_written else [])
    return len(report.passes_written) - len(bad), bad + partial


# ============================================================================================== A


def study_accuracy(args, out: Path) -> bool:
    print(f"\n== A. {args.cycles} cycles x 2 heights over Modbus, processed live, vs the same passes from "
          f"files ==")
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, snr_db=args.snr_db,
                        speed_jitter=args.speed_jitter)
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
          f"(time x{args.time_scale:g}, SNR {args.snr_db} dB, speed jitter {args.speed_jitter:g}; CPU "
          f"{cpu:.0f} s for rig, acquisition and processing in one process); backend "
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
        f = chain.rig_series([located[c0], located[c]], proc.association)[0].displacement
        rows.append((c, np.array([r["retreat_m"], r["creep_m"], r["vertical_m"]]) - true,
                     np.asarray(f.advance_m) - true, r["status"], f.status))
    print(" cycle | live - truth (mm): retreat  creep  vert | files - truth (mm): retreat  creep  vert | "
          "status")
    for c, e_live, e_file, s_live, s_file in rows:
        print(f" {c:5d} | {1e3 * e_live[0]:+8.2f} {1e3 * e_live[1]:+6.2f} {1e3 * e_live[2]:+6.1f}          "
              f"| {1e3 * e_file[0]:+8.2f} {1e3 * e_file[1]:+6.2f} {1e3 * e_file[2]:+6.1f}           | "
              f"{s_live}/{s_file}")
    if rows:
        live = np.array([r[1] for r in rows])
        filed = np.array([r[2] for r in rows])

        def rms(e):
            return 1e3 * np.sqrt(np.nanmean(e ** 2, axis=0))

        print(f"RMS (mm) retreat/creep/vertical: live {np.round(rms(live), 2)}, files "
              f"{np.round(rms(filed), 2)}; max |live - files| {1e3 * np.nanmax(np.abs(live - filed)):.2f} mm")
        ok = (np.all(np.isfinite(live)) and rms(live)[0] <= rms(filed)[0] + 1.0
              and rms(live)[1] <= rms(filed)[1] + 1.0)
    ok = ok and len(rows) == args.cycles - 1 and not bad and report.ok
    print(f"A: {'PASS' if ok else 'FAIL'} ({len(rows)} displacements)")
    return bool(ok)


# ============================================================================================== B


def study_faults(args, out: Path) -> bool:
    n = args.faults
    print(f"\n== B. {n} injected faults of the kinds {', '.join(KINDS[:7])} ==")
    plan = parse_faults(f"every={args.fault_every},limit={n},seed={args.seed},reboot_s=10,slow_s=0.2,"
                        f"kinds={'+'.join(KINDS[:7])}")  # the kinds of issue 5; D has them all
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, snr_db=args.snr_db,
                        speed_jitter=args.speed_jitter)
    device = RigController(DeviceConfig(world=world, time_scale=args.time_scale, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9, reboot_s=10.0))
    with RigServer(device, LOOPBACK, 0, faults=plan) as server:
        settings = AcquireSettings(host=LOOPBACK, port=server.port, out=str(out / "B-faults"), cycles=0,
                                   heights_m=(0.15, 0.30), timeout_s=0.5, reconnect_max_s=1.0,
                                   max_attempts=10)
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
    print(f"injected: {sum(injected.values())} ({', '.join(f'{k} {v}' for k, v in injected.items())}) in "
          f"{wall:.0f} s")
    print(f"client saw: {f.no_reply} lost replies, {f.disconnects} dropped connections, {f.exceptions} "
          f"exception replies, {f.corrupt} corrupted replies, {f.reboots} reboots, {f.reconnects} reconnects")
    print(f"passes completed and written: {len(report.passes_written)} ({n_ok} identical to what the "
          f"controller produced, {len(bad)} not); incomplete and re-run: {len(report.passes_incomplete)}; "
          f"failed after {settings.max_attempts} attempts: {len(report.passes_failed)}; lost: {len(lost)}")
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
        cmd = [sys.executable, "-m", "uwbcl.cli", "simulate-device", "--port", "0", "--range-samples", "957",
               "--state", "", "--buffer", "40", "--window-regs", "8192", "--time-scale", f"{scale:g}",
               "--first-cycle-after", f"{3 * scale:g}", "--max-cycles", "1", "--seed", str(args.seed)]
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
        print(f"x{scale:g} ({rate:.0f} kbit/s): {len(scans)} passes, {pulses} pulses x 957 samples in "
              f"{wall:.1f} s; incomplete {len(report.passes_incomplete)}; most pulses waiting in the "
              f"40-pulse buffer: {report.max_backlog_pulses}; client CPU {cpu:.1f} s = "
              f"{100 * cpu / wall:.0f} % of one core over the run ({100 * cpu / max(stream_s, 1e-9):.0f} % "
              f"of the {stream_s:.0f} s of streaming); max RSS {r1.ru_maxrss / 1024:.0f} MiB; rig simulator "
              f"(its own process) CPU {device_cpu:.1f} s")
        ok = ok and report.ok and len(scans) == 2 and not report.passes_incomplete
    print(f"C: {'PASS' if ok else 'FAIL'}")
    return ok


# ============================================================================================== D


def _metadata_differs(path: str, audit: dict, header: dict) -> list[str]:
    """What in the archive differs from what the controller used for the pass (empty: nothing)."""
    scan = archive.read_pass(path)
    diffs = []
    radar = audit["radar"]
    for name in ("carrier_frequency_hz", "bandwidth_hz", "sample_rate_hz", "pulse_repetition_frequency_hz",
                 "antenna_aperture_m"):
        if not np.isclose(getattr(scan.radar, name), getattr(radar, name), rtol=1e-9, atol=0.0):
            diffs.append(f"{name} {getattr(scan.radar, name):g} != {getattr(radar, name):g}")
    if scan.rig_id != audit["rig_id"]:
        diffs.append(f"rig_id {scan.rig_id} != {audit['rig_id']}")
    if scan.cycle != audit["cycle"]:
        diffs.append(f"cycle {scan.cycle} != {audit['cycle']}")
    if abs(scan.range_window_start_s - audit["range_window_start_s"]) > 1e-15:
        diffs.append("range_window_start_s")
    if abs(scan.geometry.height_m - audit["height_m"]) > 1e-6 or \
            abs(scan.geometry.rotation_table_angle_deg - audit["angle_deg"]) > 1e-3:
        diffs.append("height or angle")
    if f"-b{audit['boot_id']:08X}-" not in header["pass_id"]:
        diffs.append(f"pass_id {header['pass_id']} not of boot {audit['boot_id']:08X}")
    iq = np.rint(np.stack([scan.echo.real, scan.echo.imag], axis=-1) / audit["scale"])
    if not (scan.n_pulses == audit["n_pulses"] and audit["overflow"] == 0
            and np.array_equal(np.rint(scan.pulse_position_m * 1e6), audit["positions_um"])
            and np.array_equal(np.rint(scan.pulse_time_s * 1e6), audit["times_us"])
            and np.array_equal(iq, audit["iq"])):
        diffs.append("pulses differ from those produced")
    return diffs


def study_campaign(args, out: Path) -> bool:
    n = args.campaign_faults
    every = args.campaign_every
    # Drawn at random per request (seeded), not in a fixed rotation: a rotation would hit every kind at the
    # same phase of the cycle each time (e.g. a counter going back always while waiting).
    p_kind = 1.0 / (every * len(KINDS))
    spec = (",".join(f"{k}={p_kind:.6f}" for k in KINDS)
            + f",limit={n},seed={args.seed},slow_s=0.3,overflow_pulses=4")
    print(f"\n== D. issue 12 campaign: {n} faults, each request a fault with probability 1/{every}, kinds "
          f"{', '.join(KINDS)} equally likely ==")
    print(f"   (uwbcl simulate-device --faults '{spec}' --first-seq {SEQ_MODULUS - 100} --initial-cycle "
          f"{SEQ_MODULUS - 3} --time-scale 50, FAST world: 61 pulses x 32 samples per pass)")
    world = WorldConfig(scenario="paper-sim1", seed=args.seed, aperture_length_m=0.45, range_samples=32)
    device = RigController(DeviceConfig(world=world, time_scale=50.0, first_cycle_after_s=1e9,
                                        cycle_interval_s=1e9, reboot_s=10.0, first_seq=SEQ_MODULUS - 100,
                                        initial_cycle=SEQ_MODULUS - 3))
    device.completed_passes = collections.deque()  # audit every pass, not the last 200 (8 KiB each here)
    plan = parse_faults(spec)
    with RigServer(device, LOOPBACK, 0, faults=plan) as server:
        settings = AcquireSettings(host=LOOPBACK, port=server.port, out=str(out / "D-campaign"), cycles=0,
                                   heights_m=(0.15, 0.30), timeout_s=0.25, reconnect_max_s=0.5,
                                   max_attempts=10, stall_timeout_s=1.5, command_timeout_s=20.0)
        marks = {}

        def enough(session):  # one more cycle after the last fault, then stop while waiting for the next
            if len(server.faults.injected) >= n and "at" not in marks:
                marks["at"] = finished_cycles(session)
            return "at" in marks and finished_cycles(session) >= marks["at"] + 1

        report, wall, cpu = run_acquisition(server, settings, enough=enough, by_value=True)
        snap = server.snapshot()
        injected = server.faults.counts()
        requests = server.faults.requests
        seq_wraps = sum(1 for a in snap["completed_passes"] if a["first_seq"] + a["n_pulses"] > SEQ_MODULUS)
        cycle_log = [c for c, _ in snap["cycle_log"]]
    audits = {a["token"]: a for a in snap["completed_passes"]}
    bad_meta, headers = [], {}
    for path in report.passes_written:
        header = archive.read_pass_header(path)
        headers[path] = header
        token = int(re.search(r"-p(\d+)$", header["pass_id"]).group(1))
        audit = audits.get(token)
        diffs = ["no whole pass of that token on the controller"] if audit is None else \
            _metadata_differs(path, audit, header)
        if diffs:
            bad_meta.append(f"{path}: {'; '.join(diffs)}")
    # Whole passes lost: a (cycle, height) scanned but neither written nor reported failed; names taken.
    written = {(h["cycle"], round(h["height_m"] * 1000)) for h in headers.values()}
    scanned = {(c, hmm) for c in report.cycles_complete for hmm in (150, 300)}
    failed = {(int(m.group(1)), int(m.group(2))) for m in
              (re.search(r"c(\d+) h(\d+)", f) for f in report.passes_failed) if m}
    lost = scanned - written - failed
    dropped_for_name = [f for f in report.passes_failed if "exists" in f]
    # Every incomplete attempt: followed by another attempt of the same pass, or its cycle left
    # (face moved on).
    attempts: dict[tuple[int, int], list[int]] = {}
    for line in report.passes_incomplete:
        m = re.search(r"c(\d+) h(\d+) attempt (\d+):", line)
        attempts.setdefault((int(m.group(1)), int(m.group(2))), []).append(int(m.group(3)))
    rerun = left = not_rerun = 0
    for key, ks in attempts.items():
        for k in ks:
            if k + 1 in ks or key in written and k < 10 or key in failed:
                rerun += 1
            elif key[0] in report.cycles_incomplete:
                left += 1
            else:
                not_rerun += 1
    f = report.faults
    reasons: dict[str, int] = {}
    for line in report.passes_incomplete:
        key = re.sub(r"\d+", "N", line.split(": ", 1)[1])[:90]
        reasons[key] = reasons.get(key, 0) + 1
    print(f"injected: {sum(injected.values())} faults in {requests} requests, {wall:.0f} s "
          f"({requests / wall:.0f} requests/s on average, CPU {cpu:.0f} s):")
    print("   " + ", ".join(f"{k} {v}" for k, v in injected.items()))
    print(f"wraps: {seq_wraps} whole passes ran across sequence 2^32-1 -> 0 (every boot starts 100 pulses "
          f"before it); cycle counter values {cycle_log[:3]}... "
          f"({sum(1 for a, b in itertools.pairwise(cycle_log) if b < a)} decreases or wraps among "
          f"{len(cycle_log)} changes)")
    print(f"client saw: {f.no_reply} lost replies, {f.disconnects} dropped connections, {f.exceptions} "
          f"exception replies ({f.refused} refused 01/02/03), {f.corrupt} damaged replies, {f.reboots} "
          f"reboots, {f.reconnects} reconnects, {f.description_changes} IDENTITY/RADAR changes under a pass, "
          f"{f.rig_id_changes} RIG_ID changes, {f.absurd_values} absurd values, {f.no_progress} watchdog "
          f"aborts, {f.counter_decreases} counter decreases, {report.cycles_missed} cycles missed, "
          f"{f.names_taken} archives under a unique name, {f.requests_failed} requests given up, "
          f"{f.rate_limited} rate-bounded")
    print(f"passes written: {len(report.passes_written)}; archives whose metadata or data differ from what "
          f"the controller used: {len(bad_meta)}; whole passes lost: {len(lost)} (dropped for a taken name: "
          f"{len(dropped_for_name)}); failed after {settings.max_attempts} attempts: "
          f"{len(report.passes_failed)}")
    print(f"incomplete attempts: {len(report.passes_incomplete)}: re-run {rerun}, cycle left because the "
          f"face moved on {left}, neither {not_rerun}")
    for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]):
        print(f"   {v:3d} x {k}")
    print(f"cycles: {len(report.cycles_complete)} complete, {len(report.cycles_incomplete)} incomplete; "
          f"service stops: {1 if report.error else 0}{' (' + report.error + ')' if report.error else ''}")
    for line in bad_meta[:10]:
        print(f"   BAD: {line}")
    ok = (sum(injected.values()) >= n and not bad_meta and not lost and not dropped_for_name
          and not report.error and not not_rerun
          and (n < 10 * len(KINDS) or all(v > 0 for v in injected.values())))
    print(f"D: {'PASS' if ok else 'FAIL'}")
    return ok


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cycles", type=int, default=10)
    p.add_argument("--faults", type=int, default=100)
    p.add_argument("--fault-every", type=int, default=250, help="requests between faults in study B")
    p.add_argument("--campaign-faults", type=int, default=180,
                   help="faults in study D (12 of each kind on average)")
    p.add_argument("--campaign-every", type=int, default=40, help="requests between faults in study D")
    p.add_argument("--time-scale", type=float, default=20.0, help="device time / real time in A and B")
    p.add_argument("--keepup-scales", type=lambda s: [float(v) for v in s.split(",")], default=[1.0, 4.0],
                   help="time scales of study C (1 = the module's 612 kbit/s)")
    p.add_argument("--snr-db", type=float, default=10.0)
    p.add_argument("--speed-jitter", type=float, default=0.1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--backend", default="",
                   help="processing backend for A (default: the pipeline's, else numpy)")
    p.add_argument("--skip", default="", help="comma-separated studies to skip (A, B, C, D)")
    p.add_argument("--out", help="work directory (default: a temporary one)")
    args = p.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="uwbcl-acq-study-"))
    skip = {s.strip().upper() for s in args.skip.split(",") if s.strip()}
    print(f"work directory {out}")
    results = []
    for name, fn in (("A", study_accuracy), ("B", study_faults), ("C", study_keepup), ("D", study_campaign)):
        if name not in skip:
            results.append(fn(args, out))
    print(f"\noverall: {'PASS' if all(results) else 'FAIL'}")
    return 0 if all(results) else 1


if __name__ == "__main__":
    logging = __import__("logging")
    logging.basicConfig(level=logging.ERROR, format="%(asctime)s %(levelname)s %(message)s")
    sys.exit(main())
