"""Read a user's dataset files (.npz, DeepLearningStudio folders); every mistake in them is a UserError."""

from __future__ import annotations

import codecs
import csv
import io
import math
import os
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.workspace import not_regular

NPZ_HINT = "save the data with numpy.savez(path, x=images, y=labels)"
NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
KIND_NAMES = {"O": "Python objects", "U": "text", "S": "bytes", "b": "booleans", "c": "complex numbers",
              "V": "structured records", "M": "dates", "m": "time spans"}
EXPECTED = {"x": "images as integers or floats, shape (N, H, W) or (N, H, W, C)",
            "y": "labels as integers or floats, shape (N,) or (N, K)",
            "groups": "one integer group id per sample, shape (N,)"}
BOMS = ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"), (codecs.BOM_UTF16_LE, "utf-16"),
        (codecs.BOM_UTF16_BE, "utf-16"))
IMAGE_FORMATS = ("PNG", "JPEG")
IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg")
MAX_IMAGE_PIXELS = 8192 * 8192  # a camera frame is far smaller; more is a decompression bomb or a mistake
CHUNK = 256  # samples checked for NaN/Inf at a time
FLOAT32_MAX = float(np.finfo(np.float32).max)


def require_file(path: Path, expected: str) -> None:
    """Refuse a path that is missing, unreadable or not a regular file (never open a pipe)."""
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):
        raise UserError(f"{path}: not found; expected {expected}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot be read ({_why(exc)}); expected {expected}") from None
    if kind := not_regular(mode):
        raise UserError(f"{path}: is {kind}, not a regular file; expected {expected}")


