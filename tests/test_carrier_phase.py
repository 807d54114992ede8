"""Specification of the carrier-phase refinement (eq. R5 in uwbcl.detect.phase, eq. M8 in uwbcl.displacement;
docs/method.md 6.5).

A plate's echo, backprojected at a point with the carrier restored, has the phase 2k x (its distance from the
plate along the line of sight) plus the plate's own scattering phase, which a plate keeps between cycles. So
the phase difference of a matched plate between two cycles measures their translation along each rail
height's line of sight to a small part of the wavelength (~70 mm), where the plates' positions give
millimetres. Tolerances: the slopes are 2k (sin, cos) of the look angle, within 5 % (the look angles spread
over the beam); eq. R5's first-order move over 3 mm is good to 0.02 rad (its second order: 2k x 3 mm^2 / R);
the phase sigma is the scatter over 40 noise draws within -30/+40 % (the 40 draws' own sampling error is
11 %); the refinement must at least halve the plates' creep and vertical errors at SNR 10 dB and keep every
error within 3 x its bound (the bound's calibration of docs/method.md 6.1).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from uwbcl import chain, pipeline, simulate
from uwbcl.chain import RigChain
from uwbcl.detect.phase import PointEcho, carrier_phase
from uwbcl.displacement import carrier_phase_refinement, estimate_advance, phase_looks
from uwbcl.geometry import closest_approach_range_m
from uwbcl.model import PassGeometry, RadarParameters
from uwbcl.records import AssociationSettings, ProcessingSettings

RIB_M = 2.5
HEIGHTS_M = (0.2, 0.6)
SQUINT_DEG = 30.0
RAIL_CENTRE_M = 1.5
PLATES_M = np.array([[2.2, -RIB_M, 0.7], [3.0, -RIB_M, 1.3], [3.8, -RIB_M, 0.8]])  # crossings on the rail
STEP_M = np.array([0.9, 0.004, -0.003])  # the rig's advance a -> b: P_b = P_a - STEP
SETTINGS = AssociationSettings(prior_advance_m=(0.9, 0.0, 0.0))


def one_pass(targets_m: np.ndarray, height_m: float, snr_db: float | None, seed: int):
    th = math.radians(SQUINT_DEG)
    geometry = PassGeometry(height_m=height_m, rotation_table_angle_deg=SQUINT_DEG,
                            reference_point_m=(RAIL_CENTRE_M + RIB_M * math.tan(th), -RIB_M, 1.0),
                            boresight_y_sign=-1)
    return simulate.simulate_pass(RadarParameters(), geometry, targets_m, aperture_length_m=4.0,
                                  speed_m_s=0.25, aperture_centre_m=RAIL_CENTRE_M, snr_db=snr_db,
                                  speed_jitter=0.1, rng=np.random.default_rng(seed))


def two_cycles(seed: int, snr_db: float | None = 10.0):
    """Cycles a and b of the three plates (b after STEP), located by the default pipeline (numpy)."""
    cycles = []
    for c, shift in ((0, np.zeros(3)), (1, STEP_M)):
        passes = [one_pass(PLATES_M - shift, h, snr_db, 100 * seed + 10 * c + k)
                  for k, h in enumerate(HEIGHTS_M)]
        cycles.append(pipeline.locate_cycle(passes, ProcessingSettings()))
    return cycles


def advance(a, b, carrier_phase_on: bool, tested_only: bool = False, settings=SETTINGS):
    s = dataclasses.replace(settings, carrier_phase=carrier_phase_on)
    return estimate_advance(a.plates, b.plates, s, before_cov_m2=chain.plate_covariances(a, s.range_sigma_m),
                            after_cov_m2=chain.plate_covariances(b, s.range_sigma_m),
                            phase_tested_only=tested_only)


def with_random_phases(cycle, rng: np.random.Generator):
    """The cycle with every detection's phase drawn anew (plates whose phase does not hold between passes)."""
    return dataclasses.replace(cycle, plates=[dataclasses.replace(p, looks=tuple(
        (h, dataclasses.replace(d, phase_rad=float(rng.uniform(-np.pi, np.pi)))) for h, d in p.looks))
        for p in cycle.plates])


