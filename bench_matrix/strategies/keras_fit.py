"""Fitting a Keras model under tfmot: the training split in the model's input order, and the task's loss.

Regression: the MSE of every output (flattened per sample and concatenated, as evaluation compares them)
against the label columns. Classification: sparse categorical cross-entropy of the first output with the int64
class ids, on logits; on probabilities when the model ends in a softmax (a Softmax layer, or a layer whose
activation is softmax).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench_matrix.plugin import Inputs, TensorSpec, epoch_phases, keras, tensorflow, training_arrays

LOSSES = {"regression": "mse", "classification": "cross_entropy"}


@dataclass(frozen=True)
class TrainingData:
    """Training samples as a Keras model takes them: its inputs in its order, and the task's labels."""

    inputs: tuple[np.ndarray, ...]
    labels: np.ndarray  # (N, columns) float32 for regression, (N,) int64 class ids for classification
    task: str
    softmax: bool  # the model's first output is a softmax: cross-entropy on probabilities, not logits

    def __len__(self) -> int:
        return len(self.labels)

    def model_inputs(self, rows: slice = slice(None)) -> Any:
        """The rows of every input, as a Keras model is called: one array, or a tuple in input order."""
        picked = tuple(x[rows] for x in self.inputs)
        return picked[0] if len(picked) == 1 else picked


def training_data(inputs: Inputs, labels: np.ndarray, specs: tuple[TensorSpec, ...], task: str,
                  model: Any) -> TrainingData:
    """The training split's named inputs in the model's input order, and labels typed for the task's loss."""
    arrays, target = training_arrays(inputs, labels, specs, task)
    return TrainingData(arrays, target, task, ends_in_softmax(model))


def ends_in_softmax(model: Any) -> bool:
    """Whether the model's first output comes from a Softmax layer or a layer with a softmax activation."""
    k = keras()
    layer = model.outputs[0]._keras_history.layer
    layer = getattr(layer, "layer", layer)  # a tfmot wrapper: the layer it wraps
    activation = getattr(layer, "activation", None)
    return isinstance(layer, k.layers.Softmax) or activation is k.activations.softmax or (
        isinstance(layer, k.layers.Activation) and getattr(activation, "__name__", "") == "softmax")


def fit(model: Any, data: TrainingData, lr: float, batch: int, n_epochs: int, per_epoch: int, seed: int,
        callbacks: list[Any] = ()) -> float:
    """Adam on the task's loss, BatchNormalization frozen; the mean loss of the last epoch."""
    tf, k = tensorflow(), keras()
    # Keep the learned normalisation while fine-tuning (a frozen Keras 2 BatchNorm runs in inference mode),
    # and unfreeze it after: tfmot's prune-preserving QAT registry takes a layer with no trainable weights for
    # one it quantizes.
    norms = [layer for layer in model.layers
             if isinstance(getattr(layer, "layer", layer), k.layers.BatchNormalization) and layer.trainable]
    for layer in norms:
        layer.trainable = False
    loss, weights, targets = _objective(model, data)
    model.compile(optimizer=k.optimizers.Adam(lr), loss=loss, loss_weights=weights)
    ds = (tf.data.Dataset.from_tensor_slices((data.model_inputs(), targets))
          .shuffle(len(data), seed=seed, reshuffle_each_iteration=True).batch(batch).repeat())
    history = model.fit(ds, epochs=n_epochs, steps_per_epoch=per_epoch, verbose=0,
                        callbacks=[*callbacks, epoch_phases(n_epochs, "fine-tune")])
    for layer in norms:
        layer.trainable = True
    final = float(history.history["loss"][-1])
    if not math.isfinite(final):
        raise ValueError(f"fine-tuning diverged: the {LOSSES[data.task]} loss is {final} after "
                         f"{n_epochs * per_epoch} steps (lower lr?)")
    return final


def _objective(model: Any, data: TrainingData) -> tuple[Any, list[float] | None, Any]:
    """(loss, loss weights, targets) for model.compile and model.fit; one each per output of a multi-output
    model."""
    k = keras()
    outputs = model.outputs
    if data.task == "classification":
        entropy = k.losses.SparseCategoricalCrossentropy(from_logits=not data.softmax)
        if len(outputs) == 1:
            return entropy, None, data.labels
        ignored = tuple(np.zeros((len(data), *_shape(o)), np.float32) for o in outputs[1:])  # no loss on them
        return [entropy] + [None] * len(ignored), None, (data.labels, *ignored)
    shapes = [_shape(o) for o in outputs]
    widths = [math.prod(s) for s in shapes]
    if sum(widths) != data.labels.shape[1]:
        raise ValueError(f"the model outputs {sum(widths)} values per sample but the labels have "
                         f"{data.labels.shape[1]} column(s)")
    if len(outputs) == 1:
        return "mse", None, data.labels.reshape(len(data), *shapes[0])
    columns = np.split(data.labels, np.cumsum(widths)[:-1], axis=1)
    # weighted by width: the sum of the outputs' MSEs is the MSE over all label columns
    return (["mse"] * len(outputs), [w / sum(widths) for w in widths],
            tuple(c.reshape(len(data), *s) for c, s in zip(columns, shapes)))


def _shape(output: Any) -> tuple[int, ...]:
    shape = tuple(output.shape[1:])
    if any(d is None for d in shape):
        raise ValueError(f"fine-tuning needs outputs of a fixed shape per sample; {output.name} has {shape}")
    return tuple(int(d) for d in shape)
