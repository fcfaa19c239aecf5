"""Datasets with several named inputs, class labels, image class folders, synthetic inputs and preprocessing:
what is cached, what a split loads as, and the mistakes refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench_matrix import data
from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import DatasetSpec, Preprocess, SplitSpec
from bench_matrix.tensors import TensorSpec
from bench_matrix.workspace import Workspace

RED, GREEN = (255, 0, 0), (0, 255, 0)
SPLIT = SplitSpec(train=0.5, calibration=0.25, test=0.25)


def npz_spec(tmp_path: Path, task: str, name: str = "d.npz", **arrays) -> DatasetSpec:
    np.savez(tmp_path / name, **arrays)
    return DatasetSpec(kind="npz", paths=(tmp_path / name,), task=task, split=SPLIT)


def prepare(tmp_path: Path, spec: DatasetSpec, inputs=None) -> tuple[Path, dict]:
    return data.prepare(spec, Workspace(tmp_path / "ws"), inputs)


def refused(call, *culprits: str) -> None:
    with pytest.raises(UserError) as info:
        call()
    for culprit in culprits:
        assert culprit in str(info.value), str(info.value)


def test_two_inputs_without_labels_pass_through_untouched(tmp_path):
    rng = np.random.default_rng(0)
    ids, features = rng.integers(0, 1000, (40, 12)), rng.random((40, 5)).astype(np.float32)
    spec = npz_spec(tmp_path, "none", input_ids=ids, features=features)
    directory, info = prepare(tmp_path, spec)
    assert info["inputs"] == [{"name": "input_ids", "shape": [12], "dtype": "int64", "image": False},
                              {"name": "features", "shape": [5], "dtype": "float32", "image": False}]
    assert info["task"] == "none" and "label_columns" not in info and "classes" not in info
    assert not list(directory.glob("*__y.npy"))
    inputs, labels = data.load_split(directory, "test", Preprocess(mean=None), "nchw")
    assert labels is None and list(inputs) == ["input_ids", "features"]
    assert inputs["input_ids"].dtype == np.int64 and np.array_equal(inputs["input_ids"], ids[30:])
    assert np.array_equal(inputs["features"], features[30:])
    expected = (TensorSpec("input_ids", (12,), "int64"), TensorSpec("features", (5,), "float32"))
    assert data.data_inputs(info, "nchw") == expected
    assert tuple(data.describe(spec).values()) == expected


def test_classification_labels_are_class_ids_with_the_majority_baseline(tmp_path):
    y = np.array([0, 0, 0, 1, 2, 0, 0, 1] * 5)  # training split (first half): class 0 most common
    spec = npz_spec(tmp_path, "classification", x=np.zeros((40, 3), np.float32), y=y.astype(np.float64))
    directory, info = prepare(tmp_path, spec)
    assert info["classes"] == ["0", "1", "2"]
    assert info["majority_top1"] == pytest.approx(np.mean(y[30:] == 0))
    assert "mean_predictor_mse" not in info
    _, labels = data.load_split(directory, "test", spec.preprocess, "nhwc", limit=4)
    assert labels.dtype == np.int64 and labels.tolist() == y[30:34].tolist()


@pytest.mark.parametrize("y, culprit", [
    (np.eye(3)[np.arange(40) % 3], "has shape (40, 3); classification needs one class id per sample"),
    (np.arange(40) * 0.5, "sample 1 is 0.5; classification labels must be whole numbers"),
    (np.arange(40) - 2, "sample 0 is -2; classification labels must be class ids >= 0"),
])
def test_classification_labels_that_are_not_class_ids_are_refused(tmp_path, y, culprit):
    spec = npz_spec(tmp_path, "classification", x=np.zeros((40, 3), np.float32), y=y)
    refused(lambda: prepare(tmp_path, spec), str(spec.paths[0]), "labels", culprit)


def test_arrays_of_different_lengths_are_refused_naming_them(tmp_path):
    spec = npz_spec(tmp_path, "regression", ids=np.zeros((40, 4), np.int64),
                    mask=np.zeros((39, 4), np.int64), y=np.zeros(40))
    refused(lambda: prepare(tmp_path, spec), str(spec.paths[0]), "different numbers of samples",
            "'ids' 40, 'mask' 39, 'y' 40")


def test_layout_and_normalisation_apply_to_images_only(tmp_path):
    rng = np.random.default_rng(1)
    images, gray = rng.integers(0, 256, (20, 4, 6, 3), dtype=np.uint8), np.full((20, 5, 5), 51, np.uint8)
    features = rng.random((20, 3)).astype(np.float32)
    spec = npz_spec(tmp_path, "regression", x=images, gray=gray, features=features, y=np.ones((20, 2)))
    pre = Preprocess(scale=1 / 255, mean=(0.5,), std=(0.25,))
    spec = DatasetSpec(kind="npz", paths=spec.paths, split=SPLIT, preprocess=pre)
    directory, info = prepare(tmp_path, spec)
    assert [i["image"] for i in info["inputs"]] == [True, True, False] and "scale" not in info["inputs"][2]
    inputs, labels = data.load_split(directory, "train", pre, "nchw")
    expected = (images[:10].astype(np.float32) / 255 - 0.5) / 0.25
    np.testing.assert_allclose(inputs["x"], expected.transpose(0, 3, 1, 2), atol=1e-6)
    assert inputs["gray"].shape == (10, 1, 5, 5) and np.allclose(inputs["gray"], (0.2 - 0.5) / 0.25)
    assert np.array_equal(inputs["features"], features[:10])  # neither scaled nor normalised
    assert labels.shape == (10, 2) and labels.dtype == np.float32
    seen = data.data_inputs(info, "nchw")
    assert seen[0] == TensorSpec("x", (3, 4, 6), "float32") and seen[1] == TensorSpec("gray", (1, 5, 5))
    assert tuple(data.describe(spec, "nchw").values()) == seen


def test_image_preprocessing_without_an_image_input_is_refused(tmp_path):
    spec = npz_spec(tmp_path, "none", features=np.zeros((20, 3), np.float32))
    spec = DatasetSpec(kind="npz", paths=spec.paths, task="none",
                       preprocess=Preprocess(mean=(0.5,), std=(1.0,)))
    refused(lambda: prepare(tmp_path, spec), "dataset.preprocess.mean applies to images",
            "its inputs: features")


def banded(height: int, width: int, portrait: bool) -> np.ndarray:
    """A green image with red bands on its long sides' ends (a sixth of the long side each)."""
    image = np.zeros((height, width, 3), np.uint8)
    image[:] = GREEN
    band = (height if portrait else width) // 6
    if portrait:
        image[:band], image[-band:] = RED, RED
    else:
        image[:, :band], image[:, -band:] = RED, RED
    return image


