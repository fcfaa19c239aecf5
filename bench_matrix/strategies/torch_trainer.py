"""PyTorch fine-tuning: L1 magnitude pruning (torch.nn.utils.prune) and FX quantisation-aware training (torch.ao).

Every finetune starts from `request.source.load()` (a fresh module), never from an object another strategy
touched. Pruning writes a state_dict for the source's own factory (format "state_dict"); QAT, alone or after
pruning, writes an int8 TorchScript file (FX convert, then trace and freeze; format "torchscript").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.plugin import Epochs, FineTuned, FineTuneRequest, Inputs, StrategySpec, TensorSpec, \
    Trainer, fx_prepare, installed_versions, quiet_torch, training_arrays, use_engine, weight_stats

if TYPE_CHECKING:
    import torch
    from torch import nn

FILE = "model.pt"

# Fine-tuning defaults: a 1.6 M-parameter PilotNet on ~700 samples of 3x66x200 takes ~22 Adam steps of 32 per
# epoch, seconds to tens of seconds an epoch on 2 cores (QAT's fake quantisation roughly doubles that).
TRAINING_DEFAULTS: dict[str, Any] = {"epochs": 2, "fraction": 0.25, "lr": 1e-4, "batch_size": 32}
# The reference study: per-layer L1 pruning of conv 0.3 / linear 0.5, or global L1 pruning of 0.3, at once.
# Kernels under min_weights weights stay dense (as in tfmot): they hold almost no storage and are the most sensitive.
PRUNE_DEFAULTS: dict[str, Any] = {"scope": "local", "schedule": "constant", "conv_sparsity": 0.3,
                                  "linear_sparsity": 0.5, "global_sparsity": 0.3, "initial_sparsity": 0.0,
                                  "min_weights": 10_000}
POLYNOMIAL_POWER = 3  # the sparsity ramp s_k = final + (initial - final) * (1 - k / K) ** 3, as tfmot's

_TRAINING_OPTIONS = ("epochs", "fraction", "lr", "batch_size")
_OPTIONS = {"prune": _TRAINING_OPTIONS + ("initial_sparsity", "final_sparsity", "schedule", "scope",
                                          "conv_sparsity", "linear_sparsity", "min_weights"),
            "qat": _TRAINING_OPTIONS}
_COMBINATIONS = (("prune",), ("qat",), ("prune", "qat"))


def _flatten(steps: tuple[StrategySpec, ...]) -> list[StrategySpec]:
    """The single-kind steps in order (a combination's steps may themselves be combinations)."""
    flat: list[StrategySpec] = []
    for step in steps:
        flat.extend(_flatten(step.steps) if step.steps else [step])
    return flat


def _prune_reason(options: dict[str, Any]) -> str | None:
    scope = options.get("scope", PRUNE_DEFAULTS["scope"])
    schedule = options.get("schedule", PRUNE_DEFAULTS["schedule"])
    per_kind = [k for k in ("conv_sparsity", "linear_sparsity") if k in options]
    if scope == "global" and per_kind:
        return (f"prune with scope: global ranks all conv and linear weights together and prunes one amount "
                f"(final_sparsity); {' and '.join(per_kind)} are per-layer (scope: local) targets")
    if per_kind and "final_sparsity" in options:
        return (f"prune: give either final_sparsity (every conv and linear layer) or "
                f"{' / '.join(per_kind)} (per layer kind), not both")
    if "initial_sparsity" in options and schedule != "polynomial":
        return "prune: initial_sparsity is where a schedule: polynomial ramp starts; a constant schedule has none"
    if schedule == "polynomial":
        finals = ([options.get("final_sparsity", PRUNE_DEFAULTS["global_sparsity"])] if scope == "global" else
                  [options.get("final_sparsity", options.get(k, PRUNE_DEFAULTS[k]))
                   for k in ("conv_sparsity", "linear_sparsity")])
        initial = options.get("initial_sparsity", PRUNE_DEFAULTS["initial_sparsity"])
        if any(initial >= final for final in finals):
            return f"prune: initial_sparsity {initial} must be below every final sparsity ({finals})"
    return None


class TorchTrainer(Trainer):
    """L1 pruning and FX QAT of an nn.Module (a state_dict source), fine-tuned with Adam on the task's
    loss."""

    name = "torch"
    description = ("PyTorch: L1 unstructured pruning (per layer or global) and FX quantisation-aware training "
                   "to int8 TorchScript; prune then qat combines them, sparsity kept through QAT")
    framework = "pytorch"
    kinds = ("prune", "qat")
    revision = 2  # 2: kernels below min_weights stay dense when pruning

    def versions(self) -> dict[str, str]:
        return installed_versions("torch")

    def probe(self) -> str | None:
        return None

    def output_format(self, steps: tuple[StrategySpec, ...], source_format: str) -> str:
        """A QAT model ends converted to int8 TorchScript; a pruned one is a state_dict."""
        return "torchscript" if _flatten(steps)[-1].kind == "qat" else "state_dict"

    def steps_reason(self, steps: tuple[StrategySpec, ...], source_format: str,
                     task: str = "regression") -> str | None:
        flat = _flatten(steps)
        kinds = tuple(s.kind or "" for s in flat)
        if missing := [k for k in kinds if k not in self.kinds]:
            return (f"{self.name} does not implement {', '.join(missing)} "
                    f"(it implements {', '.join(self.kinds)})")
        if reason := super().steps_reason(tuple(flat), source_format, task):  # e.g. no labels to train on
            return reason
        if kinds not in _COMBINATIONS:
            return (f"{self.name} applies prune, qat, or prune then qat; not {' then '.join(kinds)} "
                    f"(QAT's int8 result cannot be pruned or quantised again, and a step may appear once)")
        if source_format != "state_dict":
            what = {"torchscript": "a TorchScript file", "torch_export": "a torch.export program"}.get(
                source_format, f"format {source_format!r}")
            return (f"{self.name} fine-tunes an nn.Module (pruning reparametrises its layers, FX QAT traces its "
                    f"Python code), but this model is {what}; give it as factory + weights (a state_dict)")
        for step in flat:
            if unknown := sorted(set(step.options) - set(_OPTIONS[step.kind or ""])):
                return (f"{step.kind} in {self.name} has no option {', '.join(unknown)} "
                        f"(it takes {', '.join(_OPTIONS[step.kind or ''])})"
                        + ("; QAT learns its ranges from the fine-tuning data (fraction), it does not calibrate"
                           if "calibration_samples" in unknown else ""))
            if step.kind == "prune" and (reason := _prune_reason(step.options)):
                return reason
        return None

    def finetune(self, request: FineTuneRequest) -> FineTuned:
        import torch

        if reason := self.steps_reason(request.steps, request.source.format, request.task):
            raise ValueError(reason)
        torch.manual_seed(request.seed)
        torch.set_num_threads(request.threads)
        module = request.source.load()  # fresh: nothing carried over from another strategy
        flat = _flatten(request.steps)
        facts: dict[str, Any] = {"kinds": [s.kind for s in flat], "steps": [], "targets": {}}
        masks: dict[str, torch.Tensor] = {}
        kernels: list[np.ndarray] = []
        for index, step in enumerate(flat):
            inputs, labels = request.train(float(step.options.get("fraction", TRAINING_DEFAULTS["fraction"])))
            data = _data(inputs, labels, request.source.inputs, request.task)
            generator = torch.Generator().manual_seed(request.seed + index)
            if step.kind == "prune":
                module, step_facts, masks = _prune(module, step.options, data, generator)
            else:
                module, step_facts, kernels = _qat(module, step.options, data, generator, masks, request)
            facts["targets"].update(step_facts.pop("targets"))
            facts["steps"].append({"kind": step.kind, **step_facts})
        pruned = [s["pruned_kernel_sparsity"] for s in facts["steps"] if "pruned_kernel_sparsity" in s]
        if pruned:  # over the pruned kernels only (those below min_weights stay dense)
            facts["pruned_kernel_sparsity"] = pruned[0]
        last = facts["steps"][-1]
        facts.update(epochs=sum(s["epochs"] for s in facts["steps"]), samples=last["samples"],
                     final_loss=last["final_loss"], loss=last["loss"])
        if len(flat) == 1:
            facts.update(lr=last["lr"], batch_size=last["batch_size"])
        if flat[-1].kind == "qat":
            facts.update(engine=last["engine"], weights="int8 weights of the converted model, dequantised",
                         **weight_stats(kernels))
            torch.jit.save(module, str(request.out_dir / FILE))
            return FineTuned(file=FILE, format="torchscript", facts=facts)
        facts.update(weights="float weights after pruning was made permanent",
                     **weight_stats([_numpy(m.weight) for m in _prunable(module)]))
        torch.save({k: v.detach().clone() for k, v in module.state_dict().items()}, request.out_dir / FILE)
        return FineTuned(file=FILE, format="state_dict", facts=facts)


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return tensor.detach().cpu().float().numpy().copy()


def _prunable(module: nn.Module) -> list[nn.Module]:
    from torch import nn

    return [m for m in module.modules() if isinstance(m, (nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.Linear))]


def _training(options: dict[str, Any]) -> tuple[float, float, int]:
    return (float(options.get("epochs", TRAINING_DEFAULTS["epochs"])),
            float(options.get("lr", TRAINING_DEFAULTS["lr"])),
            int(options.get("batch_size", TRAINING_DEFAULTS["batch_size"])))


@dataclass(frozen=True)
class _Data:
    """Training samples as tensors: the model's inputs in its order, and the task's labels."""

    inputs: tuple[torch.Tensor, ...]
    labels: torch.Tensor  # (N, columns) float32 for regression, (N,) int64 class ids for classification
    task: str

    def __len__(self) -> int:
        return len(self.labels)

    def take(self, index: torch.Tensor) -> tuple[tuple[torch.Tensor, ...], torch.Tensor]:
        return tuple(t[index] for t in self.inputs), self.labels[index]


def _data(inputs: Inputs, labels: np.ndarray, specs: tuple[TensorSpec, ...], task: str) -> _Data:
    """The training split's named inputs in the model's input order, and labels typed for the task's loss."""
    import torch

    arrays, target = training_arrays(inputs, labels, specs, task)
    return _Data(tuple(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays), torch.from_numpy(target), task)


LOSSES = {"regression": "mse", "classification": "cross_entropy"}


def _loss(out: Any, labels: torch.Tensor, task: str) -> torch.Tensor:
    """Cross-entropy of the first output's logits with the class ids, or the MSE of every output (flattened
    per sample and concatenated, as evaluation compares them) against the label columns."""
    import torch

    outputs = list(out) if isinstance(out, (tuple, list)) else [out]
    if task == "classification":
        return torch.nn.functional.cross_entropy(outputs[0], labels)
    flat = torch.cat([o.reshape(len(o), -1) for o in outputs], dim=1)
    if flat.shape != labels.shape:
        raise ValueError(f"the model outputs {flat.shape[1]} values per sample but the labels have "
                         f"{labels.shape[1]} column(s)")
    return torch.nn.functional.mse_loss(flat, labels)


def _fit(module: nn.Module, options: dict[str, Any], data: _Data, generator: torch.Generator,
         on_epoch: Callable[[int, int], None] | None = None,
         after_step: Callable[[], None] | None = None) -> dict[str, Any]:
    """Adam on the task's loss in train mode, BatchNorm statistics kept, for `epochs` (may be fractional) of
    shuffled mini-batches; on_epoch(k, K) before each of the K started epochs, after_step after each step."""
    import torch

    epochs, lr, batch_size = _training(options)
    if len(data) == 0:
        raise ValueError("no training samples to fine-tune on (is the training split or fraction empty?)")
    per_epoch = math.ceil(len(data) / batch_size)
    total = max(1, round(epochs * per_epoch))
    started = math.ceil(total / per_epoch)
    optimiser = torch.optim.Adam([p for p in module.parameters() if p.requires_grad], lr=lr)
    module.train()
    for layer in module.modules():  # fine-tuning on a fraction of the data: keep the learned normalisation
        if isinstance(layer, torch.nn.modules.batchnorm._BatchNorm):
            layer.eval()
    losses: list[float] = []
    order = torch.arange(len(data))
    progress = Epochs(started, "fine-tune")
    for step in range(total):
        if step % per_epoch == 0:
            if step:
                progress.ended(step // per_epoch, sum(losses) / len(data))
            if on_epoch is not None:
                on_epoch(step // per_epoch, started)
            order = torch.randperm(len(data), generator=generator)
            losses = []
        index = order[(step % per_epoch) * batch_size:(step % per_epoch + 1) * batch_size]
        inputs, labels = data.take(index)
        optimiser.zero_grad()
        loss = _loss(module(*inputs), labels, data.task)
        loss.backward()
        optimiser.step()
        if after_step is not None:
            after_step()
        losses.append(float(loss.detach()) * len(index))
    module.eval()
    seen = (total - 1) % per_epoch * batch_size + len(index)
    final_loss = sum(losses) / seen  # the mean loss over the last (possibly partial) epoch
    progress.ended(started, final_loss)
    if not math.isfinite(final_loss):
        raise ValueError(f"fine-tuning diverged: the {LOSSES[data.task]} loss is {final_loss} after {total} "
                         f"steps (lower lr?)")
    return {"epochs": total / per_epoch, "samples": len(data), "lr": lr, "batch_size": batch_size,
            "steps": total, "batchnorm": "frozen running statistics", "loss": LOSSES[data.task],
            "final_loss": final_loss}


def _prune(module: nn.Module, options: dict[str, Any], data: _Data,
           generator: torch.Generator) -> tuple[nn.Module, dict[str, Any], dict[str, torch.Tensor]]:
    """Prune (masks in place while fine-tuning, so pruned weights stay zero), then make it permanent."""
    from torch import nn
    from torch.nn.utils import prune

    every = {name: m for name, m in module.named_modules() if m in _prunable(module)}
    if not every:
        raise ValueError("prune: the model has no Conv or Linear layer to prune")
    min_weights = int(options.get("min_weights", PRUNE_DEFAULTS["min_weights"]))
    layers = [m for m in every.values() if m.weight.numel() >= min_weights]
    if not layers:
        largest = max(m.weight.numel() for m in every.values())
        raise ValueError(f"prune: no Conv/Linear weight has min_weights ({min_weights}) weights or more (the "
                         f"largest has {largest}); lower min_weights")
    scope = options.get("scope", PRUNE_DEFAULTS["scope"])
    schedule = options.get("schedule", PRUNE_DEFAULTS["schedule"])
    initial = float(options.get("initial_sparsity", PRUNE_DEFAULTS["initial_sparsity"]))
    if scope == "global":
        targets: dict[str, Any] = {"scope": "global", "sparsity": float(options.get(
            "final_sparsity", PRUNE_DEFAULTS["global_sparsity"]))}
    else:
        final = options.get("final_sparsity")
        targets = {"scope": "local",
                   "conv_sparsity": float(final if final is not None else options.get(
                       "conv_sparsity", PRUNE_DEFAULTS["conv_sparsity"])),
                   "linear_sparsity": float(final if final is not None else options.get(
                       "linear_sparsity", PRUNE_DEFAULTS["linear_sparsity"]))}
    targets.update(method="l1_unstructured", schedule=schedule, min_weights=min_weights,
                   dense_layers={n: m.weight.numel() for n, m in every.items() if m not in layers})
    if schedule == "polynomial":
        targets["initial_sparsity"] = initial

    def amount(final_amount: float, k: int, count: int) -> float:
        if schedule != "polynomial":
            return final_amount
        return final_amount + (initial - final_amount) * (1 - (k + 1) / count) ** POLYNOMIAL_POWER

    def apply(k: int, count: int) -> None:
        # Re-pruning a permanent result: its zeros are the smallest magnitudes, so a growing amount keeps them.
        if k > 0 and schedule != "polynomial":
            return
        for layer in layers:
            if prune.is_pruned(layer):
                prune.remove(layer, "weight")
        # Whole weights, rounded up: the measured sparsity is never below the target (torch itself rounds).
        if scope == "global":
            total = sum(layer.weight.numel() for layer in layers)
            prune.global_unstructured([(layer, "weight") for layer in layers], pruning_method=prune.L1Unstructured,
                                      amount=math.ceil(amount(targets["sparsity"], k, count) * total - 1e-9))
        else:
            for layer in layers:
                final_amount = targets["linear_sparsity" if isinstance(layer, nn.Linear) else "conv_sparsity"]
                prune.l1_unstructured(layer, "weight", amount=math.ceil(
                    amount(final_amount, k, count) * layer.weight.numel() - 1e-9))

    facts = _fit(module, options, data, generator, on_epoch=apply)
    for layer in layers:
        prune.remove(layer, "weight")
    masks = {name: p.detach() != 0 for name, p in module.named_parameters()
             if any(p is layer.weight for layer in layers)}
    pruned_sparsity = weight_stats([_numpy(layer.weight) for layer in layers])["sparsity"]
    return module, {**facts, "targets": targets, "pruned_kernel_sparsity": pruned_sparsity}, masks


def _qat(module: nn.Module, options: dict[str, Any], data: _Data, generator: torch.Generator,
         masks: dict[str, torch.Tensor],
         request: FineTuneRequest) -> tuple[torch.jit.ScriptModule, dict[str, Any], list[np.ndarray]]:
    """FX QAT (fake quantisation in train mode), convert to int8, trace and freeze to TorchScript.
    `masks` (from a prune step) are re-applied after every optimiser step so that sparsity survives QAT."""
    import warnings

    import torch
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_qat_fx

    engine = use_engine()
    example = tuple(t[:2] for t in data.inputs)
    with quiet_torch(captured=True), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Please use quant_min and quant_max")  # torch's own qconfig
        module.train()
        prepared = fx_prepare(prepare_qat_fx, module, _qat_mapping(engine), example,
                              f"model {request.source.name}")
        params = dict(prepared.named_parameters())
        if lost := sorted(set(masks) - set(params)):
            raise ValueError(f"qat after prune: FX QAT renamed the pruned weights {', '.join(lost)}; "
                             f"their sparsity could not be kept")
        kept = [(params[name], mask) for name, mask in masks.items()]

        def keep_sparsity() -> None:
            with torch.no_grad():
                for param, mask in kept:
                    param.mul_(mask)

        facts = _fit(prepared, options, data, generator, after_step=keep_sparsity if kept else None)
        prepared.eval()
        quantised = convert_fx(prepared)
        # A batch of 2, not 1, so that nothing in the trace specialises on a size-1 batch.
        with torch.no_grad():
            twice = tuple(torch.cat([t[:1]] * 2) for t in example)
            traced = torch.jit.freeze(torch.jit.trace(quantised, twice).eval())
    facts["engine"] = engine
    facts["targets"] = {"quantisation": f"int8 FX QAT, {engine} default QAT qconfig (per-channel weights)"}
    return traced, facts, _int8_kernels(quantised)


def _qat_mapping(engine: str) -> Any:
    """The engine's default QAT qconfigs, and int8 weight-only fake quantisation for embeddings (the default's
    symmetric per-channel weights do not apply to them)."""
    from torch import nn
    from torch.ao.quantization import default_embedding_qat_qconfig, get_default_qat_qconfig_mapping

    mapping = get_default_qat_qconfig_mapping(engine)
    return mapping.set_object_type(nn.Embedding, default_embedding_qat_qconfig)


def _int8_kernels(quantised: nn.Module) -> list[np.ndarray]:
    from torch.ao.nn import quantized as nnq

    return [_numpy(m.weight().dequantize()) for m in quantised.modules()
            if isinstance(m, (nnq.Conv1d, nnq.Conv2d, nnq.Conv3d, nnq.Linear))]
