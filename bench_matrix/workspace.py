"""Where bench-matrix keeps its cache, logs and results, and the content hashes that key them."""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import re
import shutil
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from bench_matrix.errors import UserError

DEFAULT_ROOT = Path(".bench-matrix")
OWNED = re.compile(r"(?:job|session|partial)-(\d+)-\d+")  # named by the pid of the process that wrote it
SERIAL = itertools.count()  # tells apart one process's partial paths
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
        removed as each job ends, and by `sweep` where a killed run left them."""
        from bench_matrix.measure.env import host_name

        return self.root / "jobs" / host_name()

    @property
    def partials(self) -> Path:
        """Files and folders being written, a folder per host: each is moved into its place whole once
        written, so nothing half-written is ever in cache/; `sweep` removes those a killed process left."""
        from bench_matrix.measure.env import host_name

        return self.root / "tmp" / host_name()

    def partial(self, final: Path) -> Path:
        """A new path of this process's own (its pid in the name) to write `final` at before moving it into
        place (Path.replace, rename); `final`'s folder is created."""
        final.parent.mkdir(parents=True, exist_ok=True)
        self.partials.mkdir(parents=True, exist_ok=True)
        return self.partials / f"partial-{os.getpid()}-{next(SERIAL)}-{final.name}"

    def sweep(self) -> None:
        """Remove this host's job files and partial files whose process has ended (a run's own once it ends, a
        killed run's); those of a live process, another run's, stay."""
        for folder in (self.jobs, self.partials):
            for path in folder.glob("*") if folder.is_dir() else ():
                found = OWNED.match(path.name)
                if found and not _alive(int(found[1])):
                    _remove(path)

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

    def peak(self, fingerprint: str) -> Path:
        """The machine's peak measured at one host and thread count (measure/peak.py)."""
        return self.root / "cache" / "peaks" / f"{fingerprint}.json"

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


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


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