def class_folder(root: Path, sizes: dict[str, list[tuple[int, int]]]) -> Path:
    for name, shapes in sizes.items():
        (root / name).mkdir(parents=True)
        for i, (h, w) in enumerate(shapes):
            Image.fromarray(banded(h, w, portrait=h > w)).save(root / name / f"{i}.png")
    return root


def test_image_class_folders_resize_the_shorter_side_and_crop_the_centre(tmp_path):
    root = class_folder(tmp_path / "imgs", {"cat": [(40, 60)] * 3, "bird": [(60, 40)] * 3,
                                            "dog": [(30, 45), (45, 30), (90, 60)]})
    (root / "cat" / "notes.txt").write_text("not an image")
    (root / ".cache").mkdir()
    pre = Preprocess(resize_shorter=20, center_crop=(20, 20), scale=1.0)
    spec = DatasetSpec(kind="images", paths=(root,), task="classification", preprocess=pre,
                       split=SplitSpec(train=0.34, calibration=0.33, test=0.33, by="random"))
    directory, info = prepare(tmp_path, spec)
    assert info["classes"] == ["bird", "cat", "dog"] and sum(info["counts"].values()) == 9
    assert info["inputs"] == [{"name": "x", "shape": [20, 20, 3], "dtype": "uint8", "image": True,
                               "range": [0.0, 255.0], "scale": 1.0}]
    for split in ("train", "calibration", "test"):
        inputs, labels = data.load_split(directory, split, pre, "nhwc")
        assert labels.dtype == np.int64 and set(labels.tolist()) <= {0, 1, 2}
        assert (inputs["x"][..., 1] > 200).all() and (inputs["x"][..., 0] < 60).all()  # the centre: green
    assert data.describe(spec, "nchw") == {"x": TensorSpec("x", (3, 20, 20), "float32")}


