"""The matrix format as a JSON Schema: the single source for validation and for editors. The core is here;
each selectable scenario adds its own section (bench_matrix/scenarios)."""

from __future__ import annotations

from typing import Any

from bench_matrix.matrix.requirements import SCHEMA as REQUIREMENTS
from bench_matrix.measurement import TASKS
from bench_matrix.tensors import DTYPES
from bench_matrix.workload.driving import defaults as builtin_data

FRAMEWORKS = ("pytorch", "tensorflow", "onnx")
PRECISIONS = ("fp32", "fp16", "bf16", "int8")
BUILTIN_MODELS = ("pilotnet", "pilotnet_jderobot")
BUILTIN_FRAMEWORKS = ("pytorch", "tensorflow")  # each built-in model exists in both
BUILTIN_DATASETS = tuple(builtin_data.TASKS)
DATASET_KINDS = ("builtin", "npz", "folder", "images", "synthetic")
CELL_KEYS = ("model", "framework", "backend", "strategy", "precision", "target")

# Upper limits no real matrix reaches; they keep every later computation (timers, allocations, seeds) sane.
MAX_ITERATIONS = 1_000_000
MAX_SECONDS = 86_400  # one measurement phase: a day
MAX_TIMEOUT_S = 604_800  # a cell: a week
MAX_BATCH = 65_536
MAX_THREADS = 1_024
MAX_SAMPLES = 10_000_000
MAX_SEED = 2**31 - 1  # every library's seed type holds it
MAX_EPOCHS = 10_000
MAX_LR = 10.0
MAX_IMAGE_SIDE = 65_536
MAX_RESIZE = 8_192
MAX_SYNTHETIC = 1_000_000
MAX_INPUTS = 64  # named inputs of one model
MAX_RANK = 8  # axes of one input
MAX_DIM = 1_000_000  # length of one axis
MAX_SAMPLE_ELEMENTS = 1 << 26  # values in one sample of one input (a 4K RGB image has 25 M)


def _count(minimum: int, maximum: int, **extra: Any) -> dict[str, Any]:
    return {"type": "integer", "minimum": minimum, "maximum": maximum, **extra}


def seconds(maximum: int = MAX_SECONDS, exclusive: bool = False, **extra: Any) -> dict[str, Any]:
    return {"type": "number", "exclusiveMinimum" if exclusive else "minimum": 0, "maximum": maximum, **extra}


_SEED = _count(0, MAX_SEED)
_RETIRED = {"deprecated": True, "description": "retired with the single timed loop: read with a warning for "
                                               "now (docs/matrix.md, Retired keys)"}
# Settings of the timed loop the interleaved rounds replaced, with the bounds they had: accepted for a
# deprecation period (matrix/retired.py reads them); a value they never allowed is still refused.
RETIRED = {key: {**rule, **_RETIRED} for key, rule in {
    "min_iterations": _count(1, MAX_ITERATIONS),
    "min_time_s": seconds(),
    "max_time_s": seconds(exclusive=True),
    "ci_rel_width": {"type": "number", "exclusiveMinimum": 0, "maximum": 1},
    "throughput_time_s": seconds(exclusive=True),
    "passes": _count(1, 100),
}.items()}
_EPOCHS = {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_EPOCHS}
_LR = {"type": "number", "exclusiveMinimum": 0, "maximum": MAX_LR}

_TRAINING = {
    "epochs": {**_EPOCHS, "description": "fine-tuning epochs"},
    "fraction": {"type": "number", "exclusiveMinimum": 0, "maximum": 1,
                 "description": "fraction of the training split used for fine-tuning"},
    "lr": {**_LR, "description": "learning rate"},
    "batch_size": _count(1, MAX_BATCH),
}
_CALIBRATION = {
    "calibration_samples": _count(1, MAX_SAMPLES,
                                  description="samples of the calibration split used to calibrate"),
}
_SPARSITY = {
    "initial_sparsity": {"type": "number", "minimum": 0, "exclusiveMaximum": 1},
    "final_sparsity": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
    "schedule": {"enum": ["polynomial", "constant"]},
    "scope": {"enum": ["local", "global"], "description": "per-layer (local) or whole-model (global) pruning"},
    "conv_sparsity": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
    "linear_sparsity": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
    "min_weights": _count(0, 1_000_000_000,
                          description="kernels with fewer weights stay dense (default 10000)"),
}
_CLUSTERS = {
    "clusters": _count(2, 65_536, description="distinct values per weight tensor"),
    "init": {"enum": ["kmeans++", "linear", "density", "random"]},
    "cluster_epochs": _EPOCHS,
    "qat_epochs": _EPOCHS,
    "prune_epochs": _EPOCHS,
}

