"""PulsON 440 import (issue 13, phase 1): real bytes in, complex baseband out, paired with the rail, archived.

Measured numbers quoted in docs/importing.md come from these tests.
"""

from __future__ import annotations

import logging
import math
import os
import struct
from pathlib import Path

import h5py
import numpy as np
import pytest

from uwbcl import archive, cli, geometry, pipeline
from uwbcl.importers import RecordingError, baseband, p440, passes, synthetic
from uwbcl.model import SPEED_OF_LIGHT_M_S, PassGeometry, RadarParameters, ScanPass
from uwbcl.records import ProcessingSettings
from uwbcl.simulate import simulate_pass

REAL_DIR = Path(os.environ.get("UWBCL_P440_DATA", Path(__file__).resolve().parents[2] / "shared/data/p440"))
REAL = REAL_DIR / "scan_281414.p440"
if not REAL.exists():
    REAL = Path("/work/shared/data/p440/scan_281414.p440")
needs_real = pytest.mark.skipif(not REAL.exists(), reason="the shared real P440 file is not here")

T_BIN_S = 32 / (512 * 1.024e9)
NUMPY_NLCS = ProcessingSettings(backend="numpy", algorithm="nlcs")


# ---------------------------------------------------------------------------------------------- the real file


@needs_real
def test_the_shared_real_file_reads_every_complete_scan_and_drops_the_partial_last_one_with_a_log_line(
    caplog,
):
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(REAL)
    assert rec.samples.shape == (710, 1152) and rec.samples.dtype == np.int32
    assert rec.n_dropped == 1
    assert "dropped the incomplete last scan" in caplog.text and "byte 4123712" in caplog.text
    assert rec.bin_period_s == pytest.approx(61.035e-12, rel=1e-5)
    assert rec.scan_start_s == pytest.approx(36.684e-9)
    assert list(rec.scan_id[:3]) == [0, 1, 2] and rec.scan_id[-1] == 709
    dt = np.diff(rec.scan_time_s)
    assert (dt > 0).all() and np.median(dt) == pytest.approx(0.0206, abs=0.001)


@needs_real
def test_the_real_file_spectrum_is_centred_near_4_ghz_with_its_minus_10_db_band_reported():
    rec = p440.READER.read(REAL)
    band = baseband.measure_band(rec.samples, rec.bin_period_s)
    # Measured: centre 3.963 GHz, -10 dB band 3.329-4.598 GHz, peak 3.868 GHz.
    assert 3.85e9 < band.centre_hz < 4.1e9
    assert 3.2e9 < band.low_hz < 3.45e9 and 4.45e9 < band.high_hz < 4.75e9
    assert 3.0e9 < band.low_20db_hz < band.low_hz and band.high_hz < band.high_20db_hz < 5.1e9


@needs_real
def test_the_writer_reproduces_the_real_file_byte_for_byte_up_to_its_partial_last_scan(tmp_path):
    rec = p440.READER.read(REAL)
    copy = p440.write_p440_stream(
        tmp_path / "copy.p440",
        rec.samples,
        np.rint(rec.scan_time_s * 1e3).astype(int),
        scan_start_ps=36684,
        node_id=1,
        pii=11,
        partial_last_scan_messages=1,
    )
    a, b = REAL.read_bytes(), copy.read_bytes()
    assert len(a) == len(b) and a[: -p440.RECORD_BYTES] == b[: -p440.RECORD_BYTES]


@needs_real
def test_the_cli_imports_the_real_file_on_a_constant_speed_track_keeping_the_raw_rf(tmp_path, capsys):
    out = tmp_path / "archives"
    rc = cli.main(
        [
            "import",
            "p440",
            str(REAL),
            "--out",
            str(out),
            "--speed-m-s",
            "0.1",
            "--height-m",
            "0.5",
            "--rig-id",
            "bwsi",
            "--pass-start-time",
            "2019-07-26T12:00:00Z",
            "--range-delay-s",
            "10e-9",
        ]
    )
    text = capsys.readouterr().out
    assert rc == 0
    assert "710 complete scans read, 1 incomplete dropped" in text
    assert "centre 3.963 GHz, -10 dB band 3.329-4.598 GHz" in text
    files = archive.find_pass_files(out)
    assert len(files) == 1 and f"wrote 1 archive: {files[0]}" in text
    scan = archive.read_pass(files[0])
    assert scan.n_pulses == 710 and scan.range_delay_s == 10e-9
    assert scan.range_window_start_s == pytest.approx(36.684e-9 - 10e-9)
    assert scan.mean_speed_m_s == pytest.approx(0.1)
    raw = archive.read_raw_rf(files[0])
    np.testing.assert_array_equal(raw.samples, p440.READER.read(REAL).samples)
    assert raw.scan_start_s == pytest.approx(36.684e-9)


