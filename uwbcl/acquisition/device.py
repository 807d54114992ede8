"""The simulated rig controller: the register map of docs/modbus-register-map.md served by pymodbus.

`RigController` is the controller's logic with an explicit clock (device seconds), free of sockets: commands,
carriage and table motion, passes whose pulses enter a finite ring buffer at the pulse rate, the read-
acknowledge window, the cycle counter of the longwall control system, reboots. `RigServer` serves it over
Modbus TCP (pymodbus `ModbusTcpServer` with a `SimDevice` whose access hook calls the controller) in a
background thread, and applies the faults a `FaultInjector` draws.

Persistence: with a state file (`DeviceConfig.state_file`, `uwbcl simulate-device --state`), CYCLE_COUNTER,
the last BOOT_ID and the clock survive a restart of the simulator, as the map requires of a controller (the
counter lives in the longwall control system; BOOT_ID must differ from the previous boot's; DEVICE_TIME is a
clock, which never goes back).

Time: device time runs `time_scale` times faster than the host's monotonic clock, so a 45-minute cycle or a
13-second pass can be compressed for tests and the demo; every rate in the registers stays in device time.
"""

from __future__ import annotations

import asyncio
import binascii
import collections
import dataclasses
import datetime as dt
import json
import logging
import math
import os
import secrets
import threading
import time
from pathlib import Path

import numpy as np

from . import registers as R
from .faults import FaultInjector, FaultPlan
from .rig import Campaign, WorldConfig

log = logging.getLogger("uwbcl.device")

DEVICE_EPOCH = dt.datetime(2026, 11, 2, 6, 0, tzinfo=dt.timezone.utc)
HEARTBEAT_PERIOD_S = 0.1
_SERVE = object()  # RigServer._answer_fault: no fault reply, serve the request
INT16_FULL_SCALE = 32767


@dataclasses.dataclass(frozen=True)
class DeviceConfig:
    world: WorldConfig = dataclasses.field(default_factory=WorldConfig)
    rig_id: str = "sim-rig"
    time_scale: float = 1.0
    initial_cycle: int = 1000  # the longwall counter when the simulation starts (and no state file holds one)
    first_cycle_after_s: float = 5.0  # device seconds until the first cycle signal
    cycle_interval_s: float = 2700.0  # device seconds between cycle signals (45 min)
    max_cycles: int | None = None  # stop raising the signal after this many
    hold_cycle_while_busy: bool = True  # the face waits while the rig scans (interlock)
    buffer_capacity: int = 512  # pulses
    window_regs: int = 2048
    max_samples_per_pulse: int = 4096  # the radar's limit; RADAR reports at most what one window record holds
    height_speed_m_s: float = 0.05
    table_speed_deg_s: float = 15.0
    height_range_m: tuple[float, float] = (0.0, 2.0)
    table_max_deg: float = 60.0
    reboot_s: float = 20.0  # device seconds a reboot takes
    serial: int = 4242
    first_seq: int = 1  # sequence number of the first pulse after each boot (tests start near 2^32 - 1)
    state_file: str | None = None  # CYCLE_COUNTER and the last BOOT_ID, kept across restarts; None: not kept

    def __post_init__(self):
        if not (math.isfinite(self.time_scale) and self.time_scale > 0):  # NaN too: a clock that never runs
            raise ValueError(f"time_scale must be finite and > 0, got {self.time_scale}")
        if not 1 <= self.buffer_capacity <= 65535:
            raise ValueError("buffer_capacity must be in 1..65535")
        if not R.WINDOW_HEADER.length + R.record_regs(1) <= self.window_regs <= 65535 - R.WINDOW_ADDRESS:
            raise ValueError(f"window_regs must be in {R.WINDOW_HEADER.length + R.record_regs(1)}.."
                             f"{65535 - R.WINDOW_ADDRESS}")
        if not 0 <= self.first_seq < R.SEQ_MODULUS or not 0 <= self.initial_cycle < R.SEQ_MODULUS:
            raise ValueError("first_seq and initial_cycle must be u32 values")

    @property
    def max_samples(self) -> int:
        """MAX_SAMPLES_PER_PULSE as reported: what the radar can deliver and one window record can hold."""
        fit = (self.window_regs - R.WINDOW_HEADER.length - R.record_regs(0)) // 2
        return max(1, min(self.max_samples_per_pulse, fit))


@dataclasses.dataclass
class _Motion:
    code: R.Command
    t_start: float
    t_end: float
    start: float
    target: float


@dataclasses.dataclass
class _Pass:
    token: int
    cycle: int
    k: int  # campaign cycle index
    first_seq: int
    t_start: float  # device seconds
    start_time_ms: int  # device clock at t_start
    times: np.ndarray
    positions: np.ndarray
    records: np.ndarray  # (N, record_regs) uint16, CRC included
    scale: float
    range_window_start_s: float
    samples_per_pulse: int
    direction: int
    height_m: float
    angle_deg: float
    iq: np.ndarray  # (N, M, 2) int16, kept for the audit of completed passes
    radar: object = None  # the RadarParameters this pass was produced with (RADAR at START_PASS)
    rig_id: str = ""
    boot_id: int = 0
    short: bool = False  # cut short by fault injection: never a whole pass
    stalled: bool = False  # fault injection: the radar stops delivering, the pass stays RUNNING
    produced: int = 0
    overflow: int = 0
    state: R.PassState = R.PassState.RUNNING


class ModbusFault(Exception):
    """A request the controller answers with a Modbus exception code."""

    def __init__(self, code: int, reason: str):
        super().__init__(reason)
        self.code = code


ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, DEVICE_BUSY = 1, 2, 3, 4, 6


