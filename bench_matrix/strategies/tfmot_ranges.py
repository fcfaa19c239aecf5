"""Start a tfmot QAT model's activation ranges at the ranges the float model really produces.

tfmot starts every activation range at [-6, 6] and moves it by an EMA with decay 0.999 per training step,
so a fine-tuning of a few hundred steps ends with ranges still near [-5.5, 5.7] (measured on PilotNet after 88
steps): steps of 0.04 where the activations span 0..1, and QAT far worse than post-training quantisation.
"""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from bench_matrix.plugin import keras
from bench_matrix.strategies.keras_fit import TrainingData

# Activation range variables: NAME_min and NAME_max; a QuantizeLayer's are named after the layer
# (quantize_layer, quantize_layer_1, ...).
RANGE_VARIABLE = re.compile(r"(?:post_activation|output|quantize_layer(?:_\d+)?)_(min|max)")
SAMPLES = 512  # fine-tuning samples whose activations set the starting ranges
BATCH = 64


def observed_ranges(model: Any, data: TrainingData) -> dict[str, tuple[float, float]]:
    """(min, max) of every layer's output over the first SAMPLES of the training data, by layer name; each
    input's under input_key(its position)."""
    k = keras()
    fresh = k.models.clone_model(model)  # one clean graph: a stripped model's layers may hold several
    fresh.set_weights(model.get_weights())
    layers = [layer for layer in fresh.layers if not isinstance(layer, k.layers.InputLayer)]
    probe = k.Model(fresh.inputs, [layer.output for layer in layers])
    samples = min(SAMPLES, len(data))
    ranges = {input_key(i): (float(x[:samples].min()), float(x[:samples].max()))
              for i, x in enumerate(data.inputs)}
    for start in range(0, samples, BATCH):
        outputs = probe(data.model_inputs(slice(start, min(start + BATCH, samples))), training=False)
        for layer, out in zip(layers, outputs if isinstance(outputs, list) else [outputs], strict=True):
            values = np.asarray(out)
            lo, hi = ranges.get(layer.name, (np.inf, -np.inf))
            ranges[layer.name] = (min(lo, float(values.min())), max(hi, float(values.max())))
    return ranges


def input_key(position: int) -> str:
    """The key of a model input's range in observed_ranges (no layer name has angle brackets)."""
    return f"<input {position}>"


def _observed_tensor(layer: Any, inputs: list[Any]) -> str | None:
    """The name under which observed_ranges holds what this QAT layer's activation quantizer sees, if known;
    `inputs` are the QAT model's input layers, in order."""
    inner = getattr(layer, "layer", None)
    if inner is not None:  # QuantizeWrapper: it quantizes the wrapped layer's (post-activation) output
        return inner.name
    history = getattr(getattr(layer, "input", None), "_keras_history", None)  # QuantizeLayer: its input
    source = getattr(history, "layer", None)
    if source is None:
        return None
    return input_key(inputs.index(source)) if source in inputs else source.name


def init_activation_ranges(qat_model: Any, ranges: dict[str, tuple[float, float]]) -> list[str]:
    """Set each scalar activation range variable of qat_model from `ranges` (widened to hold 0, as tfmot
    does); return the names of the variables set."""
    done = []
    inputs = [tensor._keras_history.layer for tensor in qat_model.inputs]
    for layer in qat_model.layers:
        observed = ranges.get(_observed_tensor(layer, inputs) or "\0")
        if observed is None:
            continue
        for var in layer.weights:
            name = var.name.split("/")[-1].split(":")[0]
            if (match := RANGE_VARIABLE.fullmatch(name)) and var.shape.rank == 0:
                var.assign(min(observed[0], 0.0) if match[1] == "min" else max(observed[1], 0.0))
                done.append(f"{layer.name}/{name}")
    return done
