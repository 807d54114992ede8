"""`uwbcl acquire`: drive the rig over Modbus TCP, drain its pulse buffer, archive every pass whole or not at all.

`RigLink` owns the Modbus connection: every request is retried through exception replies, lost replies and
dropped connections, reconnecting with exponential backoff; CRC-checked blocks are re-read when a reply comes
back corrupted; a changed BOOT_ID after a reconnect raises `DeviceRebooted`. `AcquisitionSession` runs the
cycle loop of docs/modbus-register-map.md section 8: wait for the cycle counter, then per height move, turn,
start a pass, drain and acknowledge its pulses, check the pass end to end and write it atomically. A pass
that lost anything is logged, never written, and re-run.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import queue
import random
import threading
import time
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    try:
        import tomli as tomllib  # type: ignore[no-redef]
    except ModuleNotFoundError:
        tomllib = None  # type: ignore[assignment]

from . import registers as R
from .recorder import DeviceRefused, Limits, PassAssembler, PassIncomplete, check_radar, write_scan

log = logging.getLogger("uwbcl.acquire")


class Interrupted(Exception):
    """Shutdown requested (SIGINT/SIGTERM)."""


class LinkDown(Exception):
    """The device could not be talked to within the limits (persistent exception replies, ...)."""


class DeviceRebooted(Exception):
    """BOOT_ID changed: the controller restarted and lost any pass in progress."""


class CycleSuperseded(Exception):
    def __init__(self, counter: int):
        super().__init__(f"cycle counter moved on to {counter}")
        self.counter = counter


class ConfigError(ValueError):
    pass


# ============================================================================================== settings


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
    stall_timeout_s: float = 15.0  # no new pulse for this long: the pass is given up and re-run
    command_timeout_s: float = 120.0
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
        """Scene centre T: the point of the rib on boresight (tan theta = x_T / W), at the plate row height."""
        w = self.rib_distance_m
        return (w * math.tan(math.radians(self.rotation_table_angle_deg)), boresight_y_sign * w,
                self.reference_height_m)

    def validate(self) -> None:
        if not self.heights_m:
            raise ConfigError("heights_m: at least one height")
        if len({round(h * 1000) for h in self.heights_m}) != len(self.heights_m):
            raise ConfigError("heights_m: heights must differ by at least 1 mm")
        if not -89.0 < self.rotation_table_angle_deg < 89.0:
            raise ConfigError("rotation_table_angle_deg: must be within (-89, 89)")
        for name in ("timeout_s", "reconnect_max_s", "stall_timeout_s", "command_timeout_s", "poll_s",
                     "rib_distance_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name}: must be > 0")
        if self.max_attempts < 1 or self.cycles < 0:
            raise ConfigError("max_attempts must be >= 1 and cycles >= 0")
        if not 0 < self.port < 65536 or not 0 <= self.unit_id <= 255:
            raise ConfigError("port must be in 1..65535 and unit_id in 0..255")


def load_settings(path: str | Path | None, **overrides) -> AcquireSettings:
    """Settings from the `[acquire]` table of a TOML file, then the non-None overrides (command-line flags)."""
    values: dict = {}
    if path is not None:
        if tomllib is None:
            raise ConfigError(f"{path}: reading TOML needs Python >= 3.11 or the 'tomli' package")
        try:
            with open(path, "rb") as f:
                doc = tomllib.load(f)
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise ConfigError(f"{path}: {exc}") from None
        table = doc.get("acquire", {})
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: [acquire] must be a table")
        fields = {f.name: f for f in dataclasses.fields(AcquireSettings)}
        for key, value in table.items():
            if key not in fields:
                raise ConfigError(f"{path}: [acquire] {key}: unknown setting")
            values[key] = _coerce(path, key, value, fields[key].type)
    values.update({k: v for k, v in overrides.items() if v is not None})
    if "heights_m" in values:
        values["heights_m"] = tuple(float(h) for h in values["heights_m"])
    settings = AcquireSettings(**values)
    try:
        settings.validate()
    except ConfigError as exc:
        raise ConfigError(f"{path or 'settings'}: {exc}") from None
    return settings


def _coerce(path, key, value, type_name):
    expected = {"str": str, "int": int, "float": (int, float), "bool": bool}.get(str(type_name))
    if str(type_name).startswith("tuple"):
        if not isinstance(value, list) or not all(isinstance(v, (int, float)) for v in value):
            raise ConfigError(f"{path}: [acquire] {key}: expected a list of numbers")
        return tuple(float(v) for v in value)
    if expected is None or not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
        raise ConfigError(f"{path}: [acquire] {key}: expected {type_name}, got {value!r}")
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

    def total(self) -> int:
        return self.no_reply + self.disconnects + self.exceptions + self.corrupt + self.reboots + self.stalls


class RigLink:
    """One Modbus TCP connection to the rig controller; see the module docstring."""

    MAX_EXCEPTION_RETRIES = 25
    MAX_CRC_RETRIES = 10

    def __init__(self, host: str, port: int, *, unit_id: int = 1, timeout_s: float = 1.0,
                 reconnect_max_s: float = 5.0, stop: threading.Event | None = None):
        from pymodbus.client import ModbusTcpClient

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its errors are our fault log lines
        self.client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
        self.host, self.port, self.unit_id = host, port, unit_id
        self.reconnect_max_s = reconnect_max_s
        self.stop = stop or threading.Event()
        self.boot_id: int | None = None
        self.counts = FaultCounts()
        self.requests = 0
        self._ever_connected = False
        self._jitter = random.Random(port)

    def close(self) -> None:
        self.client.close()

    def sleep(self, seconds: float) -> None:
        if self.stop.wait(seconds):
            raise Interrupted()

    # ------------------------------------------------------------------------------------------ connection

    def ensure_connected(self) -> None:
        """Connect (again) with exponential backoff; a device that accepts and then says nothing (booting) too."""
        delay = 0.05
        while not self.client.connected:
            if self.stop.is_set():
                raise Interrupted()
            if self.client.connect():
                try:
                    self._check_boot()
                except (_NoReply, LinkDown):
                    self.client.close()
                else:
                    if self._ever_connected:
                        self.counts.reconnects += 1
                        log.info("reconnected to %s:%d", self.host, self.port)
                    self._ever_connected = True
                    return
            log.log(logging.WARNING if delay >= 0.4 else logging.DEBUG,
                    "fault: %s:%d not answering; retrying in %.2f s", self.host, self.port, delay)
            self.sleep(delay * (0.8 + 0.4 * self._jitter.random()))
            delay = min(2.0 * delay, self.reconnect_max_s)

    def _check_boot(self) -> None:
        status = self._read_block_once(R.STATUS)
        boot = status["BOOT_ID"]
        if self.boot_id is not None and boot != self.boot_id:
            self.boot_id = boot
            self.counts.reboots += 1
            log.warning("fault: controller rebooted (BOOT_ID now 0x%08X)", boot)
            raise DeviceRebooted()
        self.boot_id = boot

    # ------------------------------------------------------------------------------------------ requests

    def _request(self, desc: str, fn):
        """One request, answered: retried through lost replies, dropped connections and exception replies."""
        from pymodbus.exceptions import ModbusException

        exceptions = 0
        while True:
            self.ensure_connected()
            self.requests += 1
            try:
                reply = fn()
            except (ModbusException, OSError) as exc:
                kind = "connection lost" if "onnection" in str(exc) or isinstance(exc, OSError) else "no reply"
                if kind == "no reply":
                    self.counts.no_reply += 1
                else:
                    self.counts.disconnects += 1
                log.warning("fault: %s: %s; reconnecting", desc, kind)
                self.client.close()  # a fresh connection: a late reply can never be taken for the next one
                continue
            if reply.isError():
                code = getattr(reply, "exception_code", None)
                self.counts.exceptions += 1
                if code in (1, 2, 3):  # our request is wrong for this device: retrying cannot help
                    raise LinkDown(f"{desc}: device answered Modbus exception {code}")
                exceptions += 1
                if exceptions > self.MAX_EXCEPTION_RETRIES:
                    raise LinkDown(f"{desc}: device answered exception {code} {exceptions} times")
                log.warning("fault: %s: Modbus exception %s; retrying", desc, code)
                self.sleep(min(0.01 * 2 ** exceptions, 1.0))
                continue
            return reply

    def read(self, table: R.Table, address: int, count: int) -> list[int]:
        if table is R.Table.INPUT:
            fn = lambda: self.client.read_input_registers(address, count=count, device_id=self.unit_id)
        else:
            fn = lambda: self.client.read_holding_registers(address, count=count, device_id=self.unit_id)
        regs = self._request(f"read {'IR' if table is R.Table.INPUT else 'HR'} {address}+{count}", fn).registers
        if len(regs) != count:
            self.counts.corrupt += 1
            raise _Corrupt(f"read {address}+{count}: {len(regs)} registers came back")
        return list(regs)

    def _read_block_once(self, block: R.Block) -> dict:
        """Used while (re)connecting: no reconnect loop of its own."""
        from pymodbus.exceptions import ModbusException

        for _ in range(self.MAX_CRC_RETRIES):
            try:
                fn = self.client.read_input_registers if block.table is R.Table.INPUT \
                    else self.client.read_holding_registers
                reply = fn(block.address, count=block.length, device_id=self.unit_id)
            except (ModbusException, OSError):
                raise _NoReply() from None
            if reply.isError():
                self.counts.exceptions += 1
                self.sleep(0.05)
                continue
            try:
                return block.decode(reply.registers)
            except R.RegisterError as exc:
                self.counts.corrupt += 1
                log.warning("fault: %s", exc)
        raise LinkDown(f"{block.name}: no trustworthy reply while connecting")

    def read_block(self, block: R.Block) -> dict:
        for _ in range(self.MAX_CRC_RETRIES):
            try:
                return block.decode(self.read(block.table, block.address, block.length))
            except (R.RegisterError, _Corrupt) as exc:
                self.counts.corrupt += 1 if isinstance(exc, R.RegisterError) else 0
                log.warning("fault: %s; re-reading", exc)
        raise LinkDown(f"{block.name}: corrupted {self.MAX_CRC_RETRIES} times in a row")

    def write_block(self, block: R.Block, values: dict) -> None:
        regs = block.encode(values)
        self._request(f"write {block.name}", lambda: self.client.write_registers(block.address, regs,
                                                                                 device_id=self.unit_id))


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


class AcquisitionSession:
    """Runs `uwbcl acquire` against one rig; `run()` returns an AcquisitionReport (docs/modbus-register-map.md s. 8)."""

    def __init__(self, settings: AcquireSettings, stop: threading.Event | None = None, processor=None):
        settings.validate()
        self.settings = settings
        self.stop = stop or threading.Event()
        self.link = RigLink(settings.host, settings.port, unit_id=settings.unit_id, timeout_s=settings.timeout_s,
                            reconnect_max_s=settings.reconnect_max_s, stop=self.stop)
        self.report = AcquisitionReport(faults=self.link.counts)
        self.processor = processor
        self.out = Path(settings.out)
        self._cmd_seq = 0
        self._token = int(time.time()) % 1_000_000 * 1000  # distinct from an earlier run's tokens
        self._result_seq = 0
        self._heartbeat = 0
        self._last_heartbeat_t = 0.0
        self._active_token: int | None = None
        self._heartbeat_seen = (None, time.monotonic())  # (value, when it last changed)
        self._last_result: dict | None = None
        self._published_boot: int | None = None

    # ------------------------------------------------------------------------------------------ top level

    def run(self) -> AcquisitionReport:
        try:
            self._describe_device()
            self._cycle_loop()
        except Interrupted:
            self.report.interrupted = True
            log.warning("stopping: shutdown requested; no pass in progress was written")
            self._abort_quietly()
        except (LinkDown, DeviceRefused) as exc:
            self.report.error = str(exc)
            log.error("acquisition stopped: %s", exc)
        except Exception as exc:  # a defect: stop with a clear line, not a traceback in the service log only
            self.report.error = f"{type(exc).__name__}: {exc}"
            log.exception("acquisition stopped by an unexpected error")
        finally:
            if self.processor is not None:
                self.processor.close(5.0 if self.report.interrupted else 60.0)
                self._publish_results(final=True)
            self.link.close()
        return self.report

    def _describe_device(self) -> None:
        while True:
            try:
                self.link.ensure_connected()
                ident = self.link.read_block(R.IDENTITY)
                break
            except DeviceRebooted:
                continue
        if ident["MAGIC"] != R.MAP_MAGIC:
            raise DeviceRefused(f"IDENTITY.MAGIC = 0x{ident['MAGIC']:04X}: not a uwbcl rig controller")
        if ident["MAP_MAJOR"] != R.MAP_VERSION[0]:
            raise DeviceRefused(f"register map {ident['MAP_MAJOR']}.{ident['MAP_MINOR']}: this client speaks "
                                f"{R.MAP_VERSION[0]}.x; upgrade uwbcl")
        self.radar = self._read(R.RADAR)
        check_radar(self.radar, self.settings.limits)
        self.rig_id = self.settings.rig_id or ident["RIG_ID"] or "rig"
        self.reference_point_m = self.settings.reference_point_m(self.radar["BORESIGHT_Y_SIGN"])
        if self.processor is not None and not self.processor.rig_id:
            self.processor.rig_id = self.rig_id
        log.info("rig %s (%s, serial %d, map %d.%d) at %s:%d: f_c %.3f GHz, PRF %g Hz, buffer %d pulses",
                 self.rig_id, ident["VENDOR"], ident["SERIAL"], ident["MAP_MAJOR"], ident["MAP_MINOR"],
                 self.settings.host, self.settings.port, self.radar["CARRIER_FREQUENCY"] / 1e9, self.radar["PRF"],
                 self.radar["BUFFER_CAPACITY"])

    def _read(self, block: R.Block) -> dict:
        """read_block that rides through reboots (callers that must notice them use link.read_block)."""
        while True:
            try:
                return self.link.read_block(block)
            except DeviceRebooted:
                continue

    def _status(self) -> dict:
        status = self.link.read_block(R.STATUS)
        if status["BOOT_ID"] != self.link.boot_id:  # rebooted without the connection dropping
            self.link.boot_id = status["BOOT_ID"]
            self.link.counts.reboots += 1
            log.warning("fault: controller rebooted (BOOT_ID now 0x%08X)", status["BOOT_ID"])
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
        now = time.monotonic()
        if now - self._last_heartbeat_t >= 1.0:
            self._last_heartbeat_t = now
            self._heartbeat = (self._heartbeat + 1) & 0xFFFF
            self.link.write_block(R.CLIENT, {"CLIENT_HEARTBEAT": self._heartbeat})

    # ------------------------------------------------------------------------------------------ cycles

    def _cycle_loop(self) -> None:
        last = self._read(R.STATUS)["CYCLE_COUNTER"]
        log.info("waiting for the cycle signal (counter now %d)", last)
        done = 0
        pending: int | None = None
        while not self.settings.cycles or done < self.settings.cycles:
            cycle = pending if pending is not None else self._wait_cycle(last)
            pending = None
            if cycle - last > 1:
                self.report.cycles_missed += cycle - last - 1
                log.warning("cycles %d-%d were never scanned (the counter jumped from %d to %d)", last + 1,
                            cycle - 1, last, cycle)
            last = cycle
            pending = self._scan_cycle(cycle)
            done += 1
            if pending is not None and pending == last:
                pending = None

    def _wait_cycle(self, last: int) -> int:
        while True:
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
                try:
                    scan, token = self._run_pass(cycle, height)
                except (PassIncomplete, DeviceRebooted) as exc:
                    reason = str(exc) or "controller rebooted mid-pass"
                    self.report.passes_incomplete.append(f"{name} attempt {attempt}: {reason}")
                    log.warning("pass %s attempt %d incomplete: %s; %s", name, attempt, reason,
                                "re-running it" if attempt < self.settings.max_attempts else "giving up")
                    continue
                except CycleSuperseded as exc:
                    log.warning("cycle %d superseded during its scan (%s): %d of %d heights acquired; not "
                                "processed", cycle, exc, len(passes), len(self.settings.heights_m))
                    self.report.cycles_incomplete.append(cycle)
                    self._submit(cycle, passes, complete=False, start_time=start_time)
                    return exc.counter
                pass_id = f"{self.rig_id}-c{cycle:06d}-h{round(height * 1000):04d}-p{token}"
                try:
                    path = write_scan(self.out, scan, pass_id)
                except FileExistsError as exc:
                    self.report.passes_failed.append(f"{name}: {exc.filename} already exists, not overwritten")
                    log.error("pass %s: %s already exists; not overwritten", name, exc.filename)
                    break
                except OSError as exc:  # disk full, permissions: the pass is lost to us, the service goes on
                    self.report.passes_failed.append(f"{name}: cannot write the archive: {exc}")
                    log.error("pass %s: cannot write the archive: %s", name, exc)
                    break
                self.report.passes_written.append(str(path))
                passes.append(scan)
                start_time = start_time or scan.pass_start_time
                log.info("pass %s: %d pulses x %d samples, attempt %d, written to %s", name, scan.n_pulses,
                         scan.samples_per_pulse, attempt, path)
                break
            else:
                self.report.passes_failed.append(f"{name}: incomplete {self.settings.max_attempts} times")
                log.error("pass %s failed %d times; cycle %d stays incomplete", name, self.settings.max_attempts,
                          cycle)
        complete = len(passes) == len(self.settings.heights_m)
        (self.report.cycles_complete if complete else self.report.cycles_incomplete).append(cycle)
        self._submit(cycle, passes, complete=complete, start_time=start_time)
        return None

    # ------------------------------------------------------------------------------------------ one pass

    def _run_pass(self, cycle: int, height_m: float):
        status = self._status()
        if status["CYCLE_COUNTER"] != cycle:
            raise CycleSuperseded(status["CYCLE_COUNTER"])
        self._make_idle(status)
        self._command(R.Command.MOVE_HEIGHT, round(height_m * 1e6))
        self._command(R.Command.SET_TABLE_ANGLE, round(self.settings.rotation_table_angle_deg * 1e3))
        self._token = self._token % 2_000_000_000 + 1
        token = self._token
        self._command(R.Command.START_PASS, token, wait=False)
        self._active_token = token
        desc = self.link.read_block(R.PASS)
        if desc["TOKEN"] != token:
            raise PassIncomplete(f"PASS.TOKEN is {desc['TOKEN']}, not the {token} just started")
        if desc["CYCLE"] != cycle:
            raise CycleSuperseded(desc["CYCLE"])
        assembler = PassAssembler(desc, self.radar, self.settings.limits)
        self._drain(assembler)
        end = self.link.read_block(R.PASS)
        assembler.finish(end)
        self._active_token = None
        scan = assembler.scan_pass(self.radar, rig_id=self.rig_id, reference_point_m=self.reference_point_m,
                                   cycle=cycle)
        return scan, token

    def _drain(self, asm: PassAssembler) -> None:
        """Read the window, check, store, acknowledge; until the LAST pulse (docs section 6)."""
        window_regs = int(self.radar["WINDOW_REGS"])
        hdr = R.WINDOW_HEADER.length
        last_progress = last_status = time.monotonic()
        corrupt_in_a_row = empty_after_end = 0
        while True:
            if self.stop.is_set():
                raise Interrupted()
            first = self.link.read(R.Table.INPUT, R.WINDOW_ADDRESS, min(R.MAX_REGISTERS_PER_READ, window_regs))
            try:
                head = R.WINDOW_HEADER.decode(first[:hdr])
                n, rec_regs = head["RECORDS"], head["RECORD_REGS"]
                if n:
                    if head["TOKEN"] != asm.token:
                        raise PassIncomplete(f"the window holds pulses of pass token {head['TOKEN']}")
                    if rec_regs != R.record_regs(asm.samples_per_pulse) or hdr + n * rec_regs > window_regs:
                        raise PassIncomplete(f"window header claims {n} records of {rec_regs} registers")
                    regs = first + self._read_rest(len(first), hdr + n * rec_regs)
                    seq, t, x, flags, iq, bad = R.decode_records(regs[hdr:], n, asm.samples_per_pulse)
                    if bad:
                        raise R.RegisterError(f"pulse window: CRC mismatch in record(s) {bad[:5]} "
                                              f"(seq {head['OLDEST_SEQ'] + bad[0]})")
            except R.RegisterError as exc:
                self.link.counts.corrupt += 1
                corrupt_in_a_row += 1
                log.warning("fault: %s; re-reading the window", exc)
                if corrupt_in_a_row > RigLink.MAX_CRC_RETRIES:
                    raise PassIncomplete(f"pulse window corrupted {corrupt_in_a_row} times in a row") from None
                continue
            corrupt_in_a_row = 0
            now = time.monotonic()
            self.report.max_backlog_pulses = max(self.report.max_backlog_pulses, head["NEWEST_SEQ"] - asm.last_seq)
            if n:
                stale = asm.next_seq - head["OLDEST_SEQ"]
                if stale > 0:  # our acknowledgement got lost on the way: these we already hold
                    seq, t, x, flags, iq = seq[stale:], t[stale:], x[stale:], flags[stale:], iq[stale:]
                asm.add(seq, t, x, flags, iq)
                self.link.write_block(R.ACK, {"ACK_SEQ": asm.last_seq})
                last_progress = now
                if asm.last_seen:
                    return
            if not n or now - last_status > 0.5:
                last_status = now
                status = self._status()
                if status["STATUS_WORD"] & R.Status.OVERFLOW:
                    self._abort_quietly()
                    raise PassIncomplete("device buffer overflowed: pulses were dropped")
                if not n and not status["STATUS_WORD"] & R.Status.PASS_ACTIVE:
                    d = self.link.read_block(R.PASS)
                    if d["TOKEN"] != asm.token or d["PASS_STATE"] != R.PassState.COMPLETE:
                        state = R.PassState(d["PASS_STATE"]).name if d["PASS_STATE"] < 4 else d["PASS_STATE"]
                        raise PassIncomplete(f"pass ended ({state}) before its LAST pulse arrived")
                    # The last pulses may have arrived after our window read: look once more, then give up.
                    empty_after_end += 1
                    if empty_after_end > 1:
                        raise PassIncomplete(f"pass complete but pulses after seq {asm.last_seq} never arrived")
                    continue
            if not n:
                if now - last_progress > self.settings.stall_timeout_s:
                    self._abort_quietly()
                    raise PassIncomplete(f"no pulse for {self.settings.stall_timeout_s:g} s")
                self.link.sleep(self.settings.poll_s)

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

    def _command(self, code: R.Command, arg: int = 0, wait: bool = True) -> None:
        """Write a command, confirm its acknowledgement, and (wait=True) wait until it is DONE."""
        self._cmd_seq = self._cmd_seq % 65535 + 1
        seq = self._cmd_seq
        values = {"CMD_CODE": int(code), "CMD_SEQ": seq, "ARG0": arg}
        deadline = time.monotonic() + self.settings.command_timeout_s
        self.link.write_block(R.COMMAND, values)
        while True:
            st = self._status()
            if st["CMD_ACK_SEQ"] != seq:  # cannot normally happen: the write was answered
                self.link.write_block(R.COMMAND, values)
                continue
            result = R.CommandResult(st["CMD_RESULT"])
            if result is R.CommandResult.DONE or (result is R.CommandResult.ACCEPTED and not wait):
                return
            if result is R.CommandResult.FAILED:
                raise PassIncomplete(f"{code.name} failed on the device (FAULT_WORD 0x{st['FAULT_WORD']:04X})")
            if result is R.CommandResult.REJECTED_RANGE:
                raise DeviceRefused(f"{code.name} {arg}: outside the rig's range (check heights/angle)")
            if result is not R.CommandResult.ACCEPTED:
                raise PassIncomplete(f"{code.name} rejected: {result.name}")
            if time.monotonic() > deadline:
                self._abort_quietly()
                raise PassIncomplete(f"{code.name} not done after {self.settings.command_timeout_s:g} s")
            self.link.sleep(self.settings.poll_s)

    def _make_idle(self, status: dict) -> None:
        deadline = time.monotonic() + self.settings.command_timeout_s
        while True:
            word = status["STATUS_WORD"]
            if word & R.Status.READY and not word & R.Status.BUSY:
                return
            if status["FAULT_WORD"] & ~(R.Fault.BUFFER_OVERFLOW | R.Fault.PASS_ABORTED):
                log.warning("device fault word 0x%04X: clearing faults", status["FAULT_WORD"])
                self._command(R.Command.CLEAR_FAULTS)
            elif word & R.Status.BUSY:
                log.info("device busy (state %s): aborting", R.State(status["STATE"]).name)
                self._command(R.Command.ABORT)
            if time.monotonic() > deadline:
                raise PassIncomplete("device did not become ready")
            self.link.sleep(self.settings.poll_s)
            status = self._status()

    def _abort_quietly(self) -> None:
        """Best effort: stop a pass we are walking away from, so the rig does not scan on for nothing."""
        if self._active_token is None:
            return
        self._active_token = None
        try:
            self._cmd_seq = self._cmd_seq % 65535 + 1
            self.link.write_block(R.COMMAND, {"CMD_CODE": int(R.Command.ABORT), "CMD_SEQ": self._cmd_seq})
        except Exception as exc:  # noqa: BLE001 - we are already failing; the re-run aborts again if needed
            log.debug("abort not delivered: %s", exc)

    # ------------------------------------------------------------------------------------------ results

    def _submit(self, cycle: int, passes, *, complete: bool, start_time) -> None:
        if self.processor is not None:
            self.processor.submit(cycle, passes, complete=complete, start_time=start_time)

    def _publish_results(self, final: bool = False) -> None:
        if self.processor is None:
            return
        if self._last_result is not None and self._published_boot != self.link.boot_id:
            self._write_result(self._last_result, final)  # a reboot cleared the RESULT block: restore it
        while True:
            try:
                result = self.processor.results.get_nowait()
            except queue.Empty:
                return
            self.report.results.append(result)
            self.processor.write_csv(self.out, self.report.results)
            if result.get("status_code") is None:
                continue  # the reference cycle: nothing to publish yet
            self._result_seq = self._result_seq % 0xFFFFFFFF + 1
            values = {"RESULT_SEQ": self._result_seq, "CYCLE": result["cycle"],
                      "PREVIOUS_CYCLE": result["previous_cycle"] or 0, "RETREAT": result["retreat_m"],
                      "CREEP": result["creep_m"], "VERTICAL": result["vertical_m"],
                      "STATUS": result["status_code"], "N_TARGETS": min(result["n_targets"], 65535),
                      "RESIDUAL": result["residual_m"] if math.isfinite(result["residual_m"]) else 0.0,
                      "TIME": result["time_s"]}
            self._last_result = values
            if self._write_result(values, final):
                log.info("cycle %d: published retreat %.4f m, creep %.4f m (%s) as result %d", result["cycle"],
                         result["retreat_m"], result["creep_m"], result["status"], self._result_seq)

    def _write_result(self, values: dict, final: bool) -> bool:
        try:
            boot = self.link.boot_id
            self.link.write_block(R.RESULT, values)
            self._published_boot = boot
            return True
        except (LinkDown, DeviceRebooted, Interrupted) as exc:
            if not final:
                raise
            log.warning("cycle %d: result not published: %s", values["CYCLE"], exc or "interrupted")
            return False