class RigController:
    """The rig controller's state machine; every method takes the device time `now` in seconds."""

    def __init__(self, config: DeviceConfig = DeviceConfig(), campaign: Campaign | None = None):
        self.config = config
        self.campaign = campaign or Campaign(config.world)
        self.radar = self.campaign.radar
        self.boots = 0
        self.rig_id = config.rig_id
        self.boot_id = 0
        self.cycle_counter = config.initial_cycle
        self._clock_offset_s = 0.0  # DEVICE_TIME at device time 0, after DEVICE_EPOCH
        stored = self._load_state()
        if stored is not None:
            self.cycle_counter = int(stored.get("cycle_counter", config.initial_cycle)) % R.SEQ_MODULUS
            self.boot_id = int(stored.get("boot_id", 0)) % R.SEQ_MODULUS
            clock_s = stored.get("clock_s")  # a restarted controller's clock goes on, never back
            if isinstance(clock_s, (int, float)) and math.isfinite(clock_s):
                self._clock_offset_s = max(0.0, float(clock_s) - DEVICE_EPOCH.timestamp())
        self._k_of_counter = {self.cycle_counter: 0}  # counter value -> campaign cycle index (truth)
        self.cycles_raised = 0
        self.next_cycle_due = config.first_cycle_after_s
        self.cycle_log: list[tuple[int, float]] = []  # (counter value, device time raised)
        self.height_m = 0.15
        self.angle_deg = 0.0
        self.carriage_m = -self.campaign.rail_half_travel_m
        # What the last complete passes held, for the audit of tests and the study (bounded: a long run).
        self.completed_passes: collections.deque[dict] = collections.deque(maxlen=200)
        self._boot(0.0)

    # ------------------------------------------------------------------------------------------ lifecycle

    def _boot(self, now: float) -> None:
        self.boots += 1
        previous = self.boot_id
        self.boot_id = secrets.randbits(32)
        while self.boot_id == previous:  # must differ from the previous boot's (map 4.2)
            self.boot_id = secrets.randbits(32)
        self.boot_time = now
        self.booting_until = now + (self.config.reboot_s if self.boots > 1 else 0.0)
        self.fault_word = R.Fault(0)
        self.motion: _Motion | None = None
        self.pass_: _Pass | None = None
        self.buffer: collections.deque[int] = collections.deque()  # pass indices of stored pulses
        self.next_seq = self.config.first_seq
        self.ack_seq = R.seq_add(self.next_seq, -1)  # nothing acknowledged yet
        self.drop_next = 0
        self.cmd_ack_seq = 0
        self.cmd_ack_code = 0
        self.cmd_result = R.CommandResult.NONE
        self.holding = [0] * (R.RESULT.address + R.RESULT.length)
        self._window_cache = None
        self._window_idx: list[int] = []
        self.last_busy_end = now
        self._save_state(now)

    # ------------------------------------------------------------------------------------------ persistence

    def _load_state(self) -> dict | None:
        path = self.config.state_file
        if not path or not os.path.exists(path):
            return None
        try:
            with open(path, encoding="utf-8") as f:
                return json.load(f)
        except (OSError, ValueError) as exc:
            log.warning("device: state file %s unreadable (%s); starting from the configured counter", path,
                        exc)
            return None

    def _save_state(self, now: float = 0.0) -> None:
        """Write CYCLE_COUNTER, BOOT_ID and DEVICE_TIME at device time `now` atomically (a crash leaves the
        old file or the new one)."""
        path = self.config.state_file
        if not path:
            return
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump({"cycle_counter": self.cycle_counter, "boot_id": self.boot_id, "rig_id": self.rig_id,
                       "clock_s": self._clock_ms(now) / 1000.0}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)

    def reboot(self, now: float, reconfigure: bool = False) -> None:
        """Controller restart: the pass, the buffer and the holding registers are lost; the drives
        keep position.
        reconfigure: the controller comes back with another SAMPLE_RATE (x0.75, or back) and RIG_ID (fault
        injection: a firmware update or a swapped radar head; the map allows RADAR and IDENTITY to change at a
        reboot only)."""
        log.warning("device: reboot at t=%.1f s (boot %d)%s", now, self.boots + 1,
                    " with a new RADAR and RIG_ID" if reconfigure else "")
        if self.pass_ is not None and self.pass_.state is R.PassState.RUNNING:
            self.carriage_m = self._carriage_at(now)
        if self.motion is not None:
            self._finish_motion(now, interrupted=True)
        if reconfigure:
            base = self.radar.sample_rate_hz
            rate = 0.75 * base if self.campaign.radar.sample_rate_hz == base else base
            self.campaign.radar = dataclasses.replace(self.campaign.radar, sample_rate_hz=rate)
            own_id = self.config.rig_id
            self.rig_id = f"{own_id}-b" if self.rig_id == own_id else own_id
        self._boot(now)

    def cut_short(self, now: float) -> None:
        """Fault injection: the running pass ends COMPLETE without its remaining pulses (and without a LAST
        pulse), so PULSES_PRODUCED < PULSES_PLANNED: what a non-conforming controller might do."""
        p = self.pass_
        if p is None or p.state is not R.PassState.RUNNING:
            return
        self.advance(now)
        if p.state is R.PassState.RUNNING and p.produced < len(p.times) - 1:
            p.state = R.PassState.COMPLETE
            p.short = True
            self.carriage_m = self._carriage_at(now)
            self.last_busy_end = now
            if self.cmd_ack_code == R.Command.START_PASS:
                self.cmd_result = R.CommandResult.DONE

    def booting(self, now: float) -> bool:
        return now < self.booting_until

    def inject_overflow(self, pulses: int) -> None:
        self.drop_next += pulses

    # ------------------------------------------------------------------------------------------ time

    def advance(self, now: float) -> None:
        """Bring motion, pulse production and the cycle signal up to device time `now`."""
        if self.motion is not None and now >= self.motion.t_end:
            self._finish_motion(now)
        p = self.pass_
        if p is not None and p.stalled and p.state is R.PassState.RUNNING and p.produced:
            p.t_start = now - float(p.times[p.produced - 1])  # a hung radar: the next pulse never falls due
        if p is not None and p.state is R.PassState.RUNNING:
            due = int(np.searchsorted(p.times, now - p.t_start, side="right"))
            for i in range(p.produced, min(due, len(p.times))):
                self._produce(p, i)
            if p.produced == len(p.times):
                p.state = R.PassState.COMPLETE
                self.carriage_m = float(p.positions[-1])
                self.cmd_result = R.CommandResult.DONE if self.cmd_ack_code == R.Command.START_PASS \
                    else self.cmd_result
                self.last_busy_end = p.t_start + float(p.times[-1])
                self.completed_passes.append(self._audit(p))
        self._cycle_signal(now)

    def _produce(self, p: _Pass, i: int) -> None:
        seq = self.next_seq
        self.next_seq = R.seq_add(seq, 1)  # 2^32 - 1 is followed by 0
        p.produced += 1
        if self.drop_next > 0 or len(self.buffer) >= self.config.buffer_capacity:
            self.drop_next = max(0, self.drop_next - 1)
            p.overflow += 1
            self.fault_word |= R.Fault.BUFFER_OVERFLOW
            return
        assert seq == R.seq_add(p.first_seq, i)
        self.buffer.append(i)
        if len(self.buffer) <= self._window_capacity(p):
            self._window_cache = None

    def _cycle_signal(self, now: float) -> None:
        c = self.config
        if c.max_cycles is not None and self.cycles_raised >= c.max_cycles:
            return
        if now < self.next_cycle_due:
            return
        if c.hold_cycle_while_busy and self._busy():
            return
        self.set_cycle_counter(now, R.seq_add(self.cycle_counter, 1))
        self.next_cycle_due = now + c.cycle_interval_s

    def set_cycle_counter(self, now: float, value: int) -> None:
        """The longwall control system's counter takes `value` (normally +1; a jump or a reset in faults): the
        face moved, so a running pass is aborted (map 4.2), and the state file keeps the value."""
        p = self.pass_
        if p is not None and p.state is R.PassState.RUNNING:  # the face moved under the rail
            self.carriage_m = self._carriage_at(now)
            p.state = R.PassState.ABORTED
            self.fault_word |= R.Fault.PASS_ABORTED
            log.warning("device: cycle counter changed during pass token %d: pass aborted", p.token)
        self.cycle_counter = int(value) % R.SEQ_MODULUS
        self.cycles_raised += 1
        self._k_of_counter[self.cycle_counter] = self.cycles_raised
        self.cycle_log.append((self.cycle_counter, now))
        self._save_state(now)
        log.info("device: cycle signal, counter %d at t=%.1f s", self.cycle_counter, now)

    def signal_cycle_now(self, now: float) -> None:
        """Make the next cycle signal due now (it still waits for a running pass): tests and manual runs."""
        self.next_cycle_due = min(self.next_cycle_due, now)

    def cycle_index(self, counter: int) -> int:
        """Campaign cycle index of a counter value: the first signal raised is cycle index 1 (the latest
        signal that set this value; a value set from outside counts on from the start value, modulo 2^32)."""
        k = self._k_of_counter.get(counter)
        if k is None:
            start = next(iter(self._k_of_counter))
            k = R.seq_diff(counter, start)
            k = k if 0 <= k <= 100_000 else self.cycles_raised  # a reset counter: the face still advanced
        return k

    def _busy(self) -> bool:
        return self.motion is not None or (self.pass_ is not None and self.pass_.state is R.PassState.RUNNING)

    def _finish_motion(self, now: float, interrupted: bool = False) -> None:
        m = self.motion
        value = m.target if not interrupted else m.start + (m.target - m.start) * min(
            1.0, (now - m.t_start) / max(m.t_end - m.t_start, 1e-9))
        if m.code is R.Command.MOVE_HEIGHT:
            self.height_m = value
        else:
            self.angle_deg = value
        self.motion = None
        self.last_busy_end = min(now, m.t_end)
        if not interrupted and self.cmd_ack_code == m.code:
            self.cmd_result = R.CommandResult.DONE

    def _carriage_at(self, now: float) -> float:
        p = self.pass_
        if p is None or p.state is not R.PassState.RUNNING:
            return self.carriage_m
        return float(np.interp(now - p.t_start, p.times, p.positions))

    # ------------------------------------------------------------------------------------------ commands

    def command(self, now: float, regs: list[int]) -> None:
        try:
            c = R.COMMAND.decode(regs)
        except R.RegisterError as exc:
            raise ModbusFault(ILLEGAL_VALUE, str(exc)) from None
        seq, code, arg = c["CMD_SEQ"], c["CMD_CODE"], c["ARG0"]
        if seq == 0:
            raise ModbusFault(ILLEGAL_VALUE, "CMD_SEQ 0 is reserved")
        if seq == self.cmd_ack_seq:
            return  # a retransmission: executed (or rejected) once already
        # Executed first, recorded after: a command answered with an exception was not received (map 7).
        result = self._execute(now, code, arg)
        self.cmd_ack_seq, self.cmd_ack_code, self.cmd_result = seq, code, result
        log.debug("device: command %d seq %d arg %d -> %s", code, seq, arg, self.cmd_result.name)

    def _execute(self, now: float, code: int, arg: int) -> R.CommandResult:
        cfg = self.config
        try:
            cmd = R.Command(code)
        except ValueError:
            return R.CommandResult.REJECTED_UNKNOWN
        if self.booting(now):
            return R.CommandResult.REJECTED_NOT_READY
        # ABORT and CLEAR_FAULTS are the way out of FAULTED (map 4.2, 5.1): accepted while a fault is set
        if cmd is R.Command.ABORT:
            if self.motion is not None:
                self._finish_motion(now, interrupted=True)
            if self.pass_ is not None and self.pass_.state is R.PassState.RUNNING:
                self.carriage_m = self._carriage_at(now)
                self.pass_.state = R.PassState.ABORTED
                self.fault_word |= R.Fault.PASS_ABORTED
                self.last_busy_end = now
            return R.CommandResult.DONE
        if cmd is R.Command.CLEAR_FAULTS:
            self.fault_word = R.Fault(0)
            return R.CommandResult.DONE
        if cmd is R.Command.NONE:
            return R.CommandResult.REJECTED_UNKNOWN
        if self.faulted():
            return R.CommandResult.REJECTED_NOT_READY
        if self._busy():
            return R.CommandResult.REJECTED_BUSY
        if cmd is R.Command.MOVE_HEIGHT:
            target = arg * 1e-6
            if not cfg.height_range_m[0] <= target <= cfg.height_range_m[1]:
                return R.CommandResult.REJECTED_RANGE
            duration = abs(target - self.height_m) / cfg.height_speed_m_s
            self.motion = _Motion(cmd, now, now + duration, self.height_m, target)
            return R.CommandResult.ACCEPTED
        if cmd is R.Command.SET_TABLE_ANGLE:
            target = arg * 1e-3
            if abs(target) > cfg.table_max_deg:
                return R.CommandResult.REJECTED_RANGE
            duration = abs(target - self.angle_deg) / cfg.table_speed_deg_s
            self.motion = _Motion(cmd, now, now + duration, self.angle_deg, target)
            return R.CommandResult.ACCEPTED
        # START_PASS
        if arg <= 0:
            return R.CommandResult.REJECTED_RANGE
        self._start_pass(now, arg)
        return R.CommandResult.ACCEPTED

    def _start_pass(self, now: float, token: int) -> None:
        k = max(0, self.cycle_index(self.cycle_counter))
        direction = 1 if self.carriage_m <= 0.0 else -1  # run from the end the carriage is parked at
        data = self.campaign.make_pass(k, self.height_m, self.angle_deg, direction)
        if data.echo.shape[1] > self.config.max_samples:  # the radar delivers at most MAX_SAMPLES_PER_PULSE
            data = dataclasses.replace(data, echo=data.echo[:, :self.config.max_samples])
        m = data.echo.shape[1]
        peak = float(max(np.abs(data.echo.real).max(), np.abs(data.echo.imag).max(), 1e-30))
        # 10 % headroom, as an ADC gain would leave
        scale = float(np.float32(peak / (0.9 * INT16_FULL_SCALE)))
        iq = np.stack([data.echo.real, data.echo.imag], axis=-1) / scale
        iq = np.clip(np.rint(iq), -INT16_FULL_SCALE, INT16_FULL_SCALE).astype(np.int16)
        first_seq = self.next_seq
        flags = np.zeros(len(data.time_s), dtype=np.int64)
        flags[0] |= R.RecordFlag.FIRST
        flags[-1] |= R.RecordFlag.LAST
        records = _encode_records(first_seq, data.time_s, data.position_m, flags, iq)
        self.buffer.clear()
        self.drop_next = 0
        self.fault_word &= ~(R.Fault.BUFFER_OVERFLOW | R.Fault.PASS_ABORTED)
        self._window_cache = None
        self._save_state(now)  # the clock too: a restart continues it from this pass's start, never before
        self.pass_ = _Pass(token=token, cycle=self.cycle_counter, k=k, first_seq=first_seq, t_start=now,
                           start_time_ms=self._clock_ms(now), times=data.time_s, positions=data.position_m,
                           records=records, scale=scale, range_window_start_s=data.range_window_start_s,
                           samples_per_pulse=m, direction=direction, height_m=self.height_m,
                           angle_deg=self.angle_deg, iq=iq, radar=self.campaign.radar, rig_id=self.rig_id,
                           boot_id=self.boot_id)
        log.info("device: pass token %d started (cycle %d, height %.3f m, angle %.2f deg, %d pulses x %d)",
                 token, self.cycle_counter, self.height_m, self.angle_deg, len(data.time_s), m)

    def _audit(self, p: _Pass) -> dict:
        """What a faithful archive of this pass must hold (scripts/acquisition_study.py checks every file)."""
        return {"token": p.token, "cycle": p.cycle, "k": p.k, "direction": p.direction,
                "angle_deg": p.angle_deg, "height_m": p.height_m, "n_pulses": len(p.times),
                "first_seq": p.first_seq, "radar": p.radar, "rig_id": p.rig_id, "boot_id": p.boot_id,
                "range_window_start_s": p.range_window_start_s, "overflow": p.overflow, "scale": p.scale,
                "iq": p.iq, "positions_um": np.rint(p.positions * 1e6).astype(np.int64),
                "times_us": np.rint(p.times * 1e6).astype(np.int64)}

    # ------------------------------------------------------------------------------------------ acknowledge

    def acknowledge(self, regs: list[int]) -> None:
        try:
            seq = R.ACK.decode(regs)["ACK_SEQ"]
        except R.RegisterError as exc:
            raise ModbusFault(ILLEGAL_VALUE, str(exc)) from None
        newest = R.seq_add(self.next_seq, -1)
        if R.seq_diff(seq, newest) > 0:  # modulo 2^32: 0 follows 2^32 - 1 (map 6)
            raise ModbusFault(ILLEGAL_VALUE, f"ACK_SEQ {seq} beyond the newest pulse {newest}")
        # "At or below" the acknowledgement (modulo 2^32) frees nothing more: the buffer holds only
        # later pulses.
        self.ack_seq = seq
        p = self.pass_
        while self.buffer and p is not None \
                and R.seq_at_or_before(R.seq_add(p.first_seq, self.buffer[0]), seq):
            self.buffer.popleft()
        self._window_cache = None

    # ------------------------------------------------------------------------------------------ registers

    def _clock_ms(self, now: float) -> int:
        return round((DEVICE_EPOCH.timestamp() + self._clock_offset_s + now) * 1000.0)

    def status_word(self, now: float) -> R.Status:
        s = R.Status.CYCLE_LINK_OK
        p = self.pass_
        if not self.booting(now) and not self.faulted():
            s |= R.Status.READY
        if self._busy():
            s |= R.Status.BUSY
        if p is not None and p.state is R.PassState.RUNNING:
            s |= R.Status.PASS_ACTIVE
        if p is not None and p.state is R.PassState.COMPLETE:
            s |= R.Status.PASS_COMPLETE
        if self.fault_word:
            s |= R.Status.FAULT
        if p is not None and p.overflow:
            s |= R.Status.OVERFLOW
        return s

    def faulted(self) -> bool:
        """A fault other than BUFFER_OVERFLOW / PASS_ABORTED is set: not READY, STATE FAULTED (map 4.2)."""
        return bool(self.fault_word & ~(R.Fault.BUFFER_OVERFLOW | R.Fault.PASS_ABORTED))

    def state(self, now: float) -> R.State:
        if self.booting(now):
            return R.State.BOOTING
        if self.faulted():
            return R.State.FAULTED
        if self.motion is not None:
            return R.State.MOVING if self.motion.code is R.Command.MOVE_HEIGHT else R.State.ROTATING
        if self.pass_ is not None and self.pass_.state is R.PassState.RUNNING:
            return R.State.SCANNING
        return R.State.IDLE

    def _motion_value(self, code: R.Command, now: float, resting: float) -> float:
        m = self.motion
        if m is None or m.code is not code:
            return resting
        f = min(1.0, (now - m.t_start) / max(m.t_end - m.t_start, 1e-9))
        return m.start + f * (m.target - m.start)

    def input_low(self, now: float) -> list[int]:
        """IR 0-127: IDENTITY, STATUS, RADAR, PASS."""
        cfg, radar = self.config, self.campaign.radar
        identity = R.IDENTITY.encode({
            "MAGIC": R.MAP_MAGIC, "MAP_MAJOR": R.MAP_VERSION[0], "MAP_MINOR": R.MAP_VERSION[1],
            "DEVICE_TYPE": 1, "SERIAL": cfg.serial, "FIRMWARE": 0x00010000, "RIG_ID": self.rig_id,
            "VENDOR": "uwbcl-sim"})
        status = R.STATUS.encode({
            "HEARTBEAT": int((now - self.boot_time) / HEARTBEAT_PERIOD_S) & 0xFFFF,
            "STATUS_WORD": int(self.status_word(now)), "FAULT_WORD": int(self.fault_word),
            "STATE": int(self.state(now)), "BOOT_ID": self.boot_id,
            "UPTIME": ((now - self.boot_time) * 1000.0 % 2**32) / 1000.0,
            "DEVICE_TIME": self._clock_ms(now) / 1000.0, "CYCLE_COUNTER": self.cycle_counter,
            "CARRIAGE_HEIGHT": self._motion_value(R.Command.MOVE_HEIGHT, now, self.height_m),
            "CARRIAGE_POSITION": self._carriage_at(now),
            "TABLE_ANGLE": self._motion_value(R.Command.SET_TABLE_ANGLE, now, self.angle_deg),
            "CMD_ACK_SEQ": self.cmd_ack_seq, "CMD_ACK_CODE": self.cmd_ack_code,
            "CMD_RESULT": int(self.cmd_result)})
        half = self.campaign.rail_half_travel_m
        radar_block = R.RADAR.encode({
            "CARRIER_FREQUENCY": radar.carrier_frequency_hz, "BANDWIDTH": radar.bandwidth_hz,
            "SAMPLE_RATE": radar.sample_rate_hz, "PRF": radar.pulse_repetition_frequency_hz,
            "ANTENNA_APERTURE": radar.antenna_aperture_m, "BORESIGHT_Y_SIGN": -1,
            "MAX_SAMPLES_PER_PULSE": cfg.max_samples, "BUFFER_CAPACITY": cfg.buffer_capacity,
            "WINDOW_ADDRESS": R.WINDOW_ADDRESS, "WINDOW_REGS": cfg.window_regs,
            "NOMINAL_SPEED": self.campaign.speed_m_s, "RAIL_MIN": -half, "RAIL_MAX": half,
            "HEIGHT_MIN": cfg.height_range_m[0], "HEIGHT_MAX": cfg.height_range_m[1],
            "TABLE_MAX": cfg.table_max_deg})
        p = self.pass_
        if p is None:
            pass_block = R.PASS.encode({})
        else:
            pass_block = R.PASS.encode({
                "TOKEN": p.token, "CYCLE": p.cycle, "FIRST_SEQ": p.first_seq, "PULSES_PLANNED": len(p.times),
                "PULSES_PRODUCED": p.produced, "OVERFLOW_COUNT": p.overflow,
                "RANGE_WINDOW_START": p.range_window_start_s, "SAMPLES_PER_PULSE": p.samples_per_pulse,
                "DIRECTION": p.direction, "AMPLITUDE_SCALE": p.scale, "HEIGHT": p.height_m,
                "TABLE_ANGLE": p.angle_deg, "START_TIME": p.start_time_ms / 1000.0,
                "PASS_STATE": int(p.state)})
        return identity + status + radar_block + pass_block

    def _window_capacity(self, p: _Pass) -> int:
        return (self.config.window_regs - R.WINDOW_HEADER.length) // p.records.shape[1]

    def window(self) -> np.ndarray:
        """The pulse window registers (header + the oldest unacknowledged records), as uint16."""
        p = self.pass_
        if self._window_cache is None:  # the records: rebuilt when acknowledged or appended to
            out = np.zeros(self.config.window_regs, dtype=np.uint16)
            idx = list(self.buffer)[: self._window_capacity(p)] if p is not None else []
            if idx:
                body = p.records[idx].ravel()
                out[R.WINDOW_HEADER.length:R.WINDOW_HEADER.length + body.size] = body
            self._window_cache, self._window_idx = out, idx
        out, idx = self._window_cache, self._window_idx
        if p is None:
            head = R.WINDOW_HEADER.encode({"NEWEST_SEQ": R.seq_add(self.next_seq, -1)})
        else:
            head = R.WINDOW_HEADER.encode({
                "OLDEST_SEQ": R.seq_add(p.first_seq, idx[0]) if idx else 0, "RECORDS": len(idx),
                "RECORD_REGS": p.records.shape[1], "NEWEST_SEQ": R.seq_add(self.next_seq, -1),
                "TOKEN": p.token})
        out[:R.WINDOW_HEADER.length] = head
        return out

    def meaningful(self, table: R.Table, address: int, count: int) -> int:
        """How many registers from `address` on carry data a client checks (not the window's unused tail)."""
        w0 = R.WINDOW_ADDRESS
        if table is not R.Table.INPUT or address < w0 or self.pass_ is None:
            return count
        used = R.WINDOW_HEADER.length + min(len(self.buffer), self._window_capacity(self.pass_)) \
            * self.pass_.records.shape[1]
        return max(0, min(count, w0 + used - address))

    def read(self, now: float, table: R.Table, address: int, count: int) -> list[int]:
        self.advance(now)
        end = address + count
        if table is R.Table.INPUT:
            if end <= 128:
                return self.input_low(now)[address:end]
            w0 = R.WINDOW_ADDRESS
            if w0 <= address and end <= w0 + self.config.window_regs:
                return self.window()[address - w0:end - w0].tolist()
            raise ModbusFault(ILLEGAL_ADDRESS, f"IR {address}-{end - 1} not mapped")
        if end <= len(self.holding):
            regs = list(self.holding)
            return regs[address:end]
        raise ModbusFault(ILLEGAL_ADDRESS, f"HR {address}-{end - 1} not mapped")

    def write(self, now: float, address: int, values: list[int]) -> None:
        self.advance(now)
        for block in R.HOLDING_BLOCKS:
            if address == block.address and len(values) == block.length:
                if block is R.COMMAND:
                    self.command(now, values)
                elif block is R.ACK:
                    self.acknowledge(values)
                else:
                    try:
                        block.decode(values)
                    except R.RegisterError as exc:
                        raise ModbusFault(ILLEGAL_VALUE, str(exc)) from None
                self.holding[address:address + len(values)] = values
                if block is R.COMMAND:
                    self.advance(now)
                return
        # Map 1.1, section 1: a write touching any register outside the blocks (reserved or unmapped) is an
        # address error (02) and takes precedence; one inside the blocks that is not exactly one block is 03.
        mapped = {a for b in R.HOLDING_BLOCKS for a in range(b.address, b.address + b.length)}
        if any(a not in mapped for a in range(address, address + len(values))):
            raise ModbusFault(ILLEGAL_ADDRESS,
                              f"HR {address}+{len(values)}: reaches a reserved or unmapped register")
        raise ModbusFault(ILLEGAL_VALUE,
                          f"HR {address}+{len(values)}: writes must cover exactly one holding block")


