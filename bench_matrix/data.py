"""Datasets: read (built-in, .npz, DeepLearningStudio folders), preprocess once, split disjointly, cache."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.data_readers import read_folders, read_npz, refuse_non_finite, require_file
from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import DatasetSpec, Preprocess
from bench_matrix.workspace import Workspace, digest, tree_sha256

SPLITS = ("train", "calibration", "test")
CROP_SIDES = ("top", "bottom", "left", "right")


@dataclass(frozen=True)
class Raw:
    """Images after crop/resize (N,H,W,C), raw labels (N,K), optional group per sample."""

    images: np.ndarray
    labels: np.ndarray
    groups: np.ndarray | None
    columns: tuple[str, ...]


def fingerprint(spec: DatasetSpec) -> str:
    """Content hash of the dataset: its declaration plus the bytes of its files."""
    if spec.kind == "npz":
        require_file(spec.paths[0], "an .npz archive")  # never open a pipe or a directory to hash it
    try:
        content = tree_sha256(list(spec.paths)) if spec.paths else "builtin"
    except OSError as exc:
        raise UserError(f"{exc.filename or source(spec)}: cannot be read ({exc.strerror or exc}); "
                        f"every dataset file must be readable") from None
    return digest({"spec": asdict(spec), "content": content, "format": 1})


def source(spec: DatasetSpec) -> str:
    """The user's dataset as named in messages: its file or folders."""
    return ", ".join(map(str, spec.paths)) or f"the builtin dataset ({spec.samples} samples)"


def prepare(spec: DatasetSpec, workspace: Workspace) -> tuple[Path, dict[str, Any]]:
    """Build (or reuse) the cached splits; return their directory and summary info."""
    out = workspace.datasets(fingerprint(spec))
    if (out / "info.json").is_file():
        return out, json.loads((out / "info.json").read_text())
    raw = _read(spec)
    _check_channels(spec.preprocess, raw.images.shape[-1], source(spec))
    y = _normalise(raw.labels, raw.columns, spec)
    index = assign_splits(len(y), raw.groups, spec.split, spec.seed, source(spec))
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
        "groups": ({k: sorted({int(g) for g in raw.groups[v]}) for k, v in index.items()}
                   if raw.groups is not None else None),
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
        cropped = image[top:bottom, left:right]
        if 0 in cropped.shape[:2]:
            bounds = ", ".join(f"{side}: {value}" for side, value in zip(CROP_SIDES, preprocess.crop)
                               if value is not None)
            raise UserError(f"dataset.preprocess.crop {{{bounds}}} leaves no pixels of a {image.shape[1]}×"
                            f"{image.shape[0]} image (width×height); crop bounds are row and column indices")
        image = cropped
    if preprocess.resize is not None and tuple(image.shape[:2]) != tuple(preprocess.resize):
        from PIL import Image

        h, w = preprocess.resize
        mode, dtype = ("L", np.uint8) if image.dtype == np.uint8 else ("F", np.float32)
        image = np.stack([np.asarray(Image.fromarray(image[..., c].astype(dtype), mode=mode)
                                     .resize((w, h), Image.BILINEAR)) for c in range(image.shape[2])], -1)
    return image


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


def _check_channels(preprocess: Preprocess, channels: int, where: str) -> None:
    """Refuse a per-channel mean or std whose length is neither 1 nor the images' channel count."""
    for key in ("mean", "std"):
        values = getattr(preprocess, key)
        if values is not None and len(values) not in (1, channels):
            raise UserError(f"dataset.preprocess.{key} has {len(values)} values, but the images of {where} "
                            f"have {channels} channel(s); give one value or one per channel")


def _normalise(labels: np.ndarray, columns: tuple[str, ...], spec: DatasetSpec) -> np.ndarray:
    """y' = (y - offset) / scale, after checking offset and scale fit the label columns."""
    y = labels.astype(np.float32)
    for key in ("offset", "scale"):
        values = getattr(spec.labels, key)
        if values is not None and len(values) not in (1, y.shape[1]):
            raise UserError(f"dataset.labels.{key} has {len(values)} values, but {source(spec)} has "
                            f"{y.shape[1]} label column(s) ({', '.join(columns)}); give one value or one "
                            f"per column")
    if spec.labels.offset is not None:
        y = y - np.asarray(spec.labels.offset, np.float32)
    if spec.labels.scale is not None:
        y = y / np.asarray(spec.labels.scale, np.float32)
    refuse_non_finite(y, f"{source(spec)}: labels after dataset.labels offset and scale", "sample")
    return y


def _read(spec: DatasetSpec) -> Raw:
    if spec.kind == "builtin":
        from bench_matrix.workload.driving import generate

        data = generate(spec.samples, seed=spec.seed, n_circuits=spec.circuits)
        images, labels, groups, columns = data.images, data.labels, data.groups, ("v", "w")
    elif spec.kind == "npz":
        images, labels, groups, columns = read_npz(spec.paths[0], spec.labels.columns)
    else:
        images, labels, groups = read_folders(spec.paths, spec.labels.columns,
                                              lambda image: geometric(image, spec.preprocess))
        return Raw(images, labels, groups, spec.labels.columns)  # folders are cropped/resized while reading
    if images.ndim == 3:
        images = images[..., None]
    if spec.preprocess.crop is not None or spec.preprocess.resize is not None:
        images = np.stack([geometric(img, spec.preprocess) for img in images])
    return Raw(images, labels, groups, columns)
