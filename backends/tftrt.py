"""TF-TRT: the Keras model as a SavedModel whose TensorRT-compatible subgraphs run as TensorRT engines (FP32,
FP16, or INT8 calibrated by TensorRT's entropy calibrator), built ahead of time on the GPU."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import Backend, ConvertRequest, Inputs, Session, StrategySpec, Support, TensorSpec, \
    concrete, count, flat_outputs, take, tensorflow, thread_settings

from ._common import calibration_data, static_options_reason
from ._tf import keras_arguments, probe_tftrt, tf_versions

if TYPE_CHECKING:
    import tensorflow as tf

MODES = {"fp32": "FP32", "fp16": "FP16", "int8": "INT8"}  # TrtPrecisionMode values
SIGNATURE = "serving_default"
DEVICE = "/GPU:0"
# Engines built at conversion: batch 1 (latency) and 32 (throughput). In TF-TRT's implicit batch mode an engine
# serves every batch up to its own; a larger batch builds another engine at its first call while the cache has
# room, and runs in native TensorFlow once it is full.
BUILD_BATCHES = (1, 32)
MAX_ENGINES = 4
# TF-TRT's TRTInt8Calibrator is a nvinfer1::IInt8EntropyCalibrator2; no other calibrator can be chosen.
CALIBRATOR = "IInt8EntropyCalibrator2"


class TFTRTBackend(Backend):
    """Converts a Keras model with TF-TRT's TrtGraphConverterV2 and runs its serving signature on the GPU."""

    name = "tftrt"
    slow_start = "builds TensorRT engines for a minute or more"
    description = "TF-TRT (TensorFlow with TensorRT engines): FP32, FP16, INT8 with entropy calibration"
    supports = (Support(("tensorflow",), ("none",), ("fp32", "fp16"), ("tensorrt",)),
                Support(("tensorflow",), ("ptq_static",), ("int8",), ("tensorrt",)))
    devices = {"tensorrt": "cuda"}

    def versions(self) -> dict[str, str]:
        return tf_versions("tensorrt")

    def probe(self, target: str, precision: str) -> str | None:
        return probe_tftrt(precision)

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        """INT8 takes float input and output, and calibrates with TensorRT's entropy calibrator only (also when
        the strategy names no method: the record says entropy)."""
        if step.kind != "ptq_static":
            return None
        if step.options.get("io", "float") != "float":
            return static_options_reason(step, "TF-TRT", ("entropy",))
        if "per_channel" in step.options:
            return ("TF-TRT has no per_channel setting (TensorRT's implicit int8 quantisation chooses the weight "
                    "scales itself); remove the option")
        method = step.options.get("method", "entropy")
        if method != "entropy":
            return (f"TF-TRT calibrates int8 only with TensorRT's entropy calibrator ({CALIBRATOR}, fixed in "
                    f"TF-TRT), not {method!r}; set method: entropy or leave the option out")
        return None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        step = request.step
        tf = tensorflow(request.threads)
        from tensorflow.python.compiler.tensorrt import trt_convert as trt

        mode = MODES[request.precision]
        inputs = request.source.inputs
        meta: dict[str, Any] = {"precision_mode": mode, "strategy": step.kind, "built_batches": list(BUILD_BATCHES),
                                "maximum_cached_engines": MAX_ENGINES,
                                "max_workspace_size_bytes": trt.DEFAULT_TRT_MAX_WORKSPACE_SIZE_BYTES}
        with tempfile.TemporaryDirectory(prefix="bench-matrix-tftrt-", dir=request.scratch_dir) as tmp:
            saved = Path(tmp) / "saved_model"
            export_serving(request.source.load(), inputs, saved)
            converter = trt.TrtGraphConverterV2(input_saved_model_dir=str(saved), precision_mode=mode,
                                                maximum_cached_engines=MAX_ENGINES, use_calibration=mode == "INT8")
            if mode == "INT8":
                data = calibration_data(request, step)
                # Batches of one: calibration builds the batch-1 engine, and build() below adds the batch-32 one
                # from the same calibration table.
                converted = converter.convert(calibration_input_fn=lambda: (
                    tuple(tf.constant(a) for a in take(data, slice(i, i + 1)).values()) for i in range(count(data))))
                meta["calibration"] = {"method": "entropy", "calibrator": CALIBRATOR,
                                       "calibration_samples": count(data), "batch": 1}
            else:
                converted = converter.convert()
            meta["engine_ops"] = engine_ops(converted.graph.as_graph_def())
            if not meta["engine_ops"]:
                raise RuntimeError(f"TF-TRT found no subgraph of {request.source.path} that TensorRT can run (no "
                                   f"TRTEngineOp in the converted graph): the cell would measure plain TensorFlow")
            converter.build(input_fn=lambda: (tuple(tf.zeros((n, *concrete(spec.shape)), _dtype(tf, spec))
                                                    for spec in inputs) for n in BUILD_BATCHES))
            with _temporary_files_in(tmp):  # save() serialises the engines into a mkdtemp() it never removes
                converter.save(str(request.out_dir))
        return meta

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        tf = tensorflow(threads)
        with tf.device(DEVICE):
            loaded = tf.saved_model.load(str(artifact_dir))
        facts = {key: meta[key] for key in ("precision_mode", "engine_ops", "calibration") if key in meta}
        return SignatureSession(loaded, DEVICE, facts)


