"""The rig controller's Modbus register map (version 1.0) as data: one source for the client, the simulator
and docs/modbus-register-map.md (whose tables `markdown_tables()` renders; a test holds the document to it).

Conventions (docs/modbus-register-map.md section 2): 0-based protocol addresses; 32/64-bit values high word
first; float32 is IEEE 754 binary32 in the same word order; strings ASCII, two characters per register, high
byte first; every block ends in a CRC-16/CCITT-FALSE register over the block's preceding registers (big-endian
bytes), the value `binascii.crc_hqx(data, 0xFFFF)` computes.
"""

from __future__ import annotations

import binascii
import dataclasses
import enum
import math
import struct
from collections.abc import Iterable, Mapping, Sequence

MAP_MAGIC = 0x5557  # "UW"
MAP_VERSION = (1, 1)  # (major, minor): a client refuses a major it does not know; 1.1 = 1.0 + section 12
SEQ_MODULUS = 2**32  # pulse sequence numbers, CYCLE_COUNTER, RESULT_SEQ: u32, wrapping 2^32 - 1 -> 0
CMD_SEQ_MAX = 65535  # CMD_SEQ runs 1 .. 65535, 1, ...; 0 is never a command's (exception 03)
MAX_REGISTERS_PER_READ = 125  # Modbus application protocol limit for FC03/FC04
MAX_REGISTERS_PER_WRITE = 123  # FC16
NOT_AVAILABLE_S32 = -0x80000000  # a result that could not be measured (too few plates, ...)


class RegisterError(ValueError):
    """A register block that cannot be trusted (bad CRC, value out of range); names the block and field."""


class Table(str, enum.Enum):
    INPUT = "input"  # FC04, read-only
    HOLDING = "holding"  # FC03 read, FC06/FC16 write


# --------------------------------------------------------------------------------------------- value types

_TYPES = {  # name: (registers, struct format)
    "u16": (1, ">H"), "s16": (1, ">h"), "u32": (2, ">I"), "s32": (2, ">i"), "f32": (2, ">f"),
    "u64": (4, ">Q"),
}


@dataclasses.dataclass(frozen=True)
class Field:
    """One value in a block: `value = raw * scale` in SI units (`unit`), raw of type `kind` at `offset`."""

    name: str
    offset: int  # registers from the start of the block
    kind: str  # u16 s16 u32 s32 f32 u64, or "str<n>" for n registers of ASCII
    scale: float = 1.0
    unit: str = ""
    doc: str = ""

    @property
    def size(self) -> int:
        return int(self.kind[3:]) if self.kind.startswith("str") else _TYPES[self.kind][0]

    @property
    def is_integer(self) -> bool:
        return self.kind != "f32" and not self.kind.startswith("str") and self.scale == 1.0


def crc16(registers: Iterable[int]) -> int:
    """CRC-16/CCITT-FALSE of the registers' big-endian bytes (poly 0x1021, init 0xFFFF;
    '123456789' -> 0x29B1)."""
    regs = list(registers)
    return binascii.crc_hqx(struct.pack(f">{len(regs)}H", *regs), 0xFFFF)


def _raw_from_value(block: str, f: Field, value) -> list[int]:
    if f.kind.startswith("str"):
        data = str(value).encode("ascii")
        if len(data) > 2 * f.size:
            raise RegisterError(f"{block}.{f.name}: {value!r} longer than {2 * f.size} characters")
        data = data.ljust(2 * f.size, b"\0")
        return list(struct.unpack(f">{f.size}H", data))
    if value is None or (f.kind == "s32" and f.scale != 1.0 and not math.isfinite(float(value))):
        if f.kind != "s32":
            raise RegisterError(f"{block}.{f.name}: a value is required")
        return list(struct.unpack(">2H", struct.pack(">i", NOT_AVAILABLE_S32)))
    if f.kind == "f32":
        if not math.isfinite(float(value)):
            raise RegisterError(f"{block}.{f.name}: not a finite number: {value!r}")
        raw_bytes = struct.pack(">f", float(value))
    else:
        raw = int(value) if f.scale == 1.0 else (round(float(value) * _inverse(f.scale)) if f.scale < 1.0
                                                 else round(float(value) / f.scale))
        try:
            raw_bytes = struct.pack(_TYPES[f.kind][1], raw)
        except struct.error:
            raise RegisterError(f"{block}.{f.name}: {value!r} does not fit {f.kind} "
                                f"at scale {f.scale:g}") from None
    return list(struct.unpack(f">{f.size}H", raw_bytes))