def _encode_records(first_seq: int, times_s, positions_m, flags, iq: np.ndarray) -> np.ndarray:
    """All pulse records of a pass at once (the layout of registers.encode_record), CRC per row."""
    n, m, _ = iq.shape
    head = np.zeros(n, dtype=np.dtype([("seq", ">u4"), ("t", ">u4"), ("x", ">i4"), ("flags", ">u2"),
                                       ("res", ">u2")]))
    head["seq"] = (first_seq + np.arange(n, dtype=np.int64)) % R.SEQ_MODULUS  # wraps 2^32 - 1 -> 0
    head["t"] = np.rint(np.asarray(times_s) * 1e6)  # microseconds (R.RECORD_TIME_SCALE_S)
    head["x"] = np.rint(np.asarray(positions_m) * 1e6)  # micrometres (R.RECORD_POSITION_SCALE_M)
    head["flags"] = flags
    regs = np.zeros((n, R.record_regs(m)), dtype=np.uint16)
    header_regs = np.frombuffer(head.tobytes(), dtype=">u2").reshape(n, R.RECORD_HEADER_REGS)
    regs[:, :R.RECORD_HEADER_REGS] = header_regs
    regs[:, R.RECORD_HEADER_REGS:-1] = iq.reshape(n, 2 * m).view(np.uint16)
    big = regs[:, :-1].astype(">u2")
    regs[:, -1] = [binascii.crc_hqx(big[i].tobytes(), 0xFFFF) for i in range(n)]
    return regs


