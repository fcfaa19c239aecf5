"""TensorFlow Lite on the CPU: Keras models converted to .tflite in fp32, fp16, dynamic-range or integer modes."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from bench_matrix.backends.base import Backend, ConvertRequest, Session, Support
from bench_matrix.matrix.expand import QAT_KINDS, backend_kind
from bench_matrix.matrix.spec import StrategySpec
from bench_matrix.sources.tensorflow import tensorflow

from ._common import calibration_data
from ._tf import missing_tensorflow, tf_versions

FILE = "model.tflite"
KERAS_FORMATS = ("keras", "h5", "saved_model", "keras_qat")


class TFLiteBackend(Backend):
    """Converts Keras models with TFLiteConverter and runs them with the LiteRT (TFLite) interpreter."""

    name = "tflite"
    description = ("TensorFlow Lite (LiteRT interpreter) on the CPU: fp32, fp16 weights, dynamic-range int8, "
                   "integer int8 with float or int8 inputs and outputs")
    supports = (Support(("tensorflow",), ("none",), ("fp32", "fp16"), ("cpu",)),
                Support(("tensorflow",), ("ptq_dynamic", "ptq_static", *QAT_KINDS), ("int8",), ("cpu",)))

    def versions(self) -> dict[str, str]:
        return tf_versions("ai-edge-litert")

    def probe(self, target: str, precision: str) -> str | None:
        return missing_tensorflow()  # TFLiteConverter is TensorFlow's

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        """Keras sources only; per-channel weights and min/max calibration are what TFLite's converter does."""
        if source_format not in KERAS_FORMATS:
            return (f"tflite converts Keras models (.keras, .h5 or a Keras SavedModel) with "
                    f"TFLiteConverter.from_keras_model, not {source_format!r} sources")
        if step.kind in ("ptq_dynamic", "ptq_static") and not step.options.get("per_channel", True):
            return ("TFLite's converter quantises the weights of convolutions and dense layers per output channel "
                    "(one scale per channel) in ptq_dynamic and ptq_static; per-tensor weights (per_channel: "
                    "false) are not available through its public API; remove the option or set per_channel: true")
        if step.kind == "ptq_static" and (method := step.options.get("method", "minmax")) != "minmax":
            return (f"TFLite calibrates with the min/max of the representative dataset, not {method!r}; remove "
                    f"the option or use method: minmax")
        return None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        step = backend_kind(request.strategy)
        if reason := (self.invalid_reason(request.source.framework, step.kind, request.precision, request.target)
                      or self.option_reason(step, request.source.format)):
            raise ValueError(reason)
        tf = tensorflow(request.threads)
        converter = tf.lite.TFLiteConverter.from_keras_model(request.source.load())
        settings = _configure(converter, tf, step, request)
        with warnings.catch_warnings():
            # ptq_static conversion warns that no input statistics were given: calibration supplies them.
            warnings.filterwarnings("ignore", message="Statistics for quantized inputs were expected")
            try:
                content = converter.convert()
            except Exception as exc:  # the converter's errors name the op it could not convert
                hint = "; with io: float, ops without int8 kernels stay float" if settings["io"] == "int8" else ""
                raise ValueError(f"TFLiteConverter cannot convert {request.source.name} to a {settings['mode']} "
                                 f"model: {type(exc).__name__}: {exc}{hint}") from exc
        (request.out_dir / FILE).write_bytes(content)
        return {"file": FILE, "strategy": step.kind, **settings}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return TFLiteSession((artifact_dir / meta["file"]).read_bytes(), threads)


def _configure(converter: Any, tf: Any, step: StrategySpec, request: ConvertRequest) -> dict[str, Any]:
    """Set the converter up for the step and precision; return the mode, io type and quantisation settings."""
    if step.kind == "none" and request.precision == "fp32":
        return {"mode": "fp32", "io": "float"}
    converter.optimizations = [tf.lite.Optimize.DEFAULT]
    if step.kind == "none":  # fp16
        converter.target_spec.supported_types = [tf.float16]
        return {"mode": "fp16", "io": "float",
                "quantization": {"weights": "float16", "activations": "float32"}}
    if step.kind in QAT_KINDS:  # quantisation-aware trained: int8 with the ranges learned in fine-tuning
        return {"mode": "qat", "io": "float",
                "quantization": {"weights": "int8", "activations": "int8, ranges learned by fake quantisation"}}
    if step.kind == "ptq_dynamic":  # no representative dataset: weights only, activations quantised at run time
        return {"mode": "dynamic_range", "io": "float",
                "quantization": {"weights": "int8", "per_channel": True,
                                 "activations": "float32, quantised to int8 at run time by the int8 kernels"}}
    data = calibration_data(request, step)

    def representative() -> Iterator[list[np.ndarray]]:
        for i in range(len(data)):
            yield [data[i:i + 1]]

    converter.representative_dataset = representative
    io = step.options.get("io", "float")
    if io == "int8":
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
        converter.inference_input_type = tf.int8
        converter.inference_output_type = tf.int8
    return {"mode": "full_integer" if io == "int8" else "integer_float_fallback", "io": io,
            "quantization": {"weights": "int8", "per_channel": True, "activations": "int8", "method": "minmax",
                             "calibration_samples": len(data)}}


