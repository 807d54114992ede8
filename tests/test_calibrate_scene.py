"""Acceptance (issue 13): a PulsON-like pass over two reflectors beyond the rail's ends, written in the P440
stream layout, imported with `uwbcl import p440` uncalibrated (the radar adds 2.3 ns), calibrated with
`uwbcl calibrate`, then focused with the calibrated site file.

The rail runs x = -1...+1 m at h = 0.15 m, squint 30 deg: at the processing squint it images x = 0.386...2.386
m at R_c = 2.405 m. The reflectors stand at x = -0.014 and 2.886 m (0.4 and 0.5 m beyond its ends, inside the
beam's -3 dB footprint). Measured (numpy, NLCS, [detection] min_range_m = 2.2, cfar_db = 10, search =
"footprint"; tests below):

- uncalibrated, the ranges are +287 mm off on average (+334 and +241 mm) and the along-track positions +83
  and +243 mm: `uwbcl calibrate` prints it;
- `uwbcl calibrate` finds 2.3028 ns (standard uncertainty 0.0056 ns) in 3 refocusing steps (slope 0.834:
  R_c moves by 0.83 of c dD / 2);
- focused with that delay, the two reflectors are the only detections, at dx = -4.3, -6.5 mm and
  dR_c = -0.7, +0.7 mm (NLCS placed again on the backprojection sum beyond the rail's ends);
- with search = "rail" neither is found.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import logging
import math
import os

import numpy as np
import pytest

from uwbcl import archive, calibrate, cli, config, detect, locate, pipeline
from uwbcl import geometry as geo
from uwbcl.importers import synthetic
from uwbcl.model import MIN_WINDOW_RANGE_M, SPEED_OF_LIGHT_M_S
from uwbcl.records import ConfigError, Detection, DetectionSettings, ProcessingSettings
from uwbcl.scenarios import PAPER_SIM1

HEIGHT_M = 0.15
REFLECTORS_M = np.array([[-0.014, -2.4, 0.3], [2.886, -2.4, 0.3]])
RC_TRUE_M = math.hypot(2.4, 0.3 - HEIGHT_M)
DELAY_S = 2.3e-9  # synthetic.P440Scene's internal delay
SITE = synthetic.IMPORT_SITE_TOML + '\n[detection]\nmin_range_m = 2.2\ncfar_db = 10.0\nsearch = "footprint"\n'
REFLECTOR_FLAGS = [f"--reflector={x},{y},{z}" for x, y, z in REFLECTORS_M]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The P440 stream, its positions, the site file and the uncalibrated archive `uwbcl import` wrote."""
    root = tmp_path_factory.mktemp("calibrate")
    p440_scene = synthetic.P440Scene(targets_m=REFLECTORS_M, amplitudes=(1.0, 1.0), height_m=HEIGHT_M)
    scan_file, positions = synthetic.write_recording(root, p440_scene)
    site = root / "site.toml"
    site.write_text(SITE)
    common = ["--positions", str(positions), "--pass-start-time", "2026-11-23T06:00:00Z"]
    assert cli.main(["import", "p440", str(scan_file), "--out", str(root / "raw"), "--config", str(site),
                     *common]) == 0
    (path,) = archive.find_pass_files(root / "raw")
    return {"root": root, "scan_file": scan_file, "site": site, "archive": path, "common": common}


@pytest.fixture(scope="module")
def calibrated(scene):
    """`uwbcl calibrate` on the uncalibrated archive: (exit code, the written site file, what it printed)."""
    out = scene["root"] / "calibrated.toml"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = cli.main(["calibrate", str(scene["archive"]), *REFLECTOR_FLAGS, "--config", str(scene["site"]),
                         "--backend", "numpy", "--write-config", str(out)])
    return code, out, printed.getvalue()


def _strongest_two(rows):
    return sorted(rows, key=lambda r: -float(r["amplitude"]))[:2]


def test_calibrate_recovers_the_radars_delay_within_0_02_ns_and_writes_it_to_the_site_file(calibrated):
    code, out, _ = calibrated
    assert code == 0
    delay = config.load_config(out).range_delay_s
    assert abs(delay - DELAY_S) < 0.02e-9
    assert config.load_config(out).detection == config.load_config(out.parent / "site.toml").detection


