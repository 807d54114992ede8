"""Specification of the echo simulator (eq. 2 with the rig's rail motion and receiver noise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbcl import geometry as geo
from uwbcl import simulate as sim
from uwbcl.model import SPEED_OF_LIGHT_M_S as C
from uwbcl.model import PassGeometry, RadarParameters
from uwbcl.scenarios import PAPER_SIM1

RADAR = RadarParameters()
REF = tuple(float(c) for c in PAPER_SIM1.reference_point_m(0))
GEOM = PassGeometry(height_m=0.15, rotation_table_angle_deg=PAPER_SIM1.rotation_table_angle_deg(0),
                    reference_point_m=REF)


def _pass(seed, **kw):
    return sim.simulate_pass(RADAR, GEOM, [REF], aperture_length_m=2.0, speed_m_s=0.15,
                             rng=np.random.default_rng(seed), **kw)


def test_simulated_pass_is_deterministic_under_a_seed():
    a = _pass(3, snr_db=0.0, speed_jitter=0.1)
    b = _pass(3, snr_db=0.0, speed_jitter=0.1)
    np.testing.assert_array_equal(a.echo, b.echo)
    np.testing.assert_array_equal(a.pulse_position_m, b.pulse_position_m)
    c = _pass(4, snr_db=0.0, speed_jitter=0.1)
    assert not np.array_equal(a.echo, c.echo)  # the seed matters, so the equality above is not vacuous
    assert not np.array_equal(a.pulse_position_m, c.pulse_position_m)


def test_scenario_simulation_is_deterministic_under_a_seed():
    a = PAPER_SIM1.simulate(seed=5, snr_db=10.0, speed_jitter=0.05)
    b = PAPER_SIM1.simulate(seed=5, snr_db=10.0, speed_jitter=0.05)
    assert len(a) == len(b) == 4
    for p, q in zip(a, b):
        np.testing.assert_array_equal(p.echo, q.echo)
        np.testing.assert_array_equal(p.pulse_position_m, q.pulse_position_m)


@pytest.mark.parametrize("snr_db", [0.0, 10.0, -10.0])
def test_noise_power_per_sample_follows_the_snr_definition(snr_db):
    positions = np.arange(301) * 0.0075 - 1.125
    behind = [(-60.0, -2.4, 0.3)]  # far behind the rail start: outside the forward-squinted beam
    t0, n_r = 2 * 58.0 / C, 256
    clean = sim.simulate_echo(RADAR, GEOM, positions, behind, 1.0, t0, n_r, None, np.random.default_rng(0))
    assert not clean.any()  # the target really is out of view: whatever comes back below is noise
    noisy = sim.simulate_echo(RADAR, GEOM, positions, behind, 1.0, t0, n_r, snr_db, np.random.default_rng(0))
    power = np.mean(np.abs(noisy) ** 2)
    # 77k complex samples: the power estimate has a relative std of 1/sqrt(77k) = 0.4 %, so 5 % is > 10 sigma
    assert power == pytest.approx(10 ** (-snr_db / 10), rel=0.05)
    # circular: I and Q carry half the power each
    assert np.mean(noisy.real**2) == pytest.approx(power / 2, rel=0.05)


def test_a_unit_target_on_boresight_gives_a_unit_peak_sample_at_the_two_way_delay():
    h, theta_h = 0.15, math.radians(GEOM.rotation_table_angle_deg)
    target = np.array([1.386, -2.4, 0.3])
    x_a = target[0] - 2.4 * math.tan(theta_h)  # the antenna position that sees the target on boresight
    r = geo.range_history_m([x_a], target, h)[0]
    k_peak = 40
    t0 = 2 * r / C - k_peak / RADAR.sample_rate_hz  # put the echo delay exactly on sample k_peak
    echo = sim.simulate_echo(RADAR, GEOM, [x_a], [target], 1.0, t0, 128, None, np.random.default_rng(0))[0]
    assert int(np.argmax(np.abs(echo))) == k_peak
    # on boresight with the delay on a sample the only loss could be a wrong gain or envelope: 2 % is the spec
    assert abs(echo[k_peak]) == pytest.approx(1.0, rel=0.02)
    # carrier phase of eq. (2): exp(-j 4 pi f_c R / c), checked to a milliradian
    expected_phase = -4 * math.pi * RADAR.carrier_frequency_hz * r / C
    assert abs(np.angle(echo[k_peak] * np.exp(-1j * expected_phase))) < 1e-3
    # the Gaussian envelope: one sample away the modulus is exp(-dt^2 / 2 sigma^2)
    dt = 1 / RADAR.sample_rate_hz
    assert abs(echo[k_peak + 1]) == pytest.approx(math.exp(-0.5 * (dt / RADAR.pulse_sigma_s) ** 2), rel=1e-6)


def test_amplitude_scales_the_echo_linearly():
    one = _pass(0)
    three = sim.simulate_pass(RADAR, GEOM, [REF], aperture_length_m=2.0, speed_m_s=0.15, amplitudes=3.0,
                              rng=np.random.default_rng(0))
    np.testing.assert_allclose(three.echo, 3.0 * one.echo, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_speed_jitter_keeps_every_pulse_to_pulse_speed_within_the_stated_fraction(seed):
    v, prf, jitter = 0.15, 20.0, 0.1
    t, x = sim.rail_motion(301, prf, v, -1.0, jitter, np.random.default_rng(seed))
    np.testing.assert_allclose(np.diff(t), 1 / prf, rtol=1e-12)  # pulses stay on the PRF clock
    speed = np.diff(x) / np.diff(t)
    assert np.all(np.diff(x) > 0)  # the carriage never stops or reverses
    # the per-pulse speed is an average of v (1 + 0.1 u), |u| <= 1: within +-10 %; 1e-9 covers round-off
    assert np.all(np.abs(speed / v - 1) <= jitter + 1e-9)
    # and the jitter is really there (u is normalised to max |u| = 1, so most of the 10 % is reached)
    assert np.max(np.abs(speed / v - 1)) > 0.05
    assert x[0] == -1.0


def test_zero_speed_jitter_gives_uniformly_spaced_positions():
    _, x = sim.rail_motion(269, 20.0, 0.15, -1.0, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(np.diff(x), 0.15 / 20.0, rtol=1e-12)


def test_reverse_direction_pass_moves_towards_negative_x():
    _, x = sim.rail_motion(101, 20.0, 0.15, 1.0, 0.1, np.random.default_rng(0), direction=-1)
    assert np.all(np.diff(x) < 0)


def test_range_window_covers_every_target_over_the_aperture_with_margin():
    p = _pass(0)
    r = geo.range_history_m(p.pulse_position_m, REF, 0.15)
    axis = p.range_axis_m
    assert axis[0] <= r.min() - 1.0 + 1e-9
    assert axis[-1] >= r.max() + 1.0 - RADAR.range_bin_m
    assert p.samples_per_pulse & (p.samples_per_pulse - 1) == 0  # a power of two


def test_pass_has_an_odd_number_of_pulses_spanning_the_nominal_aperture():
    p = _pass(0)
    assert p.n_pulses % 2 == 1
    # 2.0 m at 7.5 mm per pulse is 266.7 spacings: the span is rounded to whole pulses (within 2 spacings)
    span = p.pulse_position_m[-1] - p.pulse_position_m[0]
    assert abs(span - 2.0) <= 2 * 0.0075 + 1e-12


def test_pass_is_centred_on_the_nominal_aperture_centre():
    p = _pass(0)
    assert p.aperture_centre_m == pytest.approx(0.0, abs=1e-9)