def interpreter_class() -> tuple[type, str]:
    """The LiteRT interpreter when ai_edge_litert is installed, else TensorFlow's own; with its name and version."""
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:
        tf = tensorflow()
        return tf.lite.Interpreter, f"tensorflow.lite {tf.__version__}"
    return Interpreter, f"ai_edge_litert {version('ai-edge-litert')}"


class Prepared(NamedTuple):
    """What one timed call needs: the interpreter sized for the batch, its tensor indices and the input."""

    interpreter: Any
    input_index: int
    output_index: int
    x: np.ndarray


class TFLiteSession(Session):
    """One interpreter per batch size, made in `prepare`; execute is set_tensor + invoke + get_tensor."""

    def __init__(self, content: bytes, threads: int):
        self._content = content
        self._threads = threads
        self._class, self._interpreter_name = interpreter_class()
        self._interpreters: dict[int, Any] = {}
        first = self._interpreter(1)
        self._input = first.get_input_details()[0]
        self._output = first.get_output_details()[0]

    def _interpreter(self, batch: int) -> Any:
        """The interpreter whose input is resized to `batch` samples, with its tensors allocated."""
        if batch not in self._interpreters:
            interpreter = self._class(model_content=self._content, num_threads=self._threads)
            detail = interpreter.get_input_details()[0]
            interpreter.resize_tensor_input(detail["index"], [batch, *detail["shape"][1:]], strict=True)
            interpreter.allocate_tensors()
            self._interpreters[batch] = interpreter
        return self._interpreters[batch]

    def prepare(self, x: np.ndarray) -> Prepared:
        x = np.ascontiguousarray(x, dtype=np.float32)
        sample = tuple(self._input["shape"][1:])
        if x.shape[1:] != sample:
            raise ValueError(f"the TFLite model takes samples of shape {sample}, not {x.shape[1:]}")
        dtype = self._input["dtype"]
        if np.issubdtype(dtype, np.integer):  # a full-integer model: quantise with the input's scale and zero point
            scale, zero_point = self._input["quantization"]
            limits = np.iinfo(dtype)
            x = np.clip(np.round(x / scale + zero_point), limits.min, limits.max).astype(dtype)
        return Prepared(self._interpreter(len(x)), self._input["index"], self._output["index"], x)

    def execute(self, prepared: Prepared) -> np.ndarray:
        interpreter, input_index, output_index, x = prepared
        interpreter.set_tensor(input_index, x)
        interpreter.invoke()  # synchronous: the outputs are ready when it returns
        return interpreter.get_tensor(output_index)  # a copy, safe from the next invoke

    def fetch(self, outputs: np.ndarray) -> np.ndarray:
        if np.issubdtype(outputs.dtype, np.integer):
            # Integer outputs are quantised values: without (q - zero_point) * scale they are off by orders of
            # magnitude (a study that skipped this step reported an MSE of 28157).
            scale, zero_point = self._output["quantization"]
            return (outputs.astype(np.float32) - np.float32(zero_point)) * np.float32(scale)
        return np.asarray(outputs, dtype=np.float32)

    def info(self) -> dict[str, Any]:
        return {"interpreter": self._interpreter_name, "threads": self._threads,
                "input": _tensor_info(self._input), "output": _tensor_info(self._output)}


def _tensor_info(detail: dict[str, Any]) -> dict[str, Any]:
    """A tensor's dtype, with its scale and zero point when it is quantised."""
    info: dict[str, Any] = {"dtype": np.dtype(detail["dtype"]).name}
    scale, zero_point = detail["quantization"]
    if scale:
        info.update(scale=float(scale), zero_point=int(zero_point))
    return info
