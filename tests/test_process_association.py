"""Matching look-alike bolt plates between cycles (displacement.py) and chaining cycles (chain.rig_series)."""

from __future__ import annotations

import numpy as np

from uwbcl import chain
from uwbcl.displacement import estimate_advance, location_covariance_m2, robust_mean
from uwbcl.locate import locate_target
from uwbcl.records import AssociationSettings, CycleResult, Located

HEIGHTS = (0.2, 0.6)
PRIOR = AssociationSettings(prior_advance_m=(0.9, 0.0, 0.0))


def plate(p) -> Located:
    return Located(position_m=np.asarray(p, dtype=float), residual_m=0.0, n_passes=2, amplitude=1.0)


def covs(points) -> np.ndarray:
    return np.array([location_covariance_m2(p, HEIGHTS, 0.003) for p in points])


def rib(xs_by_row: dict[float, list[float]], wall: float = 2.4) -> np.ndarray:
    return np.array([(x, -wall, z) for z, xs in xs_by_row.items() for x in xs])


def seen(points: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return points[(points[:, 0] >= lo) & (points[:, 0] <= hi)]


def test_a_row_spaced_close_to_the_web_depth_leaves_a_blind_consensus_in_doubt_but_not_the_prior():
    row = rib({0.5: [0.4 + 1.1 * k for k in range(8)]})
    advance = np.array([0.9, 0.005, 0.0])
    before, after = seen(row, 0.0, 3.0), seen(row - advance, 0.0, 3.0)
    blind = estimate_advance([plate(p) for p in before], [plate(q) for q in after])
    # The one-plate shift that lines up more plates is -0.2 m, a backward move of the face: no answer (eq.
    # M2b). Blind, the advance leads the next forward look-alike by one plate only: not trusted.
    assert abs(blind.retreat_m - 0.9) < 1e-9 and blind.status == "ambiguous" and blind.margin < 8.0
    d = estimate_advance([plate(p) for p in before], [plate(q) for q in after], PRIOR)
    # The one-plate shift lies 7 sigma outside the prior: unique (not ambiguous); without covariances the
    # bound may still be above max_bound_m.
    assert d.status in ("ok", "low_confidence")
    np.testing.assert_allclose(d.advance_m, advance, atol=1e-9)


def test_the_3d_pattern_of_irregular_rows_identifies_the_plates_without_a_prior():
    points = rib({0.5: [0.1, 1.3, 2.35, 3.8, 4.9], 1.1: [0.6, 1.7, 3.15, 4.3], 1.7: [0.2, 1.45, 2.6, 3.7]})
    advance = np.array([0.93, -0.04, 0.003])
    d = estimate_advance([plate(p) for p in seen(points, 0.0, 3.0)],
                         [plate(q) for q in seen(points - advance, 0.0, 3.0)])
    assert d.status == "ok" and d.n_targets >= 5
    np.testing.assert_allclose(d.advance_m, advance, atol=1e-9)


def test_an_advance_far_outside_the_prior_is_reported_as_a_prior_conflict_not_forced_into_the_window():
    points = rib({0.5: [0.1, 1.3, 2.35, 3.8, 4.9], 1.1: [0.6, 1.7, 3.15, 4.3], 1.7: [0.2, 1.45, 2.6, 3.7]})
    advance = np.array([1.85, 0.0, 0.0])  # two webs: a cycle's scan was lost but the numbering went on
    before, after = seen(points, 0.0, 4.9), seen(points - advance, 0.0, 4.9)
    d = estimate_advance([plate(p) for p in before], [plate(q) for q in after], PRIOR)
    assert d.status == "prior_conflict"
    np.testing.assert_allclose(d.advance_m, advance, atol=1e-9)
    bridged = estimate_advance([plate(p) for p in before], [plate(q) for q in after], PRIOR.for_gap(2))
    assert bridged.status == "ok"


def test_two_lone_plates_that_could_each_be_the_match_are_ambiguous():
    before = [plate((1.0, -2.4, 0.5)), plate((1.5, -2.4, 1.1))]
    after = [plate((0.05, -2.4, 0.5)), plate((0.7, -2.4, 1.1))]  # 0.95 or 0.80: one plate each
    d = estimate_advance(before, after, PRIOR)
    assert d.status == "ambiguous" and d.runner_up_targets == 1


def _noisy_plates(points: np.ndarray, rng, range_sigma_m: float, bad: dict[int, float] | None = None):
    """Plates located like locate.py does, from ranges with errors (bad: index -> extra range error, m)."""
    out = []
    for k, p in enumerate(points):
        rc = np.hypot(p[1], p[2] - np.asarray(HEIGHTS)) + rng.normal(0.0, range_sigma_m, 2)
        if bad and k in bad:
            rc[1] += bad[k]
        loc = locate_target(HEIGHTS, [p[0] + rng.normal(0, range_sigma_m)] * 2, rc)
        out.append(loc.position_m)
    return np.array(out)


def test_location_covariances_let_the_z_residuals_correct_the_creep():
    points = rib({0.5: [0.4, 1.5, 2.7], 1.1: [0.9, 2.0], 1.7: [0.3, 1.4, 2.5]})
    advance = np.array([0.9, 0.02, 0.0])
    rng = np.random.default_rng(4)
    gls_err, mean_err = [], []
    for _ in range(40):
        p = _noisy_plates(points, rng, 0.003)
        q = _noisy_plates(points - advance, rng, 0.003)
        d = estimate_advance([plate(x) for x in p], [plate(x) for x in q], PRIOR, before_cov_m2=covs(p),
                             after_cov_m2=covs(q))
        gls_err.append(d.advance_m - advance)
        mean_err.append(robust_mean(p - q, floor=0.01) - advance)
    gls_rms = np.sqrt(np.mean(np.square(gls_err), axis=0))
    mean_rms = np.sqrt(np.mean(np.square(mean_err), axis=0))
    assert gls_rms[1] < 0.6 * mean_rms[1]  # creep
    assert gls_rms[1] < 0.003


def test_a_plate_located_from_one_bad_range_is_rejected():
    points = rib({0.5: [0.4, 1.5, 2.7], 1.1: [0.9, 2.0]})
    advance = np.array([0.9, 0.02, 0.0])
    rng = np.random.default_rng(1)
    p = _noisy_plates(points, rng, 0.001)
    q = _noisy_plates(points - advance, rng, 0.001, bad={3: 0.02})  # 2 cm off at one height
    d = estimate_advance([plate(x) for x in p], [plate(x) for x in q], PRIOR, before_cov_m2=covs(p),
                         after_cov_m2=covs(q))
    assert d.status == "ok" and d.n_targets == 4 and (3, 3) not in d.pairs
    assert abs(d.creep_m - advance[1]) < 0.003


def test_a_range_error_along_a_plates_poor_direction_is_absorbed_by_its_covariance():
    points = rib({0.5: [0.4], 1.1: [1.0]})
    advance = np.array([0.9, 0.02, 0.0])
    p = _noisy_plates(points, np.random.default_rng(2), 0.0005)
    q = _noisy_plates(points - advance, np.random.default_rng(3), 0.0005, bad={1: 0.02})
    assert abs((p - q)[1, 1] - advance[1]) > 0.03  # the high plate alone is 4 cm off in creep
    d = estimate_advance([plate(x) for x in p], [plate(x) for x in q], PRIOR, before_cov_m2=covs(p),
                         after_cov_m2=covs(q))
    assert d.status == "ok" and d.n_targets == 2
    assert abs(d.creep_m - advance[1]) < 0.005


def test_two_plates_that_disagree_beyond_their_precision_are_flagged_inconsistent():
    points = rib({0.5: [0.4], 1.1: [1.0]})
    advance = np.array([0.9, 0.02, 0.0])
    p = _noisy_plates(points, np.random.default_rng(2), 0.0005)
    q = _noisy_plates(points - advance, np.random.default_rng(3), 0.0005)
    q[1, 0] += 0.03  # 3 cm along track: no range error explains that
    d = estimate_advance([plate(x) for x in p], [plate(x) for x in q], PRIOR, before_cov_m2=covs(p),
                         after_cov_m2=covs(q))
    assert d.status == "inconsistent" and d.n_targets == 2


# ----------------------------------------------------------------------------------------------- the chain
def _cycles(points: np.ndarray, rig_positions: np.ndarray, window=(0.0, 3.0)) -> list[CycleResult]:
    out = []
    for c, rig in enumerate(rig_positions):
        visible = seen(points - rig, *window)
        out.append(CycleResult("rig-1", c, f"2026-11-02T{6 + c:02d}:00:00Z", HEIGHTS,
                               [plate(x) for x in visible]))
    return out


RIB = rib({0.5: [0.1 + 1.23 * k + 0.2 * np.sin(k) for k in range(20)],
           1.1: [0.5 + 1.31 * k + 0.15 * np.cos(2 * k) for k in range(20)]})


def test_a_cycle_that_cannot_be_matched_is_bridged_and_costs_no_cumulative_drift():
    rigs = np.cumsum([[0.0, 2.4, 0.0]] + [[0.9 + 0.02 * (k % 3), 0.004, 0.0] for k in range(6)], axis=0)
    cycles = _cycles(RIB, rigs)
    cycles[3] = CycleResult("rig-1", 3, cycles[3].start_time, HEIGHTS, [])  # nothing located
    rows = chain.rig_series(cycles, PRIOR)
    by_cycle = {r.cycle.cycle: r for r in rows}
    assert by_cycle[3].displacement.status == "too_few_targets" and np.isnan(by_cycle[3].cumulative_m).all()
    assert by_cycle[4].reference.cycle == 2  # measured across the gap
    for c in (1, 2, 4, 5, 6):
        np.testing.assert_allclose(by_cycle[c].cumulative_m, rigs[c] - rigs[0], atol=1e-9)


def test_after_too_many_unmatched_cycles_a_new_chain_starts_rather_than_a_guess():
    rigs = np.cumsum([[0.0, 2.4, 0.0]] + [[0.9, 0.0, 0.0]] * 7, axis=0)
    cycles = _cycles(RIB, rigs)
    for c in (2, 3, 4):
        cycles[c] = CycleResult("rig-1", c, cycles[c].start_time, HEIGHTS, [])
    rows = {r.cycle.cycle: r for r in chain.rig_series(cycles, PRIOR, max_bridge_cycles=3)}
    assert [rows[c].chain for c in range(1, 8)] == [0, 0, 0, 1, 1, 1, 1]
    assert rows[4].reference.cycle == 1 and rows[4].displacement.status == "too_few_targets"
    np.testing.assert_allclose(rows[7].cumulative_m, rigs[7] - rigs[5], atol=1e-9)  # counted from cycle 5
