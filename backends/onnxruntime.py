"""ONNX Runtime on the CPU, CUDA or TensorRT, with fp16 conversion and int8 quantisation: QDQ on the CPU, a
calibration table for TensorRT, whose engines are built at conversion and kept in the artifact."""

from __future__ import annotations

import contextlib
import importlib.util
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import QAT_KINDS, Backend, ConvertRequest, Inputs, Profile, Session, StrategySpec, \
    Support, count, installed_versions, onnx_work, resize

from ._common import CALIBRATION_BATCH, batches, calibration_data, static_options_reason
from ._onnx_export import fp32_model, graph_feeds, opset
from ._ort_profile import ort_profile
from ._ort_gpu import CACHE_DIR, CALIBRATION_TABLE, DISTRIBUTIONS, DeviceSession, EngineSpec, build_engines, \
    feed_dtypes, open_session, probe_reasons, profile_reason, write_calibration_table

if TYPE_CHECKING:
    import onnx
    import onnxruntime
    from onnxruntime.quantization import CalibrationDataReader

FILE = "model.onnx"
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
    # 2: the quantisation pre-pass falls back where it fails; 3: it runs in a relative scratch folder; 4: the
    # manifest counts the fp32 graph's work
    revision = 4
    description = ("ONNX Runtime: CPU, CUDA and TensorRT providers; fp16 conversion, int8 QDQ quantisation (CPU) "
                   "and TensorRT int8 from a calibration table")
    supports = (Support(FRAMEWORKS, ("none",), ("fp32", "fp16"), ("cpu", "cuda", "tensorrt")),
                Support(FRAMEWORKS, ("ptq_dynamic", "ptq_static"), ("int8",), ("cpu",)),
                Support(FRAMEWORKS, ("ptq_static",), ("int8",), ("tensorrt",)),
                # a tfmot QAT model: tf2onnx turns its fake-quantisation into QuantizeLinear/DequantizeLinear pairs
                Support(("tensorflow",), QAT_KINDS, ("int8",), ("cpu",)))
    baseline_for = ("onnx",)
    devices = {"cuda": "cuda", "tensorrt": "cuda"}  # the TensorRT provider runs on the NVIDIA GPU

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

        step = request.step
        if reason := _tensorrt_option_reason(step, request):
            raise ValueError(reason)
        out = request.out_dir / FILE
        engines = None
        with tempfile.TemporaryDirectory(prefix="bench-matrix-ort-", dir=request.scratch_dir) as tmp:
            model = fp32_model(request, Path(tmp))
            feeds, batch = graph_feeds(model, request.source)
            work = onnx_work(model, request.source.inputs).to_json()  # the fp32 graph's: every mode the same
            quantisation = None
            if request.target == "tensorrt":  # TensorRT builds its fp16 and int8 engines from the fp32 model
                onnx.save(model, str(out))
                quantisation, engines = _tensorrt(request, step, feeds, batch, Path(tmp))
            elif step.kind in ("ptq_dynamic", "ptq_static"):
                prepared, pre_processed = _pre_process(model, Path(tmp))
                quantisation = (_quantise_dynamic(prepared, step, out) if step.kind == "ptq_dynamic"
                                else _quantise_static(prepared, step, request, feeds, batch))
                quantisation["pre_process"] = pre_processed
            elif step.kind in QAT_KINDS:  # the export already holds the learned int8 ranges as QDQ pairs
                onnx.save(model, str(out))
                quantisation = {"format": "QDQ", "ranges": "learned in quantisation-aware training",
                                "via": "tf2onnx (FakeQuantWithMinMaxVars -> QuantizeLinear/DequantizeLinear)"}
            elif request.precision == "fp16":
                from onnxruntime.transformers.float16 import convert_float_to_float16

                onnx.save(convert_float_to_float16(model, keep_io_types=True), str(out))
            else:
                onnx.save(model, str(out))
        return {"file": FILE, "inputs": feeds, "opset": opset(onnx.load(str(out), load_external_data=False)),
                "strategy": step.kind, "quantization": quantisation, "work": work,
                **({"tensorrt": engines} if engines else {})}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        spec = EngineSpec.at_load(artifact_dir, meta) if target == "tensorrt" else None
        model = artifact_dir / meta["file"]
        session = open_session(model, target, precision, threads, spec)
        found = OrtSession(session, meta["inputs"], partial(_profiled_session, model, precision, threads)) \
            if target == "cpu" else DeviceSession(session, meta["inputs"], "cuda")
        found.quantization = meta.get("quantization")  # how it was quantised, for the record (session)
        return found


