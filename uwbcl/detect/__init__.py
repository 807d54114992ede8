"""Point-target (bolt plate) detection in a focused pass (docs/method.md section 4).

Both focusers give an image on (azimuth, r_LRCM) axes. Peaks are found on the pixel grid (`peaks`: local
maxima above a floor relative to the strongest peak and to the image's noise level), refined to sub-cell
accuracy on the underlying band-limited image (`refine`), refined again with the neighbours' modelled
responses removed (`cancel`: close plates bias each other's sub-cell peaks through their point responses'
arms), and mapped to the target's closest-approach coordinates (x_M, R_c) of the pass: for NLCS through the
inverse of the focus-position map t_f(t_n) (`calibration`, eqs. 18-19, C12) corrected by synthesis (each
plate where its own focused model peaks at the image's peak: `synthesis`), for backprojection directly.

The focusing backend is a `Focuser` (`uwbcl.focus.protocol`): detection models the neighbours and the
calibration targets with the backend that focused the pass.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from .. import geometry as geo
from ..focus import backprojection as bp
from ..focus import nlcs
from ..focus.protocol import Focuser
from ..focus.reference import NUMPY_FOCUSER
from ..model import ScanPass
from ..records import Detection, DetectionSettings
from . import calibration, cancel, peaks, refine, split, synthesis

# The lattice (m) of the backprojection refinement of NLCS detections beyond the rail ends (BP's pixel).
BP_SUBSCENE_CELL_M = 0.01
# Two peaks refined to within this many cells of each other climbed to one maximum: one target, kept once.
SAME_PEAK_CELLS = 0.25

__all__ = ["detect_bp", "detect_nlcs", "distinct_cells", "distinct_positions", "search_footprint"]


def detect_nlcs(products: nlcs.NlcsProducts, settings: DetectionSettings = DetectionSettings(),
                scan: ScanPass | None = None, focuser: Focuser = NUMPY_FOCUSER,
                footprint: geo.BeamFootprint | None = None) -> list[Detection]:
    """Point targets of an NLCS image, in the pass's closest-approach coordinates.

    Parameters
    ----------
    products : NlcsProducts
        The focused pass (`Focuser.nlcs_focus`); its `focus_calibration` cache is filled.
    settings : DetectionSettings
        Floors, non-maximum suppression and neighbour cancellation.
    scan : ScanPass, optional
        The pass's echo: with it, the peaks are re-refined with the neighbours' modelled responses removed
        (`cancel.NlcsModel`) and located by synthesis (`synthesis.locate`); without it, refined on the image
        alone and located by the t_f(t_n) calibration alone.
    focuser : Focuser
        Focuses the models and the calibration targets: the backend that focused `products`.
    footprint : BeamFootprint, optional
        Search the beam's footprint beside the rail (`settings.search`, `search_footprint`); None: the rail.

    Returns
    -------
    list of Detection
        Strongest first: x_M and R_c (m), t_n (s), r0 (m), the peak's image position (m) and amplitude, and
        the SNR over the image's median magnitude (dB).
    """
    grid = products.grid
    pixels, floor = peaks.nlcs_peaks(products, settings, footprint)
    rows, spectrum, interpolant = refine.nlcs_interpolant(products)
    cells = distinct_cells([interpolant.maximise(float(i), float(j)) for i, j in pixels])
    if footprint is not None and cells:  # a peak past where the focus-position map reaches cannot be placed
        t_n = calibration.peak_track_times(products, [c[0] for c in cells], [c[1] for c in cells], focuser)[2]
        placed = np.isfinite(t_n)
        cells = [c for c, ok in zip(cells, placed) if ok]
    if not cells:
        return []
    cancelling = settings.neighbour_cancellation_passes > 0 and len(cells) > 1
    model = None
    if scan is not None and (cancelling or settings.synthesis_passes > 0):
        model = cancel.NlcsModel.of(products, scan, focuser, rows, spectrum)
    n, pairs = _modelled(len(cells), settings), []
    if cancelling and model is not None:
        cells, n, pairs = _cancel(cells, model, settings, floor)
    a, b = [c[0] for c in cells], [c[1] for c in cells]
    t_f, r, t_n = calibration.peak_track_times(products, a, b, focuser)
    if settings.synthesis_passes > 0 and model is not None:  # the modelled plates, by synthesis (S1)
        t_f[:n], r[:n], t_n[:n] = synthesis.locate(cells[:n], model, settings.synthesis_passes,
                                                   settings.synthesis_tol_m, settings.neighbour_gain_degree,
                                                   {k for pair in pairs for k in pair})
    r0 = r - grid.speed_m_s * grid.sin_squint * t_n  # eq. (19), C12: r_LC = r_LRCM - v sin(theta_q) t_nc
    if footprint is not None and scan is not None:  # a split pair keeps its joint fit (S2)
        t_n, r0 = _beyond_rail_by_backprojection(scan, grid, t_n, r0, {k for pair in pairs for k in pair})
    found = [_detection(grid, float(t_n[i]), float(r0[i]), grid.speed_m_s * float(t_f[i]), float(r[i]),
                        abs(val), floor) for i, (_, _, val) in enumerate(cells)]
    if footprint is not None and scan is not None:  # two peaks past the rail may climb to one BP maximum
        split = {k for pair in pairs for k in pair}
        keep = distinct_positions(t_n * grid.speed_m_s, r0, [abs(c[2]) for c in cells],
                                  SAME_PEAK_CELLS * BP_SUBSCENE_CELL_M, exempt=split)
        found = [found[i] for i in keep]
        pairs = [(keep.index(i), keep.index(j)) for i, j in pairs]
    for i, j in pairs:  # the two plates of a split peak (S2) carry their distance
        apart = math.hypot(found[i].x_m - found[j].x_m, found[i].rc_m - found[j].rc_m)
        found[i], found[j] = (dataclasses.replace(found[k], split_separation_m=apart) for k in (i, j))
    # a peak the focus-position map does not reach has no place (NaN): it is not a detection
    found = [d for d in found if math.isfinite(d.x_m) and math.isfinite(d.rc_m)]
    return _in_range(_in_footprint(_beyond_rail(found, grid), grid, footprint), settings)


def detect_bp(products: bp.BackprojectionProducts, settings: DetectionSettings = DetectionSettings(),
              footprint: geo.BeamFootprint | None = None) -> list[Detection]:
    """Point targets of a backprojection image, in the pass's closest-approach coordinates.

    The image's pixels are already on (u = v t_n, r_LRCM): no focus-position calibration. Neighbour
    cancellation models the targets in the range-compressed echo the products carry
    (`cancel.BackprojectionModel`).

    Parameters
    ----------
    products : BackprojectionProducts
        The focused pass (`Focuser.backprojection_focus`).
    settings : DetectionSettings
        Floors, non-maximum suppression and neighbour cancellation.
    footprint : BeamFootprint, optional
        As `detect_nlcs` (the image must reach it: `peaks.search_extent_u_m`).

    Returns
    -------
    list of Detection
        As `detect_nlcs`.
    """
    grid = products.grid
    du = products.u_axis_m[1] - products.u_axis_m[0]
    dr = products.r_axis_m[1] - products.r_axis_m[0]
    pixels, floor = peaks.bp_peaks(products, settings, footprint)
    value = refine.bp_evaluator(products, products.compressed)
    step = refine.BP_SIMPLEX_STEP_CELLS
    cells = distinct_cells([refine.maximise_nelder_mead(value, float(i), float(j), step=step)
                            for i, j in pixels])
    if settings.neighbour_cancellation_passes > 0 and len(cells) > 1:
        cells = _cancel(cells, cancel.BackprojectionModel(products), settings)[0]
    out = []
    for a, b, val in cells:
        u = products.u_axis_m[0] + a * du
        r = products.r_axis_m[0] + b * dr
        t_n = u / grid.speed_m_s
        out.append(_detection(grid, t_n, r - grid.sin_squint * u, u, r, abs(val), floor))
    return _in_range(_beyond_rail(out, grid), settings)


def pass_search(scan: ScanPass, settings: DetectionSettings) -> str:
    """The search region of one pass: `settings.search`, with "auto" taken as "footprint" on a track (the
    extent of the pulse positions, m) shorter than `settings.short_track_m` and "rail" otherwise."""
    if settings.search != "auto":
        return settings.search
    x = scan.pulse_position_m
    return "footprint" if float(x.max() - x.min()) < settings.short_track_m else "rail"


def search_footprint(scan: ScanPass, settings: DetectionSettings) -> geo.BeamFootprint | None:
    """The beam footprint `settings.search` asks for (docs/method.md section 4): None for "rail", else the
    pass's footprint to the beam's -3 dB edges ("footprint") or first nulls ("main_lobe"), from the rail's
    extent about the aperture centre, the rotation table angle and the beam the focusing processes (C6b).
    "auto" as `pass_search` resolves it."""
    search = pass_search(scan, settings)
    if search == "rail":
        return None
    edge = {"footprint": "3db", "main_lobe": "null"}.get(search)
    if edge is None:
        raise ValueError(f"unknown detection search region {search!r} (auto|rail|footprint|main_lobe)")
    x = scan.pulse_position_m - scan.aperture_centre_m
    return geo.pass_footprint(float(x.min()), float(x.max()),
                              scan.geometry.rotation_table_angle_rad, nlcs.beam_aperture_m(scan),
                              scan.radar.wavelength_m, edge)


def _cancel(cells: list[cancel.Cell], model: cancel.CancellationModel, settings: DetectionSettings,
            floor: float | None = None) -> tuple[list[cancel.Cell], int, list[tuple[int, int]]]:
    """Neighbour cancellation of the strongest `cancel_max_targets` cells (all when 0; `cells` are strongest
    first) within `cancel_time_budget_s` (0: none); the others keep their first refinement. Then, with
    `split_merged` and an NLCS model, a second plate added where a modelled peak holds two (`split`, eq. S2),
    after the modelled ones; `floor` is the image's noise level (`peaks.local_peaks`). Returns the cells, how
    many of the first are modelled and the split pairs' indices (`split.split_merged`)."""
    n = _modelled(len(cells), settings)
    if n < 2:
        return cells, n, []
    budget = settings.cancel_time_budget_s
    deadline = time.monotonic() + budget if budget > 0 else math.inf
    args = (settings.neighbour_cancellation_passes, settings.neighbour_cancellation_tol_m,
            settings.neighbour_gain_degree, deadline)
    modelled, residual = cancel.cancel_neighbours_with_residual(cells[:n], model, *args)
    pairs: list[tuple[int, int]] = []
    if settings.split_merged and isinstance(model, cancel.NlcsModel) and floor is not None \
            and residual is not None:
        threshold = peaks.detection_threshold(max(abs(c[2]) for c in cells), floor, settings)
        modelled, pairs = split.split_merged(
            modelled, residual, model, (settings.separation_m, settings.range_separation_m), threshold,
            peaks.detection_threshold(0.0, floor, settings), settings.neighbour_cancellation_tol_m,
            settings.neighbour_gain_degree, deadline)
    return modelled + cells[n:], len(modelled), pairs