def _value_from_raw(f: Field, regs: Sequence[int]):
    data = struct.pack(f">{f.size}H", *regs)
    if f.kind.startswith("str"):
        return data.rstrip(b"\0").decode("ascii", errors="replace")
    raw = struct.unpack(_TYPES[f.kind][1], data)[0]
    if f.kind == "f32":
        return float(raw)
    if f.scale == 1.0:
        return raw
    if f.kind == "s32" and raw == NOT_AVAILABLE_S32:
        return math.nan
    return raw / _inverse(f.scale) if f.scale < 1.0 else raw * f.scale


def _inverse(scale: float) -> int:
    # 1e-6 etc. are not exact binary fractions: dividing by the integer 10**k gives correctly rounded metres.
    return round(1.0 / scale)


@dataclasses.dataclass(frozen=True)
class Block:
    """A run of registers read or written in one request; the last register is the CRC of the others."""

    name: str
    table: Table
    address: int
    length: int  # registers, CRC included
    fields: tuple[Field, ...]
    doc: str = ""

    def __post_init__(self):
        used = set()
        for f in self.fields:
            span = set(range(f.offset, f.offset + f.size))
            if used & span or f.offset + f.size > self.length - 1:
                raise ValueError(f"block {self.name}: field {f.name} overlaps or runs into the CRC")
            used |= span
        if self.length > MAX_REGISTERS_PER_READ:
            raise ValueError(f"block {self.name}: longer than one Modbus read")

    @property
    def crc_address(self) -> int:
        return self.address + self.length - 1

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(f"{self.name} has no field {name}")

    def encode(self, values: Mapping[str, object]) -> list[int]:
        """SI values by field name (missing ones are 0) -> the block's registers, CRC last."""
        unknown = set(values) - {f.name for f in self.fields}
        if unknown:
            raise KeyError(f"{self.name}: unknown fields {sorted(unknown)}")
        regs = [0] * self.length
        for f in self.fields:
            if f.name in values:
                regs[f.offset:f.offset + f.size] = _raw_from_value(self.name, f, values[f.name])
        regs[-1] = crc16(regs[:-1])
        return regs

    def decode(self, regs: Sequence[int]) -> dict:
        """The block's registers -> SI values by field name; RegisterError if the CRC does not match."""
        if len(regs) != self.length:
            raise RegisterError(f"{self.name}: expected {self.length} registers, got {len(regs)}")
        crc = crc16(regs[:-1])
        if crc != regs[-1]:
            raise RegisterError(f"{self.name} (IR/HR {self.address}-{self.crc_address}): CRC mismatch "
                                f"(computed 0x{crc:04X}, register 0x{regs[-1]:04X})")
        return {f.name: _value_from_raw(f, regs[f.offset:f.offset + f.size]) for f in self.fields}


# ------------------------------------------------------------------------------------------ wrapping counters
# Serial-number arithmetic (RFC 1982 style) for the u32 counters of the map: a is "before" b when b is less
# than half the number space ahead of a. Buffers and cycle gaps are far below 2^31, so this is unambiguous.


def seq_add(seq: int, n: int) -> int:
    """seq + n modulo 2^32: what follows 2^32 - 1 is 0."""
    return (int(seq) + int(n)) % SEQ_MODULUS


def seq_diff(a: int, b: int) -> int:
    """a - b as a signed distance in -2^31 .. 2^31 - 1 (positive: a is after b)."""
    d = (int(a) - int(b)) % SEQ_MODULUS
    return d - SEQ_MODULUS if d >= SEQ_MODULUS // 2 else d


def seq_at_or_before(a: int, b: int) -> bool:
    """a is b or comes before it, across the wrap ("at or below" in the map)."""
    return seq_diff(a, b) <= 0


def cmd_seq_next(seq: int) -> int:
    """The CMD_SEQ after `seq`: 1 .. 65535, then 1 again (0 is not a command's)."""
    return int(seq) % CMD_SEQ_MAX + 1


# --------------------------------------------------------------------------------------------- enumerations


class Status(enum.IntFlag):
    READY = 1 << 0
    BUSY = 1 << 1
    PASS_ACTIVE = 1 << 2
    PASS_COMPLETE = 1 << 3
    FAULT = 1 << 4
    OVERFLOW = 1 << 5
    CYCLE_LINK_OK = 1 << 6
    LOCAL = 1 << 7


class Fault(enum.IntFlag):
    DRIVE = 1 << 0
    ENCODER = 1 << 1
    RADAR = 1 << 2
    TABLE = 1 << 3
    LIMIT = 1 << 4
    BUFFER_OVERFLOW = 1 << 5
    PASS_ABORTED = 1 << 6
    CYCLE_LINK_LOST = 1 << 7


