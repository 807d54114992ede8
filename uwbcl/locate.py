"""3-D location of a bolt plate from its passes at N >= 2 heights (paper section 3, eqs. 20-23 generalised).

Each pass i at rail height h_i gives the target's along-track position x_i and closest-approach range R_c,i.
With the rib at distance W and the target at height z, R_c,i^2 = W^2 + (z - h_i)^2, i.e.

    R_c,i^2 - h_i^2 = c0 - 2 z h_i,   c0 = W^2 + z^2        (linear least squares in c0, z)

which is exact for any target height and any number of heights (eqs. 20-23 are the special case N = 2 with a
common t_n; docs/method.md C13). P = (mean x_i, sign * W, z) in the radar frame.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize

from .archive import height_mm
from .geometry import closest_approach_range_m
from .records import AssociationSettings, Detection, DetectionSettings, Located

# Cross-height association gates (`associate_across_heights`): their one home is DetectionSettings, where a
# site can set them ([detection] cross_height_x_tol_m, cross_height_rc_tol_m, cross_height_wall_tol_m).
CROSS_HEIGHT_X_TOL_M = DetectionSettings.cross_height_x_tol_m
CROSS_HEIGHT_RC_TOL_M = DetectionSettings.cross_height_rc_tol_m
CROSS_HEIGHT_WALL_TOL_M = DetectionSettings.cross_height_wall_tol_m
# Eq. L2 needs the cycle's wall distance: from at least this many plates grouped without it (fewer, and one
# wrong grouping could set it),
WALL_MIN_PLATES = 3
# and a rib rougher than the gate: the gate widens to this many robust standard deviations (1.4826 x MAD) of
# the wall distances about W of those plates whose pairing was unambiguous (an undulating rib, +-0.3 m over a
# few metres, is ordinary in a gate road: with the 0.15 m gate it lost every plate more than 0.2 m off the
# median wall; a bolting ring's phantoms, most of a first grouping at times, must not widen it)
WALL_SPREAD_SIGMAS = 3.0
_GATED = 1e6  # the assignment cost of a pair outside either gate: never chosen over a gated-in pair
# Eq. L1 (`shared_look`): a neighbour predicted within this many of the detector's non-maximum-suppression
# ellipses of a detection, and not detected on its own in that pass, shares the detection's peak. At 1.0 the
# two would have been one peak by construction; up to ~1.5 the two responses still overlap enough to pull the
# peak by centimetres (measured: 2 cm at 1.2 resolution cells, a 1.2 GHz radar).
SHARED_LOOK_REACH = 1.5
# and only a neighbour of at least this fraction of the detection's amplitude: a weaker one moves the peak by
# less than about ratio x offset, millimetres
SHARED_LOOK_MIN_AMPLITUDE = 0.1
# Eq. S3: the standard deviation of a look split from a peak that held two plates (eq. S2), in units of a lone
# plate's (association.range_sigma_m), along track and in range. Measured against the availability study's
# truth (docs/method.md section 5): split looks 7.7 / 7.2 mm RMS in x / R_c against 3.7 / 3.1 mm for lone
# plates (dense-3h, 10 dB), with tails to 37 mm; 3 covers the bulk, and eq. M6 widens the tails.
SPLIT_SIGMA_FACTOR = 3.0
# Eq. L3: a look found beyond the rail's end (a footprint search, detect.search_footprint) is seen through
# part of the aperture. Measured against the truth of 13 footprint runs (the availability study's generator,
# rails 1.5-3.5 m), x / R_c RMS: 5.4 / 5.2 mm on the rail, 9.2 / 9.3 within 0.2 m past its end, 9.3 / 10.5
# at 0.2-0.5 m, 10.3 / 17.5 at 0.5-1 m, 15 / 23 beyond; 1 + 3 sqrt(b) (1.95 at 0.1 m, 3.6 at 0.75, 4.7 at
# 1.5 m) covers them.
BEYOND_RAIL_SIGMA_PER_SQRT_M = 3.0


def locate_target(heights_m, x_m, rc_m, weights=None, boresight_y_sign: int = -1) -> Located | None:
    """Least-squares position from per-height (x, R_c); None when the ranges admit no real solution."""
    h = np.asarray(heights_m, dtype=float)
    x = np.asarray(x_m, dtype=float)
    rc = np.asarray(rc_m, dtype=float)
    if h.size < 2 or np.ptp(h) <= 0:
        return None
    w = np.ones_like(h) if weights is None else np.asarray(weights, dtype=float)
    a = np.column_stack([np.ones_like(h), -2.0 * h]) * np.sqrt(w)[:, None]
    (c0, z), *_ = np.linalg.lstsq(a, (rc**2 - h**2) * np.sqrt(w), rcond=None)
    wall2 = c0 - z * z
    if wall2 <= 0:
        return None
    wall = math.sqrt(wall2)
    x_hat = float(np.average(x, weights=w))
    misfit = np.concatenate([np.hypot(wall, z - h) - rc, x - x_hat])
    return Located(position_m=np.array([x_hat, boresight_y_sign * wall, z]),
                   residual_m=float(np.sqrt(np.mean(misfit**2))), n_passes=int(h.size), amplitude=0.0)


def look_sigma_factor(det: Detection) -> float:
    """A look's standard deviation in units of a lone plate's on the rail: SPLIT_SIGMA_FACTOR for one of the
    two plates of a split peak (eq. S3), times 1 + BEYOND_RAIL_SIGMA_PER_SQRT_M sqrt(b) for a plate found b m
    beyond the rail's end (eq. L3)."""
    split = 1.0 if math.isnan(det.split_separation_m) else SPLIT_SIGMA_FACTOR
    return split * beyond_rail_factor(det)