def test_calibrate_reports_the_uncalibrated_range_error_and_a_line_per_reflector(calibrated):
    _, _, printed = calibrated
    assert "uncalibrated" in printed
    offset_mm = float(printed.split("the ranges were ")[1].split(" mm")[0])
    assert 200 < offset_mm < 345  # the envelope is c D / 2 = 345 mm late; the focused range lands short of it
    assert sum(line.startswith("syn_c000000_h0150.h5") for line in printed.splitlines()) == 2
    assert "standard uncertainty" in printed and "along-track offset" in printed


def test_focus_with_the_calibrated_site_file_puts_both_reflectors_first_and_within_1_cm(scene, calibrated,
                                                                                          capsys):
    out = scene["root"] / "focus"
    assert cli.main(["focus", str(scene["archive"]), "--out", str(out), "--backend", "numpy",
                     "--config", str(calibrated[1])]) == 0
    assert "range delay 2.30" in capsys.readouterr().out
    with open(out / "detections.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    strongest = sorted(_strongest_two(rows), key=lambda r: float(r["x_m"]))
    for row, (x, _, _) in zip(strongest, REFLECTORS_M):
        assert abs(float(row["x_m"]) - x) < 0.01 and abs(float(row["rc_m"]) - RC_TRUE_M) < 0.01


def test_an_import_with_the_calibrated_site_file_records_the_delay_and_places_the_reflectors(scene,
                                                                                             calibrated):
    root = scene["root"]
    assert cli.main(["import", "p440", str(scene["scan_file"]), "--out", str(root / "cal"), "--config",
                     str(calibrated[1]), *scene["common"]]) == 0
    (path,) = archive.find_pass_files(root / "cal")
    scan = archive.read_pass(path)
    assert scan.range_delay_s == config.load_config(calibrated[1]).range_delay_s
    settings = config.load_config(calibrated[1]).processing_settings()
    found = pipeline.detect_pass(scan, dataclasses.replace(settings, backend="numpy", range_delay_s=None))
    assert len(found) == 2
    for d, (x, _, _), beyond in zip(sorted(found, key=lambda d: d.x_m), REFLECTORS_M, (0.4, 0.5)):
        assert abs(d.x_m - x) < 0.01 and abs(d.rc_m - RC_TRUE_M) < 0.01
        # eq. L3: the antenna was 0.4 / 0.5 m past the rail's ends when the beam centre crossed them
        assert d.beyond_rail_m == pytest.approx(beyond, abs=0.01)
        assert locate.look_sigma_factor(d) == pytest.approx(1 + locate.BEYOND_RAIL_SIGMA_PER_SQRT_M
                                                            * math.sqrt(d.beyond_rail_m))


def test_without_calibration_focus_says_the_pass_is_uncalibrated(scene, capsys):
    out = scene["root"] / "focus-raw"
    assert cli.main(["focus", str(scene["archive"]), "--out", str(out), "--backend", "numpy"]) == 0
    assert "uncalibrated" in capsys.readouterr().out


def test_a_rail_search_misses_the_reflectors_beyond_the_rail_ends(scene):
    scan = pipeline.shift_range_delay(archive.read_pass(scene["archive"]), DELAY_S)
    settings = ProcessingSettings(backend="numpy", detection=DetectionSettings(min_range_m=2.2, cfar_db=10.0,
                                                                               search="rail"))
    found = pipeline.detect_pass(scan, settings)
    assert not any(abs(d.x_m - x) < 0.05 for d in found for x in REFLECTORS_M[:, 0])
    # sought on the rail; a peak refined a little past its end carries how far (eq. L3), and only those
    assert all(d.beyond_rail_m <= 0.1 for d in found)
    assert all((locate.look_sigma_factor(d) == 1.0) == (d.beyond_rail_m == 0.0) for d in found)


def test_the_default_search_looks_past_a_short_rails_ends_and_only_along_a_long_one(scene):
    scan = pipeline.shift_range_delay(archive.read_pass(scene["archive"]), DELAY_S)
    track_m = float(np.ptp(scan.pulse_position_m))
    auto = DetectionSettings(min_range_m=2.2, cfar_db=10.0)
    assert auto.search == "auto" and track_m < auto.short_track_m
    assert detect.pass_search(scan, auto) == "footprint"
    found = pipeline.detect_pass(scan, ProcessingSettings(backend="numpy", detection=auto))
    for x, _, _ in REFLECTORS_M:
        assert any(abs(d.x_m - x) < 0.01 and d.beyond_rail_m > 0.3 for d in found)
    assert detect.search_footprint(scan, auto) == detect.search_footprint(
        scan, dataclasses.replace(auto, search="footprint"))
    # the same pass counted as long: the rail search
    long = dataclasses.replace(auto, short_track_m=track_m)
    assert detect.pass_search(scan, long) == "rail" and detect.search_footprint(scan, long) is None


# ----------------------------------------------------------------------------------- the delay's rules
def _sim1_pass():
    return PAPER_SIM1.simulate(seed=1)[0]


def test_the_site_delay_moves_the_window_by_its_difference_from_the_recorded_delay(caplog):
    scan = dataclasses.replace(_sim1_pass(), range_delay_s=1.0e-9)
    moved = pipeline.apply_range_delay(scan, 2.3e-9)
    assert moved.range_window_start_s == pytest.approx(scan.range_window_start_s - 1.3e-9, abs=1e-21)
    assert moved.range_delay_s == 2.3e-9
    assert pipeline.apply_range_delay(scan, None) is scan
    unrecorded = _sim1_pass()
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        full = pipeline.apply_range_delay(unrecorded, 2.3e-9)
    assert full.range_window_start_s == pytest.approx(unrecorded.range_window_start_s - 2.3e-9, abs=1e-21)
    assert "records no range_delay_s" in caplog.text


def test_a_site_delay_past_the_window_start_drops_the_near_field_and_past_its_end_is_refused():
    scan = dataclasses.replace(_sim1_pass(), range_delay_s=1.0e-9)
    fs = scan.radar.sample_rate_hz
    past_start = scan.range_window_start_s + 1.0e-9 + 2.0e-9  # the window now starts 0.30 m behind
    cropped = pipeline.apply_range_delay(scan, past_start)
    near_s = 2 * MIN_WINDOW_RANGE_M / SPEED_OF_LIGHT_M_S  # processed from 0.1 m in front of the antenna
    assert near_s <= cropped.range_window_start_s < near_s + 1 / fs
    dropped = scan.samples_per_pulse - cropped.samples_per_pulse
    np.testing.assert_array_equal(cropped.echo, scan.echo[:, dropped:])
    past_end = scan.range_window_start_s + 1.0e-9 + scan.samples_per_pulse / fs
    with pytest.raises(ValueError, match=r"in front of the antenna \(a delay for another radar"):
        pipeline.apply_range_delay(scan, past_end)
    assert pipeline.apply_range_delay(scan, past_start - 2.5e-9).range_window_start_s > near_s  # no crop


def test_the_radar_table_and_the_new_detection_keys_are_read_and_checked():
    cfg = config.parse_config({"radar": {"range_delay_s": 2.3e-9},
                               "detection": {"search": "footprint", "cancel_time_budget_s": 2.0}})
    settings = cfg.processing_settings()
    assert (settings.range_delay_s, settings.detection.search, settings.detection.cancel_time_budget_s) == (
        2.3e-9, "footprint", 2.0)
    assert config.SiteConfig().processing_settings().range_delay_s is None
    assert DetectionSettings().search == "auto" and DetectionSettings().cancel_time_budget_s == 0.0
    for bad, key in (({"detection": {"search": "everywhere"}}, "detection.search"),
                     ({"detection": {"search": 1}}, "detection.search"),
                     ({"detection": {"cancel_time_budget_s": -1.0}}, "detection.cancel_time_budget_s"),
                     ({"detection": {"short_track_m": -1.0}}, "detection.short_track_m"),
                     ({"detection": {"short_track_m": float("nan")}}, "detection.short_track_m"),
                     ({"radar": {"range_delay_s": 2.3}}, "radar.range_delay_s"),
                     ({"radar": {"range_delay": 2.3e-9}}, "radar.range_delay")):
        with pytest.raises(ConfigError) as err:
            config.parse_config(bad)
        assert err.value.key == key


def test_the_site_files_delay_is_set_where_it_is_or_added_to_its_table_or_appended():
    assert calibrate.with_range_delay("", 1e-9) == "[radar]\nrange_delay_s = 1e-09  # s, uwbcl calibrate\n"
    # an [import] delay alone: replaced, and a [radar] table appended with the same value
    assert config.tomllib.loads(calibrate.with_range_delay("[import]\nrange_delay_s = 5e-9\n", 2e-9)) == {
        "import": {"range_delay_s": 2e-9}, "radar": {"range_delay_s": 2e-9}}
    text = '[radar]\nrange_delay_s = 5e-9\n\n[detection]\ncfar_db = 10.0\n'
    assert config.tomllib.loads(calibrate.with_range_delay(text, 2e-9)) == {
        "radar": {"range_delay_s": 2e-9}, "detection": {"cfar_db": 10.0}}
    text = '[radar]\n# calibrated\n[detection]\ncfar_db = 10.0'
    assert config.tomllib.loads(calibrate.with_range_delay(text, 2e-9))["radar"] == {"range_delay_s": 2e-9}
    # a quoted key is the same key; an [import] delay is replaced too (`uwbcl import` refuses two delays)
    text = '[radar]\n"range_delay_s" = 5e-9\n[import]\nrange_delay_s = 5e-9\n'
    assert config.tomllib.loads(calibrate.with_range_delay(text, 2e-9)) == {
        "radar": {"range_delay_s": 2e-9}, "import": {"range_delay_s": 2e-9}}
    # the replaced line's provenance is kept, as a comment above the new value
    text = '[radar]\nrange_delay_s = 1.0e-9 # measured 2026-10 by J. Smith\n'
    assert calibrate.with_range_delay(text, 2e-9).splitlines()[1:] == [
        "# before uwbcl calibrate: range_delay_s = 1.0e-9 # measured 2026-10 by J. Smith",
        "range_delay_s = 2e-09  # s, uwbcl calibrate"]


@pytest.mark.parametrize("text", ["radar = { range_delay_s = 2e-9 }\n", "radar.range_delay_s = 2e-9\n"])
def test_a_site_file_whose_delay_calibrate_cannot_edit_is_named_not_a_traceback(text, tmp_path):
    base = tmp_path / "site.toml"
    base.write_text(text)
    with pytest.raises(ConfigError, match="in a form uwbcl calibrate does not edit"):
        calibrate.write_config(tmp_path / "out.toml", base, 1e-9)
    assert not (tmp_path / "out.toml").exists()


@pytest.mark.parametrize("kind", ["fifo", "symlink"])
def test_calibrate_writes_a_config_only_to_a_regular_file_or_a_new_name(kind, tmp_path, capsys):
    real = tmp_path / "real.toml"
    real.write_text("[site]\nweb_depth_m = 0.9\n")
    out = tmp_path / "out.toml"
    if kind == "fifo":
        os.mkfifo(out)
    else:
        out.symlink_to(real)
    code = cli.main(["calibrate", str(tmp_path / "a.h5"), "--reflector=1,-2.4,0.3", "--backend", "numpy",
                     "--write-config", str(out)])
    assert code == 2 and "--write-config" in capsys.readouterr().err
    assert real.read_text() == "[site]\nweb_depth_m = 0.9\n" and (out.is_symlink() or not out.is_file())


def test_import_refuses_two_different_delays_in_one_site_file(scene, tmp_path, capsys):
    site = tmp_path / "both.toml"
    both = SITE.replace("[import]\n", "[import]\nrange_delay_s = 1e-9\n")
    both += "\n[radar]\nrange_delay_s = 2e-9\n"
    site.write_text(both)
    code = cli.main(["import", "p440", str(scene["scan_file"]), "--out", str(tmp_path / "o"), "--config",
                     str(site), *scene["common"]])
    assert code == 2 and "import.range_delay_s" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--reflector=1,2"], "expected three finite numbers"),
    (["--reflector=a,b,c"], "expected X,Y,Z"),
    (["--reflector=1,2,3", "--gate-m", "0"], "--gate-m"),
])
def test_calibrate_refuses_bad_flags_with_exit_2(tmp_path, capsys, argv, message):
    assert cli.main(["calibrate", str(tmp_path / "none.h5"), *argv, "--backend", "numpy"]) == 2
    assert message in capsys.readouterr().err


