"""TensorFlow with Keras 2 (tf_keras), imported the one way bench-matrix uses it; safe Keras model loading."""

from __future__ import annotations

import os
from contextlib import suppress
from typing import TYPE_CHECKING, Any

from bench_matrix.phases import Epochs
from bench_matrix.sources import ModelFileError
from bench_matrix.sources.keras_files import RESAVE, check_keras_file

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


def epoch_phases(total: int, what: str = "train") -> Any:
    """A Keras callback that tells the parent each epoch's end, its loss and the time left (phases.Epochs)."""
    epochs = Epochs(total, what)

    class EpochPhases(keras().callbacks.Callback):
        def on_epoch_end(self, epoch: int, logs: dict | None = None) -> None:
            epochs.ended(epoch + 1, float((logs or {}).get("loss", float("nan"))))

    return EpochPhases()


def thread_settings() -> dict[str, int]:
    """The TensorFlow thread pools in force (0 means TensorFlow's own choice)."""
    tf = tensorflow()
    return {"intra_op_threads": tf.config.threading.get_intra_op_parallelism_threads(),
            "inter_op_threads": tf.config.threading.get_inter_op_parallelism_threads()}


def load_keras(source: "SourceModel") -> Any:
    """A fresh Keras model from a .keras or .h5 file or a Keras SavedModel, checked first (no Lambda layer, no
    non-Keras object, no SavedModel op calling Python or touching files), then read in `safe_mode`."""
    k = keras()
    from tf_keras.src.saving.serialization_lib import SafeModeScope

    check_keras_file(source.path, source.label)
    try:
        with SafeModeScope(True):
            model = k.models.load_model(str(source.path), compile=False)
    except Exception as exc:  # tf_keras raises many kinds for a damaged or foreign file
        text = str(exc).strip().splitlines()[0][:400] if str(exc).strip() else ""
        raise ModelFileError(f"{source.label}: cannot load this Keras model with tf_keras {k.__version__} in "
                             f"safe mode: {type(exc).__name__}: {text}; {RESAVE}") from None
    if not isinstance(model, k.Model):
        raise ModelFileError(f"{source.label}: this SavedModel was not written by Keras (it loads as "
                             f"{type(model).__name__}); save the model with Keras 2 (tf_keras) as .keras, "
                             f".h5 or a Keras SavedModel")
    return model


def count_params(model: Any) -> int:
    return int(model.count_params())