# ----------------------------------------------------------------------------------------------- conversion


def _gaussian_rf(f0_hz: float, bandwidth_hz: float, n_bins: int = 1152, t0_s: float = 36.684e-9):
    t = t0_s + np.arange(n_bins) * T_BIN_S
    sigma = math.sqrt(math.log(10.0)) / (math.pi * bandwidth_hz)
    tau, phi = t0_s + 31.3e-9, 0.7

    def envelope(tt, fc):  # the analytic complex envelope, demodulated at fc (absolute delay)
        return 1000.0 * np.exp(
            -0.5 * ((tt - tau) / sigma) ** 2
            + 1j * (2 * np.pi * f0_hz * (tt - tau) + phi)
            - 2j * np.pi * fc * tt
        )

    return t, np.real(envelope(t, 0.0)), envelope


@pytest.mark.parametrize(("decimation", "max_error_db"), [(3, -90.0), (4, -55.0), (5, -42.0)])
def test_a_gaussian_modulated_rf_pulse_converts_to_its_analytic_complex_envelope_within_the_stated_error(
    decimation, max_error_db
):
    # Measured (max |error| / peak): D=3 (5.46 GHz) -95 dB, D=4 (4.10 GHz) -60 dB, D=5 (3.28 GHz) -50 dB: the
    # pulse's spectrum beyond the flat part of the kept band, which the conversion removes.
    t0 = 36.684e-9
    _, rf, envelope = _gaussian_rf(4.3e9, 1.7e9, t0_s=t0)
    fc = 4.27e9  # off the FFT grid: the fractional mix is exercised
    z, rate = baseband.to_baseband(rf[None, :], T_BIN_S, t0, fc, decimation)
    t_out = t0 + np.arange(z.shape[1]) / rate
    ref = envelope(t_out, fc)
    error_db = 20 * np.log10(np.abs(z[0] - ref).max() / np.abs(ref).max())
    assert error_db < max_error_db


def test_the_band_of_a_gaussian_pulse_is_measured_at_its_carrier_and_its_minus_10_db_width():
    _, rf, _ = _gaussian_rf(4.3e9, 1.7e9)
    band = baseband.measure_band(rf[None, :], T_BIN_S)
    assert band.centre_hz == pytest.approx(4.3e9, abs=15e6)
    assert band.bandwidth_hz == pytest.approx(1.7e9, rel=0.01)
    assert baseband.choose_decimation(1 / T_BIN_S, band) == 4  # 4.1 GHz for 1.7 GHz, as the paper's 4 GHz


def test_a_tone_in_the_band_keeps_its_amplitude_in_adc_counts():
    t = np.arange(2048) * T_BIN_S
    rf = 500.0 * np.cos(2 * np.pi * 4.1e9 * t + 0.3)
    z, _ = baseband.to_baseband(rf[None, :], T_BIN_S, 0.0, 4.0e9, 4)
    middle = np.abs(z[0, 100:-100])
    assert middle == pytest.approx(500.0, rel=1e-5)  # the ends of the cut tone ring a little (module doc)


# ----------------------------------------------------------------------------------------------- malformed


def _small_stream(tmp_path, n_scans=3, n_bins=700) -> Path:
    rf = np.arange(n_scans * n_bins, dtype=np.int32).reshape(n_scans, n_bins)
    return p440.write_p440_stream(tmp_path / "s.p440", rf, 1000 + 20 * np.arange(n_scans), scan_start_ps=9000)


def _patch(path: Path, offset: int, fmt: str, value) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))


def _record(k: int) -> int:
    return p440.CONFIG.size + k * p440.RECORD_BYTES


