"""`uwbcl import p440` refuses flag values that would make a wrong archive, and says what it chose
(docs/importing.md sections 4 and 5): bad values exit 2 naming the flag, before the file is read where the
file is not needed; a recording or positions log that cannot make an archive exits 1 naming that file.

The recordings here are small PulsON-like files: a 4 GHz Gaussian-modulated pulse in every scan, 20 ms apart.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from test_p440_import import REAL, needs_real

from uwbcl import archive, cli, config
from uwbcl.importers import p440
from uwbcl.model import SPEED_OF_LIGHT_M_S

T_BIN_S = 32 / (512 * 1.024e9)
BOOT_S = 3400.0  # the radar's clock at the first scan, s since boot


def _recording(path, scan_start_ps=9000, n_bins=480, n_scans=40, spike=None, noise=3):
    """A P440 file: one echo at 14 ns into the window (amplitude 1000 counts, 1.5 GHz -10 dB band at 4 GHz)
    and +-`noise` counts of noise; ``spike`` = (scan, bin, value) corrupts one sample."""
    t = np.arange(n_bins) * T_BIN_S
    sigma = math.sqrt(math.log(10.0)) / (math.pi * 1.5e9)
    pulse = 1000.0 * np.exp(-0.5 * ((t - 14e-9) / sigma) ** 2) * np.cos(2 * np.pi * 4.0e9 * (t - 14e-9))
    rng = np.random.default_rng(1)
    rf = np.rint(pulse + rng.uniform(-noise, noise, (n_scans, n_bins))).astype(np.int64)
    if spike is not None:
        rf[spike[0], spike[1]] = spike[2]
    stamps = np.rint(1e3 * BOOT_S + 20.0 * np.arange(n_scans)).astype(int)
    return p440.write_p440_stream(path, rf, stamps, scan_start_ps=scan_start_ps)


@pytest.fixture
def small(tmp_path):
    return _recording(tmp_path / "small.p440")


TRACK = ["--speed-m-s", "0.1", "--height-m", "0.5"]  # a constant-speed track: 2 mm between pulses


def _run(scan_file, out, *flags):
    return cli.main(["import", "p440", str(scan_file), "--out", str(out), *flags])


# ------------------------------------------------------------------------------------ bad values: exit 2


@pytest.mark.parametrize(("flags", "message"), [
    (["--speed-m-s", "0.1"], "--height-m: required with --speed-m-s"),
    (["--speed-m-s", "0", "--height-m", "0.5"], "--speed-m-s: must be finite, non-zero and within +-10 m/s"),
    (["--speed-m-s", "nan", "--height-m", "0.5"], "--speed-m-s: must be finite, non-zero and within +-10"),
    # a tester: 1e308 overflowed the track and the error named an archive never written
    (["--speed-m-s", "1e308", "--height-m", "0.5"], "--speed-m-s: must be finite, non-zero and within"),
    ([*TRACK, "--pass-start-time", "yesterday"],
     "--pass-start-time: not an ISO 8601 date-time: 'yesterday'"),
    ([*TRACK, "--cycle", "-3"], "--cycle: must be >= 0, got -3"),
    ([*TRACK, "--cycle", "99999999999999999999"], "--cycle: must be at most 9223372036854775807"),
    ([*TRACK, "--range-delay-s", "1"],
     f"--range-delay-s: must be within +-{config.MAX_RANGE_DELAY_S:g} s"),
    ([*TRACK, "--range-delay-s", "12.3"],
     f"--range-delay-s: must be within +-{config.MAX_RANGE_DELAY_S:g} s"),
    (["--positions", "pos.csv", "--time-offset-s", "inf"], "--time-offset-s: must be finite"),
    ([*TRACK, "--pulse-window-m", "nan", "0.3"], "--pulse-window-m: must be finite, got nan"),
    ([*TRACK, "--pulse-window-m", "0.3", "-0.2"], "--pulse-window-m: the reference window needs"),
])
def test_a_bad_flag_value_exits_2_naming_the_flag_before_the_recording_is_read(tmp_path, capsys, flags,
                                                                                message):
    # the recording does not exist: the value is refused before it would be read
    assert _run(tmp_path / "absent.p440", tmp_path / "out", *flags) == 2
    assert capsys.readouterr().err.startswith(f"uwbcl import p440: {message}")
    assert not (tmp_path / "out").exists()


def test_a_bad_value_from_the_site_file_names_the_file_and_its_key(tmp_path, capsys):
    site = tmp_path / "site.toml"
    site.write_text("[import]\ncycle = -3\n")
    assert _run(tmp_path / "absent.p440", tmp_path / "out", "--speed-m-s", "0.1", "--height-m", "0.5",
                "--config", str(site)) == 2
    assert f"uwbcl import p440: {site}: import.cycle: must be >= 0" in capsys.readouterr().err


def test_a_carrier_that_leaves_out_the_measured_band_exits_2_naming_the_flag(small, tmp_path, capsys):
    assert _run(small, tmp_path / "out", *TRACK, "--carrier-hz", "9e9") == 2
    err = capsys.readouterr().err
    assert "uwbcl import p440: --carrier-hz: 9e+09 Hz: the complex band" in err and "-10 dB band" in err


def test_a_decimation_whose_rate_is_below_the_bandwidth_exits_2_with_the_numbers(small, tmp_path, capsys):
    assert _run(small, tmp_path / "out", *TRACK, "--decimation", "50") == 2
    err = capsys.readouterr().err
    assert "--decimation: 50: the complex band" in err and "rate 0.328 GHz = RF 16.384 GHz / 50" in err
    most = int(err.split("decimation <= ")[1].split()[0])
    # the largest decimation offered keeps the complex rate at or above the measured bandwidth
    assert _run(small, tmp_path / "ok", *TRACK, "--decimation", str(most)) == 0
    assert _run(small, tmp_path / "no", "--speed-m-s", "0.1", "--height-m", "0.5",
                "--decimation", str(most + 1)) == 2


# ------------------------------------------------------------------------------------------- the delay


def test_a_delay_beyond_the_whole_scan_window_is_refused_and_one_inside_it_imported(small, tmp_path, capsys):
    # scan start 9 ns: a 10 ns delay starts the window 15 cm behind the antenna, a window that holds the
    # antenna's coupling: imported as it is, processed from 0.1 m in front (pipeline.crop_near_field); a delay
    # past the window's end puts all of it behind the antenna: refused, naming the window
    assert _run(small, tmp_path / "in", *TRACK, "--range-delay-s", "10e-9") == 0
    (path,) = archive.find_pass_files(tmp_path / "in")
    assert archive.read_pass(path).range_window_start_s == pytest.approx(-1e-9)
    assert _run(small, tmp_path / "out", *TRACK, "--range-delay-s", "900e-9") == 2
    err = capsys.readouterr().err
    assert "--range-delay-s: 9e-07 s is more than the recording's whole scan window (9e-09 to" in err
    assert "behind the antenna" in err and not (tmp_path / "out").exists()
    assert _run(small, tmp_path / "ok", *TRACK, "--range-delay-s", "5e-9") == 0
    (path,) = archive.find_pass_files(tmp_path / "ok")
    assert archive.read_pass(path).range_window_start_s == pytest.approx(4e-9)


def test_a_measured_pulse_window_starting_behind_the_antenna_holds_a_calibrated_coupling(small, tmp_path):
    # the echo (same in every scan, as a coupling) is 14 ns into a window starting at 9 ns: calibrated with
    # a delay of 23 ns it sits at 0 m, and its window starts below 0 (docs/importing.md section 5)
    assert _run(small, tmp_path / "out", *TRACK, "--range-delay-s", "23e-9", "--pulse", "measured",
                "--pulse-window-m", "-0.2", "0.3") == 0
    [path] = (tmp_path / "out").rglob("*.h5")
    assert archive.read_pass(path).radar.measured_pulse is not None


def test_a_negative_delay_is_imported_with_a_warning(small, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _run(small, tmp_path / "out", "--speed-m-s", "0.1", "--height-m", "0.5",
                    "--range-delay-s=-1e-9") == 0
    assert "range_delay_s -1e-09 s is negative" in caplog.text


# --------------------------------------------------------------------------------- the reference point


def _reference_range_m(out):
    (path,) = archive.find_pass_files(out)
    scan = archive.read_pass(path)
    centre = (0.5 * (scan.pulse_position_m[0] + scan.pulse_position_m[-1]), 0.0, scan.geometry.height_m)
    return math.dist(centre, scan.geometry.reference_point_m), scan


def test_the_default_reference_range_moves_to_the_middle_of_a_window_that_does_not_hold_it(
        small, tmp_path, capsys):
    far = _recording(tmp_path / "far.p440", scan_start_ps=30000, n_bins=300)  # 4.50-7.18 m
    assert _run(far, tmp_path / "far", *TRACK) == 0
    r, scan = _reference_range_m(tmp_path / "far")
    lo, hi = scan.range_axis_m[0], scan.range_axis_m[-1]
    assert r == pytest.approx(0.5 * (lo + hi)) and lo > 3.0
    out = capsys.readouterr().out
    assert f"reference: on boresight at {r:.2f} m, the middle of the recording's window" in out
    # a window that holds 3 m (1.35-5.74 m) keeps it, silently
    assert _run(small, tmp_path / "near", *TRACK) == 0
    assert _reference_range_m(tmp_path / "near")[0] == pytest.approx(3.0)
    assert "reference:" not in capsys.readouterr().out


def test_a_given_reference_range_outside_the_window_is_kept_with_a_warning(tmp_path, caplog):
    far = _recording(tmp_path / "far.p440", scan_start_ps=30000, n_bins=300)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _run(far, tmp_path / "out", "--speed-m-s", "0.1", "--height-m", "0.5",
                    "--reference-range-m", "3") == 0
    assert _reference_range_m(tmp_path / "out")[0] == pytest.approx(3.0)
    assert "the reference range 3.00 m (--reference-range-m) lies outside the recording's window 4.50-" \
        in caplog.text


# ------------------------------------------------------------------------------------------- the track


def test_pulses_further_apart_than_a_quarter_wavelength_are_imported_with_a_warning(small, tmp_path, caplog):
    quarter_mm = 1e3 * SPEED_OF_LIGHT_M_S / 4.0e9 / 4  # about 18.7 mm at the pulse's 4 GHz
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _run(small, tmp_path / "slow", "--speed-m-s", "0.5", "--height-m", "0.5") == 0  # 10 mm
        assert "quarter wavelength" not in caplog.text
        assert _run(small, tmp_path / "fast", "--speed-m-s", "2", "--height-m", "0.5") == 0  # 40 mm
    assert "the pulses are 40.0 mm apart along the rail (median), more than a quarter wavelength" \
        in caplog.text
    assert f"({quarter_mm:.1f} mm at" in caplog.text


def test_positions_that_cover_no_scan_give_the_scans_own_time_range(small, tmp_path, capsys):
    pos = tmp_path / "pos.csv"
    pos.write_text("time_s,x_m\n0,0\n1,0.1\n2,0.2\n")
    assert _run(small, tmp_path / "out", "--positions", str(pos), "--height-m", "0.5",
                "--time-offset-s", "0") == 1
    err = capsys.readouterr().err
    assert f"the positions of {pos} (0.000..2.000 s) cover 0 scans" in err
    assert "the scans run from 3400.000 to 3400.780 s on the radar's clock" in err
    assert "-3400.000 s would put the first scan at the first position" in err


def test_a_rail_deviation_beyond_half_a_metre_names_the_csv_line_and_leaves_no_directory(small, tmp_path,
                                                                                          capsys):
    pos = tmp_path / "pos.csv"
    pos.write_text("time_s,x_m,y_m,z_m\n\n0,-0.1,0.0,0.5\n0.4,0,0.7,0.5\n0.8,0.1,0.0,0.5\n")
    out = tmp_path / "out"
    assert _run(small, out, "--positions", str(pos), "--time-offset-s", f"{-BOOT_S}") == 1
    err = capsys.readouterr().err
    assert f"uwbcl import p440: {pos}: line 4: y_m +0.700 m is beyond the +-0.5 m" in err
    assert ".h5" not in err and not out.exists()


def test_a_failed_write_removes_the_directories_the_import_made_and_only_those(small, tmp_path, monkeypatch,
                                                                                capsys):
    def failing_write(path, scan, **kwargs):
        path.parent.mkdir(parents=True)
        raise archive.ArchiveError(path, "/echo", "simulated failure")

    monkeypatch.setattr(archive, "write_pass", failing_write)
    out = tmp_path / "out"
    (out / "rig-1" / "keep").mkdir(parents=True)
    assert _run(small, out, *TRACK) == 1
    assert "simulated failure" in capsys.readouterr().err
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["rig-1", "rig-1/keep"]


# -------------------------------------------------------------------------------------- the recording


def test_a_corrupt_sample_is_reported_as_an_implausibly_wide_band_naming_the_file_and_the_sample(
        tmp_path, capsys):
    bad = _recording(tmp_path / "spike.p440", spike=(7, 123, 16776217))
    assert _run(bad, tmp_path / "out", *TRACK) == 1
    err = capsys.readouterr().err
    assert f"uwbcl import p440: {bad}: the measured spectrum is implausibly wide" in err
    assert "the largest |sample| is 1.67762e+07 (scan 7, sample 123)" in err
    assert "1 scan(s) hold a sample over 100 x it (scans 7)" in err


def test_a_noisy_recording_without_a_spike_is_converted_with_a_warning_not_refused(tmp_path, caplog):
    # a noise floor within 20 dB of the pulse's spectrum is not a corrupt sample (indepZh N2)
    noisy = _recording(tmp_path / "noisy.p440", noise=150)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _run(noisy, tmp_path / "out", *TRACK) == 0
    assert f"{noisy}: the spectrum is never 20 dB down at an end" in caplog.text
    assert "a noise floor within 20 dB of the pulse" in caplog.text


def test_the_summary_prints_the_pass_start_and_where_it_came_from(small, tmp_path, capsys):
    assert _run(small, tmp_path / "a", *TRACK) == 0
    assert "(the file's modification time minus the recording's length" in capsys.readouterr().out
    assert _run(small, tmp_path / "b", "--speed-m-s", "0.1", "--height-m", "0.5",
                "--pass-start-time", "2019-07-26T12:00:00Z") == 0
    assert "pass start: 2019-07-26T12:00:00Z\n" in capsys.readouterr().out


@needs_real
def test_the_real_file_without_its_coupling_tells_which_option_sets_the_pulse_window(tmp_path, capsys):
    assert _run(REAL, tmp_path / "out", *TRACK, "--pulse", "measured") == 2
    err = capsys.readouterr().err
    assert "--pulse-window-m: the pulse's reference window 1.5-2.6 m holds 0 samples" in err
    assert "spans 5.50-16.02 m" in err and "give --pulse-window-m START STOP" in err


def test_an_import_length_beyond_a_kilometre_is_a_usage_error_as_in_the_site_file():
    # `--height-m 5000` wrote ..._h5000000.h5 (indepZe 9)
    from uwbcl.importers import OptionError, passes

    for key, value in (("height_m", 5000.0), ("reference_range_m", 5000.0),
                       ("reference_point_m", (0.0, -2.5, 1001.0))):
        with pytest.raises(OptionError) as err:
            passes.check_options(passes.ImportOptions(**{key: value}))
        assert err.value.key == key and "within +-1000 m" in err.value.reason
    passes.check_options(passes.ImportOptions(height_m=999.0, reference_point_m=(0.0, -2.5, 1.0)))
