"""OpenVINO on the CPU and on the Intel GPU and NPU it finds: PyTorch, Keras and ONNX models through
their fp32 ONNX export; fp32 forced as fp32, bf16 and fp16 where the device computes them, int8 by NNCF
post-training quantisation."""

from __future__ import annotations

import importlib.util
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from bench_matrix.plugin import Backend, ConvertRequest, Inputs, Profile, Session, StrategySpec, Support, \
    installed_versions, onnx_work

from ._common import static_options_reason
from ._nncf import METHODS, quantise
from ._onnx_export import OPSET, fp32_model, graph_feeds
from ._openvino import DEVICES, OPTION_DEFAULTS, compile_config, device_name, device_reason, in_force, \
    INSTALL, missing_reason, openvino
from ._ov_profile import PERF_COUNT, ov_profile

if TYPE_CHECKING:
    import openvino as ov

FILE = "model.xml"  # OpenVINO IR: the graph, with its weights in model.bin beside it
FRAMEWORKS = ("pytorch", "tensorflow", "onnx")
TARGETS = tuple(DEVICES)
WEIGHTS = {"fp16": "float16", "int8": "int8"}  # how the IR stores the weights of each precision
EXPORTS = {"pytorch": f"torch.onnx (opset {OPSET})", "tensorflow": f"tf2onnx (opset {OPSET})",
           "onnx": "as given"}


class OpenVinoBackend(Backend):
    """Converts every source through its fp32 ONNX model into OpenVINO IR (quantised by NNCF for int8) and
    runs it compiled for the target's device and each batch's shapes, with synchronous infer requests."""

    name = "openvino"
    revision = 2  # 2: the manifest counts the fp32 graph's work
    description = ("OpenVINO on the CPU, Intel GPU and Intel NPU: fp32 (forced), bf16 and fp16 where the "
                   "device computes them, int8 by NNCF post-training quantisation")
    supports = (Support(FRAMEWORKS, ("none",), ("fp32", "fp16", "bf16"), TARGETS),
                Support(FRAMEWORKS, ("ptq_static",), ("int8",), TARGETS, convert_needs=("nncf",)))
    devices = {}  # not CUDA: the Intel GPU and NPU are timed from the host, as the CPU is
    options = {
        "hint": {"enum": ["latency", "throughput"], "default": "latency",
                 "description": "OpenVINO's PERFORMANCE_HINT at compile_model"},
        "streams": {"type": "integer", "minimum": 1, "maximum": 64, "default": 1,
                    "description": "NUM_STREAMS: inference streams (parallel requests) of a compiled model"},
        "pinning": {"type": "boolean", "default": True,
                    "description": "ENABLE_CPU_PINNING: pin the inference threads to cores (cpu only)"},
    }

    def versions(self) -> dict[str, str]:
        return installed_versions("openvino", "nncf", "onnx", "torch", "tf2onnx", "tensorflow")

    def probe(self, target: str, precision: str) -> str | None:
        return missing_reason() or device_reason(target, precision)

    def probe_source(self, framework: str, source_format: str) -> str | None:
        """Every source reaches OpenVINO as ONNX: onnx, and tf2onnx for Keras models."""
        if importlib.util.find_spec("onnx") is None:
            return f"onnx is not installed (models reach OpenVINO as ONNX): {INSTALL}"
        if framework != "tensorflow" or importlib.util.find_spec("tf2onnx") is not None:
            return None
        return "converting Keras models to ONNX needs tf2onnx, which is not installed (pip install tf2onnx)"

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        return static_options_reason(step, "OpenVINO", METHODS) if step.kind == "ptq_static" else None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        step = request.step
        if reason := self.option_reason(step, request.source.format):
            raise ValueError(reason)
        ov = openvino()
        quantisation = None
        with tempfile.TemporaryDirectory(prefix="bench-matrix-ov-", dir=request.scratch_dir) as tmp:
            model, feeds, batch, work = _fp32_model(request, Path(tmp))
            if step.kind == "ptq_static":
                model, quantisation = quantise(model, request, feeds, batch)
            # Saved, never kept: a converted model may share its weights' memory with what it was made from.
            # fp32 weights stay fp32 (save_model halves them to fp16 by default); fp16 cells get fp16 weights.
            ov.save_model(model, str(request.out_dir / FILE), compress_to_fp16=request.precision == "fp16")
        return {"file": FILE, "inputs": feeds, "batch": batch, "export": EXPORTS[request.source.framework],
                "strategy": step.kind, "weights": WEIGHTS.get(request.precision, "float32"), "work": work,
                "quantization": quantisation, "options": {**OPTION_DEFAULTS, **request.options}}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        core = openvino().Core()
        device = DEVICES[target]
        # OpenVINO 2026.4's CPU plugin computes zeros for int8 models compiled with a static batch of 4 or more
        # on AVX-512 machines (Xeon Sapphire Rapids; right with ONEDNN_MAX_CPU_ISA=AVX2 or a dynamic batch)
        compiler = Compiler(core, core.read_model(str(artifact_dir / meta["file"])), device,
                            compile_config(core, device, precision, meta["options"], threads),
                            static=precision != "int8")
        if single := compiler.batch_of_one():  # the latency batch, compiled (and checked) now
            compiler.for_shapes(single)
        return OpenVinoSession(compiler, meta["inputs"])


