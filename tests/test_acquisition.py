"""The acquisition front end: register map, simulated rig controller, `uwbcl acquire` over loopback.

Every test talks to 127.0.0.1 only (a guard below fails any other connect) and is bounded in time: sessions
run in a thread joined with a deadline, subprocesses with a timeout.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from uwbcl import archive
from uwbcl.acquisition import registers as R
from uwbcl.acquisition.client import AcquireSettings, AcquisitionSession, ConfigError, load_settings
from uwbcl.acquisition.device import ILLEGAL_VALUE, DeviceConfig, ModbusFault, RigController, RigServer
from uwbcl.acquisition.faults import CYCLE_KINDS, KINDS, FaultInjector, parse_faults
from uwbcl.acquisition.recorder import AbsurdValue, Limits, PassAssembler, PassIncomplete
from uwbcl.acquisition.rig import WorldConfig

ROOT = Path(__file__).resolve().parents[1]
LOOPBACK = "127.0.0.1"
# A short pass (61 pulses x 32 samples, 3 s of device time) on a clock 50x faster than real time.
FAST_WORLD = WorldConfig(aperture_length_m=0.45, range_samples=32)
FAST_DEVICE = DeviceConfig(world=FAST_WORLD, time_scale=50.0, first_cycle_after_s=25.0,
                           cycle_interval_s=100.0, reboot_s=5.0)


@pytest.fixture(autouse=True)
def loopback_only(monkeypatch):
    real_connect = socket.socket.connect

    def connect(sock, address):
        if sock.family in (socket.AF_INET, socket.AF_INET6):
            assert address[0] in (LOOPBACK, "::1", "localhost"), f"test tried to reach {address}"
        return real_connect(sock, address)

    monkeypatch.setattr(socket.socket, "connect", connect)


def run_session(settings: AcquireSettings, timeout_s: float = 30.0, processor=None):
    """AcquisitionSession.run() in a thread, stopped and failed if it outlives timeout_s."""
    stop = threading.Event()
    session = AcquisitionSession(settings, stop=stop, processor=processor)
    box = {}
    thread = threading.Thread(target=lambda: box.setdefault("report", session.run()), daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        stop.set()
        thread.join(10.0)
        pytest.fail(f"acquisition did not finish within {timeout_s} s")
    return box["report"]


def settings_for(server: RigServer, out, **kw) -> AcquireSettings:
    base = {"host": LOOPBACK, "port": server.port, "out": str(out), "cycles": 1, "timeout_s": 0.5,
            "reconnect_max_s": 0.5, "stall_timeout_s": 5.0, "command_timeout_s": 10.0}
    base.update(kw)
    return AcquireSettings(**base)


def signal_cycle_after_passes(server: RigServer, passes: int, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while len(server.snapshot()["completed_passes"]) < passes and time.monotonic() < deadline:
        time.sleep(0.02)
    with server.lock:
        server.controller.signal_cycle_now(server.now())


def assert_archives_match_device(report, server: RigServer) -> None:
    """Every written file is whole and holds exactly the pulses the device produced for that pass."""
    audits = {a["token"]: a for a in server.snapshot()["completed_passes"]}
    for path in report.passes_written:
        header = archive.read_pass_header(path)
        scan = archive.read_pass(path)
        token = int(re.search(r"-p(\d+)$", header["pass_id"]).group(1))
        audit = audits[token]
        assert audit["overflow"] == 0 and scan.cycle == audit["cycle"]
        assert scan.n_pulses == audit["n_pulses"]
        np.testing.assert_array_equal(np.rint(scan.pulse_position_m * 1e6), audit["positions_um"])
        np.testing.assert_array_equal(np.rint(scan.pulse_time_s * 1e6), audit["times_us"])
        iq = np.stack([scan.echo.real, scan.echo.imag], axis=-1) / audit["scale"]
        np.testing.assert_array_equal(np.rint(iq), audit["iq"])
    leftovers = ([p for p in Path(report.passes_written[0]).parents[2].rglob(".*")]
                 if report.passes_written else [])
    assert leftovers == [], f"partial files left: {leftovers}"


# ============================================================================================== register map


def test_32_bit_values_are_high_word_first_and_floats_are_ieee_binary32():
    regs = R.RADAR.encode({"CARRIER_FREQUENCY": 4.3e9, "RAIL_MIN": -1.0})
    assert regs[0:2] == [4_300_000 >> 16, 4_300_000 & 0xFFFF]  # kHz, high word first
    assert struct.unpack(">i", struct.pack(">2H", *regs[18:20]))[0] == -1_000_000  # micrometres, signed
    p = R.PASS.encode({"AMPLITUDE_SCALE": 1.5})
    assert p[16:18] == list(struct.unpack(">2H", struct.pack(">f", 1.5)))


def test_every_block_round_trips_in_si_units_and_a_flipped_bit_fails_its_crc():
    values = {"TOKEN": 7, "CYCLE": 1001, "FIRST_SEQ": 1, "PULSES_PLANNED": 267,
              "RANGE_WINDOW_START": 9.387e-9, "SAMPLES_PER_PULSE": 128, "DIRECTION": -1,
              "AMPLITUDE_SCALE": 2.5e-5, "HEIGHT": 0.15, "TABLE_ANGLE": 30.0, "START_TIME": 1793599210.25,
              "PASS_STATE": 2}
    regs = R.PASS.encode(values)
    decoded = R.PASS.decode(regs)
    for name, v in values.items():
        assert decoded[name] == pytest.approx(v, rel=1e-7), name
    regs[5] ^= 0x0100
    with pytest.raises(R.RegisterError, match="CRC"):
        R.PASS.decode(regs)


def test_crc_is_crc16_ccitt_false():
    assert R.crc16([0x3132, 0x3334, 0x3536, 0x3738]) == 0xA12B  # "12345678"
    assert R.crc16(struct.unpack(">5H", b"123456789\0")) != 0  # defined over whole registers


def test_unavailable_results_are_the_s32_sentinel():
    regs = R.RESULT.encode({"RETREAT": float("nan"), "CREEP": 0.1})
    assert struct.unpack(">i", struct.pack(">2H", *regs[6:8]))[0] == R.NOT_AVAILABLE_S32
    assert math.isnan(R.RESULT.decode(regs)["RETREAT"]) and R.RESULT.decode(regs)["CREEP"] == 0.1


def test_values_that_do_not_fit_are_refused_with_the_field_named():
    with pytest.raises(R.RegisterError, match="PASS.SAMPLES_PER_PULSE"):
        R.PASS.encode({"SAMPLES_PER_PULSE": 70000})


def test_the_document_holds_the_register_tables_of_the_code():
    doc = (ROOT / "docs" / "modbus-register-map.md").read_text()
    for name, table in R.markdown_tables().items():
        assert table in doc, (f"docs/modbus-register-map.md: table {name} differs from "
                              f"uwbcl.acquisition.registers")


def test_pulse_records_round_trip_and_a_damaged_record_is_named():
    iq = np.array([[[1, -2], [32767, -32767]], [[0, 5], [-7, 8]]], dtype=np.int16)
    regs = (R.encode_record(41, 2.05, -0.75, R.RecordFlag.FIRST, iq[0])
            + R.encode_record(42, 2.1, -0.7425, 0, iq[1]))
    seq, t, x, _flags, out, bad = R.decode_records(regs, 2, 2)
    assert seq.tolist() == [41, 42] and t.tolist() == [2.05, 2.1] and x.tolist() == [-0.75, -0.7425]
    np.testing.assert_array_equal(out, iq)
    assert bad == []
    regs[R.record_regs(2) + 9] ^= 1
    assert R.decode_records(regs, 2, 2)[-1] == [1]


# ============================================================================================== faults spec


def test_fault_spec_parses_and_bad_items_are_named():
    plan = parse_faults("drop=0.01,corrupt@120,every=50,kinds=reboot+overflow,seed=3,slow_s=0.2")
    assert plan.probabilities == (("drop", 0.01),) and plan.at == ((120, "corrupt"),)
    assert plan.every == 50 and plan.kinds == ("reboot", "overflow") and plan.seed == 3 and plan.slow_s == 0.2
    for bad in ("melt=0.1", "drop=2", "every=x", "bogus"):
        with pytest.raises(ValueError, match=re.escape(bad.split("=")[0])):
            parse_faults(bad)


def test_fault_rotation_is_deterministic_and_pass_faults_wait_for_a_pass():
    inj = FaultInjector(parse_faults("every=2"))
    kinds = [inj.next_request(pass_running=True, device_time_s=0.0) for _ in range(2 * len(KINDS))]
    assert [k for k in kinds if k] == list(KINDS)
    inj = FaultInjector(parse_faults("reboot@1"))
    assert inj.next_request(False, 0.0) is None and inj.next_request(True, 0.0) == "reboot"


# ============================================================================================= the controller


def command(c: RigController, now, seq, code, arg=0):
    c.write(now, 0, R.COMMAND.encode({"CMD_CODE": int(code), "CMD_SEQ": seq, "ARG0": arg}))
    return R.CommandResult(c.cmd_result)


def window(c: RigController, now):
    regs = c.read(now, R.Table.INPUT, R.WINDOW_ADDRESS, 125)
    return R.WINDOW_HEADER.decode(regs[:R.WINDOW_HEADER.length])


def test_a_retransmitted_command_runs_once_and_a_busy_rig_rejects_new_ones():
    c = RigController(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=1e9))
    assert command(c, 0.0, 1, R.Command.START_PASS, 5) is R.CommandResult.ACCEPTED
    first_seq = c.pass_.first_seq
    assert command(c, 0.1, 1, R.Command.START_PASS, 5) is R.CommandResult.ACCEPTED  # same seq: ignored
    assert c.pass_.first_seq == first_seq
    assert command(c, 0.2, 2, R.Command.MOVE_HEIGHT, 300_000) is R.CommandResult.REJECTED_BUSY
    assert command(c, 0.3, 3, R.Command.ABORT) is R.CommandResult.DONE
    assert command(c, 0.4, 4, R.Command.MOVE_HEIGHT, 5_000_000) is R.CommandResult.REJECTED_RANGE


def test_a_full_buffer_drops_new_pulses_counts_them_and_never_changes_the_window():
    c = RigController(dataclasses.replace(FAST_DEVICE, buffer_capacity=4, first_cycle_after_s=1e9))
    command(c, 0.0, 1, R.Command.START_PASS, 9)
    c.advance(0.16)  # 4 pulses at 20 Hz: the buffer is full
    before = c.read(0.16, R.Table.INPUT, R.WINDOW_ADDRESS, 125)
    c.advance(0.5)
    assert c.read(0.5, R.Table.INPUT, R.WINDOW_ADDRESS, 125)[R.WINDOW_HEADER.length:] == \
        before[R.WINDOW_HEADER.length:]
    desc = R.PASS.decode(c.input_low(0.5)[96:128])
    assert desc["OVERFLOW_COUNT"] == desc["PULSES_PRODUCED"] - 4 > 0
    assert c.status_word(0.5) & R.Status.OVERFLOW
    head = window(c, 0.5)
    c.write(0.5, R.ACK.address, R.ACK.encode({"ACK_SEQ": head["OLDEST_SEQ"] + 3}))
    c.advance(0.55)
    assert window(c, 0.55)["OLDEST_SEQ"] > head["OLDEST_SEQ"] + 4  # the dropped ones are gone for good


def test_acknowledge_is_idempotent_and_cannot_run_ahead_of_the_device():
    c = RigController(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=1e9))
    command(c, 0.0, 1, R.Command.START_PASS, 9)
    c.advance(0.3)
    head = window(c, 0.3)
    ack = R.ACK.encode({"ACK_SEQ": head["OLDEST_SEQ"] + 1})
    c.write(0.3, R.ACK.address, ack)
    c.write(0.3, R.ACK.address, ack)  # a retransmission releases nothing more
    assert window(c, 0.3)["OLDEST_SEQ"] == head["OLDEST_SEQ"] + 2
    with pytest.raises(ModbusFault) as err:
        c.write(0.3, R.ACK.address, R.ACK.encode({"ACK_SEQ": head["NEWEST_SEQ"] + 1}))
    assert err.value.code == ILLEGAL_VALUE
    damaged = list(ack)
    damaged[1] ^= 4
    with pytest.raises(ModbusFault):
        c.write(0.3, R.ACK.address, damaged)


def test_a_reboot_loses_the_pass_and_changes_the_boot_id_but_not_the_cycle_counter():
    c = RigController(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=0.0))
    c.advance(0.0)
    counter = c.cycle_counter
    boot = c.boot_id
    command(c, 0.1, 1, R.Command.START_PASS, 9)
    c.reboot(0.2)
    assert c.booting(1.0) and not c.booting(5.3)
    status = R.STATUS.decode(c.input_low(6.0)[32:64])
    assert status["BOOT_ID"] != boot and status["CYCLE_COUNTER"] == counter and status["CMD_ACK_SEQ"] == 0
    assert window(c, 6.0)["RECORDS"] == 0


def test_the_cycle_signal_waits_for_a_pass_to_finish():
    c = RigController(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=0.5))
    command(c, 0.0, 1, R.Command.START_PASS, 9)
    c.advance(1.0)
    assert c.cycle_counter == FAST_DEVICE.initial_cycle  # due, but the rig is scanning
    c.advance(3.5)  # the 3 s pass is over
    assert c.cycle_counter == FAST_DEVICE.initial_cycle + 1


# ============================================================================================== recorder


def descriptor(**kw):
    d = {"TOKEN": 3, "CYCLE": 1, "FIRST_SEQ": 10, "PULSES_PLANNED": 3, "PULSES_PRODUCED": 3,
         "OVERFLOW_COUNT": 0, "RANGE_WINDOW_START": 1e-8, "SAMPLES_PER_PULSE": 2, "DIRECTION": 1,
         "AMPLITUDE_SCALE": 1.0, "HEIGHT": 0.15, "TABLE_ANGLE": 30.0, "START_TIME": 1.7e9, "PASS_STATE": 2}
    d.update(kw)
    return d


RADAR_OK = {"MAX_SAMPLES_PER_PULSE": 4096, "WINDOW_REGS": 2048, "BORESIGHT_Y_SIGN": -1}


def test_absurd_pass_sizes_fail_the_pass_before_anything_is_allocated():
    with pytest.raises(AbsurdValue, match="PULSES_PLANNED"):
        PassAssembler(descriptor(PULSES_PLANNED=10**9), RADAR_OK, Limits())
    with pytest.raises(AbsurdValue, match="SAMPLES_PER_PULSE"):
        PassAssembler(descriptor(SAMPLES_PER_PULSE=60000), RADAR_OK, Limits())
    with pytest.raises(AbsurdValue, match="MiB"):
        PassAssembler(descriptor(PULSES_PLANNED=8_000, SAMPLES_PER_PULSE=4000),
                      {**RADAR_OK, "WINDOW_REGS": 60000}, Limits(max_pass_bytes=2**26))
    # a pass the archive readers would refuse (more samples than ReadLimits.max_echo_samples) is never
    # acquired, though its int16 I/Q would fit in memory
    with pytest.raises(AbsurdValue, match="more than the 33554432 an archive may hold"):
        PassAssembler(descriptor(PULSES_PLANNED=40_000, SAMPLES_PER_PULSE=1024),
                      {**RADAR_OK, "WINDOW_REGS": 60000}, Limits())


def test_gaps_repeats_and_extra_pulses_make_the_pass_incomplete():
    iq = np.zeros((1, 2, 2), dtype=np.int16)

    def add(asm, seq, flags=0, t=None):
        asm.add(np.array([seq]), np.array([t if t is not None else seq * 0.05]), np.array([seq * 0.01]),
                np.array([flags]), iq)

    asm = PassAssembler(descriptor(), RADAR_OK, Limits())
    add(asm, 10, R.RecordFlag.FIRST)
    with pytest.raises(PassIncomplete, match="lost: seq 11-11"):
        add(asm, 12)
    with pytest.raises(PassIncomplete, match="repeated"):
        add(asm, 10, R.RecordFlag.FIRST)
    add(asm, 11)
    add(asm, 12, R.RecordFlag.LAST)
    with pytest.raises(PassIncomplete):
        add(asm, 13)
    asm.finish(descriptor())
    with pytest.raises(PassIncomplete, match="overflow"):
        asm.finish(descriptor(OVERFLOW_COUNT=2))
    with pytest.raises(PassIncomplete, match="HEIGHT changed"):
        asm.finish(descriptor(HEIGHT=0.3))


# ============================================================================================== settings


def test_settings_come_from_the_acquire_table_and_flags_override_them(tmp_path):
    cfg = tmp_path / "site.toml"
    cfg.write_text('[acquire]\nhost = "127.0.0.1"\nport = 5020\nheights_m = [0.2, 0.6]\ncycles = 3\n')
    s = load_settings(cfg, cycles=5)
    assert (s.port, s.heights_m, s.cycles) == (5020, (0.2, 0.6), 5)
    cfg.write_text("[acquire]\nspeed = 3\n")
    with pytest.raises(ConfigError, match=r"site.toml: \[acquire\] speed: unknown setting"):
        load_settings(cfg)
    cfg.write_text('[acquire]\nheights_m = [0.2, 0.2]\n')
    with pytest.raises(ConfigError, match="heights"):
        load_settings(cfg)


# ============================================================================================== over loopback


def test_happy_path_two_cycles_two_heights_archived_whole(tmp_path):
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=2, timeout_s=2.0))
    assert report.ok and not report.passes_incomplete and report.faults.total() == 0
    assert len(report.passes_written) == 4 and len(report.cycles_complete) == 2
    assert_archives_match_device(report, server)
    scans = [archive.read_pass(p) for p in report.passes_written]
    assert {s.geometry.height_m for s in scans} == {0.15, 0.30}
    assert all(s.geometry.rotation_table_angle_deg == 30.0 for s in scans)
    first = scans[0]
    assert first.rig_id == "sim-rig" and first.pass_start_time.endswith("Z")
    x_c = 0.5 * (first.pulse_position_m[0] + first.pulse_position_m[-1])  # the aperture centre (map 8)
    aim = 2.4 * math.tan(math.radians(30))
    assert first.geometry.reference_point_m == pytest.approx((x_c + aim, -2.4, 0.3))


EXPECTED_COUNTER = {"drop": "disconnects", "missing": "no_reply", "exception": "exceptions",
                    "corrupt": "corrupt", "reboot": "reboots", "reconfigure": "reboots",
                    "exception02": "exceptions", "exception03": "exceptions", "exception04": "exceptions"}


# The CYCLE_KINDS left out leave the cycle: the campaign has them
@pytest.mark.parametrize("kind", [k for k in KINDS if k not in CYCLE_KINDS])
def test_each_fault_kind_is_survived_and_nothing_incomplete_is_written(kind, tmp_path):
    # One stall only: each costs the watchdog's second, and the face moves on after 2 s.
    plan = parse_faults(f"every=11,kinds={kind},limit={1 if kind == 'stall' else 3},slow_s=0.05")
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0, faults=plan) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1,
                                          stall_timeout_s=1.0 if kind == "stall" else 5.0))
        injected = server.faults.counts()[kind]
    assert injected >= 1
    assert report.ok and len(report.passes_written) == 2, report
    assert_archives_match_device(report, server)
    if EXPECTED_COUNTER.get(kind):
        assert getattr(report.faults, EXPECTED_COUNTER[kind]) >= 1
    # These always cost the pass: it is marked incomplete and run again.
    if kind in ("reboot", "overflow", "reconfigure", "absurd", "short", "stall"):
        assert len(report.passes_incomplete) >= 1


def test_a_reply_slower_than_the_timeout_counts_as_lost_and_is_recovered(tmp_path):
    plan = parse_faults("every=11,kinds=slow,limit=2,slow_s=0.5")
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0, faults=plan) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1, timeout_s=0.2))
    assert report.ok and len(report.passes_written) == 2 and report.faults.no_reply >= 1
    assert_archives_match_device(report, server)


@pytest.mark.parametrize("results_file_blocked", [False, True])
def test_live_processing_publishes_retreat_and_creep_in_the_result_registers(results_file_blocked, tmp_path,
                                                                            caplog):
    # Blocked: a directory where the results file goes (an unwritable output), which is logged; the
    # registers and the archives are published all the same.
    from pymodbus.client import ModbusTcpClient

    from uwbcl.acquisition.live import RESULTS_FILE, LiveProcessor, processing_settings

    if results_file_blocked:
        (tmp_path / RESULTS_FILE).mkdir()

    # The second cycle signal comes as soon as the first cycle's two passes are done, however
    # loaded the machine.
    device = RigController(DeviceConfig(time_scale=80.0, first_cycle_after_s=30.0, cycle_interval_s=1e9))
    processor = LiveProcessor(processing_settings("numpy", device.campaign.nominal_web_m))
    with RigServer(device, LOOPBACK, 0) as server:
        threading.Thread(target=signal_cycle_after_passes, args=(server, 2), daemon=True).start()
        report = run_session(settings_for(server, tmp_path, cycles=2, timeout_s=1.0), timeout_s=60.0,
                             processor=processor)
        client = ModbusTcpClient(LOOPBACK, port=server.port, timeout=1.0)
        regs = client.read_holding_registers(R.RESULT.address, count=R.RESULT.length, device_id=1).registers
        client.close()
    result = R.RESULT.decode(regs)
    assert result["RESULT_SEQ"] == 1 and result["STATUS"] == R.ResultStatus.OK, report
    k, k0 = device.cycle_index(result["CYCLE"]), device.cycle_index(result["PREVIOUS_CYCLE"])
    truth = device.campaign.rig_position_m(k) - device.campaign.rig_position_m(k0)
    assert result["RETREAT"] == pytest.approx(truth[0], abs=0.005)
    assert result["CREEP"] == pytest.approx(truth[1], abs=0.005)
    if results_file_blocked:
        assert "cannot write the results file" in caplog.text
    else:
        assert (tmp_path / RESULTS_FILE).read_text().count("\n") == 3  # header + 2 cycles
    assert report.ok and processor.q_sign_warning == ""


@pytest.mark.parametrize("held, first", [(41, 42), (2**32 - 1, 1)])  # after 2^32 - 1 comes 1 (never 0)
def test_a_restarted_acquire_numbers_its_results_after_the_one_the_controller_holds(held, first, tmp_path):
    # A face automation system takes a changed (or later, serial arithmetic) RESULT_SEQ as new data: a
    # restarted uwbcl that began again at 1 would repeat, or fall behind, the number it reads.
    from pymodbus.client import ModbusTcpClient

    from uwbcl.acquisition.live import LiveProcessor, processing_settings

    device = RigController(DeviceConfig(time_scale=80.0, first_cycle_after_s=30.0, cycle_interval_s=1e9))
    processor = LiveProcessor(processing_settings("numpy", device.campaign.nominal_web_m))
    with RigServer(device, LOOPBACK, 0) as server:
        client = ModbusTcpClient(LOOPBACK, port=server.port, timeout=1.0)
        earlier = R.RESULT.encode({"RESULT_SEQ": held, "CYCLE": 7, "PREVIOUS_CYCLE": 6, "STATUS": 0})
        client.write_registers(R.RESULT.address, earlier, device_id=1)  # an earlier session's last result
        threading.Thread(target=signal_cycle_after_passes, args=(server, 2), daemon=True).start()
        report = run_session(settings_for(server, tmp_path, cycles=2, timeout_s=1.0), timeout_s=60.0,
                             processor=processor)
        regs = client.read_holding_registers(R.RESULT.address, count=R.RESULT.length, device_id=1).registers
        client.close()
    assert report.ok and R.RESULT.decode(regs)["RESULT_SEQ"] == first


def test_results_that_arrive_together_are_published_a_hold_apart_in_order(tmp_path, monkeypatch):
    import queue

    from uwbcl.acquisition import client as client_module

    results = queue.Queue()
    for cycle in (11, 12):
        results.put({"cycle": cycle, "previous_cycle": cycle - 1, "retreat_m": 0.9, "creep_m": 0.0,
                     "vertical_m": 0.0, "status_code": 0, "status": "ok", "n_targets": 5, "residual_m": 0.001,
                     "time_s": 1.8e9, "revision": 0})
    processor = SimpleNamespace(results=results, write_csv=lambda out, rows: None)
    session = AcquisitionSession(AcquireSettings(host=LOOPBACK, port=1, out=str(tmp_path)),
                                 stop=threading.Event(), processor=processor)
    written = []
    monkeypatch.setattr(session.link, "read", lambda table, address, count: [0] * count)
    monkeypatch.setattr(session.link, "write_block",
                        lambda block, values: written.append((time.monotonic(), values)))
    session._publish_results()
    session._publish_results()  # within the hold: the second waits
    assert [v["CYCLE"] for _, v in written] == [11]
    session._publish_results(final=True)  # the session ends: the hold waited out, nothing dropped
    assert [(v["CYCLE"], v["RESULT_SEQ"]) for _, v in written] == [(11, 1), (12, 2)]
    assert written[1][0] - written[0][0] >= client_module.RESULT_HOLD_S - 0.01


def test_live_processing_warns_once_about_conjugated_data_as_process_does(monkeypatch, caplog):
    from uwbcl import shift
    from uwbcl.acquisition import live

    scans = [s for s in shift.simulate_shift(shift.ShiftConfig(rigs=1, cycles=2, seed=5))]
    conjugated = [dataclasses.replace(s, echo=np.conj(s.echo)) for s in scans]
    located = []

    def locate(passes, settings):
        located.append(passes)
        return SimpleNamespace(plates=[])

    monkeypatch.setattr(live.pipeline, "locate_cycle", locate)
    monkeypatch.setattr(live.chain.RigChain, "add", lambda self, cycle: None)
    clean = live.LiveProcessor(live.processing_settings("numpy"))
    wrong = live.LiveProcessor(live.processing_settings("numpy"))
    try:
        for proc, passes in ((clean, scans), (wrong, conjugated)):
            for cycle in sorted({s.cycle for s in passes}):
                proc._process(cycle, [s for s in passes if s.cycle == cycle], True, "")
    finally:
        clean.close()
        wrong.close()
    assert clean.q_sign_warning == "" and "conjugated" in wrong.q_sign_warning
    assert [r.message for r in caplog.records if r.message.startswith("q_sign")] == \
        [f"q_sign: cycle {min(s.cycle for s in scans)}: {wrong.q_sign_warning}"]  # once, not per cycle
    assert len(located) == 4  # the warning withholds nothing: the cycles are still processed


def test_a_cycle_cut_short_after_two_heights_is_measured_live_as_process_measures_it(monkeypatch):
    """A push between heights (register map section 13, item 2) leaves a cycle with some heights: two or more
    locate the plates, as `uwbcl process` uses them (batch.group_cycles); one is INCOMPLETE_CYCLE."""
    from uwbcl.acquisition import live

    located = []
    monkeypatch.setattr(live.pipeline, "locate_cycle",
                        lambda passes, settings: located.append(passes) or SimpleNamespace(plates=[]))
    monkeypatch.setattr(live.chain.RigChain, "add", lambda self, cycle: None)
    monkeypatch.setattr(live.geo, "doppler_wrong_side", lambda scan: None)  # the stand-ins have no echo
    monkeypatch.setattr(live.pipeline, "apply_range_delay", lambda scan, delay_s: scan)
    proc = live.LiveProcessor(live.processing_settings("numpy"))
    try:
        two = [SimpleNamespace(cycle=7, geometry=SimpleNamespace(height_m=h)) for h in (0.15, 0.45)]
        cut_two = proc._process(7, two, False, "")
        cut_one = proc._process(8, two[:1], False, "")
    finally:
        proc.close()
    assert len(located) == 1 and located[0] == two
    assert [r["status"] for r in cut_two] == ["reference"]  # measured (the first cycle is the reference)
    assert [r["status"] for r in cut_one] == ["incomplete_cycle"]
    assert cut_one[0]["status_code"] == R.ResultStatus.INCOMPLETE_CYCLE


def _stand_in_live_processor(monkeypatch):
    """A LiveProcessor whose cycles locate no plates (stand-in passes without echoes), and a cycle maker."""
    from uwbcl.acquisition import live
    from uwbcl.records import CycleResult

    monkeypatch.setattr(live.pipeline, "locate_cycle", lambda passes, settings: CycleResult(
        "r", passes[0].cycle, "", (0.15, 0.45), []))
    monkeypatch.setattr(live.geo, "doppler_wrong_side", lambda scan: None)  # the stand-ins have no echo
    monkeypatch.setattr(live.pipeline, "apply_range_delay", lambda scan, delay_s: scan)

    def cycle(n, heights=(0.15, 0.45)):
        return [SimpleNamespace(cycle=n, geometry=SimpleNamespace(height_m=h)) for h in heights]

    return live.LiveProcessor(live.processing_settings("numpy")), cycle


def test_a_cycle_counter_that_goes_back_starts_the_live_measurement_again_instead_of_failing_each_cycle(
        monkeypatch, caplog):
    """Register map section 12.1 item 2: a counter that moved back numbers new cycles; each is measured (the
    first as a reference), never a PROCESSING_ERROR until the numbers pass the old ones."""
    proc, cycle = _stand_in_live_processor(monkeypatch)
    try:
        rows = [proc._process(n, cycle(n), True, "") for n in (900, 901, 5, 6)]
    finally:
        proc.close()
    statuses = [[r["status"] for r in rs] for rs in rows]
    assert statuses[0] == ["reference"] and statuses[2] == ["reference"]
    assert all(r["status_code"] != R.ResultStatus.PROCESSING_ERROR for rs in rows for r in rs), statuses
    assert [r["previous_cycle"] for r in rows[3]] == [5]
    assert "the cycle counter went back" in caplog.text


def test_a_counter_that_goes_back_from_an_incomplete_cycle_starts_the_live_measurement_again_too(
        monkeypatch):
    """900, 901, then 905 with one height (incomplete), then the counter back at 903: 903 is a reference, as
    the map says, not a row from 901 (indepZi F4: it was measured from the chain, and `uwbcl process` has
    no such row)."""
    proc, cycle = _stand_in_live_processor(monkeypatch)
    try:
        rows = [proc._process(900, cycle(900), True, ""), proc._process(901, cycle(901), True, ""),
                proc._process(905, cycle(905, (0.15,)), False, ""), proc._process(903, cycle(903), True, "")]
    finally:
        proc.close()
    assert [rs[0]["status"] for rs in rows] == ["reference", rows[1][0]["status"], "incomplete_cycle",
                                                "reference"]


def test_sigint_mid_pass_stops_cleanly_without_a_partial_archive(tmp_path):
    slow = dataclasses.replace(FAST_DEVICE, time_scale=2.0, first_cycle_after_s=1e6)  # a pass lasts 1.5 s
    with RigServer(RigController(slow), LOOPBACK, 0) as server:
        proc = subprocess.Popen(
            [sys.executable, "-m", "uwbcl.cli", "acquire", "--host", LOOPBACK, "--port", str(server.port),
             "--out", str(tmp_path), "--cycles", "3", "--timeout", "0.5"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            deadline = time.monotonic() + 30.0
            while server.faults.requests < 3 and time.monotonic() < deadline:  # the client is waiting
                time.sleep(0.02)
            with server.lock:
                server.controller.signal_cycle_now(server.now())
            while time.monotonic() < deadline:  # wait for the second pass to be under way
                snap = server.snapshot()
                if len(snap["completed_passes"]) >= 1 and snap["state"] == R.State.SCANNING:
                    break
                time.sleep(0.02)
            else:
                pytest.fail("the pass never started")
            proc.send_signal(signal.SIGINT)
            done_at_signal = len(snap["completed_passes"])
            output, _ = proc.communicate(timeout=20.0)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0, output
    assert "stopped on request" in output
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert files and all(not p.name.startswith(".") for p in files), files
    for p in files:
        archive.read_pass(p)  # every file there is whole
    assert len(files) == done_at_signal  # the pass under way when the signal came was not written


def test_simulate_device_and_acquire_work_from_the_command_line(tmp_path):
    dev = subprocess.Popen(
        [sys.executable, "-m", "uwbcl.cli", "simulate-device", "--port", "0", "--time-scale", "50",
         "--state", str(tmp_path / "rig-state.json"),
         "--first-cycle-after", "100", "--cycle-interval", "50", "--range-samples", "32"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = dev.stdout.readline()
        port = int(re.search(r"listening on 127\.0\.0\.1:(\d+)", line).group(1))
        acq = subprocess.run(
            [sys.executable, "-m", "uwbcl.cli", "acquire", "--host", LOOPBACK, "--port", str(port), "--out",
             str(tmp_path), "--cycles", "1", "--heights", "0.15,0.3"],
            capture_output=True, text=True, timeout=60, check=False)
    finally:
        dev.send_signal(signal.SIGTERM)
        tail, _ = dev.communicate(timeout=10)
    assert acq.returncode == 0, acq.stdout + acq.stderr
    assert "2 passes written" in acq.stdout
    assert len(archive.find_pass_files(tmp_path)) == 2
    assert "stopped after" in tail


def test_a_cycle_the_face_moves_on_from_mid_scan_is_abandoned_and_the_new_one_scanned(tmp_path):
    device = RigController(dataclasses.replace(FAST_DEVICE, cycle_interval_s=1e9))
    with RigServer(device, LOOPBACK, 0) as server:
        # the next push comes right after the first pass of the first cycle, between its two heights
        threading.Thread(target=signal_cycle_after_passes, args=(server, 1), daemon=True).start()
        report = run_session(settings_for(server, tmp_path, cycles=2))
    first = FAST_DEVICE.initial_cycle + 1
    assert report.cycles_incomplete == [first] and report.cycles_complete == [first + 1]
    assert len(report.passes_written) == 3 and report.ok  # 1 of the abandoned cycle + 2 of the next
    assert_archives_match_device(report, server)


class _FutureMapController(RigController):
    major = 2

    def input_low(self, now):
        regs = super().input_low(now)
        return R.IDENTITY.encode({**R.IDENTITY.decode(regs[:32]), "MAP_MAJOR": self.major}) + regs[32:]


class _PastMapController(_FutureMapController):
    major = 0


def test_a_controller_with_an_unknown_map_version_or_out_of_range_heights_is_refused(tmp_path):
    with RigServer(_FutureMapController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path), timeout_s=10.0)
    assert "register map 2." in report.error and not report.ok and not report.passes_written
    assert "upgrade uwbcl" in report.error
    # an older map is the controller's to update (indepZw F5: "upgrade uwbcl" was the advice for 0.x too)
    with RigServer(_PastMapController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path), timeout_s=10.0)
    assert "register map 0." in report.error and "update its firmware" in report.error
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heights_m=(0.15, 3.0)), timeout_s=10.0)
    assert "MOVE_HEIGHT 3000000: outside the rig's range" in report.error and not report.ok


def test_the_demo_measures_retreat_and_creep_next_to_the_truth(tmp_path, capsys):
    from uwbcl.cli import main

    assert main(["demo", "--cycles", "2", "--out", str(tmp_path), "--backend", "numpy", "--time-scale",
                 "40"]) == 0
    out = capsys.readouterr().out
    row = re.search(r"^\s+1002 \|\s+(\S+)\s+(\S+)\s+(\S+) \|\s+(\S+)\s+(\S+)\s+(\S+) \| ok$", out,
                    re.MULTILINE)
    assert row, out
    assert abs(float(row.group(3))) < 5.0 and abs(float(row.group(6))) < 5.0  # mm
    assert len(archive.find_pass_files(tmp_path)) == 4 and (tmp_path / "truth.csv").exists()


class _FrozenHeartbeatController(RigController):
    def input_low(self, now):
        regs = super().input_low(now)
        return regs[:32] + R.STATUS.encode({**R.STATUS.decode(regs[32:64]), "HEARTBEAT": 7}) + regs[64:]


def test_a_frozen_heartbeat_is_logged_as_a_fault_and_the_link_renewed(tmp_path):
    with RigServer(_FrozenHeartbeatController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heartbeat_timeout_s=0.2))
    assert report.faults.stalls >= 1 and report.faults.reconnects >= 1
    assert report.ok and len(report.passes_written) == 2


def disk_refusing(monkeypatch, failing: int) -> list:
    """The archive's writes refused (ENOSPC) `failing` times, then done; returns the pass ids tried, in
    order."""
    import errno

    from uwbcl.acquisition import client as client_module

    real, calls = client_module.write_scan, []

    def full_disk_for_a_while(*args, **kwargs):
        calls.append(args[2])
        if len(calls) <= failing:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*args, **kwargs)

    monkeypatch.setattr(client_module, "write_scan", full_disk_for_a_while)
    return calls


@pytest.mark.parametrize("failing_writes", [2, 10**6])
def test_a_pass_whose_archive_cannot_be_written_is_kept_and_written_when_the_disk_takes_it(
        failing_writes, tmp_path, monkeypatch):
    # A full disk must not cost a pass: the face has moved on, it can never be scanned again.
    calls = disk_refusing(monkeypatch, failing_writes)
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1))
    if failing_writes == 2:  # the first pass waits in memory, and is written before the second
        assert report.ok and len(report.passes_written) == 2 and report.passes_failed == []
        assert_archives_match_device(report, server)
        ids = [archive.read_pass_header(p)["pass_id"] for p in report.passes_written]
        assert ids == list(dict.fromkeys(calls))  # in acquisition order
    else:  # never: both named as lost when the session ends, nothing half-written
        assert report.passes_written == [] and len(report.passes_failed) == 2
        assert all("could not be written before the end" in f for f in report.passes_failed)


def test_a_pass_the_archive_refuses_at_the_write_is_named_as_lost_and_does_not_block_the_passes_behind_it(
        tmp_path, monkeypatch):
    from uwbcl.acquisition import client as client_module

    real, calls = client_module.write_scan, []

    def first_refused(out, scan, pass_id, **names):
        calls.append(pass_id)
        if len(calls) == 1:
            raise archive.ArchiveError(out, "/geometry@rotation_table_angle_deg", "must be within (-90, 90)")
        return real(out, scan, pass_id, **names)

    monkeypatch.setattr(client_module, "write_scan", first_refused)
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=1))
    assert not report.error and len(report.passes_written) == 1
    [lost] = report.passes_failed
    assert "rotation_table_angle_deg" in lost
    assert archive.read_pass_header(report.passes_written[0])["pass_id"] == calls[1]


def test_a_height_one_micrometre_beyond_the_rigs_range_is_refused_at_the_start(tmp_path):
    # MOVE_HEIGHT is sent in whole micrometres: 2.000001 m is 2000001, beyond HEIGHT_MAX 2000000
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, heights_m=(0.15, 2.000001)), timeout_s=10.0)
    assert "MOVE_HEIGHT 2000001: outside the rig's range" in report.error and not report.passes_written


class _CarriageOff(RigController):
    """The carriage settles `off_um` micrometres above every commanded height (PASS.HEIGHT and
    CARRIAGE_HEIGHT say so)."""

    def __init__(self, config, off_um):
        super().__init__(config)
        self.off_um = off_um

    def read(self, now, table, address, count):
        regs = super().read(now, table, address, count)
        if table is R.Table.INPUT and address == R.PASS.address and self.pass_ is not None:
            full = [0] * R.PASS.address + regs
            height = R.PASS.decode(full[R.PASS.address:R.PASS.address + R.PASS.length])["HEIGHT"]
            regs = _patch_block(full, R.PASS, HEIGHT=round(height * 1e6 + self.off_um) / 1e6)[R.PASS.address:]
        return regs


def _patch_block(regs, block, **values):
    a = block.address
    return regs[:a] + block.encode({**block.decode(regs[a:a + block.length]), **values}) \
        + regs[a + block.length:]


@pytest.mark.parametrize(("off_um", "written"), [(5000, 2), (-5000, 2), (5001, 0)])
def test_a_carriage_exactly_at_the_height_tolerance_is_inside_it(off_um, written, tmp_path):
    # "farther than height_tolerance_m" (5 mm) re-runs the pass; 5.000 mm is not farther (whole micrometres)
    with RigServer(_CarriageOff(FAST_DEVICE, off_um), LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, max_attempts=2))
    assert len(report.passes_written) == written, report


class _NeverReady(RigController):
    """STATE BOOTING, READY clear, every command refused NOT_READY, while the face's counter keeps going."""

    def input_low(self, now):
        regs = super().input_low(now)
        a = R.STATUS.address
        status = R.STATUS.decode(regs[a:a + R.STATUS.length])
        status.update(STATE=int(R.State.BOOTING), STATUS_WORD=status["STATUS_WORD"] & ~int(R.Status.READY))
        return regs[:a] + R.STATUS.encode(status) + regs[a + R.STATUS.length:]


