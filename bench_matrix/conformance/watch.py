"""Where a conversion wrote besides its output directory: it runs in an empty working directory with an empty
$HOME, and the source model's folder is compared before and after."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

ALLOWED_IN_HOME = (".cache",)  # library caches ($XDG_CACHE_HOME's default) are not part of any artifact


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file and folder under `folder` with its size and modification time (ns)."""
    found = {}
    for path in folder.rglob("*"):
        with contextlib.suppress(FileNotFoundError):
            stat = path.lstat()
            found[str(path)] = (stat.st_size, stat.st_mtime_ns)
    return found


@contextlib.contextmanager
def watched(scratch: Path, source_folder: Path) -> Iterator[list[str]]:
    """Run the body in scratch/cwd with HOME=scratch/home (both empty); the yielded list is filled, on exit,
    with every path written there (but ~/.cache) or created, changed or removed in `source_folder`."""
    cwd, home = scratch / "cwd", scratch / "home"
    cwd.mkdir(parents=True)
    home.mkdir()
    before = snapshot(source_folder)
    writes: list[str] = []
    previous = os.environ.get("HOME")
    os.environ["HOME"] = str(home)
    try:
        with contextlib.chdir(cwd):
            yield writes
    finally:
        _restore_home(previous)
        after = snapshot(source_folder)
        writes += sorted(path for path in before.keys() | after.keys() if before.get(path) != after.get(path))
        writes += sorted(str(p) for p in cwd.rglob("*"))
        writes += sorted(str(p) for p in home.rglob("*")
                         if p.relative_to(home).parts[0] not in ALLOWED_IN_HOME)


def _restore_home(previous: str | None) -> None:
    if previous is None:
        os.environ.pop("HOME", None)
    else:
        os.environ["HOME"] = previous
