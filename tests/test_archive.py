"""Scan archive format v1 (docs/archive-format.md): what write_pass produces and what read_pass accepts."""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
from pathlib import Path

import h5py
import numpy as np
import pytest

from uwbcl import archive
from uwbcl.archive import ArchiveError, read_pass, read_pass_header, write_pass
from uwbcl.model import PassGeometry, RadarParameters, ScanPass

N_PULSES, N_SAMPLES = 21, 32


def make_scan(seed: int = 0, **changes) -> ScanPass:
    rng = np.random.default_rng(seed)
    scan = ScanPass(
        radar=RadarParameters(),
        geometry=PassGeometry(
            height_m=0.15, rotation_table_angle_deg=30.0, reference_point_m=(1.386, -2.4, 0.3)
        ),
        range_window_start_s=12.5e-9,
        pulse_time_s=np.arange(N_PULSES) / 20.0 + 0.01 * rng.random(N_PULSES),
        pulse_position_m=-1.0 + 0.0075 * np.arange(N_PULSES),
        echo=rng.standard_normal((N_PULSES, N_SAMPLES)) + 1j * rng.standard_normal((N_PULSES, N_SAMPLES)),
        rig_id="rig-7",
        cycle=12,
        pass_start_time="2026-11-21T10:00:00Z",
    )
    return dataclasses.replace(scan, **changes)


@pytest.fixture
def scan() -> ScanPass:
    return make_scan()


@pytest.fixture
def scan_file(tmp_path: Path, scan: ScanPass) -> Path:
    return write_pass(tmp_path / "scan.h5", scan)


def edit(path: Path, change) -> Path:
    """Damage a valid file in place, the way a buggy writer would."""
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def expect_error(path: Path, field: str, reason: str = "") -> ArchiveError:
    with pytest.raises(ArchiveError) as info:
        read_pass(path)
    err = info.value
    assert err.field == field, str(err)
    assert reason in err.reason, str(err)
    assert str(err).startswith(f"{path}: {field}: ")
    return err


# ------------------------------------------------------------------------------------------- round trips


def assert_same_metadata(got: ScanPass, want: ScanPass) -> None:
    assert got.radar == want.radar
    assert got.geometry == want.geometry
    assert got.range_window_start_s == want.range_window_start_s
    assert (got.rig_id, got.cycle, got.pass_start_time) == (want.rig_id, want.cycle, want.pass_start_time)
    np.testing.assert_array_equal(got.pulse_time_s, want.pulse_time_s)
    np.testing.assert_array_equal(got.pulse_position_m, want.pulse_position_m)


def test_complex64_round_trip_keeps_metadata_exactly_and_echo_to_float32_precision(scan, scan_file):
    got = read_pass(scan_file)

    assert_same_metadata(got, scan)
    assert got.source == str(scan_file)
    assert got.echo.dtype == np.complex128 and got.echo.shape == (N_PULSES, N_SAMPLES)
    np.testing.assert_allclose(got.echo, scan.echo, rtol=1e-7, atol=0)
    np.testing.assert_array_equal(got.echo, scan.echo.astype(np.complex64))


def test_complex128_round_trip_is_exact(tmp_path, scan):
    got = read_pass(write_pass(tmp_path / "scan.h5", scan, echo_dtype="complex128"))

    np.testing.assert_array_equal(got.echo, scan.echo)


def test_int16_layout_stores_iq_counts_and_round_trips_within_half_a_count(tmp_path, scan):
    path = write_pass(tmp_path / "scan.h5", scan, echo_dtype="int16")

    with h5py.File(path, "r") as f:
        ds = f["echo"]
        assert ds.dtype == np.int16 and ds.shape == (N_PULSES, N_SAMPLES, 2)
        assert ds.attrs["layout"] == "int16_iq"
        scale = float(ds.attrs["scale"])
        assert np.abs(ds[()]).max() == 32767  # the peak component uses full scale
    peak = max(np.abs(scan.echo.real).max(), np.abs(scan.echo.imag).max())
    assert scale == pytest.approx(peak / 32767)
    got = read_pass(path)
    assert got.echo.dtype == np.complex128
    assert_same_metadata(got, scan)
    assert np.abs(got.echo.real - scan.echo.real).max() <= scale / 2 * (1 + 1e-9)
    assert np.abs(got.echo.imag - scan.echo.imag).max() <= scale / 2 * (1 + 1e-9)


