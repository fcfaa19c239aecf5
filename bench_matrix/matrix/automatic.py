"""The automatic matrix of one model file: its YAML text, from what the installed backends run here."""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.errors import UserError
from bench_matrix.matrix.spec import DEFAULT_LAYOUT, MODEL_SUFFIXES, file_kind
from bench_matrix.tensors import DTYPES, OPEN_LENGTH, TensorSpec, axes_text, concrete, open_axes, \
    shape_text

CONVERSIONS = ("none", "ptq_dynamic", "ptq_static")  # the strategies that need no training
SAMPLES = 256  # synthetic samples, split so that static quantisation calibrates on 100 (its default)
SPLIT = "{train: 0.05, calibration: 0.4, test: 0.55}"
EXPECTED = (f"a model file ({', '.join(sorted(MODEL_SUFFIXES))}) or a Keras SavedModel folder (holding "
            f"saved_model.pb)")
Combination = tuple[str, str, str, str]  # backend, strategy, precision, target
REQUIREMENTS = "# requirements: {max_drop: 1%, p50_ms: 10}   # then `run` ends with the recommended cell\n"
ORDER = {"none": 0, "ptq_dynamic": 1, "ptq_static": 2, "fp32": 0, "fp16": 1, "bf16": 2, "int8": 3, "cpu": 0}


@dataclass(frozen=True)
class Request:
    """What the user gave: the model (absolute path), inputs it declared, data and task."""

    path: Path
    framework: str
    format: str
    inputs: tuple[TensorSpec, ...] = ()
    data: Path | None = None
    task: str | None = None


@dataclass(frozen=True)
class Found:
    """What the probe found here: the combinations that run, backends left out (why), the file's inputs and
    fixed batch size."""

    runnable: tuple[Combination, ...]
    left_out: Mapping[str, str]
    inputs: tuple[TensorSpec, ...] | None
    batch: int | None = None


def model_kind(path: Path, expected: str = EXPECTED) -> tuple[str, str]:
    """(framework, format) of a model file or SavedModel folder; a UserError saying what was expected."""
    if path.is_dir():
        if kind := file_kind(path):
            return kind
        raise UserError(f"{path}: is a folder without saved_model.pb; expected {expected}")
    if path.suffix.lower() not in MODEL_SUFFIXES:
        raise UserError(f"{path}: is not a model bench-matrix reads; expected {expected}")
    if not path.exists():
        raise UserError(f"{path}: no such file; expected {expected}")
    return MODEL_SUFFIXES[path.suffix.lower()]


def parse_input(text: str) -> TensorSpec:
    """--input NAME:SHAPE[:DTYPE], SHAPE one sample's axes separated by commas (? for any length)."""
    parts = text.split(":")
    usage = f"--input {text!r}: give NAME:SHAPE:DTYPE, e.g. x:3,224,224:float32 (? for an axis of any length)"
    if len(parts) not in (2, 3) or not parts[0].strip():
        raise UserError(usage)
    dims = [d.strip() for d in parts[1].split(",") if d.strip()]
    if not all(d == "?" or (d.isdigit() and int(d) > 0) for d in dims):
        raise UserError(f"{usage}; the shape {parts[1]!r} is not whole numbers above 0 or ?")
    dtype = parts[2].strip() if len(parts) == 3 else "float32"
    if dtype not in DTYPES:
        raise UserError(f"--input {text!r}: dtype {dtype!r} is not allowed; allowed: {', '.join(DTYPES)}")
    return TensorSpec(parts[0].strip(), tuple(None if d == "?" else int(d) for d in dims), dtype)


def candidates(framework: str, supports: Mapping[str, Iterable[Any]], slow: Mapping[str, str]
               ) -> list[Combination]:
    """Every conversion combination the backends' `Support`s declare for `framework`, but those of backends
    whose first result takes minutes (`slow`: their `slow_start`)."""
    return sorted({(name, st, p, t) for name, declared in supports.items() if name not in slow
                   for s in declared if framework in s.frameworks
                   for st in s.strategies if st in CONVERSIONS for p in s.precisions for t in s.targets})


