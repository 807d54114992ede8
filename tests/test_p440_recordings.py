"""PulsON 440 recordings we do not have (an independent tester's findings, docs/importing.md): what a
recording that is not one clean pass of one radar gets, and what a site needs to import its heights."""

from __future__ import annotations

import logging
import os
import struct
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest

from uwbcl import archive, cli
from uwbcl.importers import RecordingError, baseband, p440, passes, synthetic

TARGETS_M = np.array([[0.786, -2.4, 0.3], [1.986, -2.4, 0.3]])


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A PulsON-like pass (docs/importing.md section 6) and its positions log, as files."""
    root = tmp_path_factory.mktemp("p440rec")
    scene = synthetic.P440Scene(targets_m=TARGETS_M, amplitudes=(1.0, 1.0))
    scan_file, positions = synthetic.write_recording(root, scene)
    site = root / "site.toml"
    site.write_text(synthetic.IMPORT_SITE_TOML)
    return scan_file, positions, site


def _import(tmp_path, recording, *extra) -> tuple[int, str, str]:
    scan_file, positions, site = recording
    rc = cli.main(["import", "p440", str(scan_file), "--out", str(tmp_path / "out"), "--positions",
                   str(positions), "--config", str(site), "--pass-start-time", "2026-11-23T06:00:00Z",
                   "--range-delay-s", "2.3e-9", *extra])
    return rc


def test_a_fixed_bandwidth_and_carrier_are_written_as_given_and_said_so(tmp_path, recording, capsys):
    # Two heights imported from two recordings measure -10 dB widths about 1 % apart, and a cycle's passes
    # must agree within 1 %: the site fixes both, as it fixes the carrier.
    assert _import(tmp_path, recording, "--carrier-hz", "4.05e9", "--bandwidth-hz", "1.6e9") == 0
    out = capsys.readouterr().out
    assert "written: carrier 4.0500 GHz, -10 dB bandwidth 1.6000 GHz (given, not measured)" in out
    (path,) = archive.find_pass_files(tmp_path / "out")
    with h5py.File(path, "r") as f:
        assert f["radar"].attrs["bandwidth_hz"] == 1.6e9
        assert f["radar"].attrs["carrier_frequency_hz"] == 4.05e9


def test_a_bandwidth_far_from_the_measured_one_is_warned_about_and_a_bad_one_is_a_usage_error(
        tmp_path, recording, caplog, capsys):
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _import(tmp_path, recording, "--bandwidth-hz", "0.5e9") == 0
    assert "off the measured -10 dB width" in caplog.text
    assert _import(tmp_path / "b", recording, "--bandwidth-hz", "-1") == 2
    assert "--bandwidth-hz: must be > 0" in capsys.readouterr().err


def test_a_carrier_far_from_the_measured_centre_is_warned_about(tmp_path, recording, caplog):
    # measured: centre 4.081 GHz, -10 dB width 1.618 GHz; 10 % of the width is 162 MHz
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert _import(tmp_path, recording, "--carrier-hz", "4.05e9") == 0
        assert "from the measured -10 dB centre" not in caplog.text
        assert _import(tmp_path / "b", recording, "--carrier-hz", "3.85e9") == 0
    assert "the carrier given, 3.85e+09 Hz, is 231 MHz from the measured -10 dB centre" in caplog.text


def test_a_measured_pulse_window_holding_only_noise_is_a_usage_error(tmp_path, recording, capsys):
    # 3.0-3.3 m: between the clutter at 1.3 / 3.6 m and the reflectors' ranges, nothing stationary; the
    # coupling at 2 m is the default window's and is accepted.
    assert _import(tmp_path, recording, "--pulse", "measured", "--pulse-window-m", "2.85", "3.15") == 2
    err = capsys.readouterr().err
    assert "--pulse-window-m: the pulse's reference window 2.85-3.15 m holds no stationary echo" in err
    assert "20 dB needed" in err and not archive.find_pass_files(tmp_path / "out")
    assert _import(tmp_path / "ok", recording, "--pulse", "measured") == 0


def _stream(tmp_path, n_scans=6, n_bins=700, name="s.p440") -> Path:
    rng = np.random.default_rng(3)
    rf = rng.integers(-2000, 2000, size=(n_scans, n_bins), dtype=np.int32)
    return p440.write_p440_stream(tmp_path / name, rf, 1000 + 20 * np.arange(n_scans), scan_start_ps=9000)


def _record(k: int) -> int:
    return p440.CONFIG.size + k * p440.RECORD_BYTES


def _patch(path: Path, offset: int, fmt: str, value) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(("field_offset", "fmt", "value", "message"), [
    (4, ">I", 7, "node_id 7, antenna_id 2: the file's scans so far came from node_id 100, antenna_id 2"),
    (40, ">B", 1, "node_id 100, antenna_id 1: the file's scans so far came from node_id 100, antenna_id 2"),
])
def test_scans_of_another_radar_or_antenna_in_the_file_are_refused_at_their_byte_offset(
        tmp_path, field_offset, fmt, value, message):
    path = _stream(tmp_path)
    for k in (4, 5):  # both messages of scan 2
        _patch(path, _record(k) + field_offset, fmt, value)
    with pytest.raises(RecordingError) as err:
        p440.READER.read(path)
    assert str(err.value).startswith(f"{path}: byte {_record(4)}: {message}")
    assert "not one pass" in str(err.value)


def test_a_header_that_contradicts_the_messages_is_warned_about_and_the_messages_win(tmp_path, caplog):
    path = _stream(tmp_path)
    _patch(path, 4, ">i", 20000)  # the configuration header's scan_start
    for k in range(12):  # every message's scan_stop: 491 bins of 61 ps, not the 700 samples carried
        _patch(path, _record(k) + 32, ">i", 9000 + 30000)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(path)
    assert rec.scan_start_s == pytest.approx(9e-9) and rec.n_bins == 700
    assert "configuration header's scan window" in caplog.text and "the messages' is used" in caplog.text
    assert "holds 491.5 bins" in caplog.text and "the messages carry 700 samples" in caplog.text


def test_a_file_of_scans_that_all_claim_more_messages_lists_ten_counts_the_rest_and_says_why(
        tmp_path, caplog):
    path = _stream(tmp_path, n_scans=30)
    for k in range(60):
        _patch(path, _record(k) + 50, ">H", 188)  # num_messages_total: 188 (and 65536 samples to carry)
        _patch(path, _record(k) + 44, ">I", 65536)
        _patch(path, _record(k) + 48, ">H", 0)  # every message claims to be message 0 of its scan
    with caplog.at_level(logging.WARNING, logger="uwbcl"), pytest.raises(RecordingError) as err:
        p440.READER.read(path)
    assert caplog.text.count("dropped an incomplete scan") == p440.LISTED_DROPS
    assert f"{60 - p440.LISTED_DROPS} more incomplete scans dropped (not listed)" in caplog.text
    assert "no complete scan in the file; 60 incomplete scan(s) dropped, the first because scan 0" in str(
        err.value)


def test_a_scan_whose_message_0_is_lost_is_counted_as_dropped_once(tmp_path, caplog):
    path = _stream(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[:_record(2)] + data[_record(3):])  # message 0 of scan 1 lost
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rec = p440.READER.read(path)
    assert rec.n_scans == 5 and rec.n_dropped == 1 and list(rec.scan_id) == [0, 2, 3, 4, 5]
    assert "message 1 of scan 1 at byte" in caplog.text and "has no message 0" in caplog.text


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_given_as_the_recording_or_the_positions_is_refused_without_blocking(tmp_path, recording):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for read in (p440.READER.read, passes.read_positions_csv):
        errors = []

        def attempt(read=read, errors=errors):
            try:
                read(fifo)
            except RecordingError as exc:
                errors.append(str(exc))
        worker = threading.Thread(target=attempt, daemon=True)
        worker.start()
        worker.join(20.0)
        if worker.is_alive():  # blocked in open(): release it (a writer that closes at once), then fail
            with open(fifo, "wb"):
                pass
            pytest.fail(f"{read.__qualname__} blocked on a FIFO")
        assert errors and "not a regular file" in errors[0]


def test_a_directory_given_as_the_recording_or_the_positions_is_refused_by_its_name(tmp_path):
    for read in (p440.READER.read, passes.read_positions_csv):
        with pytest.raises(RecordingError) as err:
            read(tmp_path)
        assert str(err.value).startswith(f"{tmp_path}: ") and "not a regular file" in str(err.value)


def test_a_recording_without_signal_is_refused_as_such(tmp_path, capsys):
    path = p440.write_p440_stream(tmp_path / "z.p440", np.zeros((20, 700), np.int32),
                                  1000 + 20 * np.arange(20), scan_start_ps=9000)
    rc = cli.main(["import", "p440", str(path), "--out", str(tmp_path / "out"), "--speed-m-s", "0.1",
                   "--height-m", "0.3"])
    captured = capsys.readouterr()
    assert rc == 1 and "no signal: every kept scan is constant (0 in every sample)" in captured.err
    assert "RuntimeWarning" not in captured.err


def test_a_spreadsheets_csv_with_a_byte_order_mark_reads_and_a_semicolon_one_is_named(tmp_path):
    bom = tmp_path / "bom.csv"
    bom.write_bytes("\ufefftime_s,x_m\r\n0.0,0.0\r\n0.1,0.01\r\n".encode())
    assert passes.read_positions_csv(bom).x_m.tolist() == [0.0, 0.01]
    semi = tmp_path / "semi.csv"
    semi.write_text("time_s;x_m\n0.0;0.0\n")
    with pytest.raises(RecordingError, match="the columns must be separated by commas"):
        passes.read_positions_csv(semi)


def test_a_second_pass_in_the_recording_is_named_with_the_time_that_selects_it(tmp_path, recording, caplog):
    # The pass out and back: the way back (as long as the way out) is another pass, left out with a warning.
    scan_file, positions, site = recording
    rows = positions.read_text().splitlines()
    t = np.array([float(r.split(",")[0]) for r in rows[1:]])
    x = np.array([float(r.split(",")[1]) for r in rows[1:]])
    back = np.concatenate([x, x[::-1]])
    t2 = np.concatenate([t, t[-1] + (t - t[0]) + 0.0206])
    log2 = tmp_path / "pos2.csv"
    log2.write_text("time_s,x_m\n" + "".join(f"{a:.4f},{b:.6f}\n" for a, b in zip(t2, back)))
    rec = p440.READER.read(scan_file)
    long = dict(rec.__dict__)
    long.update(samples=np.concatenate([rec.samples, rec.samples[::-1]]),
                scan_time_s=np.concatenate([rec.scan_time_s, rec.scan_time_s[-1] + 0.0206
                                            + (rec.scan_time_s - rec.scan_time_s[0])]),
                scan_id=np.arange(2 * rec.n_scans))
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        track = passes.track_from_positions(type(rec)(**long), passes.read_positions_csv(log2), 0.0, 1e-4)
    assert track.x_m[-1] > track.x_m[0]  # the first of two equal passes is kept
    assert "the recording holds another pass, not imported" in caplog.text
    assert "give a positions log that covers only its time" in caplog.text


def test_positions_in_millimetres_are_warned_about(tmp_path, recording, caplog):
    scan_file, positions, site = recording
    rows = positions.read_text().splitlines()
    mm = tmp_path / "mm.csv"
    mm.write_text(rows[0] + "\n" + "".join(f"{r.split(',')[0]},{1e3 * float(r.split(',')[1]):.3f}\n"
                                           for r in rows[1:]))
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        rc = cli.main(["import", "p440", str(scan_file), "--out", str(tmp_path / "out"), "--positions",
                       str(mm), "--config", str(site), "--pass-start-time", "2026-11-23T06:00:00Z",
                       "--time-offset-s", "0"])
    assert rc == 0 and "the pass spans 1999.9 m along the rail" in caplog.text
    assert "are the positions in metres (x_m)?" in caplog.text


def test_a_broken_pipe_on_stdout_ends_quietly_without_a_traceback(monkeypatch, capsys):
    def closed(args):  # `uwbcl devices | head -0`: the reader went away
        raise BrokenPipeError(32, "Broken pipe")
    monkeypatch.setattr(cli, "_devices", closed)
    assert cli.main(["devices"]) == 141
    assert "Traceback" not in capsys.readouterr().err


def test_a_coarse_scan_res_whose_pulse_fits_under_nyquist_converts_although_its_kept_band_reaches_past_it():
    # scan_res 48: 91.6 ps bins, RF Nyquist 5.46 GHz; a 1.5 GHz pulse at 4.0 GHz (-20 dB band 2.94-5.06 GHz)
    # fits, the 2.4 x B complex band around it (2.2-5.8 GHz) does not: the part past Nyquist is empty.
    t_bin = p440.bin_period_s(48)
    t0, n = 10e-9, 500
    t = t0 + np.arange(n) * t_bin
    sigma = np.sqrt(np.log(10.0)) / (np.pi * 1.5e9)
    tau = t0 + 20e-9

    def envelope(tt, fc):
        return 1000.0 * np.exp(-0.5 * ((tt - tau) / sigma) ** 2 + 2j * np.pi * 4.0e9 * (tt - tau)
                               - 2j * np.pi * fc * tt)
    rf = np.real(envelope(t, 0.0))[None, :]
    band = baseband.measure_band(rf, t_bin)
    baseband.check_band(rf, 1 / t_bin, band)  # not refused
    d = baseband.choose_decimation(1 / t_bin, band)
    assert band.centre_hz + 0.5 / (d * t_bin) > 0.5 / t_bin  # the kept band does reach past Nyquist
    z, rate = baseband.to_baseband(rf, t_bin, t0, band.centre_hz, d)
    ref = envelope(t0 + np.arange(z.shape[1]) / rate, band.centre_hz)
    assert 20 * np.log10(np.abs(z[0] - ref).max() / np.abs(ref).max()) < -40.0


def test_a_recording_too_short_to_focus_is_imported_with_a_warning_and_an_hdf5_file_gets_the_hint(
        tmp_path, capsys):
    t = np.arange(700) * p440.bin_period_s(32)
    echo = np.rint(9000 * synthetic.rf_pulse(t - 20e-9, 4.0e9, 1.5e9)).astype(np.int32)
    short = p440.write_p440_stream(tmp_path / "three.p440", np.repeat(echo[None], 3, axis=0),
                                   1000 + 20 * np.arange(3), scan_start_ps=9000)
    assert cli.main(["import", "p440", str(short), "--out", str(tmp_path / "out"), "--speed-m-s", "0.1",
                     "--height-m", "0.3"]) == 0
    assert "warning: 3 pulses: too few to focus (at least 6)" in capsys.readouterr().err
    h5 = tmp_path / "pass.h5"
    with h5py.File(h5, "w") as f:
        f["x"] = np.zeros(100)
    assert cli.main(["import", "p440", str(h5), "--out", str(tmp_path / "out2"), "--speed-m-s", "0.1",
                     "--height-m", "0.3"]) == 1
    assert "(not a PulsON 440 scan file?)" in capsys.readouterr().err


def test_a_scan_lost_whole_is_counted_by_the_radars_scan_counter(tmp_path, capsys):
    t = np.arange(700) * p440.bin_period_s(32)
    echo = np.rint(9000 * synthetic.rf_pulse(t - 20e-9, 4.0e9, 1.5e9)).astype(np.int32)
    path = p440.write_p440_stream(tmp_path / "gap.p440", np.repeat(echo[None], 12, axis=0),
                                  1000 + 20 * np.arange(12), scan_start_ps=9000)
    data = path.read_bytes()
    path.write_bytes(data[:_record(10)] + data[_record(12):])  # both messages of scan 5: never received
    assert cli.main(["import", "p440", str(path), "--out", str(tmp_path / "out"), "--speed-m-s", "0.1",
                     "--height-m", "0.3"]) == 0
    out = capsys.readouterr().out
    assert ("11 complete scans read, 0 incomplete dropped, 1 lost whole (the radar's scan counter skips them)"
            in out)


def test_a_scan_counter_that_stays_put_is_warned_about_since_scans_lost_whole_cannot_be_counted(tmp_path,
                                                                                                 caplog):
    t = np.arange(700) * p440.bin_period_s(32)
    echo = np.rint(9000 * synthetic.rf_pulse(t - 20e-9, 4.0e9, 1.5e9)).astype(np.int32)
    path = p440.write_p440_stream(tmp_path / "stuck.p440", np.repeat(echo[None], 12, axis=0),
                                  1000 + 20 * np.arange(12), scan_start_ps=9000)
    for k in range(24):  # a firmware that numbers every scan 7 (both messages of each of the 12 scans)
        _patch(path, _record(k) + 2, ">H", 7)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        assert cli.main(["import", "p440", str(path), "--out", str(tmp_path / "out"), "--speed-m-s", "0.1",
                         "--height-m", "0.3"]) == 0
    assert "scan counter (message_id) stays or goes back at 11 of 11 scans" in caplog.text


def test_a_recording_that_starts_after_the_rail_is_warned_about_and_one_that_stops_early_is_not_refused(
        tmp_path, recording, caplog, capsys):
    """First-motion alignment assumes both ends at rest, checked on the last motion: a recording whose first
    74 scans were not recorded (its 1.5 s rest is 73) is shifted along the rail by the 0.17 s the rail had
    moved, said in a warning with both offsets (indepZb F1); one that stops while the rail still moves cannot
    be checked, which a warning says, and imports (it was refused: indepZe 1)."""
    scan_file, positions, site = recording
    data = scan_file.read_bytes()
    per_scan = int.from_bytes(data[32 + 50:32 + 52], "big")  # num_messages_total of the first record
    late, early_stop = tmp_path / "late.p440", tmp_path / "early-stop.p440"
    late.write_bytes(data[:32] + data[32 + 1452 * per_scan * 74:])
    early_stop.write_bytes(data[:len(data) - 1452 * per_scan * 150])  # the last 3 s: the rail still moves
    for name, path in (("late", late), ("stop", early_stop)):
        args = ["import", "p440", str(path), "--out", str(tmp_path / name), "--positions", str(positions),
                "--config", str(site), "--pass-start-time", "2026-11-23T06:00:00Z",
                "--range-delay-s", "2.3e-9"]
        with caplog.at_level(logging.WARNING, logger="uwbcl"):
            caplog.clear()
            assert cli.main(args) == 0
        said = {"late": "late.p440: the clocks aligned on the first motion (positions time = scan time "
                        "-0.179 s, used) and on the last one (+0.040 s) are 219 ms apart",
                "stop": "early-stop.p440: the clocks aligned on the first motion could not be checked"}
        assert said[name] in caplog.text
    assert "cannot align" not in capsys.readouterr().err


def test_a_missing_rail_height_is_a_usage_error_before_the_recording_is_read(tmp_path, capsys):
    # reading a 1 GB recording takes about a minute: a height neither given nor in the positions (no z_m)
    # is said first (indepZb)
    positions = tmp_path / "pos.csv"
    positions.write_text("time_s,x_m\n0,0\n1,0.1\n2,0.2\n")
    unread = tmp_path / "not-yet-read.p440"
    unread.write_text("not a recording: never opened when the flags already fail")
    assert cli.main(["import", "p440", str(unread), "--out", str(tmp_path / "out"), "--positions",
                     str(positions)]) == 2
    err = capsys.readouterr().err
    assert "--height-m: required: the rail height is the median z_m of the positions" in err
    assert "not a PulsON 440" not in err