class OrtSession(Session):
    """An InferenceSession fed every named input; execute is one sess.run and nothing else."""

    def __init__(self, session: "onnxruntime.InferenceSession", feeds: dict[str, str],
                 open_profiled: Callable[[str], "onnxruntime.InferenceSession"]):
        self._session = session
        self._open_profiled = open_profiled  # profile file prefix -> a profiling session like this one
        self._run = session.run
        self._feeds = feeds  # source input name -> graph input name
        self._dtypes = feed_dtypes(session)
        self.quantization: dict[str, Any] | None = None

    def prepare(self, inputs: Inputs) -> dict[str, np.ndarray]:
        """The feed dict: each input contiguous, in the dtype its graph input takes (converted here, untimed)."""
        return {graph: np.ascontiguousarray(inputs[name], dtype=self._dtypes.get(graph))
                for name, graph in self._feeds.items()}

    def execute(self, prepared: dict[str, np.ndarray]) -> list[np.ndarray]:
        return self._run(None, prepared)

    def profile(self, prepared: dict[str, np.ndarray], calls: int) -> Profile:
        """Per node, from a second session with ONNX Runtime's profiling on (its options otherwise the same)."""
        return ort_profile(self._open_profiled, prepared, calls)

    def info(self) -> dict[str, Any]:
        return {"providers": self._session.get_providers(),
                "threads": self._session.get_session_options().intra_op_num_threads,
                **({"quantization": self.quantization} if self.quantization else {})}


def _profiled_session(model: Path, precision: str, threads: int, prefix: str) -> "onnxruntime.InferenceSession":
    """A CPU session on `model` as `load` opens it, profiling into files starting `prefix`."""
    return open_session(model, "cpu", precision, threads, profile_prefix=prefix)


def _pre_process(model: "onnx.ModelProto", tmp: Path) -> tuple[Path, dict[str, str]]:
    """The model after ONNX Runtime's recommended pre-quantisation pass (shape inference, optimisation), and
    what was applied. Optional steps: where ONNX Runtime's symbolic shape inference fails (tf2onnx's int64
    gathers; it asserts on transformer graphs), ONNX's own is used; where that fails too, none."""
    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    tmp = tmp.absolute()  # a run's scratch directory is relative to the project, and the pass works inside it
    fp32, prepared = tmp / "fp32.onnx", tmp / "prepared.onnx"
    onnx.save(model, str(fp32))
    failed: list[str] = []
    with contextlib.chdir(tmp):  # where it gives up, it saves sym_shape_infer_temp.onnx in the working directory
        for how, skip in (("full", False), ("without symbolic shape inference", True)):
            try:
                quant_pre_process(str(fp32), str(prepared), skip_symbolic_shape=skip)
                return prepared, {"applied": how, **({"failed": " | ".join(failed)} if failed else {})}
            except Exception as exc:  # any: the pass is optional
                failed.append(f"{how}: {type(exc).__name__}: {_first_line(exc)}")
    return fp32, {"applied": "none", "failed": " | ".join(failed)}


def _first_line(exc: Exception) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else "(no message)"


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


