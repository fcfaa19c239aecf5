"""The kit's small real models, the same three in every framework: an image regressor and an image classifier
with a BatchNorm, and a model with two inputs (float features, int64 token ids) and two outputs of one shape;
their data and fp32 outputs. Their weights are random (He-initialised, zero biases) and their inputs centred,
so that every activation varies with the input about as much as it is large: a precision check is never
vacuous."""

from __future__ import annotations

import hashlib
import importlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs, TensorSpec

MODELS = ("regression", "classification", "multi_io")
# framework -> (the module that builds its models, the source format they are saved in)
BUILDERS = {"pytorch": ("bench_matrix.conformance.models_torch", "state_dict"),
            "tensorflow": ("bench_matrix.conformance.models_keras", "keras"),
            "onnx": ("bench_matrix.conformance.models_onnx", "onnx")}
SIDE, CHANNELS, CLASSES = 16, 3, 3  # images: 16x16 RGB; the classifier's classes
FEATURES, TOKENS, VOCABULARY = 6, 5, 10  # multi_io: float features and int64 token ids per sample
HEAD = 2  # the width of each of multi_io's outputs: one shape, so only their values tell their order
HIDDEN = 16  # the width of the image models' last hidden layer
# multi_io's hidden layer: wide enough (10 x 128 weights) that TFLite's dynamic-range quantisation, which
# leaves tensors under 1024 elements in float, quantises it
WIDE = 128
# Samples compared with the reference; calibrated on; the largest batch (request.max_batch), run at once by
# the execute check and the batch check (the calibration samples over again: int8 results differ by
# rounding, not by clipping, at every batch size).
EVAL, CALIBRATION, LARGE = 16, 40, 64
# The batch check's sizes, one after another in one session: every size class that has broken a runtime: 1
# and 2 (the smallest, and an example batch of 2), odd ones, 15 to 17 around a plan made for 15 samples from
# an example batch of 2 (ExecuTorch's) and a tile of 8 or 16, and max_batch - 1 and max_batch.
BATCHES = (1, 2, 3, 7, 15, 16, 17, LARGE - 1, LARGE)
# What every conversion and load is asked for (settings.threads' default); TensorFlow, whose threads are set
# once per process, runs the kit's own Keras code with it too, as a cell's process would.
THREADS = 1


@dataclass(frozen=True)
class KitModel:
    """One model as a backend gets it, with the kit's inputs and the framework's fp32 outputs on `eval` and
    `large` (calibration starts with the `eval` samples: int8 results differ by rounding only)."""

    name: str
    source: SourceModel
    eval: Inputs
    calibration: Inputs
    large: Inputs
    reference: list[np.ndarray]
    large_reference: list[np.ndarray]


def build(framework: str, name: str, folder: Path) -> KitModel:
    """Build and save model `name` of `framework` in `folder`; ImportError if its library is missing."""
    module_name, source_format = BUILDERS[framework]
    builder = importlib.import_module(module_name)
    channels_last = framework == "tensorflow"
    folder.mkdir(parents=True, exist_ok=True)
    path = builder.save(name, folder)
    source = SourceModel(name=name, framework=framework, format=source_format, path=path,
                         sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                         inputs=specs(name, channels_last), factory=builder.factory(name))
    calibration = sample(name, CALIBRATION, 1, channels_last)
    evaluated = {key: array[:EVAL] for key, array in calibration.items()}
    cycled = np.arange(LARGE) % CALIBRATION
    large = {key: np.take(array, cycled, axis=0) for key, array in calibration.items()}
    return KitModel(name, source, evaluated, calibration, large, builder.reference(source, evaluated),
                    builder.reference(source, large))


def specs(name: str, channels_last: bool) -> tuple[TensorSpec, ...]:
    """The model's named inputs: one image, or float features and int64 token ids."""
    if name == "multi_io":
        return TensorSpec("features", (FEATURES,)), TensorSpec("ids", (TOKENS,), "int64", (0, VOCABULARY))
    shape = (SIDE, SIDE, CHANNELS) if channels_last else (CHANNELS, SIDE, SIDE)
    return (TensorSpec("image", shape),)


def sample(name: str, n: int, seed: int, channels_last: bool) -> Inputs:
    """n samples of the model's inputs: smooth images (each channel a random level plus random horizontal and
    vertical ramps, values about -3..3, with a little noise), or standard-normal features with token ids."""
    rng = np.random.default_rng(seed)
    if name == "multi_io":
        return {"features": rng.standard_normal((n, FEATURES)).astype(np.float32),
                "ids": rng.integers(0, VOCABULARY, (n, TOKENS)).astype(np.int64)}
    level, across, down = (rng.uniform(-1, 1, (n, CHANNELS, 1, 1)) for _ in range(3))
    ramp = np.linspace(-1, 1, SIDE)
    images = (level + across * ramp + down * ramp[:, None]
              + 0.1 * rng.standard_normal((n, CHANNELS, SIDE, SIDE))).astype(np.float32)
    return {"image": np.ascontiguousarray(images.transpose(0, 2, 3, 1)) if channels_last else images}


def batch_norm_statistics(channels: int) -> dict[str, np.ndarray]:
    """The image models' BatchNorm (after the first convolution): seeded scale and statistics (zero shift),
    named as PyTorch names them; each channel's output keeps a spread of the order of its input's."""
    rng = np.random.default_rng(3)
    return {"weight": rng.uniform(0.5, 1.5, channels).astype(np.float32),
            "bias": np.zeros(channels, np.float32),
            "running_mean": (0.2 * rng.standard_normal(channels)).astype(np.float32),
            "running_var": rng.uniform(0.5, 2.0, channels).astype(np.float32)}