def _beyond_rail(found: list[Detection], grid: nlcs.FocusGrid) -> list[Detection]:
    """Each detection with how far past the rail's nearer end the antenna was when it crossed the beam centre,
    v (|t_n| - half track) (`Detection.beyond_rail_m`, eq. L3): whatever the search, since the rail search's
    peaks are sought on the rail but refined where they are, and one refined past its end was seen through
    part of the aperture as a footprint search's is (an independent tester's plate 0.05 m past the end: its
    four heights' x all 5-12 mm off, one way)."""
    return [dataclasses.replace(d, beyond_rail_m=grid.speed_m_s * max(0.0, abs(d.t_n_s) - grid.half_track_s))
            for d in found]


def distinct_cells(cells: list[cancel.Cell], tol_cells: float = SAME_PEAK_CELLS) -> list[cancel.Cell]:
    """`cells` (fractional image indices and value) without those refined to within `tol_cells` of a
    stronger one: two pixel peaks of one broad or aliased response climb to the same sub-cell maximum, and
    the copy would be a second detection of the same target (and a singular pair in neighbour cancellation).
    Order kept."""
    keep = distinct_positions(np.array([c[0] for c in cells]), np.array([c[1] for c in cells]),
                              [abs(c[2]) for c in cells], tol_cells)
    return [cells[i] for i in keep]


