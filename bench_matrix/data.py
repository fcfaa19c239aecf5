"""Datasets: read (built-in, .npz, DeepLearningStudio folders, image class folders, synthetic inputs),
preprocess once, split disjointly, cache one array per split and input."""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.data_readers import GROUPS, LABELS, class_ids, npz_headers, read_npz, refuse_non_finite, \
    require_file
from bench_matrix.errors import UserError
from bench_matrix.image_readers import first_class_image_size, read_class_folders, read_folders
from bench_matrix.images import (GEOMETRIC, check_preprocess, geometric, geometric_shape, in_layout,
                                 pixel_scale, to_model_input, value_range)
from bench_matrix.matrix.spec import DatasetSpec, LabelSpec, Preprocess
from bench_matrix.tensors import SINGLE, Inputs, TensorSpec, count, data_names, random_inputs, shape_fits, \
    specs_to_list
from bench_matrix.sources.code import module_file
from bench_matrix.workload.driving import defaults
from bench_matrix.workspace import Workspace, digest, tree_sha256

SPLITS = ("train", "calibration", "test")
FORMAT = 2  # of the cache: {split}__{input}.npy per input, {split}__y.npy, info.json


@dataclass(frozen=True)
class Raw:
    """Model inputs as stored (images (N,H,W,C) after geometric preprocessing), labels as read, groups,
    which inputs are images, and the names of the label columns (regression) or classes."""

    inputs: dict[str, np.ndarray]
    labels: np.ndarray | None
    groups: np.ndarray | None
    images: tuple[str, ...] = ()
    columns: tuple[str, ...] = ()
    classes: tuple[str, ...] = ()


def fingerprint(spec: DatasetSpec, inputs: Sequence[TensorSpec] | None = None,
                as_is: Sequence[str] = ()) -> str:
    """Content hash of the dataset: its declaration (paths aside) plus the bytes of its files; for synthetic
    data, the inputs drawn; the arrays passed as they are. A moved checkout keeps its cache."""
    if spec.kind == "npz":
        require_file(spec.paths[0], "an .npz archive")  # never open a pipe or a directory to hash it
    try:
        content = tree_sha256(list(spec.paths)) if spec.paths else _generator(spec)
    except OSError as exc:
        raise UserError(f"{exc.filename or source(spec)}: cannot be read ({exc.strerror or exc}); "
                        f"every dataset file must be readable") from None
    drawn = specs_to_list(inputs or ()) if spec.kind == "synthetic" else None
    return digest({"spec": {**asdict(spec), "paths": None}, "content": content, "inputs": drawn,
                   "format": FORMAT, **({"as_is": sorted(as_is)} if as_is else {})})


def _generator(spec: DatasetSpec) -> str:
    """What draws data no file holds: the built-in workload's code (its Python files), or the kind's name."""
    if spec.kind != "builtin":
        return spec.kind
    package = module_file("bench_matrix.workload.driving")
    return tree_sha256(sorted(package.parent.glob("*.py"))) if package else spec.kind


def source(spec: DatasetSpec) -> str:
    """The user's dataset as named in messages: its file or folders."""
    if spec.kind == "synthetic":
        return f"the synthetic inputs ({spec.samples} samples)"
    return ", ".join(map(str, spec.paths)) or f"the builtin dataset {spec.builtin} ({spec.samples} samples)"


