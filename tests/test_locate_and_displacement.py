"""Specification of multi-height 3-D localisation (docs/method.md C13) and of the advance between cycles."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from uwbcl import batch, chain, locate
from uwbcl.displacement import estimate_advance, location_covariance_m2, robust_mean
from uwbcl.locate import (
    associate_across_heights,
    locate_plates,
    locate_target,
    misfit_scale,
    two_look_wall_m,
    wall_gate_m,
)
from uwbcl.records import AssociationSettings, CycleResult, Detection, DetectionSettings, Located


def _rc(wall, z, heights):
    return np.hypot(wall, z - np.asarray(heights, dtype=float))


def _detection(x, rc, amplitude=1.0):
    return Detection(x_m=x, rc_m=rc, t_n_s=0.0, r0_m=rc, image_azimuth_m=0.0, image_range_m=rc,
                     amplitude=amplitude, snr_db=40.0)


def _plate(p):
    return Located(position_m=np.asarray(p, dtype=float), residual_m=0.0, n_passes=2, amplitude=1.0)


# --------------------------------------------------------------------------------------------- locate
@pytest.mark.parametrize("heights", [(0.15, 0.30), (0.05, 0.25, 0.65)], ids=["2 heights", "3 heights"])
@pytest.mark.parametrize("wall, z", [(2.4, 0.30), (2.0, 1.6), (1.9, -0.2)])
def test_least_squares_recovers_height_and_wall_distance_exactly_from_noise_free_ranges(heights, wall, z):
    loc = locate_target(heights, [1.386] * len(heights), _rc(wall, z, heights))
    assert loc is not None
    # the LS model R_c^2 - h^2 = c0 - 2 z h is exact, so only round-off remains
    np.testing.assert_allclose(loc.position_m, [1.386, -wall, z], rtol=0, atol=1e-9)
    assert loc.residual_m < 1e-9
    assert loc.n_passes == len(heights)


def test_wall_side_follows_the_boresight_sign():
    loc = locate_target((0.15, 0.30), (1.0, 1.0), _rc(2.4, 0.3, (0.15, 0.30)), boresight_y_sign=+1)
    assert loc.position_m[1] == pytest.approx(2.4, abs=1e-9)


def test_along_track_position_is_the_mean_of_the_per_height_positions():
    loc = locate_target((0.15, 0.30), (1.000, 1.004), _rc(2.4, 0.3, (0.15, 0.30)))
    assert loc.position_m[0] == pytest.approx(1.002, abs=1e-12)
    assert loc.residual_m > 0  # the x scatter shows in the misfit


def test_three_inconsistent_heights_leave_a_positive_residual():
    heights = (0.05, 0.25, 0.65)
    rc = _rc(2.0, 1.2, heights) + np.array([0.0, 0.004, 0.0])  # 4 mm range error on the middle pass
    loc = locate_target(heights, [1.678] * 3, rc)
    assert loc is not None
    # three equations, two unknowns: the misfit cannot vanish; it is of the order of the injected error
    assert 1e-4 < loc.residual_m < 4e-3


def test_an_impossible_geometry_or_a_single_height_gives_no_location():
    # R_c^2 - h^2 = c0 - 2 z h with R_c 1.0 at h = 0 and 3.0 at h = 0.1: z = -40, c0 = 1 < z^2
    assert locate_target((0.0, 0.1), (1.0, 1.0), (1.0, 3.0)) is None
    assert locate_target((0.15,), (1.0,), (2.4,)) is None
    assert locate_target((0.15, 0.15), (1.0, 1.0), (2.4, 2.4)) is None  # no vertical baseline


def test_association_pairs_plates_of_one_vertical_column_by_range():
    """sim2-like: D, E, F at one x, z = 0.4 / 1.2 / 1.6 m, wall 2.0 m, rail at 0.05 and 0.25 m."""
    heights = (0.05, 0.25)
    zs = (0.4, 1.2, 1.6)
    by_height = {h: [_detection(1.678, float(_rc(2.0, z, h)), amplitude=z) for z in zs] for h in heights}
    by_height[0.25] = by_height[0.25][::-1]  # order of detections carries no information
    groups = associate_across_heights(by_height)
    assert len(groups) == 3
    for g in groups:
        assert set(g) == set(heights)
        assert g[0.05].amplitude == g[0.25].amplitude  # the same plate (amplitude tags it here)
    plates = locate_plates(by_height)
    np.testing.assert_allclose(sorted(p.position_m[2] for p in plates), zs, rtol=0, atol=1e-9)
    for p in plates:
        assert p.position_m[1] == pytest.approx(-2.0, abs=1e-9)


def _ring(heights, wall, zs, x=1.0):
    """Detections of one bolting ring (plates at zs m, one x) on a rib `wall` m away, plus two lone plates
    along the rib that give the cycle its wall distance."""
    return {h: [_detection(x, float(_rc(wall, z, h)), 1.0) for z in zs]
            + [_detection(x0, float(_rc(wall, 0.9, h)), 1.0) for x0 in (3.0, 4.5)] for h in heights}


def test_the_rib_gate_rejects_a_cross_height_pair_that_would_put_a_plate_off_the_rib():
    """A ring of three plates (z 0.5 / 1.1 / 1.7 m) on a 1.82 m rib from rail heights 0.107 and 0.675 m, the
    lowest plate merged into the middle one at 0.675 m (their ranges 4 cm apart). Without the rib, x and R_c
    pair the middle plate at 0.107 m with the top one at 0.675 m (R_c 5 mm apart): a plate 0.25 m off the rib
    and 0.5 m off in height. On the rib (eq. L2) the pairs are the true ones."""
    heights, wall = (0.107, 0.675), 1.82
    by_height = _ring(heights, wall, (0.5, 1.1, 1.7))
    merged = float(np.mean(_rc(wall, np.array([0.5, 1.1]), 0.675)))
    by_height[0.675] = [_detection(1.0, merged, 1.0), *by_height[0.675][2:]]
    plain = locate_plates(by_height, wall_tol_m=0.0)
    ring = [p for p in plain if p.position_m[0] < 2]
    assert max(abs(abs(p.position_m[1]) - wall) for p in ring) > 0.2  # the pairing without the rib
    on_rib = [p for p in locate_plates(by_height) if p.position_m[0] < 2]
    assert len(on_rib) == 2
    assert max(abs(abs(p.position_m[1]) - wall) for p in on_rib) < 0.05
    # the top plate exactly; the merged look puts the other between its two plates
    assert min(abs(p.position_m[2] - 1.7) for p in on_rib) < 1e-6


def test_the_rib_is_the_median_of_the_plates_not_of_the_multipath_copies_behind_them():
    """Four plates on a 2.4 m rib and, at each plate's x, what an independent tester's floor multipath located
    there: the once-bounced echo's point 0.3 m behind the rib and a second copy 0.85 m behind (its cycles held
    as many copies as plates). The median of all of them lay among the copies; the rib gate then kept the
    copies and set every plate aside."""
    heights, wall = (0.2, 0.6), 2.4
    plates = [(0.5, 0.9), (1.6, 1.9), (2.7, 0.9), (3.8, 1.9)]
    points = [(x, wall, z, 1.0) for x, z in plates] + [(x, wall + 0.3, z - 1.0, 0.6) for x, z in plates] \
        + [(x, wall + 0.85, z - 1.5, 0.4) for x, z in plates]
    by_height = {h: [_detection(x, float(_rc(w, z, h)), a) for x, w, z, a in points] for h in heights}
    located = locate_plates(by_height)
    for x, z in plates:
        assert any(np.allclose(p.position_m, [x, -wall, z], atol=1e-6) for p in located), (x, z)
    assert all(abs(abs(p.position_m[1]) - wall) < 0.16 for p in located)  # the copies set aside


_XS = np.arange(8) * 1.3


@pytest.mark.parametrize("points", [
    [(x, 2.30 + 0.25 * k / 7, 0.9 if k % 2 else 1.6, 1.0) for k, x in enumerate(_XS)],  # rail off parallel
    [(x, 2.4 if k < 4 else 2.6, 0.9 if k % 2 else 1.6, 1.0) for k, x in enumerate(_XS)],  # a stepped rib
    [(x, 2.4, 0.9 if k % 2 else 1.6, 1.0) for k, x in enumerate(_XS[:3])]
    + [(5.0, 1.9, 1.0, 0.55), (6.1, 2.0, 1.3, 0.55)],  # weak noise met across heights in front of the rib
    [(x, 2.4, 0.9 if k % 2 else 1.6, 1.0) for k, x in enumerate(_XS[:6])]
    + [(0.6, 1.6, 1.2, 2.0), (3.2, 1.6, 1.2, 2.0)],  # two strong reflectors in front of it
], ids=["rail off parallel", "stepped rib", "noise in front", "reflectors in front"])
def test_what_casts_no_shadow_leaves_the_rib_gate_keeping_every_plate(points):
    # a review of the first multipath rule (the nearest strong cluster): each of these lost plates to it
    heights = (0.2, 0.6)
    by_height = {h: [_detection(x, float(_rc(w, z, h)), a) for x, w, z, a in points] for h in heights}
    located = locate_plates(by_height)
    plates = [(x, w, z) for x, w, z, a in points if a == 1.0]
    for x, w, z in plates:
        assert any(np.allclose(p.position_m, [x, -w, z], atol=1e-6) for p in located), (x, w, z)


def test_an_undulating_rib_widens_the_rib_gate_and_keeps_its_plates():
    """An independent tester's rib wandered +-0.3 m over a few metres (a 3 m wave and its 1.35 m partner, two
    staggered rows): the 0.15 m gate about the median wall set aside every plate more than 0.2 m off it. The
    gate now widens to the plates' own spread (eq. L2b); the ring of the test above keeps its 0.15 m gate."""
    heights = (0.2, 0.6)
    xs = np.arange(10) * 0.55
    walls = 2.4 + 0.3 * (np.sin(2 * np.pi * xs / 3.0 + 0.4) + 0.4 * np.sin(2 * np.pi * xs / 1.35 + 1.0)) / 1.4
    points = [(x, w, 0.45 if k % 2 else 1.15) for k, (x, w) in enumerate(zip(xs, walls))]
    by_height = {h: [_detection(x, float(_rc(w, z, h))) for x, w, z in points] for h in heights}
    located = locate_plates(by_height)
    assert max(abs(walls - np.median(walls))) > 0.25
    for x, w, z in points:
        assert any(np.allclose(p.position_m, [x, -w, z], atol=1e-6) for p in located), (x, w, z)
    flat = {h: [_detection(x, float(_rc(2.4 + 0.01 * (k % 3), z, h))) for k, (x, _, z) in enumerate(points)]
            for h in heights}
    first = [(g, locate_target(sorted(g), [g[h].x_m for h in sorted(g)], [g[h].rc_m for h in sorted(g)]))
             for g in associate_across_heights(flat)]
    assert wall_gate_m(first, 0.15)[1] == 0.15
    # bolting rings on a flat rib whose first grouping is mostly phantoms (a review: the gate widened to
    # 0.3 m and let them through): their pairings were ambiguous, and the gate stays
    wall, zs = 2.3, np.array([0.5, 1.1, 1.7])
    rings = {h: [] for h in heights}
    for x in (1.0, 2.5, 4.0):
        rings[0.2] += [_detection(x, float(r)) for r in _rc(wall, zs, 0.2)]
        r = _rc(wall, zs, 0.6)
        rings[0.6] += [_detection(x, float((r[0] + r[1]) / 2)), _detection(x, float(r[2]))]
    first = [(g, locate_target(sorted(g), [g[h].x_m for h in sorted(g)], [g[h].rc_m for h in sorted(g)]))
             for g in associate_across_heights(rings)]
    assert wall_gate_m(first, 0.15)[1] > 0.15  # every plate's spread: widened
    clear = [locate._clear(g, rings, locate.CROSS_HEIGHT_X_TOL_M, locate.CROSS_HEIGHT_RC_TOL_M)
             for g, _ in first]
    assert wall_gate_m(first, 0.15, clear)[1] == 0.15