def test_a_detections_phase_slopes_are_the_carrier_along_its_line_of_sight_and_move_it_to_nearby_points():
    scan = one_pass(PLATES_M[:1], HEIGHTS_M[0], None, 0)
    echo = PointEcho(scan)
    x, rc = PLATES_M[0, 0], float(np.hypot(PLATES_M[0, 1], PLATES_M[0, 2] - HEIGHTS_M[0]))
    phase, slope_x, slope_rc, sigma = carrier_phase(echo, x, rc)
    k2 = echo.grid.two_way_wavenumber_rad_m
    along = RIB_M * math.tan(math.radians(SQUINT_DEG))  # the beam centre's along-track offset
    look = math.atan2(along, rc)  # the look angle in the slant plane
    assert slope_x == pytest.approx(k2 * math.sin(look), rel=0.05)
    assert slope_rc == pytest.approx(k2 * math.cos(look), rel=0.05)
    assert sigma < 1e-3  # noise-free
    for dx, dr in ((0.003, 0.0), (0.0, -0.003), (-0.002, 0.002)):
        moved = np.angle(echo.image(np.array([x + dx]), np.array([rc + dr]))[0])
        predicted = phase + slope_x * dx + slope_rc * dr
        assert abs(np.angle(np.exp(1j * (moved - predicted)))) < 0.02


def test_a_detections_phase_sigma_is_the_scatter_of_its_phase_under_noise():
    x, rc = PLATES_M[0, 0], float(np.hypot(PLATES_M[0, 1], PLATES_M[0, 2] - HEIGHTS_M[0]))
    phases, sigmas = [], []
    for seed in range(40):
        echo = PointEcho(one_pass(PLATES_M[:1], HEIGHTS_M[0], -10.0, seed))
        phase, _, _, sigma = carrier_phase(echo, x, rc)
        phases.append(phase)
        sigmas.append(sigma)
    mean = np.angle(np.mean(np.exp(1j * np.array(phases))))
    scatter = float(np.std(np.angle(np.exp(1j * (np.array(phases) - mean)))))
    assert 0.05 < np.mean(sigmas) < 0.5  # a regime where the phase is measured but noisy
    assert 0.7 < scatter / np.mean(sigmas) < 1.4


@pytest.fixture(scope="module")
def noisy_pairs():
    return [two_cycles(seed) for seed in range(4)]


def test_the_phases_cut_the_plates_creep_and_vertical_errors_and_stay_within_three_bounds(noisy_pairs):
    errors = {False: [], True: []}
    for a, b in noisy_pairs:
        for on in (False, True):
            d = advance(a, b, on)
            assert d.status == "ok"
            assert d.phase_looks == (2 * d.n_targets if on else 0)
            e = d.advance_m - STEP_M
            errors[on].append(e)
            assert np.all(np.abs(e) <= 3 * d.bound_m)
    rms = {on: np.sqrt(np.mean(np.square(errors[on]), axis=0)) for on in errors}
    assert rms[True][1] < 0.5 * rms[False][1]
    assert rms[True][2] < 0.5 * rms[False][2]
    assert rms[True][1] < 0.0005  # creep to half a millimetre
    assert rms[True][0] < rms[False][0] + 0.0003  # the phases say little along the rail: retreat as before