class State(enum.IntEnum):
    BOOTING = 0
    IDLE = 1
    MOVING = 2
    ROTATING = 3
    SCANNING = 4
    FAULTED = 5


class Command(enum.IntEnum):
    NONE = 0
    MOVE_HEIGHT = 1
    SET_TABLE_ANGLE = 2
    START_PASS = 3
    ABORT = 4
    CLEAR_FAULTS = 5


class CommandResult(enum.IntEnum):
    NONE = 0
    ACCEPTED = 1
    DONE = 2
    REJECTED_BUSY = 3
    REJECTED_RANGE = 4
    REJECTED_NOT_READY = 5
    REJECTED_UNKNOWN = 6
    FAILED = 8  # 7 is reserved


class PassState(enum.IntEnum):
    NONE = 0
    RUNNING = 1
    COMPLETE = 2
    ABORTED = 3


def enum_name(kind: type[enum.IntEnum], value: int) -> str:
    """The name of `value` in `kind`, or "unknown value N": a controller of a later minor may send values this
    client does not know (section 10), and a message about them must not fail."""
    return kind(value).name if value in kind._value2member_map_ else f"unknown value {value}"


class ResultStatus(enum.IntEnum):
    OK = 0
    AMBIGUOUS = 1
    TOO_FEW_TARGETS = 2
    INCOMPLETE_CYCLE = 3
    PROCESSING_ERROR = 4
    FLAGGED = 5


class RecordFlag(enum.IntFlag):
    FIRST = 1 << 0
    LAST = 1 << 1
    SATURATED = 1 << 2


# What each enumeration value means, by "Class.NAME" (IntEnum members of different classes compare equal).
ENUM_DOCS = {
    "Status.READY": "booted, no fault, remote control: accepts commands",
    "Status.BUSY": "a command is executing (move, rotation or pass)",
    "Status.PASS_ACTIVE": "pulses of the pass in the PASS block are being produced",
    "Status.PASS_COMPLETE": "that pass has finished: all its pulses are in the buffer or acknowledged",
    "Status.FAULT": "FAULT_WORD != 0",
    "Status.OVERFLOW": "the current pass has dropped pulses (PASS.OVERFLOW_COUNT > 0)",
    "Status.CYCLE_LINK_OK": "CYCLE_COUNTER is current (the link to the longwall control system is up)",
    "Status.LOCAL": "operator in local control: remote commands are rejected",
    "Fault.DRIVE": "carriage or height drive",
    "Fault.ENCODER": "rail or height encoder",
    "Fault.RADAR": "radar module not responding or delivering bad data",
    "Fault.TABLE": "rotation table",
    "Fault.LIMIT": "travel limit reached unexpectedly",
    "Fault.BUFFER_OVERFLOW": "pulses of the current pass were dropped (cleared by the next START_PASS)",
    "Fault.PASS_ABORTED": "the last pass was aborted: ABORT, a fault, or the cycle counter changed during it "
                          "(cleared by the next accepted START_PASS, CLEAR_FAULTS or a reboot)",
    "Fault.CYCLE_LINK_LOST": "no contact with the longwall control system",
    "State.BOOTING": "starting up; the controller may refuse connections",
    "State.IDLE": "ready for a command",
    "State.MOVING": "height drive running (MOVE_HEIGHT)",
    "State.ROTATING": "rotation table turning (SET_TABLE_ANGLE)",
    "State.SCANNING": "pass in progress (START_PASS)",
    "State.FAULTED": "a fault other than BUFFER_OVERFLOW / PASS_ABORTED is set; CLEAR_FAULTS",
    "Command.NONE": "no operation (rejected as REJECTED_UNKNOWN)",
    "Command.MOVE_HEIGHT": "ARG0: carriage height, s32 micrometres; DONE when the carriage is there",
    "Command.SET_TABLE_ANGLE": "ARG0: rotation-table angle, s32 millidegrees; DONE when the table is there",
    "Command.START_PASS": "ARG0: pass token, 1 .. 2^31 - 1, echoed in PASS.TOKEN; DONE when the pass is "
                          "complete",
    "Command.ABORT": "stop any motion and the pass; DONE at once (accepted even when BUSY)",
    "Command.CLEAR_FAULTS": "clear FAULT_WORD; DONE at once",
    "CommandResult.NONE": "no command since boot",
    "CommandResult.ACCEPTED": "accepted and executing",
    "CommandResult.DONE": "finished",
    "CommandResult.REJECTED_BUSY": "another command is executing (only ABORT and CLEAR_FAULTS are taken when "
                                   "BUSY)",
    "CommandResult.REJECTED_RANGE": "argument outside the travel, the limits, or (token) 1 .. 2^31 - 1",
    "CommandResult.REJECTED_NOT_READY": "booting, faulted or in local control",
    "CommandResult.REJECTED_UNKNOWN": "unknown command code",
    "CommandResult.FAILED": "accepted, then stopped by a fault or a reboot while executing",
    "PassState.NONE": "no pass since boot",
    "PassState.RUNNING": "pulses are being produced",
    "PassState.COMPLETE": "every pulse produced, PULSES_PRODUCED = PULSES_PLANNED (some may have been "
                          "dropped: OVERFLOW_COUNT)",
    "PassState.ABORTED": "stopped before the end: the pass is unusable",
    "ResultStatus.OK": "a trustworthy estimate",
    "ResultStatus.AMBIGUOUS": "another plate correspondence explains the data as well",
    "ResultStatus.TOO_FEW_TARGETS": "not enough plates matched between the two cycles: no estimate",
    "ResultStatus.INCOMPLETE_CYCLE": "fewer than two heights of the cycle could be acquired: no estimate",
    "ResultStatus.PROCESSING_ERROR": "the processing failed: no estimate",
    "ResultStatus.FLAGGED": "an estimate the processing flags for another reason (e.g. low confidence)",
    "RecordFlag.FIRST": "first pulse of the pass",
    "RecordFlag.LAST": "last pulse of the pass",
    "RecordFlag.SATURATED": "an I or Q sample of this pulse hit the converter's limit",
}


