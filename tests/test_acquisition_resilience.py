"""`uwbcl acquire` at the edges of a long unattended session: its end with the controller gone, faults that
do not clear, a disk that refuses passes, a controller that approaches the rail end first, labels the archive
would refuse, and the simulated controller's own fault handling and arguments.

Each test drives the simulated controller over loopback (a RigController subclass with one behaviour) or one
function directly; bounded: a few seconds each.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import queue
import threading
import time
from types import SimpleNamespace

import pytest
from test_acquisition import (  # noqa: F401
    FAST_DEVICE,
    LOOPBACK,
    assert_archives_match_device,
    disk_refusing,
    loopback_only,
    run_session,
    settings_for,
)

from uwbcl import archive
from uwbcl.acquisition import client as client_module
from uwbcl.acquisition import registers as R
from uwbcl.acquisition.client import AcquisitionSession
from uwbcl.acquisition.device import ILLEGAL_ADDRESS, ModbusFault, RigController, RigServer


def _result(cycle: int) -> dict:
    return {"cycle": cycle, "previous_cycle": cycle - 1, "retreat_m": 0.9, "creep_m": 0.0, "vertical_m": 0.0,
            "status_code": 0, "status": "ok", "n_targets": 5, "residual_m": 0.001, "time_s": 1.8e9,
            "revision": 0}


def _processor(results: queue.Queue, close) -> SimpleNamespace:
    """A stand-in live processor: its results come through `results`, `close(timeout_s)` ends it."""
    return SimpleNamespace(rig_id="", results=results, submit=lambda *a, **k: True, close=close,
                           write_csv=lambda out, rows: None)


def _processor_that_stops_the_rig(server: RigServer) -> SimpleNamespace:
    """A live processor whose result comes when the session ends, after the controller went away."""
    results: queue.Queue = queue.Queue()

    def close(timeout_s):
        server.stop()
        results.put(_result(1001))

    return _processor(results, close)


# ============================================================================================== F1


def test_the_end_of_a_session_returns_when_the_controller_is_gone_and_a_result_waits(tmp_path, monkeypatch):
    monkeypatch.setattr(client_module, "FINAL_PUBLISH_S", 1.0, raising=False)
    server = RigServer(RigController(FAST_DEVICE), LOOPBACK, 0)
    server.start()
    report = run_session(settings_for(server, tmp_path, cycles=1), timeout_s=30.0,
                         processor=_processor_that_stops_the_rig(server))
    assert report.ok and not report.error and len(report.passes_written) == 2, report


def test_a_stop_while_the_last_result_waits_is_no_error_and_a_kept_pass_still_gets_its_last_write(
        tmp_path, monkeypatch):
    real, calls = client_module.write_scan, []

    def full_disk_once(*args, **kwargs):  # the second pass's first write: a disk full for a moment
        calls.append(args[2])
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(client_module, "write_scan", full_disk_once)
    monkeypatch.setattr(client_module, "FINAL_PUBLISH_S", 60.0, raising=False)
    server = RigServer(RigController(FAST_DEVICE), LOOPBACK, 0)
    server.start()
    stop = threading.Event()
    session = AcquisitionSession(settings_for(server, tmp_path, cycles=1), stop=stop,
                                 processor=_processor_that_stops_the_rig(server))
    box: dict = {}
    thread = threading.Thread(target=lambda: box.setdefault("report", session.run()), daemon=True)
    thread.start()
    deadline = time.monotonic() + 30.0
    while not server.snapshot()["completed_passes"][1:] and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # the session is now publishing to a controller that is gone
    stop.set()  # SIGTERM
    thread.join(15.0)
    assert not thread.is_alive(), "the session did not end after the stop"
    report = box["report"]
    assert not report.error and report.passes_failed == [], report
    assert len(report.passes_written) == 2 and len(calls) == 3  # the kept pass written at the end


# ============================================================================================== F2


class _JammedDrive(RigController):
    """A DRIVE fault CLEAR_FAULTS cannot remove: it comes back at once (a drive still jammed)."""

    def __init__(self, config):
        super().__init__(config)
        self.fault_word = R.Fault.DRIVE
        self.clears = 0

    def _execute(self, now, code, arg):
        if code == R.Command.CLEAR_FAULTS:
            self.clears += 1
            self.fault_word = R.Fault.DRIVE
            return R.CommandResult.DONE
        return super()._execute(now, code, arg)


def test_a_fault_that_does_not_clear_gets_one_clear_faults_per_attempt_and_one_message(tmp_path, caplog):
    device = _JammedDrive(dataclasses.replace(FAST_DEVICE, cycle_interval_s=5000.0))
    with caplog.at_level(logging.INFO, logger="uwbcl.acquire"), RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, max_attempts=2, command_timeout_s=1.5,
                                          heights_m=(0.15,)))
    assert device.clears == 2, device.clears  # once per attempt, then it waits for READY
    assert caplog.text.count("clearing faults") == 2
    assert report.passes_written == [] and len(report.passes_failed) == 1
    assert all("0x0001 not cleared by CLEAR_FAULTS" in r for r in report.passes_incomplete), report


# ============================================================================================== F3


def _command(c: RigController, now, seq, code, arg=0) -> R.CommandResult:
    c.write(now, 0, R.COMMAND.encode({"CMD_CODE": int(code), "CMD_SEQ": seq, "ARG0": arg}))
    return R.CommandResult(c.cmd_result)


def test_the_simulated_controller_reads_faulted_and_accepts_abort_and_clear_faults_while_a_fault_is_set():
    c = RigController(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=1e9))
    assert _command(c, 0.0, 1, R.Command.START_PASS, 5) is R.CommandResult.ACCEPTED
    c.fault_word |= R.Fault.DRIVE  # a drive fault while the pass runs
    assert c.state(0.4) is R.State.FAULTED and not c.status_word(0.4) & R.Status.READY
    assert _command(c, 0.45, 2, R.Command.MOVE_HEIGHT, 300_000) is R.CommandResult.REJECTED_NOT_READY
    assert _command(c, 0.5, 3, R.Command.ABORT) is R.CommandResult.DONE
    assert c.pass_.state is R.PassState.ABORTED
    assert _command(c, 0.6, 4, R.Command.CLEAR_FAULTS) is R.CommandResult.DONE
    assert c.fault_word == 0 and c.state(0.6) is R.State.IDLE and c.status_word(0.6) & R.Status.READY


# ============================================================================================== F7


class _ApproachFirst(RigController):
    """Moves the carriage for 5 device seconds before the first pulse, PASS_ACTIVE clear meanwhile (no pulse
    is being produced yet; map 13.1), PASS_STATE RUNNING."""

    APPROACH_S = 5.0

    def _start_pass(self, now, token):
        super()._start_pass(now, token)
        self.pass_.t_start = now + self.APPROACH_S

    def status_word(self, now):
        s = super().status_word(now)
        p = self.pass_
        if p is not None and p.state is R.PassState.RUNNING and p.produced == 0:
            s &= ~R.Status.PASS_ACTIVE
        return s


def test_a_pass_that_approaches_the_rail_end_before_its_first_pulse_is_waited_for_not_ended(tmp_path):
    device = _ApproachFirst(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, max_attempts=1))
    assert report.ok and len(report.passes_written) == 2 and report.passes_incomplete == [], report
    assert_archives_match_device(report, server)


class _ApproachForever(_ApproachFirst):
    APPROACH_S = 1e9  # the carriage never arrives: a stall the watchdog must end


def test_an_approach_that_never_ends_is_a_stall_the_watchdog_aborts(tmp_path):
    device = _ApproachForever(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, max_attempts=1, stall_timeout_s=1.0,
                                          heights_m=(0.15,)))
    assert report.passes_written == [] and len(report.passes_failed) == 1
    assert report.faults.no_progress == 1 and "(watchdog)" in report.passes_incomplete[0], report


# ============================================================================================== F4


@pytest.mark.parametrize("rig_id", ["   ", "rig\x00A", "\t"])
def test_a_configured_rig_id_the_archive_would_refuse_is_a_usage_error_at_the_start(rig_id, tmp_path):
    from uwbcl.records import ConfigError

    with pytest.raises(ConfigError, match="rig_id"):
        client_module.load_settings(None, out=str(tmp_path), rig_id=rig_id)


@pytest.mark.parametrize("rig_id", ["        ", "rig\x00A"])
def test_a_controller_rig_id_the_archive_would_refuse_stops_the_session_at_the_start_naming_the_register(
        rig_id, tmp_path):
    device = RigController(dataclasses.replace(FAST_DEVICE, rig_id=rig_id))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, max_attempts=1))
        drained = server.snapshot()["completed_passes"]
    assert "IDENTITY.RIG_ID" in report.error and "rig_id" in report.error, report
    assert drained == [] and report.passes_incomplete == [] and report.passes_written == []


def test_a_configured_rig_id_names_the_archives_whatever_the_controllers_rig_id(tmp_path):
    device = RigController(dataclasses.replace(FAST_DEVICE, rig_id="        "))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, rig_id="face-7"))
    assert report.ok and len(report.passes_written) == 2 and all("face-7" in p for p in report.passes_written)


def test_an_unnamed_rig_is_archived_as_rig_with_a_warning_at_the_start(tmp_path, caplog):
    # an independent tester: an all-NUL RIG_ID was archived as "rig" without a word; two such rigs would merge
    caplog.set_level(logging.WARNING, logger="uwbcl.acquire")
    device = RigController(dataclasses.replace(FAST_DEVICE, rig_id=""))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path))
    assert report.ok and all("/rig/" in p.replace("\\", "/") for p in report.passes_written), report
    assert sum("IDENTITY.RIG_ID is empty" in r.getMessage() for r in caplog.records) == 1


# ============================================================================================== F8


@pytest.mark.parametrize("flag, value", [("--port", "99999"), ("--port", "-1"), ("--prf", "0"),
                                         ("--prf", "-5"), ("--prf", "nan"), ("--time-scale", "nan"),
                                         ("--time-scale", "0"), ("--cycle-interval", "0"),
                                         ("--cycle-interval", "-1"), ("--first-cycle-after", "-1"),
                                         ("--max-cycles", "-1"), ("--speed-jitter", "2"), ("--snr-db", "nan"),
                                         ("--range-samples", "0")])
def test_simulate_device_refuses_a_port_prf_or_time_scale_out_of_range_as_a_usage_error_naming_the_flag(
        flag, value, tmp_path):
    import subprocess
    import sys

    args = ["--port", "0", "--state", ""] + [flag, value]
    try:
        run = subprocess.run([sys.executable, "-m", "uwbcl.cli", "simulate-device", *args],
                             capture_output=True, text=True, timeout=20, check=False, cwd=tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"simulate-device {flag} {value} was served")
    assert run.returncode == 2, run.stdout + run.stderr
    assert f"{flag} " in run.stderr and "Traceback" not in run.stderr, run.stderr


# ============================================================================================== F5


def _finished_pass(n: int = 40, m: int = 64, scale: float = 0.1234567891):
    import numpy as np

    from uwbcl.acquisition.recorder import Limits, PassAssembler

    radar = {"CARRIER_FREQUENCY": 4.3e9, "BANDWIDTH": 1.4e9, "SAMPLE_RATE": 3.9e9, "PRF": 20.0,
             "ANTENNA_APERTURE": 0.1, "BORESIGHT_Y_SIGN": -1, "MAX_SAMPLES_PER_PULSE": 0,
             "WINDOW_REGS": 60000}
    desc = {"SAMPLES_PER_PULSE": m, "PULSES_PLANNED": n, "AMPLITUDE_SCALE": scale, "DIRECTION": 1, "TOKEN": 1,
            "FIRST_SEQ": 1, "HEIGHT": 0.15, "TABLE_ANGLE": 30.0, "START_TIME": 1.79e9,
            "RANGE_WINDOW_START": 1e-8, "CYCLE": 5}
    asm = PassAssembler(desc, radar, Limits())
    asm.time_s[:] = np.arange(n) / 20.0
    asm.position_m[:] = np.linspace(-1.0, 1.0, n)
    asm.iq[:] = np.random.default_rng(0).integers(-32768, 32767, size=asm.iq.shape, dtype=np.int16)
    asm.count, asm.last_seen = n, True
    return asm, asm.scan_pass(radar, rig_id="r", reference_point_m=(1.0, -2.4, 0.3), cycle=5)


def test_a_finished_pass_holds_its_echo_as_archived_complex64_with_the_values_the_archive_stores(tmp_path):
    import numpy as np

    from uwbcl import archive

    asm, scan = _finished_pass()
    assert scan.echo.dtype == np.complex64  # 8 B a sample, not 16: what a pass kept in memory holds
    wide = (asm.iq[..., 0] + 1j * asm.iq[..., 1].astype(np.float64)) * 0.1234567891
    np.testing.assert_array_equal(scan.echo, wide.astype(np.complex64))  # rounded once, as before
    path = archive.write_pass(tmp_path / "p.h5", scan)
    np.testing.assert_array_equal(archive.read_pass(path).echo, archive.as_stored(scan).echo)


def test_the_memory_check_counts_the_int16_iq_and_the_archived_echo_a_finished_pass_holds():
    from uwbcl.acquisition.recorder import AbsurdValue, Limits, PassAssembler

    desc = {"SAMPLES_PER_PULSE": 1000, "PULSES_PLANNED": 1000, "AMPLITUDE_SCALE": 1.0, "DIRECTION": 1,
            "TOKEN": 1, "FIRST_SEQ": 1}
    radar = {"MAX_SAMPLES_PER_PULSE": 0, "WINDOW_REGS": 60000}
    with pytest.raises(AbsurdValue, match="11 MiB"):  # 1e6 samples x (4 + 8) B: more than 8 MiB
        PassAssembler(desc, radar, Limits(max_pass_bytes=8 * 2**20))


def test_passes_kept_beyond_the_memory_bound_drop_the_oldest_named_as_lost(tmp_path, monkeypatch):
    disk_refusing(monkeypatch, failing=10**6)
    monkeypatch.setattr(client_module, "MAX_UNWRITTEN_BYTES", 1, raising=False)  # room for the newest only
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1))
    first, second = report.passes_failed
    assert first.startswith("sim-rig c001001 h0150: ") and "dropped from memory for a newer pass" in first
    assert second.startswith("sim-rig c001001 h0300: ") and "before the end" in second


def test_a_full_queue_of_kept_passes_never_declares_lost_a_new_pass_the_disk_takes(tmp_path, monkeypatch):
    disk_refusing(monkeypatch, failing=1)  # the first pass waits; then the disk takes passes again
    monkeypatch.setattr(client_module, "MAX_UNWRITTEN_PASSES", 1)
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1))
    assert report.ok and report.passes_failed == [] and len(report.passes_written) == 2, report
    assert_archives_match_device(report, server)


# ============================================================================================== F6


class _GatewayToAGoneController(RigServer):
    """A Modbus gateway whose controller behind it went away: every request answered with exception 0B."""

    gone = False

    async def _action(self, *args, **kwargs):
        from pymodbus.constants import ExcCodes

        if self.gone:
            return ExcCodes.GATEWAY_NO_RESPONSE
        return await super()._action(*args, **kwargs)


def test_the_last_publish_gives_up_at_its_deadline_also_when_every_request_gets_an_exception_reply(
        tmp_path, monkeypatch):
    # a review: the deadline bounded reconnecting only: 25 exception replies a request, 40 s for a result
    monkeypatch.setattr(client_module, "FINAL_PUBLISH_S", 1.0, raising=False)
    server = _GatewayToAGoneController(RigController(FAST_DEVICE), LOOPBACK, 0)
    server.start()
    results: queue.Queue = queue.Queue()

    def close(timeout_s):
        server.gone = True
        results.put(_result(1001))

    session = AcquisitionSession(settings_for(server, tmp_path, cycles=1),
                                 processor=_processor(results, close))
    publish, spent = session._publish_results, []

    def timed(final=False):
        start = time.monotonic()
        try:
            return publish(final)
        finally:
            spent.append(time.monotonic() - start) if final else None

    session._publish_results = timed
    box: dict = {}
    thread = threading.Thread(target=lambda: box.setdefault("report", session.run()), daemon=True)
    thread.start()
    thread.join(60.0)
    server.stop()
    assert not thread.is_alive(), "the session did not end"
    report = box["report"]
    assert report.ok and len(report.passes_written) == 2, report
    assert spent and spent[-1] < 1.0 + 3.0, spent  # the deadline, plus at most one request's pause


class _HeartbeatClock(RigController):
    """Records when (real time) each CLIENT_HEARTBEAT arrives."""

    def __init__(self, config):
        super().__init__(config)
        self.heartbeats: list[float] = []

    def write(self, now, address, values):
        if address == R.CLIENT.address:
            self.heartbeats.append(time.monotonic())
        super().write(now, address, values)


def test_the_client_heartbeat_goes_on_while_a_pass_is_built_and_written_for_seconds(tmp_path, monkeypatch):
    real = client_module.write_scan

    def slow_share(*args, **kwargs):  # a large pass on a slow share: seconds without a request
        time.sleep(3.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(client_module, "write_scan", slow_share)
    device = _HeartbeatClock(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heights_m=(0.15, 0.3)))
    assert report.ok and len(report.passes_written) == 2, report
    gaps = [b - a for a, b in zip(device.heartbeats, device.heartbeats[1:])]
    assert max(gaps) < 2.0, gaps  # map 5.3: it changes at least every 2 s while uwbcl is connected


class _HeartbeatRefused(RigController):
    """Answers every CLIENT_HEARTBEAT write with exception 02 (not conforming: HR 12-13 are writable)."""

    def write(self, now, address, values):
        if address == R.CLIENT.address:
            raise ModbusFault(ILLEGAL_ADDRESS, "CLIENT refused")
        super().write(now, address, values)


def test_a_controller_that_refuses_every_client_heartbeat_still_gets_every_pass_scanned(tmp_path, caplog):
    # indepZw F1: the refused heartbeat failed every pass, and between cycles the step that polls STATUS
    # failed on it before it looked at the cycle counter: nothing was scanned while the cycles went by
    device = _HeartbeatRefused(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with caplog.at_level(logging.WARNING), RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heights_m=(0.15, 0.3)))
    assert report.ok and len(report.passes_written) == 2 and not report.passes_failed, report
    assert report.faults.heartbeats_unwritten >= 1
    said = [r for r in caplog.records if "CLIENT_HEARTBEAT (HR 12) not written" in r.getMessage()]
    assert len(said) == 1  # once a minute at most


class _ForeignAck(RigController):
    """Acknowledges the first SET_TABLE_ANGLE with another command's code, DONE, without running it (as if
    another client's MOVE_HEIGHT had used the same CMD_SEQ)."""

    fooled = False

    def command(self, now, regs):
        c = R.COMMAND.decode(regs)
        if c["CMD_CODE"] == R.Command.SET_TABLE_ANGLE and not self.fooled:
            self.fooled = True
            self.cmd_ack_seq, self.cmd_ack_code = c["CMD_SEQ"], int(R.Command.MOVE_HEIGHT)
            self.cmd_result = R.CommandResult.DONE
            return
        super().command(now, regs)