def test_phases_that_disagree_with_the_plates_leave_the_plates_estimate(noisy_pairs):
    a, b = noisy_pairs[0]
    # each plate's phase changed between the cycles (a plate replaced, a rib that does not keep its phase)
    offsets = iter((1.5, -1.2, 2.0, 0.9, -2.2))
    changed = [dataclasses.replace(p, looks=tuple((h, dataclasses.replace(d, phase_rad=d.phase_rad + off))
                                                  for (h, d), off in zip(p.looks, [next(offsets)] * 2)))
               for p in b.plates]
    plain = advance(a, b, False)
    s = SETTINGS
    d = estimate_advance(a.plates, changed, s, before_cov_m2=chain.plate_covariances(a, s.range_sigma_m),
                         after_cov_m2=chain.plate_covariances(b, s.range_sigma_m))
    assert d.phase_looks == 0
    np.testing.assert_array_equal(d.advance_m, plain.advance_m)
    np.testing.assert_array_equal(d.bound_m, plain.bound_m)


def _lowered(p):
    """The plate and its looks 0.1 m lower: the row's vertical +0.1 m."""
    q = p.position_m - [0, 0, 0.1]
    return dataclasses.replace(p, position_m=q, looks=tuple(
        (h, dataclasses.replace(d, rc_m=float(closest_approach_range_m(q, h)))) for h, d in p.looks))


def test_plates_whose_vertical_the_rig_cannot_have_and_whose_phases_disagree_are_withheld(noisy_pairs):
    """Eq. M5c. An independent tester's dense grid from three heights: five plates, three of them located
    through looks shared with a neighbour, all pulled along their dilution direction (y and z together): the
    row's vertical +42 mm against a rig that moves millimetres, its creep 28 mm off against a 4 mm bound,
    `ok`.
    A floor step moves every plate alike and its phases hold; plates pulled off do neither."""
    a, b = noisy_pairs[0]
    lifted = dataclasses.replace(b, plates=[_lowered(p) for p in b.plates])
    scrambled = with_random_phases(lifted, np.random.default_rng(5))

    def row(after, vertical_prior_m, phases=True):
        s = dataclasses.replace(SETTINGS, vertical_prior_m=vertical_prior_m, carrier_phase=phases)
        # plates placed to ~1 cm in z (the tester's were seen from three heights)
        return estimate_advance(a.plates, after.plates, s,
                                before_cov_m2=0.04 * chain.plate_covariances(a, s.range_sigma_m),
                                after_cov_m2=0.04 * chain.plate_covariances(after, s.range_sigma_m))

    d = row(scrambled, (0.0, 0.005))
    assert d.phase_check == -1 and d.status == "inconsistent"
    # the same plates with a vertical prior they agree with, or without the phases: the plates' estimate
    assert row(scrambled, (0.1, 0.005)).status == "ok"
    assert row(scrambled, (0.0, 0.005), phases=False).status == "ok"
    step = row(lifted, (0.0, 0.005))  # a floor step: every plate and look moved alike, the phases hold
    assert step.phase_check == 1 and step.status == "ok" and step.advance_m[2] > 0.09


def test_on_a_rig_whose_phases_have_not_held_a_failed_phase_test_withholds_no_floor_step(noisy_pairs):
    # a review: M5c withheld a uniform floor step whose phases failed for another reason on a rig whose
    # phases had never held; it acts once they have (RigChain's phase_tested_only False)
    a, b = noisy_pairs[0]
    lifted = dataclasses.replace(b, plates=[_lowered(p) for p in b.plates])
    scrambled = with_random_phases(lifted, np.random.default_rng(5))
    s = dataclasses.replace(SETTINGS, vertical_prior_m=(0.0, 0.005))
    d = estimate_advance(a.plates, scrambled.plates, s, phase_tested_only=True,
                         before_cov_m2=0.04 * chain.plate_covariances(a, s.range_sigma_m),
                         after_cov_m2=0.04 * chain.plate_covariances(scrambled, s.range_sigma_m))
    assert d.phase_check == -1 and d.status != "inconsistent"