def memory_budget() -> int:
    """Bytes the images of a dataset may take: half of this machine's memory (the splits copy them)."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2


def read_npz(path: Path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple]:
    """x (N,H,W[,C]), y (N,K) float32, optional groups (N,) and the label column names of an .npz archive."""
    require_file(path, "an .npz archive")
    try:
        with open(path, "rb") as f:
            head = f.read(8)
        archive = zipfile.ZipFile(path)
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({_why(exc)})") from None
    except Exception as exc:  # anything else the zip reader raises means the bytes are not an archive
        raise UserError(_not_npz(path, head, exc)) from None
    with archive:
        members = {n.removesuffix(".npy"): n for n in archive.namelist()}
        missing = [k for k in ("x", "y") if k not in members]
        if missing:
            raise UserError(f"{path}: missing array(s) {', '.join(missing)}; an .npz dataset needs 'x' "
                            f"(N,H,W[,C] images) and 'y' (N[,K] labels), optionally 'groups' (N,); "
                            f"it has: {', '.join(members) or 'nothing'}")
        shapes = {name: _npy_header(archive, path, name, members[name])
                  for name in ("x", "y", "groups") if name in members}
        n = _check_shapes(path, shapes)
        arrays = {name: _npy_array(archive, path, name, members[name]) for name in shapes}
    x, groups = arrays["x"], arrays.get("groups")
    with np.errstate(over="ignore"):  # a value beyond float32 becomes Inf, refused below
        y = arrays["y"].reshape(n, -1).astype(np.float32)
    for name, values in (("x", x), ("y", y)):
        if values.dtype.kind == "f":
            refuse_non_finite(values, f"{path}: array '{name}'", "sample")
    names = columns if len(columns) == y.shape[1] else tuple(f"y{i}" for i in range(y.shape[1]))
    return x, y, None if groups is None else groups.reshape(n), names


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
        return f"{path}: is a damaged or truncated zip archive ({_why(exc)}); {NPZ_HINT}"
    return f"{path}: is not an .npz archive (not a zip file); {NPZ_HINT}"


def _npy_header(archive: zipfile.ZipFile, path: Path, name: str, member: str) -> tuple[int, ...]:
    """The shape of one member, after checking its header says plain numbers (nothing is loaded yet)."""
    what = f"{path}: array '{name}'"
    try:
        with archive.open(member) as fp:
            version = np.lib.format.read_magic(fp)
            header = NPY_HEADERS.get(version)
            shape, _, dtype = header(fp) if header else ((), False, None)
    except Exception as exc:  # a damaged member: any reader exception means the same
        raise UserError(f"{what} is not a readable .npy array ({_why(exc)}); {NPZ_HINT}") from None
    if header is None:
        raise UserError(f"{what} uses .npy format version {version[0]}.{version[1]}, which holds structured "
                        f"arrays; expected {EXPECTED[name]}")
    _check_dtype(what, dtype, "iu" if name == "groups" else "iuf", EXPECTED[name])
    size = math.prod(shape) * dtype.itemsize
    if size > memory_budget():
        raise UserError(f"{what} {shape} needs {size / 2**30:.1f} GiB, more than half of this machine's "
                        f"memory; use fewer or smaller samples")
    return shape


def _check_dtype(what: str, dtype: np.dtype, allowed: str, expected: str) -> None:
    """Refuse objects (never unpickled), text, booleans, complex numbers... : `allowed` dtype kinds only."""
    if dtype.hasobject:
        raise UserError(f"{what} holds Python objects (dtype object), which bench-matrix never loads "
                        f"(unpickling could run code); save plain numeric arrays: {expected}")
    if dtype.kind not in allowed:
        found = "floats" if dtype.kind == "f" else KIND_NAMES.get(dtype.kind, "values")
        raise UserError(f"{what} holds {found} (dtype {dtype}); expected {expected}")


def _check_shapes(path: Path, shapes: dict[str, tuple[int, ...]]) -> int:
    """The number of samples, after checking x, y and groups have shapes that agree."""
    x, y = shapes["x"], shapes["y"]
    if len(x) not in (3, 4) or 0 in x[1:]:
        raise UserError(f"{path}: array 'x' has shape {x}; expected {EXPECTED['x']} with H, W, C > 0")
    if len(y) == 0 or 0 in y[1:]:
        raise UserError(f"{path}: array 'y' has shape {y}; expected {EXPECTED['y']} with K > 0")
    n = x[0]
    if y[0] != n:
        raise UserError(f"{path}: 'x' has {n} samples but 'y' has {y[0]} labels; expected one label row "
                        f"per sample")
    groups = shapes.get("groups")
    if groups is not None and groups not in ((n,), (n, 1)):
        raise UserError(f"{path}: array 'groups' has shape {groups} for {n} samples; "
                        f"expected {EXPECTED['groups']}")
    if n == 0:
        raise UserError(f"{path}: holds no samples (x has shape {x}); expected at least one per split")
    return n


def _npy_array(archive: zipfile.ZipFile, path: Path, name: str, member: str) -> np.ndarray:
    try:
        with archive.open(member) as fp:
            return np.lib.format.read_array(fp, allow_pickle=False)
    except Exception as exc:  # truncated or corrupt data (zlib, CRC, EOF): any reader exception says so
        raise UserError(f"{path}: array '{name}' cannot be read ({_why(exc)}); the file is damaged or "
                        f"truncated: {NPZ_HINT}") from None


def read_folders(folders: tuple[Path, ...], columns: tuple[str, ...],
                 shape_image: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, ...]:
    """Images (each passed through `shape_image`), float32 labels and the folder index of each row."""
    images, labels, groups = [], [], []
    first, budget = None, memory_budget()
    for g, folder in enumerate(folders):
        table = folder / "data.csv"
        rows = read_table(table, columns)
        for line, name, values in rows:
            where = f"{table}:{line}"
            path = _image_path(folder, name, where)
            image, size = read_image(path, where)
            image = shape_image(image)
            first = first or (path, size, image.shape)
            if image.shape != first[2]:
                raise UserError(f"{where}: image {path} is {_size(size)}, but the first image ({first[0]}) "
                                f"is {_size(first[1])}; all images must have one size (or give "
                                f"preprocess.resize)")
            budget -= image.nbytes
            if budget < 0:
                raise UserError(f"{where}: the images up to here need more than half of this machine's "
                                f"memory; use fewer or smaller images (preprocess.crop, preprocess.resize)")
            images.append(image)
            labels.append(values)
            groups.append(g)
    return np.stack(images), np.asarray(labels, np.float32), np.asarray(groups, np.int32)


def read_table(path: Path, columns: tuple[str, ...]) -> list[tuple[int, str, list[float]]]:
    """(line number, image_name, label values) of every row of a data.csv; at least one row."""
    require_file(path, "a data.csv file")
    reader = csv.reader(io.StringIO(_decode(path), newline=""), strict=True)
    rows = []
    try:
        header = [name.strip() for name in next((r for r in reader if r), [])]
        index = _columns(path, header, ("image_name", *columns))
        for fields in reader:
            if fields:
                rows.append(_row(path, reader.line_num, fields, header, index))
    except csv.Error as exc:
        raise UserError(f"{path}:{reader.line_num}: not valid CSV ({exc})") from None
    if not rows:
        raise UserError(f"{path}: lists no images (only a header); expected one row per image")
    return rows


def _decode(path: Path) -> str:
    """The text of a CSV file: UTF-8 (with or without a byte-order mark), or UTF-16/32 with one."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise UserError(f"{path}: cannot be read ({_why(exc)})") from None
    encoding = next((enc for bom, enc in BOMS if raw.startswith(bom)), "utf-8-sig")
    try:
        text = raw.decode(encoding)
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise UserError(f"{path}:{line}: is not {encoding.removesuffix('-sig').upper()} text (byte "
                        f"0x{raw[exc.start]:02x} at offset {exc.start}); save data.csv as UTF-8") from None
    if "\0" in text:
        line = text[:text.index("\0")].count("\n") + 1
        raise UserError(f"{path}:{line}: holds a NUL character (UTF-16 without a byte-order mark?); "
                        f"save data.csv as UTF-8")
    return text


