"""ONNX Runtime on the CPU, CUDA or TensorRT, with fp16 conversion and int8 quantisation: QDQ on the CPU, a
calibration table for TensorRT, whose engines are built at conversion and kept in the artifact."""

from __future__ import annotations

import importlib.util
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.backends.base import Backend, ConvertRequest, Session, Support
from bench_matrix.matrix.expand import QAT_KINDS, backend_kind
from bench_matrix.matrix.spec import StrategySpec
from bench_matrix.measure.env import installed_versions
from bench_matrix.sources import ModelFileError
from bench_matrix.sources.onnx_file import load_onnx

from ._common import CALIBRATION_BATCH, batches, calibration_data, static_options_reason
from ._ort_gpu import CACHE_DIR, CALIBRATION_TABLE, DISTRIBUTIONS, DeviceSession, EngineSpec, build_engines, \
    open_session, probe_reasons, write_calibration_table
from ._torch import quiet_torch

if TYPE_CHECKING:
    import onnx
    import onnxruntime
    from onnxruntime.quantization import CalibrationDataReader

FILE = "model.onnx"
OPSET = 17
# The TensorRT libraries' wheels: engines are valid for one TensorRT version only.
TENSORRT = ("tensorrt-cu12-libs", "tensorrt-cu13-libs")
# quantize_static's own calibrator settings. "entropy" is not offered: ORT 1.31's entropy histogram (128 bins
# for 128 quantised bins) leaves the KL search one candidate, the full range, so it would calibrate exactly like
# "minmax" under another name.
METHODS = {"minmax": "MinMax", "percentile": "Percentile"}
FRAMEWORKS = ("pytorch", "tensorflow", "onnx")  # PyTorch through torch.onnx, Keras through tf2onnx


class OnnxRuntimeBackend(Backend):
    """Exports PyTorch and Keras models to ONNX (or takes ONNX files as given) and runs them with ONNX Runtime."""

    name = "onnxruntime"
    description = ("ONNX Runtime: CPU, CUDA and TensorRT providers; fp16 conversion, int8 QDQ quantisation (CPU) "
                   "and TensorRT int8 from a calibration table")
    supports = (Support(FRAMEWORKS, ("none",), ("fp32", "fp16"), ("cpu", "cuda", "tensorrt")),
                Support(FRAMEWORKS, ("ptq_dynamic", "ptq_static"), ("int8",), ("cpu",)),
                Support(FRAMEWORKS, ("ptq_static",), ("int8",), ("tensorrt",)),
                # a tfmot QAT model: tf2onnx turns its fake-quantisation into QuantizeLinear/DequantizeLinear pairs
                Support(("tensorflow",), QAT_KINDS, ("int8",), ("cpu",)))
    baseline_for = ("onnx",)

    def versions(self) -> dict[str, str]:
        return installed_versions(*DISTRIBUTIONS, *TENSORRT, "onnx", "torch", "tf2onnx", "tensorflow")

    def probe(self, target: str, precision: str) -> str | None:
        return None if target == "cpu" else "; ".join(probe_reasons(target, precision)) or None

    def probe_source(self, framework: str, source_format: str) -> str | None:
        if framework != "tensorflow" or importlib.util.find_spec("tf2onnx") is not None:
            return None
        return "converting Keras models to ONNX needs tf2onnx, which is not installed (pip install tf2onnx)"

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        return static_options_reason(step, "ONNX Runtime", tuple(METHODS)) if step.kind == "ptq_static" else None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        import onnx

        step = backend_kind(request.strategy)
        if reason := self.option_reason(step, request.source.format) or _tensorrt_option_reason(step, request):
            raise ValueError(reason)
        out = request.out_dir / FILE
        engines = None
        with tempfile.TemporaryDirectory(prefix="bench-matrix-ort-") as tmp:
            model = _fp32_model(request, Path(tmp))
            input_name, batch = _single_input(model, request.source.label)
            quantisation = None
            if request.target == "tensorrt":  # TensorRT builds its fp16 and int8 engines from the fp32 model
                onnx.save(model, str(out))
                quantisation, engines = _tensorrt(request, step, input_name, batch, Path(tmp))
            elif step.kind in ("ptq_dynamic", "ptq_static"):
                prepared = _pre_process(model, Path(tmp))
                quantisation = (_quantise_dynamic(prepared, step, out) if step.kind == "ptq_dynamic"
                                else _quantise_static(prepared, step, request, input_name, batch))
            elif step.kind in QAT_KINDS:  # the export already holds the learned int8 ranges as QDQ pairs
                onnx.save(model, str(out))
                quantisation = {"format": "QDQ", "ranges": "learned in quantisation-aware training",
                                "via": "tf2onnx (FakeQuantWithMinMaxVars -> QuantizeLinear/DequantizeLinear)"}
            elif request.precision == "fp16":
                from onnxruntime.transformers.float16 import convert_float_to_float16

                onnx.save(convert_float_to_float16(model, keep_io_types=True), str(out))
            else:
                onnx.save(model, str(out))
        opset = _opset(onnx.load(str(out), load_external_data=False))
        return {"file": FILE, "input_name": input_name, "opset": opset, "strategy": step.kind,
                "quantization": quantisation, **({"tensorrt": engines} if engines else {})}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        spec = EngineSpec.at_load(artifact_dir, meta) if target == "tensorrt" else None
        session = open_session(artifact_dir / meta["file"], target, precision, threads, spec)
        if target == "cpu":
            return OrtSession(session, meta["input_name"])
        return DeviceSession(session, meta["input_name"], "cuda")