def test_the_rib_gate_needs_three_plates_and_keeps_every_plate_of_a_clean_column():
    heights, wall = (0.05, 0.25, 0.6), 2.5
    by_height = _ring(heights, wall, (0.4, 1.0, 1.6))
    with_gate, without = locate_plates(by_height), locate_plates(by_height, wall_tol_m=0.0)
    assert len(with_gate) == len(without) == 5
    for a, b in zip(with_gate, without):
        np.testing.assert_allclose(a.position_m, b.position_m, atol=1e-9)
    two = {h: d[:1] + d[3:4] for h, d in by_height.items()}  # two plates: no wall distance, no gate
    assert len(locate_plates(two)) == 2


def test_the_wall_of_two_looks_and_its_sigma_match_finite_differences():
    h_a, h_b, wall, z = 0.2, 0.7, 2.0, 1.1
    ra, rb = float(_rc(wall, z, h_a)), float(_rc(wall, z, h_b))
    w, sigma = two_look_wall_m(h_a, ra, 0.003, h_b, rb, 0.004)
    assert w == pytest.approx(wall, abs=1e-12)
    e = 1e-7
    ga = (two_look_wall_m(h_a, ra + e, 0, h_b, rb, 0)[0] - w) / e
    gb = (two_look_wall_m(h_a, ra, 0, h_b, rb + e, 0)[0] - w) / e
    assert sigma == pytest.approx(np.hypot(0.003 * ga, 0.004 * gb), rel=1e-5)
    # the same first-order propagation as a two-height plate's covariance (D2), written in closed form
    cov = location_covariance_m2((0.0, -wall, z), (h_a, h_b), (0.003, 0.004))
    assert sigma == pytest.approx(np.sqrt(cov[1, 1]), rel=1e-9)
    assert np.isnan(two_look_wall_m(0.0, 1.0, 0.0, 0.1, 3.0, 0.0)[0])  # the ranges meet nowhere


