"""The documents are the repository's own: no citation of design notes kept outside it, and every label of
docs/method.md (C1.. corrections to the paper, D1.. derivations) that code or documents cite is defined
there."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
METHOD = REPO / "docs" / "method.md"
SUFFIXES = {".py", ".cl", ".md", ".toml", ".sh", ".txt"}

# What a citation of the external notes (nlcs-notes.md, platform-notes.md) looks like: "notes section 8",
# "notes 7b", "notes §1", "notes table 10", "pitfall 7", "design notes", the notes' "[fix]" marker, or a path.
EXTERNAL = re.compile(r"notes section|notes \d|notes §|notes table|pitfall|design notes|\[fix\]"
                      r"|nlcs-notes|platform-notes|shared/design|\.\./shared/", re.IGNORECASE)
# A label citation: C12, D4 (also the ends of ranges such as C3-C12), not inside a quoted string such as
# matplotlib's colour "C0", and not part of a longer word.
LABEL = re.compile(r"(?<![\w\"'])([CD]\d+)(?![\w\"'])")
HEADING = re.compile(r"^#{2,4}\s+([CD]\d+)\.\s+\S", re.MULTILINE)


def _files(*, include_method: bool) -> list[Path]:
    paths = [REPO / "README.md"]
    for top in ("uwbcl", "kernels", "scripts", "docs", "tests"):
        paths += sorted(p for p in (REPO / top).rglob("*") if p.is_file() and p.suffix in SUFFIXES)
    this = Path(__file__).resolve()
    return [p for p in paths if p.resolve() != this and (include_method or p.resolve() != METHOD.resolve())]


def _defined_labels() -> list[str]:
    return HEADING.findall(METHOD.read_text(encoding="utf-8"))


def test_no_file_in_the_repository_cites_the_design_notes_kept_outside_it():
    hits = []
    for path in _files(include_method=True):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if EXTERNAL.search(line):
                hits.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert not hits, "cite the labels of docs/method.md instead:\n" + "\n".join(hits)


def test_every_label_cited_in_code_and_documents_is_a_heading_of_method_md():
    defined = set(_defined_labels())
    cited: dict[str, list[str]] = {}
    for path in _files(include_method=False):
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for label in LABEL.findall(line):
                cited.setdefault(label, []).append(f"{path.relative_to(REPO)}:{n}")
    missing = {label: where for label, where in cited.items() if label not in defined}
    assert not missing, f"labels cited but not defined in docs/method.md: {missing}"
    # the check is not vacuous: the code does cite the corrections
    assert len(cited) >= 10


def test_method_md_numbers_its_corrections_and_derivations_once_each_and_in_order():
    labels = _defined_labels()
    for kind in "CD":
        numbers = [int(label[1:]) for label in labels if label[0] == kind]
        assert numbers == list(range(1, len(numbers) + 1)), f"{kind} labels: {numbers}"
    assert any(label.startswith("C") for label in labels) and any(label.startswith("D") for label in labels)


def test_method_md_has_the_corrections_to_the_paper_and_the_derivations_sections():
    text = METHOD.read_text(encoding="utf-8")
    assert re.search(r"^## \d+\. Corrections to the paper$", text, re.MULTILINE)
    assert re.search(r"^## \d+\. Derivations$", text, re.MULTILINE)


def _documented_columns(heading: str) -> list[str]:
    """The column names of the first table after `heading` in docs/outputs.md whose header cell is "Column",
    in the table's order (a row naming several columns, `a`, `b`, gives them in that order)."""
    lines = (REPO / "docs" / "outputs.md").read_text(encoding="utf-8").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("#") and heading in line)
    table = next(i for i in range(start, len(lines)) if re.match(r"\|\s*column\s*\|", lines[i], re.I))
    names = []
    for line in lines[table + 2:]:
        if not line.startswith("|"):
            break
        names += re.findall(r"`([a-z0-9_]+)`", line.split("|")[1])
    return names


def test_every_output_table_of_outputs_md_lists_the_columns_the_code_writes_in_its_order():
    from uwbcl import commission, outputs
    from uwbcl.acquisition import live

    assert _documented_columns("2.1 `displacements.csv`") == list(outputs.DISPLACEMENT_COLUMNS)
    assert _documented_columns("2.3 `targets.csv`") == list(outputs.TARGET_COLUMNS)
    assert _documented_columns("7. uwbcl focus") == list(commission.COLUMNS)
    assert _documented_columns("9. `acquire-results.csv`") == list(live.RESULT_COLUMNS)
    assert "Columns `file`, `kind`, `reason`." in (REPO / "docs" / "outputs.md").read_text(encoding="utf-8")
    assert outputs.ERROR_COLUMNS == ("file", "kind", "reason")