@pytest.mark.parametrize(
    ("field_offset", "fmt", "value", "message"),
    [
        (0, ">H", 0x1234, "message type 0x1234 is not MRM_SCAN_INFO"),
        (44, ">I", 10**9, "num_samples_total 1000000000 outside"),
        (42, ">H", 351, "num_samples_message 351 outside"),
        (28, ">i", 9999, "scan configuration changed mid-file"),
    ],
)
def test_a_malformed_record_is_rejected_with_a_message_naming_the_file_and_its_byte_offset(
    tmp_path, field_offset, fmt, value, message
):
    path = _small_stream(tmp_path)
    _patch(path, _record(3) + field_offset, fmt, value)  # message 1 of scan 1
    with pytest.raises(RecordingError) as err:
        p440.READER.read(path)
    assert str(err.value).startswith(f"{path}: byte {_record(3)}: ") and message in str(err.value)


def test_a_truncated_configuration_header_is_rejected_at_byte_0(tmp_path):
    path = tmp_path / "short.p440"
    path.write_bytes(bytes(20))
    with pytest.raises(RecordingError, match=r"short.p440: byte 0: truncated configuration header: 20 of 32"):
        p440.READER.read(path)


def test_a_truncated_last_record_and_a_scan_missing_a_message_are_dropped_with_log_lines(tmp_path, caplog):
    path = _small_stream(tmp_path, n_scans=4)
    data = path.read_bytes()
    # Lose message 1 of scan 1 (a lost packet) and cut the file inside the last record.
    damaged = data[: _record(3)] + data[_record(4) : -100]
    path.write_bytes(damaged)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(path)
    assert rec.n_scans == 2 and list(rec.scan_id) == [0, 2] and rec.n_dropped == 2
    assert "trailing bytes" in caplog.text and "stops after message 0 of 2" in caplog.text
    np.testing.assert_array_equal(rec.samples[1], np.arange(1400, 2100))


def _stream_with_stamps(tmp_path, stamps_ms, rows=None) -> Path:
    n_bins = 700
    rf = np.arange(len(stamps_ms) * n_bins, dtype=np.int32).reshape(len(stamps_ms), n_bins)
    if rows is not None:
        rf = rf[rows]
    return p440.write_p440_stream(tmp_path / "t.p440", rf, stamps_ms, scan_start_ps=9000)


def test_the_49_7_day_clock_rollover_is_a_short_step_forward_and_two_swapped_scans_a_short_step_back():
    wrap = 1 << 32
    np.testing.assert_array_equal(p440.unwrap_timestamps_ms([wrap - 30, wrap - 10, 10, 30]),
                                  [wrap - 30, wrap - 10, wrap + 10, wrap + 30])
    np.testing.assert_array_equal(p440.unwrap_timestamps_ms([1000, 1041, 1020, 1062]),
                                  [1000, 1041, 1020, 1062])


def test_two_scans_logged_out_of_order_are_put_back_in_the_radars_time_order_with_a_warning(tmp_path, caplog):
    # scans 1 and 2 swapped in the file: the second timestamp steps back 20 ms (the importer once took that
    # for a 2**32 ms rollover and put the pass 49.7 days away)
    path = _stream_with_stamps(tmp_path, [1000, 1040, 1020, 1060], rows=[0, 2, 1, 3])
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(path)
    np.testing.assert_allclose(rec.scan_time_s, [1.0, 1.02, 1.04, 1.06])
    np.testing.assert_array_equal(rec.samples[:, 0], [0, 700, 1400, 2100])
    assert "2 scans were out of time order (the first at byte" in caplog.text


def test_a_repeated_scan_is_dropped_naming_both_byte_offsets_and_counted_apart_from_incomplete_ones(
        tmp_path, caplog):
    path = _small_stream(tmp_path, n_scans=3)
    data = path.read_bytes()
    scan1 = data[_record(2):_record(4)]  # 700 bins: two messages per scan
    path.write_bytes(data[:_record(4)] + scan1 + data[_record(4):])
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(path)
    assert rec.n_scans == 3 and rec.n_repeated == 1 and rec.n_dropped == 0
    assert f"repeats the scan at byte {_record(2)}; dropped" in caplog.text
    assert (np.diff(rec.scan_time_s) > 0).all()