def test_all_zero_echo_in_int16_layout_gets_a_positive_scale(tmp_path):
    scan = make_scan(echo=np.zeros((N_PULSES, N_SAMPLES), complex))

    got = read_pass(write_pass(tmp_path / "scan.h5", scan, echo_dtype="int16"))

    np.testing.assert_array_equal(got.echo, 0)


def test_rail_may_run_in_either_direction(tmp_path, scan):
    backwards = make_scan(pulse_position_m=scan.pulse_position_m[::-1].copy())

    got = read_pass(write_pass(tmp_path / "back.h5", backwards))

    np.testing.assert_array_equal(got.pulse_position_m, backwards.pulse_position_m)


def test_file_follows_documented_layout(scan_file):
    with h5py.File(scan_file, "r") as f:
        assert f.attrs["format"] == "uwbcl-scan" and f.attrs["format_version"] == 1
        assert f.attrs["format_version"].dtype == np.int64 and f.attrs["cycle"].dtype == np.int64
        assert f.attrs["pass_id"] == "rig-7-c000012-h0150"
        assert set(f.attrs) == {
            "format",
            "format_version",
            "rig_id",
            "cycle",
            "pass_id",
            "pass_start_time",
            "created_by",
        }
        assert set(f["radar"].attrs) == {
            "carrier_frequency_hz",
            "bandwidth_hz",
            "bandwidth_definition",
            "pulse_shape",
            "sample_rate_hz",
            "pulse_repetition_frequency_hz",
            "antenna_aperture_m",
            "range_window_start_s",
            "samples_per_pulse",
        }
        assert f["radar"].attrs["bandwidth_definition"] == "-10 dB"
        assert f["radar"].attrs["pulse_shape"] == "gaussian"
        assert set(f["geometry"].attrs) == {
            "height_m",
            "rotation_table_angle_deg",
            "reference_point_m",
            "boresight_y_sign",
        }
        assert f["geometry"].attrs["reference_point_m"].shape == (3,)
        units = {name: f[name].attrs["units"] for name in ("pulses/time_s", "pulses/position_m", "echo")}
        assert units == {"pulses/time_s": "s", "pulses/position_m": "m", "echo": "arb"}
        echo = f["echo"]
        assert echo.dtype == np.complex64 and echo.attrs["layout"] == "complex" and echo.attrs["scale"] == 1.0
        assert echo.chunks is not None and echo.compression == "gzip" and echo.fletcher32
        # libver=("v110", "v110"): superblock version 3 is what HDF5 1.10 writes and reads.
        assert f.id.get_create_plist().get_version()[0] == 3


def test_header_gives_metadata_without_reading_the_echo(scan_file):
    corrupt_echo_chunk(scan_file)  # the echo is unreadable now; the header must not care

    header = read_pass_header(scan_file)

    assert header["rig_id"] == "rig-7" and header["cycle"] == 12 and header["height_m"] == 0.15
    assert header["pass_id"] == "rig-7-c000012-h0150"
    assert header["pass_start_time"] == "2026-11-21T10:00:00Z"
    assert (header["n_pulses"], header["samples_per_pulse"]) == (N_PULSES, N_SAMPLES)
    assert header["echo_layout"] == "complex" and header["path"] == str(scan_file)
    assert header["reference_point_m"] == (1.386, -2.4, 0.3)


def test_explicit_pass_id_and_created_by_are_stored(tmp_path, scan):
    path = write_pass(tmp_path / "scan.h5", scan, pass_id="rescan-2", created_by="unit test")

    header = read_pass_header(path)

    assert (header["pass_id"], header["created_by"]) == ("rescan-2", "unit test")


def test_unknown_extra_attributes_and_datasets_are_ignored(scan, scan_file):
    def add_extras(f):
        f.attrs["operator"] = "night shift"
        f["radar"].attrs["firmware"] = "1.2.3"
        f.create_dataset("calibration/noise_floor", data=[1.0, 2.0])

    assert_same_metadata(read_pass(edit(scan_file, add_extras)), scan)


def test_one_element_arrays_are_accepted_as_scalars(scan, scan_file):
    # MATLAB's h5writeatt writes scalars as shape (1,): still a valid file.
    def as_arrays(f):
        f["radar"].attrs["sample_rate_hz"] = np.array([4.0e9])
        f.attrs["cycle"] = np.array([12], dtype=np.int32)

    assert_same_metadata(read_pass(edit(scan_file, as_arrays)), scan)