def test_association_leaves_a_plate_seen_at_one_height_unlocated():
    by_height = {0.15: [_detection(0.786, 2.405), _detection(1.386, 2.405)], 0.30: [_detection(0.786, 2.4)]}
    groups = associate_across_heights(by_height)
    assert len(groups) == 1
    assert groups[0][0.30].x_m == 0.786 and groups[0][0.15].x_m == 0.786


SEPARATION_M = (DetectionSettings.separation_m, DetectionSettings.range_separation_m)


def _column_scene(heights, seen_q, pull_m, pull_x_m=0.01):
    """Plate P (x 1.0, z 0.6) under a neighbour Q (x 1.04, z 1.3) on a rib 2.0 m away, and a plate R far along
    the rib. Q is detected at the heights in `seen_q`; at the others its response merges with P's, whose peak
    is pulled by `pull_m` (per height) towards Q."""
    p, q, r = (1.0, 2.0, 0.6), (1.04, 2.0, 1.3), (3.0, 2.0, 0.9)
    by_height = {}
    for h in heights:
        dets = [_detection(r[0], float(_rc(r[1], r[2], h)), 0.8)]
        if h in seen_q:
            dets += [_detection(p[0], float(_rc(p[1], p[2], h)), 1.0),
                     _detection(q[0], float(_rc(q[1], q[2], h)), 0.6)]
        else:
            dets.append(_detection(p[0] + pull_x_m, float(_rc(p[1], p[2], h)) + pull_m[h], 1.0))
        by_height[h] = dets
    return by_height, np.array([p[0], -p[1], p[2]])