# --------------------------------------------------------------------------------------------- fault taxonomy


class FaultClass(str, enum.Enum):
    """What a fault costs (docs/modbus-register-map.md section 9). Only SERVICE stops acquisition."""

    TRANSIENT = "transient"  # the same request is repeated after a backoff
    REQUEST = "request"  # the request failed: repeated a few times, then the step it belongs to fails
    PASS = "pass"  # the pass fails: ABORT sent, the pass is run again (max_attempts per pass)
    NOTICE = "notice"  # logged (and counted); acquisition goes on
    SERVICE = "service"  # acquisition stops with a message: the controller is not a compatible rig


@dataclasses.dataclass(frozen=True)
class FaultRule:
    name: str
    cls: FaultClass
    when: str
    action: str


FAULT_TAXONOMY = (
    FaultRule("NO_REPLY", FaultClass.TRANSIENT, "no reply within the timeout; connection dropped or refused",
              "close the connection, reconnect with backoff (0.05 s doubling to reconnect_max_s, jitter), "
              "repeat"),
    FaultRule("BUSY", FaultClass.TRANSIENT, "exception 04 or 06 (the request was not executed)",
              "wait 20 ms doubling to 1 s, repeat; after 25 in a row the request fails (REFUSED)"),
    FaultRule("DAMAGED", FaultClass.TRANSIENT,
              "CRC mismatch or wrong length in a reply; a reply of another function code than the "
              "request's; an FC16 reply echoing another address or quantity",
              "read (write) again; after 10 in a row the request fails (REFUSED)"),
    FaultRule("HUNG", FaultClass.TRANSIENT, "HEARTBEAT unchanged for 2 s while replies keep coming",
              "log, reconnect"),
    FaultRule("REFUSED", FaultClass.REQUEST, "exception 01, 02 or 03 (e.g. a request damaged on the way)",
              "repeat up to 3 times with backoff; then the step fails: inside a pass the pass fails, outside "
              "one the client waits (backoff) and starts the step again"),
    FaultRule("REBOOT", FaultClass.PASS, "BOOT_ID changed",
              "re-read IDENTITY and RADAR; the pass in progress is lost: run it again with the new values"),
    FaultRule("DESCRIPTION_CHANGED", FaultClass.PASS,
              "IDENTITY or RADAR, re-read on a new connection or boot, differ from what the pass assumed",
              "ABORT, run the pass again with the new values"),
    FaultRule("PASS_INCOMPLETE", FaultClass.PASS,
              "sequence gap, OVERFLOW, PASS_STATE ABORTED (or not COMPLETE at the end), PULSES_PRODUCED != "
              "PULSES_PLANNED, a PASS value that changed, a foreign TOKEN or CYCLE, PASS.HEIGHT more than "
              "height_tolerance_m from the commanded height, a DIRECTION the positions contradict, "
              "CYCLE_COUNTER changed while the pass ran",
              "ABORT if still running, log, run the pass again (a changed CYCLE_COUNTER: scan the new "
              "cycle)"),
    FaultRule("ABSURD_VALUE", FaultClass.PASS,
              "a PASS or RADAR value the client will not use (sizes over its limits, a record that does not "
              "fit WINDOW_REGS, AMPLITUDE_SCALE not finite > 0, DIRECTION not +1 or -1), or a pass no "
              "archive may hold (docs/archive-format.md: TABLE_ANGLE not within (−90, 90)°, START_TIME past "
              "year 9999, an echo past 1e30 after AMPLITUDE_SCALE). uwbcl's limits: SAMPLES_PER_PULSE ≤ "
              "8192, PULSES_PLANNED ≤ 100,000, and PULSES_PLANNED × SAMPLES_PER_PULSE ≤ 2^25 (what an "
              "archive reader accepts by default, docs/configuration.md `[limits]`)",
              "ABORT, log, re-read, run the pass again"),
    FaultRule("NO_PROGRESS", FaultClass.PASS,
              "no new pulse and no change of STATE, PASS_STATE or PULSES_PRODUCED for stall_timeout_s",
              "log, ABORT, run the pass again"),
    FaultRule("COMMAND_FAILED", FaultClass.PASS,
              "REJECTED_BUSY, REJECTED_NOT_READY, REJECTED_UNKNOWN, REJECTED_RANGE or FAILED; not "
              "acknowledged or not DONE within command_timeout_s (default 120 s; the same CMD_SEQ is written "
              "again at growing intervals, 20 ms doubling to 1 s, meanwhile)",
              "ABORT, log, run the pass again; a CYCLE_COUNTER change while waiting: scan the new cycle"),
    FaultRule("CYCLES_MISSED", FaultClass.NOTICE, "CYCLE_COUNTER moved on by more than 1 (modulo 2^32)",
              "log the cycles never scanned; scan the new one"),
    FaultRule("COUNTER_DECREASED", FaultClass.NOTICE, "CYCLE_COUNTER moved back (modulo 2^32)",
              "log both values as a fault; scan the new value as a new cycle"),
    FaultRule("RIG_ID_CHANGED", FaultClass.NOTICE, "IDENTITY.RIG_ID differs from the last one read",
              "log both; later archives carry the new id"),
    FaultRule("NAME_TAKEN", FaultClass.NOTICE, "the archive name of a whole pass is already taken",
              "write it as <name>_b<BOOT_ID hex>_p<TOKEN>.h5 (then _2, _3, ...): never dropped"),
    FaultRule("ARCHIVE_UNWRITABLE", FaultClass.NOTICE,
              "a whole pass's archive cannot be written (disk full, a share gone read-only)",
              "keep the pass in memory as archived (complex64; up to 64 passes and 2 GiB: beyond, the "
              "oldest kept pass is named as lost) and process it live; write the kept passes again, oldest "
              "first, every 10 s and before each new pass; name those still unwritten when the session "
              "ends as lost"),
    FaultRule("INCOMPATIBLE", FaultClass.SERVICE,
              "MAGIC not 0x5557, MAP_MAJOR not 1 or WINDOW_ADDRESS not 1024, read twice",
              "stop with a message naming the value"),
    FaultRule("CONFIGURATION", FaultClass.SERVICE,
              "a configured height or table angle outside the rig's RADAR limits",
              "stop with a message naming the setting"),
)
FAULT_RULES = {f.name: f for f in FAULT_TAXONOMY}