def test_a_column_or_row_vector_is_accepted_for_a_three_vector(scan, scan_file):
    # MATLAB writes a vector attribute as (3, 1) or (1, 3) (indepZa F7)
    for shape in ((3, 1), (1, 3)):
        def as_matrix(f, shape=shape):
            f["geometry"].attrs["reference_point_m"] = np.reshape(scan.geometry.reference_point_m, shape)

        assert_same_metadata(read_pass(edit(scan_file, as_matrix)), scan)


def test_a_sample_rate_below_the_bandwidth_is_read_with_a_warning(scan_file, caplog):
    def undersampled(f):
        f["radar"].attrs["sample_rate_hz"] = 0.8 * f["radar"].attrs["bandwidth_hz"]

    path = edit(scan_file, undersampled)
    with caplog.at_level(logging.WARNING, logger="uwbcl"):
        read_pass(path)
    assert f"{path}: /radar@sample_rate_hz" in caplog.text and "is below bandwidth_hz" in caplog.text


def test_recommended_file_name(scan):
    assert archive.default_relative_path(scan) == Path("rig-7/2026-11-21/rig-7_c000012_h0150.h5")


def test_discovery_skips_partial_files(tmp_path, scan):
    final = write_pass(tmp_path / "rig-7" / "a.h5", scan)
    (tmp_path / "rig-7" / ".b.h5.partial").write_bytes(b"")
    (tmp_path / "rig-7" / ".c.h5").write_bytes(b"")

    assert archive.find_pass_files(tmp_path) == [final]


# ------------------------------------------------------------------------------------------- damaged files