def test_a_peak_shared_with_a_located_neighbour_is_set_aside_and_the_plate_located_from_its_clean_looks():
    heights = (0.24, 0.45, 0.66)
    by_height, truth = _column_scene(heights, seen_q=heights[:2], pull_m={0.66: 0.02})
    plain = min(locate_plates(by_height), key=lambda p: np.linalg.norm(p.position_m - truth))
    assert np.linalg.norm(plain.position_m - truth) > 0.01  # the merged peak spoils the 3-height fit
    plates = locate_plates(by_height, separation_m=SEPARATION_M)
    plate = min(plates, key=lambda p: np.linalg.norm(p.position_m - truth))
    np.testing.assert_allclose(plate.position_m, truth, atol=1e-9)
    assert plate.shared_heights_m == (0.66,) and plate.n_passes == 2
    assert [h for h, _ in plate.looks] == [0.24, 0.45]
    assert len(plates) == 3 and sum(bool(p.shared_heights_m) for p in plates) == 1


def test_a_look_split_from_a_peak_that_held_two_is_set_aside_even_where_the_fit_agrees():
    """Q detected on its own at every height, but at 0.66 m P and Q come from one split peak (eq. S2): P's
    look there is 6 mm off and marked. The 3-height fit hides that along the dilution direction (it passes M6)
    while moving P by centimetres; with two clean looks left, the split look is set aside."""
    heights = (0.24, 0.45, 0.66)
    by_height, truth = _column_scene(heights, seen_q=heights, pull_m={})
    split = {h: [dataclasses.replace(d, rc_m=d.rc_m + 0.006, split_separation_m=0.1)
                 if h == 0.66 and d.amplitude == 1.0 else d for d in dets] for h, dets in by_height.items()}
    plain = min(locate_plates(split), key=lambda p: np.linalg.norm(p.position_m - truth))
    assert np.linalg.norm(plain.position_m - truth) > 0.01
    assert misfit_scale(plain, AssociationSettings.range_sigma_m) == 1.0
    plate = min(locate_plates(split, separation_m=SEPARATION_M),
                key=lambda p: np.linalg.norm(p.position_m - truth))
    np.testing.assert_allclose(plate.position_m, truth, atol=1e-9)
    assert plate.shared_heights_m == (0.66,) and plate.n_passes == 2


