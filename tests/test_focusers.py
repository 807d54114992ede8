"""The backend seam: every backend is a `Focuser`, the stage table names real code in each, and the documents
print the same tables the code holds (docs/method.md section 3, docs/configuration.md [detection])."""

from __future__ import annotations

import ast
import dataclasses
import importlib.util
import re
from pathlib import Path

import pytest

from uwbcl import config
from uwbcl.focus import backprojection, nlcs, scipy32
from uwbcl.focus.engine import FocusEngine
from uwbcl.focus.protocol import FOCUSER_METHODS, STAGES, Focuser
from uwbcl.focus.reference import NUMPY_FOCUSER, NumpyFocuser
from uwbcl.focus.scipy32 import SCIPY32_FOCUSER, Scipy32Focuser
from uwbcl.records import DetectionSettings

ROOT = Path(__file__).resolve().parents[1]
FOCUS_MODULES = {"nlcs": nlcs, "backprojection": backprojection, "scipy32": scipy32}


def _kernels() -> set[str]:
    """{"file.cl: name"} of every kernel in kernels/."""
    out = set()
    for path in (ROOT / "kernels").glob("*.cl"):
        out |= {f"{path.name}: {m}" for m in re.findall(r"__kernel\s+void\s+(\w+)\s*\(", path.read_text())}
    return out


def _resolve(name: str, kernels: set[str]) -> bool:
    if ".cl: " in name:
        return name in kernels
    owner, _, attr = name.partition(".")
    if owner == "FocusEngine":
        return callable(getattr(FocusEngine, attr, None))
    return owner in FOCUS_MODULES and callable(getattr(FOCUS_MODULES[owner], attr, None))


def test_the_numpy_reference_the_scipy32_baseline_and_the_opencl_engine_are_focusers():
    assert isinstance(NUMPY_FOCUSER, Focuser) and isinstance(NumpyFocuser(), Focuser)
    assert isinstance(SCIPY32_FOCUSER, Focuser) and isinstance(Scipy32Focuser(), Focuser)
    assert issubclass(FocusEngine, Focuser)  # an instance needs a device: tests/test_opencl_engine.py
    # modules are no longer passed as focusers: the numpy module lacks backprojection_focus
    assert not isinstance(nlcs, Focuser) and not isinstance(scipy32, Focuser)


def test_the_protocols_methods_are_the_stage_tables_focuser_stages():
    members = {n for n, v in vars(Focuser).items() if callable(v) and not n.startswith("_")}
    assert members == set(FOCUSER_METHODS)
    assert set(FOCUSER_METHODS) <= {s.name for s in STAGES}
    assert len({s.name for s in STAGES}) == len(STAGES)


def test_every_stage_names_a_function_or_kernel_that_exists_in_each_backend():
    kernels = _kernels()
    for stage in STAGES:
        for backend, name in (("numpy", stage.numpy), ("scipy32", stage.scipy32), ("opencl", stage.opencl)):
            assert _resolve(name, kernels), f"{stage.name}: {backend} names {name!r}, which does not exist"
        assert not stage.numpy.startswith("scipy32."), "the numpy column names float64 reference functions"


@pytest.mark.parametrize("focuser", [NUMPY_FOCUSER, SCIPY32_FOCUSER], ids=repr)
def test_the_cpu_focusers_methods_call_the_functions_the_stage_table_names(focuser, monkeypatch):
    column = "scipy32" if isinstance(focuser, Scipy32Focuser) else "numpy"
    args = {"nlcs_focus": (None,), "backprojection_focus": (None,), "nlcs_model_spectra": (None,) * 4,
            "calibration_spectra": (None,) * 3, "backproject_track_points": (None,) * 4}
    for stage in (s for s in STAGES if s.name in FOCUSER_METHODS):
        owner, _, attr = getattr(stage, column).partition(".")
        sentinel = object()
        monkeypatch.setattr(FOCUS_MODULES[owner], attr, lambda *a, _s=sentinel, **k: _s)
        assert getattr(focuser, stage.name)(*args[stage.name]) is sentinel, (column, stage.name)


def test_method_md_prints_the_stage_table_of_the_code():
    text = (ROOT / "docs" / "method.md").read_text()
    block = text.split("<!-- focuser stages: begin", 1)[1].split("<!-- focuser stages: end -->", 1)[0]
    rows = [[c.strip().strip("`") for c in line.strip().strip("|").split("|")]
            for line in block.splitlines() if line.startswith("| `")]
    assert rows == [[s.name, s.numpy, s.scipy32, s.opencl] for s in STAGES]


def test_configuration_md_lists_every_detection_setting_at_its_default():
    if config.tomllib is None:
        pytest.skip("reading TOML needs Python >= 3.11 or tomli")
    text = (ROOT / "docs" / "configuration.md").read_text()
    toml = text.split("```toml", 1)[1].split("```", 1)[0]
    table = config.tomllib.loads(toml)["detection"]
    assert set(table) == {f.name for f in dataclasses.fields(DetectionSettings)}
    assert config.parse_config({"detection": table}).detection_settings() == DetectionSettings()


def _imports(path: Path) -> list[tuple[str, bool]]:
    """(absolute uwbcl module, at module level) of every import in a uwbcl source file."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts)
    if path.name != "__init__.py":
        package = package.rsplit(".", 1)[0]
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            relative = "." * node.level + (node.module or "")
            base = importlib.util.resolve_name(relative, package) if node.level else node.module
            names = [base] if node.module else [f"{base}.{a.name}" for a in node.names]
            out += [(n, id(node) in top) for n in names if n.startswith("uwbcl")]
        elif isinstance(node, ast.Import):
            out += [(a.name, id(node) in top) for a in node.names if a.name.startswith("uwbcl")]
    return out


def test_the_focus_layer_never_imports_detection_and_detection_imports_only_at_module_level():
    below_detect = ("uwbcl.records", "uwbcl.model", "uwbcl.geometry", "uwbcl.opencl", "uwbcl.focus")
    for path in sorted((ROOT / "uwbcl" / "focus").glob("*.py")):
        for name, _ in _imports(path):
            assert name.startswith(below_detect), f"{path.name} imports {name}, above the focus layer"
    for path in sorted((ROOT / "uwbcl" / "detect").glob("*.py")):
        for name, top_level in _imports(path):
            assert top_level, f"detect/{path.name} imports {name} inside a function"
            assert name.startswith((*below_detect, "uwbcl.detect")), f"detect/{path.name} imports {name}"


def test_detection_and_the_pipeline_call_the_focuser_without_duck_typing():
    for path in [*sorted((ROOT / "uwbcl" / "detect").glob("*.py")), ROOT / "uwbcl" / "pipeline.py"]:
        assert "getattr(" not in path.read_text(), path.name
