"""Quantisation-aware-trained Keras models (format 'keras_qat', written by the tfmot trainer): importing
tensorflow-model-optimization the way bench-matrix uses it, and loading such a model back."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.sources.tensorflow import keras, tensorflow

if TYPE_CHECKING:
    from bench_matrix.sources import SourceModel

# A tfmot QAT model is saved as a Keras SavedModel directory: .keras cannot restore QuantizeWrapper
# variables, and .h5 cannot restore cluster-preserving quantizers (they create one variable per centroid when
# built, and a model rebuilt from its config has unclustered kernels); the SavedModel restores every kind.
QAT_FORMAT = "keras_qat"


def tfmot_module() -> Any:
    """tensorflow_model_optimization, imported after TensorFlow is set up for Keras 2 (tf_keras)."""
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


def load_source(source: SourceModel) -> Any:
    """A fresh Keras model from our trainer's QAT model (`source`, format keras_qat)."""
    return load_qat(source.path)


def load_qat(path: str | Path) -> Any:
    """A fresh Keras model from a QAT model the tfmot trainer saved (a Keras SavedModel directory holding
    tfmot QuantizeWrapper layers), loaded inside tfmot's quantize_scope, without compiling."""
    k = keras()
    tfmot = tfmot_module()
    with tfmot.quantization.keras.quantize_scope(qat_custom_objects()):
        return k.models.load_model(str(path), compile=False)
