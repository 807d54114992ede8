"""`uwbcl calibrate ARCHIVE... --reflector X,Y,Z ...`: the radar's two-way delay offset from reflectors at
surveyed positions (docs/outputs.md section 8, docs/configuration.md [radar]).

The delay D (`range_delay_s`) is what the radar's own delay axis reads for an echo from the antenna phase
centre. A wrong D moves every target's closest-approach range R_c by about c (D - D_true) / 2; not exactly
(the envelope moves, the carrier phase history does not, and the focused range lands in between: 0.85 of it
on the PulsON-like set). So D is found by iteration on the focused passes themselves: every pass is focused
with the trial D (`pipeline.apply_range_delay`), each surveyed reflector is matched to the nearest detection,
and D moves by 2 mean(R_c measured - R_c surveyed) / c, then by secant steps, until the step is below
`DELAY_TOL_S`. The mean over reflectors and passes is the least-squares common offset; its standard
uncertainty is the scatter of the residuals over sqrt(n), divided by the measured slope of R_c in c D / 2.
The along-track offset (x measured - x surveyed) is reported the same way; it is not applied.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from . import config, pipeline
from .atomic import write_text_atomic
from .model import SPEED_OF_LIGHT_M_S, ScanPass
from .records import ConfigError, Detection, ProcessingSettings

log = logging.getLogger("uwbcl")

C = SPEED_OF_LIGHT_M_S
DELAY_TOL_S = 1e-13  # stop once a step of D is below 0.1 ps (15 um of range)
MAX_ITERATIONS = 8  # the secant converges in 3-4 steps from 2.3 ns off; a bound for a pathological scene
DEFAULT_GATE_M = 0.5  # a reflector's detection must lie this close to it in (x, R_c) at the starting delay
MATCH_CANDIDATES = 4  # per reflector, the nearest detections within the gate considered


@dataclasses.dataclass(frozen=True)
class Match:
    """One surveyed reflector seen in one pass, at the final delay."""

    file: str
    reflector: int  # index into the reflectors given
    surveyed_m: tuple[float, float, float]
    x_surveyed_m: float
    rc_surveyed_m: float  # sqrt(Y^2 + (Z - h)^2) at the pass's rail height h
    x_m: float  # measured
    rc_m: float
    snr_db: float

    @property
    def dx_m(self) -> float:
        return self.x_m - self.x_surveyed_m

    @property
    def drc_m(self) -> float:
        return self.rc_m - self.rc_surveyed_m


@dataclasses.dataclass(frozen=True)
class Calibration:
    delay_s: float  # the estimated range_delay_s
    delay_sigma_s: float  # its standard uncertainty (NaN with one reflector-pass)
    start_delay_s: float  # the delay the passes were first focused with
    start_offset_m: float  # mean R_c measured - surveyed at the start delay: the uncalibrated range error
    along_track_m: float  # mean x measured - surveyed at the final delay (reported, not applied)
    along_track_sigma_m: float
    slope: float  # d(mean R_c) / d(c D / 2), measured (1 if only one step was taken)
    iterations: int
    matches: list[Match]
    missing: list[tuple[str, int]]  # (file, reflector) pairs without a detection within the gate


def parse_reflector(text: str) -> tuple[float, float, float]:
    """`X,Y,Z` in metres (radar frame) -> a tuple; ValueError naming the text otherwise."""
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--reflector {text!r}: expected X,Y,Z in metres, e.g. 2.9,-2.4,0.3") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"--reflector {text!r}: expected three finite numbers X,Y,Z in metres")
    return values  # type: ignore[return-value]


def surveyed_track(reflector_m: Sequence[float], height_m: float) -> tuple[float, float]:
    """(x, R_c) of a surveyed reflector seen from a rail at height h (docs/method.md section 1)."""
    x, y, z = reflector_m
    return float(x), math.hypot(y, z - height_m)


def match_reflectors(detections: Sequence[Detection], reflectors: Sequence[Sequence[float]], height_m: float,
                     gate_m: float) -> list[Detection | None]:
    """Per reflector, its detection in one pass, or None: among the MATCH_CANDIDATES nearest detections
    within `gate_m` of its surveyed (x, R_c), the assignment (one detection per reflector) that matches the
    most reflectors, then whose R_c residuals agree best (one delay moves every reflector's R_c alike: a
    clutter or coupling peak near one reflector does not), then the nearest."""
    truth = [surveyed_track(r, height_m) for r in reflectors]
    options = []
    for x, rc in truth:
        near = sorted((math.hypot(d.x_m - x, d.rc_m - rc), j) for j, d in enumerate(detections))
        options.append([j for dist, j in near if dist <= gate_m][:MATCH_CANDIDATES] + [None])
    best, best_key = [None] * len(reflectors), None
    for combo in itertools.product(*options):
        chosen = [j for j in combo if j is not None]
        if len(set(chosen)) < len(chosen):
            continue
        residual = [detections[j].rc_m - truth[i][1] for i, j in enumerate(combo) if j is not None]
        dist = sum(math.hypot(detections[j].x_m - truth[i][0], detections[j].rc_m - truth[i][1])
                   for i, j in enumerate(combo) if j is not None)
        key = (-len(chosen), float(np.ptp(residual)) if residual else 0.0, dist)
        if best_key is None or key < best_key:
            best, best_key = list(combo), key
    return [None if j is None else detections[j] for j in best]


def _measure(scans: Sequence[ScanPass], reflectors, settings: ProcessingSettings, delay_s: float,
             gate_m: float) -> tuple[list[Match], list[tuple[str, int]]]:
    """Every pass focused with the trial delay; each reflector's match, or (file, reflector) if none."""
    matches, missing = [], []
    for scan in scans:
        shifted = pipeline.shift_range_delay(scan, delay_s)
        found = pipeline.detect_pass(shifted, settings)
        h = scan.geometry.height_m
        for i, d in enumerate(match_reflectors(found, reflectors, h, gate_m)):
            if d is None:
                missing.append((scan.source, i))
                continue
            x, rc = surveyed_track(reflectors[i], h)
            matches.append(Match(scan.source, i, tuple(reflectors[i]), x, rc, d.x_m, d.rc_m, d.snr_db))
    return matches, missing


