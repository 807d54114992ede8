"""Conformance of `uwbcl simulate-device` to docs/modbus-register-map.md, checked by a client that knows
only the map: a plain pymodbus client (and raw Modbus TCP frames where pymodbus refuses to build an illegal
request), register numbers written out from the document, CRC-16/CCITT-FALSE from binascii. Nothing of
uwbcl.acquisition is imported here on purpose: if the map and the simulator disagree, this test, not the
shared code, says so.
"""

from __future__ import annotations

import binascii
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import time

import pytest
from pymodbus.client import ModbusTcpClient

LOOPBACK = "127.0.0.1"
# Register numbers from the map (sections 4-6).
IDENTITY, STATUS, RADAR, PASS, WINDOW = (0, 32), (32, 32), (64, 32), (96, 32), 1024
START_PASS, ABORT = 3, 4
ACCEPTED = 1
PASS_RUNNING, PASS_COMPLETE, PASS_ABORTED_STATE = 1, 2, 3
FAULT_PASS_ABORTED = 1 << 6
SEQ_MOD = 2**32


def crc(regs) -> int:
    return binascii.crc_hqx(struct.pack(f">{len(regs)}H", *regs), 0xFFFF)


def u32(regs, i) -> int:
    return regs[i] << 16 | regs[i + 1]


def s32_regs(v: int) -> list[int]:
    return [(v >> 16) & 0xFFFF, v & 0xFFFF]


def block(client, start_count) -> list[int]:
    """A CRC-checked input block (re-read on a mismatch, as the map says)."""
    for _ in range(5):
        rr = client.read_input_registers(start_count[0], count=start_count[1], device_id=1)
        assert not rr.isError(), rr
        if crc(rr.registers[:-1]) == rr.registers[-1]:
            return rr.registers
    raise AssertionError(f"IR {start_count}: CRC never matched")


def command(client, code, seq, arg0=0):
    regs = [code, seq, *s32_regs(arg0), 0, 0, 0]
    return client.write_registers(0, regs + [crc(regs)], device_id=1)


def ack(client, seq):
    regs = s32_regs(seq)
    return client.write_registers(8, regs + [crc(regs)], device_id=1)


def raw_exception(port, function, address, count) -> int:
    """Send one read request as raw bytes; return the exception code of the reply (0 if none)."""
    with socket.create_connection((LOOPBACK, port), timeout=2.0) as s:
        s.sendall(struct.pack(">HHHBBHH", 0x4242, 0, 6, 1, function, address, count))
        reply = s.recv(512)
    assert len(reply) >= 9 and struct.unpack(">H", reply[:2])[0] == 0x4242, reply
    return reply[8] if reply[7] & 0x80 else 0