def test_image_class_folders_of_differing_sizes_need_resizing(tmp_path):
    root = class_folder(tmp_path / "imgs", {"a": [(16, 16)], "b": [(16, 16), (20, 24)]})
    spec = DatasetSpec(kind="images", paths=(root,), task="classification")
    refused(lambda: prepare(tmp_path, spec), f"{root / 'b' / '1.png'} is 24×20",
            f"({root / 'a' / '0.png'}) is 16×16", "resize_shorter with center_crop")
    small = DatasetSpec(kind="images", paths=(root,), task="classification",
                        preprocess=Preprocess(center_crop=(18, 18)))
    refused(lambda: prepare(tmp_path, small), "center_crop [18, 18] (height, width) is larger than a 16×16")
    regression = DatasetSpec(kind="images", paths=(root,), task="regression",
                             preprocess=Preprocess(resize=(8, 8)))
    refused(lambda: prepare(tmp_path, regression), "is labelled by class (a, b); use task: classification")


def test_synthetic_inputs_are_drawn_by_seed_for_the_models_inputs(tmp_path):
    specs = (TensorSpec("image", (3, 8, 8)), TensorSpec("ids", (None,), "int64", (0, 50)))
    spec = DatasetSpec(kind="synthetic", task="none", samples=16, seed=3)
    directory, info = prepare(tmp_path, spec, specs)
    again, _ = data.prepare(spec, Workspace(tmp_path / "other"), specs)
    other, _ = prepare(tmp_path, DatasetSpec(kind="synthetic", task="none", samples=16, seed=4), specs)
    first, labels = data.load_split(directory, "train", Preprocess(), "nhwc")
    assert labels is None and not any(i["image"] for i in info["inputs"])  # already in the model's layout
    assert first["image"].shape == (info["counts"]["train"], 3, 8, 8) and first["ids"].dtype == np.int64
    assert 0 <= first["ids"].min() and first["ids"].max() < 50
    same = data.load_split(again, "train", Preprocess(), "nhwc")[0]
    assert all(np.array_equal(first[k], same[k]) for k in first)
    drawn_otherwise = data.load_split(other, "train", Preprocess(), "nhwc")[0]
    assert not np.array_equal(first["image"], drawn_otherwise["image"])
    assert data.describe(spec) is None
    refused(lambda: prepare(tmp_path, spec), "synthetic inputs are drawn for the model's inputs")
    labelled = DatasetSpec(kind="synthetic", task="regression", samples=16)
    refused(lambda: prepare(tmp_path, labelled, specs), "has no labels, which task regression needs")


def test_builtin_driving_bends_has_five_bend_classes(tmp_path):
    spec = DatasetSpec(kind="builtin", builtin="driving_bends", task="classification", samples=60,
                       circuits=3, preprocess=Preprocess(resize=(33, 100)))
    directory, info = prepare(tmp_path, spec)
    assert info["classes"] == ["sharp_left", "left", "straight", "right", "sharp_right"]
    assert info["split_by"] == "group" and 0 <= info["majority_top1"] <= 1
    inputs, labels = data.load_split(directory, "test", spec.preprocess, "nchw")
    assert inputs["x"].shape[1:] == (3, 33, 100) and labels.dtype == np.int64 and labels.max() <= 4
    stored = np.load(directory / "test__x.npy").transpose(0, 3, 1, 2)  # uint8 pixels, divided by 255 as ever
    assert info["inputs"][0]["scale"] == 1 / 255 and np.array_equal(inputs["x"], stored * np.float32(1 / 255))
    assert data.describe(spec, "nchw") == {"x": TensorSpec("x", (3, 33, 100), "float32")}
    wrong = DatasetSpec(kind="builtin", builtin="driving", task="classification", samples=60, circuits=3)
    refused(lambda: prepare(tmp_path, wrong), "labelled for regression", "use builtin: driving_bends")


