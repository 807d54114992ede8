"""Fixtures shared by the batch tests: the shift of shift_case.py, written and processed once per module."""

from __future__ import annotations

from pathlib import Path

import pytest
from shift_case import CONFIG, SETTINGS, options

from uwbcl import batch, shift


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