def test_a_command_acknowledged_with_another_commands_code_is_written_again_under_a_new_number(tmp_path):
    # indepZw F3: the client took the acknowledgement of its CMD_SEQ for its own command; the angle was never
    # set and the pass was archived at the rig's old angle, which `uwbcl check` then refused with its cycle
    device = _ForeignAck(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with RigServer(device, LOOPBACK, 0) as server:
        settings = settings_for(server, tmp_path, heights_m=(0.15, 0.3))
        report = run_session(settings)
    assert device.fooled and report.ok and len(report.passes_written) == 2, report
    assert report.faults.foreign_acks == 1
    for path in archive.find_pass_files(tmp_path):
        assert archive.read_pass(path).geometry.rotation_table_angle_deg == pytest.approx(
            settings.rotation_table_angle_deg)


class _NeverTheCode(RigController):
    """Runs every command but leaves CMD_ACK_CODE at 0 (a controller off the map)."""

    runs = 0

    def command(self, now, regs):
        before = self.cmd_ack_seq
        super().command(now, regs)
        if self.cmd_ack_seq != before:
            self.runs += 1
        self.cmd_ack_code = 0


def test_a_controller_that_never_shows_the_commands_code_is_not_sent_it_again_and_again(tmp_path):
    # a review: the resend under a new number ran MOVE_HEIGHT 710 times in 16 s with 710 warnings
    device = _NeverTheCode(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heights_m=(0.15, 0.3), max_attempts=1))
    assert not report.passes_written and report.passes_failed
    assert device.runs <= 2 * (client_module.FOREIGN_ACK_RETRIES + 1) + 2, device.runs
    assert "CMD_ACK_CODE 0, not" in " ".join(report.passes_incomplete)


def test_the_client_heartbeat_goes_on_while_the_last_cycle_is_processed_at_the_end_of_the_session(tmp_path):
    # a review: the session waited in the processor's close (up to a minute) connected and silent, then
    # published a result: a reader that sees the heartbeat still for 2 s knows no result will come (map 5.3)
    device = _HeartbeatClock(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e6))
    results: queue.Queue = queue.Queue()

    def close(timeout_s):
        time.sleep(4.0)
        results.put(_result(1001))

    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1), processor=_processor(results, close))
    assert report.ok and len(report.passes_written) == 2, report
    gaps = [b - a for a, b in zip(device.heartbeats, device.heartbeats[1:])]
    assert max(gaps) < 2.0, gaps