class OrtSession(Session):
    """An InferenceSession with a single float32 input; execute is one sess.run and nothing else."""

    def __init__(self, session: "onnxruntime.InferenceSession", input_name: str):
        self._session = session
        self._run = session.run
        self._input = input_name

    def prepare(self, x: np.ndarray) -> dict[str, np.ndarray]:
        return {self._input: np.ascontiguousarray(x, dtype=np.float32)}

    def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self._run(None, prepared)

    def fetch(self, outputs: list[np.ndarray]) -> np.ndarray:
        return np.asarray(outputs[0], dtype=np.float32)

    def info(self) -> dict[str, Any]:
        return {"providers": self._session.get_providers(),
                "threads": self._session.get_session_options().intra_op_num_threads}


def _fp32_model(request: ConvertRequest, tmp: Path) -> "onnx.ModelProto":
    """The fp32 ONNX model: the ONNX source as is, or a PyTorch or Keras source exported with a dynamic batch
    axis (once per source: the export is kept in request.shared_dir for the other modes)."""
    import onnx

    source = request.source
    if source.framework == "onnx":  # checked, external data read in from the model's directory only
        return load_onnx(source.path, source.label)
    kept = request.shared_dir / "fp32.onnx" if request.shared_dir else None
    if kept and kept.is_file():
        return onnx.load(str(kept))
    model = _keras_to_onnx(request) if source.framework == "tensorflow" else _torch_to_onnx(request, tmp)
    if kept:
        partial = kept.with_name(f"fp32.onnx.tmp{os.getpid()}")
        onnx.save(model, str(partial))
        partial.replace(kept)
    return model


def _torch_to_onnx(request: ConvertRequest, tmp: Path) -> "onnx.ModelProto":
    """A PyTorch source through the TorchScript-based exporter, with a dynamic batch axis."""
    import onnx
    import torch

    source = request.source
    path = tmp / "exported.onnx"
    generator = torch.Generator().manual_seed(request.seed)
    example = torch.rand((2, *source.input_shape), generator=generator)
    with quiet_torch(captured=source.format == "torch_export"), torch.no_grad():
        module = source.load()
        if source.format == "torch_export":  # the TorchScript-based exporter cannot call .train() on it
            module = torch.jit.trace(module, example)
        torch.onnx.export(module, (example,), str(path), dynamo=False, opset_version=OPSET,
                          input_names=["input"], output_names=["output"],
                          dynamic_axes={"input": {0: "batch"}, "output": {0: "batch"}})
    return onnx.load(str(path))


def _keras_to_onnx(request: ConvertRequest) -> "onnx.ModelProto":
    """A Keras model through tf2onnx, with a dynamic batch axis; the layout (NHWC) stays the model's own."""
    from bench_matrix.sources.tensorflow import tensorflow

    tf = tensorflow(request.threads)
    import tf2onnx

    source = request.source
    signature = (tf.TensorSpec((None, *source.input_shape), tf.float32, name="input"),)
    model, _ = tf2onnx.convert.from_keras(source.load(), input_signature=signature, opset=OPSET)
    return model


def _single_input(model: "onnx.ModelProto", label: str) -> tuple[str, int | None]:
    """The name of the model's one input and its fixed batch size (None when the batch axis is dynamic)."""
    initializers = {init.name for init in model.graph.initializer}
    inputs = [i for i in model.graph.input if i.name not in initializers]
    if len(inputs) != 1:
        names = ", ".join(i.name for i in inputs)
        raise ModelFileError(f"{label}: the model has {len(inputs)} inputs ({names}); bench-matrix feeds "
                             f"exactly one image tensor: export a model with one input")
    dims = inputs[0].type.tensor_type.shape.dim
    return inputs[0].name, (dims[0].dim_value or None) if dims else None


def _opset(model: "onnx.ModelProto") -> int:
    return next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))


def _pre_process(model: "onnx.ModelProto", tmp: Path) -> Path:
    """The model after ONNX Runtime's recommended pre-quantisation pass (shape inference, optimisation)."""
    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    fp32, prepared = tmp / "fp32.onnx", tmp / "prepared.onnx"
    onnx.save(model, str(fp32))
    quant_pre_process(str(fp32), str(prepared))
    return prepared


