"""Read a user's .npz dataset (one array per model input, labels y, groups); every mistake is a UserError."""

from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.workspace import not_regular

NPZ_HINT = ("save the data with numpy.savez(path, x=images, y=labels), one array per model input named after "
            "it (x for a single input)")
NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
KIND_NAMES = {"O": "Python objects", "U": "text", "S": "bytes", "b": "booleans", "c": "complex numbers",
              "V": "structured records", "M": "dates", "m": "time spans"}
LABELS, GROUPS = "y", "groups"  # every other array of an .npz is a model input
EXPECTED = {"input": "a model input: integers, floats or booleans, one row per sample, shape (N, ...)",
            LABELS: "labels as integers or floats, shape (N,) or (N, K)",
            GROUPS: "one integer group id per sample, shape (N,)"}
ALLOWED_KINDS = {"input": "iufb", LABELS: "iuf", GROUPS: "iu"}
CHUNK = 256  # samples checked for NaN/Inf at a time


@dataclass(frozen=True)
class NpzData:
    """The model inputs of an .npz archive (in its order), its labels as stored (or None) and groups."""

    inputs: dict[str, np.ndarray]
    labels: np.ndarray | None
    groups: np.ndarray | None


def require_file(path: Path, expected: str) -> None:
    """Refuse a path that is missing, unreadable or not a regular file (never open a pipe)."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        raise UserError(f"{path}: not found; expected {expected}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot be read ({why(exc)}); expected {expected}") from None
    if kind := not_regular(mode):
        raise UserError(f"{path}: is {kind}, not a regular file; expected {expected}")


def memory_budget() -> int:
    """Bytes the arrays of a dataset may take: half of this machine's memory (the splits copy them)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