def fault_table() -> str:
    rows = ["| fault | class | when | what the client does |", "|---|---|---|---|"]
    rows += [f"| {f.name} | {f.cls.value} | {f.when} | {f.action} |" for f in FAULT_TAXONOMY]
    return "\n".join(rows)


# --------------------------------------------------------------------------------------------- blocks

IDENTITY = Block("IDENTITY", Table.INPUT, 0, 32, (
    Field("MAGIC", 0, "u16", doc="0x5557 (\"UW\"): this is a uwbcl rig controller"),
    Field("MAP_MAJOR", 1, "u16",
          doc="register map major version (1); a client refuses a major it does not know"),
    Field("MAP_MINOR", 2, "u16", doc="minor version: additions only"),
    Field("DEVICE_TYPE", 3, "u16", doc="1 = UWB SAR rail rig"),
    Field("SERIAL", 4, "u32", doc="controller serial number"),
    Field("FIRMWARE", 6, "u32", doc="firmware version, major * 65536 + minor"),
    Field("RIG_ID", 8, "str8",
          doc="rig identifier, up to 16 ASCII characters, NUL padded (A-Z a-z 0-9 . _ -)"),
    Field("VENDOR", 16, "str8", doc="vendor name, up to 16 ASCII characters"),
), "who the device is; constant while it runs")