def test_the_phases_coupling_carries_a_retreat_competitor_into_the_creep_bound(noisy_pairs, monkeypatch):
    # eq. M8b wired into the bound (a review found it moved, by mistake, under M5c's condition)
    from uwbcl import displacement

    a, b = noisy_pairs[0]
    plain = advance(a, b, True)
    real = displacement._with_phases

    def coupled(*args):
        adv, cov, looks, check, _ = real(*args)
        return adv, cov, looks, check, np.array([2.0, 0.0])

    real_competitors = displacement._competitors

    def rival(best, rivals, settings):
        margin, unknown, rival_var = real_competitors(best, rivals, settings)
        return margin, unknown + np.array([1e-4, 0.0, 0.0]), rival_var

    monkeypatch.setattr(displacement, "_with_phases", coupled)
    monkeypatch.setattr(displacement, "_competitors", rival)
    d = advance(a, b, True)
    assert d.bound_m[1] ** 2 == pytest.approx(plain.bound_m[1] ** 2 + 4.0 * 1e-4, rel=1e-6)


def test_a_look_whose_fringe_the_plates_cannot_fix_is_not_used(noisy_pairs):
    a, b = noisy_pairs[0]
    d = advance(a, b, False)
    looks = phase_looks(a.plates, b.plates, d.pairs)
    assert looks
    # plates that place the translation to 2 cm along the line of sight: the phase could be any fringe
    assert carrier_phase_refinement(d.advance_m, np.diag([0.02, 0.02, 0.02]) ** 2, looks) is None
    refined = carrier_phase_refinement(d.advance_m, np.diag([0.002, 0.002, 0.005]) ** 2, looks)
    assert refined is not None and refined.looks == len(looks) and refined.consistent
    # nothing to refine against: a degenerate or undefined covariance leaves the plates' estimate
    assert carrier_phase_refinement(d.advance_m, np.zeros((3, 3)), looks) is None
    assert carrier_phase_refinement(d.advance_m, np.full((3, 3), np.nan), looks) is None


def test_the_phases_move_the_creep_with_the_retreat_as_their_x_coupling_says(noisy_pairs):
    # eq. M8b: the retreat is held at the plates', so a retreat error the covariance does not hold (M3a's
    # immaterial competitor) reaches the creep through the line of sight, about tan(squint) per metre
    a, b = noisy_pairs[0]
    d = advance(a, b, False)
    looks = phase_looks(a.plates, b.plates, d.pairs)
    cov = np.diag([0.002, 0.002, 0.005]) ** 2
    base = carrier_phase_refinement(d.advance_m, cov, looks)
    moved = carrier_phase_refinement(d.advance_m + np.array([0.0005, 0.0, 0.0]), cov, looks)
    slope = (moved.advance_m[1:] - base.advance_m[1:]) / 0.0005
    np.testing.assert_allclose(slope, base.x_coupling, atol=0.02)
    assert abs(base.x_coupling[0]) == pytest.approx(math.tan(math.radians(SQUINT_DEG)), rel=0.25)


def test_noise_free_cycles_are_refined_to_a_tenth_of_a_millimetre():
    a, b = two_cycles(0, snr_db=None)
    d = advance(a, b, True)
    assert d.phase_looks == 2 * len(PLATES_M)
    assert np.max(np.abs(d.advance_m[1:] - STEP_M[1:])) < 1e-4


def test_phases_of_another_carrier_or_another_rail_height_are_not_compared(noisy_pairs):
    a, b = noisy_pairs[0]
    pairs = advance(a, b, False).pairs
    assert len(phase_looks(a.plates, b.plates, pairs)) == 2 * len(pairs)
    def carrier(factor):
        return [dataclasses.replace(p, looks=tuple(
            (h, dataclasses.replace(d, phase_wavenumber_rad_m=factor * d.phase_wavenumber_rad_m))
            for h, d in p.looks)) for p in b.plates]

    assert phase_looks(a.plates, carrier(1.05), pairs) == []  # another radar
    assert phase_looks(a.plates, carrier(1.002), pairs) == []  # 8 MHz off at 4 GHz
    assert len(phase_looks(a.plates, carrier(1.0005), pairs)) == 2 * len(pairs)  # one radar, re-measured
    other_height = [dataclasses.replace(p, looks=tuple((h + 0.002, d) for h, d in p.looks)) for p in b.plates]
    assert phase_looks(a.plates, other_height, pairs) == []
    same_height = [dataclasses.replace(p, looks=tuple((h + 1e-5, d) for h, d in p.looks)) for p in b.plates]
    assert len(phase_looks(a.plates, same_height, pairs)) == 2 * len(pairs)