def test_a_shared_peak_the_fit_agrees_with_is_kept():
    """Unpulled, the shared look fits the others: setting it aside would only shorten the baseline."""
    heights = (0.24, 0.45, 0.66)
    by_height, truth = _column_scene(heights, seen_q=heights[:2], pull_m={0.66: 0.0005}, pull_x_m=0.0)
    plate = min(locate_plates(by_height, separation_m=SEPARATION_M),
                key=lambda p: np.linalg.norm(p.position_m - truth))
    assert plate.shared_heights_m == (0.66,) and plate.n_passes == 3


def test_a_neighbour_seen_at_one_height_only_is_placed_on_the_rib_to_find_the_peaks_it_shares():
    heights = (0.24, 0.45, 0.66)
    by_height, truth = _column_scene(heights, seen_q=(0.24,), pull_m={0.45: 0.015, 0.66: -0.012})
    plate = min(locate_plates(by_height, separation_m=SEPARATION_M),
                key=lambda p: np.linalg.norm(p.position_m - truth))
    # one clean look is not a location: the shared ones are kept, and marked
    assert plate.shared_heights_m == (0.45, 0.66) and plate.n_passes == 3


def test_a_shared_peak_is_kept_when_fewer_than_two_clean_looks_remain():
    heights = (0.24, 0.66)
    by_height, truth = _column_scene(heights, seen_q=(0.24,), pull_m={0.66: 0.02})
    plate = min(locate_plates(by_height, separation_m=SEPARATION_M),
                key=lambda p: np.linalg.norm(p.position_m - truth))
    assert plate.shared_heights_m == (0.66,) and plate.n_passes == 2


