"""The archive reader is a security boundary: it reads only what the file itself holds, only regular files,
and never more than the limits admit (issue: hostile and broken input cannot hurt the nightly batch)."""

from __future__ import annotations

import math
import os
import resource
import subprocess
import sys
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest
from test_archive import make_scan

from uwbcl.archive import ArchiveError, read_pass, read_pass_header, write_pass
from uwbcl.records import ReadLimits


@pytest.fixture
def good(tmp_path: Path) -> Path:
    return write_pass(tmp_path / "tree" / "good.h5", make_scan())


def copy_with(src: Path, dst: Path, change) -> Path:
    dst.write_bytes(src.read_bytes())
    with h5py.File(dst, "r+") as f:
        change(f)
    return dst


def refused(path: Path, field: str, words: str) -> ArchiveError:
    with pytest.raises(ArchiveError) as info:
        read_pass(path)
    assert info.value.field == field and words in info.value.reason, str(info.value)
    assert str(path) in str(info.value)
    return info.value


def test_an_external_link_to_a_file_outside_the_tree_is_refused_by_name(tmp_path, good):
    outside = write_pass(tmp_path / "outside.h5", make_scan(seed=5))

    def link(f):
        del f["echo"]
        f["echo"] = h5py.ExternalLink(str(outside), "/echo")

    bad = copy_with(good, good.with_name("ext.h5"), link)
    refused(bad, "/echo", "external link")


def test_an_external_link_to_etc_passwd_is_refused_without_opening_it(good):
    def link(f):
        del f["radar"]
        f["radar"] = h5py.ExternalLink("/etc/passwd", "/x")

    refused(copy_with(good, good.with_name("passwd.h5"), link), "/radar", "external link")


def test_a_virtual_dataset_is_refused(tmp_path, good):
    outside = write_pass(tmp_path / "outside.h5", make_scan(seed=5))

    def virtual(f):
        shape = f["pulses/time_s"].shape
        layout = h5py.VirtualLayout(shape=shape, dtype="f8")
        layout[:] = h5py.VirtualSource(str(outside), "/pulses/time_s", shape=shape)
        del f["pulses/time_s"]
        ds = f["pulses"].create_virtual_dataset("time_s", layout)
        ds.attrs["units"] = "s"

    refused(copy_with(good, good.with_name("vds.h5"), virtual), "/pulses/time_s", "virtual dataset")


def test_external_raw_storage_is_refused(tmp_path, good):
    raw = tmp_path / "raw.bin"
    raw.write_bytes(np.arange(21, dtype="<f8").tobytes())

    def external(f):
        del f["pulses/time_s"]
        ds = f["pulses"].create_dataset("time_s", shape=(21,), dtype="<f8", external=[(str(raw), 0, 21 * 8)])
        ds.attrs["units"] = "s"

    refused(copy_with(good, good.with_name("extraw.h5"), external), "/pulses/time_s", "external raw storage")


def test_a_soft_link_loop_is_refused_naming_the_object(good):
    def loop(f):
        del f["echo"]
        f["echo"] = h5py.SoftLink("/echo")

    refused(copy_with(good, good.with_name("loop.h5"), loop), "/echo", "soft link")


def test_a_dataset_declaring_a_trillion_samples_is_refused_before_any_read(good):
    def huge(f):
        del f["echo"]
        ds = f.create_dataset("echo", shape=(1_000_000, 1_000_000), dtype="c8", chunks=(64, 64))
        ds.attrs["units"], ds.attrs["layout"], ds.attrs["scale"] = "arb", "complex", 1.0

    bad = copy_with(good, good.with_name("huge.h5"), huge)
    assert bad.stat().st_size < 1 << 20
    refused(bad, "/echo", "exceed the limit")
    with pytest.raises(ArchiveError, match="exceed the limit"):
        read_pass_header(bad)


