"""Every mistake in a user's dataset file is a UserError naming the file, the array/row/image and what is
expected; a few checks go through the CLI (exit 2, no traceback)."""

from __future__ import annotations

import io
import os
import pickle
import struct
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench_matrix import data
from bench_matrix.images import geometric
from bench_matrix.data_readers import read_npz
from bench_matrix.image_readers import read_folders, read_table
from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import DatasetSpec, LabelSpec, Preprocess, SplitSpec
from bench_matrix.workspace import Workspace
from conftest import cli, matrix_text

COLUMNS = ("v", "w")
TASK = "regression"


class WritesMarker:
    """Unpickling this would create the marker file: the proof that no pickle in a data file is ever run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


def refused(call, *culprits: str) -> str:
    """The UserError message of `call()`, after checking it names every culprit."""
    with pytest.raises(UserError) as info:
        call()
    message = str(info.value)
    for culprit in culprits:
        assert culprit in message, message
    return message


def npz(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def good_arrays(n: int = 10) -> dict[str, np.ndarray]:
    return {"x": np.zeros((n, 4, 4, 3), np.uint8), "y": np.ones((n, 2), np.float32)}


# .npz archives: the file itself


def test_npz_file_that_is_not_an_archive(tmp_path):
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    refused(lambda: read_npz(empty, TASK), str(empty), "is empty (0 bytes)", "numpy.savez")
    text = tmp_path / "text.npz"
    text.write_text("x,y\n1,2\n")
    refused(lambda: read_npz(text, TASK), str(text), "not an .npz archive (not a zip file)")
    single = tmp_path / "single.npz"
    with open(single, "wb") as f:
        np.save(f, np.zeros(3))
    refused(lambda: read_npz(single, TASK), str(single), "single .npy array, not an .npz archive")
    whole = npz(tmp_path / "whole.npz", **good_arrays())
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    refused(lambda: read_npz(truncated, TASK), str(truncated), "damaged or truncated zip archive")


def test_npz_with_a_damaged_member(tmp_path):
    path = tmp_path / "damaged.npz"
    np.savez_compressed(path, x=np.random.default_rng(0).integers(0, 255, (50, 8, 8, 3), dtype=np.uint8),
                        y=np.ones(50))
    raw = bytearray(path.read_bytes())
    raw[200:260] = bytes(60)  # inside x's compressed data
    path.write_bytes(bytes(raw))
    refused(lambda: read_npz(path, TASK), str(path), "array 'x'", "damaged")


def test_npz_pickles_are_refused_and_never_run(tmp_path):
    marker = tmp_path / "marker"
    pickled = tmp_path / "pickled.npz"
    pickled.write_bytes(pickle.dumps({"x": WritesMarker(marker)}))
    refused(lambda: read_npz(pickled, TASK), str(pickled), "Python pickle", "never loads")
    objects = npz(tmp_path / "objects.npz", x=np.array([WritesMarker(marker)] * 10, dtype=object),
                  y=np.zeros(10))
    refused(lambda: read_npz(objects, TASK), str(objects), "array 'x' holds Python objects",
            "save plain numeric arrays")
    assert not marker.exists()


def test_npz_missing_arrays_name_what_is_there(tmp_path):
    path = npz(tmp_path / "d.npz", x=np.zeros((10, 4, 4)), labels=np.zeros(10))
    refused(lambda: read_npz(path, TASK), str(path), "missing array 'y': task regression needs labels",
            "it has: x, labels", "task: none")
    assert read_npz(path, "none").labels is None
    only_labels = npz(tmp_path / "y.npz", y=np.zeros(10))
    refused(lambda: read_npz(only_labels, TASK), str(only_labels), "holds no input array (it has: y)")


@pytest.mark.parametrize("name, values, found", [
    ("x", np.array([["a"] * 4] * 10), "holds text (dtype <U1)"),
    ("x", np.zeros((10, 4, 4), complex), "holds complex numbers"),
    ("x", np.zeros((10, 4), "S3"), "holds bytes"),
    ("mask", np.zeros((10, 4), "datetime64[s]"), "array 'mask' holds dates"),
    ("y", np.zeros(10, bool), "array 'y' holds booleans"),
    ("y", np.array(["fast"] * 10), "array 'y' holds text"),
    ("groups", np.arange(10) / 2, "array 'groups' holds floats (dtype float64)"),
])
def test_npz_arrays_of_the_wrong_type(tmp_path, name, values, found):
    path = npz(tmp_path / "d.npz", **{**good_arrays(), "groups": np.arange(10), name: values})
    refused(lambda: read_npz(path, TASK), str(path), found, "expected")


@pytest.mark.parametrize("arrays, culprit", [
    ({"x": np.zeros(())}, "array 'x' has shape (); expected a model input"),
    ({"x": np.zeros((10, 0, 4, 3))}, "array 'x' has shape (10, 0, 4, 3)"),
    ({"y": np.zeros(())}, "array 'y' has shape ()"),
    ({"y": np.zeros((10, 0))}, "array 'y' has shape (10, 0)"),
    ({"y": np.zeros(9)}, "different numbers of samples (first axis): 'x' 10, 'y' 9"),
    ({"ids": np.zeros((11, 3), np.int64)}, "'x' 10, 'y' 10, 'ids' 11"),
    ({"groups": np.arange(9)}, "array 'groups' has shape (9,) for 10 samples"),
    ({"x": np.zeros((0, 4, 4)), "y": np.zeros(0)}, "holds no samples"),
])
def test_npz_arrays_whose_shapes_do_not_agree(tmp_path, arrays, culprit):
    path = npz(tmp_path / "d.npz", **{**good_arrays(), **arrays})
    refused(lambda: read_npz(path, TASK), str(path), culprit)


def test_npz_non_finite_values_name_the_first_sample(tmp_path):
    x = np.zeros((10, 4, 4), np.float32)
    x[3, 1, 1], x[7, 0, 0] = np.nan, np.inf
    path = npz(tmp_path / "nan.npz", x=x, y=np.zeros(10))
    refused(lambda: read_npz(path, TASK), str(path), "array 'x': sample 3 (and 1 more) holds NaN or Inf")
    y = np.zeros((10, 2))
    y[5, 1] = 1e300  # finite in float64, Inf in float32
    path = npz(tmp_path / "big.npz", x=np.zeros((10, 4, 4)), y=y)
    refused(lambda: read_npz(path, TASK), str(path), "array 'y': sample 5 holds", "float32")


def test_npz_whose_header_claims_more_than_memory_is_refused_unread(tmp_path):
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False,
                                                  "shape": (10**9, 1000, 1000, 3)})
    path = tmp_path / "huge.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("x.npy", header.getvalue())
        archive.writestr("y.npy", b"")
    refused(lambda: read_npz(path, TASK), str(path), "array 'x' (1000000000, 1000, 1000, 3) needs",
            "more than half of this machine's memory")


@pytest.mark.timeout(30)  # opening a named pipe would block: fail fast instead
def test_paths_that_are_not_regular_files_fail_without_opening(tmp_path):
    pipe = tmp_path / "pipe.npz"
    os.mkfifo(pipe)
    refused(lambda: read_npz(pipe, TASK), str(pipe), "is a named pipe, not a regular file")
    refused(lambda: read_npz(tmp_path, TASK), str(tmp_path), "is a directory, not a regular file")
    refused(lambda: read_npz(tmp_path / "nope.npz", TASK), "nope.npz: not found")
    os.mkfifo(tmp_path / "data.csv")
    refused(lambda: read_table(tmp_path / "data.csv", COLUMNS), "data.csv: is a named pipe")


# DeepLearningStudio folders: data.csv


def recording(root: Path, csv_text: str | None = None, sizes: tuple = ((16, 16),) * 4) -> Path:
    """A folder with images 0.png ... and a data.csv (by default listing every image with labels v, w)."""
    folder = root / "rec"
    folder.mkdir(exist_ok=True)
    for i, (w, h) in enumerate(sizes):
        Image.fromarray(np.full((h, w, 3), 40 * i, np.uint8)).save(folder / f"{i}.png")
    rows = "".join(f"{i},{i}.5,-{i}\n" for i in range(len(sizes)))
    text = csv_text if csv_text is not None else "image_name,v,w\n" + rows
    (folder / "data.csv").write_text(text)
    return folder


def read(folder: Path):
    return read_folders((folder,), COLUMNS, lambda image: image)


def test_csv_encodings_utf8_with_bom_and_utf16_are_read(tmp_path):
    folder = recording(tmp_path)
    text = (folder / "data.csv").read_text()
    expected = read_table(folder / "data.csv", COLUMNS)
    for encoding in ("utf-8-sig", "utf-16"):
        (folder / "data.csv").write_bytes(text.encode(encoding))
        assert read_table(folder / "data.csv", COLUMNS) == expected
    assert expected[1] == (3, "1", [1.5, -1.0])


def test_csv_in_another_encoding_is_refused_with_the_line(tmp_path):
    folder = recording(tmp_path)
    table = folder / "data.csv"
    table.write_bytes("image_name,v,w\n0,1,2\ncaf\u00e9,1,2\n".encode("latin-1"))
    refused(lambda: read(folder), f"{table}:3: is not UTF-8 text (byte 0xe9", "save data.csv as UTF-8")
    table.write_bytes("image_name,v,w\n0,1,2\n".encode("utf-16-le"))
    refused(lambda: read(folder), f"{table}:1: holds a NUL character")


@pytest.mark.parametrize("text, culprit", [
    ("", "data.csv: is empty; expected a header line such as image_name,v,w"),
    ("image_name,v,w\n", "data.csv: lists no images"),
    ("image_name,v\n0,1\n", "data.csv: missing column(s) w; header is image_name, v"),
    ("image_name;v;w\n0;1;2\n", "header is image_name;v;w (the file looks ';'-separated"),
    ("image_name,v,w,v\n0,1,2,3\n", "data.csv: column(s) v appear more than once"),
    ("image_name,v,w\n0,1,2\n1,2\n", "data.csv:3: has 2 field(s) but the header has 3 (image_name, v, w)"),
    ("image_name,v,w\n0,1,2,4\n", "data.csv:2: has 4 field(s) but the header has 3"),
    ("image_name,v,w\n0,1,2\n1,fast,2\n", "data.csv:3: column 'v' is 'fast'; labels must be numbers"),
    ("image_name,v,w\n0,1,\n", "data.csv:2: column 'w' is ''; labels must be numbers"),
    ("image_name,v,w\n0,1,nan\n", "data.csv:2: column 'w' is 'nan'; labels must be finite numbers"),
    ("image_name,v,w\n0,1e39,1\n", "data.csv:2: column 'v' is '1e39'; labels must be finite"),
    ('image_name,v,w\n0,1,"2\n', "data.csv:2: not valid CSV (unexpected end of data)"),
])
def test_csv_mistakes_name_the_line_and_column(tmp_path, text, culprit):
    folder = recording(tmp_path, text)
    refused(lambda: read(folder), str(folder), culprit)


def test_csv_spaces_around_names_and_values_are_ignored(tmp_path):
    folder = recording(tmp_path, "image_name, v , w\n 0 , 1.5, 2\n")
    images, labels, groups = read(folder)
    assert images.shape == (1, 16, 16, 3) and labels.tolist() == [[1.5, 2.0]] and groups.tolist() == [0]


# DeepLearningStudio folders: images


@pytest.mark.parametrize("name, culprit", [
    ("7", "data.csv:2: image '7' not found in"),
    ("../0.png", "data.csv:2: image_name '../0.png' points outside"),
    ("/etc/passwd", "data.csv:2: image_name '/etc/passwd' points outside"),
    ("sub", "rec/sub is a directory, not a regular file; expected a PNG, JPEG or BMP image"),
])
def test_image_names_that_do_not_name_an_image_in_the_folder(tmp_path, name, culprit):
    folder = recording(tmp_path, f"image_name,v,w\n{name},1,2\n")
    (folder / "sub").mkdir()
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "0.png")
    refused(lambda: read(folder), culprit)


def png_header(width: int, height: int) -> bytes:
    """A PNG that declares width × height pixels but holds almost no data (a decompression bomb's header)."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    body = chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")
    return b"\x89PNG\r\n\x1a\n" + body


def test_damaged_images_and_bombs_name_the_row_and_file(tmp_path):
    folder = recording(tmp_path)
    noise = io.BytesIO()
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8)).save(noise, "PNG")
    cases = {
        "0.png": (b"not an image at all", "not a readable PNG, JPEG or BMP image"),
        "1.png": (noise.getvalue()[:400], "damaged or truncated"),
        "2.png": (png_header(9000, 9000), "is 9000×9000 pixels, more than the"),
        "3.png": (png_header(100_000, 100_000), "refused as a decompression bomb"),
    }
    for line, (name, (content, culprit)) in enumerate(cases.items(), start=2):
        original = (folder / name).read_bytes()
        (folder / name).write_bytes(content)
        refused(lambda: read(folder), f"data.csv:{line}: {folder / name}", culprit)
        (folder / name).write_bytes(original)