def export_serving(model: Any, inputs: tuple[TensorSpec, ...], directory: Path) -> None:
    """Save the Keras model's inference call as a SavedModel whose serving signature takes batches of any size of
    every input (`input`, or input_0.. for several) and returns {"output": ...} (output_0.. in flat_outputs' order
    for several)."""
    tf = tensorflow()
    names = _names("input", len(inputs))
    specs = [tf.TensorSpec([None, *spec.shape], _dtype(tf, spec), name=name) for spec, name in zip(inputs, names)]

    @tf.function(input_signature=specs)
    def serve(*tensors: "tf.Tensor") -> dict[str, "tf.Tensor"]:
        outputs = flat_outputs(model(keras_arguments(tensors), training=False))
        return dict(zip(_names("output", len(outputs)), outputs))

    root = tf.Module()
    root.model_variables = list(model.variables)  # the variables the signature captures, without Keras' objects
    tf.saved_model.save(root, str(directory), signatures={SIGNATURE: serve.get_concrete_function()})


def _names(what: str, n: int) -> list[str]:
    """'input' for one tensor, input_0.. for several."""
    return [what] if n == 1 else [f"{what}_{i}" for i in range(n)]


def _dtype(tf: Any, spec: TensorSpec) -> Any:
    return tf.float32 if spec.dtype == "bfloat16" else tf.as_dtype(spec.dtype)


def engine_ops(graph_def: Any) -> int:
    """How many TRTEngineOp nodes a GraphDef holds, in its graph and in its function library."""
    nodes = [*graph_def.node, *(node for function in graph_def.library.function for node in function.node_def)]
    return sum(node.op == "TRTEngineOp" for node in nodes)


class SignatureSession(Session):
    """A SavedModel's serving signature (export_serving's names) run on `device`: inputs fed in order, every
    output returned in order."""

    def __init__(self, loaded: Any, device: str, facts: dict[str, Any]):
        tf = tensorflow()
        self._tf = tf
        self._loaded = loaded  # the signature's resources (engines, variables) live as long as this object
        self._function = loaded.signatures[SIGNATURE]
        _, inputs = self._function.structured_input_signature
        self._inputs = _names("input", len(inputs))
        self._outputs = _names("output", len(self._function.structured_outputs))
        if sorted(self._inputs) != sorted(inputs) or sorted(self._outputs) != sorted(self._function.structured_outputs):
            raise ValueError(f"the {SIGNATURE} signature has inputs {sorted(inputs)} and outputs "
                             f"{sorted(self._function.structured_outputs)}, not the ones bench-matrix exports")
        self._device = device
        self._sync = tf.test.experimental.sync_devices if "GPU" in device else None
        self._facts = facts
        # The first call loads the engines (or builds any missing one): part of load time, never of a timed call.
        first = {name: np.zeros((1, *(d or 1 for d in spec.shape[1:])), spec.dtype.as_numpy_dtype)
                 for name, spec in inputs.items()}
        self.execute(self.prepare({name: first[name] for name in self._inputs}))

    def prepare(self, inputs: Inputs) -> dict[str, "tf.Tensor"]:
        with self._tf.device(self._device):
            return {name: self._tf.identity(np.ascontiguousarray(
                array, dtype=np.float32 if np.issubdtype(array.dtype, np.floating) else None))
                for name, array in zip(self._inputs, inputs.values())}

    def execute(self, prepared: dict[str, "tf.Tensor"]) -> dict[str, "tf.Tensor"]:
        out = self._function(**prepared)
        if self._sync:
            self._sync()
        return out

    def fetch(self, outputs: dict[str, "tf.Tensor"]) -> list[np.ndarray]:
        return [np.asarray(outputs[name].numpy(), dtype=np.float32) for name in self._outputs]

    def info(self) -> dict[str, Any]:
        return {"device": self._device, "call_path": f"SavedModel signature {SIGNATURE}", **self._facts,
                **thread_settings()}


@contextmanager
def _temporary_files_in(directory: str) -> Iterator[None]:
    """Point Python's temporary files into `directory` for the duration."""
    previous = tempfile.tempdir
    tempfile.tempdir = directory
    try:
        yield
    finally:
        tempfile.tempdir = previous
