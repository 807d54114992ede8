"""Site configuration for `uwbcl process` (TOML, docs/configuration.md): file values, then command-line overrides.

Every key is checked: an unknown section or key, or a value of the wrong type, is an error naming the file and
the key, so a typo cannot silently fall back to a default.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path
from typing import Any

from .records import (
    AC_MODES,
    ALGORITHMS,
    BACKENDS,
    AssociationSettings,
    BatchOptions,
    ConfigError,
    DetectionSettings,
    OutputOptions,
    ProcessingSettings,
)

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
    height_tolerance_m: float = 0.005
    max_bridge_cycles: int = 3  # how many cycles a displacement may span after an untrusted one
    association: dict[str, Any] = dataclasses.field(default_factory=dict)  # AssociationSettings overrides
    detection: dict[str, Any] = dataclasses.field(default_factory=dict)  # DetectionSettings overrides
    output: OutputOptions = OutputOptions()

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
            raise ConfigError(None, "processing.backend", f"{self.backend!r} is not one of {', '.join(BACKENDS)}")
        if self.algorithm is not None and self.algorithm not in ALGORITHMS:
            raise ConfigError(None, "processing.algorithm",
                              f"{self.algorithm!r} is not one of {', '.join(ALGORITHMS)}")
        if self.ac_mode is not None and self.ac_mode not in AC_MODES:
            raise ConfigError(None, "processing.ac_mode", f"{self.ac_mode!r} is not 'exact' or 'series'")
        chosen = {k: getattr(self, k) for k in ("algorithm", "backend", "device", "ac_mode")
                  if getattr(self, k) is not None}
        return dataclasses.replace(ProcessingSettings(), **chosen, detection=self.detection_settings(),
                                   association=self.association_settings())

    def batch_options(self, **extra):
        return BatchOptions(jobs=self.jobs, cache=self.cache, heights_m=self.heights_m,
                            height_tolerance_m=self.height_tolerance_m, max_bridge_cycles=self.max_bridge_cycles,
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
                    "motion_model": _bool},
    "output": {f.name: _bool for f in dataclasses.fields(OutputOptions)},
}


def _detection_schema() -> dict:
    out = {}
    for f in dataclasses.fields(DetectionSettings):
        default = f.default
        out[f.name] = _bool if isinstance(default, bool) else _int if isinstance(default, int) else _number
    return out


OTHER_COMMANDS_SECTIONS = ("acquire",)


def parse_config(data: dict[str, Any], path: str | os.PathLike[str] | None = None) -> SiteConfig:
    """A SiteConfig from the parsed TOML tables."""
    schema = dict(_SCHEMA, detection=_detection_schema())
    values: dict[str, dict[str, Any]] = {}
    for section, table in data.items():
        if section in OTHER_COMMANDS_SECTIONS:
            continue  # one site file serves every command; `uwbcl acquire` checks its own table
        if section not in schema:
            raise ConfigError(path, section, f"unknown section; expected one of {', '.join(sorted(schema))}")
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
                     detection=values.get("detection", {}), output=OutputOptions(**values.get("output", {})))
    validate(cfg, path)
    return cfg


def validate(cfg: SiteConfig, path=None) -> None:
    def positive(key, v):
        if v is not None and not v > 0:
            raise ConfigError(path, key, f"must be > 0, got {v}")

    positive("site.web_depth_m", cfg.web_depth_m)
    positive("site.height_tolerance_m", cfg.height_tolerance_m)
    positive("processing.jobs", cfg.jobs)
    if cfg.prior_window_m is not None and not all(v > 0 for v in cfg.prior_window_m):
        raise ConfigError(path, "site.prior_window_m", f"must be > 0, got {list(cfg.prior_window_m)}")
    if cfg.heights_m is not None and len(set(cfg.heights_m)) < 2:
        raise ConfigError(path, "site.heights_m", "needs two or more distinct heights")
    positive("association.max_bound_m", cfg.association.get("max_bound_m"))
    if cfg.association.get("min_margin", 0.0) < 0:
        raise ConfigError(path, "association.min_margin",
                          f"must be >= 0, got {cfg.association['min_margin']}")
    if cfg.max_bridge_cycles < 1:
        raise ConfigError(path, "association.max_bridge_cycles", f"must be >= 1, got {cfg.max_bridge_cycles}")
    try:
        cfg.processing_settings()
    except ConfigError as e:
        raise ConfigError(path, e.key, e.reason) from None
    except (TypeError, ValueError) as e:
        raise ConfigError(path, "association/detection", str(e)) from e


def load_config(path: str | os.PathLike[str]) -> SiteConfig:
    if tomllib is None:
        raise ConfigError(path, "-", "reading TOML needs Python >= 3.11 or the 'tomli' package")
    try:
        with Path(path).open("rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(path, "-", f"cannot read: {e.strerror or e}") from e
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(path, "-", f"not valid TOML: {e}") from e
    return parse_config(data, path)


def override(cfg: SiteConfig, **flags: Any) -> SiteConfig:
    """Command-line flags win over the file; a flag left at None keeps the file's (or default) value."""
    output = {k: flags.pop(k) for k in [f.name for f in dataclasses.fields(OutputOptions)]
              if flags.get(k) is not None}
    kw = {k: v for k, v in flags.items() if v is not None}
    cfg = dataclasses.replace(cfg, **kw, output=dataclasses.replace(cfg.output, **output))
    validate(cfg, "command line")
    return cfg