def distinct_positions(x: np.ndarray, y: np.ndarray, strength: list[float], tol: float,
                       exempt: set[int] = frozenset()) -> list[int]:
    """Indices (ascending) of the points (x, y) left when each point within `tol` (Euclidean, the units of x
    and y) of a stronger one is dropped; ties keep the earlier; points in `exempt` are always kept and drop
    nothing."""
    order = sorted(range(len(strength)), key=lambda i: (-strength[i], i))
    kept: list[int] = []
    for i in order:
        if i in exempt or all(j in exempt or math.hypot(x[i] - x[j], y[i] - y[j]) > tol for j in kept):
            kept.append(i)
    return sorted(kept)


def _beyond_rail_by_backprojection(scan: ScanPass, grid: nlcs.FocusGrid, t_n_s: np.ndarray, r0_m: np.ndarray,
                                   split: set[int] = frozenset()) -> tuple[np.ndarray, np.ndarray]:
    """(t_n, r0) of NLCS detections beyond the rail's ends placed again on the backprojection sum (a
    subscene per detection: one processing squint focuses them poorly there, docs/method.md section 4),
    started from the NLCS estimate on a BP_SUBSCENE_CELL_M lattice; the others unchanged. The plates of a
    split peak (indices `split`) keep their joint fit: each alone would climb to the pair's one BP peak."""
    beyond = [i for i in np.flatnonzero(np.abs(t_n_s) > grid.half_track_s) if i not in split]
    if not beyond:
        return t_n_s, r0_m
    t_n_s, r0_m = t_n_s.copy(), r0_m.copy()
    rc = bp.range_compress(scan, grid)
    cell = BP_SUBSCENE_CELL_M
    for i in beyond:
        u0 = grid.speed_m_s * t_n_s[i]
        r_lrcm0 = r0_m[i] + grid.sin_squint * u0
        a, b, _ = refine.maximise_nelder_mead(
            lambda a, b, u0=u0, r_lrcm0=r_lrcm0: complex(bp.backproject_points(rc, grid, u0 + a * cell,
                                                                               r_lrcm0 + b * cell)),
            0.0, 0.0, step=refine.BP_SIMPLEX_STEP_CELLS)
        u = u0 + a * cell
        t_n_s[i], r0_m[i] = u / grid.speed_m_s, r_lrcm0 + b * cell - grid.sin_squint * u
    return t_n_s, r0_m


