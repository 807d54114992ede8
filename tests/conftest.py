"""Fixtures shared by the tests: the shift of shift_case.py, written and processed once per module (the
batch tests), and the process's OpenCL engine."""

from __future__ import annotations

import os
from pathlib import Path

from uwbcl.threads import one_blas_thread

# Before numpy loads: BLAS on one thread in this process as in `uwbcl` and its workers, so that a run in this
# process and one in the pool agree to the last bit.
one_blas_thread()

import pytest  # noqa: E402
from shift_case import CONFIG, SETTINGS, options  # noqa: E402

from uwbcl import batch, opencl, shift  # noqa: E402


@pytest.fixture(scope="module")
def archive_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("shift")
    shift.write_shift(out, CONFIG)
    return out


@pytest.fixture(scope="module")
def clean(archive_dir, tmp_path_factory):
    """The clean run over archive_dir: (output directory, report)."""
    out = tmp_path_factory.mktemp("clean-out")
    report = batch.process_directory(archive_dir, out, SETTINGS, options())
    return out, report


@pytest.fixture(scope="module")
def engine():
    """The process's OpenCL engine (`shared_engine`); skipped without OpenCL unless UWBCL_REQUIRE_OPENCL=1, as
    CI sets it, where a missing OpenCL fails."""
    try:
        from uwbcl.focus.engine import shared_engine

        return shared_engine()
    except opencl.OpenClUnavailable as exc:
        if os.environ.get("UWBCL_REQUIRE_OPENCL") == "1":
            raise
        pytest.skip(f"no OpenCL: {exc}")