def prepare(spec: DatasetSpec, workspace: Workspace, inputs: Sequence[TensorSpec] | None = None,
            as_is: Sequence[str] = ()) -> tuple[Path, dict[str, Any]]:
    """Build (or reuse) the cached splits; return their directory and summary info. `inputs`: the model's
    inputs, which synthetic data is drawn for; `as_is`: arrays passed as they are (model_shaped)."""
    out = workspace.datasets(fingerprint(spec, inputs, as_is))
    if (out / "info.json").is_file():
        return out, json.loads((out / "info.json").read_text())
    raw = _read(spec, inputs, as_is)
    ranges, labels = _checked(raw, spec, as_is)
    index = assign_splits(count(raw.inputs), raw.groups, spec.split, spec.seed, source(spec))
    building = workspace.partial(out)  # this process's, renamed when complete
    building.mkdir()
    for split, rows in index.items():
        for name, array in raw.inputs.items():
            np.save(building / split_file(split, name), array[rows])
        if labels is not None:
            np.save(building / split_file(split, LABELS), labels[rows])
    info = {
        "fingerprint": out.name, "format": FORMAT, "kind": spec.kind, "task": spec.task,
        "inputs": [_input_info(name, a, ranges, spec.preprocess) for name, a in raw.inputs.items()],
        "counts": {k: int(len(v)) for k, v in index.items()},
        "split_by": _split_method(raw.groups, spec.split.by),
        "groups": ({k: sorted({int(g) for g in raw.groups[v]}) for k, v in index.items()}
                   if raw.groups is not None else None),
        **_label_info(labels, index, raw, spec.task),
    }
    (building / "info.json").write_text(json.dumps(info, indent=1))
    _publish(building, out)
    return out, info


def _input_info(name: str, array: np.ndarray, ranges: dict[str, tuple[float, float]],
                preprocess: Preprocess) -> dict[str, Any]:
    """An input as cached: its name, per-sample shape and dtype; for an image, its values' range and the
    scale they are multiplied by when loaded."""
    info = {"name": name, "shape": list(array.shape[1:]), "dtype": str(array.dtype), "image": name in ranges}
    if name in ranges:
        info.update(range=list(ranges[name]), scale=pixel_scale(preprocess))
    return info


def read_problem(spec: DatasetSpec, as_is: Sequence[str] = ()) -> str | None:
    """Why `prepare` would refuse an .npz dataset (its arrays, labels, image preprocessing), or None: the same
    checks, made at plan time."""
    if spec.kind != "npz":
        return None
    try:
        _checked(_read(spec, None, as_is), spec, as_is)
    except UserError as exc:
        return str(exc)
    return None


def _checked(raw: Raw, spec: DatasetSpec, as_is: Sequence[str]) -> tuple[dict, np.ndarray | None]:
    """The value range of each image input, after refusing preprocessing that does not fit; the labels."""
    ranges = {name: value_range(raw.inputs[name]) for name in raw.images}
    check_preprocess(spec.preprocess, raw.inputs, ranges, source(spec), as_is)
    return ranges, _labels(raw, spec)


def _publish(building: Path, out: Path) -> None:
    """Rename a complete cache folder into place; when another run published the same one first, keep
    theirs (same fingerprint, same content): nobody ever reads a folder while it is written."""
    if out.is_dir() and not (out / "info.json").is_file():
        shutil.rmtree(out, ignore_errors=True)  # left half-written by an older release or a crash
    try:
        building.rename(out)
    except OSError:
        if not (out / "info.json").is_file():
            raise
        shutil.rmtree(building, ignore_errors=True)


def measured(name: str) -> bool:
    """Whether a file of a prepared dataset's folder is read when measuring: its info and the test split's
    (what travels to a device), not the training or calibration splits."""
    return not name.startswith(tuple(f"{split}__" for split in SPLITS if split != "test"))


def split_file(split: str, name: str) -> str:
    """The cache file of one input (or the labels, `y`) of a split; odd characters of a name %-escaped."""
    safe = "".join(c if c.isascii() and (c.isalnum() or c in "_.-") else f"%{ord(c):02x}" for c in name)
    return f"{split}__{safe}.npy"


def load_split(directory: Path, split: str, preprocess: Preprocess, layout: str,
               limit: int | None = None) -> tuple[Inputs, np.ndarray | None]:
    """A split's inputs as the model takes them (images scaled, normalised, in `layout`; other inputs as
    stored) and its labels: regression float32 (N, K), classification int64 (N,), or None without labels."""
    info = json.loads((directory / "info.json").read_text())
    inputs: Inputs = {}
    for item in info["inputs"]:
        stored = np.load(directory / split_file(split, item["name"]), mmap_mode="r")[:limit]
        image = item["image"]
        inputs[item["name"]] = to_model_input(stored, preprocess, layout) if image else np.array(stored)
    labels = np.load(directory / split_file(split, LABELS))[:limit] if info["task"] != "none" else None
    return inputs, labels