def test_calibrate_names_an_archive_it_cannot_read_and_exits_1(tmp_path, capsys):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5")
    assert cli.main(["calibrate", str(bad), "--reflector=1,-2.4,0.3", "--backend", "numpy"]) == 1
    err = capsys.readouterr().err
    assert "bad.h5" in err and "Traceback" not in err


def test_calibrate_refuses_a_config_output_in_a_missing_directory(tmp_path, capsys):
    code = cli.main(["calibrate", str(tmp_path / "a.h5"), "--reflector=1,-2.4,0.3", "--backend", "numpy",
                     "--write-config", str(tmp_path / "missing" / "site.toml")])
    assert code == 2 and "is not a directory" in capsys.readouterr().err


def test_reflectors_are_matched_by_agreeing_range_residuals_not_by_distance_alone():
    def det(x, rc):
        return Detection(x_m=x, rc_m=rc, t_n_s=0.0, r0_m=rc, image_azimuth_m=0.0, image_range_m=rc,
                                  amplitude=1.0, snr_db=30.0)
    reflectors = [(0.0, -2.4, 0.15), (3.0, -2.4, 0.15)]
    coupling, first, second = det(0.1, 2.35), det(0.1, 2.70), det(3.2, 2.65)  # the radar reads 0.3 m long
    assert calibrate.match_reflectors([coupling, first, second], reflectors, 0.15, 0.5) == [first, second]


