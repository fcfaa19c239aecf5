"""Artifact size: every file of the artifact directory, raw and gzip-compressed."""

from __future__ import annotations

import gzip
import json
from pathlib import Path


def artifact_size(directory: Path, cache: Path | None = None, partial: Path | None = None) -> dict[str, int]:
    """size_bytes (sum of all files) and size_gzip_bytes (sum of each file gzipped at level 9). With `cache`, the
    result is kept there (written at `partial` first) and reused while every file keeps its name, size and
    mtime: gzip -9 of a pruned 65 MB model takes ~40 s, and re-measuring a cached artifact should not repeat
    it."""
    files = sorted(p for p in directory.rglob("*") if p.is_file())
    stamp = [[str(p.relative_to(directory)), p.stat().st_size, p.stat().st_mtime_ns] for p in files]
    if cache is not None and cache.is_file():
        kept = json.loads(cache.read_text())
        if kept.get("files") == stamp:
            return kept["size"]
    raw = sum(p.stat().st_size for p in files)
    compressed = sum(len(gzip.compress(p.read_bytes(), compresslevel=9, mtime=0)) for p in files)
    size = {"size_bytes": raw, "size_gzip_bytes": compressed, "files": len(files)}
    if cache is not None and partial is not None:
        partial.write_text(json.dumps({"files": stamp, "size": size}))
        partial.replace(cache)
    return size
