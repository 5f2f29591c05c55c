"""Canonical JSON, code digests and stage keys.

``key = blake3(canonical_json({schema, stage, version, code, config, inputs}))`` where ``config`` is
the stage's own section after validation through its pydantic ``Config`` (defaults filled, ints
coerced to floats where the field is a float), ``code`` is a digest of the stage's source, and
``inputs`` maps each needed stage to *its* key. Artifact bytes are never read to decide anything.

Keys follow the science, not the engine: the code digest never includes the engine's own package
(``ENGINE_PACKAGES``), even where a stage imports ``pipeline.context`` for a type. What the engine
does to an artifact is versioned by ``ENGINE_VERSION`` instead, bumped by hand when an engine change
alters what a stage produces (it never has so far), so editing ``pipeline/progress.py`` does not
re-collect 22 minutes of data.
"""
from __future__ import annotations

import ast
import json
import os
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable, Mapping

import blake3

KEY_SCHEMA = 1
ENGINE_VERSION = 1
ENGINE_PACKAGES = frozenset({"pipeline"})  # top-level packages that are the engine, never hashed into a stage
_SKIP_DIRS = {"__pycache__", ".pytest_cache"}
_SKIP_SUFFIXES = {".pyc", ".pyo"}


def canonical_json(obj: Any) -> str:
    """One string per meaning: sorted keys, no whitespace, non-ASCII kept, NaN refused."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def stage_key(stage: str, version: int, code_digest: str, config: Mapping[str, Any], inputs: Mapping[str, str]) -> str:
    """The content address of a stage's output; see the module docstring."""
    payload = {
        "schema": KEY_SCHEMA,
        "engine": ENGINE_VERSION,
        "stage": stage,
        "version": version,
        "code": code_digest,
        "config": config,
        "inputs": dict(inputs),
    }
    return blake3.blake3(canonical_json(payload).encode()).hexdigest()


def _module_file(name: str, roots: Iterable[Path]) -> Path | None:
    """The source file of module ``name`` under one of ``roots``, without importing it."""
    parts = name.split(".")
    for root in roots:
        base = root.joinpath(*parts)
        for cand in (base.with_suffix(".py"), base / "__init__.py"):
            if cand.is_file():
                return cand
    return None


def _package_inits(name: str, roots: Iterable[Path]) -> list[Path]:
    """``__init__.py`` of every parent package of ``name`` (they run on import too)."""
    out = []
    parts = name.split(".")
    for i in range(1, len(parts)):
        f = _module_file(".".join(parts[:i]), roots)
        if f is not None and f.name == "__init__.py":
            out.append(f)
    return out


@lru_cache(maxsize=4096)
def _imports_of(path: Path, mtime_ns: int) -> tuple[str, ...]:
    """Absolute module names imported by a source file (relative imports resolved)."""
    del mtime_ns  # part of the cache key only
    tree = ast.parse(path.read_bytes(), filename=str(path))
    pkg_parts = _package_parts(path)
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[: len(pkg_parts) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod:
                names.append(mod)
                names.extend(f"{mod}.{a.name}" for a in node.names)
    return tuple(names)


def _package_parts(path: Path) -> list[str]:
    """Dotted package of a file, found by walking up while ``__init__.py`` exists."""
    parts: list[str] = []
    d = path.parent
    while (d / "__init__.py").is_file():
        parts.insert(0, d.name)
        d = d.parent
    return parts


def source_closure(module: str, roots: Iterable[Path]) -> list[Path]:
    """Files whose content defines a stage's behaviour.

    Every file of the stage's own package (data files included), plus, transitively, every
    project-local module it imports (found statically by reading ``import`` statements), except the
    engine's (``ENGINE_PACKAGES``). Third-party packages are pinned by requirements.lock and are not
    hashed.
    """
    roots = [Path(r).resolve() for r in roots]
    entry = _module_file(module, roots)
    if entry is None:
        return []
    files: set[Path] = set()
    if entry.name == "__init__.py":
        for dirpath, dirnames, filenames in os.walk(entry.parent):
            dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS and not d.startswith("."))
            for fn in filenames:
                p = Path(dirpath) / fn
                if p.suffix not in _SKIP_SUFFIXES and not fn.startswith("."):
                    files.add(p)
    files.add(entry)
    files.update(_package_inits(module, roots))
    todo = [p for p in files if p.suffix == ".py"]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        for name in _imports_of(f, f.stat().st_mtime_ns):
            if name.split(".")[0] in ENGINE_PACKAGES:
                continue  # the engine is versioned by ENGINE_VERSION, not by its bytes
            dep = _module_file(name, roots)
            if dep is None:
                continue
            for g in [dep, *_package_inits(name, roots)]:
                if g not in files:
                    files.add(g)
                    todo.append(g)
    return sorted(files)


def code_digest(module: str, roots: Iterable[Path]) -> str:
    """blake3 over (relative path, bytes) of ``source_closure(module)``; '' if the module has no source."""
    roots = [Path(r).resolve() for r in roots]
    h = blake3.blake3()
    files = source_closure(module, roots)
    if not files:
        return ""
    for f in files:
        rel = next((str(f.relative_to(r)) for r in roots if f.is_relative_to(r)), str(f))
        data = f.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()