STATUS = Block("STATUS", Table.INPUT, 32, 32, (
    Field("HEARTBEAT", 0, "u16", doc="+1 every 100 ms of device time, wraps to 0 after 65535"),
    Field("STATUS_WORD", 1, "u16", doc="bits: table Status word"),
    Field("FAULT_WORD", 2, "u16", doc="bits: table Fault word; 0 = no fault"),
    Field("STATE", 3, "u16", doc="enumeration: table States"),
    Field("BOOT_ID", 4, "u32",
          doc="changes at every controller start: a new value means the controller rebooted"),
    Field("UPTIME", 6, "u32", 1e-3, "s", "time since boot, milliseconds"),
    Field("DEVICE_TIME", 8, "u64", 1e-3, "s", "device clock, milliseconds since 1970-01-01T00:00:00Z (UTC)"),
    Field("CYCLE_COUNTER", 12, "u32",
          doc="cutting-cycle counter of the longwall control system: +1 when a cycle's conveyor push is "
              "done; 2^32 - 1 is followed by 0"),
    Field("CARRIAGE_HEIGHT", 14, "s32", 1e-6, "m",
          "measured carriage (antenna phase centre) height, micrometres"),
    Field("CARRIAGE_POSITION", 16, "s32", 1e-6, "m", "measured rail position X_r, micrometres"),
    Field("TABLE_ANGLE", 18, "s32", 1e-3, "deg", "measured rotation-table angle, millidegrees"),
    Field("CMD_ACK_SEQ", 20, "u16",
          doc="CMD_SEQ of the last command received, i.e. written without an exception "
                                         "reply (0 after boot)"),
    Field("CMD_ACK_CODE", 21, "u16", doc="CMD_CODE of that command"),
    Field("CMD_RESULT", 22, "u16", doc="its outcome: table Command results"),
), "live state; read it every poll")

RADAR = Block("RADAR", Table.INPUT, 64, 32, (
    Field("CARRIER_FREQUENCY", 0, "u32", 1e3, "Hz", "carrier f_c, kHz"),
    Field("BANDWIDTH", 2, "u32", 1e3, "Hz", "-10 dB bandwidth of the Gaussian pulse, kHz"),
    Field("SAMPLE_RATE", 4, "u32", 1e3, "Hz", "complex (I/Q) fast-time sampling rate, kHz"),
    Field("PRF", 6, "u32", 1e-3, "Hz", "pulse repetition frequency, millihertz"),
    Field("ANTENNA_APERTURE", 8, "u32", 1e-6, "m", "real antenna aperture along X_r, micrometres"),
    Field("BORESIGHT_Y_SIGN", 10, "s16", doc="side of the rail the rib is on: -1 (negative Y_r) or +1"),
    Field("MAX_SAMPLES_PER_PULSE", 11, "u16", doc="largest SAMPLES_PER_PULSE the radar can deliver; "
                                                   "10 + 9 + 2 * MAX_SAMPLES_PER_PULSE <= WINDOW_REGS"),
    Field("BUFFER_CAPACITY", 12, "u16", doc="pulses the ring buffer holds before it drops new ones"),
    Field("WINDOW_ADDRESS", 13, "u16", doc="input-register address of the pulse window (1024)"),
    Field("WINDOW_REGS", 14, "u16", doc="length of the pulse window in registers, header included"),
    Field("NOMINAL_SPEED", 16, "u32", 1e-6, "m/s",
          "carriage set speed during a pass, micrometres per second"),
    Field("RAIL_MIN", 18, "s32", 1e-6, "m",
          "rail travel, low end (a pass runs between the ends), micrometres"),
    Field("RAIL_MAX", 20, "s32", 1e-6, "m", "rail travel, high end, micrometres"),
    Field("HEIGHT_MIN", 22, "s32", 1e-6, "m", "lowest carriage height, micrometres"),
    Field("HEIGHT_MAX", 24, "s32", 1e-6, "m", "highest carriage height, micrometres"),
    Field("TABLE_MAX", 26, "s32", 1e-3, "deg", "largest absolute rotation-table angle, millidegrees"),
), "the radar and rail as built; constant while the controller runs")