def test_truncated_jpeg_and_other_formats_are_refused(tmp_path):
    folder = recording(tmp_path, "image_name,v,w\nframe.jpg,1,2\n")
    buffer = io.BytesIO()
    noise = np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)
    Image.fromarray(noise).save(buffer, "JPEG")
    for cut in (600, len(buffer.getvalue()) // 2):  # in the header, in the pixel data
        (folder / "frame.jpg").write_bytes(buffer.getvalue()[:cut])
        refused(lambda: read(folder), "data.csv:2: ", "frame.jpg", "truncated")
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / "frame.jpg", "GIF")
    refused(lambda: read(folder), "frame.jpg", "not a readable PNG, JPEG or BMP image")


def test_images_of_mixed_sizes_name_the_first_that_differs(tmp_path):
    folder = recording(tmp_path, sizes=((16, 16), (16, 16), (20, 16), (16, 12)))
    refused(lambda: read(folder), f"data.csv:4: image {folder / '2.png'} is 20×16, but the first image "
                                  f"({folder / '0.png'}) is 16×16", "preprocess.resize")
    resize = Preprocess(resize=(8, 8))
    images, _, _ = read_folders((folder,), COLUMNS, lambda image: geometric(image, resize))
    assert images.shape == (4, 8, 8, 3)