def found(framework: str, supports: Mapping[str, Iterable[Any]], slow: Mapping[str, str],
          judged: Mapping[Combination, str | None], inputs: tuple[TensorSpec, ...] | None,
          batch: int | None) -> Found:
    """What runs here (`judged`: why each candidate cannot, None when it runs), and which backends taking
    `framework` are left out, with why (slow, or their first reason)."""
    runnable = tuple(c for c, why in judged.items() if why is None)
    reasons = {c[0]: why for c, why in reversed(judged.items()) if why}
    taking = sorted(n for n, declared in supports.items()
                    if any(framework in s.frameworks for s in declared))
    out = {name: slow.get(name) or reasons.get(name, "implements none of " + ", ".join(CONVERSIONS))
           for name in taking if name not in {c[0] for c in runnable}}
    return Found(runnable, out, inputs, batch)


def data_path(data: Path | None, task: str | None) -> None:
    """--data names an .npz file or an image folder; --task other than none needs labels (--data)."""
    if data is None:
        if task not in (None, "none"):
            raise UserError(f"--task {task}: synthetic data has no labels; give --data (an .npz with "
                            f"labels y or an image folder), or --task none")
        return
    if not (data.is_dir() or (data.is_file() and data.suffix.lower() == ".npz")):
        why = "no such file or folder" if not data.exists() else "is neither an .npz file nor a folder"
        raise UserError(f"--data {data}: {why}; expected an .npz (one array per input, labels y) or an image "
                        f"folder (one subfolder per class)")


def matrix_text(request: Request, found: Found) -> str:
    """The commented matrix: the model, its data, the axes of what runs here, settings only where needed."""
    if not found.runnable:
        raise UserError(f"{request.path}: no installed backend runs {request.framework} models on this "
                        f"machine: " + "; ".join(f"{n}: {why}" for n, why in found.left_out.items()))
    inputs = request.inputs or found.inputs
    if not inputs and request.data is None:
        why = ("TorchScript files do not say them" if request.format == "torchscript"
               else f"is it a valid {request.format} model?")
        raise UserError(f"{request.path}: cannot read the model's inputs from the file ({why}); give them "
                        f"with --input NAME:SHAPE:DTYPE (repeatable, e.g. --input x:3,224,224:float32), or "
                        f"give data with --data (an .npz or an image folder)")
    return "".join([_header(request, found, inputs), _model(request, inputs),
                    _dataset(request, inputs), _axes(found), _settings(found)])


def axes(found: Found) -> dict[str, list[str]]:
    """The values of each axis that run here, in a natural order (none first, fp32 first, cpu first)."""
    return {axis: list({c[i]: None for c in sorted(found.runnable, key=lambda c: ORDER.get(c[i], 9))})
            for i, axis in enumerate(("backend", "strategy", "precision", "target"))}


def model_name(path: Path) -> str:
    """The model's name in the matrix: the file's stem, with what a name may not hold replaced."""
    name = re.sub(r"[^A-Za-z0-9_.+-]", "-", path.name.removesuffix(path.suffix))
    return name.lstrip("._+-") or "model"


def _header(request: Request, found: Found, inputs: tuple[TensorSpec, ...] | None) -> str:
    said = "declared with --input" if request.inputs else "read from the file"
    said = said if inputs else "from the data"
    described = ", ".join(s.describe() for s in inputs or ())
    lines = [f"# The automatic matrix of {request.path} ({request.framework}); inputs {said}"
             + (f": {described}" if described else "") + ".",
             f"# Every installed backend that takes {request.framework} models and runs here, the strategies",
             "# that need no training and their precisions, on the targets this machine has;",
             "# `bench-matrix plan` marks what a backend does not implement as not valid (never run).",
             "# Edit it, then: bench-matrix plan FILE; bench-matrix run FILE"]
    lines += [f"# Left out: {name}: {why}" for name, why in found.left_out.items()]
    return "\n".join(lines + _timed(request, inputs)) + "\n"


