"""Keras models under tfmot: the tfmot module itself, QAT models saved as Keras SavedModels and loaded back, and
the Conv/Dense kernels of a plain or QAT model read as the converter stores them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

# A tfmot QAT model is saved as a Keras SavedModel directory: .keras cannot restore QuantizeWrapper variables,
# and .h5 cannot restore cluster-preserving quantizers (they create one variable per centroid when built, and a
# model rebuilt from its config has unclustered kernels); the SavedModel restores every kind. Load with load_qat.
QAT_FORMAT = "keras_qat"
QAT_FILE = "model_qat"


def tfmot_module() -> Any:
    """tensorflow_model_optimization, imported after TensorFlow is set up for Keras 2 (tf_keras)."""
    from bench_matrix.sources.tensorflow import tensorflow

    tensorflow()
    import tensorflow_model_optimization as tfmot

    return tfmot


def qat_custom_objects() -> dict[str, Any]:
    """Quantizers of the collaborative (cluster/prune-preserving) schemes, which quantize_scope lacks."""
    tfmot_module()
    from tensorflow_model_optimization.python.core.quantization.keras.collab_opts.cluster_preserve import (
        cluster_preserve_quantize_registry as cp,
    )
    from tensorflow_model_optimization.python.core.quantization.keras.collab_opts.prune_preserve import (
        prune_preserve_quantize_registry as pp,
    )

    return {name: obj for module in (cp, pp) for name, obj in vars(module).items()
            if isinstance(obj, type) and obj.__module__ == module.__name__}


def load_qat(path: str | Path) -> Any:
    """A fresh Keras model from a QAT model this trainer saved (format 'keras_qat': a Keras SavedModel directory
    holding tfmot QuantizeWrapper layers), loaded inside tfmot's quantize_scope, without compiling."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    tfmot = tfmot_module()
    with tfmot.quantization.keras.quantize_scope(qat_custom_objects()):
        return k.models.load_model(str(path), compile=False)


def is_weighted(layer: Any) -> bool:
    """A Conv*/Dense layer: the layers whose kernels are pruned, clustered and counted in the facts."""
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    conv = k.layers.Conv1D, k.layers.Conv2D, k.layers.Conv3D, k.layers.Conv2DTranspose
    return isinstance(layer, (*conv, k.layers.Dense)) and not isinstance(
        layer, (k.layers.DepthwiseConv2D, k.layers.SeparableConv2D))


def stored_kernels(model: Any, names: set[str] | None = None) -> list[np.ndarray]:
    """Conv/Dense kernels of a plain or QAT model, or only those of the named layers. A QAT model's kernels are
    read as the converter stores them: fake-quantised to int8 with the learned ranges (dequantised), so a PCQAT
    centroid that rounds to 0 counts as the zero it becomes."""
    found = []
    for layer in model.layers:
        inner = getattr(layer, "layer", layer)
        if not is_weighted(inner) or (names is not None and inner.name not in names):
            continue
        # A QuantizeWrapper's `_weight_vars` hold (variable, quantizer, quantizer variables); in inference mode
        # the quantizer applies the ranges the converter uses.
        quantized = [quantizer(var, training=False, weights=qvars)
                     for var, quantizer, qvars in getattr(layer, "_weight_vars", ()) if "kernel" in var.name]
        found.append(np.asarray(quantized[0] if quantized else inner.kernel.numpy()))
    return found