def npz_headers(path: Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """(shape, dtype) of every array of an .npz archive, read from the .npy headers (no array is loaded)."""
    with _open_npz(path) as archive:
        members = _members(archive)
        return {name: _npy_header(archive, path, name, member) for name, member in members.items()}


def read_npz(path: Path, task: str) -> NpzData:
    """The inputs, labels (unless the task is none) and groups of an .npz archive, after checking them."""
    with _open_npz(path) as archive:
        members = _members(archive)
        if task != "none" and LABELS not in members:
            raise UserError(f"{path}: missing array 'y': task {task} needs labels; it has: "
                            f"{', '.join(members) or 'nothing'}. Store the labels as 'y' (class ids for "
                            f"classification), or use task: none")
        wanted = {n: m for n, m in members.items() if n != LABELS or task != "none"}
        headers = {name: _npy_header(archive, path, name, member) for name, member in wanted.items()}
        n = _check_shapes(path, {name: shape for name, (shape, _) in headers.items()})
        arrays = {name: _npy_array(archive, path, name, wanted[name]) for name in headers}
    for name, values in arrays.items():
        if values.dtype.kind == "f":
            refuse_non_finite(values, f"{path}: array '{name}'", "sample")
    groups = arrays.pop(GROUPS, None)
    labels = arrays.pop(LABELS, None)
    return NpzData(arrays, labels, None if groups is None else groups.reshape(n))


def refuse_non_finite(values: np.ndarray, what: str, unit: str) -> None:
    """Refuse NaN, Inf or float32-overflowing values, naming the first bad sample and how many there are."""
    first, count = None, 0
    for start in range(0, len(values), CHUNK):
        chunk = values[start:start + CHUNK]
        with np.errstate(over="ignore"):
            bad = np.flatnonzero(~np.isfinite(chunk.reshape(len(chunk), -1).astype(np.float32)).all(axis=1))
        first = start + int(bad[0]) if first is None and len(bad) else first
        count += len(bad)
    if first is not None:
        more = f" (and {count - 1} more)" if count > 1 else ""
        raise UserError(f"{what}: {unit} {first}{more} holds NaN or Inf (or a value beyond float32's range); "
                        f"every value must be a finite number: fix or drop those samples")


def why(exc: BaseException) -> str:
    """An exception's message, or its type when it has none."""
    return str(exc) or type(exc).__name__


def _open_npz(path: Path) -> zipfile.ZipFile:
    require_file(path, "an .npz archive")
    try:
        with open(path, "rb") as f:
            head = f.read(8)
        return zipfile.ZipFile(path)
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({why(exc)})") from None
    except Exception as exc:  # anything else the zip reader raises means the bytes are not an archive
        raise UserError(_not_npz(path, head, exc)) from None


def _members(archive: zipfile.ZipFile) -> dict[str, str]:
    """Array name -> zip member, in the archive's order."""
    return {n.removesuffix(".npy"): n for n in archive.namelist()}


def _not_npz(path: Path, head: bytes, exc: Exception) -> str:
    """What a file that is no zip archive is, judged by its first bytes."""
    if not head:
        return f"{path}: is empty (0 bytes); expected an .npz archive: {NPZ_HINT}"
    if head.startswith(b"\x93NUMPY"):
        return f"{path}: is a single .npy array, not an .npz archive; {NPZ_HINT}"
    if head.startswith(b"\x80"):
        return (f"{path}: is a Python pickle, which bench-matrix never loads (it could run code); "
                f"save plain numeric arrays: {NPZ_HINT}")
    if head.startswith(b"PK"):
        return f"{path}: is a damaged or truncated zip archive ({why(exc)}); {NPZ_HINT}"
    return f"{path}: is not an .npz archive (not a zip file); {NPZ_HINT}"


def _role(name: str) -> str:
    return name if name in (LABELS, GROUPS) else "input"


def _npy_header(archive: zipfile.ZipFile, path: Path, name: str,
                member: str) -> tuple[tuple[int, ...], np.dtype]:
    """The shape and dtype of one member, after checking it holds plain numbers (nothing is loaded yet)."""
    what, role = f"{path}: array '{name}'", _role(name)
    try:
        with archive.open(member) as fp:
            version = np.lib.format.read_magic(fp)
            header = NPY_HEADERS.get(version)
            shape, _, dtype = header(fp) if header else ((), False, None)
    except Exception as exc:  # a damaged member: any reader exception means the same
        raise UserError(f"{what} is not a readable .npy array ({why(exc)}); {NPZ_HINT}") from None
    if header is None:
        raise UserError(f"{what} uses .npy format version {version[0]}.{version[1]}, which holds structured "
                        f"arrays; expected {EXPECTED[role]}")
    _check_dtype(what, dtype, ALLOWED_KINDS[role], EXPECTED[role])
    size = math.prod(shape) * dtype.itemsize
    if size > memory_budget():
        raise UserError(f"{what} {shape} needs {size / 2**30:.1f} GiB, more than half of this machine's "
                        f"memory; use fewer or smaller samples")
    return shape, dtype


def _check_dtype(what: str, dtype: np.dtype, allowed: str, expected: str) -> None:
    """Refuse objects (never unpickled), text, complex numbers... : `allowed` dtype kinds only."""
    if dtype.hasobject:
        raise UserError(f"{what} holds Python objects (dtype object), which bench-matrix never loads "
                        f"(unpickling could run code); save plain numeric arrays: {expected}")
    if dtype.kind not in allowed:
        found = "floats" if dtype.kind == "f" else KIND_NAMES.get(dtype.kind, "values")
        raise UserError(f"{what} holds {found} (dtype {dtype}); expected {expected}")


def _check_shapes(path: Path, shapes: dict[str, tuple[int, ...]]) -> int:
    """The number of samples, after checking the arrays have shapes that agree."""
    inputs = [name for name in shapes if _role(name) == "input"]
    if not inputs:
        raise UserError(f"{path}: holds no input array (it has: {', '.join(shapes) or 'nothing'}); every "
                        f"array but 'y' and 'groups' is a model input: {NPZ_HINT}")
    for name, shape in shapes.items():
        if len(shape) == 0 or 0 in shape[1:]:
            raise UserError(f"{path}: array '{name}' has shape {shape}; expected {EXPECTED[_role(name)]} "
                            f"with every axis after N > 0")
    lengths = {name: shape[0] for name, shape in shapes.items() if name != GROUPS}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"'{name}' {length}" for name, length in lengths.items())
        raise UserError(f"{path}: the arrays have different numbers of samples (first axis): {listed}; "
                        f"every array needs one row per sample")
    n = lengths[inputs[0]]
    groups = shapes.get(GROUPS)
    if groups is not None and groups not in ((n,), (n, 1)):
        raise UserError(f"{path}: array 'groups' has shape {groups} for {n} samples; "
                        f"expected {EXPECTED[GROUPS]}")
    if n == 0:
        raise UserError(f"{path}: holds no samples ('{inputs[0]}' has shape {shapes[inputs[0]]}); expected "
                        f"at least one per split")
    return n


def _npy_array(archive: zipfile.ZipFile, path: Path, name: str, member: str) -> np.ndarray:
    try:
        with archive.open(member) as fp:
            return np.lib.format.read_array(fp, allow_pickle=False)
    except Exception as exc:  # truncated or corrupt data (zlib, CRC, EOF): any reader exception says so
        raise UserError(f"{path}: array '{name}' cannot be read ({why(exc)}); the file is damaged or "
                        f"truncated: {NPZ_HINT}") from None


def class_ids(labels: np.ndarray, what: str) -> np.ndarray:
    """Classification labels as int64 (N,) class ids, after checking they are whole numbers >= 0."""
    if labels.ndim > 2 or (labels.ndim == 2 and labels.shape[1] > 1):
        raise UserError(f"{what} has shape {labels.shape}; classification needs one class id per sample, "
                        f"shape (N,): store class ids (for one-hot rows, y.argmax(axis=1)), not one-hot or "
                        f"per-class columns")
    ids = labels.reshape(len(labels))
    for bad, rule in ((ids != np.round(ids), "whole numbers"), (ids < 0, "class ids >= 0")):
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise UserError(f"{what}: sample {first} is {ids[first]}; classification labels must be {rule} "
                            f"(0 for the first class, 1 for the second...)")
    return ids.astype(np.int64)
