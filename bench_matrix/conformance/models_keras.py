"""The kit's Keras 2 (tf_keras) models, channels last, saved as .keras files, and their fp32 outputs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.conformance.models import CHANNELS, CLASSES, FEATURES, HEAD, HIDDEN, SIDE, THREADS, \
    TOKENS, VOCABULARY, WIDE, batch_norm_statistics
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs

HE = "he_normal"


def image_net(outputs: int) -> Any:
    """Two strided convolutions, the first with a BatchNorm, and a dense head: (16, 16, 3) -> `outputs`."""
    from bench_matrix.sources.tensorflow import keras

    layers = keras().layers
    image = layers.Input((SIDE, SIDE, CHANNELS), name="image")
    hidden = layers.Conv2D(8, 3, strides=2, kernel_initializer=HE)(image)
    norm = layers.BatchNormalization()
    hidden = layers.ReLU()(norm(hidden))
    statistics = batch_norm_statistics(8)
    norm.set_weights([statistics[key] for key in ("weight", "bias", "running_mean", "running_var")])
    hidden = layers.Conv2D(8, 3, strides=2, activation="relu", kernel_initializer=HE)(hidden)
    hidden = layers.Flatten()(hidden)
    hidden = layers.Dense(HIDDEN, activation="relu", kernel_initializer=HE)(hidden)
    return keras().Model(image, layers.Dense(outputs, kernel_initializer=HE)(hidden))


def multi_io() -> Any:
    """features (6,) and ids int64 (5,) -> [zeta (2,), alpha (2,)]: output names not in sorted order."""
    from bench_matrix.sources.tensorflow import keras

    layers = keras().layers
    features = layers.Input((FEATURES,), name="features")
    ids = layers.Input((TOKENS,), dtype="int64", name="ids")
    embedded = layers.Embedding(VOCABULARY, 4, embeddings_initializer="normal")(ids)
    joined = layers.Concatenate()([features, layers.GlobalAveragePooling1D()(embedded)])
    hidden = layers.Dense(WIDE, activation="relu", kernel_initializer=HE)(joined)
    return keras().Model([features, ids], [layers.Dense(HEAD, name="zeta", kernel_initializer=HE)(hidden),
                                           layers.Dense(HEAD, name="alpha", kernel_initializer=HE)(hidden)])


def factory(name: str) -> None:
    return None  # a .keras file holds the whole model


def save(name: str, folder: Path) -> Path:
    """The model with seeded He-initialised weights (zero biases, Keras' default) saved as a .keras file."""
    from bench_matrix.sources.tensorflow import keras, tensorflow

    tensorflow(THREADS)  # before TensorFlow's runtime starts: its thread pools are set once per process
    keras().utils.set_random_seed(0)
    model = multi_io() if name == "multi_io" else image_net(2 if name == "regression" else CLASSES)
    path = folder / f"{name}.keras"
    model.save(path)
    return path


def reference(source: SourceModel, inputs: Inputs) -> list[np.ndarray]:
    """The Keras model's own fp32 outputs, in its output order."""
    model = source.load()
    arrays = list(inputs.values())
    out = model(arrays[0] if len(arrays) == 1 else arrays, training=False)
    values = out if isinstance(out, (list, tuple)) else [out]
    return [np.asarray(value, dtype=np.float32) for value in values]