def test_a_rig_that_never_becomes_ready_is_named_at_once_and_loses_each_cycle_as_the_counter_moves(
        tmp_path, caplog):
    device = _NeverReady(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=0.5, cycle_interval_s=60.0))
    with RigServer(device, LOOPBACK, 0) as server, caplog.at_level(logging.INFO, logger="uwbcl"):
        report = run_session(settings_for(server, tmp_path, cycles=2, command_timeout_s=100.0),
                             timeout_s=20.0)
    assert "rig not ready (state BOOTING" in caplog.text
    assert "superseded during its scan" in caplog.text  # not after command_timeout_s: when the counter moved
    assert not report.passes_written


def test_a_samples_per_pulse_above_the_radars_own_maximum_names_that_maximum():
    with pytest.raises(AbsurdValue, match="more than RADAR.MAX_SAMPLES_PER_PULSE = 415"):
        PassAssembler(descriptor(SAMPLES_PER_PULSE=416), {**RADAR_OK, "MAX_SAMPLES_PER_PULSE": 415}, Limits())


class _StopAtFirstMove(RigController):
    """Sets the client's stop event when the first MOVE_HEIGHT arrives (SIGINT while the carriage moves)."""

    def __init__(self, config, stop):
        super().__init__(config)
        self.stop, self.commands = stop, []

    def write(self, now, address, values):
        if address == R.COMMAND.address:
            self.commands.append(R.Command(values[0]))
            if self.commands[-1] is R.Command.MOVE_HEIGHT:
                self.stop.set()
        return super().write(now, address, values)