def test_odd_input_names_are_cached_and_fingerprints_ignore_where_files_lie(tmp_path):
    spec = npz_spec(tmp_path, "none", **{"input:0": np.arange(20.0).reshape(20, 1)})
    directory, _ = prepare(tmp_path, spec)
    assert (directory / "train__input%3a0.npy").is_file()
    test = data.load_split(directory, "test", Preprocess(), "nhwc")[0]
    assert test["input:0"].ravel().tolist() == [15, 16, 17, 18, 19]
    before = data.fingerprint(spec)
    (tmp_path / "moved").mkdir()
    moved = DatasetSpec(kind="npz", paths=(spec.paths[0].rename(tmp_path / "moved" / "d.npz"),), task="none",
                        split=SPLIT)
    assert data.fingerprint(moved) == before == directory.name


# the default scale, 1/255, is for pixels 0..255 only


def images_spec(tmp_path: Path, x: np.ndarray, preprocess: Preprocess = Preprocess()) -> DatasetSpec:
    spec = npz_spec(tmp_path, "none", x=x)
    return DatasetSpec(kind="npz", paths=spec.paths, task="none", split=SPLIT, preprocess=preprocess)


def train_images(tmp_path: Path, spec: DatasetSpec) -> tuple[np.ndarray, dict]:
    directory, info = prepare(tmp_path, spec)
    return data.load_split(directory, "train", spec.preprocess, "nhwc")[0]["x"], info["inputs"][0]


RNG = np.random.default_rng(5)
UNIT = RNG.random((8, 4, 4, 3)).astype(np.float32)  # float images already in [0, 1]
PIXELS = {"uint8": RNG.integers(0, 256, (8, 4, 4, 3)).astype(np.uint8),
          "int64": RNG.integers(0, 256, (8, 4, 4, 3)), "float32 0..255": UNIT * 255}
SCALED = {"float32 [0, 1]": (UNIT, "already in [0, 1]"),
          "float32 [-1, 1]": (UNIT * 2 - 1, "negative values"),
          "float64 standardised": ((UNIT.astype(np.float64) - 0.5) / 0.29, "negative values"),
          "uint16": ((UNIT * 4095).astype(np.uint16), "beyond 255"),
          "bool": (UNIT > 0.5, "already in [0, 1]")}


@pytest.mark.parametrize("images", PIXELS.values(), ids=PIXELS)
def test_the_default_scale_divides_pixels_0_to_255(tmp_path, images):
    x, info = train_images(tmp_path, images_spec(tmp_path, images))
    np.testing.assert_allclose(x, images[:4].astype(np.float32) / 255, rtol=1e-6)
    assert info["scale"] == pytest.approx(1 / 255)
    assert info["range"] == [float(images.min()), float(images.max())]


@pytest.mark.parametrize("images, why", SCALED.values(), ids=SCALED)
def test_images_outside_0_to_255_need_a_scale_given(tmp_path, images, why):
    spec = images_spec(tmp_path, images)
    low, high = float(images.min()), float(images.max())
    refused(lambda: prepare(tmp_path, spec), f"{spec.paths[0]}: input 'x' holds {images.dtype} images",
            f"values {low:.4g} to {high:.4g}", why, "set dataset.preprocess.scale")
    assert not (tmp_path / "ws" / "cache" / "datasets").exists()  # nothing cached
    x, info = train_images(tmp_path, images_spec(tmp_path, images, Preprocess(scale=1.0)))
    np.testing.assert_array_equal(x, images[:4].astype(np.float32))
    assert info["scale"] == 1.0 and info["range"] == [low, high]


def test_a_scale_given_is_honoured_whatever_the_values(tmp_path):
    pixels = PIXELS["uint8"]
    x, _ = train_images(tmp_path, images_spec(tmp_path, pixels, Preprocess(scale=1.0)))
    np.testing.assert_array_equal(x, pixels[:4].astype(np.float32))  # uint8 kept 0..255 when asked
    given = Preprocess(scale=1 / 255, mean=(0.5,), std=(0.25,))  # 1/255 given, on [0, 1] data: as asked
    x, info = train_images(tmp_path, images_spec(tmp_path, UNIT, given))
    np.testing.assert_allclose(x, (UNIT[:4] / 255 - 0.5) / 0.25, rtol=1e-6)
    assert info["scale"] == pytest.approx(1 / 255)