def test_a_fit_without_spare_looks_refines_only_where_asked_and_reports_no_test(noisy_pairs):
    a, b = noisy_pairs[0]
    one = dataclasses.replace(a, plates=[p for p in a.plates if p.position_m[0] > 2.5][:1])
    # one plate's vertical is known to millimetres only with the rig's (learned) vertical step prior
    vertical = dataclasses.replace(SETTINGS, vertical_prior_m=(0.0, 0.003))
    d = advance(one, b, True, settings=vertical)
    assert d.n_targets == 1 and d.phase_looks == 2 and d.phase_check == 0  # 2 looks: nothing spare
    d = advance(one, b, True, tested_only=True, settings=vertical)
    assert d.phase_looks == 0 and d.phase_check == 0
    d = advance(a, b, True, tested_only=True)  # 3 plates x 2 heights: 3 spare looks
    assert d.phase_looks == 6 and d.phase_check == 1


def rig_cycles(seed: int, n: int, random_phases: bool = False):
    """n cycles of a rig advancing STEP per cycle past plates every metre along 12 m of rib (each pass sees
    three or four), SNR 10 dB; with `random_phases`, each detection's phase drawn anew."""
    rib = np.array([[x, -RIB_M, (0.7, 1.3)[k % 2]] for k, x in enumerate(np.arange(1.0, 13.0, 1.0))])
    rng = np.random.default_rng(seed)
    cycles = []
    for c in range(n):
        seen = rib - c * STEP_M
        seen = seen[(seen[:, 0] > 0.6) & (seen[:, 0] < 5.2)]
        passes = [one_pass(seen, h, 10.0, 1000 * seed + 10 * c + k) for k, h in enumerate(HEIGHTS_M)]
        cycle = dataclasses.replace(pipeline.locate_cycle(passes, ProcessingSettings()), cycle=c)
        cycles.append(with_random_phases(cycle, rng) if random_phases else cycle)
    return cycles


@pytest.fixture(scope="module")
def rig():
    return rig_cycles(7, 6)


def test_a_rig_whose_phases_hold_earns_the_trust_that_refines_every_row(rig):
    chain_ = RigChain(SETTINGS)
    rows = [chain_.add(c) for c in rig][1:]
    assert chain_.phase_trusted()
    assert all(r.displacement.status == "ok" and r.displacement.phase_looks > 0 for r in rows)
    assert sum(r.displacement.phase_check == 1 for r in rows) >= 2


def test_a_rig_whose_phases_do_not_hold_keeps_the_plates_estimates(rig):
    rng = np.random.default_rng(11)
    scrambled = [with_random_phases(c, rng) for c in rig]
    off = RigChain(dataclasses.replace(SETTINGS, carrier_phase=False))
    plain = [r for r in (off.add(c) for c in rig) if r]
    chain_ = RigChain(SETTINGS)
    rows = [r for r in (chain_.add(c) for c in scrambled) if r]
    assert not chain_.phase_trusted()
    for r, p in zip(rows, plain):
        assert r.displacement.phase_looks == 0 and r.displacement.phase_check == -1
        assert r.displacement.status == p.displacement.status
        np.testing.assert_allclose(r.displacement.advance_m, p.displacement.advance_m, atol=1e-12)
