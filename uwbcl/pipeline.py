"""One pass through the focusing backend to its detections; one cycle's passes to its located plates.

The backend seam: `focuser(settings)` returns the chosen backend's `Focuser` (`uwbcl.focus.protocol`: the
float64 numpy reference or the OpenCL engine); it focuses the pass, and detection models the neighbours and
the calibration targets with the same focuser. Cycle-to-cycle displacement is `chain`'s.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence

import numpy as np

from . import chain, detect
from .detect import phase as detect_phase
from .focus import backprojection, nlcs
from .focus.engine import shared_engine  # pyopencl and pyvkfft are imported when an engine is built, not here
from .focus.protocol import Focuser
from .focus.reference import NUMPY_FOCUSER
from .model import MIN_WINDOW_RANGE_M, SPEED_OF_LIGHT_M_S, ScanPass
from .opencl import OpenClUnavailable
from .records import (
    ALGORITHMS,
    BACKENDS,
    AssociationSettings,
    CycleResult,
    Detection,
    DetectionSettings,
    LimitExceeded,
    PassTooSmall,
    ProcessingSettings,
)
from .utc import time_order

log = logging.getLogger("uwbcl")


def focuser(settings: ProcessingSettings) -> Focuser:
    """The backend's focuser: the numpy reference, or this process's engine for the settings' device."""
    if settings.backend == "numpy":
        return NUMPY_FOCUSER
    if settings.backend == "opencl":
        return shared_engine(settings.device)
    raise ValueError(f"unknown backend {settings.backend!r}; available: {', '.join(BACKENDS)}")


BP_PIXEL_M = 0.01  # backprojection image pixel (backprojection.backprojection_focus's default)
BP_RANGE_MARGIN_M = 0.1


MIN_FOCUS_PULSES = nlcs.LAGRANGE_ORDER
MIN_FOCUS_SAMPLES = 2


def apply_range_delay(scan: ScanPass, site_delay_s: float | None, *, quiet: bool = False) -> ScanPass:
    """The pass with the site's calibrated delay in place of the one its archive records
    (docs/configuration.md [radar]): the window start moves earlier by site - recorded, so an echo's range is
    that of the radar's axis less the site's delay. None: the pass as recorded. An archive that records no
    delay (0: a 1.0 file, or an uncalibrated import) gets the site's delay in full, with a warning (`quiet`:
    at debug level, for a pass read again after it was focused). Logged. Then the samples nearer than
    MIN_WINDOW_RANGE_M to the antenna are dropped (`crop_near_field`): a window that began before the
    antenna's delay (one that holds the coupling) is processed from there on.
    ValueError when no more than that near field is left in front of the antenna."""
    if site_delay_s is None or site_delay_s == scan.range_delay_s:
        return crop_near_field(scan, quiet=quiet)
    shift_s = site_delay_s - scan.range_delay_s
    if scan.range_delay_s == 0.0:
        say = log.debug if quiet else log.warning
        say("%s records no range_delay_s: the site's %.4f ns applied in full (window start %+.4f ns, ranges "
            "%+.4f m)", scan.source or "pass", site_delay_s * 1e9, -shift_s * 1e9,
            -0.5 * SPEED_OF_LIGHT_M_S * shift_s)
    else:
        log.info("%s: range_delay_s %.4f ns recorded, site %.4f ns: window start %+.4f ns",
                 scan.source or "pass", scan.range_delay_s * 1e9, site_delay_s * 1e9, -shift_s * 1e9)
    return crop_near_field(shift_range_delay(scan, site_delay_s), quiet=quiet)


def crop_near_field(scan: ScanPass, *, quiet: bool = False) -> ScanPass:
    """The pass without its samples nearer than MIN_WINDOW_RANGE_M (one-way) to the antenna, or behind it;
    logged (`quiet`: at debug level). ValueError when fewer than MIN_FOCUS_SAMPLES would be left (a delay for
    another radar, or in the wrong unit)."""
    start_s = 2.0 * MIN_WINDOW_RANGE_M / SPEED_OF_LIGHT_M_S
    if scan.range_window_start_s >= start_s:
        return scan
    fs = scan.radar.sample_rate_hz
    k = math.ceil((start_s - scan.range_window_start_s) * fs - 1e-9)
    if scan.samples_per_pulse - k < MIN_FOCUS_SAMPLES:
        end_m = 0.5 * SPEED_OF_LIGHT_M_S * (scan.range_window_start_s + scan.samples_per_pulse / fs)
        raise ValueError(
            f"the range window ends {end_m:.2f} m from the antenna, the calibrated delay removed "
            f"(range_delay_s {scan.range_delay_s * 1e9:.4f} ns): nothing of it lies {MIN_WINDOW_RANGE_M} m "
            "or more in front of the antenna (a delay for another radar, or in the wrong unit?)")
    (log.debug if quiet else log.warning)(
        "%s: the first %d samples lie nearer than %.2f m to the antenna (or behind it) once its delay is "
        "removed: dropped (the antenna's coupling, no plate)", scan.source or "pass", k, MIN_WINDOW_RANGE_M)
    return dataclasses.replace(scan, echo=scan.echo[:, k:],
                               range_window_start_s=scan.range_window_start_s + k / fs)


