"""Torch-TensorRT: a PyTorch model compiled ahead of time into TensorRT engines by the dynamo frontend, saved with
its engines as an ExportedProgram and run by torch on the GPU; fp32, fp16, and int8 calibrated by NVIDIA ModelOpt."""

from __future__ import annotations

import importlib.util
import inspect
import re
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any


from bench_matrix.plugin import Backend, ConvertRequest, Session, SourceModel, StrategySpec, Support, \
    TensorSpec, count, example_inputs, installed_versions, specs_from_list, specs_to_list

from ._common import batches, calibration_data, static_options_reason
from ._torch import (
    TorchSession,
    as_tensors,
    cuda_reasons,
    example_tensors,
    missing_torch,
    pin_threads,
    place,
    quiet_torch,
    torch_dtype,
)

if TYPE_CHECKING:
    import torch

FILE = "model.ep"
# The cache key: Torch-TensorRT, the TensorRT it builds engines with, torch, and ModelOpt (int8).
LIBRARIES = ("torch", "torch-tensorrt", "tensorrt", "tensorrt-cu12", "tensorrt-cu13", "nvidia-modelopt")
# ModelOpt int8 reached the dynamo frontend in pytorch/TensorRT#3058 (August 2024), released in 2.5.
INT8_SINCE = (2, 5)
SOURCES = ("state_dict", "torch_export")  # what the dynamo frontend compiles: an nn.Module or a torch.export program
ENGINE_DTYPES = {"fp32": "float32", "fp16": "float16", "int8": "int8"}  # enabled_precisions of weakly typed releases