def _timed(request: Request, inputs: tuple[TensorSpec, ...] | None) -> list[str]:
    """What the inputs are timed at: the data's shapes, or synthetic ones (open axes given OPEN_LENGTH)."""
    if request.data is not None:
        return ["# Inputs are timed at the shapes of the data's arrays."]
    shapes = ", ".join(f"{s.name} {shape_text(concrete(s.shape))} {s.dtype}" for s in inputs or ())
    return [f"# Synthetic inputs are timed at {shapes} per sample."] + [
        f"# {s.name}: {axes_text(open_axes(s))} open in the file (the batch axis is 0), given {OPEN_LENGTH} "
        f"by synthetic data; set the lengths under inputs: below." for s in _defaulted(request, inputs)]


def _defaulted(request: Request, inputs: tuple[TensorSpec, ...] | None) -> tuple[TensorSpec, ...]:
    """The inputs with an open axis that synthetic data would give the default length."""
    return () if request.data is not None else tuple(s for s in inputs or () if open_axes(s))


def _model(request: Request, inputs: tuple[TensorSpec, ...] | None) -> str:
    text = (f"models:\n  - name: {json.dumps(model_name(request.path))}\n"
            f"    framework: {request.framework}\n    file: {json.dumps(str(request.path))}\n")
    if request.inputs:
        text += "    inputs:\n" + "".join(f"      - {_input(s)}\n" for s in request.inputs)
    elif _defaulted(request, inputs):  # every input, in order: inputs: replaces what the file says
        text += (f"    # inputs:   # replace each null by the length to time (synthetic data gives it "
                 f"{OPEN_LENGTH})\n" + "".join(f"    #   - {_input(s)}\n" for s in inputs or ()))
    return text


def _input(spec: TensorSpec) -> str:
    shape = json.dumps(list(spec.shape))
    return f"{{name: {json.dumps(spec.name)}, shape: {shape}, dtype: {spec.dtype}}}"


def _dataset(request: Request, inputs: tuple[TensorSpec, ...] | None) -> str:
    data, task = request.data, request.task
    if data is None:
        return (f"dataset:\n  synthetic: {{samples: {SAMPLES}}}   # random inputs, no labels: latency, size "
                f"and fidelity to the fp32 baseline\n  split: {SPLIT}   # nothing is trained: calibration "
                f"and test samples\n  # or your data: npz: data.npz (arrays named after the inputs, "
                f"labels y), or images: val/ (a subfolder per class)\n")
    kind = "npz" if data.suffix.lower() == ".npz" else "images"
    text = f"dataset:\n  {kind}: {json.dumps(str(data))}\n" + (f"  task: {task}\n" if task else "")
    size = _image_size(request.framework, inputs) if kind == "images" else None
    resize = f"  preprocess: {{resize: {json.dumps(size)}}}   # the model's input size\n"
    return text + (resize if size else "")


def _image_size(framework: str, inputs: tuple[TensorSpec, ...] | None) -> list[int] | None:
    """[height, width] of a single image input of known size, in the framework's layout."""
    if not inputs or len(inputs) != 1 or len(inputs[0].shape) != 3 or None in inputs[0].shape:
        return None
    shape = inputs[0].shape
    return list(shape[:2] if DEFAULT_LAYOUT.get(framework) == "nhwc" else shape[1:])


def _axes(found: Found) -> str:
    values = {axis: json.dumps(v) for axis, v in axes(found).items()}
    return (f"axes:\n  backend: {values['backend']}\n  strategy: {values['strategy']}\n"
            f"  precision: {values['precision']}   # pairs a backend does not implement: not valid, not run\n"
            f"  target: {values['target']}\n")


def _settings(found: Found) -> str:
    settings = "# settings: {threads: 1, batch_size: 32, timing_budget_s: 3.0}   # the defaults\n"
    if found.batch is not None:
        settings = f"settings: {{batch_size: {found.batch}}}   # the model's batch axis is fixed\n"
    return settings + REQUIREMENTS