@needs_real
def test_lost_packets_and_scans_lost_whole_are_each_counted_once(tmp_path):
    """A scan losing a middle message is one incomplete scan (not two: its later messages are its own), and
    only incomplete scans between complete ones fill counter gaps: the partial last scan is no scan lost
    whole less (indepZb F2)."""
    data = REAL.read_bytes()
    records = [data[_record(i):_record(i + 1)] for i in range((len(data) - 32) // p440.RECORD_BYTES)]
    for scan in (600, 550, 500, 450, 420):  # lost packets: message 1 of these scans
        del records[4 * scan + 1]
    del records[400:440]  # scans 100-109 lost whole
    path = tmp_path / "lost.p440"
    path.write_bytes(data[:32] + b"".join(records))
    rec = p440.READER.read(path)
    assert rec.n_scans == 695 and rec.n_dropped == 6 and rec.n_lost == 10


@pytest.mark.parametrize(("stamps", "message"), [
    ([1000, 1020, 1020, 1040], "has the timestamp of a different scan"),
    ([5_000_000, 5_000_020, 40, 60], "the radar clock goes back"),
])
def test_a_clock_that_goes_back_beyond_a_reordering_or_two_scans_at_one_time_are_rejected_at_the_scan(
        tmp_path, stamps, message):
    path = _stream_with_stamps(tmp_path, stamps)
    with pytest.raises(RecordingError) as err:
        p440.READER.read(path)
    assert str(err.value).startswith(f"{path}: byte {_record(4)}: ") and message in str(err.value)


# ----------------------------------------------------------------------------------------------- positions


def test_the_longest_monotonic_moving_segment_drops_rests_and_the_turn_back():
    _, x = synthetic.rail_with_rests(-1.0, 1.0, 0.15, rest_s=1.0, scan_period_s=0.02)
    seg = passes.moving_segment(x, 1e-4)
    kept = x[seg]
    assert (np.diff(kept) > 0).all()
    assert kept[0] < -0.999 and kept[-1] > 0.999
    assert seg.start > 40 and seg.stop < len(x) - 40  # a second of rest at each end, and the turn back, cut


def test_a_positions_csv_error_names_the_file_and_line(tmp_path):
    path = tmp_path / "pos.csv"
    path.write_text("time_s,x_m\n0.0,1.0\n0.1,abc\n")
    with pytest.raises(RecordingError, match=r"pos.csv: line 3: x_m: not a number"):
        passes.read_positions_csv(path)
    path.write_text("t,x\n0,1\n")
    with pytest.raises(RecordingError, match=r"line 1: no column 'time_s'"):
        passes.read_positions_csv(path)
    path.write_text("time_s,x_m\n0.0,1.0\n0.1,1e308\n")  # a tester: it named an archive never written
    with pytest.raises(RecordingError, match=r"pos.csv: line 3: x_m: 1e\+308 m is beyond \+-1000 m"):
        passes.read_positions_csv(path)


# ----------------------------------------------------------------------------------------------- round trip

TARGETS_M = np.array([[0.786, -2.4, 0.3], [1.986, -2.4, 0.3]])  # paper-sim1's A and C; reference B
HEIGHT_M = 0.15
BOOT_S = 3436.645  # radar clock at the first scan
LOGGER_OFFSET_S = 1000.0 - BOOT_S  # positions time = radar time + this


@pytest.fixture(scope="module")
def synthetic_recording(tmp_path_factory):
    """A PulsON-like pass (real RF, differentiated-Gaussian pulse, 2.3 ns delay, coupling at 2 m, clutter,
    rests and a turn back at the ends, a partial last scan) and its encoder log, as files."""
    root = tmp_path_factory.mktemp("p440")
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0), height_m=HEIGHT_M)
    t, x = synthetic.rail_with_rests(-1.0, 1.0, 0.15, rest_s=1.5, scan_period_s=0.0206)
    rf = synthetic.simulate_rf(scene, x, 9000e-12, 480, np.random.default_rng(7))
    scan_file = p440.write_p440_stream(
        root / "pass.p440",
        rf,
        np.rint((BOOT_S + t) * 1e3).astype(int),
        scan_start_ps=9000,
        partial_last_scan_messages=1,
    )
    log_t = np.arange(0.0, t[-1], 0.01)  # the encoder logs at 100 Hz on its own clock
    positions = root / "pos.csv"
    rows = [f"{BOOT_S + LOGGER_OFFSET_S + tt:.4f},{xx:.6f}" for tt, xx in zip(log_t, np.interp(log_t, t, x))]
    positions.write_text("time_s,x_m\n" + "\n".join(rows) + "\n")
    site = root / "site.toml"
    site.write_text(synthetic.IMPORT_SITE_TOML)
    return scan_file, positions, site