# ---------------------------------------------------------------------------------- footprint and budget
def test_the_beams_3db_edge_is_where_the_two_way_pattern_is_3db_down():
    edge = geo.beam_edge_rad(0.14, 0.075, "3db")
    assert geo.two_way_beam_gain(edge, 0.0, 0.14, 0.075) == pytest.approx(10 ** (-3 / 20), rel=1e-9)
    assert geo.beam_edge_rad(0.14, 0.075, "null") == geo.beam_half_width_rad(0.14, 0.075)


def test_the_footprint_edges_on_the_image_axes_are_its_edges_in_x_and_r_c():
    beam = geo.pass_footprint(-1.0, 1.0, math.radians(30.0), 0.14, 0.075)
    sin_q, r = 0.5, np.linspace(2.0, 4.0, 5)
    for side, u in enumerate(beam.u_edges_m(r, sin_q)):
        r0 = r - sin_q * u  # P1: back to (x_rel, R_c)
        x_rel, rc = u + r0 * sin_q, r0 * math.sqrt(1 - sin_q**2)
        assert np.allclose(x_rel, beam.x_rel_bounds_m(rc)[side], atol=1e-12)


@pytest.mark.parametrize("search", ["footprint", "main_lobe"])
def test_a_footprint_search_leaves_paper_sim1s_nlcs_detections_identical(search):
    scan = _sim1_pass()
    rail = pipeline.detect_pass(scan, ProcessingSettings(backend="numpy"))
    wide = pipeline.detect_pass(scan, ProcessingSettings(backend="numpy",
                                                         detection=DetectionSettings(search=search)))
    assert len(rail) == 3 and wide == rail


def test_a_spent_cancellation_budget_keeps_the_first_refinement_and_a_generous_one_changes_nothing(caplog):
    scan = _sim1_pass()

    def run(**kw):
        settings = ProcessingSettings(backend="numpy", detection=DetectionSettings(**kw))
        return pipeline.detect_pass(scan, settings)

    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        exhausted = run(cancel_time_budget_s=1e-9)
    assert "time budget" in caplog.text
    assert exhausted == run(neighbour_cancellation_passes=0)
    assert run(cancel_time_budget_s=3600.0) == run()