def calibrate(scans: Sequence[ScanPass], reflectors: Sequence[Sequence[float]], settings: ProcessingSettings,
              start_delay_s: float | None = None, gate_m: float = DEFAULT_GATE_M) -> Calibration:
    """The delay that puts the reflectors' measured R_c on their surveyed R_c (module docstring).

    Parameters
    ----------
    scans : passes over the reflectors (any heights); each is refocused with every trial delay.
    reflectors : surveyed positions (X, Y, Z) in the radar frame (m).
    settings : focusing and detection (its own range_delay_s is ignored: the trial delay replaces it).
    start_delay_s : the first trial; default the mean of the delays the archives record.
    gate_m : matching gate in (x, R_c) at the first trial (m).

    Raises
    ------
    ValueError when no reflector is matched in any pass at the start delay.
    """
    settings = dataclasses.replace(settings, range_delay_s=None)
    if start_delay_s is None:
        start_delay_s = float(np.mean([s.range_delay_s for s in scans]))
    delay = float(start_delay_s)
    start = delay
    matches, missing = _measure(scans, reflectors, settings, delay, gate_m)
    if not matches:
        raise ValueError(f"no reflector was detected within {gate_m} m of its surveyed (x, R_c) in any "
                         f"pass at the start delay {delay * 1e9:.4f} ns (give a nearer start with [radar] "
                         "range_delay_s, a wider --gate-m, or a region of interest that keeps them)")
    start_offset = float(np.mean([m.drc_m for m in matches]))
    offset, slope, iterations = start_offset, 1.0, 0
    previous: tuple[float, float] | None = None
    while iterations < MAX_ITERATIONS:
        step = 2.0 * offset / (C * slope)  # R_c too long: the delay was too small
        if abs(step) < DELAY_TOL_S:
            break
        previous = (delay, offset)
        delay += step
        iterations += 1
        matches, missing = _measure(scans, reflectors, settings, delay, gate_m + abs(0.5 * C * step))
        if not matches:
            raise ValueError(f"the reflectors were lost at the trial delay {delay * 1e9:.4f} ns")
        offset = float(np.mean([m.drc_m for m in matches]))
        change = 0.5 * C * (delay - previous[0])
        if change != 0 and (offset - previous[1]) != 0:
            slope = -(offset - previous[1]) / change  # d(mean R_c) / d(c D / 2), about 0.85
            slope = min(max(slope, 0.1), 10.0)  # a bound against a noisy secant
    drc = np.array([m.drc_m for m in matches])
    dx = np.array([m.dx_m for m in matches])
    n = drc.size
    sigma_rc = float(np.std(drc, ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    sigma_x = float(np.std(dx, ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return Calibration(delay_s=delay, delay_sigma_s=2.0 * sigma_rc / (C * slope), start_delay_s=start,
                       start_offset_m=start_offset, along_track_m=float(dx.mean()),
                       along_track_sigma_m=sigma_x, slope=slope, iterations=iterations, matches=matches,
                       missing=missing)


def report_lines(cal: Calibration, recorded_delays_s: Sequence[float]) -> list[str]:
    """The table per reflector and pass, the estimate with its uncertainty and the uncalibrated error."""
    lines = [f"{'file':40s} {'reflector (X, Y, Z) m':>26s} {'x m':>9s} {'R_c m':>8s} {'dx mm':>8s} "
             f"{'dR_c mm':>8s} {'SNR dB':>7s}"]
    for m in cal.matches:
        xyz = ", ".join(f"{v:.3f}" for v in m.surveyed_m)
        lines.append(f"{Path(m.file).name[-40:]:40s} {xyz:>26s} {m.x_m:9.4f} {m.rc_m:8.4f} "
                     f"{m.dx_m * 1e3:+8.2f} {m.drc_m * 1e3:+8.2f} {m.snr_db:7.1f}")
    for file, i in cal.missing:
        lines.append(f"{Path(file).name[-40:]:40s} reflector {i + 1}: not detected within the gate")
    sigma = ("n/a (one reflector-pass)" if math.isnan(cal.delay_sigma_s)
             else f"{cal.delay_sigma_s * 1e9:.4f} ns")
    lines.append(f"range_delay_s = {cal.delay_s:.6e} s ({cal.delay_s * 1e9:.4f} ns, standard uncertainty "
                 f"{sigma}) from {len(cal.matches)} reflector-passes, {cal.iterations} refocusing steps, "
                 f"slope {cal.slope:.3f}")
    along = "" if math.isnan(cal.along_track_sigma_m) else f" +- {cal.along_track_sigma_m * 1e3:.2f}"
    lines.append(f"along-track offset (x measured - surveyed): {cal.along_track_m * 1e3:+.2f}{along} mm "
                 "(reported, not applied)")
    recorded = sorted(set(float(d) for d in recorded_delays_s))
    rec = ", ".join(f"{d * 1e9:.4f} ns" for d in recorded)
    state = "uncalibrated" if recorded == [0.0] else "recorded"
    lines.append(f"archives: range_delay_s {rec} ({state}); at the start delay "
                 f"{cal.start_delay_s * 1e9:.4f} ns the ranges were {cal.start_offset_m * 1e3:+.1f} mm off; "
                 f"this calibration changes the delay by {(cal.delay_s - cal.start_delay_s) * 1e9:+.4f} ns")
    return lines


_ANY_HEADER = re.compile(r"^\s*\[")
_DELAY_KEY = re.compile(r"""^\s*(range_delay_s|"range_delay_s"|'range_delay_s')\s*=""")


def _header(table: str) -> re.Pattern:
    return re.compile(rf"^\s*\[\s*{table}\s*\]\s*(#.*)?$")


def _set_delay(lines: list[str], table: str, value: str, *, add: bool) -> bool:
    """Replace `range_delay_s` in [table] of `lines` in place (its old line kept above as a comment), or add
    it at the table's top when `add`; False when the table is not there as a `[table]` header."""
    start = next((i for i, line in enumerate(lines) if _header(table).match(line)), None)
    if start is None:
        return False
    end = next((i for i in range(start + 1, len(lines)) if _ANY_HEADER.match(lines[i])), len(lines))
    for i in range(start + 1, end):
        if _DELAY_KEY.match(lines[i]):
            lines[i:i + 1] = [f"# before uwbcl calibrate: {lines[i].strip()}", value]
            return True
    if add:
        lines.insert(start + 1, value)
    return True


def with_range_delay(toml_text: str, delay_s: float) -> str:
    """The site file's text with `[radar] range_delay_s` set (the key replaced where it is, its old line kept
    above it as a comment with whatever provenance it carried, else added to the [radar] table, else a
    [radar] table appended), and an `[import] range_delay_s` replaced alike (one delay per site: `uwbcl
    import` refuses two); everything else kept as written. Keys written another way (an inline table, a
    dotted key) are not edited: `write_config` then finds the delay not set and says so."""
    lines = toml_text.splitlines()
    value = f"range_delay_s = {delay_s!r}  # s, uwbcl calibrate"
    _set_delay(lines, "import", value, add=False)
    if not _set_delay(lines, "radar", value, add=True):
        lines += [""] if lines else []  # a blank line before the appended table, none at a new file's top
        lines += ["[radar]", value]
    return "\n".join(lines) + "\n"


def write_config(out: Path, base: Path | None, delay_s: float) -> None:
    """OUT.toml: the site file `base` (or an empty one) with the delay set, checked as `uwbcl process` reads
    it before it is written (atomically). ConfigError naming OUT when the result would not load, or would not
    hold the delay (a site file that writes the key in a form `with_range_delay` does not edit)."""
    text = with_range_delay(config.read_site_text(base) if base is not None else "", delay_s)
    try:
        parsed = config.tomllib.loads(text)
    except config.tomllib.TOMLDecodeError as exc:
        parsed, why = None, f"would not be valid TOML ({exc})"
    else:
        held = [parsed.get(t, {}).get("range_delay_s") for t in ("radar", "import")
                if isinstance(parsed.get(t), dict) and "range_delay_s" in parsed[t]]
        why = "" if held and all(v == delay_s for v in held) else "would not hold the new delay"
    if why:
        raise ConfigError(out, "radar.range_delay_s",
                          f"{why}: the site file sets range_delay_s in a form uwbcl calibrate does not "
                          "edit (an inline table, a dotted key); write it as `range_delay_s = ...` "
                          f"under a `[radar]` header, or set {delay_s!r} by hand")
    config.parse_config(parsed, out)  # ConfigError naming OUT if the result would not load
    write_text_atomic(out, text)