# Strategy kinds: what is done to the model. "conversion" kinds happen inside a backend's convert;
# "training" kinds fine-tune the source model first and are implemented per framework.
STRATEGY_KINDS: dict[str, dict[str, Any]] = {
    "none": {"stage": "conversion", "options": {},
             "help": "the model as it is, converted to the backend's format"},
    "ptq_dynamic": {"stage": "conversion", "options": {"per_channel": {"type": "boolean"}},
                    "help": "post-training dynamic(-range) quantisation: int8 weights, activations quantised at run time"},
    "ptq_static": {"stage": "conversion", "options": {
        **_CALIBRATION,
        "per_channel": {"type": "boolean"},
        "io": {"enum": ["float", "int8"], "description": "float: float inputs/outputs (float fallback allowed); "
                                                         "int8: full-integer model with int8 inputs and outputs"},
        "method": {"enum": ["minmax", "entropy", "percentile"]},
    }, "help": "post-training static quantisation calibrated on the calibration split"},
    "qat": {"stage": "training", "options": {**_TRAINING, **_CALIBRATION},
            "help": "quantisation-aware training, then integer conversion"},
    "prune": {"stage": "training", "options": {**_TRAINING, **_SPARSITY},
              "help": "magnitude (L1) weight pruning with fine-tuning"},
    "cluster": {"stage": "training", "options": {**_TRAINING, **_CLUSTERS},
                "help": "weight clustering (weight sharing) with fine-tuning"},
    "cqat": {"stage": "training", "options": {**_TRAINING, **_CLUSTERS},
             "help": "cluster-preserving quantisation-aware training"},
    "pqat": {"stage": "training", "options": {**_TRAINING, **_SPARSITY, **_CLUSTERS},
             "help": "prune-preserving quantisation-aware training"},
    "pcqat": {"stage": "training", "options": {**_TRAINING, **_SPARSITY, **_CLUSTERS},
              "help": "sparsity- and cluster-preserving quantisation-aware training"},
}

NAME = {"type": "string", "pattern": r"^[A-Za-z0-9][A-Za-z0-9_.+-]*$",
        "x-message": "use letters, digits and _ . + - (starting with a letter or digit)"}


def _strategy_schema() -> dict[str, Any]:
    branches = []
    for kind, info in STRATEGY_KINDS.items():
        branches.append({
            "if": {"properties": {"kind": {"const": kind}}, "required": ["kind"],
                   "not": {"required": ["steps"]}},
            "then": {"properties": {"kind": {}, "description": {"type": "string"}, **info["options"]},
                     "additionalProperties": False},
        })
    return {
        "type": "object",
        "description": "a named strategy: a kind with options, or a combination of steps applied in order",
        "properties": {
            "kind": {"enum": list(STRATEGY_KINDS)},
            "steps": {"type": "array", "minItems": 2, "items": {"type": "string"}},
            "description": {"type": "string"},
        },
        "oneOf": [{"required": ["kind"]}, {"required": ["steps"]}],
        "x-message": "give either 'kind' (with its options) or 'steps' (a list of strategy names), not both",
        "allOf": branches + [{"if": {"required": ["steps"], "not": {"required": ["kind"]}},
                              "then": {"properties": {"steps": {}, "description": {}},
                                       "additionalProperties": False}}],
    }


def axis(values: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "minItems": 1, "uniqueItems": True, "items": values}


SELECTOR = {
    "type": "object", "minProperties": 1, "additionalProperties": False,
    "properties": {key: {"type": "string"} for key in CELL_KEYS},
}
# a scenario section's selection of cells: every cell, or partial cells as in include, less those excluded
SELECTION = {
    "cells": {"if": {"type": "string"}, "then": {"const": "all"},
              "else": {"type": "array", "minItems": 1, "items": SELECTOR},
              "description": "'all' (default) or a list of partial cells, as in include"},
    "exclude": {"type": "array", "items": SELECTOR},
}

_FOLDERS = {"oneOf": [{"type": "string"}, {"type": "array", "minItems": 1, "items": {"type": "string"}}],
            "x-message": "give a folder or a list of folders"}
_SIDE = _count(1, MAX_RESIZE)

