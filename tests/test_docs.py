"""docs/architecture.md's paper-to-code table names only code that exists."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
REF = re.compile(r"`([\w/]+\.py):([\w.]+)`")


def _table_rows(doc: Path, heading: str) -> list[str]:
    """The rows (not header or rule) of the first table under ``heading``."""
    lines = doc.read_text().splitlines()
    start = lines.index(heading)
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("## "):
            break
        if line.startswith("|") and not set(line) <= set("|-: "):
            rows.append(line)
    return rows[1:]  # drop the header


def test_every_paper_reference_names_an_existing_file_and_definition():
    rows = _table_rows(REPO / "docs" / "architecture.md", "## The paper in the code")
    papers = [r.split("|")[1].strip() for r in rows]
    for eq in ("Eq. 1", "Eq. 5", "Eq. 6", "Eq. 7", "Eq. 8"):
        assert eq in papers, f"{eq} has no row"
    assert any(p.startswith("Algorithm 1") for p in papers)
    for row in rows:
        refs = REF.findall(row.split("|")[3])
        assert refs, f"row without a `file:function`: {row}"
        for path, name in refs:
            source = REPO / path
            assert source.is_file(), f"{path} (in docs/architecture.md) does not exist"
            text = source.read_text()
            for part in name.split("."):  # Class.method: both must be defined in that file
                assert re.search(rf"^\s*(def|class) {re.escape(part)}\b", text, re.M), \
                    f"{path} has no `def {part}` or `class {part}` (docs/architecture.md: {path}:{name})"


def test_no_doc_or_code_points_at_a_file_outside_the_repository():
    """The repository stands alone: no reference to the design notes it was started from."""
    name = "DESIGN" + ".md"  # spelled in two parts so that this file does not match itself
    checked = [p for ext in ("*.py", "*.md", "*.yaml", "*.sh", "*.toml") for p in REPO.rglob(ext)
               if not any(part.startswith(".") for part in p.relative_to(REPO).parts) and "artifacts" not in p.parts]
    assert len(checked) > 50
    offenders = [str(p.relative_to(REPO)) for p in checked if name in p.read_text(errors="ignore")]
    assert not offenders, offenders