def data_inputs(info: dict[str, Any], layout: str) -> tuple[TensorSpec, ...]:
    """Each input of a prepared dataset as the model sees it: images float32 in `layout`, others as stored."""
    return tuple(TensorSpec(i["name"], in_layout(tuple(i["shape"]), layout), "float32") if i["image"]
                 else TensorSpec(i["name"], tuple(i["shape"]), i["dtype"]) for i in info["inputs"])


def describe(spec: DatasetSpec, layout: str = "nhwc",
             as_is: Sequence[str] = ()) -> dict[str, TensorSpec] | None:
    """The dataset's inputs as a model in `layout` sees them (`as_is`: arrays passed as they are), from
    headers only, to find mistakes at plan time; None where that needs the data read (folders, synthetic)."""
    stored = _stored(spec)
    if stored is None:
        return None
    return {name: TensorSpec(name, shape, str(dtype)) if name in as_is else
            _as_seen(name, shape, dtype, spec.preprocess, layout) for name, (shape, dtype) in stored.items()}


def model_shaped(spec: DatasetSpec, inputs: Sequence[TensorSpec] | None, layout: str) -> tuple[str, ...]:
    """The float .npz arrays already in their model input's per-sample shape, which reading them as H×W×C
    images (and laying those out as `layout`) would change: they are passed to the model as they are."""
    if spec.kind != "npz" or not inputs:
        return ()
    stored = _stored(spec) or {}
    fed = {name: model.shape for name, model in zip(data_names(stored, inputs), inputs)}
    return tuple(name for name, (shape, dtype) in stored.items() if name in fed
                 and dtype.kind == "f" and _is_image(shape, dtype) and shape_fits(shape, fed[name])
                 and not shape_fits(_as_seen(name, shape, dtype, spec.preprocess, layout).shape, fed[name]))


def images_read(spec: DatasetSpec, as_is: Sequence[str] = ()) -> dict[str, tuple[int, ...]]:
    """The arrays read as H×W×C images, each with its per-sample shape as stored (for messages)."""
    stored = _stored(spec) or {}
    return {name: shape for name, (shape, dtype) in stored.items()
            if name not in as_is and _is_image(shape, dtype)}


def _stored(spec: DatasetSpec) -> dict[str, tuple[tuple[int, ...], np.dtype]] | None:
    """Each input's per-sample shape and dtype as stored, read cheaply; None for folders, synthetic data."""
    if spec.kind == "npz":
        return {name: (shape[1:], dtype) for name, (shape, dtype) in npz_headers(spec.paths[0]).items()
                if name not in (LABELS, GROUPS)}
    if spec.kind == "builtin":
        from bench_matrix.workload.driving import Camera

        return {SINGLE: ((Camera().rows, Camera().cols, 3), np.dtype(np.uint8))}
    if spec.kind == "images":
        return {SINGLE: ((*first_class_image_size(spec.paths[0]), 3), np.dtype(np.uint8))}
    return None


def _as_seen(name: str, shape: tuple[int, ...], dtype: np.dtype, preprocess: Preprocess,
             layout: str) -> TensorSpec:
    if not _is_image(shape, dtype):
        return TensorSpec(name, tuple(shape), str(dtype))
    h, w = geometric_shape(shape[:2], preprocess)
    return TensorSpec(name, in_layout((h, w, shape[2] if len(shape) == 3 else 1), layout), "float32")


def _is_image(sample_shape: tuple[int, ...], dtype: np.dtype) -> bool:
    """Images are (H, W, C) per sample, or (H, W) of uint8 (grayscale)."""
    return len(sample_shape) == 3 or (len(sample_shape) == 2 and dtype == np.uint8)


def _labels(raw: Raw, spec: DatasetSpec) -> np.ndarray | None:
    """The labels the task scores against: regression normalised float32 (N, K), class ids, or None."""
    if spec.task == "none":
        return None
    if raw.labels is None:
        raise UserError(f"{source(spec)}: has no labels, which task {spec.task} needs; use task: none")
    if spec.task == "classification":
        return class_ids(raw.labels, f"{source(spec)}: labels")
    if raw.classes:
        raise UserError(f"{source(spec)}: is labelled by class ({', '.join(raw.classes)}); use task: "
                        f"classification (or none)")
    with np.errstate(over="ignore"):  # a value beyond float32 becomes Inf, refused after normalising
        return _normalise(raw.labels.reshape(len(raw.labels), -1).astype(np.float32), raw.columns, spec)