def test_truncated_file_is_reported(scan_file):
    data = scan_file.read_bytes()
    scan_file.write_bytes(data[: len(data) // 2])

    expect_error(scan_file, "/", "truncated")


def test_non_hdf5_file_is_reported(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("this is not HDF5\n")

    expect_error(path, "/", "not an HDF5 file")


def test_missing_file_is_not_a_format_error(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_pass(tmp_path / "nowhere.h5")


def corrupt_echo_chunk(path: Path) -> None:
    with h5py.File(path, "r") as f:
        chunk = f["echo"].id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(chunk.byte_offset + chunk.size // 2)
        byte = fh.read(1)
        fh.seek(-1, os.SEEK_CUR)
        fh.write(bytes([byte[0] ^ 0xFF]))


def test_corrupted_echo_data_is_caught_by_the_checksum(scan_file):
    corrupt_echo_chunk(scan_file)

    expect_error(scan_file, "/echo", "cannot read data")


def test_foreign_hdf5_file_is_reported_by_format(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["x"] = [1, 2, 3]

    expect_error(path, "/@format", "missing")


@pytest.mark.parametrize(
    ("group", "attr"),
    [
        ("/", "rig_id"),
        ("/", "pass_start_time"),
        ("/radar", "sample_rate_hz"),
        ("/radar", "samples_per_pulse"),
        ("/geometry", "boresight_y_sign"),
        ("/echo", "scale"),
        ("/pulses/time_s", "units"),
    ],
)
def test_missing_attribute_is_named(scan_file, group, attr):
    edit(scan_file, lambda f: f[group].attrs.__delitem__(attr))

    field = f"/@{attr}" if group == "/" else f"{group}@{attr}"
    err = expect_error(scan_file, field, "missing")
    assert str(err) == f"{scan_file}: {field}: missing"


@pytest.mark.parametrize("name", ["/pulses/time_s", "/pulses/position_m", "/echo", "/geometry"])
def test_missing_dataset_or_group_is_named(scan_file, name):
    edit(scan_file, lambda f: f.__delitem__(name))

    expect_error(scan_file, name, "missing")


def test_nan_in_echo_is_reported_with_its_location(scan_file):
    def put_nan(f):
        f["echo"][3, 5] = complex(np.nan, 0.0)

    err = expect_error(edit(scan_file, put_nan), "/echo", "NaN or inf")
    assert "pulse 3, sample 5" in err.reason


def test_an_echo_whose_values_would_overflow_float32_focusing_is_refused_and_one_below_is_read(scan_file):
    def scale_to(value):
        def change(f):
            f["echo"].attrs["scale"] = value / float(np.max(np.abs(f["echo"][()].view(np.float32))))
        return change

    read_pass(edit(scan_file, scale_to(1e29)))  # far beyond any radar, still safe in float32
    err = expect_error(edit(scan_file, scale_to(3e37)), "/echo", "where float32 focusing would overflow")
    assert "values up to 3e+37" in err.reason


@pytest.mark.parametrize("name", ["/pulses/time_s", "/pulses/position_m"])
def test_non_finite_pulse_values_are_reported(scan_file, name):
    def put_inf(f):
        f[name][4] = np.inf

    err = expect_error(edit(scan_file, put_inf), name, "NaN or inf")
    assert "pulse 4" in err.reason


def replace_dataset(f, name, data):
    units = f[name].attrs["units"]
    del f[name]
    f.create_dataset(name, data=data).attrs["units"] = units


def test_pulse_times_shorter_than_echo_rows_is_reported(scan, scan_file):
    edit(scan_file, lambda f: replace_dataset(f, "/pulses/time_s", scan.pulse_time_s[:-1]))

    expect_error(scan_file, "/pulses/time_s", f"expected ({N_PULSES},)")


def test_samples_per_pulse_must_match_echo(scan_file):
    edit(scan_file, lambda f: f["radar"].attrs.__setitem__("samples_per_pulse", np.int64(N_SAMPLES + 1)))

    expect_error(scan_file, "/radar@samples_per_pulse", "disagrees with /echo")


def test_pulse_times_must_increase(scan, scan_file):
    times = scan.pulse_time_s.copy()
    times[7] = times[6]
    edit(scan_file, lambda f: replace_dataset(f, "/pulses/time_s", times))

    expect_error(scan_file, "/pulses/time_s", "strictly increasing (at pulse 7)")


def test_rail_positions_must_not_stand_still_or_reverse(scan, scan_file):
    positions = scan.pulse_position_m.copy()
    positions[10] = positions[8]
    edit(scan_file, lambda f: replace_dataset(f, "/pulses/position_m", positions))

    expect_error(scan_file, "/pulses/position_m", "strictly monotonic (at pulse 10)")


def test_newer_format_version_asks_for_an_upgrade(scan_file):
    edit(scan_file, lambda f: f.attrs.__setitem__("format_version", np.int64(2)))

    expect_error(scan_file, "/@format_version", "newer than this reader supports")


def test_unknown_older_format_version_is_rejected(scan_file):
    edit(scan_file, lambda f: f.attrs.__setitem__("format_version", np.int64(0)))

    expect_error(scan_file, "/@format_version", "unknown version 0")


@pytest.mark.parametrize(
    ("group", "attr", "value", "reason"),
    [
        ("/", "format", "hdf5-scan", "expected 'uwbcl-scan'"),
        ("/", "format_version", 1.0, "expected an integer"),
        ("/", "pass_start_time", "2026-11-21T10:00:00+02:00", "must be UTC"),
        ("/", "pass_start_time", "yesterday", "not an ISO 8601"),
        ("/radar", "sample_rate_hz", -4.0e9, "must be > 0"),
        ("/radar", "carrier_frequency_hz", np.nan, "must be finite"),
        ("/radar", "bandwidth_definition", "-3 dB", "expected '-10 dB'"),
        ("/radar", "pulse_shape", "chirp", "expected one of 'gaussian', 'measured'"),
        ("/radar", "bandwidth_hz", "1.7 GHz", "expected a real number"),
        ("/geometry", "boresight_y_sign", np.int64(0), "must be -1 or +1"),
        ("/geometry", "rotation_table_angle_deg", 95.0, "within (-90, 90)"),
        ("/geometry", "reference_point_m", np.array([1.0, 2.0]), "expected 3 real numbers"),
        ("/echo", "units", "V", "expected 'arb'"),
        ("/echo", "layout", "float32", "expected 'complex' or 'int16_iq'"),
        ("/echo", "scale", 0.0, "must be finite and > 0"),
        ("/echo", "scale", np.inf, "must be finite and > 0"),
    ],
)
def test_bad_attribute_values_are_named(scan_file, group, attr, value, reason):
    edit(scan_file, lambda f: f[group].attrs.__setitem__(attr, value))

    field = f"/@{attr}" if group == "/" else f"{group}@{attr}"
    expect_error(scan_file, field, reason)


def test_echo_layout_must_match_its_storage(scan_file):
    edit(scan_file, lambda f: f["echo"].attrs.__setitem__("layout", "int16_iq"))

    expect_error(scan_file, "/echo", "needs int16 of shape (N, M, 2)")


def test_archive_error_is_a_value_error_that_survives_pickling(tmp_path):
    err = ArchiveError(tmp_path / "scan.h5", "/radar@sample_rate_hz", "missing")

    copy = pickle.loads(pickle.dumps(err))

    assert isinstance(copy, ValueError)
    assert str(copy) == str(err) == f"{tmp_path / 'scan.h5'}: /radar@sample_rate_hz: missing"


# ------------------------------------------------------------------------------------------- writing safely


def test_existing_file_is_not_overwritten_unless_asked(tmp_path, scan, scan_file):
    before = scan_file.read_bytes()
    with pytest.raises(FileExistsError):
        write_pass(scan_file, make_scan(seed=1))
    assert scan_file.read_bytes() == before

    write_pass(scan_file, make_scan(seed=1), overwrite=True)
    np.testing.assert_allclose(read_pass(scan_file).echo, make_scan(seed=1).echo, rtol=1e-7)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.h5"]


def test_failure_while_writing_leaves_no_file_behind(tmp_path, scan, monkeypatch):
    real_write = archive._write_dataset

    def fail_on_echo(f, name, data):
        if name == "/echo":
            assert any(p.name.endswith(".partial") for p in tmp_path.iterdir())  # really mid-write
            raise OSError("disk full")
        return real_write(f, name, data)

    monkeypatch.setattr(archive, "_write_dataset", fail_on_echo)
    with pytest.raises(OSError, match="disk full"):
        write_pass(tmp_path / "scan.h5", scan)

    assert list(tmp_path.iterdir()) == []


def test_failed_fsync_leaves_no_file_behind(tmp_path, scan, monkeypatch):
    def no_fsync(fd):
        raise OSError("I/O error")

    monkeypatch.setattr(archive.os, "fsync", no_fsync)
    with pytest.raises(OSError, match="I/O error"):
        write_pass(tmp_path / "scan.h5", scan)

    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"echo": np.full((N_PULSES, N_SAMPLES), np.nan + 0j)}, "/echo"),
        ({"echo": np.ones((N_PULSES, N_SAMPLES))}, "/echo"),  # real, not complex baseband
        ({"pulse_time_s": np.zeros(N_PULSES)}, "/pulses/time_s"),
        ({"pulse_position_m": np.zeros(N_PULSES - 1)}, "/pulses/position_m"),
        ({"pass_start_time": "2026-11-21 10:00"}, "/@pass_start_time"),
        (
            {"geometry": PassGeometry(0.15, 30.0, (0.0, -2.4, 0.3), boresight_y_sign=2)},
            "/geometry@boresight_y_sign",
        ),
        # a scene centre on the rail's own line (a tester: a ZeroDivisionError in the focusing)
        ({"geometry": PassGeometry(0.15, 30.0, (0.0, 0.0, 0.15))}, "/geometry@reference_point_m"),
        ({"cycle": 2**63}, "/@cycle"),
    ],
)
def test_writer_refuses_a_pass_the_reader_would_reject(tmp_path, changes, field):
    with pytest.raises(ArchiveError) as info:
        write_pass(tmp_path / "scan.h5", make_scan(**changes))

    assert info.value.field == field
    assert list(tmp_path.iterdir()) == []


def test_unknown_echo_dtype_is_refused(tmp_path, scan):
    with pytest.raises(ValueError, match="echo_dtype"):
        write_pass(tmp_path / "scan.h5", scan, echo_dtype="float32")


@pytest.mark.parametrize("echo_dtype", ["complex64", "int16", "complex128"])
def test_a_pass_as_stored_is_what_reading_its_archive_gives_to_the_last_bit(scan, tmp_path, echo_dtype):
    # `acquire --process` measures this, so that its rows are `uwbcl process`'s (indepZi F2)
    path = write_pass(tmp_path / f"{echo_dtype}.h5", scan, echo_dtype=echo_dtype)
    np.testing.assert_array_equal(archive.as_stored(scan, echo_dtype).echo, read_pass(path).echo)
    if echo_dtype != "complex128":
        assert not np.array_equal(archive.as_stored(scan, echo_dtype).echo, scan.echo)
