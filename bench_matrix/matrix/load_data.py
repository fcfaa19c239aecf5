"""The data sections of a matrix, validated: a dataset (the matrix's or a model's own), a model's inputs."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.matrix import paths
from bench_matrix.matrix.schema import DATASET_KINDS, MAX_SAMPLE_ELEMENTS
from bench_matrix.matrix.spec import DatasetSpec, LabelSpec, Preprocess, SplitSpec
from bench_matrix.matrix.yamlpos import Located
from bench_matrix.tensors import TensorSpec, concrete
from bench_matrix.workload.driving.defaults import SPEED_LABELS

DRIVING_LABELS = LabelSpec(**SPEED_LABELS)
CLASS_LABELS = LabelSpec(columns=("class",), offset=None, scale=None)  # one integer class id per sample
# What the labels of a data source are, and the tasks they allow, the default first (npz, folder: any task;
# regression by default).
LABELS_OF = {
    "driving": ("the builtin driving data, whose labels are [v, w] speeds", ("regression", "none")),
    "driving_bends": ("the builtin driving_bends data, whose labels are bend classes",
                      ("classification", "none")),
    "images": ("image folders, whose labels are their class subfolders", ("classification", "none")),
    "synthetic": ("synthetic data, which has no labels", ("none",)),
}
ONE_INPUT = {"builtin": "the builtin data", "images": "image folders", "folder": "DeepLearningStudio folders"}


def labels_source(spec: DatasetSpec) -> str:
    """What the dataset's labels come from: the builtin workload's name, else the dataset's kind."""
    return spec.builtin if spec.kind == "builtin" else spec.kind


def task_problem(task: str, spec: DatasetSpec) -> str | None:
    """Why `task` cannot be scored on the dataset's labels, or None."""
    what, allowed = LABELS_OF.get(labels_source(spec), ("", ()))
    if not allowed or task in allowed:
        return None
    return f"task '{task}' does not fit {what}; allowed: {', '.join(allowed)}"


def one_input_problem(spec: DatasetSpec, inputs: tuple[TensorSpec, ...]) -> str | None:
    """Why the dataset cannot feed these declared inputs (it holds one image per sample), or None."""
    if spec.kind not in ONE_INPUT or len(inputs) < 2:
        return None
    return (f"{ONE_INPUT[spec.kind]} feed one input, but the model declares {len(inputs)} "
            f"({', '.join(s.name for s in inputs)}); give an npz with one array per input, or synthetic data")


def dataset(base: Path, d: dict[str, Any], at: tuple, report: Located) -> DatasetSpec:
    """A dataset mapping (already schema-valid) at key path `at`, with its cross-key checks."""
    kind = next(k for k in DATASET_KINDS if k in d)
    builtin = d["builtin"] if kind == "builtin" else DatasetSpec.builtin
    _misplaced_keys(kind, builtin, d, at, report)
    samples = d["synthetic"]["samples"] if kind == "synthetic" else d.get("samples", DatasetSpec.samples)
    circuits = d.get("circuits", DatasetSpec.circuits)
    if kind == "builtin" and circuits > samples:
        report.add(at + ("circuits",), f"{circuits} circuits for {samples} samples: every circuit needs at "
                                       f"least one sample; lower circuits or raise samples")
    source = builtin if kind == "builtin" else kind
    task = d.get("task", "regression" if source not in LABELS_OF else LABELS_OF[source][1][0])
    spec = DatasetSpec(kind=kind, paths=_data_paths(base, kind, d, at, report), builtin=builtin, task=task,
                       samples=samples, circuits=circuits, seed=d.get("seed", DatasetSpec.seed),
                       preprocess=_preprocess(d.get("preprocess", {}), at + ("preprocess",), report),
                       labels=_labels(source, d.get("labels", {}), at + ("labels",), report),
                       split=_split(d.get("split", {}), at + ("split",), report))
    if problem := task_problem(task, spec):
        report.add(at + ("task",), problem)
    return spec


def _misplaced_keys(kind: str, builtin: str, d: dict[str, Any], at: tuple, report: Located) -> None:
    """Keys that are valid in the schema but mean nothing for this kind of dataset."""
    if kind != "builtin":
        for key in ("samples", "circuits"):
            if key in d:
                hint = " (synthetic data: synthetic: {samples: N})" if kind == "synthetic" else ""
                report.add(at + (key,), f"'{key}' only applies to the builtin dataset{hint}")
    if "labels" in d and (kind in ("images", "synthetic") or builtin == "driving_bends"):
        what = LABELS_OF[builtin if kind == "builtin" else kind][0]
        report.add(at + ("labels",), f"'labels' does not apply to {what}")
    if "preprocess" in d and kind == "synthetic":
        report.add(at + ("preprocess",), "'preprocess' does not apply to synthetic data: its inputs are "
                                         "drawn already in the model's shapes, dtypes and ranges")


def _data_paths(base: Path, kind: str, d: dict[str, Any], at: tuple, report: Located) -> tuple[Path, ...]:
    """The npz file or the folders, each checked: a regular .npz file; DeepLearningStudio folders holding a
    regular data.csv; image folders."""
    if kind in ("builtin", "synthetic"):
        return ()
    listed = isinstance(d[kind], list)
    located = []
    for j, text in enumerate(d[kind] if listed else [d[kind]]):
        where = at + (kind,) + ((j,) if listed else ())
        path, problem = paths.resolve(base, text)
        if path is not None:
            located.append(path)
            if kind == "npz":
                problem = paths.file_problem(path, "dataset file")
            elif kind == "images":
                problem = paths.dir_problem(path, "image folder")
            else:
                problem = paths.dir_problem(path, "dataset folder") or _csv_problem(path / "data.csv")
        if problem:
            report.add(where, problem)
    return tuple(located)