def _quantise_static(model: Path, step: StrategySpec, request: ConvertRequest, names: dict[str, str],
                     batch: int | None) -> dict[str, Any]:
    """QDQ for the CPU: u8 activations and 7-bit s8 weights keep x86's VPMADDUBSW int16 pair sums unsaturated
    (no VNNI). Integer inputs (token ids, masks) feed the calibration as they are and stay unquantised."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    feeds = calibration_feeds(request, step, names, batch)
    per_channel = bool(step.options.get("per_channel", False))
    method = step.options.get("method", "minmax")
    quantize_static(model, request.out_dir / FILE, feed_reader(feeds), quant_format=QuantFormat.QDQ,
                    per_channel=per_channel, reduce_range=True, activation_type=QuantType.QUInt8,
                    weight_type=QuantType.QInt8, calibrate_method=getattr(CalibrationMethod, METHODS[method]))
    return {"format": "QDQ", "activations": "QUInt8", "weights": "QInt8", "reduce_range": True,
            "per_channel": per_channel, "method": method, "calibration_samples": sum(map(count, feeds))}


def calibration_feeds(request: ConvertRequest, step: StrategySpec, names: dict[str, str],
                      batch: int | None) -> list[Inputs]:
    """The first `calibration_samples` samples of the calibration split, in the batches the calibrator runs,
    each a feed of every graph input (`names`: source input name -> graph input name)."""
    data = calibration_data(request, step)
    n = count(data)
    if batch:  # a fixed batch size: whole batches only
        n -= n % batch
        if n == 0:
            raise ValueError(f"{request.source.path} takes batches of exactly {batch}: raise "
                             f"calibration_samples to at least {batch}")
    else:  # equal batches: the entropy and percentile calibrators cannot merge ragged ones
        batch = max(d for d in range(1, CALIBRATION_BATCH + 1) if n % d == 0)
    graph = {names[name]: array[:n] for name, array in data.items()}
    return batches(graph, batch)


def feed_reader(feeds: list[Inputs]) -> "CalibrationDataReader":
    """ONNX Runtime's calibration data reader over `feeds`."""
    from onnxruntime.quantization import CalibrationDataReader

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self._feeds = iter(feeds)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self._feeds, None)

    return Reader()


def _tensorrt_option_reason(step: StrategySpec, request: ConvertRequest) -> str | None:
    if request.target == "tensorrt" and step.kind == "ptq_static" and "per_channel" in step.options:
        return ("ONNX Runtime's TensorRT int8 has no per_channel setting (the calibration table ranges activations "
                "only; TensorRT chooses the weight scales itself); remove the option for target tensorrt")
    return None


def _tensorrt(request: ConvertRequest, step: StrategySpec, names: dict[str, str], batch: int | None,
              tmp: Path) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """The calibration table (ptq_static) and the engines, built into the artifact's cache directory; returns the
    quantisation facts and the engines' metadata."""
    shapes = tuple((names[spec.name], spec.shape) for spec in request.source.inputs)
    if reason := profile_reason(shapes):
        raise ValueError(f"{request.source.label}: {reason}")
    cache = request.out_dir / CACHE_DIR
    cache.mkdir()
    quantisation = None
    if step.kind == "ptq_static":
        feeds = calibration_feeds(request, step, names, batch)
        method = step.options.get("method", "minmax")
        tensors = write_calibration_table(request.out_dir / FILE, feed_reader(feeds), METHODS[method], cache)
        quantisation = {"format": "TensorRT calibration table", "table": f"{CACHE_DIR}/{CALIBRATION_TABLE}",
                        "method": method, "symmetric": True, "tensors": tensors,
                        "calibration_samples": sum(map(count, feeds))}
    timing = (request.shared_dir or tmp) / "trt_timing_cache"  # layer timings, shared by the source's other modes
    timing.mkdir(exist_ok=True)
    spec = EngineSpec(shapes, None if batch else request.max_batch, cache, quantisation is not None, timing)
    engines = build_engines(request.out_dir / FILE, request.precision, request.threads, spec,
                            _engine_feeds(request, names, batch))
    return quantisation, {**spec.to_meta(), "engines": engines}


def _engine_feeds(request: ConvertRequest, names: dict[str, str], batch: int | None) -> list[Inputs]:
    """Calibration samples at every batch size an engine must serve: the model's fixed one, else 1 and max_batch
    (zeros when the calibration split is empty: the engines depend on shapes only)."""
    sizes = [batch] if batch else sorted({1, request.max_batch})
    samples = request.calibration(max(sizes))
    if count(samples) == 0:
        samples = {spec.name: np.zeros((1, *spec.shape), np.float32 if spec.dtype == "bfloat16" else spec.dtype)
                   for spec in request.source.inputs}
    return [{names[name]: array for name, array in resize(samples, n).items()} for n in sizes]
