"""PilotNet reference models in Keras 2 (NHWC 66x200x3 in, normalised [v, w] out), as in the study."""

from __future__ import annotations

from typing import Any

from bench_matrix.sources.tensorflow import keras

INPUT_SHAPE = (66, 200, 3)


def _model(padding: str, head: list[int], name: str) -> Any:
    k = keras()
    layers = [k.layers.Input(INPUT_SHAPE), k.layers.BatchNormalization(epsilon=1e-3)]
    for filters, size, stride in ((24, 5, 2), (36, 5, 2), (48, 5, 2), (64, 3, 1), (64, 3, 1)):
        layers.append(k.layers.Conv2D(filters, size, strides=stride, padding=padding, activation="relu"))
    layers.append(k.layers.Flatten())
    layers += [k.layers.Dense(width, activation="relu") for width in head]
    layers.append(k.layers.Dense(2))
    return k.Sequential(layers, name=name)


def pilotnet() -> Any:
    """NVIDIA's PilotNet: valid convolutions (flatten 1152) -> 100 -> 50 -> 10 -> 2 (252,242 parameters)."""
    return _model("valid", [100, 50, 10], "pilotnet")


def pilotnet_jderobot() -> Any:
    """The JdeRobot TensorFlow variant: 'same' convolutions (flatten 14400) -> 1164 -> 100 -> 50 -> 10 -> 2
    (17,016,206 parameters; the 14400x1164 layer holds 98.5 % of them)."""
    return _model("same", [1164, 100, 50, 10], "pilotnet_jderobot")


BUILDERS = {"pilotnet": pilotnet, "pilotnet_jderobot": pilotnet_jderobot}
