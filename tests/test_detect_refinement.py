"""Specification of the NLCS peak refinement: the Newton maximum of the band-limited image interpolant
(`detect.refine.TrigInterpolant`) and the vectorised t_f(t_n) calibration
(`detect.calibration.focus_position`).

Both replaced derivative-free searches (Nelder-Mead on the interpolant, one bounded scalar search per
simulated target). Those searches are kept here as references: the new refinements must find the same maxima,
and the detections of whole paper passes must not move.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize

from uwbcl import detect, pipeline
from uwbcl.detect import calibration, peaks, refine
from uwbcl.focus import nlcs
from uwbcl.records import DetectionSettings, ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1, PAPER_SIM2


# --------------------------------------------------------------------------------------------- references
def nelder_mead_maximise(interpolant, a0, b0, step=0.5):
    """Derivative-free reference: Nelder-Mead on |V|^2 (the former refinement, tolerances tightened)."""
    res = optimize.minimize(lambda p: -abs(interpolant.value(p[0], p[1])) ** 2, x0=[a0, b0],
                            method="Nelder-Mead",
                            options={"xatol": 1e-9, "fatol": 1e-30, "maxiter": 4000,
                                     "initial_simplex": [[a0, b0], [a0 + step, b0], [a0, b0 + step]]})
    a, b = res.x
    return float(a), float(b), interpolant.value(a, b)


def reference_columns(products, r_m, t_n_s):
    """The former calibration chain, stage by stage: focused spectra (centred f_a) of targets at (r, t_n)
    through the chain of the bin nearest r, their coarse t_f and the bin's H8 band."""
    grid = products.grid
    bins = grid.range_bins_m
    j = int(np.clip(np.rint((r_m - bins[0]) / (bins[1] - bins[0])), 0, bins.size - 1))
    k = nlcs.select_bins(products.coefficients, [j])
    ac = nlcs.select_bins(products.compression, [j])
    rd = nlcs.az_fft(nlcs.slow_time_point_response(r_m, t_n_s, grid, products.aperture_m))
    y = nlcs.azimuth_compression(nlcs._azimuth_nlcs_chain(rd, k, grid), ac, grid)
    coarse = grid.t_azimuth_s[np.argmax(np.abs(nlcs.az_ifft(y)), axis=0)]
    band = (grid.f_azimuth_hz >= ac.f_lo_hz[0]) & (grid.f_azimuth_hz <= ac.f_hi_hz[0])
    return y, coarse, band


def scalar_search_focus_position(products, r_m, t_n_s):
    """The former focus_position: one bounded scalar search of |Y(t)| per target, +-dt about the coarse
    peak."""
    grid = products.grid
    y, coarse, band = reference_columns(products, r_m, t_n_s)
    f = grid.f_azimuth_hz[band]
    return np.array([
        optimize.minimize_scalar(lambda t, col=y[band, i]: -abs(np.exp(2j * np.pi * f * t) @ col),
                                 bounds=(coarse[i] - grid.dt_s, coarse[i] + grid.dt_s),
                                 method="bounded", options={"xatol": 1e-7}).x
        for i in range(y.shape[1])])


def derivative_root_focus_position(products, r_m, t_n_s):
    """t_f as the root of d|Y|^2/dt = 2 Re(Y* Y') in (t_c - dt, t_c + dt), by bracketing (brentq): resolves
    the peak far below the ~1e-8 s that a search on the flat |Y| itself can."""
    grid = products.grid
    y, coarse, band = reference_columns(products, r_m, t_n_s)
    w = 2j * np.pi * grid.f_azimuth_hz[band]
    out = []
    for i in range(y.shape[1]):
        col = y[band, i]

        def slope(t, col=col):
            e = np.exp(w * t)
            return ((e @ col).conjugate() * ((w * e) @ col)).real

        lo, hi = coarse[i] - grid.dt_s, coarse[i] + grid.dt_s
        assert slope(lo) > 0 > slope(hi)  # the bracket holds the peak
        out.append(optimize.brentq(slope, lo, hi, xtol=1e-14, rtol=1e-15))
    return np.array(out)


# --------------------------------------------------------------------------------------------- synthetic peak
N_AZ, N_R = 256, 32
A_BAND = np.arange(-20, 13)  # azimuth spectral rows, off-centre like the NLCS band (centre -4)
R_BAND = np.arange(-6, 7)
PEAK = (100.37, 13.81)


