"""Where bench-matrix keeps its cache, logs and results, and the content hashes that key them."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULT_ROOT = Path(".bench-matrix")


@dataclass(frozen=True)
class Workspace:
    """Directory layout under one root (default ./.bench-matrix)."""

    root: Path

    @property
    def results(self) -> Path:
        return self.root / "results.sqlite"

    def datasets(self, fingerprint: str) -> Path:
        return self.root / "cache" / "datasets" / fingerprint

    def models(self, fingerprint: str) -> Path:
        return self.root / "cache" / "models" / fingerprint

    def artifact(self, backend: str, fingerprint: str) -> Path:
        return self.root / "cache" / "artifacts" / backend / fingerprint

    def intermediates(self, backend: str, fingerprint: str) -> Path:
        return self.root / "cache" / "intermediates" / backend / fingerprint

    @property
    def logs(self) -> Path:
        return self.root / "logs"


def digest(obj: Any) -> str:
    """Short stable hash of a JSON-serialisable object."""
    text = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's content (of a directory, such as a SavedModel: of every file below it)."""
    if path.is_dir():
        return tree_sha256([path])
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def tree_sha256(paths: list[Path]) -> str:
    """Hash of files' contents (directories: every file below, in sorted order)."""
    h = hashlib.sha256()
    for path in paths:
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            h.update(str(f.relative_to(path) if path.is_dir() else f.name).encode())
            h.update(file_sha256(f).encode())
    return h.hexdigest()
