"""Read image files: DeepLearningStudio folders (data.csv + images) and class-per-subfolder image folders."""

from __future__ import annotations

import codecs
import csv
import io
import math
import os
import warnings
from collections.abc import Callable
from pathlib import Path, PurePosixPath

import numpy as np

from bench_matrix.data_readers import memory_budget, require_file, why
from bench_matrix.errors import UserError
from bench_matrix.workspace import not_regular

BOMS = ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"), (codecs.BOM_UTF16_LE, "utf-16"),
        (codecs.BOM_UTF16_BE, "utf-16"))
IMAGE_FORMATS = ("PNG", "JPEG", "BMP")
IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg")  # tried after a data.csv image_name
CLASS_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")  # the files of a class folder that are images
MAX_IMAGE_PIXELS = 8192 * 8192  # a camera frame is far smaller; more is a decompression bomb or a mistake
FLOAT32_MAX = float(np.finfo(np.float32).max)
SAME_SIZE = "give dataset.preprocess.resize, or resize_shorter with center_crop"


class ImageStack:
    """Images read one by one, shaped by `shape_image`, checked to share one size and to fit in memory."""

    def __init__(self, shape_image: Callable[[np.ndarray], np.ndarray]):
        self.shape_image, self.images, self.budget = shape_image, [], memory_budget()
        self.first: tuple[Path, tuple[int, int], tuple[int, ...]] | None = None

    def add(self, path: Path, where: str) -> None:
        image, size = read_image(path, where)
        image = self.shape_image(image)
        self.first = self.first or (path, size, image.shape)
        if image.shape != self.first[2]:
            raise UserError(f"{where}: image {path} is {_size(size)}, but the first image ({self.first[0]}) "
                            f"is {_size(self.first[1])}; all images must have one size: {SAME_SIZE}")
        self.budget -= image.nbytes
        if self.budget < 0:
            raise UserError(f"{where}: the images up to here need more than half of this machine's memory; "
                            f"use fewer or smaller images (dataset.preprocess.crop, resize, center_crop)")
        self.images.append(image)

    def array(self) -> np.ndarray:
        return np.stack(self.images)


def read_folders(folders: tuple[Path, ...], columns: tuple[str, ...],
                 shape_image: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, ...]:
    """Images (each passed through `shape_image`), float32 labels and the folder index of each row."""
    stack, labels, groups = ImageStack(shape_image), [], []
    for g, folder in enumerate(folders):
        table = folder / "data.csv"
        for line, name, values in read_table(table, columns):
            where = f"{table}:{line}"
            stack.add(_image_path(folder, name, where), where)
            labels.append(values)
            groups.append(g)
    return stack.array(), np.asarray(labels, np.float32), np.asarray(groups, np.int32)


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
        raise UserError(f"{path}: cannot be read ({why(exc)})") from None
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
            raise UserError(f"{where}: {candidate} is {kind}, not a regular file; expected a PNG, "
                            f"JPEG or BMP image")
        return candidate
    raise UserError(f"{where}: image '{name}' not found in {folder} (tried the name as given and with "
                    f"{', '.join(IMAGE_SUFFIXES[1:])})")


def read_image(path: Path, where: str) -> tuple[np.ndarray, tuple[int, int]]:
    """One PNG, JPEG or BMP as 8-bit RGB (H, W, 3) and its (width, height); bombs, 16-bit, damage: refused."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(path, formats=IMAGE_FORMATS)
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise UserError(f"{where}: {path}: refused as a decompression bomb ({exc})") from None
    except Exception as exc:  # the bytes are not an image header: any reader exception means the same
        raise UserError(f"{where}: {path}: not a readable PNG, JPEG or BMP image (damaged, truncated or "
                        f"another format: {why(exc)})") from None
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
                            f"{why(exc)})") from None


def read_class_folders(roots: tuple[Path, ...], shape_image: Callable[[np.ndarray], np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...]]:
    """Images of `root/<class>/...` folders (as torchvision's ImageFolder), their class ids, the root index
    of each image, and the class names: the sorted subfolder names of every root together."""
    listed = {root: _class_images(root) for root in roots}
    classes = tuple(sorted({name for found in listed.values() for name in found}))
    stack, labels, groups = ImageStack(shape_image), [], []
    for g, (root, found) in enumerate(listed.items()):
        for name, files in found.items():
            for path in files:
                stack.add(path, f"class '{name}'")
                labels.append(classes.index(name))
                groups.append(g)
    return stack.array(), np.asarray(labels, np.int64), np.asarray(groups, np.int32), classes


def first_class_image_size(root: Path) -> tuple[int, int]:
    """(height, width) of the first image of a class-per-subfolder folder, read from its header."""
    from PIL import Image

    path = next(iter(_class_images(root).values()))[0]
    try:
        with Image.open(path, formats=IMAGE_FORMATS) as image:
            return image.size[1], image.size[0]
    except Exception as exc:  # not an image: any reader exception means the same
        raise UserError(f"{path}: not a readable PNG, JPEG or BMP image ({why(exc)})") from None


def _class_images(root: Path) -> dict[str, list[Path]]:
    """Class name -> its image files (sorted, subfolders included), for every subfolder of `root`."""
    try:
        folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError as exc:
        raise UserError(f"{root}: cannot be read ({why(exc)}); expected a folder with one subfolder of "
                        f"images per class") from None
    if not folders:
        raise UserError(f"{root}: has no subfolders; expected one subfolder of images per class "
                        f"(root/<class>/*.png), as torchvision's ImageFolder reads")
    found = {}
    for folder in folders:
        files = sorted(p for p in folder.rglob("*")
                       if p.suffix.lower() in CLASS_IMAGE_SUFFIXES and p.is_file())
        if not files:
            raise UserError(f"{folder}: class '{folder.name}' holds no images "
                            f"({', '.join(CLASS_IMAGE_SUFFIXES)}); add images or remove the folder")
        found[folder.name] = files
    return found


def _size(size: tuple[int, int]) -> str:
    return f"{size[0]}×{size[1]}"
