"""TensorFlow 2 with Keras 2: the model's call under tf.function (the TensorFlow fp32 baseline), and Keras'
model.predict as a cell of its own."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import Backend, ConvertRequest, Inputs, Profile, Session, SourceModel, Support, \
    TensorSpec, example_inputs, flat_outputs, tensorflow, thread_settings

from ._tf import keras_arguments, missing_tensorflow, probe_tensorflow_gpu, tf_versions
from ._tf_profile import GPU_REASON, tf_profile

if TYPE_CHECKING:
    import tensorflow as tf

DEVICES = {"cpu": "/CPU:0", "cuda": "/GPU:0"}


class TensorFlowBackend(Backend):
    """The Keras model as it is, its call traced once into a tf.function on the target device."""

    name = "tensorflow"
    description = "TensorFlow 2 / Keras 2: the model's call under tf.function (the TensorFlow fp32 baseline)"
    # fp32 only on cuda: a Keras model cannot be switched to fp16 after the fact (a mixed_float16 clone works for
    # Sequential and functional models only, not for a revived SavedModel); TF-TRT runs TensorFlow models at fp16.
    supports = (Support(("tensorflow",), ("none",), ("fp32",), ("cpu", "cuda")),)
    baseline_for = ("tensorflow",)
    devices = {"cuda": "cuda"}

    def versions(self) -> dict[str, str]:
        return tf_versions()

    def probe(self, target: str, precision: str) -> str | None:
        return missing_tensorflow() if target == "cpu" else probe_tensorflow_gpu()

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        """Copy the source model (a file, or a SavedModel directory) into the artifact unchanged."""
        step = request.step
        if step.kind != "none":
            raise ValueError(f"the {self.name} backend runs the Keras model as it is; strategy kind {step.kind!r} "
                             f"needs another backend (tflite, or tftrt on a GPU)")
        source = request.source
        destination = request.out_dir / source.path.name
        if source.path.is_dir():
            shutil.copytree(source.path, destination)
        else:
            shutil.copy2(source.path, destination)
        return {"source": {**source.to_dict(), "path": source.path.name}}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        tf = tensorflow(threads)  # before any TensorFlow op runs in this process, or the pools stay as they are
        if target == "cuda":  # fp32 means fp32: TensorFlow would otherwise run matmuls and convolutions in TF32
            tf.config.experimental.enable_tensor_float_32_execution(False)
        source = artifact_source(artifact_dir, meta)
        with tf.device(DEVICES[target]):
            model = source.load()
        return FunctionSession(model, source.inputs, target)


class KerasPredictBackend(TensorFlowBackend):
    """Keras' model.predict on every call, as a user who never wrapped the model in tf.function would time it."""

    name = "keras_predict"
    description = "Keras model.predict per call (it builds a tf.data pipeline each call); not a baseline"
    supports = (Support(("tensorflow",), ("none",), ("fp32",), ("cpu",)),)
    baseline_for = ()
    devices = {}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        tf = tensorflow(threads)
        source = artifact_source(artifact_dir, meta)
        with tf.device(DEVICES["cpu"]):
            model = source.load()
        return PredictSession(model, source.inputs)


def artifact_source(artifact_dir: Path, meta: dict[str, Any]) -> SourceModel:
    """The source model as copied into the artifact directory by `convert`."""
    return SourceModel.from_dict({**meta["source"], "path": str(artifact_dir / meta["source"]["path"])})


class FunctionSession(Session):
    """The model's call as one concrete function (every input in its dtype, any batch), traced and run once in
    __init__; inputs go to the model in its input order, outputs come back in flat_outputs' order."""

    def __init__(self, model: Any, inputs: tuple[TensorSpec, ...], target: str):
        tf = tensorflow()
        self._tf = tf
        self._model = model  # the concrete function captures only the variables' handles: keep them alive
        self._device = DEVICES[target]
        self._sync = tf.test.experimental.sync_devices if target == "cuda" else None

        def call(*tensors: "tf.Tensor") -> Any:
            return model(keras_arguments(tensors), training=False)

        specs = [tf.TensorSpec([None, *spec.shape], _tf_dtype(tf, spec.dtype)) for spec in inputs]
        with tf.device(self._device):  # the traced graph's ops keep this placement
            self._call = tf.function(call, input_signature=specs).get_concrete_function()
        first = flat_outputs(self.execute(self.prepare(example_inputs(inputs, batch=1))))
        self._output_device = first[0].device

    def prepare(self, inputs: Inputs) -> list["tf.Tensor"]:
        with self._tf.device(self._device):
            return [self._tf.identity(_host(array)) for array in inputs.values()]

    def execute(self, prepared: list["tf.Tensor"]) -> Any:
        out = self._call(*prepared)
        if self._sync:
            self._sync()
        return out

    def fetch(self, outputs: Any) -> list[np.ndarray]:
        return [np.asarray(out.numpy(), dtype=np.float32) for out in flat_outputs(outputs)]

    def profile(self, prepared: list["tf.Tensor"], calls: int) -> Profile:
        """tf.profiler's op times over `calls` calls (docs/metrics.md, Profiles); none on a GPU."""
        if self._sync:
            return Profile(reason=GPU_REASON)
        return tf_profile(lambda: self.execute(prepared), calls, "fp32")

    def info(self) -> dict[str, Any]:
        facts = {"device": self._device, "output_device": self._output_device, "call_path": "tf.function",
                 **thread_settings()}
        if self._sync:  # a GPU: whether matmuls and convolutions may round to TF32
            facts["tensor_float_32"] = self._tf.config.experimental.tensor_float_32_execution_enabled()
        return facts


class PredictSession(Session):
    """model.predict on the host arrays, on the CPU; one call in __init__ builds Keras' predict function."""

    def __init__(self, model: Any, inputs: tuple[TensorSpec, ...]):
        self._tf = tensorflow()
        self._model = model
        self.execute(self.prepare(example_inputs(inputs, batch=1)))

    def prepare(self, inputs: Inputs) -> Any:
        return keras_arguments([_host(array) for array in inputs.values()])

    def execute(self, prepared: Any) -> Any:
        with self._tf.device(DEVICES["cpu"]):
            return self._model.predict(prepared, verbose=0)

    def fetch(self, outputs: Any) -> list[np.ndarray]:
        return [np.asarray(out, dtype=np.float32) for out in flat_outputs(outputs)]

    def profile(self, prepared: Any, calls: int) -> Profile:
        """tf.profiler's op times over `calls` calls of predict, its tf.data pipeline's ops among them."""
        return tf_profile(lambda: self.execute(prepared), calls, "fp32")

    def info(self) -> dict[str, Any]:
        return {"device": DEVICES["cpu"], "call_path": "model.predict", **thread_settings()}


def _host(array: np.ndarray) -> np.ndarray:
    """A contiguous host array, floating ones as float32."""
    return np.ascontiguousarray(array, dtype=np.float32 if np.issubdtype(array.dtype, np.floating) else None)


def _tf_dtype(tf: Any, dtype: str) -> Any:
    """The TensorFlow dtype a Keras input of `dtype` is fed in (bfloat16 inputs are fed as float32 arrays)."""
    return tf.float32 if dtype == "bfloat16" else tf.as_dtype(dtype)
