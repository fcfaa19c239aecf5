"""TensorFlow with Keras 2 (tf_keras), imported the one way bench-matrix uses it; safe Keras model loading."""

from __future__ import annotations

import os
from contextlib import suppress
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from bench_matrix.sources import SourceModel


def tensorflow(threads: int | None = None) -> Any:
    """The `tensorflow` module with Keras 2 selected and C++ info logs off; `threads` pins the intra-op pool
    (and one inter-op thread) when the runtime has not started yet."""
    # tensorflow-model-optimization and our Keras code need Keras 2 (tf_keras): tf.keras must be the same.
    os.environ["TF_USE_LEGACY_KERAS"] = "1"
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    import tensorflow as tf

    if threads is not None:
        with suppress(RuntimeError):  # the runtime already started in this process: values stay as they are
            tf.config.threading.set_intra_op_parallelism_threads(threads)
            tf.config.threading.set_inter_op_parallelism_threads(1)
    return tf


def keras() -> Any:
    """The Keras 2 package (tf_keras), after `tensorflow()` has configured the environment."""
    tensorflow()
    import tf_keras

    return tf_keras


def thread_settings() -> dict[str, int]:
    """The TensorFlow thread pools in force (0 means TensorFlow's own choice)."""
    tf = tensorflow()
    return {"intra_op_threads": tf.config.threading.get_intra_op_parallelism_threads(),
            "inter_op_threads": tf.config.threading.get_inter_op_parallelism_threads()}


def load_keras(source: "SourceModel") -> Any:
    """A fresh Keras model from a .keras file, an .h5 file or a Keras SavedModel directory, loaded safely:
    `safe_mode` refuses Python code (Lambda bytecode) in .keras and .h5 files; a SavedModel holds graphs only."""
    k = keras()
    from tf_keras.src.saving.serialization_lib import SafeModeScope

    path = str(source.path)
    if source.format == "keras_qat":  # our own trainer's output, in the workspace cache
        from bench_matrix.strategies.tfmot_models import load_qat

        return load_qat(source.path)
    try:
        with SafeModeScope(True):
            model = k.models.load_model(path, compile=False)
    except (ValueError, OSError, TypeError) as exc:
        raise ValueError(f"{path}: cannot load this Keras model with tf_keras {k.__version__} in safe mode: "
                         f"{exc}") from exc
    if not isinstance(model, k.Model):
        raise ValueError(f"{path}: this SavedModel was not written by Keras (it loads as "
                         f"{type(model).__name__}); save the model with Keras 2 (tf_keras) as .keras, .h5 or "
                         f"a Keras SavedModel")
    if len(model.inputs) != 1 or len(model.outputs) != 1:
        raise ValueError(f"{path}: bench-matrix runs models with one input and one output; this one has "
                         f"{len(model.inputs)} input(s) and {len(model.outputs)} output(s)")
    return model


def count_params(model: Any) -> int:
    return int(model.count_params())