def test_resolved_or_weak_neighbours_share_nothing():
    heights = (0.24, 0.45, 0.66)
    by_height, _ = _column_scene(heights, seen_q=heights, pull_m={})
    assert all(p.shared_heights_m == () for p in locate_plates(by_height, separation_m=SEPARATION_M))
    # a neighbour at a twentieth of the plate's amplitude, seen at one height only, pulls nothing that counts
    by_height, _ = _column_scene(heights, seen_q=(0.24,), pull_m={0.45: 0.0, 0.66: 0.0})
    weak = {h: [dataclasses.replace(d, amplitude=0.05) if d.amplitude == 0.6 else d for d in dets]
            for h, dets in by_height.items()}
    assert all(p.shared_heights_m == () for p in locate_plates(weak, separation_m=SEPARATION_M))


def test_a_plate_located_from_its_clean_looks_has_their_covariance_not_a_missed_heights():
    heights = (0.24, 0.45, 0.66)
    by_height, truth = _column_scene(heights, seen_q=heights[:2], pull_m={0.66: 0.02})
    cycle = CycleResult("rig", 0, "", heights, locate_plates(by_height, separation_m=SEPARATION_M))
    covs = chain.plate_covariances(cycle, 0.003)
    k = next(i for i, p in enumerate(cycle.plates) if p.shared_heights_m)
    p = cycle.plates[k]
    np.testing.assert_allclose(covs[k], location_covariance_m2(p.position_m, (0.24, 0.45), 0.003)
                               * chain.misfit_scale(p, 0.003), rtol=1e-12)


def test_a_per_height_sigma_gives_the_covariance_of_the_fit():
    """Eq. S3 through D2: one height's look three times less precise. The propagated covariance is the least
    squares' (Monte Carlo of locate_target), equal sigmas give the scalar's, and x's variance is that of the
    mean."""
    heights, wall, z = (0.24, 0.45, 0.66), 2.0, 1.1
    sigma = np.array([0.003, 0.009, 0.003])
    truth = np.array([0.5, -wall, z])
    cov = location_covariance_m2(truth, heights, sigma)
    np.testing.assert_allclose(location_covariance_m2(truth, heights, np.full(3, 0.003)),
                               location_covariance_m2(truth, heights, 0.003), rtol=1e-12)
    assert cov[0, 0] == pytest.approx(np.sum(sigma**2) / 9, rel=1e-12)
    rng = np.random.default_rng(3)
    rc = _rc(wall, z, heights)
    samples = np.array([locate_target(heights, 0.5 + rng.normal(0, sigma), rc + rng.normal(0, sigma))
                        .position_m for _ in range(4000)])
    # each sample covariance within 4 standard errors (sqrt(s_ii s_jj / n)) of the propagated one
    se = np.sqrt(np.outer(np.diag(cov), np.diag(cov)) / len(samples))
    assert np.all(np.abs(np.cov(samples.T) - cov) <= 4 * se), (np.cov(samples.T) - cov) / se
    # a look with three times the sigma widens the plate against all-equal looks (the middle height of three
    # carries no information on z's slope, so z's variance stays)
    equal = np.diag(location_covariance_m2(truth, heights, 0.003))
    assert np.all(np.diag(cov) >= equal * (1 - 1e-12)) and np.all(np.diag(cov)[:2] > equal[:2])


