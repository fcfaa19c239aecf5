"""Start a tfmot QAT model's activation ranges at the ranges the float model really produces.

tfmot starts every activation range at [-6, 6] and moves it by an EMA with decay 0.999 per training step,
so a fine-tuning of a few hundred steps ends with ranges still near [-5.5, 5.7] (measured on PilotNet after 88
steps): steps of 0.04 where the activations span 0..1, and QAT far worse than post-training quantisation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

RANGE_NAMES = ("post_activation", "output", "quantize_layer")  # activation range variables: NAME_min, NAME_max
SAMPLES = 512  # fine-tuning samples whose activations set the starting ranges
BATCH = 64


def observed_ranges(model: Any, x: np.ndarray) -> dict[str, tuple[float, float]]:
    """(min, max) of every layer's output over the first SAMPLES of x, by layer name; the input's under ''."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    fresh = k.models.clone_model(model)  # one clean graph: a stripped model's layers may hold several
    fresh.set_weights(model.get_weights())
    layers = [layer for layer in fresh.layers if not isinstance(layer, k.layers.InputLayer)]
    probe = k.Model(fresh.inputs, [layer.output for layer in layers])
    sample = x[:SAMPLES]
    ranges = {"": (float(sample.min()), float(sample.max()))}
    for start in range(0, len(sample), BATCH):
        outputs = probe(sample[start:start + BATCH], training=False)
        for layer, out in zip(layers, outputs if isinstance(outputs, list) else [outputs], strict=True):
            values = np.asarray(out)
            lo, hi = ranges.get(layer.name, (np.inf, -np.inf))
            ranges[layer.name] = (min(lo, float(values.min())), max(hi, float(values.max())))
    return ranges


def _observed_tensor(layer: Any) -> str | None:
    """The name under which observed_ranges holds what this QAT layer's activation quantizer sees, if known."""
    inner = getattr(layer, "layer", None)
    if inner is not None:  # QuantizeWrapper: it quantizes the wrapped layer's (post-activation) output
        return inner.name
    history = getattr(getattr(layer, "input", None), "_keras_history", None)  # QuantizeLayer: its input
    source = getattr(history, "layer", None)
    if source is None:
        return None
    return "" if type(source).__name__ == "InputLayer" else source.name


def init_activation_ranges(qat_model: Any, ranges: dict[str, tuple[float, float]]) -> list[str]:
    """Set each scalar activation range variable of qat_model from `ranges` (widened to hold 0, as tfmot does);
    return the names of the variables set."""
    done = []
    for layer in qat_model.layers:
        observed = ranges.get(_observed_tensor(layer) or "\0")
        if observed is None:
            continue
        for var in layer.weights:
            name = var.name.split("/")[-1].split(":")[0]
            base, _, end = name.rpartition("_")
            if base in RANGE_NAMES and end in ("min", "max") and var.shape.rank == 0:
                var.assign(min(observed[0], 0.0) if end == "min" else max(observed[1], 0.0))
                done.append(f"{layer.name}/{name}")
    return done