def start_device(*args) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([sys.executable, "-m", "uwbcl.cli", "simulate-device", "--port", "0",
                             "--range-samples", "8", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stdout.readline()
    m = re.search(r"listening on 127\.0\.0\.1:(\d+)", line)
    if not m:
        proc.kill()
        pytest.fail(f"simulate-device did not start: {line!r}")
    return proc, int(m.group(1))


def stop_device(proc) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


def wait_for(predicate, timeout_s=10.0, what=""):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    pytest.fail(f"timed out waiting for {what}")


def test_boot_id_changes_and_the_cycle_counter_persists_across_restarts_and_wraps(tmp_path):
    state = tmp_path / "rig-state.json"
    proc, port = start_device("--state", str(state), "--time-scale", "50", "--initial-cycle",
                              str(SEQ_MOD - 2), "--first-cycle-after", "1", "--cycle-interval", "2",
                              "--max-cycles", "2")
    try:
        c = ModbusTcpClient(LOOPBACK, port=port, timeout=2.0)
        wait_for(lambda: u32(block(c, STATUS), 12) == 0, what="the cycle counter to wrap 2^32-1 -> 0")
        boot_1 = u32(block(c, STATUS), 4)
        c.close()
    finally:
        stop_device(proc)
    proc, port = start_device("--state", str(state), "--first-cycle-after", "1e6")
    try:
        c = ModbusTcpClient(LOOPBACK, port=port, timeout=2.0)
        status = block(c, STATUS)
        assert u32(status, 12) == 0, "CYCLE_COUNTER must keep its value across a restart"
        assert u32(status, 4) != boot_1, "BOOT_ID must differ from the previous boot's"
        # DEVICE_TIME (u64 ms) goes on from the last cycle signal, 3 device seconds after the simulator's
        # epoch 2026-11-02T06:00Z (map section 11), instead of starting from the epoch again
        epoch_ms = 1_793_599_200_000
        assert u32(status, 8) << 32 | u32(status, 10) >= epoch_ms + 3000, "DEVICE_TIME went back"

        identity, radar = block(c, IDENTITY), block(c, RADAR)
        assert identity[0] == 0x5557 and identity[1] == 1 and identity[2] >= 1  # map 1.1: these answers exist
        max_samples, window_regs = radar[11], radar[14]
        assert 10 + 9 + 2 * max_samples <= window_regs, "a MAX_SAMPLES_PER_PULSE record must fit the window"

        # Exception codes (section 1): quantity 03, address 02, value 03, function 01.
        assert raw_exception(port, 4, 0, 126) == 3 and raw_exception(port, 3, 0, 126) == 3
        assert raw_exception(port, 4, 0, 0) == 3
        assert c.read_input_registers(128, count=1, device_id=1).exception_code == 2
        assert c.read_input_registers(120, count=10, device_id=1).exception_code == 2
        assert c.read_holding_registers(11, count=1, device_id=1).registers == [0]  # reserved reads as 0
        assert c.read_holding_registers(37, count=1, device_id=1).exception_code == 2
        regs = s32_regs(0)
        assert c.write_registers(8, regs + [crc(regs), 0], device_id=1).exception_code == 2  # spans HR 11
        assert c.write_registers(14, [0, 0], device_id=1).exception_code == 2
        assert c.write_registers(8, regs + [crc(regs) ^ 1], device_id=1).exception_code == 3  # CRC
        assert c.write_registers(0, [0] * 7, device_id=1).exception_code == 3  # part of a block
        assert command(c, START_PASS, 0, 5).exception_code == 3  # CMD_SEQ 0
        assert c.write_register(1, 5, device_id=1).exception_code == 3
        assert c.write_register(11, 5, device_id=1).exception_code == 2
        assert c.read_coils(0, count=1, device_id=1).exception_code == 1
        assert u32(block(c, PASS), 0) == 0  # none of that started anything
        c.close()
    finally:
        stop_device(proc)


def test_cmd_seq_counts_only_on_acceptance_sequence_numbers_wrap_and_pass_aborted_clears(tmp_path):
    first_seq = SEQ_MOD - 6
    # Request 2 (the first START_PASS) is answered with exception 04: not executed, CMD_SEQ not recorded.
    proc, port = start_device("--state", str(tmp_path / "s.json"), "--time-scale", "5", "--first-cycle-after",
                              "1e6", "--first-seq", str(first_seq), "--faults", "exception04@2")
    try:
        c = ModbusTcpClient(LOOPBACK, port=port, timeout=2.0)
        assert block(c, STATUS)[20] == 0  # 1: CMD_ACK_SEQ 0 after boot
        assert command(c, START_PASS, 7, 1234).exception_code == 4  # 2
        status = block(c, STATUS)  # 3
        assert status[20] == 0 and u32(block(c, PASS), 0) == 0
        assert not command(c, START_PASS, 7, 1234).isError()  # the same CMD_SEQ again: a new command
        status = block(c, STATUS)
        assert status[20] == 7 and status[22] == ACCEPTED
        desc = block(c, PASS)
        assert u32(desc, 0) == 1234 and u32(desc, 4) == first_seq

        # Drain across 2^32 - 1 -> 0 (section 6): the records run on modulo 2^32.
        wait_for(lambda: block(c, (WINDOW, 10))[2] >= 12, what="12 records")
        head = block(c, (WINDOW, 10))
        n, rec_regs = head[2], head[3]
        regs = []
        while len(regs) < 10 + n * rec_regs:
            count = min(125, 10 + n * rec_regs - len(regs))
            regs += c.read_input_registers(WINDOW + len(regs), count=count, device_id=1).registers
        seqs = [u32(regs, 10 + i * rec_regs) for i in range(n)]
        assert u32(head, 0) == first_seq and seqs == [(first_seq + i) % SEQ_MOD for i in range(n)]
        assert 0 in seqs
        last = seqs[-1]
        assert not ack(c, last).isError()  # beyond the wrap, but not beyond NEWEST_SEQ
        assert u32(block(c, (WINDOW, 10)), 0) in (0, (last + 1) % SEQ_MOD)
        assert not ack(c, SEQ_MOD - 1).isError()  # "at or below" the acknowledgement, across the wrap
        newest = u32(block(c, (WINDOW, 10)), 4)
        assert ack(c, (newest + 1000) % SEQ_MOD).exception_code == 3  # beyond NEWEST_SEQ

        # ABORT sets PASS_ABORTED; the next accepted START_PASS clears it.
        assert not command(c, ABORT, 8).isError()
        assert block(c, PASS)[26] == PASS_ABORTED_STATE and block(c, STATUS)[2] & FAULT_PASS_ABORTED
        assert not command(c, START_PASS, 9, 1235).isError()
        assert not block(c, STATUS)[2] & FAULT_PASS_ABORTED and block(c, PASS)[26] == PASS_RUNNING

        # At COMPLETE, PULSES_PRODUCED equals PULSES_PLANNED (section 4.4). Keep the buffer drained.
        def complete():
            head = block(c, (WINDOW, 10))
            if head[2]:
                ack(c, (u32(head, 0) + head[2] - 1) % SEQ_MOD)
            return block(c, PASS)[26] == PASS_COMPLETE
        wait_for(complete, timeout_s=30.0, what="the pass to complete")
        desc = block(c, PASS)
        assert u32(desc, 8) == u32(desc, 6) and u32(desc, 10) == 0
        c.close()
    finally:
        stop_device(proc)