def _in_footprint(found: list[Detection], grid: nlcs.FocusGrid, footprint: geo.BeamFootprint | None
                  ) -> list[Detection]:
    """The NLCS detections whose own (t_n, r0) lie on the rail or in the footprint (the pixels were searched
    with a margin for the focus-position distortion, `peaks.NLCS_FOOTPRINT_MARGIN_M`)."""
    if footprint is None:
        return found
    u = np.array([grid.speed_m_s * d.t_n_s for d in found])
    r_lrcm = np.array([d.r0_m for d in found]) + grid.sin_squint * u
    keep = peaks.in_search(grid, u, r_lrcm, footprint) if found else []
    return [d for d, k in zip(found, keep) if k]


def _modelled(n_cells: int, settings: DetectionSettings) -> int:
    """How many of the strongest peaks are modelled (neighbour cancellation, location by synthesis): all, or
    `cancel_max_targets`."""
    return n_cells if settings.cancel_max_targets <= 0 else min(settings.cancel_max_targets, n_cells)


def _in_range(found: list[Detection], settings: DetectionSettings) -> list[Detection]:
    """The detections whose exact R_c is in the region of interest (the pixels were gated on an estimate)."""
    if settings.min_range_m <= 0 and settings.max_range_m <= 0:
        return found
    keep = peaks.range_of_interest(np.array([d.rc_m for d in found]), settings)
    return [d for d, k in zip(found, keep) if k]


def _detection(grid: nlcs.FocusGrid, t_n: float, r0: float, image_az: float, image_r: float, amp: float,
               floor: float) -> Detection:
    """A peak at P1 coordinates (t_n, r0) as a Detection: x_M = x_c + v t_n + r0 sin(theta_q),
    R_c = r0 cos(theta_q) (docs/method.md section 1)."""
    x_rel = grid.speed_m_s * t_n + r0 * grid.sin_squint
    return Detection(x_m=grid.aperture_centre_m + x_rel, rc_m=r0 * grid.cos_squint, t_n_s=t_n, r0_m=r0,
                     image_azimuth_m=image_az, image_range_m=image_r, amplitude=amp,
                     snr_db=20 * math.log10(amp / floor) if floor > 0 else math.inf)