def test_image_modes_grayscale_rgba_palette_are_rgb_and_16_bit_is_refused(tmp_path):
    folder = recording(tmp_path)
    gray = np.arange(256, dtype=np.uint8).reshape(16, 16)
    Image.fromarray(gray).save(folder / "0.png")
    Image.fromarray(np.dstack([gray] * 3 + [np.zeros_like(gray)])).save(folder / "1.png")  # fully transparent
    palette = np.stack([255 - np.arange(256), np.arange(256), np.zeros(256)], -1).astype(np.uint8)
    indexed = Image.fromarray(gray).convert("P")  # no dithering from L: index i is pixel value i
    indexed.putpalette(palette.tobytes())
    indexed.save(folder / "2.png")
    images, _, _ = read(folder)
    assert images.shape == (4, 16, 16, 3)
    assert (images[0] == gray[..., None]).all() and (images[1] == gray[..., None]).all()
    assert (images[2] == palette[gray]).all()
    Image.fromarray(gray.astype(np.uint16) * 256).save(folder / "3.png")
    refused(lambda: read(folder), f"data.csv:5: {folder / '3.png'} is a 16-bit", "8-bit grayscale, RGB")


# the dataset as a whole: labels, splits, preprocessing


def prepare(tmp_path: Path, path: Path, **spec) -> tuple[Path, dict]:
    return data.prepare(DatasetSpec(kind="npz", paths=(path,), **spec), Workspace(tmp_path / "ws"))


