"""Specification of the modified NLCS chain on single point targets (paper section 2.2, method.md C3-C12)."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest

from uwbcl import detect
from uwbcl import geometry as geo
from uwbcl import simulate as sim
from uwbcl.focus import coefficients as coef
from uwbcl.focus import nlcs
from uwbcl.model import SPEED_OF_LIGHT_M_S as C
from uwbcl.model import PassGeometry, RadarParameters
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2

RADAR = RadarParameters()
H = 0.15
REF = np.array(PAPER_SIM1.reference_point_m(0), dtype=float)  # target B of sim1, the scene centre
GEOM = PassGeometry(height_m=H, rotation_table_angle_deg=PAPER_SIM1.rotation_table_angle_deg(0),
                    reference_point_m=tuple(float(c) for c in REF))


def _single_target_pass(target, speed_jitter=0.0, seed=0):
    return sim.simulate_pass(RADAR, GEOM, [target], aperture_length_m=2.0, speed_m_s=0.15,
                             speed_jitter=speed_jitter, rng=np.random.default_rng(seed))


def _half_power_width(cut: np.ndarray, spacing: float, upsample: int = 64) -> float:
    """3 dB width of a band-limited periodic cut, measured on its trigonometric interpolation."""
    n = cut.size
    spec = np.fft.fft(cut)
    pad = np.zeros(n * upsample, dtype=complex)
    half = n // 2
    pad[:half], pad[-(n - half):] = spec[:half], spec[half:]
    mag = np.abs(np.fft.ifft(pad))
    mag /= mag.max()
    k = int(np.argmax(mag))
    above = mag >= 1 / math.sqrt(2)
    lo, hi = k, k
    while above[(lo - 1) % mag.size]:
        lo -= 1
    while above[(hi + 1) % mag.size]:
        hi += 1
    return (hi - lo + 1) * spacing / upsample


@pytest.fixture(scope="module")
def centre_pass():
    return _single_target_pass(REF)


@pytest.fixture(scope="module")
def centre_products(centre_pass):
    return nlcs.nlcs_focus(centre_pass, ac_mode="exact")


@pytest.fixture(scope="module")
def centre_detections(centre_products):
    return detect.detect_nlcs(centre_products)


# --------------------------------------------------------------------------------------------- LRWC
def _range_peaks(s: np.ndarray) -> np.ndarray:
    """Per-pulse range peak in bins, refined by a parabola through the three top samples."""
    a = np.abs(s)
    i = np.clip(np.argmax(a, axis=1), 1, a.shape[1] - 2)
    rows = np.arange(a.shape[0])
    y0, y1, y2 = a[rows, i - 1], a[rows, i], a[rows, i + 1]
    return i + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)


def test_linear_range_walk_correction_removes_the_range_walk(centre_pass):
    grid = nlcs.focus_grid(centre_pass)
    echo, x_rel = nlcs.prepare_track(centre_pass, grid)
    s1 = nlcs.range_fft(echo, grid)
    before = _range_peaks(nlcs.range_ifft(s1, grid))
    after = _range_peaks(nlcs.range_ifft(nlcs.linear_range_walk_correction(s1, x_rel, grid), grid))
    # Over the whole 2 m aperture the residual after LRWC is the range curvature k2 tau^2 (~0.13 m = 3.6 bins
    # at the ends), which LRWC is not meant to remove; over the central 0.8 m the curvature is < 0.6 bin.
    central = np.abs(x_rel) <= 0.4
    aperture = np.ptp(x_rel[central])  # = v T
    expected_walk_bins = aperture * grid.sin_squint / RADAR.range_bin_m  # v sin(theta_q) T: 10.6 bins
    assert np.ptp(before[central]) == pytest.approx(expected_walk_bins, rel=0.05)  # curvature adds < 5 %
    assert np.ptp(after[central]) < 1.0
    # The slope of range vs rail position is -sin(theta_q) before and ~0 after (the curvature is symmetric
    # about the aperture centre, so it does not bias the slope; 0.01 allows for the asymmetric cubic term).
    slope_before = np.polyfit(x_rel[central], before[central] * RADAR.range_bin_m, 1)[0]
    slope_after = np.polyfit(x_rel[central], after[central] * RADAR.range_bin_m, 1)[0]
    assert slope_before == pytest.approx(-grid.sin_squint, abs=0.01)
    assert abs(slope_after) < 0.01


def test_range_fft_and_range_ifft_are_inverse(centre_pass):
    grid = nlcs.focus_grid(centre_pass)
    back = nlcs.range_ifft(nlcs.range_fft(centre_pass.echo, grid), grid)
    np.testing.assert_allclose(back, centre_pass.echo, rtol=0, atol=1e-12)  # FFT round-off on unit samples


# --------------------------------------------------------------------------------------------- resampling
def test_resampling_to_the_uniform_track_is_the_identity_for_uniform_positions(centre_pass):
    grid = nlcs.focus_grid(centre_pass)
    _, x_rel = nlcs.prepare_track(centre_pass, grid)
    rng = np.random.default_rng(0)
    s = rng.standard_normal((x_rel.size, 3)) + 1j * rng.standard_normal((x_rel.size, 3))
    out = nlcs.resample_to_uniform_track(s, x_rel, grid)
    # nodes and outputs coincide up to round-off (1e-16 m), so the Lagrange weights are a Kronecker delta
    np.testing.assert_allclose(out, s, rtol=0, atol=1e-10)


def test_resampling_reproduces_a_smooth_signal_sampled_at_jittered_positions():
    scan = _single_target_pass(REF, speed_jitter=0.1, seed=2)
    grid = nlcs.focus_grid(scan)
    _, x_rel = nlcs.prepare_track(scan, grid)
    assert np.ptp(np.diff(x_rel)) > 0.1 * np.mean(np.diff(x_rel))  # the input really is non-uniform
    # slowly varying in slow time, as after LRWC: periods of 0.5 m and 0.3 m (40-67 pulses per cycle)
    wavenumbers = np.array([2 * np.pi / 0.5, -2 * np.pi / 0.3])

    def signal(x):
        return np.exp(1j * np.outer(x, wavenumbers))

    out = nlcs.resample_to_uniform_track(signal(x_rel), x_rel, grid)
    expected = signal(grid.t_track_s * grid.speed_m_s)
    # 6-point Lagrange error ~ (k dx)^6 / 6! ~ 1e-9 here; the spec is 1e-4
    assert np.max(np.abs(out - expected)) < 1e-4


# --------------------------------------------------------------------------------------------- coefficients
def test_azimuth_phase_series_coefficients_are_the_taylor_coefficients_of_the_exact_phase():
    v, r, lam = 0.15, 2.776, C / 4.3e9
    s = math.sin(math.radians(29.96))
    c_q = math.sqrt(1 - s * s)
    f = np.linspace(-0.3, 0.3, 201)
    x = s + lam * f / (2 * v)
    phi0 = -(4 * np.pi * r / lam) * (c_q * np.sqrt(1 - x**2) + s * x)  # C7, exact under P1
    fit = np.polynomial.polynomial.polyfit(f, (phi0 - phi0[100]) / np.pi, 8)
    eta = coef.azimuth_phase_series(r, v, s, lam)
    # a degree-8 fit over +-0.3 Hz recovers the low coefficients to ~1e-6 relative
    assert float(eta[0]) == 0.0
    for n in (2, 3, 4):
        assert float(eta[n - 1]) == pytest.approx(fit[n], rel=1e-4)


def test_nlcs_coefficients_at_the_sim1_reference_match_the_design_notes():
    v, r, lam = 0.15, 2.776, C / 4.3e9
    s = math.sin(math.radians(29.96))
    k = coef.nlcs_coefficients(r, v, s, lam)
    ka0 = float(coef.azimuth_fm_rate(r, v, s, lam))
    b = v * s / r
    # C9 and C10 print 3-4 significant figures; 1 % covers their rounding (K_a0 -0.17452 is printed -0.1746)
    assert ka0 == pytest.approx(-0.1746, rel=0.01)
    assert b == pytest.approx(0.0270, rel=0.01)
    assert float(k.q3) == pytest.approx(1.57e-3, rel=0.01)
    assert float(k.q4) == pytest.approx(3.18e-5, rel=0.01)
    assert float(k.y3) == pytest.approx(-0.295, rel=0.01)
    assert float(k.y4) == pytest.approx(-0.137, rel=0.01)
    assert float(k.q2) == 0.0 and float(k.eta1) == 0.0  # alpha = 1/2 and P1
    assert float(k.ac_c2) == pytest.approx(18.0, rel=0.01)
    # c3 and c4 are printed with 2 figures: half a unit of the last digit
    assert float(k.ac_c3) == pytest.approx(0.93, abs=0.005)
    assert float(k.ac_c4) == pytest.approx(0.22, abs=0.005)
    # the identity K_a0^2 eta30 = b of C7
    eta30 = float(coef.azimuth_phase_series(r, v, s, lam)[2])
    assert ka0**2 * eta30 == pytest.approx(b, rel=1e-12)


def test_nlcs_coefficients_vary_per_range_bin():
    r = np.array([2.0, 2.776, 3.5])
    k = coef.nlcs_coefficients(r, 0.15, 0.5, C / 4.3e9)
    assert k.y3.shape == (3,) and np.all(np.diff(k.q3) < 0)  # q3 = -K_a0 b / 3 ~ 1/r^2
    ka0 = coef.azimuth_fm_rate(r, 0.15, 0.5, C / 4.3e9)
    np.testing.assert_allclose(ka0 * r, ka0[0] * r[0], rtol=1e-12)  # K_a0 ~ 1/r


# --------------------------------------------------------------------------------------------- point target
def test_a_target_at_the_scene_centre_focuses_at_zero_azimuth_time_and_the_reference_range(
        centre_products, centre_detections):
    grid = centre_products.grid
    assert len(centre_detections) == 1
    d = centre_detections[0]
    t_f = d.image_azimuth_m / grid.speed_m_s
    # within a tenth of a cell (0.1 azimuth cell = 0.75 mm, 0.1 range bin = 3.75 mm); measured 0.01 and 0.02
    assert abs(t_f) < 0.1 * grid.dt_s
    assert abs(d.image_range_m - grid.reference_range_m) < 0.1 * RADAR.range_bin_m
    assert d.x_m == pytest.approx(REF[0], abs=1e-3)  # D4: B within 0.5 mm in nlcs-exact
    assert d.rc_m == pytest.approx(geo.closest_approach_range_m(REF, H), abs=1e-3)


def test_the_focused_point_response_has_the_expected_3db_widths(centre_products):
    image = centre_products.image
    grid = centre_products.grid
    ia, ir = np.unravel_index(np.argmax(np.abs(image)), image.shape)
    range_width = _half_power_width(image[ia, :], RADAR.range_bin_m)
    azimuth_width = _half_power_width(image[:, ir], grid.track_spacing_m)  # v * t-width, cross-range
    # Gaussian pulse after its matched filter: sigma sqrt(2 ln 2) c = 0.100 m; 10 % for the sampling/windowing
    assert RADAR.pulse_sigma_s * math.sqrt(2 * math.log(2)) * C == pytest.approx(0.100, abs=5e-4)
    assert 0.09 <= range_width <= 0.11
    # D4: 5.9-9.3 cm for nlcs-exact (paper: 0.07 m)
    assert 0.05 <= azimuth_width <= 0.10


def test_nlcs_focus_distortion_is_inverted_by_the_geometry_correction():
    target = REF + np.array([0.6, 0.0, 0.0])  # same range cell, v t_n = 0.6 m: t_n = +4 s (target C of sim1)
    scan = _single_target_pass(target)
    products = nlcs.nlcs_focus(scan)
    grid = products.grid
    t_n, _ = geo.target_to_p1(target, scan.aperture_centre_m, H, math.asin(grid.sin_squint), grid.speed_m_s)
    assert t_n == pytest.approx(4.0, abs=1e-9)
    (d,) = detect.detect_nlcs(products)
    raw_shift = d.image_azimuth_m - grid.speed_m_s * t_n
    # C12: t_f = t_n + (b/2) t_n^2 + ... puts the raw peak ~30 mm further along track (series: 32 mm)
    assert 0.020 < raw_shift < 0.040
    # after inverting t_f(t_n) the target is back to within 3 mm (measured 0.5 mm in x, 1.2 mm in R_c)
    assert d.x_m == pytest.approx(target[0], abs=3e-3)
    assert d.rc_m == pytest.approx(geo.closest_approach_range_m(target, H), abs=3e-3)
    assert d.t_n_s == pytest.approx(t_n, abs=3e-3 / grid.speed_m_s)


@pytest.mark.parametrize("ac_mode", ["exact", "series"])
def test_exact_and_series_azimuth_compression_both_focus_the_centre_target(centre_pass, centre_products,
                                                                         ac_mode):
    products = centre_products if ac_mode == "exact" else nlcs.nlcs_focus(centre_pass, ac_mode=ac_mode)
    detections = detect.detect_nlcs(products)
    assert len(detections) == 1
    d = detections[0]
    # D4 gives <= 3 mm for B in either mode; measured < 1 mm
    assert d.x_m == pytest.approx(REF[0], abs=3e-3)
    assert d.rc_m == pytest.approx(geo.closest_approach_range_m(REF, H), abs=3e-3)
    image = products.image
    _, ir = np.unravel_index(np.argmax(np.abs(image)), image.shape)
    # a focused, not smeared, peak
    assert _half_power_width(image[:, ir], products.grid.track_spacing_m) < 0.10


def test_an_unknown_azimuth_compression_mode_is_rejected(centre_pass):
    with pytest.raises(ValueError, match="azimuth compression mode"):
        nlcs.nlcs_focus(centre_pass, ac_mode="taylor")


def test_without_azimuth_compression_the_target_is_not_focused(centre_pass, centre_products):
    """Negative control for the width test: the same chain with an all-pass H8 leaves a smeared response."""
    grid = centre_products.grid
    k = centre_products.coefficients
    echo, x_rel = nlcs.prepare_track(centre_pass, grid)
    s = nlcs.range_fft(echo, grid)
    s = nlcs.linear_range_walk_correction(s, x_rel, grid)
    s = nlcs.resample_to_uniform_track(s, x_rel, grid)
    s = nlcs.az_fft(nlcs.pad_azimuth(s, grid))
    s = nlcs.range_ifft(nlcs.secondary_range_compression(s, grid), grid)
    s = nlcs.az_fft(nlcs.nlcs_scaling(nlcs.az_ifft(nlcs.nlcs_filter(s, k, grid)), k, grid))
    unfocused = nlcs.az_ifft(s)  # H8 left out
    peak_ratio = np.abs(unfocused).max() / np.abs(centre_products.image).max()
    _, ir = np.unravel_index(np.argmax(np.abs(unfocused)), unfocused.shape)
    width = _half_power_width(unfocused[:, ir], grid.track_spacing_m)
    # measured: 0.27 of the focused peak and a 1.0 m wide response (vs 0.07 m focused)
    assert peak_ratio < 0.5
    assert width > 0.5


# --------------------------------------------------------------------------------------------- H8 fit
def _fit_azimuth_compression_loop(x_ref, k, grid, degree=8):
    """The specification of nlcs.fit_azimuth_compression: one bin at a time, np.unwrap and polyfit on the
    bin's own strong segment (the implementation before it was vectorised; that one raised on a bin with no
    strong sample, here such a bin keeps the series like one whose segment misses f_a = 0)."""
    f = grid.f_azimuth_hz
    f_scale = 0.5 / grid.dt_s
    n = k.r_m.size
    series = nlcs.series_azimuth_compression(k, grid)
    poly = np.zeros((n, degree + 1))
    f_lo, f_hi = series.f_lo_hz.copy(), series.f_hi_hz.copy()
    mag = np.abs(x_ref)
    i0 = grid.n_azimuth // 2
    for j in range(n):
        strong = (mag[:, j] > 1e-2 * mag[:, j].max()) & (f >= f_lo[j]) & (f <= f_hi[j])
        sel = np.flatnonzero(strong)
        if sel.size == 0 or not sel[0] <= i0 <= sel[-1]:
            poly[j, :5] = series.poly[j] * f_scale ** np.arange(5)
            continue
        lo, hi = sel[0], sel[-1]
        seg = slice(lo, hi + 1)
        phase = np.unwrap(np.angle(x_ref[seg, j]))
        phase -= phase[i0 - lo]
        poly[j] = np.polynomial.polynomial.polyfit(f[seg] / f_scale, phase, degree, w=np.sqrt(mag[seg, j]))
        f_lo[j], f_hi[j] = f[lo], f[hi]
    return nlcs.AzimuthCompression(poly=poly, f_scale_hz=f_scale, f_lo_hz=f_lo, f_hi_hz=f_hi)


def _grid_and_coefficients(scan):
    grid = nlcs.focus_grid(scan)
    return grid, coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)


def _assert_same_compression(got, want, grid):
    """Same bands bit for bit, the same series rows, and the fitted H8 phase within 1e-9 rad over each
    band."""
    assert got.f_scale_hz == want.f_scale_hz
    np.testing.assert_array_equal(got.f_lo_hz, want.f_lo_hz)
    np.testing.assert_array_equal(got.f_hi_hz, want.f_hi_hz)
    series = (want.poly[:, 5:] == 0).all(axis=1) & (want.f_lo_hz == nlcs.doppler_band_hz(grid)[0])
    np.testing.assert_array_equal(got.poly[series], want.poly[series])
    f = grid.f_azimuth_hz
    inside = (f[:, None] >= want.f_lo_hz) & (f[:, None] <= want.f_hi_hz)
    # measured: < 1e-12 rad on the paper passes and on the synthetic spectra
    assert np.abs(np.where(inside, got.phase(f) - want.phase(f), 0.0)).max() < 1e-9


@pytest.mark.parametrize("scenario", [PAPER_SIM1, PAPER_SIM2], ids=lambda s: s.name)
@pytest.mark.parametrize("which", [0, 3])
@pytest.mark.parametrize("dtype", [np.complex128, np.complex64])  # complex64: engines without fp64
def test_the_vectorised_h8_fit_is_the_per_bin_fit_on_the_paper_reference_spectra(scenario, which, dtype):
    scan = scenario.simulate(snr_db=10.0, speed_jitter=0.1, seed=0)[which]
    grid, k = _grid_and_coefficients(scan)
    ref = nlcs.az_fft(nlcs.slow_time_point_response(k.r_m, 0.0, grid, scan.radar.antenna_aperture_m,
                                                    rail_only=False))
    x_ref = nlcs._azimuth_nlcs_chain(ref, k, grid).astype(dtype)
    want = _fit_azimuth_compression_loop(x_ref, k, grid)
    assert (want.f_lo_hz > nlcs.doppler_band_hz(grid)[0]).all()  # every bin fitted: the paper's case
    _assert_same_compression(nlcs.fit_azimuth_compression(x_ref, k, grid), want, grid)


def _synthetic_reference_spectra(grid, n, seed=0):
    """Gaussian |X| with a noisy polynomial phase (many wraps), the bump chosen per bin (j mod 8) so that the
    strong segment: 0 spans the whole band, 1/2 misses f_a = 0 above/below (series kept), 3/4 touches the
    lower/upper band edge, 5 is two bumps with a weak stretch (holding f_a = 0) between them, 6 has fewer
    samples than coefficients (polyfit's rank-deficient solution), 7 is a shifted noisy bump; bin 7 is all
    zero."""
    rng = np.random.default_rng(seed)
    f = grid.f_azimuth_hz[:, None]
    case = np.arange(n) % 8
    bump = {0: (0.0, 3.0), 1: (1.0, 0.2), 2: (-1.0, 0.2), 3: (-1.5, 0.6), 4: (1.2, 0.5), 6: (0.0, 0.004),
            7: (0.3, 0.8)}
    centre = np.array([bump.get(c, (0.0, 1.0))[0] for c in case])
    width = np.array([bump.get(c, (0.0, 1.0))[1] for c in case])
    mag = np.exp(-0.5 * ((f - centre) / width) ** 2)
    two = case == 5
    mag[:, two] = (np.exp(-0.5 * ((f + 0.8) / 0.15) ** 2) + np.exp(-0.5 * ((f - 0.6) / 0.15) ** 2) + 1e-4)
    mag *= np.abs(1 + 0.05 * rng.standard_normal(mag.shape))
    mag[:, 7] = 0.0
    phase = (rng.uniform(-30, 30, n) * f**2 + rng.uniform(-10, 10, n) * f**3 + rng.uniform(-np.pi, np.pi, n)
             + 0.05 * rng.standard_normal(mag.shape))
    return mag * np.exp(1j * phase)


@pytest.mark.parametrize("dtype", [np.complex128, np.complex64])
def test_the_vectorised_h8_fit_is_the_per_bin_fit_on_synthetic_spectra_with_every_kind_of_band(dtype):
    grid, k = _grid_and_coefficients(PAPER_SIM1.simulate()[0])
    x_ref = _synthetic_reference_spectra(grid, k.r_m.size).astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", np.exceptions.RankWarning)  # case 6, in both
        want = _fit_azimuth_compression_loop(x_ref, k, grid)
        got = nlcs.fit_azimuth_compression(x_ref, k, grid)
    _assert_same_compression(got, want, grid)
    # the synthetic spectra do reach every branch
    f, band = grid.f_azimuth_hz, nlcs.doppler_band_hz(grid)
    case = np.arange(k.r_m.size) % 8
    series = want.f_lo_hz == band[0]
    assert series[(case == 1) | (case == 2)].all() and series[7]
    assert not series[(case == 0) | (case == 3) | (case == 4) | (case == 5) | (case == 6)].any()
    edge_lo, edge_hi = f[f >= band[0]][0], f[f <= band[1]][-1]
    assert (want.f_lo_hz[case == 0] == edge_lo).all() and (want.f_hi_hz[case == 0] == edge_hi).all()
    assert (want.f_lo_hz[case == 3] == edge_lo).all() and (want.f_hi_hz[case == 4] == edge_hi).all()
    assert ((want.f_hi_hz - want.f_lo_hz)[case == 6] < 8.5 * (f[1] - f[0])).all()  # < 9 samples


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_fast_unwrap_is_np_unwrap_of_each_column_from_its_start_bit_for_bit(dtype):
    rng = np.random.default_rng(1)
    p = rng.uniform(-np.pi, np.pi, (500, 7))
    p[:8, 0] = [0.0, np.pi, 0.0, -np.pi, np.pi, -np.pi, 0.0, np.pi]  # steps of exactly +-pi, both signs
    p[::3, 1] = np.pi
    p[100, 2] = np.nan
    p[:, 3] = np.angle(np.exp(1j * 40 * np.linspace(-1, 1, 500) ** 2))  # a smooth phase wrapped many times
    p[:, 4] = np.cumsum(rng.uniform(-3, 3, 500))
    p = p.astype(dtype)
    np.testing.assert_array_equal(nlcs._unwrap_from(p, np.zeros(7, dtype=int)), np.unwrap(p, axis=0))
    start = np.array([0, 5, 150, 37, 250, 499, 1])
    got = nlcs._unwrap_from(p, start)
    assert got.dtype == dtype
    for j, s in enumerate(start):
        np.testing.assert_array_equal(got[s:, j], np.unwrap(p[s:, j]))
        np.testing.assert_array_equal(got[:s, j], p[:s, j])


def test_a_bin_whose_strong_segment_misses_zero_doppler_keeps_the_series_phase_law():
    scan = PAPER_SIM1.simulate(seed=0)[0]
    grid = nlcs.focus_grid(scan)
    k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
    x_ref = nlcs.reference_spectra(k, grid, scan.radar.antenna_aperture_m)
    x_ref[: grid.n_azimuth // 2 + 1, 7] = 0  # bin 7: nothing strong at or below f_a = 0
    ac = nlcs.fit_azimuth_compression(x_ref, k, grid)
    series = nlcs.series_azimuth_compression(k, grid)
    f = grid.f_azimuth_hz
    np.testing.assert_allclose(ac.phase(f)[:, 7], series.phase(f)[:, 7], rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------------------------------- the azimuth axis (D5)
def test_the_largest_h6_delay_is_that_of_a_dense_sampling_of_the_band():
    grid, k = _grid_and_coefficients(PAPER_SIM1.simulate()[0])
    for lo, hi in ((-2.7, 2.0), (0.5, 3.0), (-4.0, -1.0)):
        dense = np.abs(nlcs.h6_group_delay_s(np.linspace(lo, hi, 20001), k)).max()
        assert nlcs.max_h6_delay_s(lo, hi, k) == pytest.approx(dense, rel=1e-6)


def test_the_paper_passes_get_1024_azimuth_rows_and_a_2048_row_reference_axis():
    for scenario in (PAPER_SIM1, PAPER_SIM2):
        scan = scenario.simulate()[0]
        grid = nlcs.focus_grid(scan)
        assert grid.n_azimuth == 1024
        assert grid.n_azimuth * grid.dt_s >= 3.0 * nlcs.azimuth_half_support_s(grid)
        assert nlcs.reference_grid(grid, scan.radar.antenna_aperture_m).n_azimuth == 2048
        eight_fold = nlcs.focus_grid(scan, azimuth_oversampling=8).n_azimuth
        assert eight_fold == (4096 if scenario is PAPER_SIM1 else 2048)


def test_a_broad_beam_is_focused_on_the_processed_beam_with_a_bounded_axis_and_the_same_target():
    """C6b: a 0.05 m aperture at 4.3 GHz (its main lobe reaches endfire) is processed as the aperture whose
    first null is at 35 deg; the 0.14 m antenna keeps its own beam. Without C6b the broad beam's axis was
    16384 rows."""
    broad = dataclasses.replace(RADAR, antenna_aperture_m=0.05)
    scans = [sim.simulate_pass(radar, GEOM, [REF], aperture_length_m=2.0, speed_m_s=0.15,
                               rng=np.random.default_rng(0)) for radar in (RADAR, broad)]
    assert nlcs.beam_aperture_m(scans[0]) == RADAR.antenna_aperture_m
    null = geo.beam_half_width_rad(nlcs.beam_aperture_m(scans[1]), broad.wavelength_m)
    assert math.degrees(null) == pytest.approx(35.0)
    grids = [nlcs.focus_grid(s) for s in scans]
    assert grids[1].n_azimuth <= 2 * grids[0].n_azimuth
    assert grids[1].doppler_band[1] < math.sin(GEOM.rotation_table_angle_rad + null) + 1e-12
    found = [detect.detect_nlcs(nlcs.nlcs_focus(s))[0] for s in scans]
    assert abs(found[1].x_m - found[0].x_m) < 1e-3 and abs(found[1].rc_m - found[0].rc_m) < 1e-3


def test_the_shorter_azimuth_axis_focuses_the_paper_pass_as_the_8x_padding_does():
    scan = PAPER_SIM1.simulate()[0]  # noise-free
    short = nlcs.nlcs_focus(scan)
    long = nlcs.nlcs_focus(scan, grid=nlcs.focus_grid(scan, azimuth_oversampling=8))
    n, m = short.grid.n_azimuth, long.grid.n_azimuth
    rail = np.arange(n // 2 - short.grid.n_track // 2 - 40, n // 2 + short.grid.n_track // 2 + 40)
    ref = long.image[m // 2 - n // 2:][rail]
    assert np.abs(short.image[rail] - ref).max() < 1e-3 * np.abs(ref).max()  # measured 2.5e-4


def test_the_reference_on_its_own_axis_is_the_untruncated_reference_at_the_grid_frequencies():
    scan = PAPER_SIM1.simulate()[0]
    grid = nlcs.focus_grid(scan)
    k = coef.nlcs_coefficients(grid.range_bins_m, grid.speed_m_s, grid.sin_squint, grid.wavelength_m)
    aperture = scan.radar.antenna_aperture_m
    wide = dataclasses.replace(grid, n_azimuth=8192)
    untruncated = nlcs._azimuth_nlcs_chain(
        nlcs.az_fft(nlcs.slow_time_point_response(k.r_m, 0.0, wide, aperture, rail_only=False)), k, wide)
    ref = nlcs.on_grid_frequencies(untruncated, wide, grid)
    out = nlcs.reference_spectra(k, grid, aperture)
    assert np.abs(out - ref).max() < 1e-5 * np.abs(ref).max()  # measured 5e-7
