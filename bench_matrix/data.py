"""Datasets: read (built-in, .npz, DeepLearningStudio folders), preprocess once, split disjointly, cache."""

from __future__ import annotations

import csv
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import DatasetSpec, Preprocess
from bench_matrix.workspace import Workspace, digest, tree_sha256

SPLITS = ("train", "calibration", "test")
IMAGE_SUFFIXES = ("", ".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class Raw:
    """Images after crop/resize (N,H,W,C), raw labels (N,K), optional group per sample."""

    images: np.ndarray
    labels: np.ndarray
    groups: np.ndarray | None
    columns: tuple[str, ...]


def fingerprint(spec: DatasetSpec) -> str:
    """Content hash of the dataset: its declaration plus the bytes of its files."""
    content = tree_sha256(list(spec.paths)) if spec.paths else "builtin"
    return digest({"spec": asdict(spec), "content": content, "format": 1})


def prepare(spec: DatasetSpec, workspace: Workspace) -> tuple[Path, dict[str, Any]]:
    """Build (or reuse) the cached splits; return their directory and summary info."""
    out = workspace.datasets(fingerprint(spec))
    if (out / "info.json").is_file():
        return out, json.loads((out / "info.json").read_text())
    raw = _read(spec)
    y = _normalise(raw.labels, spec)
    index = assign_splits(len(y), raw.groups, spec.split, spec.seed)
    out.mkdir(parents=True, exist_ok=True)
    for name, idx in index.items():
        np.save(out / f"{name}_x.npy", raw.images[idx])
        np.save(out / f"{name}_y.npy", y[idx])
    train_mean = y[index["train"]].mean(axis=0)
    test_y = y[index["test"]]
    info = {
        "fingerprint": out.name, "kind": spec.kind, "sample_shape": list(raw.images.shape[1:]),
        "label_columns": list(raw.columns), "counts": {k: int(len(v)) for k, v in index.items()},
        "split_by": _split_method(raw.groups, spec.split.by),
        "groups": {k: sorted({int(g) for g in raw.groups[v]}) for k, v in index.items()} if raw.groups is not None else None,
        "train_label_mean": train_mean.tolist(),
        "mean_predictor_mse": float(np.mean((test_y - train_mean) ** 2)),
    }
    tmp = out / "info.json.tmp"
    tmp.write_text(json.dumps(info, indent=1))
    os.replace(tmp, out / "info.json")
    return out, info


def load_split(directory: Path, split: str, preprocess: Preprocess, layout: str,
               limit: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A split as float32 model input in `layout` and its normalised labels."""
    x = np.load(directory / f"{split}_x.npy", mmap_mode="r")[:limit]
    y = np.load(directory / f"{split}_y.npy")[:limit]
    return to_model_input(np.asarray(x), preprocess, layout), y


def to_model_input(images: np.ndarray, preprocess: Preprocess, layout: str) -> np.ndarray:
    """Scale and normalise (N,H,W,C) images, then lay them out as the model expects."""
    x = images.astype(np.float32) * np.float32(preprocess.scale)
    if preprocess.mean is not None:
        x = (x - np.asarray(preprocess.mean, np.float32)) / np.asarray(preprocess.std, np.float32)
    if layout == "nchw":
        x = x.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(x)


def geometric(image: np.ndarray, preprocess: Preprocess) -> np.ndarray:
    """Crop then resize one (H,W,C) image; the same function serves every split."""
    if preprocess.crop is not None:
        top, bottom, left, right = preprocess.crop
        image = image[top:bottom, left:right]
    if preprocess.resize is not None and tuple(image.shape[:2]) != tuple(preprocess.resize):
        from PIL import Image

        h, w = preprocess.resize
        if image.dtype == np.uint8:
            image = np.asarray(Image.fromarray(image).resize((w, h), Image.BILINEAR))
        else:
            image = np.stack([np.asarray(Image.fromarray(image[..., c].astype(np.float32), mode="F")
                                         .resize((w, h), Image.BILINEAR)) for c in range(image.shape[2])], -1)
    return image


def assign_splits(n: int, groups: np.ndarray | None, split: Any, seed: int) -> dict[str, np.ndarray]:
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
        raise UserError(f"dataset: {n} samples are too few for the split fractions "
                        f"{fractions.tolist()}: every split needs at least one sample")
    return {name: np.sort(p) for name, p in zip(SPLITS, parts)}


def _split_method(groups: np.ndarray | None, by: str) -> str:
    count = 0 if groups is None else len(np.unique(groups))
    if by == "auto":
        return "group" if count >= 3 else "block"
    if by == "group" and count < 3:
        raise UserError(f"dataset.split.by: 'group' needs at least 3 groups (circuits, recordings or an npz "
                        f"'groups' array); this dataset has {count}. Use by: block or by: random")
    return by


def _normalise(labels: np.ndarray, spec: DatasetSpec) -> np.ndarray:
    y = labels.astype(np.float32)
    if spec.labels.offset is not None:
        y = y - np.asarray(spec.labels.offset, np.float32)
    if spec.labels.scale is not None:
        y = y / np.asarray(spec.labels.scale, np.float32)
    return y


def _read(spec: DatasetSpec) -> Raw:
    if spec.kind == "builtin":
        from bench_matrix.workload.driving import generate

        data = generate(spec.samples, seed=spec.seed, n_circuits=spec.circuits)
        images, labels, groups, columns = data.images, data.labels, data.groups, ("v", "w")
    elif spec.kind == "npz":
        images, labels, groups, columns = _read_npz(spec.paths[0], spec.labels.columns)
    else:
        images, labels, groups, columns = _read_folders(spec.paths, spec.labels.columns, spec.preprocess)
        return Raw(images, labels, groups, columns)  # folders are cropped/resized while reading
    if images.ndim == 3:
        images = images[..., None]
    if spec.preprocess.crop is not None or spec.preprocess.resize is not None:
        images = np.stack([geometric(img, spec.preprocess) for img in images])
    return Raw(images, labels, groups, columns)


def _read_npz(path: Path, columns: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, tuple]:
    try:
        archive = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read as .npz: {exc}") from None
    missing = [k for k in ("x", "y") if k not in archive.files]
    if missing:
        raise UserError(f"{path}: missing array(s) {', '.join(missing)}; an .npz dataset needs 'x' (N,H,W[,C] "
                        f"images) and 'y' (N[,K] labels), optionally 'groups' (N,); it has: {', '.join(archive.files)}")
    x, y = archive["x"], archive["y"]
    y = y.reshape(len(y), -1)
    if len(x) != len(y) or x.ndim not in (3, 4):
        raise UserError(f"{path}: 'x' must be (N,H,W) or (N,H,W,C) and 'y' must have N rows; "
                        f"got x {x.shape}, y {y.shape}")
    groups = archive["groups"] if "groups" in archive.files else None
    names = columns if len(columns) == y.shape[1] else tuple(f"y{i}" for i in range(y.shape[1]))
    return x, y, groups, names


def _read_folders(folders: tuple[Path, ...], columns: tuple[str, ...],
                  preprocess: Preprocess) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple]:
    from PIL import Image

    images, labels, groups = [], [], []
    for g, folder in enumerate(folders):
        with open(folder / "data.csv", newline="") as f:
            reader = csv.DictReader(f)
            absent = [c for c in ("image_name", *columns) if c not in (reader.fieldnames or [])]
            if absent:
                raise UserError(f"{folder / 'data.csv'}: missing column(s) {', '.join(absent)}; "
                                f"header is {', '.join(reader.fieldnames or [])}")
            for line, row in enumerate(reader, start=2):
                image = _find_image(folder, row["image_name"])
                if image is None:
                    raise UserError(f"{folder / 'data.csv'}:{line}: image '{row['image_name']}' not found in {folder}")
                try:
                    labels.append([float(row[c]) for c in columns])
                except ValueError:
                    raise UserError(f"{folder / 'data.csv'}:{line}: label columns {', '.join(columns)} "
                                    f"must be numbers") from None
                with Image.open(image) as im:
                    images.append(geometric(np.asarray(im.convert("RGB")), preprocess))
                groups.append(g)
    if not images:
        raise UserError(f"{', '.join(map(str, folders))}: data.csv lists no images")
    return np.stack(images), np.asarray(labels, np.float32), np.asarray(groups, np.int32), columns


def _find_image(folder: Path, name: str) -> Path | None:
    return next((folder / (name + s) for s in IMAGE_SUFFIXES if (folder / (name + s)).is_file()), None)