def test_label_normalisation_must_fit_the_label_columns(tmp_path):
    path = npz(tmp_path / "d.npz", **good_arrays())
    refused(lambda: prepare(tmp_path, path, labels=LabelSpec(columns=COLUMNS, offset=(1.0, 2.0, 3.0))),
            "dataset.labels.offset has 3 values", f"{path} has 2 label column(s) (v, w)")
    _, info = prepare(tmp_path, path, labels=LabelSpec(columns=COLUMNS, offset=(1.0,), scale=(2.0, 4.0)))
    assert info["train_label_mean"] == [0.0, 0.0]


def test_too_few_samples_for_the_split_say_how_many_would_do(tmp_path):
    path = npz(tmp_path / "d.npz", **good_arrays(2))
    refused(lambda: prepare(tmp_path, path), f"{path}: 2 samples are too few for the split fractions",
            "add samples (6 would do)")


def test_preprocessing_that_does_not_fit_the_images(tmp_path):
    path = npz(tmp_path / "d.npz", x=np.zeros((10, 8, 8), np.uint8), y=np.zeros(10))
    refused(lambda: prepare(tmp_path, path, preprocess=Preprocess(mean=(0.5, 0.5, 0.5), std=(1.0, 1.0, 1.0))),
            "dataset.preprocess.mean has 3 values", "have 1 channel(s)")
    refused(lambda: prepare(tmp_path, path, preprocess=Preprocess(crop=(20, 30, None, None))),
            "dataset.preprocess.crop {top: 20, bottom: 30} leaves no pixels of a 8×8 image")
    directory, info = prepare(tmp_path, path, preprocess=Preprocess(resize=(4, 6)))  # grayscale resized
    assert info["inputs"] == [{"name": "x", "shape": [4, 6, 1], "dtype": "uint8", "image": True,
                               "range": [0.0, 0.0], "scale": 1 / 255}]
    assert np.load(directory / "test__x.npy").dtype == np.uint8


