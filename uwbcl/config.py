"""Site configuration for `uwbcl process` (TOML, docs/configuration.md): file values, then command-line
overrides.

Every key is checked: an unknown section or key, or a value of the wrong type, is an error naming the file and
the key, so a typo cannot silently fall back to a default.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

from .atomic import read_regular_file
from .records import (
    AC_MODES,
    ALGORITHMS,
    BACKENDS,
    BACKGROUND_MODES,
    HEIGHT_TOLERANCE_M,
    SEARCH_REGIONS,
    AssociationSettings,
    BatchOptions,
    ConfigError,
    DetectionSettings,
    OutputOptions,
    ProcessingSettings,
    ReadLimits,
)

# A two-way delay beyond +-1 us (150 m of range) is no antenna/cable delay: a unit error (ns for s).
MAX_RANGE_DELAY_S = 1e-6

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    try:
        import tomli as tomllib  # type: ignore[no-redef]
    except ModuleNotFoundError:
        tomllib = None  # type: ignore[assignment]


@dataclasses.dataclass(frozen=True)
class SiteConfig:
    """Everything `uwbcl process` takes beyond the input and output directories."""

    algorithm: str | None = None  # None: ProcessingSettings' default
    backend: str | None = None
    device: str | None = None
    ac_mode: str | None = None
    jobs: int | None = None  # None: batch.default_jobs (all cores for numpy, 2 for opencl)
    cache: bool = True
    web_depth_m: float | None = None  # nominal advance per cycle: the association prior along X
    prior_creep_m: float = 0.0
    prior_vertical_m: float = 0.0
    prior_window_m: tuple[float, float, float] | None = None  # None: AssociationSettings' default
    heights_m: tuple[float, ...] | None = None  # expected rail heights; passes at others are rejected
    height_tolerance_m: float = HEIGHT_TOLERANCE_M
    max_bridge_cycles: int = 3  # how many cycles a displacement may span after an untrusted one
    association: dict[str, Any] = dataclasses.field(default_factory=dict)  # AssociationSettings overrides
    detection: dict[str, Any] = dataclasses.field(default_factory=dict)  # DetectionSettings overrides
    limits: dict[str, Any] = dataclasses.field(default_factory=dict)  # ReadLimits overrides
    output: OutputOptions = OutputOptions()
    range_delay_s: float | None = None  # [radar] range_delay_s: the site's calibrated delay (uwbcl calibrate)

    def association_settings(self) -> AssociationSettings:
        kw = dict(self.association)
        if self.web_depth_m is not None:
            kw["prior_advance_m"] = (self.web_depth_m, self.prior_creep_m, self.prior_vertical_m)
        if self.prior_window_m is not None:
            kw["prior_window_m"] = tuple(self.prior_window_m)
        return AssociationSettings(**kw)

    def detection_settings(self) -> DetectionSettings:
        return DetectionSettings(**self.detection)

    def processing_settings(self):
        if self.backend is not None and self.backend not in BACKENDS:
            raise ConfigError(None, "processing.backend",
                              f"{self.backend!r} is not one of {', '.join(BACKENDS)}")
        if self.algorithm is not None and self.algorithm not in ALGORITHMS:
            raise ConfigError(None, "processing.algorithm",
                              f"{self.algorithm!r} is not one of {', '.join(ALGORITHMS)}")
        if self.ac_mode is not None and self.ac_mode not in AC_MODES:
            raise ConfigError(None, "processing.ac_mode", f"{self.ac_mode!r} is not 'exact' or 'series'")
        chosen = {k: getattr(self, k) for k in ("algorithm", "backend", "device", "ac_mode")
                  if getattr(self, k) is not None}
        return dataclasses.replace(ProcessingSettings(), **chosen, detection=self.detection_settings(),
                                   association=self.association_settings(), limits=ReadLimits(**self.limits),
                                   range_delay_s=self.range_delay_s)

    def batch_options(self, **extra):
        return BatchOptions(jobs=self.jobs, cache=self.cache, heights_m=self.heights_m,
                            height_tolerance_m=self.height_tolerance_m,
                            max_bridge_cycles=self.max_bridge_cycles,
                            outputs=self.output, **extra)


# key -> (type check, converter); the sections mirror docs/configuration.md
def _bool(v):
    return isinstance(v, bool), v


def _int(v):
    return isinstance(v, int) and not isinstance(v, bool), v


def _number(v):
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    return ok, float(v) if ok else v


def _str(v):
    return isinstance(v, str), v


def _triple(v):
    ok = isinstance(v, list) and len(v) == 3 and all(_number(x)[0] for x in v)
    return ok, tuple(float(x) for x in v) if ok else v


def _number_list(v):
    ok = isinstance(v, list) and len(v) >= 1 and all(_number(x)[0] for x in v)
    return ok, tuple(float(x) for x in v) if ok else v


_TYPE_NAMES = {_bool: "true or false", _int: "an integer", _number: "a finite number", _str: "a string",
               _triple: "a list of 3 numbers", _number_list: "a list of numbers"}

_SCHEMA = {
    "processing": {"algorithm": _str, "backend": _str, "device": _str, "ac_mode": _str, "jobs": _int,
                   "cache": _bool},
    "site": {"web_depth_m": _number, "prior_creep_m": _number, "prior_vertical_m": _number,
             "prior_window_m": _triple, "heights_m": _number_list, "height_tolerance_m": _number},
    "association": {"tolerance_m": _triple, "min_targets": _int, "min_confident_targets": _int,
                    "weighted": _bool, "range_sigma_m": _number, "outlier_chi2": _number,
                    "max_bridge_cycles": _int, "min_margin": _number, "max_bound_m": _number,
                    "motion_model": _bool, "second_look": _bool, "rib_registration": _bool,
                    "carrier_phase": _bool, "vertical_step_sigma_m": _number,
                    "vertical_trend_sigma_m": _number, "max_backward_m": _number},
    "output": {f.name: _bool for f in dataclasses.fields(OutputOptions)},
    "limits": {f.name: _int for f in dataclasses.fields(ReadLimits)},
    "radar": {"range_delay_s": _number},
}


def _detection_schema() -> dict:
    out = {}
    for f in dataclasses.fields(DetectionSettings):
        default = f.default
        out[f.name] = (_bool if isinstance(default, bool) else _int if isinstance(default, int)
                       else _str if isinstance(default, str) else _number)
    return out


OTHER_COMMANDS_SECTIONS = ("acquire", "import")  # `uwbcl import` checks [import]


def parse_config(data: dict[str, Any], path: str | os.PathLike[str] | None = None) -> SiteConfig:
    """A SiteConfig from the parsed TOML tables."""
    schema = dict(_SCHEMA, detection=_detection_schema())
    values: dict[str, dict[str, Any]] = {}
    known = ", ".join(sorted([*schema, *OTHER_COMMANDS_SECTIONS]))
    for section, table in data.items():
        if section in OTHER_COMMANDS_SECTIONS:
            continue  # one site file serves every command; `uwbcl acquire` checks its own table
        if section not in schema and not isinstance(table, dict):
            raise ConfigError(path, section,
                              f"a key outside any table: put it under its [section] (one of {known})")
        if section not in schema:
            raise ConfigError(path, section, f"unknown section; expected one of {known}")
        if not isinstance(table, dict):
            raise ConfigError(path, section, "must be a table ([section])")
        values[section] = {}
        for key, value in table.items():
            check = schema[section].get(key)
            if check is None:
                raise ConfigError(path, f"{section}.{key}",
                                  f"unknown key; expected one of {', '.join(sorted(schema[section]))}")
            ok, converted = check(value)
            if not ok:
                raise ConfigError(path, f"{section}.{key}", f"expected {_TYPE_NAMES[check]}, got {value!r}")
            values[section][key] = converted
    proc, site = values.get("processing", {}), values.get("site", {})
    assoc = dict(values.get("association", {}))
    max_bridge = assoc.pop("max_bridge_cycles", SiteConfig.max_bridge_cycles)
    cfg = SiteConfig(**proc, **site, max_bridge_cycles=max_bridge, association=assoc,
                     detection=values.get("detection", {}), limits=values.get("limits", {}),
                     output=OutputOptions(**values.get("output", {})),
                     range_delay_s=values.get("radar", {}).get("range_delay_s"))
    validate(cfg, path)
    return cfg


MAX_LENGTH_M = 1000.0  # no length of a gate road's survey is larger (and a larger one overflows the maths)
MAX_BRIDGE_CYCLES = 1000


def beyond_max_length(v) -> bool:
    """Whether a finite value of a length (one, or a tuple or list; None: none) lies beyond +-MAX_LENGTH_M (a
    value not finite is the finiteness checks' to name)."""
    values = () if v is None else v if isinstance(v, (tuple, list)) else (v,)
    return any(MAX_LENGTH_M < abs(x) < math.inf for x in values)


def _check_length(path, key: str, v) -> None:
    """ConfigError unless every value of a length (one, or a tuple) is within +-MAX_LENGTH_M."""
    if beyond_max_length(v):
        raise ConfigError(path, key, f"must be within +-{MAX_LENGTH_M:g} m, got {v!r}")


def check_heights(heights, path, key: str) -> None:
    """ConfigError unless the rail heights (None: any) are finite, within +-MAX_LENGTH_M and two or more
    distinct ones."""
    if heights is None:
        return
    if not all(math.isfinite(h) for h in heights):
        raise ConfigError(path, key, f"must be finite, got {list(heights)}")
    _check_length(path, key, tuple(heights))
    if len(set(heights)) < 2:
        raise ConfigError(path, key, "needs two or more distinct heights")


def _positive(v) -> bool:
    return all(math.isfinite(x) and x > 0 for x in (v if isinstance(v, tuple) else (v,)))


# The smallest length a positive length setting may be: a micrometre is below any precision, gate or
# tolerance the method uses, and 1e-300 m divided by itself overflowed (an independent tester).
MIN_LENGTH_M = 1e-6
# The non-maximum-suppression semi-axes at most this: beyond a plate spacing they suppress plates, and
# beyond the image no row was searched at all.
MAX_SEPARATION_M = 1.0
MAX_DB = 200.0  # decibel settings within +-this: 10^(1e308 / 10) overflowed


def _length(lo_m: float, hi_m: float | None = None):
    """(check, what the value must be) for a length setting (one value or a tuple) in [lo_m, hi_m]."""
    def check(v) -> bool:
        return all(math.isfinite(x) and lo_m <= x and (hi_m is None or x <= hi_m)
                   for x in (v if isinstance(v, tuple) else (v,)))
    return check, f"finite and between {lo_m:g} and {hi_m:g} m" if hi_m else f"finite and >= {lo_m:g} m"


def _decibels(lo_db: float, hi_db: float):
    return (lambda v: math.isfinite(v) and lo_db <= v <= hi_db), f"finite and between {lo_db:g} and {hi_db:g}"


# Values of the effective settings that would make the maths singular, an index negative or a loop unbounded:
# "section.key" -> (check, what the value must be). Every other number must at least be finite.
_RANGES = {
    "association.tolerance_m": _length(MIN_LENGTH_M),
    "association.prior_window_m": _length(MIN_LENGTH_M),
    "association.min_targets": (lambda v: v >= 1, ">= 1"),
    "association.min_confident_targets": (lambda v: v >= 1, ">= 1"),
    "association.range_sigma_m": _length(MIN_LENGTH_M, 1.0),
    "association.outlier_chi2": (_positive, "finite and > 0"),
    "association.vertical_step_sigma_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0 (0: off)"),
    "association.vertical_trend_sigma_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0"),
    "detection.separation_m": _length(1e-3, MAX_SEPARATION_M),
    "detection.range_separation_m": _length(1e-3, MAX_SEPARATION_M),
    "detection.min_snr_db": _decibels(-MAX_DB, MAX_DB),
    "detection.max_targets": (lambda v: 1 <= v <= 4096, "between 1 and 4096"),
    "detection.relative_floor_db": _decibels(-MAX_DB, 0.0),
    "detection.neighbour_cancellation_passes": (lambda v: 0 <= v <= 16, "between 0 and 16"),
    "detection.neighbour_cancellation_tol_m": _length(MIN_LENGTH_M),
    "detection.neighbour_gain_degree": (lambda v: 0 <= v <= 32, "between 0 and 32"),
    "detection.min_range_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0"),
    "detection.max_range_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0 (0: no upper bound)"),
    "detection.cfar_db": _decibels(0.0, MAX_DB),
    "detection.cancel_max_targets": (lambda v: 0 <= v <= 4096, "between 0 (all) and 4096"),
    "detection.cancel_time_budget_s": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0 (0: none)"),
    "detection.synthesis_passes": (lambda v: 0 <= v <= 16, "between 0 and 16"),
    "detection.synthesis_tol_m": _length(MIN_LENGTH_M),
    "detection.cross_height_x_tol_m": _length(MIN_LENGTH_M),
    "detection.cross_height_rc_tol_m": _length(MIN_LENGTH_M),
    "detection.short_track_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0 (0: never short)"),
    "detection.cross_height_wall_tol_m": (lambda v: math.isfinite(v) and v >= 0, "finite and >= 0 (0: off)"),
    **{f"limits.{f.name}": (lambda v: v >= 1, ">= 1") for f in dataclasses.fields(ReadLimits)},
}


