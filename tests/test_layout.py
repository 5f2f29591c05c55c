"""The test tree stays collectable: pytest's default import mode imports a test file that sits in a
folder without ``__init__.py`` under its bare basename, so two such files with the same name make the
second fail to collect ("import file mismatch") and the whole run stops before any test runs."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def test_rootless_test_files_have_unique_basenames():
    by_name: dict[str, list[str]] = defaultdict(list)
    for path in TESTS.rglob("test_*.py"):
        if not (path.parent / "__init__.py").exists():
            by_name[path.name].append(str(path.relative_to(TESTS)))
    clashes = {name: paths for name, paths in by_name.items() if len(paths) > 1}
    assert not clashes, f"test files sharing a basename (rename one): {clashes}"