DATASET: dict[str, Any] = {
    "type": "object", "additionalProperties": False,
    "properties": {
        "builtin": {"enum": list(BUILTIN_DATASETS), "description": builtin_data.DESCRIPTION},
        "npz": {"type": "string", "description": "one array per model input (x for one input), labels y"},
        "folder": {**_FOLDERS, "description": "DeepLearningStudio recordings: data.csv and images"},
        "images": {**_FOLDERS, "description": "image folders with one subfolder per class"},
        "synthetic": {"type": "object", "additionalProperties": False, "required": ["samples"],
                      "properties": {"samples": _count(1, MAX_SYNTHETIC)},
                      "description": "random inputs of the models' shapes and dtypes; no labels"},
        "task": {"enum": list(TASKS), "description": "default: classification for images and driving_bends, "
                                                     "none for synthetic, regression otherwise"},
        "samples": _count(10, 200_000, default=4000),
        "circuits": _count(3, 1_000, default=20),
        "seed": _SEED,
        "preprocess": {"type": "object", "additionalProperties": False, "properties": {
            "crop": {"type": "object", "additionalProperties": False, "properties": {
                side: _count(0, MAX_IMAGE_SIDE) for side in ("top", "bottom", "left", "right")}},
            "resize": {"type": "array", "items": _SIDE, "minItems": 2, "maxItems": 2,
                       "description": "[height, width]"},
            "resize_shorter": {**_SIDE, "description": "resize so the shorter side has this length"},
            "center_crop": {"type": "array", "items": _SIDE, "minItems": 2, "maxItems": 2,
                            "description": "[height, width] cut from the centre, after resizing"},
            "scale": {"type": "number", "exclusiveMinimum": 0, "maximum": 1e6,
                      "description": "image values are multiplied by it; not given: 1/255, for pixels 0 to "
                                     "255 only (other images need it given)"},
            "mean": {"type": "array", "items": {"type": "number", "minimum": -1e6, "maximum": 1e6},
                     "minItems": 1},
            "std": {"type": "array", "items": {"type": "number", "minimum": 1e-6, "maximum": 1e6},
                    "minItems": 1},
        }},
        "labels": {"type": "object", "additionalProperties": False, "properties": {
            "columns": {"type": "array", "items": {"type": "string"}, "minItems": 1},
            "offset": {"type": "array", "items": {"type": "number", "minimum": -1e9, "maximum": 1e9},
                       "minItems": 1},
            "scale": {"type": "array", "items": {"type": "number", "minimum": 1e-9, "maximum": 1e9},
                      "minItems": 1},
        }},
        "split": {"type": "object", "additionalProperties": False, "properties": {
            "train": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
            "calibration": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
            "test": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1},
            "by": {"enum": ["auto", "group", "block", "random"]},
        }},
    },
    "oneOf": [{"required": [kind]} for kind in DATASET_KINDS],
    "x-message": f"give exactly one of {', '.join(repr(k) for k in DATASET_KINDS[:-1])} or "
                 f"'{DATASET_KINDS[-1]}'",
}

_INPUT = {
    "type": "object", "additionalProperties": False, "required": ["name", "shape"],
    "properties": {
        "name": {"type": "string", "minLength": 1},
        "shape": {"type": "array", "maxItems": MAX_RANK,
                  "description": "one sample, no batch axis; null: any length",
                  "items": {"oneOf": [{"type": "null"}, _count(1, MAX_DIM)],
                            "x-message": f"each axis is a whole number from 1 to {MAX_DIM}, or null "
                                         f"(any length)"}},
        "dtype": {"enum": list(DTYPES), "default": "float32"},
        "range": {"type": "array", "minItems": 2, "maxItems": 2,
                  "description": "[low, high] of synthetic values",
                  "items": {"type": "number", "minimum": -1e9, "maximum": 1e9}},
    },
}

SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://bench-matrix.dev/schema/matrix.schema.json",
    "title": "bench-matrix matrix file",
    "type": "object",
    "additionalProperties": False,
    "required": ["models", "dataset", "axes"],
    "properties": {
        "version": {"const": 1},
        "name": {"type": "string"},
        "description": {"type": "string"},
        "models": {"type": "array", "minItems": 1, "items": {
            "type": "object", "additionalProperties": False, "required": ["name", "framework"],
            "properties": {
                "name": NAME,
                "framework": {"enum": list(FRAMEWORKS)},
                "builtin": {"enum": list(BUILTIN_MODELS), "description":
                            "trained on the dataset: pilotnet (NVIDIA's, ~250 k parameters) or pilotnet_jderobot "
                            "(JdeRobot's variant of the framework: PyTorch 1.6 M parameters, TensorFlow 17 M)"},
                "file": {"type": "string", "description": "TorchScript .pt/.pth, torch.export .pt2, Keras .keras/.h5, "
                                                         "a Keras SavedModel directory, or .onnx"},
                "factory": {"type": "string", "pattern": r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*$",
                            "x-message": "write it as 'package.module:function'"},
                "weights": {"type": "string", "description": "state_dict file for 'factory'"},
                "python_path": {"type": "array", "items": {"type": "string"}},
                "layout": {"enum": ["nchw", "nhwc"]},
                "training": {"type": "object", "additionalProperties": False, "properties": {
                    "epochs": _count(1, MAX_EPOCHS),
                    "batch_size": _count(1, MAX_BATCH),
                    "lr": _LR}},
                "inputs": {"type": "array", "minItems": 1, "maxItems": MAX_INPUTS, "items": _INPUT,
                           "description": "the model's named inputs, in order (default: read from the model "
                                          "file, else the dataset's)"},
                "task": {"enum": list(TASKS), "description": "this model's task (default: the dataset's)"},
                "dataset": {**DATASET, "description": "this model's own dataset (default: the matrix's)"},
                "requirements": {**REQUIREMENTS, "description": "this model's own requirements, over the "
                                                                "matrix's key by key"},
            },
            "oneOf": [{"required": ["builtin"]}, {"required": ["file"]}, {"required": ["factory"]}],
            "x-message": "give exactly one of 'builtin', 'file' or 'factory' (with 'weights')",
        }},
        "dataset": DATASET,
        "strategies": {"type": "object", "additionalProperties": _strategy_schema(),
                       "propertyNames": {"pattern": NAME["pattern"]}},
        "axes": {
            "type": "object", "additionalProperties": False,
            "required": ["strategy", "precision", "target"],
            "properties": {
                "framework": axis({"enum": list(FRAMEWORKS)}),
                "backend": axis({"type": "string"}),
                "strategy": axis({"type": "string"}),
                "precision": axis({"enum": list(PRECISIONS)}),
                "target": axis({"type": "string", "description": "a target an installed backend declares "
                                                                  "(bench-matrix backends lists them)"}),
            },
        },
        "backend_options": {"type": "object", "description": "each backend's own options, by backend name",
                            "additionalProperties": {"type": "object"}},
        "metrics": {"type": "array", "uniqueItems": True, "items": {"type": "string"},
                    "description": "metric plugins to compute for every cell, besides the task's own"},
        "requirements": REQUIREMENTS,
        "include": {"type": "array", "items": SELECTOR},
        "exclude": {"type": "array", "items": SELECTOR},
        "settings": {"type": "object", "additionalProperties": False, "properties": {
            "warmup_iterations": _count(0, MAX_ITERATIONS, description="untimed calls when a session is "
                                                                        "loaded, before its rounds"),
            "warmup_s": seconds(description="and seconds of them at least"),
            "window_s": seconds(60, exclusive=True, description="each cell's timed window of each kind in "
                                                                 "a round"),
            "min_rounds": _count(2, 1000, description="rounds before the intervals may stop them"),
            "ci_target": {"type": "number", "exclusiveMinimum": 0, "maximum": 1,
                          "description": "ask for this precision on every cell: its p50 and speed-up 95 % "
                                         "intervals within ± this fraction (0.02 = ±2 %); unset, a cell "
                                         "whose answer is settled leaves the rounds at ±5 %"},
            "timing_budget_s": seconds(exclusive=True, description="seconds of rounds per cell at most: a "
                                                                   "model's rounds stop when its cells' "
                                                                   "share is spent"),
            "processes": _count(1, 16, description="session processes per cell, timed in the same rounds; "
                                                    "how they differ widens the intervals"),
            "memory_share": {"type": "number", "exclusiveMinimum": 0, "maximum": 1,
                             "description": "share of the available memory the loaded sessions of a model "
                                            "may use at once; beyond it, cells are measured in groups"},
            "batch_size": _count(1, MAX_BATCH),
            "threads": _count(1, MAX_THREADS),
            "timeout_s": seconds(MAX_TIMEOUT_S, exclusive=True,
                                  description="per cell, conversion and measurement together"),
            "seed": _SEED,
            "eval_samples": _count(1, MAX_SAMPLES),
            **RETIRED,
        }},
    },
}