def test_split_needs_enough_groups(tmp_path):
    path = npz(tmp_path / "d.npz", **good_arrays(), groups=np.array([0] * 5 + [1] * 5))
    refused(lambda: prepare(tmp_path, path, split=SplitSpec(by="group")), "'group' needs at least 3 groups",
            "has 2")


# through the command line: exit 2, the file named, no traceback


def run_with_dataset(project: Path, dataset: str, command: str = "run") -> tuple[int, str]:
    (project / "m.yaml").write_text(matrix_text(["pytorch"], ["none"], ["fp32"], ["cpu"]).replace(
        "npz: data.npz", dataset))
    out = cli(project, command, "m.yaml")
    assert "Traceback" not in out.stderr + out.stdout
    return out.returncode, out.stderr


def test_cli_truncated_npz_and_nan_labels_exit_2(tiny_project):
    data_npz = tiny_project / "data.npz"
    (tiny_project / "cut.npz").write_bytes(data_npz.read_bytes()[:500])
    code, err = run_with_dataset(tiny_project, "npz: cut.npz")
    assert code == 2 and f"{tiny_project / 'cut.npz'}: is a damaged or truncated" in err
    arrays = dict(np.load(data_npz))
    arrays["y"][40, 0] = np.nan
    np.savez(tiny_project / "nan.npz", **arrays)
    code, err = run_with_dataset(tiny_project, "npz: nan.npz")
    assert code == 2 and f"{tiny_project / 'nan.npz'}: array 'y': sample 40 holds NaN or Inf" in err


@pytest.mark.parametrize("command", ["plan", "run"])
def test_cli_float_images_already_in_0_1_exit_2_without_a_scale(tiny_project, command):
    """`plan` refuses what `run` would: the same check, before anything runs, at the dataset's line."""
    arrays = dict(np.load(tiny_project / "data.npz"))
    np.savez(tiny_project / "unit.npz", x=arrays["x"] / np.float32(255), y=arrays["y"])
    code, err = run_with_dataset(tiny_project, "npz: unit.npz", command)
    lines = (tiny_project / "m.yaml").read_text().splitlines()
    line = next(i for i, text in enumerate(lines, 1) if text.startswith("dataset:"))
    assert code == 2 and (f"m.yaml:{line}: dataset: {tiny_project / 'unit.npz'}: input 'x' "
                          f"holds float32 images with values 0 to 1 (already in [0, 1])") in err
    assert "set dataset.preprocess.scale" in err


def test_cli_folder_with_a_corrupt_image_exits_2(tiny_project):
    folder = recording(tiny_project)
    (folder / "2.png").write_bytes(b"\x89PNG\r\n\x1a\n broken")
    code, err = run_with_dataset(tiny_project, "folder: rec")
    assert code == 2
    assert f"{folder / 'data.csv'}:4: {folder / '2.png'}: not a readable PNG, JPEG or BMP image" in err