def synthetic(a, b):
    """A 2-D band-limited peak: sum_k sum_l w_k v_l exp(2 pi i (k (a - a*) / n + l (b - b*) / m) + i phi) with
    weights symmetric about each band's centre, so that |V| is largest, sum w sum v, exactly at (a*, b*)."""
    w = np.hanning(A_BAND.size + 2)[1:-1]
    v = np.hanning(R_BAND.size + 2)[1:-1]
    ea = np.exp(2j * np.pi * np.multiply.outer(np.asarray(a, float) - PEAK[0], A_BAND) / N_AZ) @ w
    eb = np.exp(2j * np.pi * np.multiply.outer(np.asarray(b, float) - PEAK[1], R_BAND) / N_R) @ v
    return np.multiply.outer(ea, eb) * np.exp(0.7j)


@pytest.fixture(scope="module")
def synthetic_interpolant():
    image = synthetic(np.arange(N_AZ), np.arange(N_R))
    band = ((A_BAND[0] - 1) / N_AZ, (A_BAND[-1] + 1) / N_AZ)
    interp = refine.TrigInterpolant.from_image(image, band)
    assert interp.coeffs.shape == (A_BAND.size + 2, N_R)
    return interp


def test_the_interpolant_is_the_band_limited_image_between_its_samples(synthetic_interpolant):
    rng = np.random.default_rng(0)
    for a, b in rng.uniform([0, 0], [N_AZ, N_R], size=(20, 2)):
        assert synthetic_interpolant.value(a, b) == pytest.approx(synthetic(a, b), abs=1e-12)


def test_the_interpolant_can_be_built_from_spectra_alone(synthetic_interpolant):
    same = refine.TrigInterpolant(synthetic_interpolant.coeffs.copy(), synthetic_interpolant.ka.copy(),
                                  synthetic_interpolant.kb.copy())
    assert same.maximise(100.0, 14.0) == synthetic_interpolant.maximise(100.0, 14.0)


def test_newton_finds_the_known_maximum_of_a_band_limited_peak(synthetic_interpolant):
    a, b, val = synthetic_interpolant.maximise(100.0, 14.0)
    assert abs(a - PEAK[0]) < 1e-7 and abs(b - PEAK[1]) < 1e-7
    assert val == pytest.approx(synthetic(*PEAK), rel=1e-12)


def test_newton_climbs_from_where_the_surface_is_not_concave(synthetic_interpolant):
    a0, b0 = PEAK[0] + 4.0, PEAK[1] - 1.8
    _, _, _, hess = synthetic_interpolant._local(a0, b0)
    assert np.linalg.eigvalsh(hess)[-1] > 0  # no Newton step here: the trust region must carry it
    a, b, _ = synthetic_interpolant.maximise(a0, b0)
    assert abs(a - PEAK[0]) < 1e-7 and abs(b - PEAK[1]) < 1e-7


# --------------------------------------------------------------------------------------------- paper images
@pytest.fixture(scope="module")
def paper_products():
    """The first pass of each paper scenario (noise-free) and its NLCS focus."""
    return [(scan, nlcs.nlcs_focus(scan)) for scan in (PAPER_SIM1.simulate(seed=1)[0],
                                                       PAPER_SIM2.simulate(seed=1)[0])]


def _peaks(products):
    grid = products.grid
    mag = np.abs(products.image)
    valid = np.zeros(mag.shape, dtype=bool)
    valid[np.abs(grid.t_azimuth_s) <= 0.5 * (grid.n_track - 1) * grid.dt_s, 2:-2] = True
    dr = grid.range_bins_m[1] - grid.range_bins_m[0]
    found, _ = peaks.local_peaks(mag, valid, (grid.track_spacing_m, dr), DetectionSettings())
    return found


def test_newton_maximum_of_a_focused_image_is_the_nelder_mead_maximum(paper_products):
    for _, products in paper_products:
        interp = refine.TrigInterpolant.from_image(products.image,
                                                   nlcs.spectrum_band(products.grid, products.compression))
        peaks = _peaks(products)
        assert len(peaks) == 3
        for i, j in peaks:
            a, b, val = interp.maximise(float(i), float(j))
            a_ref, b_ref, val_ref = nelder_mead_maximise(interp, float(i), float(j))
            # measured <= 9e-7 cell: the simplex's own resolution of a flat maximum
            assert abs(a - a_ref) < 1e-5 and abs(b - b_ref) < 1e-5
            assert abs(val) >= abs(val_ref) * (1 - 1e-12)
            assert abs(a - i) < 1 and abs(b - j) < 1