class TorchTensorRTBackend(Backend):
    """Compiles the model with torch_tensorrt.dynamo.compile on the GPU and saves it, engines included."""

    name = "torch_tensorrt"
    slow_start = "builds a TensorRT engine for a minute or more"
    description = "Torch-TensorRT: TensorRT engines compiled ahead of time (dynamo frontend); int8 by NVIDIA ModelOpt"
    supports = (Support(("pytorch",), ("none",), ("fp32", "fp16"), ("tensorrt",)),
                Support(("pytorch",), ("ptq_static",), ("int8",), ("tensorrt",)))
    devices = {"tensorrt": "cuda"}

    def versions(self) -> dict[str, str]:
        return installed_versions(*LIBRARIES)

    def probe(self, target: str, precision: str) -> str | None:
        """The GPU and torch checks of the cuda target, then Torch-TensorRT (and ModelOpt for int8)."""
        if missing := missing_torch():
            return missing
        reasons = cuda_reasons(precision, f"TensorRT {precision}")
        import torch

        wanted = release(torch.__version__)
        install = f"pip install 'torch-tensorrt=={wanted[0]}.{wanted[1]}.*'"
        found = torch_tensorrt_version()
        if found is None:
            reasons.append(f"Torch-TensorRT is not installed: {install} (its release for torch {torch.__version__})")
        elif (built_for := release(found)) != wanted:
            reasons.append(f"torch-tensorrt {found} is built for torch {built_for[0]}.{built_for[1]}, not the "
                           f"installed torch {torch.__version__}: {install}")
        if precision == "int8":
            if found is not None and release(found) < INT8_SINCE:
                reasons.append(f"torch-tensorrt {found} has no int8 in its dynamo frontend (ModelOpt int8 came with "
                               f"2.5): install torch and torch-tensorrt 2.5 or newer")
            if importlib.util.find_spec("modelopt") is None:
                reasons.append("int8 in Torch-TensorRT is calibrated by NVIDIA ModelOpt (modelopt.torch.quantization), "
                               "which is not installed: pip install nvidia-modelopt")
        return "; ".join(reasons) or None

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        """An nn.Module or a torch.export program; int8 quantises the module's layers with ModelOpt's INT8 default
        (per-channel weights, max calibration, float input and output)."""
        if source_format not in SOURCES:
            kind = "a TorchScript file" if source_format == "torchscript" else f"a {source_format!r} source"
            return (f"torch_tensorrt compiles an nn.Module or a torch.export program (its dynamo frontend traces with "
                    f"torch.export), but this model is {kind}; give it as factory + weights (a state_dict) or as a "
                    f"torch.export .pt2 file")
        if step.kind != "ptq_static":
            return None
        if source_format != "state_dict":
            return ("ptq_static in torch_tensorrt quantises with NVIDIA ModelOpt, which swaps an nn.Module's "
                    "convolution and linear layers for quantised ones, but this model is a torch.export program; "
                    "give it as factory + weights (a state_dict) to quantise it")
        if not step.options.get("per_channel", True):
            return ("ModelOpt's INT8_DEFAULT_CFG quantises weights per output channel; per-tensor weights "
                    "(per_channel: false) are not available in torch_tensorrt; remove the option or set "
                    "per_channel: true")
        return static_options_reason(step, "Torch-TensorRT", ("minmax",))

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        step = request.step
        if reason := free_axes_reason(request.source):
            raise ValueError(reason)
        import torch

        torch.set_num_threads(request.threads)
        inputs = request.source.inputs
        dtype = torch_dtype(request.precision)
        meta: dict[str, Any] = {"file": FILE, "strategy": step.kind, "inputs": specs_to_list(inputs),
                                "profile": {"min": 1, "opt": 1, "max": request.max_batch}}
        with quiet_torch(captured=True):
            import torch_tensorrt

            module = place(request.source.load(), request.target, request.precision)
            if step.kind == "ptq_static":
                meta["quantization"] = _quantise(module, step, request)
            options = compile_options(torch_tensorrt.dynamo.compile, request.precision)
            with _export_mode(step.kind), torch.no_grad():
                program, example = export(module, inputs, request.max_batch, "cuda", dtype, request.seed)
                specs = [input_spec(torch_tensorrt, spec, request.max_batch, dtype) for spec in inputs]
                compiled = torch_tensorrt.dynamo.compile(program, inputs=specs, **options)
            meta["compile_options"] = {key: _plain(value) for key, value in options.items()}
            meta.update(blocks(compiled))
            if not meta["engines"]:
                raise RuntimeError(f"Torch-TensorRT built no TensorRT engine for {request.source.path} (no "
                                   f"_run_on_acc module in the compiled graph): the cell would measure plain PyTorch")
            # retrace=False serialises the compiled graph as it is, keeping its dynamic batch dimension.
            torch_tensorrt.save(compiled, str(request.out_dir / FILE), output_format="exported_program",
                                inputs=list(example), retrace=False)
        return meta

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        pin_threads(threads)
        with quiet_torch(captured=True):
            import torch_tensorrt

            module = torch_tensorrt.load(str(artifact_dir / meta["file"])).module()
        facts = {key: meta[key] for key in ("engines", "pytorch_blocks", "profile", "compile_options", "quantization")
                 if key in meta}
        session = TorchSession(module, target, precision, facts)
        # The first call sets the engines up on this GPU: part of load time, never of a timed call.
        session.execute(session.prepare(example_inputs(specs_from_list(meta["inputs"]), batch=1)))
        return session


def free_axes_reason(source: SourceModel) -> str | None:
    """Why the engines cannot be built for this model's inputs: a free axis (engines are built for fixed sample
    shapes), or None."""
    free = [spec.describe() for spec in source.inputs if None in spec.shape]
    if not free:
        return None
    return (f"{source.label}: torch_tensorrt builds engines for fixed sample shapes, but input {', '.join(free)} "
            f"has a free axis; declare its length in the model's `inputs:`")


def torch_tensorrt_version() -> str | None:
    """The installed torch-tensorrt distribution's version, read from its metadata (nothing imported)."""
    try:
        return version("torch-tensorrt")
    except PackageNotFoundError:
        return None


def release(text: str) -> tuple[int, int]:
    """(2, 13) of '2.13.0+cu130': Torch-TensorRT releases track torch's major.minor."""
    found = re.match(r"(\d+)\.(\d+)", text)
    return (int(found[1]), int(found[2])) if found else (0, 0)


