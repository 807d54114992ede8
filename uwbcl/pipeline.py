"""One pass through the focusing backend to its detections; one cycle's passes to its located plates.

The backend seam: `_focuser(settings)` returns the chosen backend's `Focuser` (`uwbcl.focus.protocol`: the
float64 numpy reference or the OpenCL engine); it focuses the pass, and detection models the neighbours and
the calibration targets with the same focuser. Cycle-to-cycle displacement is `chain`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from . import chain, detect
from .focus import backprojection, nlcs
from .focus.engine import shared_engine  # pyopencl and pyvkfft are imported when an engine is built, not here
from .focus.protocol import Focuser
from .focus.reference import NUMPY_FOCUSER
from .model import ScanPass
from .records import (
    ALGORITHMS,
    BACKENDS,
    CycleResult,
    Detection,
    DetectionSettings,
    LimitExceeded,
    ProcessingSettings,
)

log = logging.getLogger("uwbcl")


def _focuser(settings: ProcessingSettings) -> Focuser:
    """The backend's focuser: the numpy reference, or this process's engine for the settings' device."""
    if settings.backend == "numpy":
        return NUMPY_FOCUSER
    if settings.backend == "opencl":
        return shared_engine(settings.device)
    raise ValueError(f"unknown backend {settings.backend!r}; available: {', '.join(BACKENDS)}")


BP_PIXEL_M = 0.01  # backprojection image pixel (backprojection.backprojection_focus's default)
BP_RANGE_MARGIN_M = 0.1


def check_plan(scan: ScanPass, settings: ProcessingSettings) -> None:
    """LimitExceeded when focusing or detecting this pass would allocate more cells than
    settings.limits.max_focus_cells: the arrays are sized from the pass's metadata (rail length, pulse
    spacing, range window), so a pass whose positions are off by orders of magnitude is refused before any
    allocation."""
    limit = settings.limits.max_focus_cells
    grid = nlcs.focus_grid(scan)
    range_bin_m = grid.range_bins_m[1] - grid.range_bins_m[0] if grid.n_range > 1 else 1.0
    if settings.algorithm == "bp":
        u, r = backprojection.image_axes(grid, BP_PIXEL_M, BP_RANGE_MARGIN_M)
        cells, what, pixel_m = u.size * r.size, "backprojection image", (BP_PIXEL_M, BP_PIXEL_M)
    else:
        cells, what = grid.n_azimuth * grid.n_range, "NLCS focus grid"
        pixel_m = (grid.track_spacing_m, range_bin_m)
    if cells > limit:
        raise LimitExceeded(f"the {what} would have {cells} cells (limit {limit}, limits.max_focus_cells): "
                            f"rail {grid.n_track} pulses {grid.track_spacing_m:.3g} m apart, "
                            f"{grid.n_range} range bins")
    d = settings.detection
    footprint = ((2 * int(d.separation_m / pixel_m[0]) + 1)
                 * (2 * int(d.range_separation_m / pixel_m[1]) + 1))
    if footprint > limit:
        raise LimitExceeded(f"detection's separation ellipse would span {footprint} cells (limit {limit}): "
                            f"pulses {grid.track_spacing_m:.3g} m apart for a {d.separation_m} m separation")


def focus_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()):
    """Focus one pass and detect its point targets: (the focused products, the detections). The products are
    `NlcsProducts` or `BackprojectionProducts` by settings.algorithm; LimitExceeded, before any allocation,
    for a pass too large for settings.limits."""
    if settings.algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {settings.algorithm!r}; available: {', '.join(ALGORITHMS)}")
    check_plan(scan, settings)
    scan = nlcs.condition_pass(scan, settings.detection.background)  # every backend: host-side, before upload
    focuser = _focuser(settings)
    if settings.algorithm == "nlcs":
        products = focuser.nlcs_focus(scan, ac_mode=settings.ac_mode)
        # The echo lets detection model the neighbours, focused by the same backend.
        return products, detect.detect_nlcs(products, settings.detection, scan, focuser)
    products = focuser.backprojection_focus(scan)
    return products, detect.detect_bp(products, settings.detection)


def detect_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()) -> list[Detection]:
    """Focus one pass and return its point targets in closest-approach coordinates (LimitExceeded, before any
    allocation, for a pass too large for settings.limits)."""
    return focus_pass(scan, settings)[1]


def locate_detections(passes: Sequence[ScanPass], detections: Sequence[Sequence[Detection]],
                      detection: DetectionSettings = DetectionSettings()) -> CycleResult:
    """The plates of one cycle from its passes and each pass's detections (same order)."""
    first = min(passes, key=lambda p: p.pass_start_time)
    by_height = {p.geometry.height_m: list(d) for p, d in zip(passes, detections)}
    return chain.locate_cycle(first.rig_id, first.cycle, first.pass_start_time, by_height,
                              passes[0].geometry.boresight_y_sign, detection)


def locate_cycle(passes: Sequence[ScanPass], settings: ProcessingSettings = ProcessingSettings()
                 ) -> CycleResult:
    """All passes of one rig and cycle (one per height) -> the 3-D plates of that cycle."""
    if len({p.geometry.height_m for p in passes}) < 2:
        raise ValueError("a cycle needs passes at two or more heights")
    return locate_detections(passes, [detect_pass(p, settings) for p in passes], settings.detection)
