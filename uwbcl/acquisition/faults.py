"""Fault injection for the simulated rig: which Modbus request gets which fault, seeded and reproducible.

The spec (`uwbcl simulate-device --faults SPEC`) and every kind are in docs/modbus-register-map.md section 11.
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
