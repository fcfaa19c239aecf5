"""Paths named in a matrix: resolved against the matrix's folder and checked without opening anything."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from bench_matrix.workspace import not_regular

MAX_PATH_BYTES = 4096  # Linux PATH_MAX
MAX_SAVED_MODEL_ENTRIES = 10_000  # a SavedModel holds a handful of files


def resolve(base: Path, text: str) -> tuple[Path | None, str | None]:
    """The path `text` names, or None and why it cannot name one: an absolute path as written (expanded), a
    relative one taken from `base` and resolved."""
    if "\0" in text:
        return None, f"the path {text!r} contains a NUL byte"
    try:
        path = Path(text).expanduser()
    except RuntimeError:
        return None, f"cannot expand '{text.split('/')[0]}' in '{text}': no such user (write the full path)"
    if len(os.fsencode(path if path.is_absolute() else base / path)) > MAX_PATH_BYTES:
        return None, f"the path is longer than {MAX_PATH_BYTES} bytes (the system's limit): '{text[:60]}...'"
    try:
        return (path if path.is_absolute() else (base / path).resolve()), None
    except (OSError, RuntimeError) as exc:  # a symlink loop
        return None, f"cannot resolve '{text}': {exc}"


def mode(path: Path) -> tuple[int | None, str | None]:
    """(st_mode, None) of what `path` names (symlinks followed), (None, None) when nothing is there, or
    (None, why it cannot be looked at)."""
    try:
        return os.stat(path).st_mode, None
    except (FileNotFoundError, NotADirectoryError):
        return None, None
    except OSError as exc:
        return None, f"cannot look at {path}: {exc.strerror}"


def file_problem(path: Path, noun: str) -> str | None:
    """Why `path` is not a regular file to read as `noun` ('model file', ...), or None."""
    found, problem = _existing(path, noun)
    kind = not_regular(found) if found is not None else None
    return problem or (f"{path} is {kind}, not a {noun}; give a regular file" if kind else None)


def dir_problem(path: Path, noun: str) -> str | None:
    """Why `path` is not a directory to use as `noun`, or None."""
    found, problem = _existing(path, noun)
    if problem or found is None or stat.S_ISDIR(found):
        return problem
    return f"{path} is {not_regular(found) or 'a file'}, not a directory"


def _existing(path: Path, noun: str) -> tuple[int | None, str | None]:
    """(st_mode, None) of what `path` names, or (None, why there is nothing to use as `noun`)."""
    found, error = mode(path)
    if error or found is None:
        return None, error or f"{noun} not found: {path}"
    return found, None


def saved_model_problem(path: Path) -> str | None:
    """Why the SavedModel directory `path` cannot be read safely (a file that is not regular), or None."""
    seen = 0
    for folder, _, files in os.walk(path):
        seen += len(files)
        for name in files:
            entry = Path(folder) / name
            found, error = mode(entry)
            if error or found is None:
                return error or f"{entry} is a broken symbolic link"
            kind = not_regular(found)
            if kind:
                return (f"{entry} in the SavedModel is {kind}; every file of a SavedModel must be a regular "
                        f"file")
        if seen > MAX_SAVED_MODEL_ENTRIES:
            return f"{path} holds more than {MAX_SAVED_MODEL_ENTRIES} files; is it really a SavedModel?"
    return None