def beyond_rail_factor(det: Detection) -> float:
    """Eq. L3: 1 + BEYOND_RAIL_SIGMA_PER_SQRT_M sqrt(b / 1 m) for a look b m past the rail's end (1 on it)."""
    return 1.0 + BEYOND_RAIL_SIGMA_PER_SQRT_M * math.sqrt(det.beyond_rail_m)


def misfit_scale(plate: Located, range_sigma_m: float) -> float:
    """Eq. M6: max(1, chi^2 / dof) of a plate's own fit. Its 2n misfits (n per-height ranges to the located
    point, n per-height along-track x to their mean) have sigma_R each (times `look_sigma_factor` for a split
    look, eq. S3) and dof = (n - 2) + (n - 1); without its looks, chi^2 = 2n rho^2 / sigma_R^2 from their RMS
    `Located.residual_m`. Passes that do not meet at one point (two plates grouped across heights, one
    height's peak on noise or a neighbour) are not the point the plate's covariance describes: it is as
    uncertain as its own misfit says."""
    dof = 2 * plate.n_passes - 3
    if dof <= 0 or range_sigma_m <= 0:
        return 1.0
    if not plate.looks:
        return max(1.0, 2 * plate.n_passes * plate.residual_m**2 / (range_sigma_m**2 * dof))
    chi2 = 0.0
    for h, d in plate.looks:
        miss_r = float(closest_approach_range_m(plate.position_m, h)) - d.rc_m
        miss_x = d.x_m - float(plate.position_m[0])
        chi2 += (miss_r**2 + miss_x**2) / (look_sigma_factor(d) * range_sigma_m) ** 2
    return max(1.0, chi2 / dof)


def two_look_wall_m(h_a, rc_a, sigma_a, h_b, rc_b, sigma_b) -> tuple[np.ndarray, np.ndarray]:
    """Eq. L2: the wall distance W (m) of the one point that two looks (rail height h, range R_c, its standard
    deviation sigma; m, arrays that broadcast, h_a != h_b) put on a rib parallel to the rail, and W's standard
    deviation (first order: D2's propagation for two heights, `displacement.location_covariance_m2`, in
    closed form so that every pair of a cycle's looks is one array operation). NaN where the two ranges meet
    at no real point.

    C13 with two heights: z = ((R_a^2 - h_a^2) - (R_b^2 - h_b^2)) / (2 (h_b - h_a)),
    W^2 = R_a^2 - (z - h_a)^2.
    """
    h_a, rc_a, h_b, rc_b = (np.asarray(v, dtype=float) for v in (h_a, rc_a, h_b, rc_b))
    dh = h_b - h_a
    z = ((rc_a**2 - h_a**2) - (rc_b**2 - h_b**2)) / (2.0 * dh)
    w2 = rc_a**2 - (z - h_a) ** 2
    wall = np.sqrt(np.where(w2 > 0, w2, np.nan))
    dz_a, dz_b = rc_a / dh, -rc_b / dh
    dw_a = (rc_a - (z - h_a) * dz_a) / wall
    dw_b = -(z - h_a) * dz_b / wall
    return wall, np.hypot(dw_a * sigma_a, dw_b * sigma_b)