def _fp32_model(request: ConvertRequest, tmp: Path) -> tuple["ov.Model", dict[str, str], int | None, dict]:
    """The source's fp32 ONNX model (exported once per source into the shared directory), read by OpenVINO's
    ONNX frontend from a file; with the graph input each source input feeds, the graph's fixed batch and the
    ONNX graph's work (the same as onnxruntime's cells count)."""
    import onnx

    exported = fp32_model(request, tmp)
    feeds, batch = graph_feeds(exported, request.source)
    path = tmp / "fp32.onnx"
    onnx.save(exported, str(path))
    work = onnx_work(exported, request.source.inputs).to_json()
    return openvino().convert_model(str(path)), feeds, batch, work


class Compiler:
    """The model compiled for each set of input shapes it is fed (static shapes ran 3 % faster than a dynamic
    batch axis on PilotNet), or once with its own shapes (`static` False); refuses a compiled model computing
    in another precision than asked."""

    def __init__(self, core: "ov.Core", model: "ov.Model", device: str, config: dict[str, Any],
                 static: bool = True):
        self.core, self.model, self.device, self.config, self.static = core, model, device, config, static
        self.compiled: dict[tuple[tuple[int, tuple[int, ...]], ...], "ov.CompiledModel"] = {}
        self.ports = {name: port for port in model.inputs for name in port.get_names()}
        self.facts: dict[str, Any] = {"device": device, "device_name": device_name(core, device)}

    def batch_of_one(self) -> dict[str, tuple[int, ...]] | None:
        """Every input's shape at batch 1 (by graph input name), or None when another axis is free."""
        shapes = {}
        for port in self.model.inputs:
            dims = list(port.get_partial_shape())
            if any(d.is_dynamic for d in dims[1:]):
                return None
            shapes[port.get_any_name()] = (1 if dims[0].is_dynamic else dims[0].get_length(),
                                           *(d.get_length() for d in dims[1:]))
        return shapes

    def for_shapes(self, shapes: dict[str, tuple[int, ...]]) -> "ov.CompiledModel":
        self._check(shapes)
        key = tuple(sorted((self.ports[name].get_index(), shape) for name, shape in shapes.items()))
        key = key if self.static else ()
        if key not in self.compiled:
            compiled = self.core.compile_model(self._reshaped(shapes), self.device, self.config)
            found = in_force(compiled)
            wanted = self.config.get("INFERENCE_PRECISION_HINT")
            if wanted and found.get("inference_precision") != wanted:  # never a silent bf16 or f32 instead
                raise ValueError(f"asked OpenVINO's {self.device} for inference precision {wanted} but the "
                                 f"compiled model computes in {found.get('inference_precision')}")
            self.facts.update(found)
            self.compiled[key] = compiled
        return self.compiled[key]

    def profiling(self, shapes: dict[str, tuple[int, ...]]) -> "ov.CompiledModel":
        """The model compiled again for `shapes` as for_shapes does, with per-layer counters (PERF_COUNT)."""
        return self.core.compile_model(self._reshaped(shapes), self.device, {**self.config, **PERF_COUNT})

    def _check(self, shapes: dict[str, tuple[int, ...]]) -> None:
        """Refuse `shapes` (graph input name -> shape) that change a fixed axis of the model."""
        for name, shape in shapes.items():
            dims = list(self.ports[name].get_partial_shape())
            fixed = [d.get_length() if d.is_static else s for d, s in zip(dims, shape)]
            if len(dims) != len(shape) or tuple(fixed) != tuple(shape):
                raise ValueError(f"the OpenVINO model's input {name} takes "
                                 f"{self.ports[name].get_partial_shape()}, not {shape}")

    def _reshaped(self, shapes: dict[str, tuple[int, ...]]) -> "ov.Model":
        """The model with static `shapes` (as it is, unless `static`)."""
        if not self.static or all(self.ports[name].get_partial_shape().is_static for name in shapes):
            return self.model
        model = self.model.clone()
        model.reshape({name: list(shape) for name, shape in shapes.items()})
        return model


