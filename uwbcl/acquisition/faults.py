"""Fault injection for the simulated rig: which Modbus request gets which fault, seeded and reproducible.

Spec (`uwbcl simulate-device --faults SPEC`), comma-separated items:

    KIND=P        each request gets fault KIND with probability P (a pass-only KIND: each request while a pass
                  runs, so that drawn faults do not pile up while the client waits for a cycle)
    KIND@N        request number N (1-based, counted from server start) gets fault KIND
    every=N       every N-th request gets a fault, KIND taken in turn from `kinds`
    kinds=A+B+..  the rotation for `every` (default: all kinds)
    after=N       no fault before request N (default 1)
    limit=N       at most N faults in all
    seed=S        seed of the random draws (default 0)
    slow_s=X      how late a slow reply is (real seconds, default 0.3)
    reboot_s=X    how long a reboot keeps the controller away (device seconds, default 20)
    overflow_pulses=N  pulses a buffer overflow drops (default 4)

Kinds: drop (the connection is closed instead of a reply; the request is not executed), missing (executed, no
reply), slow (the reply is late by slow_s), exception (Modbus exception 06 DEVICE BUSY or 04 DEVICE FAILURE
in turn, not executed), exception02 / exception03 / exception04 (one spurious exception of that code, not
executed), corrupt (executed; one bit of one register of the next read reply is flipped), reboot (the
controller restarts while a pass runs: the pass and the buffer are lost), reconfigure (a reboot that also
brings a new RADAR.SAMPLE_RATE, x0.75 and back, and a new IDENTITY.RIG_ID, "<rig>-b" and back), overflow (the
buffer drops the next `overflow_pulses` pulses of a running pass as if it were full), absurd (the next PASS
read carries an absurd value with a valid CRC: PULSES_PLANNED 1e9, SAMPLES_PER_PULSE 60000 or AMPLITUDE_SCALE
-1, in turn), short (the running pass ends COMPLETE with fewer pulses than planned, no LAST pulse: a
controller that breaks the map), stall (the radar of the running pass stops delivering pulses, the pass stays
RUNNING: only a no-progress watchdog notices), counter_back (the longwall counter goes back by 1),
counter_jump (it jumps by 3: two cycles missed). reboot, reconfigure, overflow, absurd, short and stall wait
for a pass to be running; the others hit the request they are drawn for. A counter change during a pass aborts
it (map 4.2).
"""

from __future__ import annotations

import dataclasses

import numpy as np

KINDS = ("drop", "missing", "slow", "exception", "corrupt", "reboot", "overflow", "exception02",
         "exception03", "exception04", "absurd", "short", "stall", "reconfigure", "counter_back",
         "counter_jump")
# Only meaningful while a pass runs.
PASS_KINDS = ("reboot", "overflow", "absurd", "short", "stall", "reconfigure")
CYCLE_KINDS = ("counter_back", "counter_jump")  # change the cycle counter: the cycle being scanned is left


@dataclasses.dataclass(frozen=True)
class FaultPlan:
    probabilities: tuple[tuple[str, float], ...] = ()
    at: tuple[tuple[int, str], ...] = ()
    every: int = 0
    kinds: tuple[str, ...] = KINDS
    after: int = 1
    limit: int | None = None
    seed: int = 0
    slow_s: float = 0.3
    reboot_s: float = 20.0
    overflow_pulses: int = 4

    @property
    def empty(self) -> bool:
        return not (self.probabilities or self.at or self.every)


def parse_faults(spec: str | None) -> FaultPlan:
    """FaultPlan from the spec above; ValueError naming the bad item."""
    if not spec:
        return FaultPlan()
    probs, at, kw = [], [], {}
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        try:
            if "@" in item:
                kind, n = item.split("@", 1)
                _check_kind(kind)
                at.append((int(n), kind))
            elif "=" in item:
                key, value = item.split("=", 1)
                if key in KINDS:
                    p = float(value)
                    if not 0.0 <= p <= 1.0:
                        raise ValueError("a probability must be in [0, 1]")
                    probs.append((key, p))
                elif key == "kinds":
                    kinds = tuple(k for k in value.split("+") if k)
                    for k in kinds:
                        _check_kind(k)
                    kw["kinds"] = kinds
                elif key in ("every", "after", "limit", "seed", "overflow_pulses"):
                    kw[key] = int(value)
                    if kw[key] < 0:
                        raise ValueError("must be >= 0")
                elif key in ("slow_s", "reboot_s"):
                    kw[key] = float(value)
                    if kw[key] < 0:
                        raise ValueError("must be >= 0")
                else:
                    raise ValueError(f"unknown key {key!r}")
            else:
                raise ValueError("expected KIND=P, KIND@N or KEY=VALUE")
        except ValueError as exc:
            raise ValueError(f"--faults item {item!r}: {exc}") from None
    return FaultPlan(probabilities=tuple(probs), at=tuple(sorted(at)), **kw)


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ValueError(f"unknown fault kind {kind!r}; kinds: {', '.join(KINDS)}")


@dataclasses.dataclass(frozen=True)
class Injected:
    request: int  # request number the fault was applied to
    kind: str
    device_time_s: float


class FaultInjector:
    """Decides, request by request, which fault to apply; remembers what it injected."""

    def __init__(self, plan: FaultPlan):
        self.plan = plan
        self.rng = np.random.default_rng(plan.seed)
        self.requests = 0
        self.injected: list[Injected] = []
        self._pending: list[str] = []  # pass-only faults waiting for a running pass
        self._rotation = 0
        self._at = dict(plan.at)
        self._hit_pass: int | None = None  # the pass the last pass-only fault was applied to

    def next_request(self, pass_running: bool, device_time_s: float,
                     pass_token: int | None = None) -> str | None:
        """Count a request; return the fault kind to apply to it, or None. With `pass_token`, pass-only faults
        waiting for a pass hit one pass each (two on one pass would count as two faults but act as one)."""
        self.requests += 1
        n = self.requests
        p = self.plan
        if p.limit is not None and len(self.injected) >= p.limit:
            return None
        drawn = [kind for kind, prob in p.probabilities  # the same draws every request: reproducible
                 if self.rng.uniform() < prob and (pass_running or kind not in PASS_KINDS)]
        if n < p.after:
            return None
        if n in self._at:
            drawn.insert(0, self._at[n])
        if p.every and n % p.every == 0:
            drawn.insert(0, p.kinds[self._rotation % len(p.kinds)])
            self._rotation += 1
        for kind in drawn:
            if kind in PASS_KINDS:
                self._pending.append(kind)
        immediate = [k for k in drawn if k not in PASS_KINDS]
        kind = None
        if pass_running and self._pending and (pass_token is None or pass_token != self._hit_pass):
            kind = self._pending.pop(0)
            self._hit_pass = pass_token
        elif immediate:
            kind = immediate[0]
        if kind is not None:
            self.injected.append(Injected(n, kind, device_time_s))
        return kind

    def counts(self) -> dict[str, int]:
        out = dict.fromkeys(KINDS, 0)
        for f in self.injected:
            out[f.kind] += 1
        return out