def test_a_plate_whose_looks_were_all_split_is_widened_not_moved():
    """Eq. S3: split looks that cannot be set aside (fewer than two clean ones remain) are kept where they are
    (the plate's fit is the plain one), but each counts SPLIT_SIGMA_FACTOR times a lone plate's standard
    deviation in the plate's covariance and in eq. M6."""
    from uwbcl import locate
    heights = (0.24, 0.66)
    wall, z = 2.0, 1.1
    clean = [_detection(1.000, float(_rc(wall, z, 0.24)))]
    split = [dataclasses.replace(_detection(1.010, float(_rc(wall, z, 0.66))), split_separation_m=0.08)]
    (plate,) = locate_plates({0.24: clean, 0.66: split}, separation_m=SEPARATION_M)
    assert plate.position_m[0] == pytest.approx(1.005, abs=1e-12)
    assert plate.shared_heights_m == (0.66,)
    cycle = CycleResult("rig", 0, "", heights, [plate])
    sig = 0.003 * np.array([1.0, locate.SPLIT_SIGMA_FACTOR])
    cov = chain.plate_covariances(cycle, 0.003)[0]
    np.testing.assert_allclose(cov, location_covariance_m2(plate.position_m, heights, sig)
                               * misfit_scale(plate, 0.003), rtol=1e-12)
    lone_cov = location_covariance_m2(plate.position_m, heights, 0.003)
    assert np.all(np.diag(cov) > 2 * np.diag(lone_cov))
    # three split looks, one 12 mm off in range: 4 sigma of a lone plate, 1.3 of a split look
    f2 = locate.SPLIT_SIGMA_FACTOR**2
    hs3 = (0.24, 0.45, 0.66)
    looks = {h: [dataclasses.replace(_detection(1.0, float(_rc(wall, z, h)) + (0.012 if h == 0.45 else 0.0)),
                                     split_separation_m=0.08)] for h in hs3}
    (plate3,) = locate_plates(looks, separation_m=SEPARATION_M)
    lone = dataclasses.replace(plate3, looks=tuple((h, dataclasses.replace(d, split_separation_m=np.nan))
                                                   for h, d in plate3.looks))
    assert misfit_scale(lone, 0.003) > 1.0  # 12 mm is beyond a lone plate's precision
    assert misfit_scale(plate3, 0.003) == max(1.0, misfit_scale(lone, 0.003) / f2) == 1.0
    cov3 = chain.plate_covariances(CycleResult("rig", 0, "", hs3, [plate3]), 0.003)[0]
    assert cov3[0, 0] == pytest.approx(f2 * 0.003**2 / 3, rel=1e-9)


def test_a_rail_height_where_many_plates_share_their_peak_is_named_in_one_warning():
    heights = (0.24, 0.45, 0.66)
    by_height, _ = _column_scene(heights, seen_q=heights[:2], pull_m={0.66: 0.02})
    plates = locate_plates(by_height, separation_m=SEPARATION_M)  # 3 plates, one shares its peak at 0.66 m
    cycles = [CycleResult("rig-a", c, "", heights, plates) for c in range(4)]
    (warning,) = batch.shared_peak_warnings(cycles)
    assert warning.kind == "shared_peaks" and warning.file == "rig rig-a"
    # at 0.66 m two plates per cycle were seen (Q was not): P, whose peak there is shared, and R
    assert "0.660 m, 4 of 8 located plates" in warning.reason
    snr = np.median([d.snr_db for p in plates for h, d in p.looks if h == 0.66])
    assert f"a noise peak beside the plate (the median look here: {snr:.1f} dB)" in warning.reason
    assert batch.shared_peak_warnings(cycles[:3]) == []  # 3 plates: fewer than SHARED_PEAKS_WARN_MIN
    resolved, _ = _column_scene(heights, seen_q=heights, pull_m={})
    assert batch.shared_peak_warnings(
        [CycleResult("rig-a", c, "", heights, locate_plates(resolved, separation_m=SEPARATION_M))
         for c in range(8)]) == []