def test_vectorised_focus_position_is_the_per_target_search(paper_products):
    _, products = paper_products[0]
    grid = products.grid
    half = 0.5 * (grid.n_track - 1) * grid.dt_s
    t_n = np.linspace(-half, half, 13)
    r = grid.range_bins_m[[30, 45, 100]] + 0.011
    together = calibration.focus_position(products, r, t_n)
    assert together.shape == (3, 13)
    for row, r_m in zip(together, r):
        np.testing.assert_allclose(calibration.focus_position(products, r_m, t_n), row, rtol=0, atol=1e-12)
        # the former search stops at xatol = 1e-7 s (measured differences up to 1.1e-7 s: 17 nm along track)
        np.testing.assert_allclose(row, scalar_search_focus_position(products, r_m, t_n), rtol=0, atol=2e-7)
        np.testing.assert_allclose(row, derivative_root_focus_position(products, r_m, t_n), rtol=0, atol=1e-9)


def test_a_calibration_target_with_two_equal_lobes_starts_on_the_same_lobe_whatever_the_rounding():
    # a real PulsON 440 pass (t_n = 0, 8.8 m): two maxima at +-5 samples, 1.1e-4 above the dip between them;
    # float32 rounding picked one lobe on the engine and the other in numpy, and the calibration moved 1 cm
    t = np.fft.ifftshift((np.arange(64) - 32) * 0.02)  # FFT order, as the focusers hold it
    lobes = 1.0 - (np.abs(t) - 0.1) ** 2  # two equal maxima, at t = +-0.1 s
    rng = np.random.default_rng(0)
    picks = {float(nlcs.coarse_focus_times((lobes * (1 + 1e-7 * rng.standard_normal(t.size)))[None, :], t,
                                           np.array([0.0]))[0]) for _ in range(50)}
    assert len(picks) == 1 and abs(abs(picks.pop()) - 0.1) < 1e-12
    # off-centre targets take the lobe nearest their t_n; a clear single maximum is the largest sample
    both = nlcs.coarse_focus_times(np.vstack([lobes, lobes]), t, np.array([-0.07, 0.07]))
    np.testing.assert_allclose(both, [-0.1, 0.1], atol=1e-12)
    single = np.exp(-((t - 0.24) / 0.1) ** 2)
    assert nlcs.coarse_focus_times(single[None, :], t, np.array([-0.5]))[0] == t[np.argmax(single)]


def test_calibration_spectra_are_the_focusing_chains(paper_products):
    _, products = paper_products[1]
    grid = products.grid
    t_n = np.linspace(-1.0, 1.0, 5)
    r = grid.range_bins_m[[20, 64]] + 0.004
    f, y, coarse = nlcs.calibration_spectra(products, r, t_n)
    f_ref = np.fft.ifftshift(grid.f_azimuth_hz)
    rows = np.isin(f_ref, f)
    for i, r_m in enumerate(r):
        y_ref, coarse_ref, _ = reference_columns(products, r_m, t_n)
        y_ref = np.fft.ifftshift(y_ref, axes=0)
        cols = slice(i * t_n.size, (i + 1) * t_n.size)
        np.testing.assert_allclose(y[:, cols], y_ref[rows], rtol=0, atol=1e-12 * np.abs(y_ref).max())
        assert not np.any(y_ref[~rows])  # H8 is zero on the rows left out
        np.testing.assert_array_equal(coarse[cols], coarse_ref)


def test_several_peaks_are_inverted_at_once_with_the_same_cache(paper_products):
    _, products = paper_products[0]
    products.focus_calibration.clear()
    r = products.grid.range_bins_m[[40, 41, 90]] + 0.002
    t_f = np.array([-1.5, 0.2, 3.0])
    t_n = calibration.invert_focus_position(products, r, t_f)
    assert set(products.focus_calibration) == {(b, 5) for b in (40, 41, 42, 90, 91)}  # the bins around each r
    for x, tf, tn in zip(r, t_f, t_n):
        assert calibration.invert_focus_position(products, x, tf) == tn
    assert len(products.focus_calibration) == 5


