"""Archive format 1.2 additions (docs/archive-format.md section 9): the measured pulse and the per-pulse rail
deviations, written, read back and validated like the rest of the format."""

from __future__ import annotations

import dataclasses
import logging

import h5py
import numpy as np
import pytest
from test_archive import N_PULSES, edit, expect_error, make_scan

from uwbcl import archive
from uwbcl.archive import ArchiveError, read_pass, read_pass_header, write_pass
from uwbcl.model import MeasuredPulse, gaussian_pulse_spectrum

F_HZ = np.linspace(-2.0e9, 2.0e9, 65)


def measured_pulse() -> MeasuredPulse:
    u = F_HZ / 1.7e9
    return MeasuredPulse(F_HZ, gaussian_pulse_spectrum(F_HZ, 1.6e-10) * (1 + 0.3 * u) * np.exp(1j * u**2))


def bent_scan():
    scan = make_scan()
    x = scan.pulse_position_m
    return dataclasses.replace(scan, radar=dataclasses.replace(scan.radar, measured_pulse=measured_pulse()),
                               antenna_y_m=0.01 * np.cos(x), antenna_z_m=-0.004 * x)


@pytest.fixture
def bent_file(tmp_path):
    return write_pass(tmp_path / "bent.h5", bent_scan())


def test_the_measured_pulse_and_the_rail_deviations_round_trip_as_a_1_2_file(bent_file):
    want = bent_scan()
    got = read_pass(bent_file)
    np.testing.assert_array_equal(got.radar.measured_pulse.frequency_hz, F_HZ)
    np.testing.assert_allclose(got.radar.measured_pulse.spectrum, want.radar.measured_pulse.spectrum,
                               rtol=1e-15, atol=1e-15)
    assert dataclasses.replace(got.radar, measured_pulse=None) == dataclasses.replace(want.radar,
                                                                                      measured_pulse=None)
    np.testing.assert_array_equal(got.antenna_y_m, want.antenna_y_m)
    np.testing.assert_array_equal(got.antenna_z_m, want.antenna_z_m)
    with h5py.File(bent_file) as f:
        assert f.attrs["format_minor_version"] == 2
        assert f["radar"].attrs["pulse_shape"] == "measured"
        assert f["radar/pulse_frequency_hz"].attrs["units"] == "Hz"
        assert f["radar/pulse_spectrum"].dtype.kind == "c"
        assert f["pulses/antenna_y_m"].attrs["units"] == "m"
    assert read_pass_header(bent_file)["pulse_shape"] == "measured"


def test_the_reader_normalises_the_spectrum_to_a_peak_of_one(tmp_path):
    pulse = measured_pulse()
    with h5py.File(write_pass(tmp_path / "p.h5", bent_scan()), "r+") as f:
        f["radar/pulse_spectrum"][...] = 7.5j * pulse.spectrum
        path = f.filename
    got = read_pass(path).radar.measured_pulse
    assert np.abs(got.spectrum).max() == pytest.approx(1.0)
    np.testing.assert_allclose(got.spectrum, 1j * pulse.spectrum, atol=1e-15)


def test_a_file_without_the_additions_stays_a_gaussian_file_without_a_minor_version(tmp_path):
    path = write_pass(tmp_path / "plain.h5", make_scan())
    with h5py.File(path) as f:
        assert "format_minor_version" not in f.attrs and "pulse_spectrum" not in f["radar"]
    scan = read_pass(path)
    assert scan.radar.measured_pulse is None and scan.antenna_y_m is None and scan.antenna_z_m is None


def test_one_deviation_alone_is_a_valid_1_2_file(tmp_path):
    path = write_pass(tmp_path / "y.h5", make_scan(antenna_y_m=np.full(N_PULSES, 0.002)))
    scan = read_pass(path)
    assert scan.antenna_z_m is None and scan.antenna_y_m[0] == 0.002
    assert h5py.File(path).attrs["format_minor_version"] == 2


def _replace(f, name, data):
    units = f[name].attrs["units"]
    del f[name]
    f[name] = data
    f[name].attrs["units"] = units