def test_a_stop_request_never_starts_a_pass(tmp_path):
    stop = threading.Event()
    # moves done at once: no wait in which the old code noticed the stop before START_PASS
    device = _StopAtFirstMove(dataclasses.replace(FAST_DEVICE, first_cycle_after_s=0.5, height_speed_m_s=1e6,
                                                  table_speed_deg_s=1e9), stop)
    with RigServer(device, LOOPBACK, 0) as server:
        report = AcquisitionSession(settings_for(server, tmp_path), stop=stop).run()
    assert report.interrupted and not report.passes_written
    assert R.Command.START_PASS not in device.commands, device.commands


class _WrongFunctionCodeServer(RigServer):
    """Answers the first three window reads (function 04) as if they were function 03 (a gateway mixing up
    the tables): the same registers, another function code."""

    wrong = 0

    def _trace_pdu(self, sending, pdu):
        pdu = super()._trace_pdu(sending, pdu)
        if sending and pdu.function_code == 4 and self.wrong < 3 and len(getattr(pdu, "registers", [])) > 100:
            self.wrong += 1
            pdu.function_code = 3
        return pdu


def test_a_reply_of_another_function_code_is_damage_and_read_again(tmp_path, caplog):
    with _WrongFunctionCodeServer(RigController(FAST_DEVICE), LOOPBACK, 0) as server, \
            caplog.at_level(logging.WARNING, logger="uwbcl"):
        report = run_session(settings_for(server, tmp_path))
    assert server.wrong == 3
    assert report.ok and len(report.passes_written) == 2
    assert report.faults.corrupt >= 3 and "function code 3, not 4" in caplog.text
    assert_archives_match_device(report, server)