# --------------------------------------------------------------------------------------------- displacement
def test_advance_is_recovered_from_shuffled_plates_with_one_extra_and_one_missing():
    before = np.array([[0.786, -2.4, 0.30], [1.386, -2.4, 0.30], [1.986, -2.4, 0.30], [2.586, -2.4, 0.30],
                       [3.186, -2.4, 0.90]])
    advance = np.array([0.8, 0.1, 0.002])
    after = before - advance
    after = after[1:]  # plate 0 is not seen after the advance
    after = np.vstack([after, [[-0.5, -2.1, 1.4]]])  # and a new plate appears
    perm = np.random.default_rng(0).permutation(len(after))
    after_shuffled = after[perm]
    # A regular row 0.6 m apart: 0.2 m lines up three plates, so without a prior this is ambiguous (one plate
    # short); the web-depth prior puts 0.2 m 4.5 sigma out.
    d = estimate_advance([_plate(p) for p in before], [_plate(q) for q in after_shuffled],
                         AssociationSettings(prior_advance_m=(0.8, 0.0, 0.0)))
    assert d.status == "ok"
    np.testing.assert_allclose(d.advance_m, advance, rtol=0, atol=1e-12)  # exact data, exact answer
    assert d.n_targets == 4
    # pairs are (index before, index after) into the given lists
    expected = {(i, int(np.flatnonzero(perm == i - 1)[0])) for i in range(1, 5)}
    assert set(d.pairs) == expected
    assert d.residual_m < 1e-12
    assert (d.retreat_m, d.creep_m, d.vertical_m) == pytest.approx(tuple(advance), abs=1e-12)


def _regular_row(xs):
    return [_plate((x, -2.4, 0.3)) for x in xs]


def test_a_regular_row_spaced_by_the_advance_is_flagged_ambiguous_without_a_prior():
    # plates every 0.8 m along the rib; the rig retreats 0.8 m. Before it sees plates at 0.8 / 1.6 / 2.4 m,
    # after it sees two of them: both "0" and "0.8 m" explain two plates.
    before = _regular_row([0.8, 1.6, 2.4])
    after = _regular_row([0.8, 1.6])  # plates 1.6 / 2.4 moved by 0.8, or plates 0.8 / 1.6 not moved at all
    d = estimate_advance(before, after)
    assert d.status == "ambiguous"


def test_a_prior_on_the_advance_resolves_the_ambiguity():
    before = _regular_row([0.8, 1.6, 2.4])
    after = _regular_row([0.8, 1.6])
    d = estimate_advance(before, after, AssociationSettings(prior_advance_m=(0.8, 0.0, 0.0)))
    assert d.status == "ok"
    np.testing.assert_allclose(d.advance_m, [0.8, 0.0, 0.0], rtol=0, atol=1e-12)
    assert sorted(d.pairs) == [(1, 0), (2, 1)]


def test_no_plates_on_either_side_gives_too_few_targets():
    d = estimate_advance([], _regular_row([1.0]))
    assert d.status == "too_few_targets"
    assert np.all(np.isnan(d.advance_m))


def test_robust_mean_rejects_a_gross_outlier():
    samples = np.array([[0.800, 0.100, 0.000], [0.801, 0.099, 0.002], [0.799, 0.101, -0.002],
                        [0.802, 0.100, 0.001], [1.600, 0.400, 0.250]])
    got = robust_mean(samples, floor=np.array([0.05, 0.10, 0.25]) / 4)
    np.testing.assert_allclose(got, samples[:4].mean(axis=0), rtol=0, atol=1e-15)
    assert abs(samples.mean(axis=0)[0] - got[0]) > 0.1  # the plain mean would have been pulled far off


def test_robust_mean_keeps_ordinary_scatter_above_the_floor():
    samples = np.array([[0.800], [0.803], [0.797]])
    assert robust_mean(samples, floor=0.0125)[0] == pytest.approx(0.8, abs=1e-15)
