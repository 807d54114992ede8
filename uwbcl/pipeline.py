"""One pass through the focusing backend to its detections; one cycle's passes to its located plates.

The backend seam: `focuser(settings)` returns the object whose `nlcs_focus` / `backprojection_focus` the chosen
backend implements (the float64 numpy reference or the OpenCL engine); detection models neighbours with the
same focuser. Cycle-to-cycle displacement is `chain`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from . import chain, detect
from .focus import backprojection, nlcs
from .model import ScanPass
from .records import ALGORITHMS, BACKENDS, CycleResult, Detection, ProcessingSettings

log = logging.getLogger("uwbcl")


def _focuser(settings: ProcessingSettings):
    """The module or engine whose `nlcs_focus` / `backprojection_focus` the backend uses."""
    if settings.backend == "numpy":
        return nlcs, backprojection
    if settings.backend == "opencl":
        from .focus.engine import shared_engine  # imports pyopencl/pyvkfft only when asked for

        engine = shared_engine(settings.device)
        return engine, engine
    raise ValueError(f"unknown backend {settings.backend!r}; available: {', '.join(BACKENDS)}")


def detect_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()) -> list[Detection]:
    """Focus one pass and return its point targets in closest-approach coordinates."""
    if settings.algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {settings.algorithm!r}; available: {', '.join(ALGORITHMS)}")
    nlcs_focuser, bp_focuser = _focuser(settings)
    if settings.algorithm == "nlcs":
        products = nlcs_focuser.nlcs_focus(scan, ac_mode=settings.ac_mode)
        # The echo lets detection model the neighbours, focused by the same engine.
        return detect.detect_nlcs(products, settings.detection, scan, nlcs_focuser)
    return detect.detect_bp(bp_focuser.backprojection_focus(scan), settings.detection)


def locate_detections(passes: Sequence[ScanPass], detections: Sequence[Sequence[Detection]]) -> CycleResult:
    """The plates of one cycle from its passes and each pass's detections (same order)."""
    first = min(passes, key=lambda p: p.pass_start_time)
    by_height = {p.geometry.height_m: list(d) for p, d in zip(passes, detections)}
    return chain.locate_cycle(first.rig_id, first.cycle, first.pass_start_time, by_height,
                              passes[0].geometry.boresight_y_sign)


def locate_cycle(passes: Sequence[ScanPass], settings: ProcessingSettings = ProcessingSettings()) -> CycleResult:
    """All passes of one rig and cycle (one per height) -> the 3-D plates of that cycle."""
    if len({p.geometry.height_m for p in passes}) < 2:
        raise ValueError("a cycle needs passes at two or more heights")
    return locate_detections(passes, [detect_pass(p, settings) for p in passes])