def _gate_terms(a_dets: list[Detection], h_a: float, b_dets: list[Detection], h_b: float, x_tol_m: float,
                rc_tol_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The cross-height grouping's gate terms of every pair of looks of two heights, (n_a, n_b) each:
    |dx| / x_tol and |dR_c| / (|dh| + rc_tol); a pair is inside the gates where both are <= 1."""
    dx = np.abs(np.subtract.outer([a.x_m for a in a_dets], [b.x_m for b in b_dets])) / x_tol_m
    dr = np.abs(np.subtract.outer([a.rc_m for a in a_dets], [b.rc_m for b in b_dets])) / (abs(h_b - h_a)
                                                                                          + rc_tol_m)
    return dx, dr


def associate_across_heights(detections_by_height: dict[float, list[Detection]],
                             x_tol_m: float = CROSS_HEIGHT_X_TOL_M, rc_tol_m: float = CROSS_HEIGHT_RC_TOL_M,
                             wall_m: float | None = None, wall_tol_m: float = CROSS_HEIGHT_WALL_TOL_M,
                             range_sigma_m: float = AssociationSettings.range_sigma_m
                             ) -> list[dict[float, Detection]]:
    """Group the detections of one plate across the passes of one cycle.

    A plate has the same along-track x from every height, and its R_c changes by at most the height
    difference, so each height is matched to the reference height (the one with most detections) by an optimal
    assignment on (dx / x_tol)^2 + (dR_c / (|dh| + rc_tol))^2, gated at 1 per term.

    With the cycle's wall distance `wall_m` (m) the pair's point must also lie on the rib (eq. L2): the term
    (dW / max(wall_tol_m, 3 sigma_W))^2, gated at 1 too, where dW is its wall distance (`two_look_wall_m`,
    each look's sigma `range_sigma_m` x `look_sigma_factor`) minus `wall_m`. In a column of plates
    (a bolting ring) every detection of one height is within the x and R_c gates of every detection of the
    other; only the rib tells which pairs are one plate.
    """
    heights = sorted(detections_by_height)
    if not heights:
        return []
    ref_h = max(heights, key=lambda h: len(detections_by_height[h]))
    ref = detections_by_height[ref_h]
    groups = [{ref_h: d} for d in ref]
    for h in heights:
        other = detections_by_height[h]
        if h == ref_h or not other or not ref:
            continue
        dx, dr = _gate_terms(ref, ref_h, other, h, x_tol_m, rc_tol_m)
        cost = dx**2 + dr**2
        inside = (dx <= 1) & (dr <= 1)
        if wall_m is not None and wall_tol_m > 0:
            sig_a = range_sigma_m * np.array([look_sigma_factor(a) for a in ref])[:, None]
            sig_b = range_sigma_m * np.array([look_sigma_factor(b) for b in other])[None, :]
            wall, sigma = two_look_wall_m(ref_h, np.array([a.rc_m for a in ref])[:, None], sig_a,
                                          h, np.array([b.rc_m for b in other])[None, :], sig_b)
            dw = np.abs(wall - wall_m) / np.maximum(wall_tol_m, 3.0 * sigma)  # NaN: no real point, no plate
            cost, inside = cost + np.nan_to_num(dw) ** 2, inside & (dw <= 1)
        gated = np.where(inside, cost, _GATED)
        for i, j in zip(*optimize.linear_sum_assignment(gated)):
            if gated[i, j] < _GATED:
                groups[i][h] = other[j]
    return [g for g in groups if len(g) >= 2]


def _wall_m(located: list[tuple[dict[float, Detection], Located]], tol_m: float = CROSS_HEIGHT_WALL_TOL_M,
            x_tol_m: float = CROSS_HEIGHT_X_TOL_M) -> float:
    """The cycle's wall distance (m): the median |y| of its located plates but their shadows. A shadow lies
    more than tol_m behind another located plate at the same x (within x_tol_m): an echo that bounced off
    the floor or the roof on its way is longer than the plate's own and locates behind it, where no plate is
    (the plates of a bolting ring share x but not |y|). An independent tester's floor multipath put as many
    such copies 0.3 m behind the rib as there were plates, the median of all of them among the copies, and
    the rib gate then kept the copies and set the plates aside; noise or a reflector in front of the rib, a
    stepped rib and a rail a little off parallel to it cast no shadows, and their median is what it was."""
    w = np.array([abs(p.position_m[1]) for _, p in located])
    x = np.array([p.position_m[0] for _, p in located])
    shadow = np.any((np.abs(x[:, None] - x[None, :]) <= x_tol_m) & (w[None, :] < w[:, None] - tol_m), axis=1)
    return float(np.median(w[~shadow] if tol_m > 0 and not shadow.all() else w))


def wall_gate_m(located: list[tuple[dict[float, Detection], Located]], tol_m: float = CROSS_HEIGHT_WALL_TOL_M,
                clear: list[bool] | None = None, x_tol_m: float = CROSS_HEIGHT_X_TOL_M
                ) -> tuple[float, float]:
    """Eq. L2's wall distance W (m, `_wall_m`) and gate (m) from a first grouping's plates: `tol_m`, widened
    to WALL_SPREAD_SIGMAS robust standard deviations (1.4826 x MAD) of the wall distances about W of the
    plates whose grouping was `clear` (each look had one candidate at the group's other heights: a pairing
    of two plates of a bolting ring, a phantom, is not) where at least WALL_MIN_PLATES are (eq. L2b)."""
    wall = _wall_m(located, tol_m, x_tol_m)
    kept = [p for (_, p), c in zip(located, clear if clear is not None else [True] * len(located)) if c]
    if len(kept) < WALL_MIN_PLATES:
        return wall, tol_m
    w = np.array([abs(p.position_m[1]) for p in kept])
    return wall, max(tol_m, WALL_SPREAD_SIGMAS * 1.4826 * float(np.median(np.abs(w - wall))))


def _clear(group: dict[float, Detection], detections_by_height: dict[float, list[Detection]], x_tol_m: float,
           rc_tol_m: float) -> bool:
    """Whether each look of a cross-height group had exactly one candidate within the grouping's gates at each
    of the group's other heights (`associate_across_heights`): no other pairing was possible."""
    for h_a, a in group.items():
        for h_b in group:
            if h_b != h_a:
                dx, dr = _gate_terms([a], h_a, detections_by_height[h_b], h_b, x_tol_m, rc_tol_m)
                if np.count_nonzero((dx <= 1) & (dr <= 1)) != 1:
                    return False
    return True


def _located_group(group: dict[float, Detection], boresight_y_sign: int) -> Located | None:
    """`locate_target` on one cross-height group, with its looks and mean amplitude."""
    hs = sorted(group)
    dets = [group[h] for h in hs]
    loc = locate_target(hs, [d.x_m for d in dets], [d.rc_m for d in dets], boresight_y_sign=boresight_y_sign)
    if loc is None:
        return None
    return dataclasses.replace(loc, amplitude=float(np.mean([d.amplitude for d in dets])),
                               looks=tuple(zip(hs, dets)))


def _within_reach(x_m: float, rc_m: float, det: Detection, separation_m: tuple[float, float]) -> bool:
    """(x, R_c) within SHARED_LOOK_REACH non-maximum-suppression ellipses of a detection."""
    return ((x_m - det.x_m) / separation_m[0]) ** 2 + ((rc_m - det.rc_m) / separation_m[1]) ** 2 \
        <= SHARED_LOOK_REACH**2


def shared_look(height_m: float, det: Detection, others: list[Located],
                singles: list[tuple[float, Detection]], wall_m: float,
                separation_m: tuple[float, float]) -> bool:
    """Eq. L1 (docs/method.md section 5): is a plate's detection at one rail height shared with a neighbour?

    A neighbour shares it when that pass did not detect the neighbour on its own, the neighbour's predicted
    (x, R_c) at this height lies within SHARED_LOOK_REACH non-maximum-suppression ellipses (`separation_m`:
    along track, in range) of the detection, and it is at least SHARED_LOOK_MIN_AMPLITUDE of its amplitude:
    two responses that overlap make one peak between them. The neighbours are the other located plates (their
    R_c at this height from their position, C13) and the detections at other heights grouped with nothing
    (height unknown: both heights z = h' +- sqrt(R_c'^2 - W^2) on the rib at the cycle's wall distance W).
    """
    floor = SHARED_LOOK_MIN_AMPLITUDE * det.amplitude
    here = height_mm(height_m)  # rail heights are one height to the millimetre (the archive's names)
    for p in others:
        if p.amplitude < floor or any(height_mm(h) == here for h, _ in p.looks):
            continue
        if _within_reach(float(p.position_m[0]), float(closest_approach_range_m(p.position_m, height_m)), det,
                         separation_m):
            return True
    for h_other, e in singles:
        if e.amplitude < floor or height_mm(h_other) == here:
            continue
        dz = math.sqrt(max(e.rc_m**2 - wall_m**2, 0.0))
        if any(_within_reach(e.x_m, float(closest_approach_range_m((e.x_m, wall_m, z), height_m)), det,
                             separation_m) for z in (h_other + dz, h_other - dz)):
            return True
    return False


def locate_plates(detections_by_height: dict[float, list[Detection]], boresight_y_sign: int = -1,
                  x_tol_m: float = CROSS_HEIGHT_X_TOL_M, rc_tol_m: float = CROSS_HEIGHT_RC_TOL_M,
                  separation_m: tuple[float, float] | None = None,
                  range_sigma_m: float = AssociationSettings.range_sigma_m,
                  wall_tol_m: float = CROSS_HEIGHT_WALL_TOL_M) -> list[Located]:
    """Every plate seen at two or more heights, located in 3-D (`x_tol_m`, `rc_tol_m`, `wall_tol_m`: the
    cross-height association's gates, `associate_across_heights`). The detections are grouped twice when
    `wall_tol_m` > 0: the second time on the rib (eq. L2) at the median wall distance of the first grouping's
    plates, once it has WALL_MIN_PLATES, with the gate widened where they show a rougher rib (eq. L2b,
    `wall_gate_m`).

    With `separation_m` (the detector's non-maximum-suppression semi-axes along track and in range, m), a
    plate's looks shared with a neighbour (`shared_look`, eq. L1) or split from a peak that held two
    (`Detection.split_separation_m`, eq. S2: 3x less precise, eq. S3) are marked in `Located.shared_heights_m`
    and set aside where at least two clean looks remain and the plate's fit with them is worse than a range
    precision `range_sigma_m` explains (eq. M6: chi^2 / dof > 1, the misfit that would otherwise widen its
    covariance): a peak pulled between two plates is neither, and the clean looks locate the plate. A shared
    look the fit agrees with stays (setting it aside would only shorten the baseline), and so do the looks of
    a plate with fewer than two clean ones (two looks cannot show which of them is off). A split look is set
    aside wherever two clean looks remain, whatever the fit.
    """
    groups = associate_across_heights(detections_by_height, x_tol_m, rc_tol_m)
    located = [(g, p) for g in groups if (p := _located_group(g, boresight_y_sign)) is not None]
    if wall_tol_m > 0 and len(located) >= WALL_MIN_PLATES:
        clear = [_clear(g, detections_by_height, x_tol_m, rc_tol_m) for g, _ in located]
        wall_m, gate_m = wall_gate_m(located, wall_tol_m, clear, x_tol_m)
        groups = associate_across_heights(detections_by_height, x_tol_m, rc_tol_m, wall_m, gate_m,
                                          range_sigma_m)
        located = [(g, p) for g in groups if (p := _located_group(g, boresight_y_sign)) is not None]
    if separation_m is not None and located:
        grouped = {id(d) for g in groups for d in g.values()}
        singles = [(h, d) for h, dets in detections_by_height.items() for d in dets if id(d) not in grouped]
        # a single that overlaps a grouped detection of its own pass is that plate's side lobe, not a plate
        singles = [(h, d) for h, d in singles
                   if not any(_within_reach(d.x_m, d.rc_m, g[h], separation_m) for g in groups if h in g)]
        wall_m = _wall_m(located, wall_tol_m)
        screened = []
        for k, (g, p) in enumerate(located):
            others = [q for j, (_, q) in enumerate(located) if j != k]
            split = any(not math.isnan(d.split_separation_m) for d in g.values())
            shared = tuple(h for h in sorted(g) if not math.isnan(g[h].split_separation_m)
                           or shared_look(h, g[h], others, singles, wall_m, separation_m))
            clean = {h: d for h, d in g.items() if h not in shared}
            # a split look is set aside whatever the fit: its few mm of bias (S2) hide along the dilution
            # direction of a poor geometry, where the fit agrees with them
            pulled = shared and len(clean) >= 2 and (split or misfit_scale(p, range_sigma_m) > 1.0)
            refit = _located_group(clean, boresight_y_sign) if pulled else None
            screened.append(dataclasses.replace(refit or p, shared_heights_m=shared))
        plates = screened
    else:
        plates = [p for _, p in located]
    return sorted(plates, key=lambda p: p.position_m[0])