def _check_ranges(settings: ProcessingSettings, path) -> None:
    for section, obj in (("association", settings.association), ("detection", settings.detection),
                         ("limits", settings.limits)):
        for f in dataclasses.fields(obj):
            key, value = f"{section}.{f.name}", getattr(obj, f.name)
            if value is None or isinstance(value, (bool, str)):
                continue
            check, want = _RANGES.get(key, (lambda v: all(math.isfinite(x) for x in (
                v if isinstance(v, tuple) else (v,))), "finite"))
            if not check(value):
                raise ConfigError(path, key, f"must be {want}, got {value!r}")
            if key.endswith("_m"):
                _check_length(path, key, value)
    d = settings.detection
    if d.background not in BACKGROUND_MODES:
        raise ConfigError(path, "detection.background",
                          f"must be one of {', '.join(map(repr, BACKGROUND_MODES))}, got {d.background!r}")
    if d.search not in SEARCH_REGIONS:
        raise ConfigError(path, "detection.search", f"{d.search!r} is not one of {', '.join(SEARCH_REGIONS)}")
    if settings.range_delay_s is not None and not abs(settings.range_delay_s) <= MAX_RANGE_DELAY_S:
        raise ConfigError(path, "radar.range_delay_s",
                          f"must be within +-{MAX_RANGE_DELAY_S:g} s, got {settings.range_delay_s!r}")
    if 0 < d.max_range_m <= d.min_range_m:
        raise ConfigError(path, "detection.max_range_m",
                          f"must be 0 (no upper bound) or > detection.min_range_m ({d.min_range_m}), "
                          f"got {d.max_range_m!r}")