def compile_options(compile_fn: Callable[..., Any], precision: str) -> dict[str, Any]:
    """The settings `compile_fn` (torch_tensorrt.dynamo.compile) takes for `precision`: strongly typed fp16 (the half
    module's own dtypes) where the release has use_explicit_typing, enabled_precisions where it is weakly typed,
    neither where every network is strongly typed (TensorRT 11); TF32 off, so fp32 layers compute in IEEE fp32."""
    import torch

    params = inspect.signature(compile_fn).parameters
    options: dict[str, Any] = {"disable_tf32": True, "min_block_size": 1}
    if precision == "fp16" and "use_explicit_typing" in params:
        options["use_explicit_typing"] = True
    elif precision != "fp32" and "enabled_precisions" in params:
        options["enabled_precisions"] = {getattr(torch, ENGINE_DTYPES[precision])}
        if "use_explicit_typing" in params:  # int8 takes the weakly typed path in these releases
            options["use_explicit_typing"] = False
    return options


def export(module: "torch.nn.Module", inputs: tuple[TensorSpec, ...], max_batch: int, device: str,
           dtype: "torch.dtype", seed: int) -> tuple["torch.export.ExportedProgram", tuple["torch.Tensor", ...]]:
    """`module` captured by torch.export for batches 1..max_batch (every input's batch axis the same dimension),
    and the example batch it was traced with."""
    import torch

    # A batch of 2, not 1: torch.export specialises a dimension whose example size is 1.
    example = example_tensors(inputs, device, dtype, seed, batch=min(2, max_batch))
    dynamic = None
    if max_batch > 1:
        batch = torch.export.Dim("batch", min=1, max=max_batch)
        dynamic = tuple({0: batch} for _ in inputs)
    return torch.export.export(module, example, dynamic_shapes=dynamic, strict=False), example


def input_spec(torch_tensorrt: Any, spec: TensorSpec, max_batch: int, dtype: "torch.dtype") -> Any:
    """An engine input: batches 1..max_batch, kernels tuned for batch 1 (the latency runs); floating inputs in the
    precision's dtype, integer ones in their own."""
    import torch

    dtype = getattr(torch, spec.dtype) if spec.is_integer else dtype
    shape = tuple(int(d) for d in spec.shape)
    if max_batch == 1:
        return torch_tensorrt.Input(shape=(1, *shape), dtype=dtype)
    return torch_tensorrt.Input(min_shape=(1, *shape), opt_shape=(1, *shape), max_shape=(max_batch, *shape),
                                dtype=dtype)


def blocks(compiled: "torch.nn.Module") -> dict[str, int]:
    """How many TensorRT engines (_run_on_acc) and PyTorch fallback blocks (_run_on_gpu) the compiled graph calls."""
    names = [name for name, _ in compiled.named_children()]
    return {"engines": sum("_run_on_acc" in name for name in names),
            "pytorch_blocks": sum("_run_on_gpu" in name for name in names)}


def _quantise(module: "torch.nn.Module", step: StrategySpec, request: ConvertRequest) -> dict[str, Any]:
    """Insert ModelOpt's int8 quantisers into `module` (in place), calibrated on the calibration split; how."""
    import modelopt.torch.quantization as mtq
    import torch

    data = calibration_data(request, step)

    def forward_loop(model: "torch.nn.Module") -> None:
        with torch.no_grad():
            for batch in batches(data):
                model(*as_tensors(batch, "cuda", torch.float32))

    mtq.quantize(module, mtq.INT8_DEFAULT_CFG, forward_loop=forward_loop)
    return {"library": "NVIDIA ModelOpt", "config": "INT8_DEFAULT_CFG", "weights": "int8 per output channel",
            "activations": "int8 per tensor", "per_channel": True, "method": "minmax",
            "calibrator": "ModelOpt max (absolute maximum, symmetric)", "calibration_samples": count(data)}


def _export_mode(kind: str) -> AbstractContextManager[Any]:
    """ModelOpt's export_torch_mode for a quantised module (its quantisers then export as Q/DQ ops)."""
    if kind != "ptq_static":
        return nullcontext()
    from modelopt.torch.quantization.utils import export_torch_mode

    return export_torch_mode()


def _plain(value: Any) -> Any:
    """A compile option as JSON: dtype sets become sorted dtype names."""
    if isinstance(value, (set, frozenset)):
        return sorted(str(item).removeprefix("torch.") for item in value)
    return value