def test_a_compression_bomb_within_the_limits_is_refused_by_a_lower_limit_and_read_within_bounded_memory(
        good):
    def bomb(f):
        del f["echo"]
        ds = f.create_dataset("echo", shape=(21, 4_000_000), dtype="c8", chunks=(1, 1 << 18),
                              compression="gzip", compression_opts=9)
        ds[...] = 0  # 670 MB of zeros in a few hundred kB
        ds.attrs["units"], ds.attrs["layout"], ds.attrs["scale"] = "arb", "complex", 1.0
        f["radar"].attrs["samples_per_pulse"] = np.int64(4_000_000)

    bad = copy_with(good, good.with_name("bomb.h5"), bomb)
    assert bad.stat().st_size < 8 << 20
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    refused(bad, "/echo", "exceed the limit")
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 64 << 10  # kB: nothing decompressed


def _tiny_chunks(pulses: int):
    def tiny(f):  # an independent tester's file: the echo declared in one-sample chunks, none written
        for name in ("echo", "pulses/time_s", "pulses/position_m"):
            del f[name]
        ds = f.create_dataset("echo", shape=(pulses, 48), dtype=np.complex64, chunks=(1, 1),
                              compression="gzip")
        ds.attrs.update({"units": "arb", "layout": "complex", "scale": 1.0})
        f["radar"].attrs["samples_per_pulse"] = np.int64(48)
        for name, values, unit in (("time_s", np.arange(pulses) * 1e-4, "s"),
                                   ("position_m", np.linspace(-0.5, 0.5, pulses), "m")):
            ds = f.create_dataset(f"pulses/{name}", shape=(pulses,), dtype="f8", chunks=(pulses,),
                                  compression="gzip")
            ds.attrs["units"] = unit
            ds[...] = values
    return tiny


def _peak_rss_kb(path: Path) -> int:
    """The peak resident memory (kB) of a fresh Python that reads the pass: VmHWM, which starts again at the
    exec (ru_maxrss keeps the forking test process's)."""
    code = ("import sys; from uwbcl.archive import read_pass; read_pass(sys.argv[1]); "
            "print(next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')))")
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return int(done.stdout)


def test_an_echo_stored_in_tens_of_thousands_of_one_sample_chunks_is_read_within_bounded_memory(good):
    # an independent tester: a 455 kB file declaring 50,000 one-sample chunks took 4 GB to read at once
    bad = copy_with(good, good.with_name("tiny.h5"), _tiny_chunks(10_000))
    assert bad.stat().st_size < 8 << 20 and math.prod(h5py.File(bad)["echo"].shape) > 40_000
    assert _peak_rss_kb(bad) - _peak_rss_kb(good) < 100 << 10  # kB; 1.8 GB read at once
    assert read_pass(bad).echo.shape[0] == 10_000


def test_an_echo_stored_in_more_than_a_million_chunks_is_refused_before_any_read(good):
    refused(copy_with(good, good.with_name("tinier.h5"), _tiny_chunks(60_000)), "/echo",
            "chunks of [1, 1], more than 1048576: not read")


@pytest.mark.parametrize("name", ["echo", "pulses/time_s"])
def test_a_chunk_declared_far_larger_than_its_dataset_is_refused_before_hdf5_inflates_it(good, name):
    def bomb(f):  # the right shape, in one chunk of gigabytes (legal with a larger maxshape)
        data, attrs = f[name][()], dict(f[name].attrs)
        del f[name]
        big = (16_000, 1024) if data.ndim == 2 else (20_000_000,)  # 125 / 153 MiB
        ds = f.create_dataset(name, data=data, chunks=big, maxshape=(None,) * data.ndim, compression="gzip")
        ds.attrs.update(attrs)

    bad = copy_with(good, good.with_name("chunkbomb.h5"), bomb)
    assert bad.stat().st_size < 1 << 20
    refused(bad, f"/{name}", "a chunk may hold at most 64 MiB or the whole dataset")


def test_filters_other_than_the_standard_lossless_ones_are_refused(good):
    def scaleoffset(f):
        data = f["pulses/position_m"][()]
        del f["pulses/position_m"]
        ds = f["pulses"].create_dataset("position_m", data=data, scaleoffset=6, chunks=(21,))
        ds.attrs["units"] = "m"

    refused(copy_with(good, good.with_name("lossy.h5"), scaleoffset), "/pulses/position_m",
            "not one of the allowed")


