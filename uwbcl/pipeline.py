"""From passes to displacements: focus -> detect -> locate -> associate between cycles.

Data flows one way: archive I/O -> focusing -> detection -> 3-D location -> displacement -> outputs.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
from collections import defaultdict
from pathlib import Path

import numpy as np

from . import detect
from .atomic import write_csv_atomic  # noqa: F401  (re-exported: pipeline.write_csv_atomic)
from .displacement import AssociationSettings, Displacement, estimate_advance
from .focus import backprojection, nlcs
from .locate import Located, locate_plates
from .model import ScanPass

log = logging.getLogger("uwbcl")

ALGORITHMS = ("nlcs", "bp")
BACKENDS = ("opencl", "numpy")  # the OpenCL engine, and the float64 numpy reference it is checked against


@dataclasses.dataclass(frozen=True)
class ProcessingSettings:
    algorithm: str = "nlcs"
    backend: str = "opencl"
    device: str | None = None  # OpenCL device spec (`uwbcl devices`); None: PYOPENCL_CTX, else GPU first
    ac_mode: str = "exact"  # NLCS azimuth compression: "exact" reference or "series" (eq. 17)
    detection: detect.DetectionSettings = dataclasses.field(default_factory=detect.DetectionSettings)
    association: AssociationSettings = dataclasses.field(default_factory=AssociationSettings)


def _focuser(settings: ProcessingSettings):
    """The module or engine whose `nlcs_focus` / `backprojection_focus` the backend uses."""
    if settings.backend == "numpy":
        return nlcs, backprojection
    if settings.backend == "opencl":
        from .focus.engine import shared_engine  # imports pyopencl/pyvkfft only when asked for

        engine = shared_engine(settings.device)
        return engine, engine
    raise ValueError(f"unknown backend {settings.backend!r}; available: {', '.join(BACKENDS)}")


def detect_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()) -> list[detect.Detection]:
    """Focus one pass and return its point targets in closest-approach coordinates."""
    if settings.algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {settings.algorithm!r}; available: {', '.join(ALGORITHMS)}")
    nlcs_focuser, bp_focuser = _focuser(settings)
    if settings.algorithm == "nlcs":
        products = nlcs_focuser.nlcs_focus(scan, ac_mode=settings.ac_mode)
        # The echo lets detection model the neighbours, focused by the same engine.
        return detect.detect_nlcs(products, settings.detection, scan, nlcs_focuser)
    return detect.detect_bp(bp_focuser.backprojection_focus(scan), settings.detection)


@dataclasses.dataclass
class CycleResult:
    rig_id: str
    cycle: int
    start_time: str
    heights_m: tuple[float, ...]
    plates: list[Located]


def locate_cycle(passes: list[ScanPass], settings: ProcessingSettings = ProcessingSettings()) -> CycleResult:
    """All passes of one rig and cycle (one per height) -> the 3-D plates of that cycle."""
    if len({p.geometry.height_m for p in passes}) < 2:
        raise ValueError("a cycle needs passes at two or more heights")
    return locate_detections(passes, {p.geometry.height_m: detect_pass(p, settings) for p in passes})


def locate_detections(passes: list[ScanPass], by_height: dict[float, list[detect.Detection]]) -> CycleResult:
    """The plates of one cycle from its passes' detections, keyed by rail height."""
    plates = locate_plates(by_height, passes[0].geometry.boresight_y_sign)
    first = min(passes, key=lambda p: p.pass_start_time)
    return CycleResult(first.rig_id, first.cycle, first.pass_start_time, tuple(sorted(by_height)), plates)


def cycle_displacements(cycles: list[CycleResult], settings: ProcessingSettings = ProcessingSettings()
                        ) -> list[tuple[CycleResult, Displacement]]:
    """Displacement of each cycle from the previous one of the same rig."""
    out = []
    by_rig = defaultdict(list)
    for c in cycles:
        by_rig[c.rig_id].append(c)
    for rig in sorted(by_rig):
        seq = sorted(by_rig[rig], key=lambda c: c.cycle)
        for prev, cur in itertools.pairwise(seq):
            out.append((cur, estimate_advance(prev.plates, cur.plates, settings.association)))
    return out


DISPLACEMENT_COLUMNS = ("rig_id", "cycle", "start_time", "retreat_m", "creep_m", "vertical_m", "n_targets",
                        "residual_m", "retreat_spread_m", "creep_spread_m", "vertical_spread_m", "status")


def displacement_rows(results: list[tuple[CycleResult, Displacement]]) -> list[dict]:
    rows = []
    for c, d in results:
        rows.append({
            "rig_id": c.rig_id, "cycle": c.cycle, "start_time": c.start_time,
            "retreat_m": f"{d.retreat_m:.6f}", "creep_m": f"{d.creep_m:.6f}", "vertical_m": f"{d.vertical_m:.6f}",
            "n_targets": d.n_targets, "residual_m": f"{d.residual_m:.6f}",
            "retreat_spread_m": f"{d.spread_m[0]:.6f}", "creep_spread_m": f"{d.spread_m[1]:.6f}",
            "vertical_spread_m": f"{d.spread_m[2]:.6f}", "status": d.status,
        })
    return rows


def process_directory(in_dir: Path, out_dir: Path, settings: ProcessingSettings = ProcessingSettings(),
                      options=None):
    """Every archive under in_dir -> the outputs of docs/outputs.md in out_dir (the batch job: uwbcl.batch)."""
    from . import batch

    return batch.process_directory(in_dir, out_dir, settings, options or batch.BatchOptions())


def plates_array(plates: list[Located]) -> np.ndarray:
    return np.array([p.position_m for p in plates]).reshape(-1, 3)
