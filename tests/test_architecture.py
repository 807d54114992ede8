"""The layers of docs/architecture.md hold: no upward import and no import cycle, function-level imports
too."""

from __future__ import annotations

import ast
import fnmatch
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "uwbcl"


def layers_from_document(text: str) -> list[tuple[str, list[str]]]:
    """[(layer, [module patterns])] bottom first, from the table under '## Layers'."""
    section = text.split("## Layers", 1)[1]
    out = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0] not in ("layer", "") and not set(cells[0]) <= set("-: "):
            out.append((cells[0], [m.strip() for m in cells[1].split(",")]))
    return out


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, root: Path) -> set[str]:
    """Every uwbcl module `path` imports, wherever the import statement is (module level or in a function)."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            # `from . import x` / `from .focus import nlcs`: x may be a module itself
            found.update(f"{mod}.{a.name}" for a in node.names)
    return {m for m in found if m == root.name or m.startswith(root.name + ".")}


def import_graph(root: Path) -> dict[str, set[str]]:
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    # `from . import sibling` names the parent package, which Python has already begun importing: not an edge.
    return {m: {i for i in imports_of(p, root) if i in files and i != m and not m.startswith(i + ".")}
            for m, p in files.items()}


def layer_of(module: str, layers) -> int:
    for index, (_, patterns) in enumerate(layers):
        if any(module == p or fnmatch.fnmatchcase(module, p) for p in patterns):
            return index
    raise LookupError(module)


def violations(graph: dict[str, set[str]], layers) -> list[str]:
    out = []
    for mod, deps in sorted(graph.items()):
        for dep in sorted(deps):
            if layer_of(dep, layers) > layer_of(mod, layers):
                out.append(f"{mod} ({layers[layer_of(mod, layers)][0]}) imports {dep} "
                           f"({layers[layer_of(dep, layers)][0]}), a higher layer")
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def layers():
    return layers_from_document((ROOT / "docs" / "architecture.md").read_text())


def test_the_document_names_the_layers_bottom_first(layers):
    names = [n for n, _ in layers]
    assert names[0] == "records" and names[-1] == "cli"
    assert len(names) == len(set(names)) >= 10


def test_every_module_of_the_package_belongs_to_exactly_one_layer(layers):
    for mod in import_graph(PACKAGE):
        owners = [n for n, pats in layers if any(mod == p or fnmatch.fnmatchcase(mod, p) for p in pats)]
        assert len(owners) == 1, f"{mod}: in layers {owners} of docs/architecture.md"


def test_no_module_imports_from_a_higher_layer(layers):
    assert violations(import_graph(PACKAGE), layers) == []


def test_there_is_no_import_cycle_even_through_function_level_imports():
    assert cycles(import_graph(PACKAGE)) == []


def test_a_deliberate_upward_import_inside_a_function_is_caught(tmp_path, layers):
    pkg = tmp_path / "uwbcl"
    for src in PACKAGE.rglob("*.py"):
        dst = pkg / src.relative_to(PACKAGE)
        dst.parent.mkdir(parents=True, exist_ok=True)
        dst.write_text(src.read_text())
    locate = pkg / "locate.py"
    locate.write_text(locate.read_text()
                      + "\n\ndef _upward():\n    from . import batch  # noqa\n    return batch\n")
    graph = import_graph(pkg)
    found = violations(graph, layers)
    assert any(re.match(r"uwbcl\.locate \(locate\) imports uwbcl\.batch \(batch\)", v) for v in found), found
    assert any("uwbcl.locate" in c and "uwbcl.batch" in c for c in cycles(graph))
