"""Packaging regression test: the OpenCL kernels must ship inside the wheel as ``uwbcl/kernels``."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_contains_kernels(tmp_path: Path) -> None:
    cl_files = sorted(p.name for p in (REPO / "kernels").glob("*.cl"))
    if not cl_files:
        pytest.skip("no kernels/*.cl files in the repository yet")
    if importlib.util.find_spec("hatchling") is None:
        pytest.skip("hatchling is not installed; cannot build the wheel without build isolation")

    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "-w", str(tmp_path), str(REPO)],
        check=False,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, f"pip wheel failed:\n{proc.stdout}\n{proc.stderr}"

    wheels = list(tmp_path.glob("uwbcl-*.whl"))
    assert len(wheels) == 1, f"expected one uwbcl wheel, found {wheels}"
    with zipfile.ZipFile(wheels[0]) as zf:
        names = set(zf.namelist())

    missing = [name for name in cl_files if f"uwbcl/kernels/{name}" not in names]
    assert not missing, f"kernels missing from {wheels[0].name}: {missing}"
