"""The code meets the lint rules pyproject.toml selects (line length 110, complexity 15, pyflakes, import
order): checked on every run, so a long line or a tangled function fails CI instead of piling up."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing_in_the_package_the_scripts_and_the_tests():
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    assert Path(ruff).exists(), "ruff is needed (pip install -e '.[test]')"
    run = subprocess.run([ruff, "check", "--no-cache", "uwbcl", "scripts", "tests"], cwd=ROOT,
                         capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