def _import(tmp_path, recording, *extra):
    scan_file, positions, site = recording
    out = tmp_path / "out"
    rc = cli.main(
        [
            "import",
            "p440",
            str(scan_file),
            "--out",
            str(out),
            "--positions",
            str(positions),
            "--config",
            str(site),
            "--pass-start-time",
            "2026-11-23T06:00:00Z",
            *extra,
        ]
    )
    assert rc == 0
    (path,) = archive.find_pass_files(out)
    return archive.read_pass(path)


def _errors_mm(detections) -> np.ndarray:
    """(2, 2) along-track and closest-approach range error of the detection nearest each reflector, mm."""
    rc_true = np.hypot(TARGETS_M[:, 1], TARGETS_M[:, 2] - HEIGHT_M)
    out = []
    for x_t, rc_t in zip(TARGETS_M[:, 0], rc_true):
        d = min(detections, key=lambda d: math.hypot(d.x_m - x_t, d.rc_m - rc_t))
        out.append((1e3 * (d.x_m - x_t), 1e3 * (d.rc_m - rc_t)))
    return np.array(out)


def test_a_pulson_like_synthetic_pass_round_trips_to_reflectors_near_truth(
    tmp_path, synthetic_recording, capsys
):
    scan = _import(
        tmp_path, synthetic_recording, "--time-offset-s", str(LOGGER_OFFSET_S), "--range-delay-s", "2.3e-9"
    )
    text = capsys.readouterr().out
    assert "810 complete scans read, 1 incomplete dropped" in text and "trimmed" in text
    assert (np.diff(scan.pulse_position_m) > 0).all()
    assert scan.pulse_position_m[0] < -0.999 and scan.pulse_position_m[-1] > 0.999
    errors = _errors_mm(pipeline.detect_pass(scan, NUMPY_NLCS))
    # Measured with NLCS (numpy): along track -2.0 and -0.8 mm, range +0.2 and -0.2 mm. The coupling at 2 m
    # also gives a detection (coupling suppression is phase 2).
    assert np.abs(errors).max() < 5.0


def test_without_the_calibrated_delay_the_range_error_is_large_and_reported(
    tmp_path, synthetic_recording, capsys
):
    scan = _import(tmp_path, synthetic_recording, "--time-offset-s", str(LOGGER_OFFSET_S))
    assert "uncalibrated" in capsys.readouterr().err
    errors = _errors_mm(pipeline.detect_pass(scan, NUMPY_NLCS))
    # The envelope is c d / 2 = 344.8 mm late but the phase history is right: NLCS settles between them.
    # Measured: +319 and +283 mm in range.
    assert (errors[:, 1] > 200.0).all() and (errors[:, 1] < 1e3 * SPEED_OF_LIGHT_M_S * 2.3e-9 / 2 + 5).all()


def test_scans_lost_mid_pass_are_named_as_a_gap_in_the_track_when_imported(tmp_path, synthetic_recording,
                                                                           capsys):
    scan_file, positions, site = synthetic_recording
    data = scan_file.read_bytes()
    per_scan = 2 * p440.RECORD_BYTES  # 480 bins: two messages per scan
    holed = tmp_path / "holed.p440"
    holed.write_bytes(data[:_record(2 * 400)] + data[_record(2 * 420):])  # 20 scans (6 cm) lost mid-rail
    assert len(data) - len(holed.read_bytes()) == 20 * per_scan
    scan = _import(tmp_path, (holed, positions, site), "--time-offset-s", str(LOGGER_OFFSET_S))
    err = capsys.readouterr().err
    assert "warning: 1 gap(s) in the track" in err and "hole in the aperture" in err
    assert len(geometry.track_gaps(scan.pulse_position_m)) == 1