def _label_info(labels: np.ndarray | None, index: dict[str, np.ndarray], raw: Raw,
                task: str) -> dict[str, Any]:
    """Regression: label columns and the mean predictor's test MSE; classification: class names and the
    test accuracy of always answering the training split's most common class."""
    if labels is None:
        return {}
    train, test = labels[index["train"]], labels[index["test"]]
    if task == "classification":
        classes = raw.classes or tuple(str(i) for i in range(int(labels.max()) + 1))
        majority = np.bincount(train).argmax()
        return {"classes": list(classes), "majority_top1": float(np.mean(test == majority))}
    k = labels.shape[1]
    columns = raw.columns if len(raw.columns) == k else tuple(f"y{i}" for i in range(k))
    mean = train.mean(axis=0)
    return {"label_columns": list(columns), "train_label_mean": mean.tolist(),
            "mean_predictor_mse": float(np.mean((test - mean) ** 2))}


def _normalise(labels: np.ndarray, columns: tuple[str, ...], spec: DatasetSpec) -> np.ndarray:
    """y' = (y - offset) / scale, after checking offset and scale fit the label columns."""
    y = labels
    for key in ("offset", "scale"):
        values = getattr(spec.labels, key)
        if values is not None and len(values) not in (1, y.shape[1]):
            named = f" ({', '.join(columns)})" if len(columns) == y.shape[1] else ""
            raise UserError(f"dataset.labels.{key} has {len(values)} values, but {source(spec)} has "
                            f"{y.shape[1]} label column(s){named}; give one value or one per column")
    if spec.labels.offset is not None:
        y = y - np.asarray(spec.labels.offset, np.float32)
    if spec.labels.scale is not None:
        y = y / np.asarray(spec.labels.scale, np.float32)
    refuse_non_finite(y, f"{source(spec)}: labels after dataset.labels offset and scale", "sample")
    return y


def denormalise(y: np.ndarray, labels: LabelSpec) -> np.ndarray:
    """Normalised labels (or a regression model's outputs) back in label units: y * scale + offset, the
    inverse of the dataset's `labels` normalisation."""
    if labels.scale is not None:
        y = y * np.asarray(labels.scale, np.float32)
    if labels.offset is not None:
        y = y + np.asarray(labels.offset, np.float32)
    return y


def _read(spec: DatasetSpec, inputs: Sequence[TensorSpec] | None, as_is: Sequence[str]) -> Raw:
    shape = partial(geometric, preprocess=spec.preprocess)  # the same for every split
    if spec.kind == "builtin":
        return _builtin(spec)
    if spec.kind == "npz":
        arrays = read_npz(spec.paths[0], spec.task)
        return _with_images(arrays.inputs, spec.preprocess, arrays.labels, arrays.groups, spec.labels.columns,
                            as_is)
    if spec.kind == "folder":
        images, labels, groups = read_folders(spec.paths, spec.labels.columns, shape)
        return Raw({SINGLE: images}, labels, groups, (SINGLE,), spec.labels.columns)
    if spec.kind == "images":
        images, labels, groups, classes = read_class_folders(spec.paths, shape)
        return Raw({SINGLE: images}, labels, groups, (SINGLE,), classes=classes)
    if not inputs:
        raise UserError("dataset: synthetic inputs are drawn for the model's inputs, which are not known; "
                        "declare the model's inputs (name, shape, dtype)")
    return Raw(random_inputs(inputs, spec.samples, spec.seed), None, None)


