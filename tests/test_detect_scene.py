"""Detection among a real scene's coupling and clutter (issue 13 item 4): the region of interest in R_c, the
CFAR-like threshold over each R_c bin's median, and the bound on neighbour cancellation. The range bounds and
the bound on cancellation are off by default; the CFAR threshold is on (12 dB) and leaves the simulated paper
scenarios' detections as they were without it.

Measured on the PulsON-like pass below (numpy): NLCS reports the two reflectors (R_c 2.404, 2.405 m; truth
2.405) and the coupling at R_c 1.91 m (3 detections); BP the reflectors and four coupling peaks along
R_c 1.99-2.01 m (6). With min_range_m = 2.2, with cfar_db = 10, or both, each reports the two reflectors only.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbcl import archive, cli, config, pipeline
from uwbcl.detect import cancel, peaks
from uwbcl.importers import synthetic
from uwbcl.records import ConfigError, DetectionSettings, ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1

TARGETS_M = np.array([[0.786, -2.4, 0.3], [1.986, -2.4, 0.3]])
HEIGHT_M = 0.15
RC_TRUE_M = math.hypot(2.4, 0.3 - HEIGHT_M)  # 2.405 m; the coupling is at 2.0 m
COUPLING_M = (1.8, 2.2)


@pytest.fixture(scope="module")
def pulson_pass(tmp_path_factory):
    """The PulsON-like pass of tests/test_p440_import.py (coupling at 2 m, clutter at 1.3, 3.6 and 4.4 m),
    imported with its delay calibrated."""
    root = tmp_path_factory.mktemp("scene")
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0), height_m=HEIGHT_M)
    scan_file, positions = synthetic.write_recording(root, scene)
    site = root / "site.toml"
    site.write_text(synthetic.IMPORT_SITE_TOML)
    rc = cli.main(["import", "p440", str(scan_file), "--out", str(root / "out"),
                   "--positions", str(positions), "--config", str(site),
                   "--pass-start-time", "2026-11-23T06:00:00Z", "--range-delay-s", "2.3e-9"])
    assert rc == 0
    (path,) = archive.find_pass_files(root / "out")
    return archive.read_pass(path)


def _detect(scan, algorithm: str, **detection):
    settings = ProcessingSettings(backend="numpy", algorithm=algorithm,
                                  detection=DetectionSettings(**detection))
    return pipeline.detect_pass(scan, settings)


def _coupling(found) -> list:
    return [d for d in found if COUPLING_M[0] <= d.rc_m <= COUPLING_M[1]]


def _the_reflectors_are_the_two_strongest(found) -> None:
    strongest = sorted(found, key=lambda d: -d.amplitude)[:2]
    assert sorted(round(d.x_m, 2) for d in strongest) == pytest.approx(TARGETS_M[:, 0], abs=0.01)
    assert all(abs(d.rc_m - RC_TRUE_M) < 0.005 for d in strongest)


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
def test_the_coupling_is_detected_without_the_cfar_threshold_and_gone_with_a_minimum_range_past_it(
    pulson_pass, algorithm
):
    plain = _detect(pulson_pass, algorithm, cfar_db=0.0)
    assert _coupling(plain)
    _the_reflectors_are_the_two_strongest(plain)
    gated = _detect(pulson_pass, algorithm, min_range_m=2.2, cfar_db=0.0)
    assert len(gated) == 2 and all(d.rc_m >= 2.2 for d in gated)
    _the_reflectors_are_the_two_strongest(gated)


def test_a_maximum_range_short_of_the_reflectors_leaves_only_what_lies_nearer(pulson_pass):
    found = _detect(pulson_pass, "nlcs", max_range_m=2.2, cfar_db=0.0)
    assert found and all(d.rc_m <= 2.2 for d in found)


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
@pytest.mark.parametrize("cfar_db", [10.0, DetectionSettings().cfar_db])
def test_the_cfar_threshold_removes_the_constant_range_coupling_stripe_and_keeps_the_reflectors(
    pulson_pass, algorithm, cfar_db
):
    found = _detect(pulson_pass, algorithm, cfar_db=cfar_db)
    assert not _coupling(found) and len(found) == 2
    _the_reflectors_are_the_two_strongest(found)


def test_the_cancellation_bound_models_only_the_strongest_peaks_and_leaves_the_others_as_first_refined(
    pulson_pass, monkeypatch
):
    modelled = []
    original = cancel.cancel_neighbours_with_residual

    def counting(cells, *args):
        modelled.append(len(cells))
        return original(cells, *args)

    monkeypatch.setattr(cancel, "cancel_neighbours_with_residual", counting)
    everything = _detect(pulson_pass, "bp", cfar_db=0.0)  # the coupling's peaks too
    bounded = _detect(pulson_pass, "bp", cancel_max_targets=2, cfar_db=0.0)
    uncancelled = _detect(pulson_pass, "bp", neighbour_cancellation_passes=0, cfar_db=0.0)
    assert modelled == [len(everything), 2] and len(everything) >= 4
    assert len(bounded) == len(everything)
    assert bounded[2:] == uncancelled[2:]
    assert [(d.x_m, d.rc_m) for d in bounded[:2]] != [(d.x_m, d.rc_m) for d in uncancelled[:2]]
    _the_reflectors_are_the_two_strongest(bounded)


@pytest.mark.parametrize("algorithm", ["nlcs", "bp"])
def test_the_new_options_at_their_defaults_or_wide_open_leave_paper_sim1_detections_identical(algorithm):
    scan = PAPER_SIM1.simulate(seed=1)[0]
    default = _detect(scan, algorithm)
    assert len(default) == 3
    explicit = _detect(scan, algorithm, min_range_m=0.0, max_range_m=0.0, cfar_db=0.0, cancel_max_targets=0)
    wide = _detect(scan, algorithm, min_range_m=0.5, max_range_m=50.0, cancel_max_targets=64)
    assert explicit == default and wide == default


def test_the_new_detection_keys_are_read_from_the_site_file_and_their_ranges_checked():
    cfg = config.parse_config({"detection": {"min_range_m": 2.2, "max_range_m": 6.0, "cfar_db": 10.0,
                                             "cancel_max_targets": 8}})
    d = cfg.processing_settings().detection
    assert (d.min_range_m, d.max_range_m, d.cfar_db, d.cancel_max_targets) == (2.2, 6.0, 10.0, 8)
    defaults = DetectionSettings()
    assert (defaults.min_range_m, defaults.max_range_m, defaults.cfar_db, defaults.cancel_max_targets) == (
        0.0, 0.0, 12.0, 0)
    for bad, key in (({"min_range_m": -1.0}, "detection.min_range_m"),
                     ({"min_range_m": 3.0, "max_range_m": 2.0}, "detection.max_range_m"),
                     ({"max_range_m": -2.0}, "detection.max_range_m"),
                     ({"cfar_db": -3.0}, "detection.cfar_db"),
                     ({"cancel_max_targets": -1}, "detection.cancel_max_targets")):
        with pytest.raises(ConfigError) as err:
            config.parse_config({"detection": bad})
        assert err.value.key == key


def test_range_bins_spread_over_kilometres_cost_memory_for_their_pixels_not_their_span():
    # positions off by orders of magnitude spread R_c over 1e9 m: 1e11 bins of 1 cm, 1,200 pixels
    rng = np.random.default_rng(4)
    mag = rng.rayleigh(size=(40, 30))
    valid = rng.random(mag.shape) > 0.2
    rc = 2.0 + np.linspace(0.0, 1e9, 40)[:, None] + np.linspace(0.0, 0.3, 30)[None, :]
    level = peaks.range_bin_medians(mag, valid, rc, 0.01)
    bins = np.floor((rc - np.floor(rc[valid].min() / 0.01) * 0.01) / 0.01).astype(np.int64)
    for b in np.unique(bins[valid]):
        here = bins == b
        assert np.allclose(level[here], np.median(mag[here & valid]))
    assert np.all(level[~np.isin(bins, bins[valid])] == 0.0)


def test_the_range_bin_medians_equal_numpys_median_over_each_bins_valid_pixels():
    rng = np.random.default_rng(3)
    mag = rng.rayleigh(size=(40, 30))
    valid = rng.random(mag.shape) > 0.2
    rc = np.linspace(2.0, 3.0, 30)[None, :] + np.linspace(0.0, 0.2, 40)[:, None]
    level = peaks.range_bin_medians(mag, valid, rc, 0.05)
    bins = np.floor((rc - np.floor(rc[valid].min() / 0.05) * 0.05) / 0.05).astype(int)
    for b in np.unique(bins[valid]):
        here = bins == b
        assert np.allclose(level[here], np.median(mag[here & valid]))
    by_column = peaks.range_bin_medians(mag, valid, None, 0.05)
    assert np.allclose(by_column[0], [np.median(mag[valid[:, j], j]) for j in range(30)])
    # a footprint search's level: each bin's rail pixels where it has any, else all its valid ones
    rail = np.zeros(mag.shape, dtype=bool)
    rail[10:30] = True
    rail[:, 25:] = False
    on_rail = peaks.range_bin_medians(mag, valid, rc, 0.05, rail)
    for b in np.unique(bins[valid]):
        here, where = bins == b, (bins == b) & valid & rail
        want = np.median(mag[where]) if where.any() else np.median(mag[here & valid])
        assert np.allclose(on_rail[here], want)
    # computed only where asked: the same values there, with and without the rail's level
    at = valid & (mag > 2.5)
    for mask in (None, rail):
        assert np.array_equal(peaks.range_bin_medians(mag, valid, rc, 0.05, mask, at=at)[at],
                              peaks.range_bin_medians(mag, valid, rc, 0.05, mask)[at])


def test_the_cfar_threshold_removes_a_constant_range_stripe_of_an_image_but_not_a_point_on_it():
    rng = np.random.default_rng(5)
    mag = rng.rayleigh(size=(200, 60))
    mag[:, 20] += 60.0 + 20.0 * rng.random(200)  # a stripe at one range: many local maxima along it
    mag[100, 40] = 90.0  # a point target elsewhere
    mag[150, 20] = 400.0  # and one on the stripe, far above it
    valid = np.ones(mag.shape, dtype=bool)
    s = DetectionSettings(relative_floor_db=-30.0, separation_m=0.02, range_separation_m=0.02, cfar_db=0.0)
    plain, _ = peaks.local_peaks(mag, valid, (0.01, 0.01), s)
    assert (plain[:, 1] == 20).sum() > 3
    cfar, _ = peaks.local_peaks(mag, valid, (0.01, 0.01), DetectionSettings(
        relative_floor_db=-30.0, separation_m=0.02, range_separation_m=0.02, cfar_db=6.0))
    assert sorted(map(tuple, cfar)) == [(100, 40), (150, 20)]


def test_the_default_cfar_threshold_keeps_noise_peaks_out_where_the_noise_is_above_the_images_median():
    """The image's ranges differ in level (the rib's clutter adds to the noise; the ranges beyond it hold
    noise alone and outnumber them): against the global median, min_snr_db lets the rib's noise peaks
    through, and the default cfar_db (the same test per R_c bin) keeps them out but not a plate among them."""
    rng = np.random.default_rng(7)
    mag = rng.rayleigh(size=(400, 80))
    mag[:, :20] *= 10 ** (4.0 / 20)  # the rib's ranges, 4 dB up (measured +2 to +4.6 dB at SNR 5 dB)
    mag[200, 10] = 25.0  # a plate there, ~24 dB over the global median
    valid = np.ones(mag.shape, dtype=bool)
    geometry = dict(relative_floor_db=-40.0, separation_m=0.02, range_separation_m=0.02)
    plain, _ = peaks.local_peaks(mag, valid, (0.01, 0.01), DetectionSettings(cfar_db=0.0, **geometry))
    assert (plain[:, 1] < 20).sum() >= 10  # noise peaks at the rib's ranges
    default, _ = peaks.local_peaks(mag, valid, (0.01, 0.01), DetectionSettings(**geometry))
    assert sorted(map(tuple, default)) == [(200, 10)]
