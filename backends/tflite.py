"""TensorFlow Lite on the CPU: Keras models converted to .tflite in fp32, fp16, dynamic-range or integer modes."""

from __future__ import annotations

import importlib.util
import warnings
from collections.abc import Iterator
from importlib.metadata import version
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from bench_matrix.plugin import QAT_KINDS, Backend, ConvertRequest, Inputs, Profile, Session, StrategySpec, \
    Support, count, take, tensorflow

from ._common import calibration_data
from ._tf import missing_tensorflow, tf_versions

FILE = "model.tflite"
KERAS_FORMATS = ("keras", "h5", "saved_model", "keras_qat")
NO_OP_PROFILER = ("its Python Interpreter gives no per-operator times (no profiler API), and the op profiler "
                  "of LiteRT's C++ benchmark_model (--enable_op_profiling=true) is in neither pip package: "
                  "ai-edge-litert's litert-benchmark times whole runs only. A benchmark_model binary built "
                  "from LiteRT's sources would give them")


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
        """Running needs LiteRT's interpreter, or TensorFlow's own where LiteRT is not installed."""
        if importlib.util.find_spec("ai_edge_litert") is None and missing_tensorflow():
            return ("running .tflite files needs LiteRT (pip install ai-edge-litert) or TensorFlow: "
                    "neither is installed")
        return None

    def probe_source(self, framework: str, source_format: str) -> str | None:
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
        step = request.step
        if reason := self.invalid_reason(request.source.framework, step.kind, request.precision, request.target):
            raise ValueError(reason)
        tf = tensorflow(request.threads)
        model = request.source.load()
        converter = tf.lite.TFLiteConverter.from_keras_model(model)
        settings = _configure(converter, tf, step, request, list(model.input_names))
        with warnings.catch_warnings():
            # ptq_static conversion warns that no input statistics were given: calibration supplies them.
            warnings.filterwarnings("ignore", message="Statistics for quantized inputs were expected")
            # Calibrating by input name runs TensorFlow's own interpreter, which warns of its deprecation.
            warnings.filterwarnings("ignore", message=".*tf.lite.Interpreter is deprecated")
            try:
                content = converter.convert()
            except Exception as exc:  # the converter's errors name the op it could not convert
                hint = "; with io: float, ops without int8 kernels stay float" if settings["io"] == "int8" else ""
                raise ValueError(f"TFLiteConverter cannot convert {request.source.name} to a {settings['mode']} "
                                 f"model: {type(exc).__name__}: {exc}{hint}") from exc
        (request.out_dir / FILE).write_bytes(content)
        # The signature's inputs and outputs by the Keras model's names, in its order: TFLite reorders both.
        return {"file": FILE, "strategy": step.kind, "inputs": list(model.input_names),
                "outputs": list(model.output_names), **settings}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        return TFLiteSession((artifact_dir / meta["file"]).read_bytes(), threads, meta["inputs"], meta["outputs"])


def _configure(converter: Any, tf: Any, step: StrategySpec, request: ConvertRequest,
               keras_names: list[str]) -> dict[str, Any]:
    """Set the converter up for the step and precision; return the mode, io type and quantisation settings.
    Calibration samples are given by the Keras model's input names (`keras_names`, in the model's order)."""
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

    def representative() -> Iterator[list[np.ndarray] | dict[str, np.ndarray]]:
        for i in range(count(data)):
            sample = list(take(data, slice(i, i + 1)).values())
            # Several inputs by name: the converter orders them its own way (a list would go by that order).
            yield dict(zip(keras_names, sample)) if len(sample) > 1 else sample

    converter.representative_dataset = representative
    io = step.options.get("io", "float")
    if io == "int8":  # float inputs and outputs become int8; integer inputs (token ids) stay as they are
        converter.target_spec.supported_ops = [tf.lite.OpsSet.TFLITE_BUILTINS_INT8]
        converter.inference_input_type = tf.int8
        converter.inference_output_type = tf.int8
    return {"mode": "full_integer" if io == "int8" else "integer_float_fallback", "io": io,
            "quantization": {"weights": "int8", "per_channel": True, "activations": "int8", "method": "minmax",
                             "calibration_samples": count(data)}}


def interpreter_class() -> tuple[type, str]:
    """The LiteRT interpreter when ai_edge_litert is installed, else TensorFlow's own; with its name and version."""
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:
        tf = tensorflow()
        return tf.lite.Interpreter, f"tensorflow.lite {tf.__version__}"
    return Interpreter, f"ai_edge_litert {version('ai-edge-litert')}"


class Prepared(NamedTuple):
    """What one timed call needs: the interpreter sized for the batch, each input's tensor index and array, and the
    output tensors' indices."""

    interpreter: Any
    inputs: tuple[tuple[int, np.ndarray], ...]
    outputs: tuple[int, ...]