def _quantise_dynamic(model: Path, step: StrategySpec, out: Path) -> dict[str, Any]:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    per_channel = bool(step.options.get("per_channel", False))
    # MatMul/Gemm only, like torch's dynamic quantisation of nn.Linear: ORT's ConvInteger is several times
    # slower than its fp32 convolution. Activations are quantised to uint8 at run time; 7-bit weights keep
    # AVX2's u8 x s8 pair sums within int16.
    ops = ["MatMul", "Gemm"]
    quantize_dynamic(model, out, op_types_to_quantize=ops, per_channel=per_channel, reduce_range=True,
                     weight_type=QuantType.QInt8)
    return {"ops": ops, "activations": "QUInt8 (dynamic)", "weights": "QInt8", "reduce_range": True,
            "per_channel": per_channel}


def _quantise_static(model: Path, step: StrategySpec, request: ConvertRequest, input_name: str,
                     batch: int | None) -> dict[str, Any]:
    """QDQ for the CPU: u8 activations and 7-bit s8 weights keep x86's VPMADDUBSW int16 pair sums unsaturated
    (no VNNI)."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    feeds = calibration_feeds(request, step, batch)
    per_channel = bool(step.options.get("per_channel", False))
    method = step.options.get("method", "minmax")
    quantize_static(model, request.out_dir / FILE, feed_reader(input_name, feeds), quant_format=QuantFormat.QDQ,
                    per_channel=per_channel, reduce_range=True, activation_type=QuantType.QUInt8,
                    weight_type=QuantType.QInt8, calibrate_method=getattr(CalibrationMethod, METHODS[method]))
    return {"format": "QDQ", "activations": "QUInt8", "weights": "QInt8", "reduce_range": True,
            "per_channel": per_channel, "method": method, "calibration_samples": sum(len(f) for f in feeds)}


def calibration_feeds(request: ConvertRequest, step: StrategySpec, batch: int | None) -> list[np.ndarray]:
    """The first `calibration_samples` samples of the calibration split, in the batches the calibrator runs."""
    data = calibration_data(request, step)
    if batch:  # a fixed batch size: whole batches only
        data = data[:len(data) - len(data) % batch]
        if len(data) == 0:
            raise ValueError(f"{request.source.path} takes batches of exactly {batch}: raise "
                             f"calibration_samples to at least {batch}")
    else:  # equal batches: the entropy and percentile calibrators cannot merge ragged ones
        batch = max(d for d in range(1, CALIBRATION_BATCH + 1) if len(data) % d == 0)
    return batches(data, batch)


def feed_reader(input_name: str, feeds: list[np.ndarray]) -> "CalibrationDataReader":
    """ONNX Runtime's calibration data reader over `feeds`."""
    from onnxruntime.quantization import CalibrationDataReader

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._feeds = iter([{input_name: f} for f in feeds])

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self._feeds, None)

    return Reader()


def _tensorrt_option_reason(step: StrategySpec, request: ConvertRequest) -> str | None:
    if request.target == "tensorrt" and step.kind == "ptq_static" and "per_channel" in step.options:
        return ("ONNX Runtime's TensorRT int8 has no per_channel setting (the calibration table ranges activations "
                "only; TensorRT chooses the weight scales itself); remove the option for target tensorrt")
    return None


def _tensorrt(request: ConvertRequest, step: StrategySpec, input_name: str, batch: int | None,
              tmp: Path) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """The calibration table (ptq_static) and the engines, built into the artifact's cache directory; returns the
    quantisation facts and the engines' metadata."""
    if ":" in input_name or "," in input_name:
        raise ValueError(f"{request.source.path}: the input {input_name!r} cannot be named in the TensorRT "
                         f"provider's shape profiles, which split at ':' and ','; rename the model's input")
    cache = request.out_dir / CACHE_DIR
    cache.mkdir()
    quantisation = None
    if step.kind == "ptq_static":
        feeds = calibration_feeds(request, step, batch)
        method = step.options.get("method", "minmax")
        tensors = write_calibration_table(request.out_dir / FILE, feed_reader(input_name, feeds), METHODS[method],
                                          cache)
        quantisation = {"format": "TensorRT calibration table", "table": f"{CACHE_DIR}/{CALIBRATION_TABLE}",
                        "method": method, "symmetric": True, "tensors": tensors,
                        "calibration_samples": sum(len(f) for f in feeds)}
    timing = (request.shared_dir or tmp) / "trt_timing_cache"  # layer timings, shared by the source's other modes
    timing.mkdir(exist_ok=True)
    spec = EngineSpec(input_name, request.source.input_shape, None if batch else request.max_batch, cache,
                      quantisation is not None, timing)
    engines = build_engines(request.out_dir / FILE, request.precision, request.threads, spec,
                            _engine_feeds(request, batch))
    return quantisation, {**spec.to_meta(), "engines": engines}


def _engine_feeds(request: ConvertRequest, batch: int | None) -> list[np.ndarray]:
    """Calibration samples at every batch size an engine must serve: the model's fixed one, else 1 and max_batch
    (zeros when the calibration split is empty: the engines depend on shapes only)."""
    shape = request.source.input_shape
    sizes = [batch] if batch else sorted({1, request.max_batch})
    samples = np.asarray(request.calibration(max(sizes)), dtype=np.float32)
    if len(samples) == 0:
        samples = np.zeros((1, *shape), np.float32)
    return [np.resize(samples, (n, *shape)) for n in sizes]