def validate(cfg: SiteConfig, path=None) -> None:
    def positive(key, v):
        if v is not None and not _positive(v):
            raise ConfigError(path, key, f"must be finite and > 0, got {v}")

    positive("site.web_depth_m", cfg.web_depth_m)
    positive("site.height_tolerance_m", cfg.height_tolerance_m)
    positive("processing.jobs", cfg.jobs)
    for key in ("site.prior_creep_m", "site.prior_vertical_m"):
        if not math.isfinite(getattr(cfg, key.split(".")[1])):
            raise ConfigError(path, key, "must be finite")
    if cfg.prior_window_m is not None and not _positive(tuple(cfg.prior_window_m)):
        raise ConfigError(path, "site.prior_window_m",
                          f"must be finite and > 0, got {list(cfg.prior_window_m)}")
    check_heights(cfg.heights_m, path, "site.heights_m")
    positive("association.max_bound_m", cfg.association.get("max_bound_m"))
    for key in ("max_backward_m", "min_margin"):
        if cfg.association.get(key, 0.0) < 0:
            raise ConfigError(path, f"association.{key}", f"must be >= 0, got {cfg.association[key]}")
    if not 1 <= cfg.max_bridge_cycles <= MAX_BRIDGE_CYCLES:
        raise ConfigError(path, "association.max_bridge_cycles",
                          f"must be between 1 and {MAX_BRIDGE_CYCLES}, got {cfg.max_bridge_cycles}")
    for key in ("web_depth_m", "height_tolerance_m", "prior_window_m", "prior_creep_m", "prior_vertical_m",
                "heights_m"):
        _check_length(path, f"site.{key}", getattr(cfg, key))
    try:
        settings = cfg.processing_settings()
    except ConfigError as e:
        raise ConfigError(path, e.key, e.reason) from None
    except (TypeError, ValueError) as e:
        raise ConfigError(path, "association/detection/limits", str(e)) from e
    _check_ranges(settings, path)