def test_lzf_and_shuffle_are_accepted(good):
    def lzf(f):
        data = f["pulses/position_m"][()]
        del f["pulses/position_m"]
        ds = f["pulses"].create_dataset("position_m", data=data, compression="lzf", shuffle=True,
                                        chunks=(21,))
        ds.attrs["units"] = "m"

    read_pass(copy_with(good, good.with_name("lzf.h5"), lzf))


def test_a_huge_attribute_is_refused_without_reading_it(good):
    def attr(f):
        del f["geometry"].attrs["reference_point_m"]
        f["geometry"].attrs.create("reference_point_m", np.zeros(100_000))

    refused(copy_with(good, good.with_name("attr.h5"), attr), "/geometry@reference_point_m", "far larger")


def test_a_fifo_named_like_an_archive_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "x.h5"
    os.mkfifo(fifo)
    box = {}

    def read():
        try:
            read_pass(fifo)
        except ArchiveError as e:
            box["error"] = e

    worker = threading.Thread(target=read, daemon=True)
    worker.start()
    worker.join(10.0)
    assert not worker.is_alive(), "read_pass blocked on a FIFO"
    assert "FIFO" in box["error"].reason


def test_a_directory_named_like_an_archive_is_refused(tmp_path):
    (tmp_path / "d.h5").mkdir()
    with pytest.raises(ArchiveError, match="a directory"):
        read_pass(tmp_path / "d.h5")


def test_a_padded_compound_echo_is_refused_naming_the_dataset(good):
    def padded(f):
        data = f["echo"][()]
        del f["echo"]
        dt = np.dtype({"names": ["r", "i"], "formats": ["<f4", "<f4"], "offsets": [0, 8], "itemsize": 16})
        arr = np.zeros(data.shape, dtype=dt)
        arr["r"], arr["i"] = data.real, data.imag
        ds = f.create_dataset("echo", data=arr)
        ds.attrs["units"], ds.attrs["layout"], ds.attrs["scale"] = "arb", "complex", 1.0

    bad = copy_with(good, good.with_name("padded.h5"), padded)
    try:
        scan = read_pass(bad)
    except ArchiveError as e:
        assert e.field == "/echo"
    else:  # h5py maps it to complex: then the values must be the stored ones, not garbage
        np.testing.assert_allclose(scan.echo, read_pass(good).echo, rtol=1e-6)


def test_tighter_limits_refuse_a_pass_the_defaults_accept(good):
    read_pass(good)
    with pytest.raises(ArchiveError, match="max_echo_samples"):
        read_pass(good, ReadLimits(max_echo_samples=100))


@pytest.mark.parametrize("short", [4096, 246_000])
def test_a_deflate_chunk_that_inflates_short_without_a_checksum_is_refused_not_read_as_zeros(good, short):
    """HDF5 fills the rest of a chunk whose deflate stream ends early with zeros, or with whatever its buffer
    held (different on every read), without an error; the format allows gzip without Fletcher-32."""
    import zlib

    def truncated_stream(f):
        echo = f["echo"][()]
        attrs = dict(f["echo"].attrs)
        del f["echo"]
        ds = f.create_dataset("echo", shape=echo.shape, dtype=echo.dtype, chunks=echo.shape,
                              compression="gzip")
        raw = echo.tobytes()
        ds.id.write_direct_chunk((0,) * echo.ndim, zlib.compress(raw[:max(8, len(raw) - short)]))
        ds.attrs.update(attrs)

    bad = copy_with(good, good.with_name("short.h5"), truncated_stream)
    refused(bad, "/echo", "inflates to")
    # the same dataset, whole, reads: gzip without a checksum is legal
    whole = copy_with(good, good.with_name("whole.h5"), lambda f: _regzip(f, zlib))
    assert read_pass(whole).echo.shape == read_pass(good).echo.shape


def _regzip(f, zlib):
    echo, attrs = f["echo"][()], dict(f["echo"].attrs)
    del f["echo"]
    ds = f.create_dataset("echo", shape=echo.shape, dtype=echo.dtype, chunks=echo.shape, compression="gzip")
    ds.id.write_direct_chunk((0,) * echo.ndim, zlib.compress(echo.tobytes()))
    ds.attrs.update(attrs)
