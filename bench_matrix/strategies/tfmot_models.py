"""Keras models under tfmot: the Conv/Dense kernels of a plain or QAT model, read as the converter stores
them. QAT models themselves (format 'keras_qat', saved as QAT_FILE) are loaded by bench_matrix.sources.keras_qat."""

from __future__ import annotations

from typing import Any

import numpy as np

from bench_matrix.plugin import keras

__all__ = ["QAT_FILE", "is_weighted", "stored_kernels"]

QAT_FILE = "model_qat"  # a Keras SavedModel directory (see sources.keras_qat)


def is_weighted(layer: Any) -> bool:
    """A Conv*/Dense layer: the layers whose kernels are pruned, clustered and counted in the facts."""
    k = keras()
    conv = k.layers.Conv1D, k.layers.Conv2D, k.layers.Conv3D, k.layers.Conv2DTranspose
    return isinstance(layer, (*conv, k.layers.Dense)) and not isinstance(
        layer, (k.layers.DepthwiseConv2D, k.layers.SeparableConv2D))


def stored_kernels(model: Any, names: set[str] | None = None) -> list[np.ndarray]:
    """Conv/Dense kernels of a plain or QAT model, or only those of the named layers; a QAT model's as the
    converter stores them (fake-quantised to int8, dequantised: a PCQAT centroid that rounds to 0 is a zero)."""
    found = []
    for layer in model.layers:
        inner = getattr(layer, "layer", layer)
        if not is_weighted(inner) or (names is not None and inner.name not in names):
            continue
        # A QuantizeWrapper's `_weight_vars` hold (variable, quantizer, quantizer variables); in inference
        # mode the quantizer applies the ranges the converter uses.
        quantized = [quantizer(var, training=False, weights=qvars)
                     for var, quantizer, qvars in getattr(layer, "_weight_vars", ()) if "kernel" in var.name]
        found.append(np.asarray(quantized[0] if quantized else inner.kernel.numpy()))
    return found