def shift_range_delay(scan: ScanPass, delay_s: float) -> ScanPass:
    """The pass as if its archive had been written with `delay_s` removed instead of the delay it records:
    window start - (delay_s - recorded), range_delay_s = delay_s (`apply_range_delay`, quietly)."""
    shift_s = delay_s - scan.range_delay_s
    return dataclasses.replace(scan, range_window_start_s=scan.range_window_start_s - shift_s,
                               range_delay_s=delay_s)


def bp_u_extent_m(scan: ScanPass, settings: ProcessingSettings) -> tuple[float, float] | None:
    """The backprojection image's u extent for the search `settings.detection.search` asks for (None: the
    rail's)."""
    footprint = detect.search_footprint(scan, settings.detection)
    if footprint is None:
        return None
    grid = nlcs.focus_grid(scan)
    _, r = backprojection.image_axes(grid, BP_PIXEL_M, BP_RANGE_MARGIN_M)
    return detect.peaks.search_extent_u_m(grid, r, footprint)




def check_plan(scan: ScanPass, settings: ProcessingSettings) -> None:
    """LimitExceeded when focusing or detecting this pass would allocate more cells than
    settings.limits.max_focus_cells: the arrays are sized from the pass's metadata (rail length, pulse
    spacing, range window), so a pass whose positions are off by orders of magnitude is refused before any
    allocation."""
    limit = settings.limits.max_focus_cells
    if scan.n_pulses < MIN_FOCUS_PULSES or scan.samples_per_pulse < MIN_FOCUS_SAMPLES:
        raise PassTooSmall(f"{scan.n_pulses} pulses of {scan.samples_per_pulse} samples: focusing needs at "
                           f"least {MIN_FOCUS_PULSES} pulses (the motion compensation's stencil) of "
                           f"{MIN_FOCUS_SAMPLES} samples")
    try:
        with np.errstate(over="raise", invalid="raise"):
            grid = nlcs.focus_grid(scan)
    except (OverflowError, FloatingPointError, ValueError) as e:
        raise LimitExceeded(f"the focus grid cannot be sized from this pass's metadata ({e}): positions, "
                            "sample rate or range window off by orders of magnitude?") from None
    range_bin_m = grid.range_bins_m[1] - grid.range_bins_m[0] if grid.n_range > 1 else 1.0
    if settings.algorithm == "bp":
        u, r = backprojection.image_axes(grid, BP_PIXEL_M, BP_RANGE_MARGIN_M, bp_u_extent_m(scan, settings))
        cells, what, pixel_m = u.size * r.size, "backprojection image", (BP_PIXEL_M, BP_PIXEL_M)
    else:
        cells, what = grid.n_azimuth * grid.n_range, "NLCS focus grid"
        pixel_m = (grid.track_spacing_m, range_bin_m)
    if cells > limit:
        raise LimitExceeded(f"the {what} would have {cells} cells (limit {limit}, limits.max_focus_cells): "
                            f"rail {grid.n_track} pulses {grid.track_spacing_m:.3g} m apart, "
                            f"{grid.n_range} range bins")
    d = settings.detection
    with np.errstate(divide="ignore", over="ignore"):  # a zero or denormal cell: an infinite footprint
        footprint = ((2 * np.floor(np.float64(d.separation_m) / pixel_m[0]) + 1)
                     * (2 * np.floor(np.float64(d.range_separation_m) / pixel_m[1]) + 1))
    if not footprint <= limit:  # NaN and inf included
        footprint = int(footprint) if math.isfinite(footprint) else footprint
        raise LimitExceeded(f"detection's separation ellipse would span {footprint} cells (limit {limit}): "
                            f"pulses {grid.track_spacing_m:.3g} m apart for a {d.separation_m} m separation")