PASS = Block("PASS", Table.INPUT, 96, 32, (
    Field("TOKEN", 0, "u32", doc="ARG0 of the START_PASS that started this pass"),
    Field("CYCLE", 2, "u32", doc="CYCLE_COUNTER when the pass started"),
    Field("FIRST_SEQ", 4, "u32", doc="sequence number of the pass's first pulse"),
    Field("PULSES_PLANNED", 6, "u32", doc="pulses the pass will produce (travel / speed * PRF + 1)"),
    Field("PULSES_PRODUCED", 8, "u32",
          doc="pulses produced so far, dropped ones included; equal to PULSES_PLANNED "
                                           "at COMPLETE"),
    Field("OVERFLOW_COUNT", 10, "u32", doc="pulses of this pass dropped because the buffer was full"),
    Field("RANGE_WINDOW_START", 12, "u32", 1e-12, "s", "two-way delay of fast-time sample 0, picoseconds"),
    Field("SAMPLES_PER_PULSE", 14, "u16", doc="M, complex samples in each pulse record"),
    Field("DIRECTION", 15, "s16", doc="+1: the carriage runs towards RAIL_MAX, -1: towards RAIL_MIN"),
    Field("AMPLITUDE_SCALE", 16, "f32", 1.0, "arb", "echo = AMPLITUDE_SCALE * (I + jQ)"),
    Field("HEIGHT", 18, "s32", 1e-6, "m", "carriage height during the pass, micrometres"),
    Field("TABLE_ANGLE", 20, "s32", 1e-3, "deg", "rotation-table angle during the pass, millidegrees"),
    Field("START_TIME", 22, "u64", 1e-3, "s", "device time of pulse time 0, ms since 1970 UTC"),
    Field("PASS_STATE", 26, "u16", doc="table Pass states"),
), "the pass in progress or last finished; snapshotted when START_PASS is accepted")

COMMAND = Block("COMMAND", Table.HOLDING, 0, 8, (
    Field("CMD_CODE", 0, "u16", doc="table Commands"),
    Field("CMD_SEQ", 1, "u16",
          doc="1..65535 (after 65535 comes 1; 0 gets exception 03), a new value for every new "
                                   "command; a repeated value is a retransmission"),
    Field("ARG0", 2, "s32", doc="first argument (table Commands)"),
    Field("ARG1", 4, "s32", doc="second argument, 0 (reserved)"),
), "written by the client in one FC16 request of all 8 registers")

ACK = Block("ACK", Table.HOLDING, 8, 3, (
    Field("ACK_SEQ", 0, "u32", doc="sequence number of the last pulse the client has stored"),
), "pulse read-acknowledge, written in one FC16 request of the 3 registers")

CLIENT = Block("CLIENT", Table.HOLDING, 12, 2, (
    Field("CLIENT_HEARTBEAT", 0, "u16",
          doc="the client writes a new value at least every 2 s while connected"),
), "client watchdog, written in one FC16 request of the 2 registers")

RESULT = Block("RESULT", Table.HOLDING, 16, 21, (
    Field("RESULT_SEQ", 0, "u32",
          doc="+1 for every result published; readers take a non-zero value not seen before as new data"),
    Field("CYCLE", 2, "u32", doc="cycle counter value of the cycle measured"),
    Field("PREVIOUS_CYCLE", 4, "u32", doc="the cycle it is measured from (normally CYCLE - 1)"),
    Field("RETREAT", 6, "s32", 1e-6, "m",
          "advance along the panel (X) since PREVIOUS_CYCLE, micrometres; -2^31: n/a"),
    Field("CREEP", 8, "s32", 1e-6, "m", "slide along the face (Y), micrometres; -2^31: n/a"),
    Field("VERTICAL", 10, "s32", 1e-6, "m", "vertical change (Z), micrometres; -2^31: n/a"),
    Field("STATUS", 12, "u16", doc="table Result status"),
    Field("N_TARGETS", 13, "u16", doc="bolt plates the estimate rests on"),
    Field("RESIDUAL", 14, "u32", 1e-6, "m", "RMS misfit of those plates, micrometres"),
    Field("TIME", 16, "u64", 1e-3, "s", "start of CYCLE's first pass, ms since 1970 UTC"),
), "published by uwbcl for the face automation system, in one FC16 request of all 21 registers")

INPUT_BLOCKS = (IDENTITY, STATUS, RADAR, PASS)
HOLDING_BLOCKS = (COMMAND, ACK, CLIENT, RESULT)

# --------------------------------------------------------------------------------------------- pulse window

WINDOW_ADDRESS = 1024
WINDOW_HEADER = Block("WINDOW_HEADER", Table.INPUT, WINDOW_ADDRESS, 10, (
    Field("OLDEST_SEQ", 0, "u32", doc="sequence number of record 0; 0 when RECORDS = 0"),
    Field("RECORDS", 2, "u16", doc="complete records that follow the header"),
    Field("RECORD_REGS", 3, "u16", doc="registers per record: 9 + 2 * SAMPLES_PER_PULSE"),
    Field("NEWEST_SEQ", 4, "u32",
          doc="sequence number of the last pulse produced since boot (before the first: "
                                      "the first's minus 1)"),
    Field("TOKEN", 6, "u32", doc="PASS.TOKEN of the pass the records belong to"),
), "start of the pulse window (section 6)")

RECORD_HEADER_REGS = 8  # SEQ u32, TIME u32 (us), POSITION s32 (um), FLAGS u16, reserved u16
RECORD_TIME_SCALE_S = 1e-6
RECORD_POSITION_SCALE_M = 1e-6