def _builtin(spec: DatasetSpec) -> Raw:
    """The rendered driving scenes, labelled (v, w) for regression or by bend class."""
    from bench_matrix.workload.driving import BEND_CLASSES, bend_classes, generate

    task = defaults.TASKS.get(spec.builtin)
    if task is None:
        raise UserError(f"dataset.builtin: '{spec.builtin}' is not a built-in dataset; choose one of "
                        f"{', '.join(defaults.TASKS)}")
    if spec.task not in (task, "none"):
        other = next(name for name, t in defaults.TASKS.items() if t == spec.task)
        raise UserError(f"dataset: the builtin dataset {spec.builtin} is labelled for {task}, not "
                        f"{spec.task}; use builtin: {other} (or task: {task} or none)")
    data = generate(spec.samples, seed=spec.seed, n_circuits=spec.circuits)
    labels, columns, classes = data.labels, ("v", "w"), ()
    if spec.builtin == "driving_bends":
        labels, columns, classes = bend_classes(data.labels[:, 1]), (), BEND_CLASSES
    raw = _with_images({SINGLE: data.images}, spec.preprocess, labels, data.groups, columns)
    return replace(raw, classes=classes)


def _with_images(arrays: dict[str, np.ndarray], preprocess: Preprocess, labels: np.ndarray | None,
                 groups: np.ndarray | None, columns: tuple[str, ...], as_is: Sequence[str] = ()) -> Raw:
    """Arrays of images (grayscale given a channel axis) cropped and resized; other arrays, and those in
    `as_is`, as given."""
    inputs, images = {}, []
    for name, array in arrays.items():
        if name not in as_is and _is_image(array.shape[1:], array.dtype):
            array = array if array.ndim == 4 else array[..., None]
            if any(getattr(preprocess, key) is not None for key in GEOMETRIC):
                array = np.stack([geometric(image, preprocess) for image in array])
            images.append(name)
        inputs[name] = array
    return Raw(inputs, labels, groups, tuple(images), columns)


def assign_splits(n: int, groups: np.ndarray | None, split: Any, seed: int,
                  where: str) -> dict[str, np.ndarray]:
    """Disjoint train/calibration/test indices: whole groups, contiguous blocks, or a seeded shuffle."""
    fractions = np.array([split.train, split.calibration, split.test])
    method = _split_method(groups, split.by)
    if method == "group":
        unique = np.unique(groups)
        order = np.random.default_rng(seed).permutation(unique)
        sizes = {g: int(np.sum(groups == g)) for g in unique}
        taken = np.zeros(3)
        chosen: list[list[int]] = [[], [], []]
        for i, g in enumerate(order):
            # each split gets one group first, then groups go to the split furthest below its share
            k = i if i < 3 else int(np.argmax(fractions * n - taken))
            chosen[k].append(g)
            taken[k] += sizes[g]
        return {name: np.flatnonzero(np.isin(groups, chosen[k])) for k, name in enumerate(SPLITS)}
    order = np.arange(n) if method == "block" else np.random.default_rng(seed).permutation(n)
    bounds = np.round(np.cumsum(fractions) * n).astype(int)
    parts = np.split(order, bounds[:2])
    if any(len(p) == 0 for p in parts):
        raise UserError(f"{where}: {n} samples are too few for the split fractions {fractions.tolist()}: "
                        f"every split needs at least one sample; add samples "
                        f"({_enough_samples(fractions, n)} would do) or change dataset.split")
    return {name: np.sort(p) for name, p in zip(SPLITS, parts)}


def _split_method(groups: np.ndarray | None, by: str) -> str:
    count = 0 if groups is None else len(np.unique(groups))
    if by == "auto":
        return "group" if count >= 3 else "block"
    if by == "group" and count < 3:
        raise UserError(f"dataset.split.by: 'group' needs at least 3 groups (circuits, recordings or an npz "
                        f"'groups' array); this dataset has {count}. Use by: block or by: random")
    return by


def _enough_samples(fractions: np.ndarray, n: int) -> int:
    """The next sample count above `n` for which every split gets one (1/smallest fraction always does)."""
    surely = int(np.ceil(1 / fractions.min()))
    ns = np.arange(n + 1, min(surely, n + 1_000_000) + 1)
    bounds = np.round(np.outer(ns, np.cumsum(fractions))).astype(int)
    enough = (np.diff(bounds, axis=1, prepend=0) > 0).all(axis=1)
    return int(ns[np.argmax(enough)]) if enough.any() else surely