def focus_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()):
    """Focus one pass and detect its point targets: (the focused products, the detections). The products are
    `NlcsProducts` or `BackprojectionProducts` by settings.algorithm; LimitExceeded, before any allocation,
    for a pass too large for settings.limits. The site's delay, if any, is applied first
    (`apply_range_delay`), and the search covers what `settings.detection.search` asks for."""
    scan = prepare_pass(scan, settings)
    backend = focuser(settings)
    footprint = detect.search_footprint(scan, settings.detection)
    products = _focus(scan, settings, backend)
    if settings.algorithm == "nlcs":
        # The echo lets detection model the neighbours, focused by the same backend.
        detections = detect.detect_nlcs(products, settings.detection, scan, backend, footprint)
    else:
        detections = detect.detect_bp(products, settings.detection, footprint)
    # Every backend's plates get the same carrier phase: measured on the echo itself (eq. R5).
    return products, detect_phase.with_phases(scan, detections)


def association_focuser(settings: ProcessingSettings) -> Focuser:
    """What backprojects the association's rib lattices in this process: the settings' backend, so a run
    gives the same bytes wherever its passes were focused (here or on a cluster's workers); the numpy
    reference where this process cannot start the engine (a cluster client without a device), logged, since
    the association margins then differ from a local run's in their last digits."""
    try:
        return focuser(settings)
    except (OpenClUnavailable, ImportError) as exc:
        log.warning("the rib registration runs on the numpy reference here (%s): association margins may "
                    "differ from a run on the %s backend in their last digits", exc, settings.backend)
        return NUMPY_FOCUSER


def prepare_pass(scan: ScanPass, settings: ProcessingSettings) -> ScanPass:
    """The pass as every focuser sees it: the site's delay applied (`apply_range_delay`), checked against
    settings.limits (LimitExceeded before any allocation), background subtracted (`nlcs.condition_pass`, on
    the host for every backend)."""
    if settings.algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {settings.algorithm!r}; available: {', '.join(ALGORITHMS)}")
    scan = apply_range_delay(scan, settings.range_delay_s)
    check_plan(scan, settings)
    return nlcs.condition_pass(scan, settings.detection.background)


def focus_only(scan: ScanPass, settings: ProcessingSettings):
    """The focused products of one pass exactly as `focus_pass` makes them, without detection (plots)."""
    scan = prepare_pass(scan, settings)
    return _focus(scan, settings, focuser(settings))


def _focus(scan: ScanPass, settings: ProcessingSettings, focuser: Focuser):
    if settings.algorithm == "nlcs":
        return focuser.nlcs_focus(scan, ac_mode=settings.ac_mode)
    return focuser.backprojection_focus(scan, u_extent_m=bp_u_extent_m(scan, settings))


def detect_pass(scan: ScanPass, settings: ProcessingSettings = ProcessingSettings()) -> list[Detection]:
    """Focus one pass and return its point targets in closest-approach coordinates (LimitExceeded, before any
    allocation, for a pass too large for settings.limits)."""
    return focus_pass(scan, settings)[1]


def locate_detections(passes: Sequence[ScanPass], detections: Sequence[Sequence[Detection]],
                      detection: DetectionSettings = DetectionSettings(),
                      range_sigma_m: float = AssociationSettings.range_sigma_m) -> CycleResult:
    """The plates of one cycle from its passes and each pass's detections (same order; range_sigma_m:
    `chain.locate_cycle`)."""
    first = min(passes, key=lambda p: time_order(p.pass_start_time))
    by_height = {p.geometry.height_m: list(d) for p, d in zip(passes, detections)}
    return chain.locate_cycle(first.rig_id, first.cycle, first.pass_start_time, by_height,
                              passes[0].geometry.boresight_y_sign, detection, range_sigma_m)


def locate_cycle(passes: Sequence[ScanPass], settings: ProcessingSettings = ProcessingSettings()
                 ) -> CycleResult:
    """All passes of one rig and cycle (one per height) -> the 3-D plates of that cycle."""
    if len({p.geometry.height_m for p in passes}) < 2:
        raise ValueError("a cycle needs passes at two or more heights")
    return locate_detections(passes, [detect_pass(p, settings) for p in passes], settings.detection,
                             settings.association.range_sigma_m)