def test_the_clocks_align_on_the_first_motion_within_one_scan(synthetic_recording):
    scan_file, positions, _ = synthetic_recording
    rec = p440.READER.read(scan_file)
    track = passes.track_from_positions(rec, passes.read_positions_csv(positions), None, 1e-4)
    # Coarse by design (the echo and the encoder notice motion at different displacements): measured -14 ms,
    # within one scan period; --time-offset-s is the precise way.
    assert track.time_offset_s == pytest.approx(LOGGER_OFFSET_S, abs=0.0206)


def test_an_import_aligned_on_the_motion_says_its_error_is_not_in_the_bounds_and_one_given_the_offset_not(
        tmp_path, synthetic_recording, capsys):
    # indepZs F1: 43-85 ms late in steps of a scan on its passes, 'ok' rows 9 mm off against 1.8 mm bounds
    _import(tmp_path / "aligned", synthetic_recording, "--range-delay-s", "2.3e-9")
    assert "the bounds do not include it: give --time-offset-s" in capsys.readouterr().err
    _import(tmp_path / "given", synthetic_recording, "--range-delay-s", "2.3e-9", "--time-offset-s",
            str(LOGGER_OFFSET_S))
    assert "--time-offset-s" not in capsys.readouterr().err


def test_a_positions_log_started_after_the_rail_moved_cannot_align_the_clocks_on_its_first_motion(
        synthetic_recording, tmp_path):
    scan_file, positions, _ = synthetic_recording
    rows = positions.read_text().splitlines()
    late = tmp_path / "late.csv"
    late.write_text("\n".join([rows[0], *rows[1 + len(rows) // 2:]]) + "\n")  # the log starts mid-rail
    rec = p440.READER.read(scan_file)
    with pytest.raises(RecordingError, match="the log started after the rail did; give --time-offset-s"):
        passes.track_from_positions(rec, passes.read_positions_csv(late), None, 1e-4)
    # given the offset, the same log pairs the scans it covers
    track = passes.track_from_positions(rec, passes.read_positions_csv(late), LOGGER_OFFSET_S, 1e-4)
    assert track.n_outside_log > 0


# ----------------------------------------------------------------------------------------------- archive 1.1


def _simulated(range_delay_s: float = 0.0) -> ScanPass:
    g = PassGeometry(height_m=0.15, rotation_table_angle_deg=30.0, reference_point_m=(1.386, -2.4, 0.3))
    scan = simulate_pass(
        RadarParameters(),
        g,
        [[1.386, -2.4, 0.3]],
        aperture_length_m=1.0,
        speed_m_s=0.15,
        rng=np.random.default_rng(0),
        pass_start_time="2026-11-02T06:00:00Z",
    )
    scan.range_delay_s = range_delay_s
    return scan


def test_a_pass_without_additions_is_written_and_read_exactly_as_format_1_0(tmp_path, caplog):
    path = archive.write_pass(tmp_path / "a.h5", _simulated())
    with h5py.File(path) as f:
        assert "format_minor_version" not in f.attrs and "range_delay_s" not in f["radar"].attrs
        assert "raw" not in f
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        scan = archive.read_pass(path)
    assert caplog.text == ""
    assert scan.range_delay_s == 0.0 and scan.range_window_start_s == _simulated().range_window_start_s
    assert archive.read_raw_rf(path) is None


def test_range_delay_s_is_a_record_of_a_correction_already_in_the_window_start_so_1_0_readers_stay_right(
        tmp_path):
    delay = 2.3e-9
    plain = _simulated()
    archive.write_pass(tmp_path / "plain.h5", plain)
    # Imported with the calibrated delay: the window start is absolute (delay removed), the delay is recorded.
    calibrated = _simulated(delay)
    archive.write_pass(tmp_path / "calibrated.h5", calibrated)
    with h5py.File(tmp_path / "calibrated.h5") as f:
        assert f.attrs["format_minor_version"] == 1
        assert f["radar"].attrs["range_delay_s"] == delay
        # what a 1.0 reader, ignoring the attribute, uses: the absolute window start
        assert f["radar"].attrs["range_window_start_s"] == plain.range_window_start_s
    read = archive.read_pass(tmp_path / "calibrated.h5")
    assert read.range_delay_s == delay and read.range_window_start_s == plain.range_window_start_s
    # The same echo imported without the calibration: its axis starts c d / 2 further out.
    uncalibrated = _simulated()
    uncalibrated.range_window_start_s = plain.range_window_start_s + delay
    archive.write_pass(tmp_path / "uncalibrated.h5", uncalibrated)
    np.testing.assert_allclose(archive.read_pass(tmp_path / "uncalibrated.h5").range_axis_m
                               - read.range_axis_m, SPEED_OF_LIGHT_M_S * delay / 2, rtol=0, atol=1e-9)
    a = pipeline.detect_pass(archive.read_pass(tmp_path / "plain.h5"), NUMPY_NLCS)[0]
    b = pipeline.detect_pass(read, NUMPY_NLCS)[0]
    c = pipeline.detect_pass(archive.read_pass(tmp_path / "uncalibrated.h5"), NUMPY_NLCS)[0]
    # the calibrated delay is fully removed
    assert (b.x_m, b.rc_m) == pytest.approx((a.x_m, a.rc_m), abs=1e-9)
    # Uncalibrated, the envelope says R + c d / 2 and the phase history R: measured +0.30 m, not hidden.
    assert 0.15 < c.rc_m - a.rc_m < SPEED_OF_LIGHT_M_S * delay / 2 + 0.01


def test_an_unknown_radar_attribute_or_a_newer_minor_version_is_read_with_a_warning(tmp_path, caplog):
    path = archive.write_pass(tmp_path / "a.h5", _simulated())
    with h5py.File(path, "a") as f:
        f["radar"].attrs["pulse_spectrum_phase_rad"] = 1.0
        f.attrs["format_minor_version"] = np.int64(7)
        f.attrs["site_note"] = "root extras are free-form"
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        archive.read_pass(path)
        archive.read_pass_header(path)  # a run reads a file more than once: the reader says it once
        archive.read_pass(path)
    assert caplog.text.count("format 1.7 is newer") == 1
    assert caplog.text.count("/radar@pulse_spectrum_phase_rad") == 1 and "site_note" not in caplog.text


def test_a_nul_character_in_a_root_string_attribute_is_refused_by_name(tmp_path):
    path = archive.write_pass(tmp_path / "a.h5", _simulated())
    with h5py.File(path, "a") as f:
        f.attrs["rig_id"] = np.bytes_(b"rig\x00-1")  # a fixed-length string: NUL allowed
    with pytest.raises(archive.ArchiveError, match="contains a NUL character") as err:
        archive.read_pass(path)
    assert err.value.field == "/@rig_id"


def test_a_bad_range_delay_is_an_archive_error_naming_the_attribute(tmp_path):
    path = archive.write_pass(tmp_path / "a.h5", _simulated())
    with h5py.File(path, "a") as f:
        f["radar"].attrs["range_delay_s"] = "ten"
    with pytest.raises(archive.ArchiveError, match=r"/radar@range_delay_s: expected a real number"):
        archive.read_pass(path)


# ----------------------------------------------------------------------------------------------- cli


def test_import_usage_errors_exit_2_and_a_bad_file_exits_1_naming_it(tmp_path, capsys):
    bad = tmp_path / "notes.p440"
    bad.write_text("this is not a scan file at all, but it is longer than thirty-two bytes\n" * 30)
    common = ["import", "p440", str(bad), "--out", str(tmp_path / "o"), "--height-m", "0.2"]
    assert cli.main(common) == 2  # neither --positions nor --speed-m-s
    assert "exactly one of --positions" in capsys.readouterr().err
    assert (
        cli.main([*common, "--speed-m-s", "0.1", "--boresight-y-sign", "1", "--table-angle-deg", "95"]) == 2
    )
    assert "p440: --table-angle-deg: must be within (-90, 90)" in capsys.readouterr().err
    assert cli.main([*common, "--speed-m-s", "0.1"]) == 1
    err = capsys.readouterr().err
    assert f"{bad}: byte 32: message type" in err and "Traceback" not in err
    site = tmp_path / "site.toml"
    site.write_text("[import]\nheigth_m = 0.2\n")
    assert cli.main([*common, "--speed-m-s", "0.1", "--config", str(site)]) == 2
    assert "import.heigth_m: unknown key" in capsys.readouterr().err