@pytest.mark.parametrize("change, field, reason", [
    (lambda f: f.__delitem__("radar/pulse_spectrum"), "/radar/pulse_spectrum", "missing"),
    (lambda f: _replace(f, "radar/pulse_spectrum", np.ones(64, complex)), "/radar/pulse_spectrum",
     "has 65"),
    (lambda f: _replace(f, "radar/pulse_spectrum", np.ones(65)), "/radar/pulse_spectrum", "complex"),
    (lambda f: _replace(f, "radar/pulse_spectrum", np.zeros(65, complex)), "/radar/pulse_spectrum",
     "all zero"),
    (lambda f: _replace(f, "radar/pulse_spectrum", np.r_[np.nan, np.ones(64)].astype(complex)),
     "/radar/pulse_spectrum", "NaN or inf at sample 0"),
    (lambda f: _replace(f, "radar/pulse_frequency_hz", F_HZ[::-1]), "/radar/pulse_frequency_hz",
     "not strictly increasing"),
    (lambda f: _replace(f, "radar/pulse_frequency_hz", np.r_[F_HZ[:-1], np.inf]), "/radar/pulse_frequency_hz",
     "inf Hz at sample 64: must be finite and within +-sample_rate_hz"),
    (lambda f: _replace(f, "radar/pulse_frequency_hz", np.linspace(-9e9, 9e9, 65)),
     "/radar/pulse_frequency_hz",     "-9000000000.0 Hz at sample 0"),
    (lambda f: _replace(f, "radar/pulse_frequency_hz", np.ones((65, 2))), "/radar/pulse_frequency_hz",
     "1-D real"),
    (lambda f: (_replace(f, "radar/pulse_frequency_hz", np.arange(70000.0) - 35000),
                _replace(f, "radar/pulse_spectrum", np.ones(70000, complex))),
     "/radar/pulse_frequency_hz", "70000 samples, expected 2 to 65536"),
    (lambda f: f["radar/pulse_frequency_hz"].attrs.__setitem__("units", "GHz"),
     "/radar/pulse_frequency_hz@units", "expected 'Hz'"),
    (lambda f: f["radar"].attrs.__setitem__("pulse_shape", "gaussian"), "/radar/pulse_frequency_hz",
     "pulse_shape is 'gaussian'"),
    (lambda f: _replace(f, "pulses/antenna_y_m", np.zeros(N_PULSES - 1)), "/pulses/antenna_y_m",
     f"shape ({N_PULSES},)"),
    (lambda f: _replace(f, "pulses/antenna_z_m", np.r_[np.zeros(N_PULSES - 1), np.nan]),
     "/pulses/antenna_z_m",     f"at pulse {N_PULSES - 1}"),
    (lambda f: _replace(f, "pulses/antenna_y_m", np.full(N_PULSES, 0.6)), "/pulses/antenna_y_m",
     "within +-0.5 m"),
])
def test_malformed_additions_are_named(bent_file, change, field, reason):
    err = expect_error(edit(bent_file, change), field, reason)
    assert str(bent_file) in str(err)


def test_measured_pulse_shape_without_its_datasets_is_named(tmp_path):
    path = write_pass(tmp_path / "p.h5", make_scan())
    edit(path, lambda f: f["radar"].attrs.__setitem__("pulse_shape", "measured"))
    expect_error(path, "/radar/pulse_frequency_hz", "missing")


def test_the_writer_refuses_deviations_the_reader_would_reject(tmp_path):
    with pytest.raises(ArchiveError, match="antenna_z_m"):
        write_pass(tmp_path / "w.h5", make_scan(antenna_z_m=np.full(N_PULSES, np.inf)))
    assert not (tmp_path / "w.h5").exists()


def test_the_reader_knows_minor_version_2():
    assert archive.FORMAT_MINOR_VERSION == 2


def test_the_additions_of_1_2_in_a_file_that_declares_1_0_are_used_with_a_warning(bent_file, caplog):
    # an independent tester: such a file's deviations doubled a row's creep without a word (both readings of
    # the version rule are defensible: the data are used, and the reader says so)
    with h5py.File(bent_file, "r+") as f:
        del f.attrs["format_minor_version"]
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        got = read_pass(bent_file)
    np.testing.assert_array_equal(got.antenna_y_m, bent_scan().antenna_y_m)
    assert "/pulses/antenna_y_m, /pulses/antenna_z_m, /radar/pulse_frequency_hz" in caplog.text
    assert "in a file that declares format 1.0: used as 1.2 defines them" in caplog.text
