"""`uwbcl acquire`: drive the rig over Modbus TCP, drain its pulse buffer, archive every pass whole or
not at all.

`RigLink` owns the Modbus connection: every request is retried through exception replies, lost replies and
dropped connections, reconnecting with exponential backoff, under a request-rate bound; CRC-checked blocks are
re-read when a reply comes back corrupted; IDENTITY and RADAR are read on every connection and after every
reboot; a changed BOOT_ID raises `DeviceRebooted`. `AcquisitionSession` runs the cycle loop of
docs/modbus-register-map.md section 8: wait for the cycle counter, then per height move, turn, start a pass,
drain and acknowledge its pulses, check the pass end to end (and that the controller's IDENTITY and RADAR are
still the ones the pass assumed) and write it atomically under a name that cannot collide. A pass that lost
anything is logged, never written, ABORTed and re-run. What each fault costs is `registers.FAULT_TAXONOMY`
(map section 9): only a controller that is not a compatible rig stops acquisition.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import queue
import random
import threading
import time
from pathlib import Path

from .. import archive
from ..config import read_toml
from ..records import HEIGHT_TOLERANCE_M, ConfigError
from ..utc import utc_seconds
from . import registers as R
from .recorder import (
    AbsurdValue,
    DeviceRefused,
    Limits,
    PassAssembler,
    PassIncomplete,
    check_radar,
    write_scan,
)

log = logging.getLogger("uwbcl.acquire")


class Interrupted(Exception):
    """Shutdown requested (SIGINT/SIGTERM)."""


class LinkDown(Exception):
    """A request failed (fault REFUSED: exception 01/02/03 repeated, 04/06 or damaged replies too many times
    in a row): the step it belongs to fails; inside a pass the pass is re-run. Never stops acquisition."""


class DescriptionChanged(PassIncomplete):
    """IDENTITY or RADAR differ from what the pass in progress assumed (fault DESCRIPTION_CHANGED)."""


class DeviceRebooted(Exception):
    """BOOT_ID changed: the controller restarted and lost any pass in progress."""


class CycleSuperseded(Exception):
    def __init__(self, counter: int):
        super().__init__(f"cycle counter moved on to {counter}")
        self.counter = counter


# ============================================================================================== settings


COMMAND_SLOW_S = 10.0  # a command not acknowledged or not DONE after this long is logged (once)
COMMAND_RESEND_MAX_S = 1.0  # the longest interval between writes of an unacknowledged command
# Two RESULT blocks are published at least this far apart (map section 5.3): a face automation system polling
# faster sees every one, also when processing that fell behind delivers several results at once.
RESULT_HOLD_S = 1.0
# Passes whose archive could not be written (a full disk, a share gone read-only) are kept in memory, as they
# are archived (a complex64 echo), and written again, in order, every UNWRITTEN_RETRY_S while the session
# runs: the face has moved on, so such a pass can never be acquired again. At most MAX_UNWRITTEN_PASSES and
# MAX_UNWRITTEN_BYTES (8 of the largest passes the limits allow, 64 of 4M samples) are kept: beyond, the
# oldest kept pass is lost, named, so that the newest are kept and the service is never killed for memory.
MAX_UNWRITTEN_PASSES = 64
MAX_UNWRITTEN_BYTES = 2 * 2**30
# The end of a session (--process) publishes the last results for at most this long: a controller that
# cannot be reached by then does not get them (they are in acquire-results.csv).
FINAL_PUBLISH_S = 15.0
UNNAMED_RIG_ID = "rig"  # the archives' rig id when neither the settings nor IDENTITY.RIG_ID name one (warned)
HEARTBEAT_POLL_S = 0.2  # how often the side thread of _off_the_link looks whether CLIENT_HEARTBEAT is due
HEARTBEAT_WARN_S = 60.0  # at most one warning this often about CLIENT_HEARTBEAT writes not done
SCANNED_CYCLES_KEPT = 100_000  # cycle numbers remembered as scanned (a rescan's files are named apart)
FOREIGN_ACK_RETRIES = 2  # a command acknowledged with another CMD_ACK_CODE is written again this often
TABLE_ANGLE_WARN_DEG = 0.1  # a table this far from the commanded angle is said (a fifth of process's 0.5 deg)
UNWRITTEN_RETRY_S = 10.0


@dataclasses.dataclass(frozen=True)
class AcquireSettings:
    host: str = "127.0.0.1"
    port: int = 502
    unit_id: int = 1
    out: str = "uwbcl-archive"
    heights_m: tuple[float, ...] = (0.15, 0.30)
    rotation_table_angle_deg: float = 30.0
    rib_distance_m: float = 2.4  # W: the rail-to-rib distance the reference point is placed at
    reference_height_m: float = 0.3  # height of the plate row the table aims at
    rig_id: str = ""  # empty: the device's IDENTITY.RIG_ID
    cycles: int = 0  # cycles to acquire; 0: until stopped
    timeout_s: float = 1.0  # per Modbus request
    reconnect_max_s: float = 5.0
    max_attempts: int = 5  # per pass
    stall_timeout_s: float = 15.0  # watchdog: no new pulse and no state change for this long -> ABORT, re-run
    max_request_rate_hz: float = 2500.0  # bound on requests per second: no loop can spin the link
    command_timeout_s: float = 120.0
    height_tolerance_m: float = HEIGHT_TOLERANCE_M  # PASS.HEIGHT this far from the commanded height: re-run
    poll_s: float = 0.02  # between window reads when the buffer is empty
    heartbeat_timeout_s: float = 2.0  # replies with a frozen HEARTBEAT for this long: the controller is hung
    max_samples_per_pulse: int = Limits.max_samples_per_pulse
    max_pulses_per_pass: int = Limits.max_pulses_per_pass
    max_pass_bytes: int = Limits.max_pass_bytes
    process: bool = False
    backend: str = ""  # empty: uwbcl.pipeline.ProcessingSettings' default
    web_depth_m: float = 0.0  # > 0: prior on the retreat for plate association

    @property
    def limits(self) -> Limits:
        return Limits(self.max_samples_per_pulse, self.max_pulses_per_pass, self.max_pass_bytes)

    def reference_point_m(self, boresight_y_sign: int) -> tuple[float, float, float]:
        """Scene centre T: the point of the rib on boresight (tan theta = x_T / W), at the plate
        row height."""
        w = self.rib_distance_m
        return (w * math.tan(math.radians(self.rotation_table_angle_deg)), boresight_y_sign * w,
                self.reference_height_m)

    def validate(self) -> None:
        if not self.heights_m:
            raise ConfigError(None, "acquire.heights_m", "at least one height")
        if len({round(h * 1000) for h in self.heights_m}) != len(self.heights_m):
            raise ConfigError(None, "acquire.heights_m", "heights must differ by at least 1 mm")
        if not -89.0 < self.rotation_table_angle_deg < 89.0:
            raise ConfigError(None, "acquire.rotation_table_angle_deg", "must be within (-89, 89)")
        for name in ("timeout_s", "reconnect_max_s", "stall_timeout_s", "command_timeout_s", "poll_s",
                     "rib_distance_m", "max_request_rate_hz", "height_tolerance_m"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(None, f"acquire.{name}",
                                  f"must be finite and > 0, got {getattr(self, name)}")
        if self.max_attempts < 1 or self.cycles < 0:
            raise ConfigError(None, "acquire.max_attempts/cycles",
                              "max_attempts must be >= 1 and cycles >= 0")
        if not 0 < self.port < 65536 or not 0 <= self.unit_id <= 255:
            raise ConfigError(None, "acquire.port/unit_id", "port must be in 1..65535 and unit_id in 0..255")
        if self.rig_id and rig_id_refused(self.rig_id):  # empty: the controller's RIG_ID
            raise ConfigError(None, "acquire.rig_id", f"{self.rig_id!r}: {rig_id_refused(self.rig_id)}")


def rig_id_refused(rig_id: str) -> str:
    """Why the archive would refuse `rig_id` as its /@rig_id (archive._check_root_attrs: every pass of the
    session would be drained only to be refused), or ''."""
    if "\x00" in rig_id:
        return "contains a NUL character"
    if not rig_id.strip():
        return "is blank"
    return ""


def load_settings(path: str | Path | None, **overrides) -> AcquireSettings:
    """Settings from the `[acquire]` table of a TOML file, then the non-None overrides
    (command-line flags)."""
    values: dict = {}
    if path is not None:
        table = read_toml(path).get("acquire", {})  # the one site file and its checks (uwbcl.config)
        if not isinstance(table, dict):
            raise ConfigError(path, "acquire", "must be a table ([acquire])")
        fields = {f.name: f for f in dataclasses.fields(AcquireSettings)}
        for key, value in table.items():
            if key not in fields:
                raise ConfigError(path, f"[acquire] {key}",
                                  f"unknown setting; expected one of {', '.join(fields)}")
            values[key] = _coerce(path, key, value, fields[key].type)
    values.update({k: v for k, v in overrides.items() if v is not None})
    if "heights_m" in values:
        values["heights_m"] = tuple(float(h) for h in values["heights_m"])
    settings = AcquireSettings(**values)
    try:
        settings.validate()
    except ConfigError as exc:
        raise ConfigError(path or "settings", exc.key, exc.reason) from None
    return settings


def _coerce(path, key, value, type_name):
    expected = {"str": str, "int": int, "float": (int, float), "bool": bool}.get(str(type_name))
    if str(type_name).startswith("tuple"):
        if not isinstance(value, list) or not all(isinstance(v, (int, float)) for v in value):
            raise ConfigError(path, f"[acquire] {key}", "expected a list of numbers")
        return tuple(float(v) for v in value)
    if expected is None or not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise ConfigError(path, f"[acquire] {key}", f"expected {type_name}, got {value!r}")
    return float(value) if type_name == "float" else value


# ============================================================================================== the link


@dataclasses.dataclass
class FaultCounts:
    no_reply: int = 0  # timeouts: the request may or may not have been executed
    disconnects: int = 0
    exceptions: int = 0  # Modbus exception replies
    corrupt: int = 0  # CRC mismatches
    reconnects: int = 0
    reboots: int = 0
    stalls: int = 0  # heartbeat frozen while replies kept coming
    refused: int = 0  # exception 01/02/03 (fault REFUSED), also counted in `exceptions`
    requests_failed: int = 0  # LinkDown: a request given up, its step failed
    description_changes: int = 0  # IDENTITY or RADAR differed from what a pass assumed
    rig_id_changes: int = 0
    absurd_values: int = 0
    no_progress: int = 0  # watchdog trips
    counter_decreases: int = 0
    names_taken: int = 0  # whole passes written under the unique name because the usual one was taken
    rate_limited: int = 0  # requests delayed by the request-rate bound
    incompatible_replies: int = 0  # IDENTITY replies of another MAGIC or MAP_MAJOR (read again, map 4.1)
    heartbeats_unwritten: int = 0  # CLIENT_HEARTBEAT writes refused or unanswered (best effort, map 5.2)
    foreign_acks: int = 0  # a command's CMD_SEQ acknowledged with another CMD_ACK_CODE (written again, map 7)

    def total(self) -> int:
        return self.no_reply + self.disconnects + self.exceptions + self.corrupt + self.reboots + self.stalls


class RigLink:
    """One Modbus TCP connection to the rig controller; see the module docstring."""

    MAX_EXCEPTION_RETRIES = 25  # 04/06 in a row
    MAX_REFUSED_RETRIES = 3  # 01/02/03 in a row: a damaged request gets 03 once, a broken one every time
    MAX_CRC_RETRIES = 10

    def __init__(self, host: str, port: int, *, unit_id: int = 1, timeout_s: float = 1.0,
                 reconnect_max_s: float = 5.0, stop: threading.Event | None = None,
                 max_request_rate_hz: float = 2500.0):
        from pymodbus.client import ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its errors are our fault log lines
        self.client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
        self.host, self.port, self.unit_id = host, port, unit_id
        self.reconnect_max_s = reconnect_max_s
        self.stop = stop or threading.Event()
        self.boot_id: int | None = None
        self.identity: dict | None = None  # IDENTITY and RADAR as read on this connection / since this boot
        self.radar: dict | None = None
        self.first_status: dict | None = None
        self.counts = FaultCounts()
        self.requests = 0
        self._ever_connected = False
        self.deadline: float | None = None  # time.monotonic() after which reconnecting gives up (LinkDown)
        self._jitter = random.Random(port)
        # Request-rate bound (token bucket): a tenth of a second of burst, then at most max_request_rate_hz.
        self._rate_hz = float(max_request_rate_hz)
        self._tokens = self._rate_hz / 10.0
        self._tokens_t = time.monotonic()
        self._rate_logged = 0.0

    def close(self) -> None:
        self.client.close()

    def sleep(self, seconds: float) -> None:
        if self.stop.wait(seconds):
            raise Interrupted()

    def _rate_bound(self) -> None:
        now = time.monotonic()
        self._tokens = min(self._rate_hz / 10.0, self._tokens + (now - self._tokens_t) * self._rate_hz)
        self._tokens_t = now
        if self._tokens < 1.0:
            self.counts.rate_limited += 1
            if now - self._rate_logged > 60.0:
                self._rate_logged = now
                log.warning("fault: request rate bound (%g/s) reached; requests are being delayed",
                            self._rate_hz)
            self.sleep((1.0 - self._tokens) / self._rate_hz)
            self._tokens = 1.0
            self._tokens_t = time.monotonic()
        self._tokens -= 1.0

    # ------------------------------------------------------------------------------------------ connection

    def ensure_connected(self) -> None:
        """Connect (again) with exponential backoff; read STATUS, IDENTITY and RADAR on every new
        connection (map 4.1, 4.3); DeviceRebooted if BOOT_ID changed since the last connection."""
        delay = 0.05
        while not self.client.connected:
            if self.stop.is_set():
                raise Interrupted()
            if self.deadline is not None and time.monotonic() > self.deadline:
                self.counts.requests_failed += 1
                raise LinkDown(f"{self.host}:{self.port} not reachable before the deadline")
            why = "not answering"
            if self.client.connect():
                # every connection after the first is a reconnect, also one whose set-up reads then failed
                # (counted); the log says so only of one that got through them (a booting controller may
                # accept and drop connections, map section 9)
                again = self._ever_connected
                self.counts.reconnects += again
                self._ever_connected = True
                try:
                    status = self._read_block_once(R.STATUS)
                    identity, radar = self._describe_once()
                except _NoReply:
                    log.debug("connection to %s:%d dropped before its set-up reads", self.host, self.port)
                    self.client.close()
                except LinkDown as exc:  # it answers, but every reply arrives damaged (a cable, EMI)
                    self.counts.requests_failed += 1
                    why = f"answering, but {exc}"
                    self.client.close()
                else:
                    if again:
                        log.info("reconnected to %s:%d", self.host, self.port)
                    self.identity, self.radar = identity, radar
                    self.first_status = self.first_status or status
                    rebooted = self.boot_id is not None and status["BOOT_ID"] != self.boot_id
                    self.boot_id = status["BOOT_ID"]
                    if rebooted:
                        self.counts.reboots += 1
                        log.warning("fault: controller rebooted (BOOT_ID now 0x%08X)", self.boot_id)
                        raise DeviceRebooted()
                    return
            log.log(logging.WARNING if delay >= 0.4 or why != "not answering" else logging.DEBUG,
                    "fault: %s:%d %s; retrying in %.2f s", self.host, self.port, why, delay)
            self.sleep(delay * (0.8 + 0.4 * self._jitter.random()))
            delay = min(2.0 * delay, self.reconnect_max_s)

    def _compatible_identity(self, read) -> dict:
        """IDENTITY by `read`, read twice before stopping (map 4.1: one reply never stops acquisition); a
        reply that is not this client's rig is a fault (INCOMPATIBLE), logged and counted even when the
        second read is right: a gateway that now and then answers for another unit is seen before it stops."""
        identity = read(R.IDENTITY)
        if _incompatible(identity):
            self.counts.incompatible_replies += 1
            log.warning("fault: an IDENTITY reply is not this client's rig (%s); reading it again",
                        _incompatible(identity))
            self.sleep(0.2)
            identity = read(R.IDENTITY)
            if _incompatible(identity):
                raise DeviceRefused(_incompatible(identity))
        return identity

    def _describe_once(self) -> tuple[dict, dict]:
        identity = self._compatible_identity(self._read_block_once)
        return identity, self._read_block_once(R.RADAR)

    def describe(self) -> None:
        """Re-read IDENTITY and RADAR on the open connection (after a reboot seen in STATUS)."""
        identity = self._compatible_identity(self.read_block)
        self.identity, self.radar = identity, self.read_block(R.RADAR)

    # ------------------------------------------------------------------------------------------ requests

    def _request(self, desc: str, fn):
        """One request, answered: retried through lost replies, dropped connections and exception replies
        (taxonomy NO_REPLY, BUSY, REFUSED), each retry after a growing pause, so that no loop can spin."""
        from pymodbus.exceptions import ModbusException

        exceptions = refused = lost = 0
        while True:
            if self.deadline is not None and time.monotonic() > self.deadline:  # exception replies too
                self.counts.requests_failed += 1
                raise LinkDown(f"{desc}: not answered before the deadline")
            self.ensure_connected()
            self._rate_bound()
            self.requests += 1
            try:
                reply = fn()
            except (ModbusException, OSError) as exc:
                lost_link = "onnection" in str(exc) or isinstance(exc, OSError)
                kind = "connection lost" if lost_link else "no reply"
                if kind == "no reply":
                    self.counts.no_reply += 1
                else:
                    self.counts.disconnects += 1
                log.warning("fault: %s: %s; reconnecting", desc, kind)
                self.client.close()  # a fresh connection: a late reply can never be taken for the next one
                lost += 1
                if lost > 1:  # the first one reconnects at once; a controller that keeps dropping us is paced
                    self.sleep(min(0.05 * 2 ** (lost - 2), self.reconnect_max_s)
                               * (0.8 + 0.4 * self._jitter.random()))
                continue
            if reply.isError():
                code = getattr(reply, "exception_code", None)
                self.counts.exceptions += 1
                # REFUSED: a damaged request gets one; a request this device refuses, all
                if code in (1, 2, 3):
                    self.counts.refused += 1
                    refused += 1
                    if refused > self.MAX_REFUSED_RETRIES:
                        self.counts.requests_failed += 1
                        raise LinkDown(f"{desc}: device answered Modbus exception {code} {refused} times")
                    log.warning("fault: %s: Modbus exception %s (refused); repeating it", desc, code)
                    self.sleep(0.02 * 2 ** refused)
                    continue
                exceptions += 1
                if exceptions > self.MAX_EXCEPTION_RETRIES:
                    self.counts.requests_failed += 1
                    raise LinkDown(f"{desc}: device answered exception {code} {exceptions} times")
                log.warning("fault: %s: Modbus exception %s; retrying", desc, code)
                self.sleep(min(0.01 * 2 ** exceptions, 1.0))
                continue
            return reply

    def read(self, table: R.Table, address: int, count: int) -> list[int]:
        reader = (self.client.read_input_registers if table is R.Table.INPUT
                  else self.client.read_holding_registers)

        def fn():
            return reader(address, count=count, device_id=self.unit_id)

        desc = f"read {'IR' if table is R.Table.INPUT else 'HR'} {address}+{count}"
        reply = self._request(desc, fn)
        expected = 4 if table is R.Table.INPUT else 3
        if getattr(reply, "function_code", expected) != expected:  # another request's reply, or damaged
            self.counts.corrupt += 1
            raise _Corrupt(f"{desc}: the reply is of function code {reply.function_code}, not {expected}")
        regs = reply.registers
        if len(regs) != count:
            self.counts.corrupt += 1
            raise _Corrupt(f"read {'IR' if table is R.Table.INPUT else 'HR'} {address}+{count}: {len(regs)} "
                           "registers came back")
        return list(regs)

    def _read_block_once(self, block: R.Block) -> dict:
        """Used while (re)connecting: no reconnect loop of its own."""
        from pymodbus.exceptions import ModbusException

        refused = damaged = 0  # each kind has its own limit, as in `_request` and `read_block`
        while refused < self.MAX_EXCEPTION_RETRIES and damaged < self.MAX_CRC_RETRIES:
            self._rate_bound()
            self.requests += 1
            try:
                fn = self.client.read_input_registers if block.table is R.Table.INPUT \
                    else self.client.read_holding_registers
                reply = fn(block.address, count=block.length, device_id=self.unit_id)
            except (ModbusException, OSError):
                raise _NoReply() from None
            if reply.isError():
                self.counts.exceptions += 1
                refused += 1
                log.warning("fault: %s: exception reply %s while connecting; reading it again", block.name,
                            getattr(reply, "exception_code", "?"))
                self.sleep(min(0.02 * 2 ** (refused - 1), 1.0))  # BUSY: 20 ms doubling to 1 s (map 9)
                continue
            try:
                return block.decode(reply.registers)
            except R.RegisterError as exc:
                self.counts.corrupt += 1
                damaged += 1
                log.warning("fault: %s", exc)
        what = (f"{refused} exception replies in a row (busy, device failure or refused)" if refused
                >= self.MAX_EXCEPTION_RETRIES else f"{damaged} replies in a row damaged (CRC)")
        raise LinkDown(f"{block.name}: {what} while connecting")

    def read_block(self, block: R.Block) -> dict:
        for _ in range(self.MAX_CRC_RETRIES):
            try:
                return block.decode(self.read(block.table, block.address, block.length))
            except (R.RegisterError, _Corrupt) as exc:
                self.counts.corrupt += 1 if isinstance(exc, R.RegisterError) else 0
                log.warning("fault: %s; re-reading", exc)
        self.counts.requests_failed += 1
        raise LinkDown(f"{block.name}: corrupted {self.MAX_CRC_RETRIES} times in a row")

    def write_block(self, block: R.Block, values: dict) -> None:
        """One FC16 write of the whole block. The reply echoes the address and quantity; a reply that echoes
        others answers some other request or was damaged (DAMAGED): the write is repeated, which every block
        of the map allows (section 7), up to MAX_CRC_RETRIES times."""
        regs = block.encode(values)
        desc = f"write {block.name} (HR {block.address}+{len(regs)})"
        for _ in range(self.MAX_CRC_RETRIES):
            reply = self._request(desc, lambda: self.client.write_registers(block.address, regs,
                                                                            device_id=self.unit_id))
            echo = (getattr(reply, "address", block.address), getattr(reply, "count", len(regs)))
            code = getattr(reply, "function_code", 16)
            if echo == (block.address, len(regs)) and code == 16:
                return
            self.counts.corrupt += 1
            if code != 16:
                log.warning("fault: %s: the reply is of function code %d, not 16; writing again", desc, code)
            else:
                log.warning("fault: %s: the reply echoes HR %d+%d; writing again", desc, *echo)
        self.counts.requests_failed += 1
        raise LinkDown(f"{desc}: the reply echoed another address or quantity {self.MAX_CRC_RETRIES} times")

    def write_once(self, block: R.Block, values: dict) -> bool:
        """One FC16 write of the whole block on the open connection, never retried and never reconnecting
        (a side thread's CLIENT_HEARTBEAT while the session's thread works off the link); False when not
        done. A write that got no reply closes the connection, as `_request` does: its late reply can never
        be taken for the next request's, and the session's next request reconnects."""
        from pymodbus.exceptions import ModbusException

        if not self.client.connected or self.stop.is_set():
            return False
        self._rate_bound()
        self.requests += 1
        try:
            reply = self.client.write_registers(block.address, block.encode(values), device_id=self.unit_id)
        except (ModbusException, OSError) as exc:
            log.debug("%s not written: %s", block.name, exc)
            self.client.close()
            return False
        return not reply.isError()


def _incompatible(identity: dict) -> str:
    """Why a controller is not a rig this client speaks to (fault INCOMPATIBLE), or ''."""
    if identity["MAGIC"] != R.MAP_MAGIC:
        return f"IDENTITY.MAGIC = 0x{identity['MAGIC']:04X}: not a uwbcl rig controller"
    if identity["MAP_MAJOR"] != R.MAP_VERSION[0]:
        newer = identity["MAP_MAJOR"] > R.MAP_VERSION[0]
        return (f"register map {identity['MAP_MAJOR']}.{identity['MAP_MINOR']}: this client speaks "
                f"{R.MAP_VERSION[0]}.x; " + ("upgrade uwbcl" if newer else
                                              "the controller's map is older: update its firmware"))
    return ""


class _NoReply(Exception):
    pass


class _Corrupt(R.RegisterError):
    pass


# ============================================================================================== the session


@dataclasses.dataclass
class AcquisitionReport:
    passes_written: list[str] = dataclasses.field(default_factory=list)
    passes_incomplete: list[str] = dataclasses.field(default_factory=list)  # "<pass>: <reason>", each re-run
    passes_failed: list[str] = dataclasses.field(default_factory=list)  # gave up after max_attempts
    cycles_complete: list[int] = dataclasses.field(default_factory=list)
    cycles_incomplete: list[int] = dataclasses.field(default_factory=list)
    cycles_missed: int = 0
    max_backlog_pulses: int = 0  # most pulses waiting in the device buffer at a window read
    results: list[dict] = dataclasses.field(default_factory=list)
    faults: FaultCounts = dataclasses.field(default_factory=FaultCounts)
    interrupted: bool = False
    error: str = ""

    @property
    def ok(self) -> bool:
        """Nothing failed. A cycle the face moved on from mid-scan is reported, but is no failure of ours."""
        return not (self.passes_failed or self.error)


@dataclasses.dataclass
class _DrainState:
    """The bookkeeping of one AcquisitionSession._drain loop."""
    last_progress: float
    last_status: float
    seen_state: tuple | None = None
    corrupt_in_a_row: int = 0
    empty_after_end: int = 0


def _held_bytes(scan) -> int:
    """Bytes a pass kept in memory holds: its echo as archived and its pulse times and positions."""
    return scan.echo.nbytes + scan.pulse_time_s.nbytes + scan.pulse_position_m.nbytes


def micrometres(height_m: float) -> int:
    """A height as the registers carry it (MOVE_HEIGHT's argument, PASS.HEIGHT, HEIGHT_MIN/MAX): whole
    micrometres, so limits and tolerances compare as the rig does."""
    return round(height_m * 1e6)


def _state_name(state: int) -> str:
    return R.State(state).name if state in R.State._value2member_map_ else str(state)


class AcquisitionSession:
    """Runs `uwbcl acquire` against one rig; `run()` returns an AcquisitionReport
    (docs/modbus-register-map.md s. 8)."""

    def __init__(self, settings: AcquireSettings, stop: threading.Event | None = None, processor=None):
        settings.validate()
        self.settings = settings
        self.stop = stop or threading.Event()
        self.link = RigLink(settings.host, settings.port, unit_id=settings.unit_id,
                            timeout_s=settings.timeout_s, reconnect_max_s=settings.reconnect_max_s,
                            stop=self.stop, max_request_rate_hz=settings.max_request_rate_hz)
        self.report = AcquisitionReport(faults=self.link.counts)
        self.processor = processor
        self.out = Path(settings.out)
        self._cmd_seq: int | None = None  # continues after the controller's CMD_ACK_SEQ (map 7)
        self._token = int(time.time()) % 1_000_000 * 1000  # distinct from an earlier run's tokens
        self._result_seq: int | None = None  # continues from the controller's RESULT_SEQ (map 5.3)
        self._to_publish: collections.deque[dict] = collections.deque()  # results waiting for RESULT_HOLD_S
        self._published_at = -math.inf  # time.monotonic() of the last RESULT written
        # (name, scan, pass id, unique, plain name allowed)
        self._unwritten: collections.deque[tuple] = collections.deque()
        # the cycle numbers scanned in this session, the last SCANNED_CYCLES_KEPT (insertion order)
        self._scanned_cycles: dict[int, None] = {}
        self._rescan = False  # the cycle being scanned has a number scanned before (a counter that went back)
        self._unwritten_tried_at = -math.inf
        self._late: set[str] = set()  # passes of _unwritten whose write failed at least once
        self._refused: set[str] = set()  # passes the archive refused (never written, not processed)
        self._current_pass: str | None = None  # the pass being attempted (named if a stop abandons it)
        self._started: int | None = None  # the token of the attempt's pass once START_PASS was sent
        self._last_start_s: float | None = None  # the last pass's START_TIME (s since 1970)
        self._heartbeat = 0
        self._last_heartbeat_t = 0.0
        self._heartbeat_warned_t = -math.inf
        self._active_token: int | None = None
        self._heartbeat_seen = (None, time.monotonic())  # (value, when it last changed)
        self._last_result: dict | None = None
        self._published_boot: int | None = None
        self.radar: dict | None = None
        self.identity: dict | None = None
        self.rig_id = settings.rig_id or ""

    # ------------------------------------------------------------------------------------------ top level

    def run(self) -> AcquisitionReport:
        try:
            self._cycle_loop()
        except Interrupted:
            self.report.interrupted = True
            if self._current_pass is not None:
                log.warning("stopping: shutdown requested; pass %s abandoned (%s), not written",
                            self._current_pass, "an ABORT is sent to the rig, if it answers"
                            if self._active_token is not None else "not started")
            else:
                log.warning("stopping: shutdown requested; no pass was in progress")
            self._abort_quietly()
        except DeviceRefused as exc:  # fault INCOMPATIBLE or CONFIGURATION: the only stops
            self.report.error = str(exc)
            log.error("acquisition stopped: %s", exc)
            self._abort_quietly()
        except Exception as exc:  # a defect: stop with a clear line, not a traceback in the service log only
            self.report.error = f"{type(exc).__name__}: {exc}"
            log.exception("acquisition stopped by an unexpected error")
            self._abort_quietly()
        finally:
            try:  # first, and on its own: the kept passes' last chance must not depend on the controller
                self._write_unwritten(force=True)
            except Exception as exc:  # a defect while ending: still name what is lost and close the link
                self.report.error = self.report.error or f"{type(exc).__name__}: {exc}"
                log.exception("error while writing the kept passes at the end of the session")
            try:
                if self.processor is not None:
                    with self._off_the_link():  # up to a minute: the controller still sees a live client
                        self.processor.close(5.0 if self.report.interrupted else 60.0)
                    # a controller gone at the end must not keep the session from ending (every pass is
                    # archived, every result in acquire-results.csv): reconnecting gives up at the deadline
                    self.link.deadline = time.monotonic() + FINAL_PUBLISH_S
                    self._publish_results(final=True)
            except Interrupted:  # a stop while the last results wait: they are in acquire-results.csv
                self.report.interrupted = True
                log.warning("stopping: shutdown requested while publishing the last results; those not "
                            "published in the RESULT block are in acquire-results.csv only")
            except Exception as exc:  # a defect while ending: still name what is lost and close the link
                self.report.error = self.report.error or f"{type(exc).__name__}: {exc}"
                log.exception("error while ending the session")
            finally:
                for name, *_ in self._unwritten:  # the session ends: what the disk still refuses is lost
                    self.report.passes_failed.append(f"{name}: the archive could not be written before the "
                                                     "end")
                    log.error("pass %s lost: its archive could not be written before the session ended", name)
                self.link.close()
        return self.report

    def _adopt_description(self) -> None:
        """Take IDENTITY and RADAR as the link last read them (this connection, this boot) for the next pass;
        log a new rig id; AbsurdValue if RADAR is unusable, DeviceRefused if the configuration does
        not fit."""
        if self.link.identity is None or self.link.radar is None:  # a reboot whose re-read failed: read now
            self.link.describe()
        identity, radar = self.link.identity, self.link.radar
        if identity == self.identity and radar == self.radar:  # the usual case: a reconnect, nothing changed
            return
        if not self.settings.rig_id and identity["RIG_ID"] and rig_id_refused(identity["RIG_ID"]):
            raise DeviceRefused(f"IDENTITY.RIG_ID {identity['RIG_ID']!r} cannot name an archive (it "
                                f"{rig_id_refused(identity['RIG_ID'])}); set rig_id in [acquire] "
                                "(or --rig-id)")
        if not self.rig_id:  # named in the log from the first contact, even while RADAR is refused
            self.rig_id = self.settings.rig_id or identity["RIG_ID"] or UNNAMED_RIG_ID
            if self.rig_id == UNNAMED_RIG_ID and not self.settings.rig_id:
                log.warning("IDENTITY.RIG_ID is empty: the passes are archived as rig %r, as every other "
                            "unnamed rig's would be; name it on the controller or set rig_id in [acquire] "
                            "(or --rig-id)", UNNAMED_RIG_ID)
        try:
            check_radar(radar, self.settings.limits)
        except AbsurdValue:
            self.link.counts.absurd_values += 1
            self.link.describe()  # one absurd reply must not stick: the next attempt uses a fresh read
            raise
        rig_id = self.settings.rig_id or identity["RIG_ID"] or "rig"
        if self.rig_id and rig_id != self.rig_id:
            self.link.counts.rig_id_changes += 1
            log.warning("fault: controller RIG_ID changed from %r to %r; archives carry the new id",
                        self.rig_id, rig_id)
        if self.radar is not None and radar != self.radar:
            changed = sorted(k for k in radar if radar[k] != self.radar.get(k))
            log.warning("controller RADAR changed (%s); passes from now on use the new values",
                        ", ".join(f"{k} {self.radar[k]:g} -> {radar[k]:g}" for k in changed))
        self._check_configuration(radar)
        m_max = radar["MAX_SAMPLES_PER_PULSE"]
        if m_max and R.WINDOW_HEADER.length + R.record_regs(m_max) > radar["WINDOW_REGS"]:
            fits = (radar["WINDOW_REGS"] - R.WINDOW_HEADER.length - R.record_regs(0)) // 2
            log.warning("controller RADAR breaks map 1.1 section 4.3: MAX_SAMPLES_PER_PULSE %d does not fit "
                        "WINDOW_REGS %d (at most %d samples do); a pass with more will fail", m_max,
                        radar["WINDOW_REGS"], fits)
        first = self.identity is None
        self.identity, self.radar, self.rig_id = identity, radar, rig_id
        self.reference_point_m = self.settings.reference_point_m(radar["BORESIGHT_Y_SIGN"])
        if self.processor is not None and (not self.processor.rig_id or not self.settings.rig_id):
            self.processor.rig_id = rig_id
        log.log(logging.INFO if first else logging.WARNING,
                "rig %s (%s, serial %d, firmware 0x%08X, map %d.%d) at %s:%d: f_c %.3f GHz, fs %.3f GHz, PRF "
                "%g Hz, buffer %d pulses", rig_id, identity["VENDOR"], identity["SERIAL"],
                identity["FIRMWARE"], identity["MAP_MAJOR"], identity["MAP_MINOR"], self.settings.host,
                self.settings.port, radar["CARRIER_FREQUENCY"] / 1e9, radar["SAMPLE_RATE"] / 1e9,
                radar["PRF"], radar["BUFFER_CAPACITY"])

    def _check_configuration(self, radar: dict) -> None:
        """Fault CONFIGURATION: configured heights and angle the rig cannot reach (when RADAR gives
        its limits)."""
        lo, hi = radar["HEIGHT_MIN"], radar["HEIGHT_MAX"]
        if math.isfinite(lo) and math.isfinite(hi) and hi > lo:
            for h in self.settings.heights_m:
                # in whole micrometres, as MOVE_HEIGHT sends it and the rig compares it with its limits
                if not micrometres(lo) <= micrometres(h) <= micrometres(hi):
                    raise DeviceRefused(f"MOVE_HEIGHT {micrometres(h)}: outside the rig's range (height "
                                        f"{h:g} m, RADAR HEIGHT_MIN..HEIGHT_MAX {lo:g}..{hi:g} m; check "
                                        f"heights)")
        table_max = radar["TABLE_MAX"]
        if math.isfinite(table_max) and table_max > 0 \
                and abs(self.settings.rotation_table_angle_deg) > table_max:
            raise DeviceRefused(f"SET_TABLE_ANGLE {self.settings.rotation_table_angle_deg:g} deg: outside "
                                f"the rig's range (RADAR TABLE_MAX {table_max:g} deg; check the angle)")

    def _status(self) -> dict:
        status = self.link.read_block(R.STATUS)
        if status["BOOT_ID"] != self.link.boot_id:  # rebooted without the connection dropping
            self.link.boot_id = status["BOOT_ID"]
            self.link.counts.reboots += 1
            log.warning("fault: controller rebooted (BOOT_ID now 0x%08X)", status["BOOT_ID"])
            self.link.identity = self.link.radar = None  # never the old boot's, even if this re-read fails
            self.link.describe()  # IDENTITY and RADAR of the new boot (map 9)
            raise DeviceRebooted()
        now = time.monotonic()
        if status["HEARTBEAT"] != self._heartbeat_seen[0]:
            self._heartbeat_seen = (status["HEARTBEAT"], now)
        elif now - self._heartbeat_seen[1] > self.settings.heartbeat_timeout_s:
            self.link.counts.stalls += 1
            self._heartbeat_seen = (status["HEARTBEAT"], now)
            log.warning("fault: controller heartbeat frozen for %.1f s; reconnecting",
                        self.settings.heartbeat_timeout_s)
            self.link.close()
            return self._status()
        self._client_heartbeat()
        return status

    def _client_heartbeat(self) -> None:
        """CLIENT_HEARTBEAT + 1, at most once a second (map 5.3: at least every 2 s), one write never retried.
        It tells the face automation system that uwbcl is alive; the data path does not depend on it, so a
        write refused or unanswered is counted and logged (at most once every HEARTBEAT_WARN_S) and never
        fails a step: a controller that refused every heartbeat write once stopped all acquisition (indepZw
        F1). Called from the session's thread and from the side thread of `_off_the_link`."""
        now = time.monotonic()
        if now - self._last_heartbeat_t >= 1.0:
            self._last_heartbeat_t = now
            self._heartbeat = (self._heartbeat + 1) & 0xFFFF
            if not self.link.write_once(R.CLIENT, {"CLIENT_HEARTBEAT": self._heartbeat}):
                self.link.counts.heartbeats_unwritten += 1
                if now - self._heartbeat_warned_t >= HEARTBEAT_WARN_S:
                    self._heartbeat_warned_t = now
                    log.warning("fault: CLIENT_HEARTBEAT (HR 12) not written (%d times so far): the "
                                "controller refused it, did not answer or the connection was down; "
                                "acquisition goes on, but a face automation system watching HR 12 may take "
                                "this client for dead",
                                self.link.counts.heartbeats_unwritten)

    @contextlib.contextmanager
    def _off_the_link(self):
        """Work that sends no request and may take seconds (building, checking, writing a large pass): a side
        thread keeps writing CLIENT_HEARTBEAT meanwhile, so that a face automation system never takes a
        working uwbcl for a dead one (map 5.3). The link has one user at a time: the side thread is joined
        before the session's thread sends again."""
        done = threading.Event()

        def beat() -> None:
            while not done.wait(HEARTBEAT_POLL_S):
                try:
                    self._client_heartbeat()
                except Exception as exc:  # noqa: BLE001 - never fails the work; the next request reconnects
                    log.debug("client heartbeat not written: %s", exc)

        thread = threading.Thread(target=beat, name="uwbcl-client-heartbeat", daemon=True)
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join()

    # ------------------------------------------------------------------------------------------ cycles

    def _cycle_loop(self) -> None:
        """Wait for each cycle and scan it. A step that fails outside a pass (a request refused, a reboot) is
        logged and started again after a pause; nothing here stops acquisition but DeviceRefused."""
        last: int | None = None
        done = 0
        pending: int | None = None
        pause_s = 0.1
        while not self.settings.cycles or done < self.settings.cycles:
            try:
                if last is None:
                    status = self._status()
                    last = status["CYCLE_COUNTER"]
                    if self._cmd_seq is None:
                        self._cmd_seq = status["CMD_ACK_SEQ"]
                    self._adopt_description()
                    log.info("waiting for the cycle signal (counter now %d)", last)
                cycle = pending if pending is not None else self._wait_cycle(last)
                pending = None
                step = R.seq_diff(cycle, last)  # modulo 2^32: 2^32 - 1 -> 0 is one step forward
                if step > 1:
                    self.report.cycles_missed += step - 1
                    log.warning("cycles %d-%d were never scanned (the counter jumped from %d to %d)",
                                R.seq_add(last, 1), R.seq_add(cycle, -1), last, cycle)
                elif step < 0:
                    self.link.counts.counter_decreases += 1
                    log.warning("fault: cycle counter decreased from %d to %d; scanning %d as a new cycle "
                                "(its archives are named so that they cannot replace earlier ones)", last,
                                cycle, cycle)
                last = cycle
                # a number scanned before in this session: every pass of this scan is named apart from the
                # first scan's, so one scan's files can be moved out whole (map section 12.1); a number the
                # counter jumped over and came back to was never scanned, and is named as usual
                self._rescan = cycle in self._scanned_cycles
                self._scanned_cycles[cycle] = None
                if len(self._scanned_cycles) > SCANNED_CYCLES_KEPT:  # years of cycles: memory stays bounded
                    del self._scanned_cycles[next(iter(self._scanned_cycles))]
                try:
                    pending = self._scan_cycle(cycle)
                except Interrupted:  # stopped mid-cycle: the report says this cycle was not completed
                    if cycle not in self.report.cycles_complete + self.report.cycles_incomplete:
                        self.report.cycles_incomplete.append(cycle)
                    raise
                done += 1
                pause_s = 0.1
                if pending is not None and pending == last:
                    pending = None
            except (LinkDown, DeviceRebooted, PassIncomplete) as exc:
                log.warning("fault: %s; waiting %.1f s before going on", exc or "controller rebooted",
                            pause_s)
                self.link.sleep(pause_s)
                pause_s = min(2.0 * pause_s, self.settings.reconnect_max_s)

    def _write_unwritten(self, force: bool = False) -> None:
        """Write the passes kept in memory, oldest first, until one fails again (then again after
        UNWRITTEN_RETRY_S; `force`: now)."""
        if not self._unwritten or (not force
                                   and time.monotonic() - self._unwritten_tried_at < UNWRITTEN_RETRY_S):
            return
        self._unwritten_tried_at = time.monotonic()
        while self._unwritten:
            name, scan, pass_id, unique, plain = self._unwritten[0]
            try:
                with self._off_the_link():  # a large pass, a slow share: seconds
                    path = write_scan(self.out, scan, pass_id, unique=unique, plain=plain)
            except OSError as exc:
                self._late.update(n for n, *_ in self._unwritten)
                log.warning("%d passes wait for the archive directory (%s)", len(self._unwritten), exc)
                return
            except archive.ArchiveError as exc:  # the pass itself (checked when scanned: a defect): never
                self._unwritten.popleft()          # block the passes behind it
                self._refused.add(name)
                self.report.passes_failed.append(f"{name}: {exc}")
                log.error("pass %s lost: its archive cannot be written: %s", name, exc)
                continue
            self._unwritten.popleft()
            self.report.passes_written.append(str(path))
            if path.name != archive.default_relative_path(scan).name:
                self.link.counts.names_taken += 1
                log.warning("pass %s: %s; written as %s", name, "the usual archive name was taken (cycle "
                            f"{scan.cycle} acquired before)" if plain else f"cycle {scan.cycle} was scanned "
                            "before in this session (the counter went back): named apart", path.name)
            if name in self._late:
                self._late.discard(name)
                log.warning("pass %s: written late to %s", name, path)

    def _bound_unwritten(self) -> None:
        """Drop the oldest kept passes, each named as lost, until at most MAX_UNWRITTEN_PASSES of at most
        MAX_UNWRITTEN_BYTES in all wait (after the newest was queued and tried: a pass the disk took is never
        counted, and one is lost only when it really is)."""
        held = sum(_held_bytes(scan) for _, scan, *_ in self._unwritten)
        while len(self._unwritten) > 1 and (len(self._unwritten) > MAX_UNWRITTEN_PASSES
                                            or held > MAX_UNWRITTEN_BYTES):
            name, scan, *_ = self._unwritten.popleft()
            held -= _held_bytes(scan)
            self._late.discard(name)
            self.report.passes_failed.append(
                f"{name}: its archive could not be written, and it was dropped from memory for a newer pass "
                f"(at most {MAX_UNWRITTEN_PASSES} passes, {MAX_UNWRITTEN_BYTES / 2**20:.0f} MiB, are kept)")
            log.error("pass %s lost: its archive could not be written, and the passes kept in memory reached "
                      "their bound (%d passes, %.0f MiB); the oldest is dropped for the newest", name,
                      MAX_UNWRITTEN_PASSES, MAX_UNWRITTEN_BYTES / 2**20)

    def _wait_cycle(self, last: int) -> int:
        while True:
            self._write_unwritten()
            self._publish_results()
            try:
                counter = self._status()["CYCLE_COUNTER"]
            except DeviceRebooted:
                continue
            if counter != last:
                return counter
            self.link.sleep(0.1)

    def _scan_cycle(self, cycle: int) -> int | None:
        """All heights of one cycle; returns the newer cycle counter if the face moved on mid-scan."""
        log.info("cycle %d: scanning %d heights", cycle, len(self.settings.heights_m))
        passes, start_time = [], None
        for height in self.settings.heights_m:
            name = f"{self.rig_id} c{cycle:06d} h{round(height * 1000):04d}"
            for attempt in range(1, self.settings.max_attempts + 1):
                self._publish_results()
                self._current_pass = name
                try:
                    scan, token, boot = self._run_pass(cycle, height)
                except CycleSuperseded as exc:
                    if self._started is not None:  # a pass was under way: an incomplete attempt, counted
                        self.report.passes_incomplete.append(f"{name} attempt {attempt}: cycle superseded "
                                                             f"({exc})")
                    log.warning("cycle %d superseded during its scan (%s): %d of %d heights acquired", cycle,
                                exc, len(passes), len(self.settings.heights_m))
                    self.report.cycles_incomplete.append(cycle)
                    self._submit(cycle, passes, complete=False, start_time=start_time)
                    self._current_pass = None
                    return exc.counter
                except (PassIncomplete, DeviceRebooted, LinkDown) as exc:  # fault class PASS: ABORT, re-run
                    self._abort_quietly()
                    reason = str(exc) or "controller rebooted before the pass was stored"
                    self.report.passes_incomplete.append(f"{name} attempt {attempt}: {reason}")
                    log.warning("pass %s attempt %d incomplete: %s; %s", name, attempt, reason,
                                "re-running it" if attempt < self.settings.max_attempts else "giving up")
                    if attempt > 1:  # a fault that repeats is not retried at full speed
                        self.link.sleep(min(0.05 * 2 ** (attempt - 2), self.settings.reconnect_max_s))
                    continue
                self._check_clock(name, scan)
                # the height in the id and the name is the one the archive records (PASS.HEIGHT), as the
                # archive format names files: a carriage a fraction of a millimetre off gives h0149
                pass_id = f"{archive.default_pass_id(scan)}-b{boot:08X}-p{token}"
                # one way to the archive: queued behind any pass still waiting (order kept), written now
                self._unwritten.append((name, scan, pass_id, f"b{boot:08X}_p{token}", not self._rescan))
                self._write_unwritten(force=True)
                self._bound_unwritten()
                if name in self._refused:  # named as lost by _write_unwritten
                    break
                if name in self._late:
                    log.error("pass %s: kept in memory, written when the archive directory takes it again "
                              "(%d waiting)", name, len(self._unwritten))
                else:
                    log.info("pass %s: %d pulses x %d samples, attempt %d, written to %s", name,
                             scan.n_pulses, scan.samples_per_pulse, attempt, self.report.passes_written[-1])
                if self.processor is not None:  # processed live as archived, written or waiting
                    with self._off_the_link():
                        scan = archive.as_stored(scan)
                passes.append(scan)  # (without processing only counted: no copy)
                start_time = start_time or scan.pass_start_time
                break
            else:
                self.report.passes_failed.append(f"{name}: incomplete {self.settings.max_attempts} times")
                log.error("pass %s failed %d times; cycle %d stays incomplete", name,
                          self.settings.max_attempts, cycle)
            self._current_pass = None
        complete = len(passes) == len(self.settings.heights_m)
        (self.report.cycles_complete if complete else self.report.cycles_incomplete).append(cycle)
        self._submit(cycle, passes, complete=complete, start_time=start_time)
        return None

    def _check_clock(self, name: str, scan) -> None:
        """A warning when the controller's clock, which dates every archive (PASS.START_TIME), goes back
        between passes: archived as the controller says, but `uwbcl process` orders and dates cycles by it.
        (Not compared with this machine's clock: a simulated rig runs its own, time-compressed.)"""
        start_s = utc_seconds(scan.pass_start_time)
        if self._last_start_s is not None and start_s < self._last_start_s:
            log.warning("pass %s: START_TIME %s is %.0f s before the previous pass's: the controller's clock "
                        "went back", name, scan.pass_start_time, self._last_start_s - start_s)
        self._last_start_s = start_s

    # ------------------------------------------------------------------------------------------ one pass

    def _not_stopping(self) -> None:
        """Interrupted once a stop was requested: no motion and no pass is started after it."""
        if self.stop.is_set():
            raise Interrupted()

    def _run_pass(self, cycle: int, height_m: float):
        """One attempt: returns (scan, token, boot id), the scan carrying the IDENTITY and RADAR the
        controller had for the whole pass; PassIncomplete (or a subclass), DeviceRebooted or LinkDown
        otherwise."""
        self._started = None  # the token of this attempt's pass once START_PASS was sent
        self._not_stopping()
        status = self._status()
        if status["CYCLE_COUNTER"] != cycle:
            raise CycleSuperseded(status["CYCLE_COUNTER"])
        self._adopt_description()
        boot, identity, radar, rig_id = self.link.boot_id, self.identity, self.radar, self.rig_id
        self._make_idle(status, cycle)
        self._not_stopping()
        self._command(R.Command.MOVE_HEIGHT, micrometres(height_m), cycle=cycle)
        angle_mdeg = round(self.settings.rotation_table_angle_deg * 1e3)  # SET_TABLE_ANGLE's argument
        self._command(R.Command.SET_TABLE_ANGLE, angle_mdeg, cycle=cycle)
        self._not_stopping()
        self._token = self._token % 2_000_000_000 + 1
        token = self._token
        self._command(R.Command.START_PASS, token, wait=False)
        self._active_token = self._started = token
        desc = self.link.read_block(R.PASS)
        if desc["TOKEN"] != token:
            raise PassIncomplete(f"PASS.TOKEN is {desc['TOKEN']}, not the {token} just started")
        if desc["CYCLE"] != cycle:
            counter = self._status()["CYCLE_COUNTER"]
            if counter != cycle:  # the face moved on between our STATUS and START_PASS
                self._abort_quietly()
                raise CycleSuperseded(counter)
            raise PassIncomplete(f"PASS.CYCLE is {desc['CYCLE']}, not the cycle {cycle} CYCLE_COUNTER shows")
        off_um = abs(micrometres(desc["HEIGHT"]) - micrometres(height_m))  # as the registers hold them
        if off_um > micrometres(self.settings.height_tolerance_m):
            tol_mm = 1e3 * self.settings.height_tolerance_m
            raise PassIncomplete(f"PASS.HEIGHT is {desc['HEIGHT']:.4f} m, {1e-3 * off_um:.1f} mm from the "
                                 f"{height_m:.4f} m commanded (tolerance {tol_mm:g} mm)")
        commanded_deg = angle_mdeg / 1e3
        if abs(desc["TABLE_ANGLE"] - commanded_deg) > TABLE_ANGLE_WARN_DEG:
            # archived at the angle the rig reports (it focuses the pass); a cycle's passes more than 0.5 deg
            # apart are `mismatched_parameters` in `uwbcl process`, so say it now, where the rig can be fixed
            angle = desc["TABLE_ANGLE"]
            log.warning("pass c%06d h%04d: PASS.TABLE_ANGLE is %.3f deg, %.3f deg from the %.3f deg "
                        "commanded; archived at the rig's", cycle, round(height_m * 1000), angle,
                        abs(angle - commanded_deg), commanded_deg)
        try:
            assembler = PassAssembler(desc, radar, self.settings.limits)
        except AbsurdValue:
            self.link.counts.absurd_values += 1
            raise
        self._drain(assembler)
        end = self.link.read_block(R.PASS)
        assembler.finish(end)
        self._active_token = None
        # The archive must carry what the controller used: same boot, same IDENTITY and RADAR throughout.
        if self.link.boot_id != boot:
            raise DeviceRebooted()
        if self.link.identity != identity or self.link.radar != radar:
            self.link.counts.description_changes += 1
            raise DescriptionChanged("IDENTITY or RADAR changed during the pass; running it again with the "
                                     "new values")
        try:
            with self._off_the_link():
                scan = assembler.scan_pass(radar, rig_id=rig_id, reference_point_m=self.reference_point_m,
                                           cycle=cycle)
        except AbsurdValue:
            self.link.counts.absurd_values += 1
            raise
        return scan, token, boot

    def _drain(self, asm: PassAssembler) -> None:
        """Read the window, check, store, acknowledge; until the LAST pulse (docs section 6). A no-progress
        watchdog (no new pulse and no change of STATE, STATUS_WORD, FAULT_WORD or PASS for stall_timeout_s)
        ABORTs the pass; every pass through the loop that stores nothing waits poll_s, so it cannot spin."""
        window_regs = int(self.radar["WINDOW_REGS"])
        now = time.monotonic()
        d = _DrainState(last_progress=now, last_status=now)
        while True:
            self._not_stopping()
            self._check_watchdog(asm, d)
            try:  # a wrong-length reply (_Corrupt) to the first read is damage as much as a bad CRC
                first = self.link.read(R.Table.INPUT, R.WINDOW_ADDRESS,
                                       min(R.MAX_REGISTERS_PER_READ, window_regs))
                head, records = self._decode_window(asm, first, window_regs)
            except R.RegisterError as exc:
                self.link.counts.corrupt += 0 if isinstance(exc, _Corrupt) else 1  # read() counted its own
                d.corrupt_in_a_row += 1
                log.warning("fault: %s; re-reading the window", exc)
                if d.corrupt_in_a_row > RigLink.MAX_CRC_RETRIES:
                    raise PassIncomplete(f"pulse window corrupted {d.corrupt_in_a_row} times "
                                         f"in a row") from None
                continue
            d.corrupt_in_a_row = 0
            now = time.monotonic()
            self.report.max_backlog_pulses = max(self.report.max_backlog_pulses,
                                                 R.seq_diff(head["NEWEST_SEQ"], asm.last_seq))
            stored = 0
            if records is not None:
                stored = self._store(asm, head, records)
                if stored:
                    d.last_progress = now
                if asm.last_seen:
                    return
            if not stored or now - d.last_status > 0.5:
                if self._poll_status(asm, d, now, window_empty=records is None):
                    continue  # the pass is over: look at the window once more, at once
            if not stored:
                self.link.sleep(self.settings.poll_s)

    def _check_watchdog(self, asm: PassAssembler, d: _DrainState) -> None:
        if time.monotonic() - d.last_progress > self.settings.stall_timeout_s:
            self.link.counts.no_progress += 1
            log.warning("fault: pass token %d: no new pulse and no state change for %g s (watchdog); "
                        "aborting", asm.token, self.settings.stall_timeout_s)
            raise PassIncomplete(f"no progress for {self.settings.stall_timeout_s:g} s (watchdog)")

    def _decode_window(self, asm: PassAssembler, first: list[int], window_regs: int):
        """The window header and its decoded records (None when it holds none), reading the rest of the
        window after `first`; R.RegisterError when a record fails its CRC, PassIncomplete when the window
        cannot belong to this pass."""
        hdr = R.WINDOW_HEADER.length
        head = R.WINDOW_HEADER.decode(first[:hdr])
        n, rec_regs = head["RECORDS"], head["RECORD_REGS"]
        if not n:
            return head, None
        if head["TOKEN"] != asm.token:
            raise PassIncomplete(f"the window holds pulses of pass token {head['TOKEN']}")
        if rec_regs != R.record_regs(asm.samples_per_pulse) or hdr + n * rec_regs > window_regs:
            raise PassIncomplete(f"window header claims {n} records of {rec_regs} registers")
        regs = first + self._read_rest(len(first), hdr + n * rec_regs)
        seq, t, x, flags, iq, bad = R.decode_records(regs[hdr:], n, asm.samples_per_pulse)
        if bad:
            raise R.RegisterError(f"pulse window: CRC mismatch in record(s) {bad[:5]} "
                                  f"(seq {R.seq_add(head['OLDEST_SEQ'], bad[0])})")
        return head, (seq, t, x, flags, iq)

    def _store(self, asm: PassAssembler, head: dict, records: tuple) -> int:
        """Store the records not stored yet and acknowledge; how many were new."""
        seq, t, x, flags, iq = records
        # Modulo 2^32 (map 6): records at or before the last one stored are ours already (a lost ACK).
        stale = min(max(R.seq_diff(asm.next_seq, head["OLDEST_SEQ"]), 0), head["RECORDS"])
        if stale:
            seq, t, x, flags, iq = seq[stale:], t[stale:], x[stale:], flags[stale:], iq[stale:]
        before = asm.count
        asm.add(seq, t, x, flags, iq)
        self.link.write_block(R.ACK, {"ACK_SEQ": asm.last_seq})
        return asm.count - before

    def _poll_status(self, asm: PassAssembler, d: _DrainState, now: float, window_empty: bool) -> bool:
        """Read STATUS: feed the watchdog, stop on an overflow or a pass that ended early; True when the
        pass is complete and the window should be read once more at once."""
        d.last_status = now
        status = self._status()
        state = (status["STATE"], status["STATUS_WORD"], status["FAULT_WORD"])
        if state != d.seen_state:  # a state change counts as progress for the watchdog
            if d.seen_state is not None:
                d.last_progress = now
            d.seen_state = state
        if status["STATUS_WORD"] & R.Status.OVERFLOW:
            raise PassIncomplete("device buffer overflowed: pulses were dropped")
        cycle = asm.descriptor["CYCLE"]
        if status["CYCLE_COUNTER"] != cycle and status["STATUS_WORD"] & R.Status.PASS_ACTIVE:
            # the rig moved under a running pass the controller neither held nor aborted (map 4.2): useless
            self._abort_quietly()
            log.warning("fault: cycle counter changed from %d to %d while pass token %d ran (the controller "
                        "did not abort it); the pass is incomplete", cycle, status["CYCLE_COUNTER"],
                        asm.token)
            raise CycleSuperseded(status["CYCLE_COUNTER"])
        if not window_empty or status["STATUS_WORD"] & R.Status.PASS_ACTIVE:
            return False
        p = self.link.read_block(R.PASS)
        if p["TOKEN"] == asm.token and p["PASS_STATE"] == R.PassState.RUNNING:
            # not ended: PASS_ACTIVE may be clear while the carriage approaches the rail end before its first
            # pulse (map 13.1); the no-progress watchdog bounds a pass that never goes on
            return False
        if p["TOKEN"] != asm.token or p["PASS_STATE"] != R.PassState.COMPLETE:
            raise PassIncomplete(f"pass ended ({R.enum_name(R.PassState, p['PASS_STATE'])}) before its LAST "
                                 "pulse arrived")
        # The last pulses may have arrived after our window read: look once more, then give up.
        d.empty_after_end += 1
        if d.empty_after_end > 1:
            raise PassIncomplete(f"pass complete but pulses after seq {asm.last_seq} never arrived")
        return True

    def _read_rest(self, have: int, total: int) -> list[int]:
        out = []
        address = R.WINDOW_ADDRESS + have
        end = R.WINDOW_ADDRESS + total
        while address < end:
            count = min(R.MAX_REGISTERS_PER_READ, end - address)
            out += self.link.read(R.Table.INPUT, address, count)
            address += count
        return out

    # ------------------------------------------------------------------------------------------ commands

    def _next_cmd_seq(self) -> int:
        self._cmd_seq = R.cmd_seq_next(self._cmd_seq or 0)  # 65535 -> 1; never 0
        return self._cmd_seq

    def _command(self, code: R.Command, arg: int = 0, wait: bool = True, cycle: int | None = None) -> None:
        """Write a command, confirm its acknowledgement, and (wait=True) wait until it is DONE.

        Not acknowledged: the same CMD_SEQ is written again (executed at most once, map section 7) at growing
        intervals, poll_s doubling to 1 s. A CMD_RESULT this client does not know is not final (map section
        10): it waits on. With `cycle`, a CYCLE_COUNTER that moves on meanwhile raises CycleSuperseded (map
        section 8, step 4): a stuck command must not make the rig miss the next cycle."""
        seq = self._next_cmd_seq()
        values = {"CMD_CODE": int(code), "CMD_SEQ": seq, "ARG0": arg}
        start = time.monotonic()
        deadline = start + self.settings.command_timeout_s
        resend_s, next_resend, told, foreign = self.settings.poll_s, start + self.settings.poll_s, False, 0
        self.link.write_block(R.COMMAND, values)
        while True:
            st = self._status()
            now = time.monotonic()
            if cycle is not None and st["CYCLE_COUNTER"] != cycle:
                raise CycleSuperseded(st["CYCLE_COUNTER"])
            known = st["CMD_RESULT"] in R.CommandResult._value2member_map_
            result = R.CommandResult(st["CMD_RESULT"]) if known else None
            if not told and now - start > COMMAND_SLOW_S:
                told = True
                log.warning("%s %d: not %s after %.0f s; waiting up to %g s", code.name, arg,
                            "done" if st["CMD_ACK_SEQ"] == seq else "acknowledged", now - start,
                            self.settings.command_timeout_s)
            if st["CMD_ACK_SEQ"] != seq:  # not recorded (a controller off the map): the same CMD_SEQ again
                if now > deadline:
                    raise PassIncomplete(f"{code.name}: never acknowledged (CMD_ACK_SEQ {st['CMD_ACK_SEQ']})")
                self.link.sleep(self.settings.poll_s)
                if time.monotonic() >= next_resend:
                    self.link.write_block(R.COMMAND, values)
                    resend_s = min(2.0 * resend_s, COMMAND_RESEND_MAX_S)
                    next_resend = time.monotonic() + resend_s
                continue
            if st["CMD_ACK_CODE"] != int(code):
                # its CMD_SEQ acknowledged for another command: another client's with the same number (this
                # one's was then taken for a retransmission and never run) or a controller off the map; a new
                # number runs it (indepZw F3: an angle never set, its pass archived at the rig's old one), a
                # few times: a controller that never shows the code would have it run again and again
                foreign += 1
                if foreign > FOREIGN_ACK_RETRIES or now > deadline:
                    raise PassIncomplete(f"{code.name}: CMD_SEQ {seq} acknowledged with CMD_ACK_CODE "
                                         f"{st['CMD_ACK_CODE']}, not {int(code)}, {foreign} times")
                self.link.counts.foreign_acks += 1
                log.warning("fault: %s: CMD_SEQ %d acknowledged for command %d, not %d (another client, or "
                            "a controller off the map); writing it again under a new CMD_SEQ", code.name, seq,
                            st["CMD_ACK_CODE"], int(code))
                seq = values["CMD_SEQ"] = self._next_cmd_seq()
                self.link.sleep(self.settings.poll_s)
                self.link.write_block(R.COMMAND, values)
                continue
            rejected = result is not None and result.name.startswith("REJECTED")
            if result is R.CommandResult.FAILED:
                raise PassIncomplete(f"{code.name} failed on the device "
                                     f"(FAULT_WORD 0x{st['FAULT_WORD']:04X})")
            if rejected:
                raise PassIncomplete(f"{code.name} {arg} rejected: {result.name}")
            if result is R.CommandResult.DONE or not wait:  # not waiting: the pass is followed through PASS
                return
            if now > deadline:
                raise PassIncomplete(f"{code.name} not done after {self.settings.command_timeout_s:g} s")
            self.link.sleep(self.settings.poll_s)

    def _make_idle(self, status: dict, cycle: int | None = None) -> None:
        """Until the rig is READY and not BUSY (ABORT, CLEAR_FAULTS as needed), within command_timeout_s;
        CycleSuperseded as soon as CYCLE_COUNTER leaves `cycle` (a rig that never became ready meanwhile
        loses the cycle, logged, not the cycles after it); one warning when it is not ready for another
        reason than a pass of ours (local control, booting)."""
        deadline = time.monotonic() + self.settings.command_timeout_s
        told = False
        cleared = 0  # the FAULT_WORD bits CLEAR_FAULTS was sent for in this wait
        while True:
            word = status["STATUS_WORD"]
            if cycle is not None and status["CYCLE_COUNTER"] != cycle:
                raise CycleSuperseded(status["CYCLE_COUNTER"])
            if word & R.Status.LOCAL and not told:  # the operator has the rig: say why nothing happens
                told = True
                log.warning("rig in local control (STATUS_WORD LOCAL): remote commands are rejected; waiting "
                            "up to %g s for remote control", self.settings.command_timeout_s)
            if word & R.Status.READY and not word & R.Status.BUSY:
                return
            if not word & (R.Status.READY | R.Status.BUSY) and not told:
                told = True
                log.warning("rig not ready (state %s, STATUS_WORD 0x%04X): waiting up to %g s", _state_name(
                    status["STATE"]), word, self.settings.command_timeout_s)
            fault = status["FAULT_WORD"] & ~(R.Fault.BUFFER_OVERFLOW | R.Fault.PASS_ABORTED)
            if fault & ~cleared:  # once per fault (map 9): one that persists (a jammed drive) is waited out
                cleared |= fault
                log.warning("device fault word 0x%04X: clearing faults; waiting up to %g s for READY",
                            status["FAULT_WORD"], self.settings.command_timeout_s)
                self._command(R.Command.CLEAR_FAULTS)
            elif word & R.Status.BUSY and not fault:
                log.info("device busy (state %s): aborting", _state_name(status["STATE"]))
                self._command(R.Command.ABORT)
            if time.monotonic() > deadline:
                raise PassIncomplete(f"device fault word 0x{status['FAULT_WORD']:04X} not cleared by "
                                     f"CLEAR_FAULTS within {self.settings.command_timeout_s:g} s" if fault
                                     else "device did not become ready")
            self.link.sleep(self.settings.poll_s)
            status = self._status()

    def _abort_quietly(self) -> None:
        """Best effort: stop a pass we are walking away from, so the rig does not scan on for nothing (the
        next attempt's _make_idle ABORTs with confirmation if this one does not arrive)."""
        if self._active_token is None:
            return
        self._active_token = None
        try:
            seq = self._next_cmd_seq()
            self.link.write_block(R.COMMAND, {"CMD_CODE": int(R.Command.ABORT), "CMD_SEQ": seq})
        except Exception as exc:  # noqa: BLE001 - we are already failing; the re-run aborts again if needed
            log.debug("abort not delivered: %s", exc)

    # ------------------------------------------------------------------------------------------ results

    def _submit(self, cycle: int, passes, *, complete: bool, start_time) -> None:
        if self.processor is not None:
            self.processor.submit(cycle, passes, complete=complete, start_time=start_time)

    def _publish_results(self, final: bool = False) -> None:
        """Every processed result into acquire-results.csv at once, and into the RESULT block at most one per
        RESULT_HOLD_S (the rest wait in order; `final`: all of them, the hold waited out)."""
        if self.processor is None:
            return
        if self._last_result is not None and self._published_boot != self.link.boot_id:
            self._write_result(self._last_result, final)  # a reboot cleared the RESULT block: restore it
        while True:
            try:
                result = self.processor.results.get_nowait()
            except queue.Empty:
                break
            self.report.results.append(result)
            try:  # the results file is rewritten whole each time: a failed write is made good by the next
                self.processor.write_csv(self.out, self.report.results)
            except OSError as exc:
                log.error("cannot write the results file under %s: %s; the RESULT block is still published",
                          self.out, exc.strerror or exc)
            if result.get("status_code") is not None and not result.get("revision", 0):
                self._to_publish.append(result)  # the reference cycle has nothing to publish; a re-issue
                # goes to the CSV only
        while self._to_publish:
            wait_s = RESULT_HOLD_S - (time.monotonic() - self._published_at)
            if wait_s > 0:
                if not final:
                    return
                time.sleep(wait_s)  # bounded: the session is ending, a few results at most
            result = self._to_publish.popleft()
            self._result_seq = self._next_result_seq()
            values = {"RESULT_SEQ": self._result_seq, "CYCLE": result["cycle"],
                      "PREVIOUS_CYCLE": result["previous_cycle"] or 0, "RETREAT": result["retreat_m"],
                      "CREEP": result["creep_m"], "VERTICAL": result["vertical_m"],
                      "STATUS": result["status_code"], "N_TARGETS": min(result["n_targets"], 65535),
                      "RESIDUAL": result["residual_m"] if math.isfinite(result["residual_m"]) else 0.0,
                      "TIME": result["time_s"]}
            self._last_result = values
            self._published_at = time.monotonic()
            if self._write_result(values, final):
                log.info("cycle %d: published retreat %.4f m, creep %.4f m (%s) as result %d",
                         result["cycle"], result["retreat_m"], result["creep_m"], result["status"],
                         self._result_seq)

    def _next_result_seq(self) -> int:
        """RESULT_SEQ of the next result: one more than the last this session published, or, for its first,
        than the one the controller holds (an earlier session's: a reader that takes a changed or later
        RESULT_SEQ as new data must never see a restarted uwbcl repeat a number); 1 on a block that reads 0 or
        cannot be trusted."""
        if self._result_seq is None:
            held = 0
            try:
                regs = self.link.read(R.RESULT.table, R.RESULT.address, R.RESULT.length)
                if any(regs):
                    held = R.RESULT.decode(regs)["RESULT_SEQ"]
            except (R.RegisterError, LinkDown, DeviceRebooted) as exc:
                log.warning("the RESULT block the controller holds was not read (%s); RESULT_SEQ starts at "
                            "1", exc)
            self._result_seq = int(held)
        return self._result_seq % 0xFFFFFFFF + 1

    def _write_result(self, values: dict, final: bool) -> bool:
        try:
            boot = self.link.boot_id
            self.link.write_block(R.RESULT, values)
            self._published_boot = boot
            return True
        except (LinkDown, DeviceRebooted, Interrupted) as exc:
            if isinstance(exc, Interrupted) and not final:
                raise
            # Written again at the next chance (a failed step never loses a result).
            self._published_boot = None
            log.warning("cycle %d: result not published%s: %s", values["CYCLE"], "" if final else " yet",
                        exc or "interrupted")
            return False