class _PushMidPassOnce(RigController):
    """The face's counter steps 20 pulses into the first pass, the pass left running (map section 4.2 says
    the controller must abort it)."""

    pushed = False

    def advance(self, now):
        super().advance(now)
        p = self.pass_
        if p is not None and not self.pushed and p.produced >= 20:
            self.pushed = True
            self.cycle_counter += 1


def test_a_pass_cut_by_a_cycle_change_counts_as_an_incomplete_attempt(tmp_path):
    device = _PushMidPassOnce(FAST_DEVICE)
    with RigServer(device, LOOPBACK, 0) as server:
        report = run_session(settings_for(server, tmp_path, cycles=2))
    assert device.pushed
    assert any("cycle superseded" in line for line in report.passes_incomplete), report.passes_incomplete


def test_a_controller_whose_every_reply_arrives_damaged_is_said_to_answer_damaged_not_to_be_silent(
        tmp_path, caplog):
    # map section 9: DAMAGED, then the request fails (REFUSED): a corrupting cable, not a silent controller
    stop, damaging = threading.Event(), parse_faults("corrupt=1.0,seed=4")
    with RigServer(RigController(FAST_DEVICE), LOOPBACK, 0, faults=damaging) as server, \
            caplog.at_level(logging.WARNING, logger="uwbcl"):
        session = AcquisitionSession(settings_for(server, tmp_path, reconnect_max_s=0.2), stop=stop)
        threading.Timer(4.0, stop.set).start()
        report = session.run()
    assert "answering, but STATUS: 10 replies in a row damaged (CRC)" in caplog.text
    assert "not answering" not in caplog.text
    assert report.faults.requests_failed >= 1 and not report.passes_written


class _TableOff(RigController):
    """The table settles 1 deg from every commanded angle (PASS.TABLE_ANGLE says so)."""

    def read(self, now, table, address, count):
        regs = super().read(now, table, address, count)
        if table is R.Table.INPUT and address == R.PASS.address and self.pass_ is not None:
            full = [0] * R.PASS.address + regs
            angle = R.PASS.decode(full[R.PASS.address:R.PASS.address + R.PASS.length])["TABLE_ANGLE"]
            regs = _patch_block(full, R.PASS, TABLE_ANGLE=angle + 1.0)[R.PASS.address:]
        return regs


def test_a_table_angle_off_its_command_is_said_and_the_pass_archived_at_the_rigs_angle(tmp_path, caplog):
    with RigServer(_TableOff(FAST_DEVICE), LOOPBACK, 0) as server, \
            caplog.at_level(logging.WARNING, logger="uwbcl"):
        report = run_session(settings_for(server, tmp_path))
    assert len(report.passes_written) == 2
    assert caplog.text.count("deg from the 30.000 deg commanded; archived at the rig's") == 2
    assert all(archive.read_pass_header(p)["rotation_table_angle_deg"] == pytest.approx(31.0)
               for p in report.passes_written)