class Prepared(NamedTuple):
    """An infer request of the compiled model with a batch bound to it (the arrays are kept: the request
    reads them in place)."""

    request: "ov.InferRequest"
    arrays: dict[str, np.ndarray]


class OpenVinoSession(Session):
    """prepare binds a batch to an infer request of its own (of the model compiled for the batch's shapes),
    execute is one synchronous infer, fetch copies every output."""

    def __init__(self, compiler: Compiler, feeds: dict[str, str]):
        self._compiler = compiler
        self._feeds = feeds  # source input name -> graph input name
        self._dtypes = {name: port.get_element_type().to_dtype() for port in compiler.model.inputs
                        for name in port.get_names()}
        self._outputs = len(compiler.model.outputs)

    def prepare(self, inputs: Inputs) -> Prepared:
        ov = openvino()
        arrays = {graph: np.ascontiguousarray(inputs[name], dtype=self._dtypes[graph])
                  for name, graph in self._feeds.items()}
        compiled = self._compiler.for_shapes({graph: tuple(a.shape) for graph, a in arrays.items()})
        request = compiled.create_infer_request()
        for graph, array in arrays.items():
            request.set_tensor(graph, ov.Tensor(array, shared_memory=True))
        return Prepared(request, arrays)

    def execute(self, prepared: Prepared) -> Prepared:
        prepared.request.infer(share_outputs=True)  # synchronous: returns once the outputs are written
        return prepared

    def fetch(self, outputs: Prepared) -> list[np.ndarray]:
        return [np.array(outputs.request.get_output_tensor(i).data, dtype=np.float32)
                for i in range(self._outputs)]

    def profile(self, prepared: Prepared, calls: int) -> Profile:
        """Per layer, from a second compilation of the batch's model with PERF_COUNT (its config otherwise the
        same)."""
        compiled = self._compiler.profiling({graph: tuple(a.shape) for graph, a in prepared.arrays.items()})
        tensors = {graph: openvino().Tensor(array, shared_memory=True)
                   for graph, array in prepared.arrays.items()}
        return ov_profile(compiled, tensors, calls)

    def info(self) -> dict[str, Any]:
        return {**self._compiler.facts, "compiled_shapes": len(self._compiler.compiled)}
