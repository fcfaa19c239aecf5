"""Test helper: a tiny PilotNet-shaped Keras 2 model (NHWC), trained a little so its outputs are not trivial."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

INPUT_SHAPE = (16, 16, 3)


def images(n: int, seed: int) -> np.ndarray:
    """Noise images in [0, 1] (NHWC) whose colour balance varies from image to image."""
    rng = np.random.default_rng(seed)
    return (rng.random((n, 1, 1, 3)) * rng.random((n, *INPUT_SHAPE))).astype(np.float32)


def colour_balance(x: np.ndarray) -> np.ndarray:
    """A learnable two-column target: red minus blue, and green."""
    means = x.mean(axis=(1, 2))
    return (np.stack([means[:, 0] - means[:, 2], means[:, 1]], axis=1) * 4 - 1).astype(np.float32)


def tiny() -> Any:
    """BatchNorm, two strided convolutions and a dense head: 16x16x3 -> 2 (about 1.9 k parameters)."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    return k.Sequential([k.layers.Input(INPUT_SHAPE), k.layers.BatchNormalization(),
                         k.layers.Conv2D(8, 3, strides=2, activation="relu"),
                         k.layers.Conv2D(8, 3, strides=2, activation="relu"), k.layers.Flatten(),
                         k.layers.Dense(16, activation="relu"), k.layers.Dense(2)])


def save_trained(path: Path, seed: int = 0, epochs: int = 30) -> Path:
    """Train `tiny` briefly on colour_balance and save it (.keras, .h5 or a SavedModel directory)."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    k.utils.set_random_seed(seed)
    model = tiny()
    model.compile(optimizer=k.optimizers.Adam(3e-3), loss="mse")
    x = images(256, seed + 100)
    model.fit(x, colour_balance(x), epochs=epochs, batch_size=32, verbose=0)
    model.save(path)
    return path


FEATURES, TOKENS, VOCABULARY = 6, 5, 10  # the two-input model's float features and int64 token ids per sample


def two_inputs_two_outputs() -> Any:
    """features float (6,) and ids int64 (5,) -> [zeta (1,), alpha (2,)]: a list whose names are not in sorted
    order (TFLite's signature sorts them), from the ids' mean embedding beside the features."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    k.utils.set_random_seed(0)
    features = k.layers.Input((FEATURES,), name="features")
    ids = k.layers.Input((TOKENS,), dtype="int64", name="ids")
    embedded = k.layers.GlobalAveragePooling1D()(k.layers.Embedding(VOCABULARY, 4)(ids))
    hidden = k.layers.Dense(16, activation="relu")(k.layers.Concatenate()([features, embedded]))
    return k.Model([features, ids], [k.layers.Dense(1, name="zeta")(hidden), k.layers.Dense(2, name="alpha")(hidden)])


def token_data(n: int, seed: int) -> dict[str, np.ndarray]:
    """Inputs of `two_inputs_two_outputs`: standard-normal features and token ids in [0, VOCABULARY)."""
    rng = np.random.default_rng(seed)
    return {"features": rng.standard_normal((n, FEATURES)).astype(np.float32),
            "ids": rng.integers(0, VOCABULARY, (n, TOKENS)).astype(np.int64)}