def _csv_problem(csv: Path) -> str | None:
    if paths.mode(csv) == (None, None):
        return f"{csv.parent} has no data.csv (expected header image_name,v,w,...)"
    return paths.file_problem(csv, "data.csv file")


def _labels(source: str, labels: dict[str, Any], at: tuple, report: Located) -> LabelSpec:
    default = {"driving": DRIVING_LABELS, "driving_bends": CLASS_LABELS, "images": CLASS_LABELS}.get(
        source, LabelSpec(offset=None, scale=None))
    spec = LabelSpec(columns=tuple(labels.get("columns", default.columns)),
                     offset=_tuple(labels.get("offset", default.offset)),
                     scale=_tuple(labels.get("scale", default.scale)))
    for key in ("offset", "scale"):
        value = getattr(spec, key)
        if value is not None and source != "npz" and len(value) not in (1, len(spec.columns)):
            report.add(at + (key,), f"has {len(value)} values for {len(spec.columns)} label columns")
    return spec


def _split(split: dict[str, Any], at: tuple, report: Located) -> SplitSpec:
    fractions = {k: split.get(k, getattr(SplitSpec, k)) for k in ("train", "calibration", "test")}
    total = sum(fractions.values())
    if abs(total - 1.0) > 1e-6:
        report.add(at, f"train + calibration + test must add up to 1, got "
                       f"{' + '.join(f'{v:g}' for v in fractions.values())} = {total:g}")
    return SplitSpec(**fractions, by=split.get("by", "auto"))


def _preprocess(pre: dict[str, Any], at: tuple, report: Located) -> Preprocess:
    crop, mean, std = pre.get("crop"), _tuple(pre.get("mean")), _tuple(pre.get("std"))
    if (mean is None) != (std is None):
        report.add(at, "give both 'mean' and 'std', or neither")
    for start, end in (("top", "bottom"), ("left", "right")):
        if crop and crop.get(start) is not None and crop.get(end) is not None and crop[end] <= crop[start]:
            report.add(at + ("crop", end), f"{end} ({crop[end]}) must be greater than {start} "
                                           f"({crop[start]}): the bounds are slice bounds, "
                                           f"image[top:bottom, left:right]")
    resize, centre = _tuple(pre.get("resize")), _tuple(pre.get("center_crop"))
    shorter = pre.get("resize_shorter")
    if resize and shorter:
        report.add(at + ("resize_shorter",), "give 'resize' ([height, width]) or 'resize_shorter' (the "
                                             "shorter side, aspect ratio kept), not both")
    elif centre and resize and (centre[0] > resize[0] or centre[1] > resize[1]):
        report.add(at + ("center_crop",), f"{list(centre)} does not fit in the resized {list(resize)} image")
    elif centre and shorter and min(centre) > shorter:
        report.add(at + ("center_crop",), f"{list(centre)} does not fit in an image whose shorter side is "
                                          f"{shorter} (resize_shorter)")
    return Preprocess(crop=(crop.get("top"), crop.get("bottom"), crop.get("left"), crop.get("right"))
                      if crop else None, resize=resize, scale=pre.get("scale"), mean=mean,
                      std=std, resize_shorter=shorter, center_crop=centre)


def inputs(entries: list[dict[str, Any]], at: tuple, report: Located) -> tuple[TensorSpec, ...]:
    """A model's declared inputs (schema-valid): unique names, a sane size, a range that fits the dtype."""
    specs, first = [], {}
    for j, entry in enumerate(entries):
        name, shape, dtype = entry["name"], tuple(entry["shape"]), entry.get("dtype", "float32")
        if name in first:
            report.add(at + (j, "name"), f"input name '{name}' is used twice (also inputs[{first[name]}]); "
                                         f"input names must be unique")
        first.setdefault(name, j)
        elements = math.prod(concrete(shape))
        if elements > MAX_SAMPLE_ELEMENTS:
            report.add(at + (j, "shape"), f"{elements} values per sample (free axes counted as 8); limit "
                                          f"{MAX_SAMPLE_ELEMENTS}")
        value_range = _tuple(entry.get("range"))
        if value_range and (problem := _range_problem(value_range, dtype)):
            report.add(at + (j, "range"), problem)
        specs.append(TensorSpec(name=name, shape=shape, dtype=dtype, range=value_range))
    return tuple(specs)


def _range_problem(value_range: tuple[float, float], dtype: str) -> str | None:
    low, high = value_range
    if low >= high:
        return f"low ({low:g}) must be less than high ({high:g})"
    if dtype == "bool" or not dtype.startswith(("int", "uint")):
        return None
    if not (float(low).is_integer() and float(high).is_integer()):
        return (f"an {dtype} input's range is whole numbers, [low, high) of the values drawn; got "
                f"{list(value_range)}")
    info = np.iinfo(dtype)
    if low < info.min or high - 1 > info.max:
        return f"[{low:g}, {high:g}) does not fit {dtype} ({info.min} to {info.max})"
    return None


def _tuple(value: Any) -> tuple | None:
    return tuple(value) if value is not None else None