def parse_heights(values) -> tuple[float, ...] | None:
    """Rail heights from command-line words, `0.2 0.6` or `0.2,0.6`; ConfigError (a usage error) for
    anything but finite numbers."""
    if not values:
        return None
    out = []
    for text in (v for item in values for v in str(item).split(",") if v.strip()):
        try:
            h = float(text)
        except ValueError:
            raise ConfigError(None, "--heights", f"{text!r} is not a number") from None
        if not math.isfinite(h):
            raise ConfigError(None, "--heights", f"{text!r} is not a finite height")
        out.append(h)
    return tuple(out)


def load_config(path: str | os.PathLike[str]) -> SiteConfig:
    return parse_config(read_toml(path), path)


# A site file is a few kilobytes; anything far larger is not one (a device, a log written over it).
MAX_CONFIG_BYTES = 1 << 20


def read_site_text(path: str | os.PathLike[str]) -> str:
    """The text of a site file: a regular file of at most MAX_CONFIG_BYTES (`atomic.read_regular_file`: never
    a FIFO or a device such as /dev/zero, which would block or never end), UTF-8, a byte-order mark dropped.
    ConfigError (file, no key) otherwise; OSError and UnicodeDecodeError pass to the caller."""
    try:
        raw = read_regular_file(path, MAX_CONFIG_BYTES)
    except ValueError as e:  # not a regular file, or too large for a site file
        raise ConfigError(path, "", f"{e}: not a site file") from None
    return raw.decode("utf-8").removeprefix("\ufeff")


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The parsed tables of a site file (`read_site_text`); ConfigError for a missing, unreadable or invalid
    one."""
    if tomllib is None:
        raise ConfigError(path, "", "reading TOML needs Python >= 3.11 or the 'tomli' package")
    try:
        return tomllib.loads(read_site_text(path))
    except OSError as e:
        raise ConfigError(path, "", f"cannot read: {e.strerror or e}") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "", f"not valid TOML: {e}") from e
    except UnicodeDecodeError as e:  # binary, UTF-16, Latin-1: TOML is UTF-8
        raise ConfigError(path, "", f"not a UTF-8 text file (TOML must be UTF-8): {e.reason} at byte "
                                     f"{e.start}") from e
    except RecursionError:  # tomllib recurses per nesting level: [[[[... thousands deep
        raise ConfigError(path, "", "not valid TOML: nested too deeply") from None


def override(cfg: SiteConfig, **flags: Any) -> SiteConfig:
    """Command-line flags win over the file; a flag left at None keeps the file's (or default) value."""
    output = {k: flags.pop(k) for k in [f.name for f in dataclasses.fields(OutputOptions)]
              if flags.get(k) is not None}
    kw = {k: v for k, v in flags.items() if v is not None}
    cfg = dataclasses.replace(cfg, **kw, output=dataclasses.replace(cfg.output, **output))
    validate(cfg, "command line")
    # on the file and the flags together: a site file's window with the night's --web-depth is a prior
    if cfg.prior_window_m is not None and cfg.web_depth_m is None:
        raise ConfigError("command line", "site.prior_window_m", "is the window of the web-depth prior: give "
                          "site.web_depth_m (--web-depth) too, or leave it out (without a prior, unused)")
    return cfg