def record_regs(samples_per_pulse: int) -> int:
    """Registers of one pulse record: the 8-register header, I/Q pairs, CRC."""
    return RECORD_HEADER_REGS + 2 * samples_per_pulse + 1


def encode_record(seq: int, time_s: float, position_m: float, flags: int, iq) -> list[int]:
    """One pulse record (section 6); iq is an (M, 2) array of int16 I, Q."""
    import numpy as np

    iq = np.asarray(iq, dtype=np.int16).reshape(-1)
    head = struct.pack(">IIiHH", seq, round(time_s * _inverse(RECORD_TIME_SCALE_S)),
                       round(position_m * _inverse(RECORD_POSITION_SCALE_M)),
                       int(flags), 0)
    regs = list(struct.unpack(">8H", head)) + iq.view(np.uint16).tolist()
    regs.append(crc16(regs))
    return regs


def decode_records(regs: Sequence[int], n_records: int, samples_per_pulse: int):
    """n_records back-to-back records -> (seq, time_s, position_m, flags, iq (n, M, 2) int16, bad) arrays.

    `bad` lists the indices of records whose CRC does not match (their other values are untrustworthy).
    """
    import numpy as np

    n_regs = record_regs(samples_per_pulse)
    if len(regs) < n_records * n_regs:
        raise RegisterError(f"pulse window: {len(regs)} registers cannot hold {n_records} records "
                            f"of {n_regs}")
    block = np.asarray(regs[:n_records * n_regs], dtype=np.uint16).reshape(n_records, n_regs)
    as_bytes = block.astype(">u2")
    bad = [i for i in range(n_records)
           if binascii.crc_hqx(as_bytes[i, :-1].tobytes(), 0xFFFF) != block[i, -1]]
    head = as_bytes[:, :RECORD_HEADER_REGS].tobytes()
    fields = np.frombuffer(head, dtype=np.dtype([("seq", ">u4"), ("t", ">u4"), ("x", ">i4"), ("flags", ">u2"),
                                                  ("res", ">u2")]), count=n_records)
    iq = block[:, RECORD_HEADER_REGS:-1].astype(np.uint16).view(np.int16)
    iq = iq.reshape(n_records, samples_per_pulse, 2)
    return (fields["seq"].astype(np.int64), fields["t"].astype(np.float64) / _inverse(RECORD_TIME_SCALE_S),
            fields["x"].astype(np.float64) / _inverse(RECORD_POSITION_SCALE_M),
            fields["flags"].astype(np.int64), iq, bad)


# --------------------------------------------------------------------------------------------- documentation


def _addr(table: Table, start: int, size: int) -> str:
    prefix = "IR" if table is Table.INPUT else "HR"
    return f"{prefix} {start}" if size == 1 else f"{prefix} {start}-{start + size - 1}"


def block_table(block: Block) -> str:
    rows = ["| address | name | type | scale | unit | meaning |", "|---|---|---|---|---|---|"]
    for f in block.fields:
        kind = f"ASCII, {f.size} regs" if f.kind.startswith("str") else f.kind
        scale = "" if f.scale == 1.0 or f.kind.startswith("str") else f"{f.scale:g}"
        rows.append(f"| {_addr(block.table, block.address + f.offset, f.size)} | {f.name} | {kind} | {scale} "
                    f"| {f.unit} | {f.doc} |")
    rows.append(f"| {_addr(block.table, block.crc_address, 1)} | {block.name}_CRC | u16 | | | CRC-16 of "
                f"{_addr(block.table, block.address, block.length - 1)} |")
    return "\n".join(rows)


def enum_table(enum_cls) -> str:
    bits = issubclass(enum_cls, enum.IntFlag)
    rows = [f"| {'bit' if bits else 'value'} | name | meaning |", "|---|---|---|"]
    for m in enum_cls:
        rows.append(f"| {int(m).bit_length() - 1 if bits else int(m)} | {m.name} | "
                    f"{ENUM_DOCS[f'{enum_cls.__name__}.{m.name}']} |")
    return "\n".join(rows)


def markdown_tables() -> dict[str, str]:
    """The tables of docs/modbus-register-map.md, keyed by the marker that precedes each in the document."""
    out = {b.name: block_table(b) for b in (*INPUT_BLOCKS, WINDOW_HEADER, *HOLDING_BLOCKS)}
    for cls in (Status, Fault, State, Command, CommandResult, PassState, ResultStatus, RecordFlag):
        out[cls.__name__] = enum_table(cls)
    out["FaultTaxonomy"] = fault_table()
    return out
