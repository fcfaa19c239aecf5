"""Generators of broken and hostile data files (.npz, recording folders, image folders) for
test_fuzz_inputs.py, each with what its error message must name; seeded."""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fuzz_cases import Case, Payload, SEED, markers, render

def png(image: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def bomb_png(side: int = 20000) -> bytes:
    """A 1-bit PNG of a few tens of kB that decodes to side x side pixels (Pillow's limit is 2 x 89 M)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    row, packer = bytes(1 + (side + 7) // 8), zlib.compressobj(9)
    pixels = b"".join(packer.compress(row) for _ in range(side)) + packer.flush()
    header = struct.pack(">IIBBBBB", side, side, 1, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


EPS = b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 16 16\n0 0 moveto 16 16 lineto stroke showpage\n"
ROWS = [f"r{i}.png,{i / 10},{-i / 10}" for i in range(12)]  # row i is line i + 2 of data.csv
NOTED = [f"{r},fine" for r in ROWS]  # with a fourth column, 'note'
SPLIT = {"train": 0.5, "calibration": 0.25, "test": 0.25}


def recording(rows: list[str] = ROWS, images: dict[str, Any] | None = None, encoding: str = "utf-8",
              header: str = "image_name,v,w", preprocess: dict | None = None) -> Callable[[Path], str]:
    """A DeepLearningStudio folder 'rec' (data.csv and 16x16 PNGs, some replaced by `images`)."""
    def build(project: Path) -> str:
        folder = project / "rec"
        folder.mkdir()
        rng = np.random.default_rng(SEED)
        files = {f"r{i}.png": png(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)) for i in range(12)}
        (project / "outside.png").write_bytes(files["r0.png"])
        for name, data in {**files, **(images or {})}.items():
            (folder / name).write_bytes(data(project) if callable(data) else data)
        (folder / "data.csv").write_bytes("\n".join([header, *rows]).encode(encoding) + b"\n")
        dataset = {"folder": "rec", "split": SPLIT, **({"preprocess": preprocess} if preprocess else {})}
        return render(((("dataset",), dataset),))
    return build


def row(i: int, text: str, rows: list[str] = ROWS) -> list[str]:
    return rows[:i] + [text] + rows[i + 1:]


def arrays(**changes: Any) -> Callable[[Path], dict[str, Any]]:
    """The good x, y with `changes` (a value, None to drop the array, or a function of the project)."""
    def make(project: Path) -> dict[str, Any]:
        rng = np.random.default_rng(SEED)
        good = {"x": rng.integers(0, 256, (48, 16, 16, 3), dtype=np.uint8),
                "y": rng.random((48, 2), np.float32)}
        for key, value in changes.items():
            good[key] = value(project) if callable(value) else value
        return {k: v for k, v in good.items() if v is not None}
    return make


def npz_bytes(**data: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **data)
    return buffer.getvalue()


def hostile_array(name: str) -> Callable[[Path], np.ndarray]:
    def make(project: Path) -> np.ndarray:
        array = np.empty(48, dtype=object)
        array[:] = [Payload(markers(project) / name) for _ in range(48)]
        return array
    return make


def with_value(array: np.ndarray, index: tuple, value: float) -> np.ndarray:
    out = array.astype(np.float32)
    out[index] = value
    return out


GOOD = arrays()(Path())
NPZ = {  # name -> (arrays or bytes, culprit besides the file name, marker)
    "empty_file": (b"", (), None), "truncated": (npz_bytes(**GOOD)[:3000], (), None),
    "random_bytes": (np.random.default_rng(SEED).bytes(3000), (), None),
    "csv_text": (b"x,y\n1,2\n", (), None),
    "object_images": (arrays(x=hostile_array("npz_x")), (r"re:\bx\b",), "npz_x"),
    "object_labels": (arrays(y=hostile_array("npz_y")), (r"re:\by\b",), "npz_y"),
    "string_labels": (arrays(y=np.array([["a", "b"]] * 48)), (r"re:\by\b",), None),
    "nan_labels": (arrays(y=with_value(GOOD["y"], (5, 1), np.nan)), (r"re:\by\b",), None),
    "inf_labels": (arrays(y=with_value(GOOD["y"], (7, 0), np.inf)), (r"re:\by\b",), None),
    "nan_images": (arrays(x=with_value(GOOD["x"], (3, 1, 2, 0), np.nan)), (r"re:\bx\b",), None),
    "inf_images": (arrays(x=with_value(GOOD["x"], (4, 0, 0, 1), -np.inf)), (r"re:\bx\b",), None),
    "length_mismatch": (arrays(y=GOOD["y"][:40]), (r"re:\by\b",), None),
    "missing_y": (arrays(y=None), (r"re:\by\b",), None),
    "groups_length": (arrays(groups=np.arange(20)), ("groups",), None),
    "groups_strings": (arrays(groups=np.array([f"run{i % 4}" for i in range(48)])), ("groups",), None),
    "groups_nan": (arrays(groups=with_value(np.arange(48) % 4, 9, np.nan)), ("groups",), None),
    "groups_2d": (arrays(groups=np.zeros((48, 2), np.int64)), ("groups",), None),
    "zero_samples": (arrays(x=GOOD["x"][:0], y=GOOD["y"][:0]), (), None),
    "zero_width_images": (arrays(x=GOOD["x"][:, :, :0]), (r"re:\bx\b",), None),
    "complex_images": (arrays(x=GOOD["x"].astype(np.complex64)), (r"re:\bx\b",), None),
}
FOLDER = {  # name -> (folder builder, culprit)
    "csv_utf16": (recording(encoding="utf-16"), ("data.csv",)),
    "csv_latin1": (recording(row(1, "r1.png,0.1,0.2,naïve", NOTED), encoding="latin-1",
                             header="image_name,v,w,note"), ("data.csv",)),
    "csv_short_row": (recording(row(2, "r2.png,0.5")), ("data.csv:4",)),
    "csv_text_label": (recording(row(1, "r1.png,fast,0.2")), ("data.csv:3",)),
    "csv_nan_label": (recording(row(1, "r1.png,nan,0.2")), ("data.csv:3",)),
    "csv_inf_label": (recording(row(1, "r1.png,0.1,-inf")), ("data.csv:3",)),
    "csv_nul_in_name": (recording(row(1, "r1.png\0,0.1,0.2")), ("data.csv:3",)),
    "csv_huge_field": (recording(row(1, "r1.png,0.1,0.2," + "z" * 200_000, NOTED),
                                 header="image_name,v,w,note"),
                       ("data.csv:3",)),
    "csv_empty_file": (recording([], header=""), ("data.csv",)),
    "png_missing": (recording(row(3, "nothere.png,0.1,0.2")), ("nothere",)),
    "png_corrupt": (recording(images={"r3.png": np.random.default_rng(SEED).bytes(500)}),
                    ("r3.png", "data.csv:5")),
    "png_truncated": (recording(images={"r3.png": png(np.full((16, 16, 3), 7, np.uint8))[:-30]}),
                      ("r3.png", "data.csv:5")),
    "png_empty": (recording(images={"r3.png": b""}), ("r3.png", "data.csv:5")),
    "png_decompression_bomb": (recording(images={"r3.png": lambda _p: bomb_png()}), ("r3.png", "data.csv:5")),
    "png_mixed_sizes": (recording(images={"r3.png": png(np.zeros((12, 20, 3), np.uint8))}),
                        ("r3.png", "data.csv:5", "resize")),
    "png_postscript_inside": (recording(images={"r3.png": EPS}), ("r3.png", "data.csv:5")),
    "png_path_dotdot": (recording(row(1, "../outside.png,0.1,0.2")), ("../outside", "data.csv:3")),
    "png_path_absolute": (recording(row(1, "/proc/self/environ,0.1,0.2")),
                          ("/proc/self/environ", "data.csv:3")),
    "png_crop_beyond_image": (recording(preprocess={"crop": {"top": 40}}), ("crop",)),
}


def class_folders(images: dict[str, Any] | None = None, flat: bool = False) -> Callable[[Path], str]:
    """Folder 'imgs': classes cat, dog of six PNGs each, some replaced by `images`; `flat`: no classes."""
    def build(project: Path) -> str:
        rng = np.random.default_rng(SEED)
        files = {f"{label}/{label[0]}{i}.png": png(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8))
                 for label in ("cat", "dog") for i in range(6)}
        for name, data in {**files, **(images or {})}.items():
            path = project / "imgs" / (name.replace("/", "_") if flat else name)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data(project) if callable(data) else data)
        return render(((("dataset",), {"images": "imgs", "split": SPLIT}),))
    return build


IMAGES = {  # name -> (image folder builder, culprit)
    "no_class_subfolders": (class_folders(flat=True), ("imgs",)),
    "png_corrupt": (class_folders({"cat/c3.png": np.random.default_rng(SEED).bytes(500)}), ("c3.png",)),
    "png_decompression_bomb": (class_folders({"cat/c2.png": lambda _p: bomb_png()}), ("c2.png",)),
}


def data_cases() -> list[Case]:
    """Broken .npz files, DeepLearningStudio folders, image folders; each culprit names the file."""
    cases = []
    for name, (content, culprit, marker) in NPZ.items():
        def build(project: Path, name: str = name, content: Any = content) -> str:
            data = content(project) if callable(content) else content
            path = project / f"{name}.npz"
            path.write_bytes(data) if isinstance(data, bytes) else np.savez(path, **data)
            return render(((("dataset", "npz"), path.name),))
        culprit = ((f"{name}.npz",),) + ((culprit,) if culprit else ())
        cases.append(Case(f"npz:{name}", build, culprit, marker))
    cases += [Case(f"folder:{name}", build, (culprit,)) for name, (build, culprit) in FOLDER.items()]
    return cases + [Case(f"images:{name}", build, (culprit,)) for name, (build, culprit) in IMAGES.items()]
