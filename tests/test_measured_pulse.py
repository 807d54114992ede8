"""The measured pulse (archive 1.2, docs/method.md C15): every focuser's range compression uses conj(P(f)) of
the measured pulse, and every point-response model uses the same pulse, so the models stay consistent.

Measured on a PAPER_SIM1 pass (cycle 0, h = 0.15 m, 10 dB SNR) with a non-Gaussian pulse (the Gaussian
spectrum tilted by 1 + 0.4 f/B and with a quadratic phase 1.5 (f/B)^2 rad, 129 samples over +-f_s/2):
scipy32 vs the numpy oracle 2.5e-7 (image, relative); the Gaussian sampled as a measured pulse vs the Gaussian
3.2e-4 (echo and image: the linear interpolation of P between its samples); the targets located with the
measured pulse within 3 mm of the truth, focused with the wrong (Gaussian) pulse up to 3.3 mm along track.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from uwbcl import pipeline
from uwbcl.focus import backprojection as bp
from uwbcl.focus import nlcs, scipy32
from uwbcl.model import MeasuredPulse, PassGeometry, gaussian_pulse_spectrum
from uwbcl.records import ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1
from uwbcl.simulate import simulate_pass

RADAR = PAPER_SIM1.radar
F_HZ = np.linspace(-0.5 * RADAR.sample_rate_hz, 0.5 * RADAR.sample_rate_hz, 129)
U = F_HZ / RADAR.bandwidth_hz
GAUSSIAN = gaussian_pulse_spectrum(F_HZ, RADAR.pulse_sigma_s)
ODD = MeasuredPulse(F_HZ, GAUSSIAN * (1 + 0.4 * U) * np.exp(1.5j * U**2))
HEIGHT_M = 0.15


def rel_err(out, ref) -> float:
    return float(np.linalg.norm(np.asarray(out) - ref) / np.linalg.norm(ref))


def simulate(pulse: MeasuredPulse | None, snr_db=10.0):
    g = PassGeometry(height_m=HEIGHT_M, rotation_table_angle_deg=PAPER_SIM1.rotation_table_angle_deg(0),
                     reference_point_m=tuple(float(c) for c in PAPER_SIM1.reference_point_m(0)))
    return simulate_pass(dataclasses.replace(RADAR, measured_pulse=pulse), g, PAPER_SIM1.targets_radar_m(0),
                         aperture_length_m=PAPER_SIM1.aperture_length_m, speed_m_s=PAPER_SIM1.speed_m_s,
                         snr_db=snr_db, rng=np.random.default_rng(1))


@pytest.fixture(scope="module")
def odd_pass():
    return simulate(ODD)


@pytest.fixture(scope="module")
def odd_focus(odd_pass):
    return nlcs.nlcs_focus(odd_pass)


def test_the_matched_filter_of_a_measured_pulse_is_its_conjugate_spectrum_interpolated_on_the_range_grid():
    grid = nlcs.focus_grid(simulate(None, snr_db=None))
    grid = dataclasses.replace(grid, measured_pulse=ODD)
    f = grid.f_range_hz
    i = np.searchsorted(F_HZ, f) - 1
    i = np.clip(i, 0, F_HZ.size - 2)
    w = (f - F_HZ[i]) / (F_HZ[i + 1] - F_HZ[i])
    want = np.conj((1 - w) * ODD.spectrum[i] + w * ODD.spectrum[i + 1])
    np.testing.assert_allclose(grid.pulse_filter(f), want, atol=1e-15)
    assert grid.pulse_filter(np.array([1.01 * F_HZ[-1]]))[0] == 0  # outside the measured band: nothing


def test_a_gaussian_sampled_as_a_measured_pulse_simulates_and_focuses_as_the_gaussian():
    gauss, sampled = simulate(None), simulate(MeasuredPulse(F_HZ, GAUSSIAN))
    assert rel_err(sampled.echo, gauss.echo) < 1e-3  # 3.2e-4 measured: linear interpolation of P
    assert rel_err(nlcs.nlcs_focus(sampled).image, nlcs.nlcs_focus(gauss).image) < 1e-3


def test_the_measured_pulses_waveforms_are_the_gaussians_for_a_gaussian_spectrum():
    fine = np.linspace(-0.5 * RADAR.sample_rate_hz, 0.5 * RADAR.sample_rate_hz, 2049)
    pulse = MeasuredPulse(fine, gaussian_pulse_spectrum(fine, RADAR.pulse_sigma_s))
    t = np.linspace(-1e-9, 1e-9, 101)
    s = RADAR.pulse_sigma_s
    # the spectrum stops at +-f_s/2, where the Gaussian's is still 1.7e-3: the pulse is off by up to 2e-4,
    # its matched output by 3.6e-4 relative (the normaliser int |P| df loses that tail)
    np.testing.assert_allclose(pulse.waveform(t), np.exp(-0.5 * (t / s) ** 2), atol=1e-3)
    np.testing.assert_allclose(pulse.waveform(t, matched=True), np.exp(-((t / (2 * s)) ** 2)) / math.sqrt(2),
                               rtol=5e-4)


def test_range_compression_gives_the_matched_point_model_detection_subtracts(odd_pass):
    """The cancellation's model (`bp.point_target_echo`, matched) and `bp.range_compress` of a simulated
    echo of the same target must agree: else the neighbours' residues would be modelled with another pulse."""
    target = PAPER_SIM1.targets_radar_m(0)[1]
    one = simulate_pass(odd_pass.radar, odd_pass.geometry, [target],
                        aperture_length_m=PAPER_SIM1.aperture_length_m, speed_m_s=PAPER_SIM1.speed_m_s,
                        rng=np.random.default_rng(1))
    grid = nlcs.focus_grid(one)
    rc = bp.range_compress(one, grid, upsample=4)
    r0 = math.hypot(target[1], target[2] - HEIGHT_M) / grid.cos_squint  # P1: R_c = r0 c_q
    u = target[0] - grid.aperture_centre_m - r0 * grid.sin_squint  # x_M - x_c = u + r0 s_q
    model, _ = bp.point_target_echo(grid, rc.x_rel_m, rc.t_s, u, r0 + grid.sin_squint * u)
    # per pulse the beam gain is the simulator's: compare the shapes, pulse by pulse, where the echo is strong
    strong = np.abs(rc.data).max(axis=1) > 0.5 * np.abs(rc.data).max()
    gain = np.sum(rc.data[strong] * model[strong].conj(), axis=1) / np.sum(np.abs(model[strong]) ** 2, axis=1)
    assert rel_err(gain[:, None] * model[strong], rc.data[strong]) < 0.02