# ============================================================================================== the server


class RigServer:
    """Serves a RigController over Modbus TCP from a background thread (or the caller's event loop).

    `start()` returns (host, port); port 0 picks a free port. Faults from `faults` are applied per request.
    """

    def __init__(self, controller: RigController, host: str = "127.0.0.1", port: int = 0,
                 faults: FaultPlan | None = None):
        self.controller = controller
        self.host, self.port = host, port
        self.faults = FaultInjector(faults or FaultPlan())
        self.lock = threading.RLock()
        self._t_origin = time.monotonic()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._swallow = False
        self._corrupt = False
        self._corrupt_span = 0
        self._exception_turn = 0
        self._absurd_pending = False
        self._absurd_turn = 0
        self._last_rx_function = 0
        self.requests_served = 0
        self._fault_rng = np.random.default_rng([self.faults.plan.seed, 99])

    # ------------------------------------------------------------------------------------------ time

    def now(self) -> float:
        return (time.monotonic() - self._t_origin) * self.controller.config.time_scale

    # ------------------------------------------------------------------------------------------ running

    def start(self, timeout_s: float = 10.0) -> tuple[str, int]:
        self._thread = threading.Thread(target=self._run_thread, name="uwbcl-rig", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError("simulated rig did not start listening")
        if self._error is not None:
            raise RuntimeError(f"simulated rig failed to start: {self._error}") from self._error
        return self.host, self.port

    def _run_thread(self) -> None:
        try:
            asyncio.run(self.serve())
        except BaseException as exc:  # noqa: BLE001 - reported to start(); the thread ends
            self._error = exc
            self._ready.set()

    async def serve(self) -> None:
        """Listen and serve until stop(); for the foreground `uwbcl simulate-device`."""
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # faults are the point; we log our own
        n_ir = R.WINDOW_ADDRESS + self.controller.config.window_regs
        n_hr = R.RESULT.address + R.RESULT.length
        device = SimDevice(
            id=0,  # every unit id
            simdata=([SimData(0, count=16, values=False, datatype=DataType.BITS)],
                     [SimData(0, count=16, values=False, datatype=DataType.BITS)],
                     [SimData(0, count=n_hr, values=0, datatype=DataType.REGISTERS)],
                     [SimData(0, count=n_ir, values=0, datatype=DataType.REGISTERS)]),
            action=self._action)
        self._loop = asyncio.get_running_loop()
        self._server = ModbusTcpServer(device, address=(self.host, self.port),
                                       trace_packet=self._trace_packet, trace_pdu=self._trace_pdu)
        await self._server.serve_forever(background=True)
        self.port = self._server.transport.sockets[0].getsockname()[1]
        log.info("device: serving rig %s on %s:%d", self.controller.config.rig_id, self.host, self.port)
        self._ready.set()
        ticker = asyncio.create_task(self._tick())
        try:
            await self._server.serving
        finally:
            ticker.cancel()

    async def _tick(self) -> None:
        while True:  # keeps the cycle signal and production current between requests
            with self.lock:
                self.controller.advance(self.now())
            await asyncio.sleep(0.05)

    def stop(self, timeout_s: float = 10.0) -> None:
        if self._loop is None or self._server is None:
            return
        if self._loop.is_running():
            asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout_s)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------------------------------ requests

    def _drop_connections(self) -> None:
        for conn in list(self._server.active_connections.values()):
            conn.close()

    async def _action(self, func_code, start_address, address, count, registers, values):
        from pymodbus.constants import ExcCodes

        if func_code in (1, 2, 5, 15):
            return ExcCodes.ILLEGAL_FUNCTION
        with self.lock:
            now = self.now()
            c = self.controller
            if c.booting(now):  # a rebooting controller does not talk
                return self._go_silent()
            running = c.pass_ is not None and c.pass_.state is R.PassState.RUNNING
            if values is None or func_code != 23:
                fault = self.faults.next_request(running, now, c.pass_.token if running else None)
            else:
                fault = None  # FC23 calls us twice: count it once, on its write
            self.requests_served += 1
            if fault is not None:
                log.info("device: injecting %s at request %d", fault, self.faults.requests)
            answer = self._answer_fault(fault, now)
            if answer is not _SERVE:
                return answer
            self._arm_fault(fault, now)
            answer = self._serve(func_code, start_address, address, count, registers, values, now, fault)
            if answer is not None:
                return answer
        if fault == "slow":
            await asyncio.sleep(self.faults.plan.slow_s)
        return None

    def _go_silent(self) -> None:
        """Send nothing back and drop the connections (a dead or rebooting controller)."""
        self._swallow = True
        self._loop.call_soon(self._drop_connections)
        return None

    def _answer_fault(self, fault, now: float):
        """The reply of a fault that replaces the request's (a dropped connection, an exception, a reboot);
        _SERVE when the request is to be served."""
        from pymodbus.constants import ExcCodes

        if fault == "drop":
            return self._go_silent()
        if fault == "exception":
            self._exception_turn += 1
            return ExcCodes.DEVICE_BUSY if self._exception_turn % 2 else ExcCodes.DEVICE_FAILURE
        if fault in ("exception02", "exception03", "exception04"):
            return ExcCodes(int(fault[-2:]))
        if fault in ("reboot", "reconfigure"):
            c = self.controller
            c.reboot(now, reconfigure=True) if fault == "reconfigure" else c.reboot(now)
            return self._go_silent()
        return _SERVE

    def _arm_fault(self, fault, now: float) -> None:
        """Set up a fault that damages the request being served or the controller behind it."""
        c = self.controller
        if fault == "absurd":
            self._absurd_pending = True
        if fault == "short":
            c.cut_short(now)
        if fault == "stall" and c.pass_ is not None:
            c.pass_.stalled = True
        if fault in ("counter_back", "counter_jump"):
            c.set_cycle_counter(now, R.seq_add(c.cycle_counter, -1 if fault == "counter_back" else 3))
        if fault == "overflow":
            c.inject_overflow(self.faults.plan.overflow_pulses)
        if fault == "missing":
            self._swallow = True
        if fault == "corrupt":
            self._corrupt = True

    def _serve(self, func_code, start_address, address, count, registers, values, now: float, fault):
        """Read or write the controller's registers; the Modbus exception code, or None."""
        from pymodbus.constants import ExcCodes

        c = self.controller
        table = R.Table.INPUT if func_code == 4 else R.Table.HOLDING
        if self._corrupt and values is None:  # damage a register the client relies on, not unused window
            self._corrupt_span = c.meaningful(table, address, count)
        try:
            if values is not None:
                c.write(now, address, list(values))
                registers[address - start_address:address - start_address + len(values)] = list(values)
            else:
                regs = c.read(now, table, address, count)
                if self._absurd_pending and table is R.Table.INPUT and address <= R.PASS.address \
                        and address + count >= R.PASS.address + R.PASS.length:
                    regs = self._absurd(regs, R.PASS.address - address)
                registers[address - start_address:address - start_address + count] = regs
        except ModbusFault as exc:
            log.debug("device: exception %d: %s", exc.code, exc)
            self._swallow = False if fault != "missing" else self._swallow
            return ExcCodes(exc.code)
        return None

    def _absurd(self, regs: list[int], offset: int) -> list[int]:
        """The PASS block inside `regs` with one absurd value and a valid CRC (fault injection)."""
        self._absurd_pending = False
        self._absurd_turn += 1
        values = R.PASS.decode(regs[offset:offset + R.PASS.length])
        name, value = (("PULSES_PLANNED", 10**9), ("SAMPLES_PER_PULSE", 60000),
                       ("AMPLITUDE_SCALE", -1.0))[self._absurd_turn % 3]
        log.info("device: PASS.%s reads %g once", name, value)
        return regs[:offset] + R.PASS.encode({**values, name: value}) + regs[offset + R.PASS.length:]

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending and len(data) > 7:
            self._last_rx_function = data[7]  # MBAP header (7 bytes), then the function code
        if sending and self._swallow:
            self._swallow = False
            return b""
        return data

    def _trace_pdu(self, sending: bool, pdu):
        if sending and getattr(pdu, "exception_code", None) == 1 and pdu.function_code == 0x80 \
                and self._last_rx_function in (3, 4, 6, 16, 23):
            # pymodbus answers a request it cannot decode (a read of 126 registers, a write of 124) with 01
            # and function code 0; the map (and the Modbus spec) say 03 for an illegal quantity of a supported
            # function. The request is the packet just received: the reply is sent from the same call.
            pdu.function_code = self._last_rx_function | 0x80
            pdu.exception_code = 3
        if sending and self._corrupt and getattr(pdu, "registers", None) and pdu.function_code in (3, 4) \
                and self._corrupt_span > 0:
            regs = list(pdu.registers)
            i = int(self._fault_rng.integers(min(self._corrupt_span, len(regs))))
            regs[i] ^= 1 << int(self._fault_rng.integers(16))
            pdu.registers = regs
            self._corrupt = False
        return pdu

    # ------------------------------------------------------------------------------------------ for tests

    def snapshot(self) -> dict:
        """Thread-safe view of the controller for tests and the study."""
        with self.lock:
            c = self.controller
            now = self.now()
            c.advance(now)
            return {"now": now, "cycle_counter": c.cycle_counter, "boots": c.boots, "state": c.state(now),
                    "buffer": len(c.buffer), "faults": self.faults.counts(), "requests": self.faults.requests,
                    "completed_passes": list(c.completed_passes), "cycle_log": list(c.cycle_log)}


class LongwallFollower(threading.Thread):
    """A longwall control system that pushes as soon as the rig is done: raises the next cycle signal each
    time `cycles_done()` reaches the number of signals raised, once `listening()` is true. For the demo and
    the study, which own both ends and should not wait out a fixed interval (or lose cycles to one) when
    faults slow a scan.
    """

    def __init__(self, server: RigServer, cycles_done, listening=lambda: True, period_s: float = 0.05):
        super().__init__(name="uwbcl-longwall", daemon=True)
        self.server, self.cycles_done = server, cycles_done
        self.listening, self.period_s = listening, period_s
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(self.period_s):
            if not self.listening():
                continue
            with self.server.lock:
                c = self.server.controller
                if self.cycles_done() >= c.cycles_raised:
                    c.signal_cycle_now(self.server.now())
                    c.advance(self.server.now())
