"""TorchScript (torch.jit.trace), optionally int8-quantised first with torch.ao (dynamic, or FX static)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.plugin import ConvertRequest, Session, StrategySpec, Support, count, fx_prepare, take

from ._common import batches, calibration_data, static_options_reason
from ._torch import TorchBackend, TorchSession, as_tensors, example_tensors, flat_module, pin_threads, place, \
    quiet_torch, torch_dtype, use_engine

if TYPE_CHECKING:
    import torch

FILE = "model.pt"


class TorchScriptBackend(TorchBackend):
    """Traces the model to TorchScript; int8 strategies quantise it with torch.ao before tracing."""

    name = "torchscript"
    description = "TorchScript via torch.jit.trace; int8 by torch.ao dynamic or FX static quantisation"
    supports = (Support(("pytorch",), ("none",), ("fp32",), ("cpu",)),
                Support(("pytorch",), ("ptq_dynamic", "ptq_static", "qat"), ("int8",), ("cpu",)),
                Support(("pytorch",), ("none",), ("fp32", "fp16", "bf16"), ("cuda",)))

    def option_reason(self, step: StrategySpec, source_format: str) -> str | None:
        """torch.ao quantises an nn.Module (a state_dict source) and calibrates with min-max only."""
        if step.kind in ("none", "qat"):  # qat: the trainer hands over an int8 TorchScript model, saved as it is
            return None
        if source_format != "state_dict":
            kind = {"torchscript": "a TorchScript file", "torch_export": "a torch.export program"}.get(
                source_format, source_format)
            return (f"{step.kind} in the torchscript backend quantises an nn.Module (torch.ao swaps its layers; "
                    f"FX traces its Python code), but this model is {kind}; give it as factory + weights "
                    f"(a state_dict) to quantise it")
        return static_options_reason(step, "torch.ao", ("minmax",)) if step.kind == "ptq_static" else None

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        import torch

        step = request.step
        torch.set_num_threads(request.threads)
        meta: dict[str, Any] = {"file": FILE, "strategy": step.kind}
        with quiet_torch(captured=step.kind != "none" or request.source.format == "torch_export"):
            module = request.source.load()
            if step.kind == "qat":
                meta["quantization"] = {"engine": use_engine(), "ranges": "learned in quantisation-aware training"}
            elif step.kind != "none":
                module, meta["quantization"] = _quantise(module, step, request)
            module = place(module, request.target, request.precision)
            device = "cpu" if request.target == "cpu" else "cuda"
            example = example_tensors(request.source.inputs, device, torch_dtype(request.precision), request.seed)
            if not isinstance(module, torch.jit.ScriptModule):  # a TorchScript source is saved as it is
                with torch.no_grad():
                    module = torch.jit.trace(flat_module(module, example)[0], example)
            module.save(str(request.out_dir / FILE))
        return meta

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        import torch

        pin_threads(threads)
        if "quantization" in meta:
            use_engine(meta["quantization"]["engine"])
        with quiet_torch():
            module = torch.jit.load(str(artifact_dir / meta["file"]),
                                    map_location="cpu" if target == "cpu" else "cuda")
        return TorchSession(module.eval(), target, precision)


def _quantise(module: "torch.nn.Module", step: StrategySpec,
              request: ConvertRequest) -> tuple["torch.nn.Module", dict[str, Any]]:
    """The int8 module and a record of how it was quantised."""
    import torch
    from torch.ao import quantization as tq

    engine = use_engine()
    per_channel = bool(step.options.get("per_channel", False))
    settings: dict[str, Any] = {"engine": engine, "per_channel": per_channel, "weights": "qint8"}
    if step.kind == "ptq_dynamic":
        qconfig = tq.per_channel_dynamic_qconfig if per_channel else tq.default_dynamic_qconfig
        settings["layers"] = ["Linear"]
        return tq.quantize_dynamic(module, {torch.nn.Linear: qconfig}, dtype=torch.qint8), settings

    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

    # minmax calibration; activations quint8 in [0, 127] as the x86/fbgemm kernels expect (no saturation).
    activation = tq.MinMaxObserver.with_args(dtype=torch.quint8, quant_min=0, quant_max=127)
    weight = tq.default_per_channel_weight_observer if per_channel else tq.default_weight_observer
    mapping = tq.get_default_qconfig_mapping(engine).set_global(tq.QConfig(activation=activation, weight=weight))
    data = calibration_data(request, step)
    example = as_tensors(take(data, slice(0, 1)), "cpu", torch.float32)
    prepared = fx_prepare(prepare_fx, module, mapping, example, f"model {request.source.name}")
    with torch.no_grad():
        for batch in batches(data):
            prepared(*as_tensors(batch, "cpu", torch.float32))
    settings.update(activations="quint8 [0, 127]", method="minmax", calibration_samples=count(data))
    return convert_fx(prepared), settings
