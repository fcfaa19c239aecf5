"""Where bench-matrix keeps its cache, logs and results, and the content hashes that key them."""

from __future__ import annotations

import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from bench_matrix.errors import UserError

DEFAULT_ROOT = Path(".bench-matrix")
JOB_FILE = re.compile(r"(?:job|session)-(\d+)-\d+\.")  # named by the pid of the process that wrote it
FILE_TYPES = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a named pipe"),
              (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
              (stat.S_ISSOCK, "a socket"))


@dataclass(frozen=True)
class Workspace:
    """Directory layout under one root (default ./.bench-matrix): every path bench-matrix writes is named here."""

    root: Path

    @property
    def results(self) -> Path:
        return self.root / "results.sqlite"

    @property
    def jobs(self) -> Path:
        """Job and result files exchanged with job processes, a folder per host (a workspace may be shared):
        removed as each job ends, and by `sweep_jobs` where a killed run left them."""
        from bench_matrix.measure.env import host_name

        return self.root / "jobs" / host_name()

    def sweep_jobs(self) -> None:
        """Remove this host's job files whose process (the run that wrote them) has ended; those of a live
        one, another run's, stay."""
        for path in self.jobs.glob("*") if self.jobs.is_dir() else ():
            found = JOB_FILE.match(path.name)
            if found and not _alive(int(found[1])):
                path.unlink(missing_ok=True)

    def datasets(self, fingerprint: str) -> Path:
        return self.root / "cache" / "datasets" / fingerprint

    def models(self, fingerprint: str) -> Path:
        return self.root / "cache" / "models" / fingerprint

    def artifact(self, backend: str, fingerprint: str) -> Path:
        return self.root / "cache" / "artifacts" / backend / fingerprint

    def intermediates(self, backend: str, fingerprint: str) -> Path:
        return self.root / "cache" / "intermediates" / backend / fingerprint

    def references(self, fingerprint: str) -> Path:
        """The fp32 outputs of a baseline artifact that `compare --remeasure` scores its side against."""
        return self.root / "cache" / "references" / fingerprint

    def finetuned(self, fingerprint: str) -> Path:
        return self.root / "cache" / "finetuned" / fingerprint

    def params(self, fingerprint: str) -> Path:
        """The parameter count of a source model."""
        return self.root / "cache" / "params" / f"{fingerprint}.json"

    def automatic(self, stem: str, fingerprint: str) -> Path:
        """The automatic matrix `run MODEL_FILE` writes and runs, by its model's name and its digest."""
        return self.root / "auto" / f"{stem}-{fingerprint}.yaml"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    def log(self, name: str) -> Path:
        """The log of a preparation step (probe, dataset, model-NAME)."""
        return self.logs / f"{name}.log"

    def cell_log(self, key: str) -> Path:
        """The log of one cell's processes (fine-tune, convert, measure), by its key."""
        return self.logs / f"{key.replace('/', '__')}.log"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True


def digest(obj: Any) -> str:
    """Short stable hash of a JSON-serialisable object."""
    text = json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def file_sha256(path: Path) -> str:
    """SHA-256 of a file's content (of a directory, such as a SavedModel: of every file below it)."""
    if path.is_dir():
        return tree_sha256([path])
    h = hashlib.sha256()
    with open_regular(path) as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def open_regular(path: Path) -> BinaryIO:
    """Open a regular file to read, never blocking on a named pipe; UserError for any other kind of file."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    kind = not_regular(os.fstat(fd).st_mode)
    if kind:
        os.close(fd)
        raise UserError(f"{path}: is {kind}, not a regular file")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def not_regular(mode: int) -> str | None:
    """What a file of this st_mode is ('a named pipe', ...), or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in FILE_TYPES if test(mode)), "not a regular file")


def tree_sha256(paths: list[Path]) -> str:
    """Hash of files' contents (directories: every file below, in sorted order)."""
    h = hashlib.sha256()
    for path in paths:
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            h.update(str(f.relative_to(path) if path.is_dir() else f.name).encode())
            h.update(file_sha256(f).encode())
    return h.hexdigest()