def test_the_inverse_is_each_bins_calibration_at_its_centre_and_linear_between_bins(paper_products):
    _, products = paper_products[0]
    grid = products.grid
    bins = grid.range_bins_m
    half = 0.5 * (grid.n_track - 1) * grid.dt_s
    t_n = np.linspace(-half, half, calibration.CALIBRATION_TARGETS)
    t_f = calibration.focus_position(products, bins[[50, 51]], t_n)
    fits = [np.polynomial.polynomial.polyfit(t_f[i], t_n, calibration.CALIBRATION_DEGREE) for i in (0, 1)]
    at = 0.8 * half
    lo, hi = (np.polynomial.polynomial.polyval(at, c) for c in fits)
    for w in (0.0, 0.3, 0.999):
        got = calibration.invert_focus_position(products, bins[50] + w * (bins[1] - bins[0]), at)
        assert got == pytest.approx((1 - w) * lo + w * hi, abs=1e-12)
    # continuous where the nearest bin changes (a nearest-bin inverse jumps there)
    mid = bins[50] + 0.5 * (bins[1] - bins[0])
    step = calibration.invert_focus_position(products, mid + 1e-9, at) - calibration.invert_focus_position(
        products, mid - 1e-9, at)
    assert abs(step) < 1e-9


# --------------------------------------------------------------------------------------------- whole passes
@pytest.mark.parametrize("scenario", [PAPER_SIM1, PAPER_SIM2], ids=lambda s: s.name)
def test_detections_of_whole_passes_match_the_derivative_free_refinement(scenario, monkeypatch):
    """detect_pass with the new refinements against detect_pass with the former ones (Nelder-Mead on the
    interpolant, a scalar search per calibration target), on every pass."""
    settings = ProcessingSettings(backend="numpy")
    for scan in scenario.simulate(seed=1):
        new = pipeline.detect_pass(scan, settings)
        with monkeypatch.context() as m:
            m.setattr(refine.TrigInterpolant, "maximise", nelder_mead_maximise)
            m.setattr(calibration, "focus_position", lambda products, r_m, t_n_s, focuser=None: np.array(
                [scalar_search_focus_position(products, x, t_n_s) for x in np.atleast_1d(r_m)]))
            ref = pipeline.detect_pass(scan, settings)
        assert len(new) == len(ref) == 3
        for d, e in zip(new, ref):
            # measured <= 2e-9 m (3.4e-8 m against the former, looser tolerances); the paper's errors are mm
            assert abs(d.x_m - e.x_m) < 1e-5 and abs(d.rc_m - e.rc_m) < 1e-5
            assert d.amplitude == pytest.approx(e.amplitude, rel=1e-9)


# --------------------------------------------------------------------------------- one maximum, one target
def test_points_within_the_tolerance_of_a_stronger_one_are_dropped_and_exempt_points_kept():
    x, y = np.array([0.0, 0.001, 1.0, 1.0005, 3.0]), np.zeros(5)
    strength = [1.0, 2.0, 5.0, 5.0, 1.0]
    # 0 is within 2 mm of the stronger 1; 3 ties with 2 and the earlier stays; 4 is alone
    assert detect.distinct_positions(x, y, strength, 0.002) == [1, 2, 4]
    assert detect.distinct_positions(x, y, strength, 0.002, exempt={0, 3}) == [0, 1, 2, 3, 4]
    assert detect.distinct_cells([(5.0, 7.0, 2j), (5.1, 7.1, 3.0 + 0j), (9.0, 7.0, 1.0 + 0j)]) == \
        [(5.1, 7.1, 3.0 + 0j), (9.0, 7.0, 1.0 + 0j)]


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
def test_two_pixel_peaks_of_one_response_give_one_detection(algorithm, monkeypatch):
    """A broad or aliased response (a short aperture at long range, a track too coarse for the wavelength)
    can hold two pixel maxima that refine to one sub-cell maximum: that is one target, not two copies (the
    real P440 file imported with an absurd speed once gave one position nine times)."""
    settings = ProcessingSettings(backend="numpy", algorithm=algorithm)
    scan = PAPER_SIM1.simulate(seed=1)[0]
    clean = pipeline.detect_pass(scan, settings)
    find = peaks.nlcs_peaks if algorithm == "nlcs" else peaks.bp_peaks

    def doubled(*args, **kwargs):  # every peak found again from the next pixel along azimuth
        pixels, floor = find(*args, **kwargs)
        return [p for i, j in pixels for p in ((i, j), (i + 1, j))], floor

    monkeypatch.setattr(peaks, "nlcs_peaks" if algorithm == "nlcs" else "bp_peaks", doubled)
    again = pipeline.detect_pass(scan, settings)
    assert len(again) == len(clean) == 3
    for d, e in zip(again, clean):
        assert abs(d.x_m - e.x_m) < 1e-4 and abs(d.rc_m - e.rc_m) < 1e-4