class TFLiteSession(Session):
    """One interpreter per set of input shapes, made in `prepare`; execute is set_tensor + invoke + get_tensor.
    Inputs are fed and outputs returned in the Keras model's order (`inputs`, `outputs`: its names)."""

    def __init__(self, content: bytes, threads: int, inputs: list[str], outputs: list[str]):
        self._content = content
        self._threads = threads
        self._class, self._interpreter_name = interpreter_class()
        self._interpreters: dict[tuple[tuple[int, ...], ...], Any] = {}
        first = self._class(model_content=content, num_threads=threads)
        runner = first.get_signature_runner()
        self._inputs = _in_order(inputs, runner.get_input_details(), first.get_input_details(), "input")
        self._outputs = _in_order(outputs, runner.get_output_details(), first.get_output_details(), "output")

    def _interpreter(self, shapes: tuple[tuple[int, ...], ...]) -> Any:
        """The interpreter whose inputs are resized to `shapes`, with its tensors allocated."""
        if shapes not in self._interpreters:
            interpreter = self._class(model_content=self._content, num_threads=self._threads)
            for detail, shape in zip(self._inputs, shapes):
                interpreter.resize_tensor_input(detail["index"], list(shape), strict=True)
            interpreter.allocate_tensors()
            self._interpreters[shapes] = interpreter
        return self._interpreters[shapes]

    def prepare(self, inputs: Inputs) -> Prepared:
        arrays = [_feed(detail, array) for detail, array in zip(self._inputs, inputs.values())]
        interpreter = self._interpreter(tuple(a.shape for a in arrays))
        return Prepared(interpreter, tuple((d["index"], a) for d, a in zip(self._inputs, arrays)),
                        tuple(d["index"] for d in self._outputs))

    def execute(self, prepared: Prepared) -> list[np.ndarray]:
        interpreter = prepared.interpreter
        for index, array in prepared.inputs:
            interpreter.set_tensor(index, array)
        interpreter.invoke()  # synchronous: the outputs are ready when it returns
        return [interpreter.get_tensor(index) for index in prepared.outputs]  # copies, safe from the next invoke

    def fetch(self, outputs: list[np.ndarray]) -> list[np.ndarray]:
        return [_dequantised(detail, out) for detail, out in zip(self._outputs, outputs)]

    def profile(self, prepared: Prepared, calls: int) -> Profile:
        """None: no interpreter reachable from Python times its ops (docs/metrics.md, Profiles)."""
        return Profile(reason=f"{self._interpreter_name}: {NO_OP_PROFILER}")

    def info(self) -> dict[str, Any]:
        return {"interpreter": self._interpreter_name, "threads": self._threads,
                "input": _tensors_info(self._inputs), "output": _tensors_info(self._outputs)}


def _in_order(names: list[str], signature: dict[str, Any], details: list[dict[str, Any]],
              what: str) -> list[dict[str, Any]]:
    """The interpreter's tensor details of the signature's `names`, in that order."""
    if sorted(names) != sorted(signature):
        raise ValueError(f"the TFLite model's signature has {what}s {sorted(signature)}, not the Keras model's "
                         f"{names}: convert it again")
    by_index = {d["index"]: d for d in details}
    return [by_index[signature[name]["index"]] for name in names]


def _feed(detail: dict[str, Any], array: np.ndarray) -> np.ndarray:
    """`array` as the input tensor takes it: float samples quantised with its scale and zero point where a
    full-integer model takes int8, else in its dtype; ValueError for a sample shape it cannot take."""
    expected = tuple(detail["shape_signature"][1:])
    if len(array.shape) != len(expected) + 1 or any(e not in (-1, a) for e, a in zip(expected, array.shape[1:])):
        sample = tuple(None if d == -1 else int(d) for d in expected)
        raise ValueError(f"the TFLite model's input {detail['name']} takes samples of shape {sample}, "
                         f"not {array.shape[1:]}")
    dtype = detail["dtype"]
    scale, zero_point = detail["quantization"]
    if np.issubdtype(dtype, np.integer) and scale and np.issubdtype(array.dtype, np.floating):
        limits = np.iinfo(dtype)
        return np.clip(np.round(array / scale + zero_point), limits.min, limits.max).astype(dtype)
    return np.ascontiguousarray(array, dtype=dtype)


def _dequantised(detail: dict[str, Any], out: np.ndarray) -> np.ndarray:
    """An output as float32: quantised integers as (q - zero_point) * scale. Without it they are off by orders of
    magnitude (a study that skipped this step reported an MSE of 28157)."""
    scale, zero_point = detail["quantization"]
    if np.issubdtype(out.dtype, np.integer) and scale:
        return (out.astype(np.float32) - np.float32(zero_point)) * np.float32(scale)
    return np.asarray(out, dtype=np.float32)


def _tensors_info(details: list[dict[str, Any]]) -> dict[str, Any] | list[dict[str, Any]]:
    """The tensors' dtypes, with scale and zero point where quantised: one dict for a single tensor, else a list."""
    infos = [_tensor_info(d) for d in details]
    return infos[0] if len(infos) == 1 else infos


def _tensor_info(detail: dict[str, Any]) -> dict[str, Any]:
    """A tensor's dtype, with its scale and zero point when it is quantised."""
    info: dict[str, Any] = {"dtype": np.dtype(detail["dtype"]).name}
    scale, zero_point = detail["quantization"]
    if scale:
        info.update(scale=float(scale), zero_point=int(zero_point))
    return info
