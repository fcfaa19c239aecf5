"""Artifact size: every file of the artifact directory, raw and gzip-compressed."""

from __future__ import annotations

import gzip
from pathlib import Path


def artifact_size(directory: Path) -> dict[str, int]:
    """size_bytes (sum of all files) and size_gzip_bytes (sum of each file gzipped at level 9)."""
    files = sorted(p for p in directory.rglob("*") if p.is_file())
    raw = sum(p.stat().st_size for p in files)
    compressed = sum(len(gzip.compress(p.read_bytes(), compresslevel=9, mtime=0)) for p in files)
    return {"size_bytes": raw, "size_gzip_bytes": compressed, "files": len(files)}