def _columns(path: Path, header: list[str], needed: tuple[str, ...]) -> list[int]:
    """The position of each needed column in the header."""
    if not header:
        raise UserError(f"{path}: is empty; expected a header line such as {','.join(needed)}")
    twice = sorted({c for c in needed if header.count(c) > 1})
    absent = [c for c in needed if c not in header]
    if twice:
        raise UserError(f"{path}: column(s) {', '.join(twice)} appear more than once in the header "
                        f"({', '.join(header)}); each column must appear once")
    if absent:
        separator = next((s for s in (";", "\t", "|") if len(header) == 1 and s in header[0]), None)
        hint = f" (the file looks {separator!r}-separated; data.csv must use commas)" if separator else ""
        raise UserError(f"{path}: missing column(s) {', '.join(absent)}; header is {', '.join(header)}{hint}")
    return [header.index(c) for c in needed]


def _row(table: Path, line: int, fields: list[str], header: list[str],
         index: list[int]) -> tuple[int, str, list[float]]:
    """(line, image_name, labels) of one CSV row, after checking its field count and label cells."""
    if len(fields) != len(header):
        raise UserError(f"{table}:{line}: has {len(fields)} field(s) but the header has {len(header)} "
                        f"({', '.join(header)}); every row needs one value per column")
    values = []
    for i in index[1:]:
        text = fields[i].strip()
        try:
            value = float(text)
        except ValueError:
            raise UserError(f"{table}:{line}: column '{header[i]}' is {text!r}; labels must be "
                            f"numbers") from None
        if not (math.isfinite(value) and abs(value) <= FLOAT32_MAX):
            raise UserError(f"{table}:{line}: column '{header[i]}' is {text!r}; labels must be finite "
                            f"numbers (within float32's range)")
        values.append(value)
    return line, fields[index[0]].strip(), values


def _image_path(folder: Path, name: str, where: str) -> Path:
    """The image file a row names: inside the folder, as given or with a known suffix, a regular file."""
    pure = PurePosixPath(name)
    if not name or "\0" in name:
        raise UserError(f"{where}: image_name is {name!r}; expected a file name inside {folder}")
    if pure.is_absolute() or ".." in pure.parts:
        raise UserError(f"{where}: image_name '{name}' points outside {folder}; give a path relative to the "
                        f"folder, without '..'")
    for suffix in IMAGE_SUFFIXES:
        candidate = folder / (name + suffix)
        try:
            kind = not_regular(os.stat(candidate).st_mode)
        except OSError:
            continue
        if kind:
            raise UserError(f"{where}: {candidate} is {kind}, not a regular file; expected a PNG or "
                            f"JPEG image")
        return candidate
    raise UserError(f"{where}: image '{name}' not found in {folder} (tried the name as given and with "
                    f"{', '.join(IMAGE_SUFFIXES[1:])})")


def read_image(path: Path, where: str) -> tuple[np.ndarray, tuple[int, int]]:
    """One PNG or JPEG as 8-bit RGB (H, W, 3) and its (width, height); bombs, 16-bit or damaged: refused."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(path, formats=IMAGE_FORMATS)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise UserError(f"{where}: {path}: refused as a decompression bomb ({exc})") from None
    except Exception as exc:  # the bytes are not a PNG or JPEG header: any reader exception means the same
        raise UserError(f"{where}: {path}: not a readable PNG or JPEG image (damaged, truncated or another "
                        f"format: {_why(exc)})") from None
    with image:
        size = image.size
        if size[0] * size[1] > MAX_IMAGE_PIXELS:
            raise UserError(f"{where}: {path} is {_size(size)} pixels, more than the {MAX_IMAGE_PIXELS} "
                            f"bench-matrix reads (a decompression bomb?); use smaller images")
        if image.mode.startswith("I") or image.mode == "F":
            raise UserError(f"{where}: {path} is a 16-bit or floating-point image (mode {image.mode}); "
                            f"bench-matrix reads 8-bit grayscale, RGB, RGBA or palette images")
        try:
            return np.asarray(image.convert("RGB")), size
        except Exception as exc:  # truncated or corrupt pixel data
            raise UserError(f"{where}: {path}: the image cannot be decoded (damaged or truncated? "
                            f"{_why(exc)})") from None


def _size(size: tuple[int, int]) -> str:
    return f"{size[0]}×{size[1]}"


def _why(exc: BaseException) -> str:
    return str(exc) or type(exc).__name__