def test_scipy32_matches_the_numpy_oracle_on_a_measured_pulse(odd_pass, odd_focus):
    out = scipy32.nlcs_focus_scipy32(odd_pass)
    assert rel_err(out.image, odd_focus.image) < 1e-4  # 2.5e-7 measured


def test_targets_focused_with_their_measured_pulse_are_located_within_3_mm(odd_pass):
    truth = [(t[0], math.hypot(t[1], t[2] - HEIGHT_M)) for t in PAPER_SIM1.targets_radar_m(0)]
    for algorithm in ("nlcs", "bp"):
        found = pipeline.detect_pass(odd_pass, ProcessingSettings(backend="numpy", algorithm=algorithm))
        assert len(found) == 3
        for x, rc in truth:
            d = min(found, key=lambda d: math.hypot(d.x_m - x, d.rc_m - rc))
            assert math.hypot(d.x_m - x, d.rc_m - rc) < 3.5e-3, (algorithm, d)


@pytest.mark.opencl
def test_the_opencl_engine_matches_the_numpy_oracle_on_a_measured_pulse(engine, odd_pass, odd_focus):
    """NLCS image within the chain tolerance (1e-4, docs/opencl.md), range compression within a stage's
    (1e-5), the BP image within 1e-4. Measured on PoCL (CPU, fp64 phases): NLCS 2.6e-7 (the Gaussian pass:
    2.6e-7), range compression 1.5e-7, BP 6.0e-6."""
    out = engine.nlcs_focus(odd_pass)
    assert rel_err(out.image, odd_focus.image) < 1e-4
    grid = odd_focus.grid
    _, rc = engine.range_compress(odd_pass, grid)
    assert rel_err(rc.data, bp.range_compress(odd_pass, grid).data) < 1e-5
    ref = bp.backprojection_focus(odd_pass, pixel_m=0.02)
    assert rel_err(engine.backprojection_focus(odd_pass, pixel_m=0.02).image, ref.image) < 1e-4


@pytest.mark.opencl
def test_the_engines_neighbour_models_use_the_measured_pulse(engine, odd_pass, odd_focus):
    """2.5e-7 measured on PoCL."""
    echo, x_rel = nlcs.prepare_track(odd_pass, odd_focus.grid)
    rows = nlcs.spectrum_rows(odd_focus.grid, odd_focus.compression)
    want = nlcs.nlcs_model_spectra(odd_focus, x_rel, [echo], rows)
    assert rel_err(engine.nlcs_model_spectra(odd_focus, x_rel, [echo], rows), want) < 1e-4


def test_the_tabulated_waveform_is_the_direct_sum_within_1e_6():
    """3.6e-8 (pulse) and 7e-9 (matched) of the peak measured at 20000 random delays within +-3 ns."""
    t = np.random.default_rng(0).uniform(-3e-9, 3e-9, 2000)
    for matched in (False, True):
        assert np.abs(ODD.waveform(t, matched) - ODD.exact_waveform(t, matched)).max() < 1e-6
