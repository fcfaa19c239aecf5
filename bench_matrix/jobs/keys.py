"""The workspace's cache keys: each hashes everything that changes what its entry holds (docs/metrics.md §12)."""

from __future__ import annotations

from typing import Any

from bench_matrix import hardware
from bench_matrix.backend import Backend
from bench_matrix.matrix.schema import STRATEGY_KINDS
from bench_matrix.matrix.spec import ModelSpec, Settings
from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import TensorSpec, specs_to_list
from bench_matrix.workspace import digest, file_sha256


def artifact_key(backend: Backend, source: SourceModel, step: StrategySpec, precision: str, target: str,
                 dataset: list[str], settings: Settings, options: dict[str, Any]) -> str:
    """A cell's artifact: its source, backend, conversion step and mode, the calibration data when the step
    calibrates (`dataset`: fingerprint and layout), the largest batch it serves, the GPU it was built on."""
    gpus = [(g.name, g.capability) for g in hardware.gpus()[:1]] if target != "cpu" else None
    return digest({"source": source.identity(), "backend": _backend(backend), "step": step.to_dict(),
                   "precision": precision, "target": target, "options": options,
                   "calibration": dataset if calibrates(step) else None, "seed": settings.seed,
                   "max_batch": settings.batch_size, "gpu": gpus})


def calibrates(step: StrategySpec) -> bool:
    """Whether a conversion step reads the calibration split (its kind takes calibration_samples)."""
    return "calibration_samples" in STRATEGY_KINDS.get(step.kind or "none", {}).get("options", {})


def intermediates_key(backend: Backend, source: SourceModel, seed: int) -> str:
    """What a backend shares between the modes of one source (e.g. its fp32 ONNX export)."""
    return digest({"source": source.identity(), "backend": _backend(backend), "seed": seed})


def params_key(source: SourceModel) -> str:
    """A source's parameter count."""
    return digest({"source": source.identity()})


def finetune_key(trainer: Any, source: SourceModel, steps: tuple[StrategySpec, ...], task: str,
                 dataset: list[str], seed: int) -> str:
    """A fine-tuned model: the pristine source, the trainer, the training steps, the training data, the seed."""
    return digest({"source": source.identity(), "trainer": trainer.name, "revision": trainer.revision,
                   "versions": trainer.versions(), "steps": [s.to_dict() for s in steps], "task": task,
                   "dataset": dataset, "seed": seed})


def model_key(spec: ModelSpec, inputs: tuple[TensorSpec, ...], code: str | None, task: str, dataset: str,
              settings: Settings, baseline: list[Any]) -> str:
    """A prepared model and its fp32 reference outputs on the test split (`baseline`: backend, versions)."""
    return digest({"model": model_identity(spec, code), "inputs": specs_to_list(inputs), "task": task,
                   "dataset": dataset, "seed": settings.seed, "eval": settings.eval_samples,
                   "batch": settings.batch_size, "format": 3, "baseline": baseline})


def builtin_key(spec: ModelSpec, code: str | None, dataset: str, seed: int, libraries: dict[str, str]) -> str:
    """A built-in model trained on the training split (its factory's code and the training libraries)."""
    return digest({"builtin": spec.builtin, "framework": spec.framework, "training": spec.training,
                   "dataset": dataset, "seed": seed, "layout": spec.layout, "code": code, "libraries": libraries})


def model_identity(spec: ModelSpec, code: str | None) -> dict[str, Any]:
    """What makes a model this model, without where its files lie: its declaration, its files' contents and
    its factory's code."""
    return {"name": spec.name, "framework": spec.framework, "builtin": spec.builtin, "factory": spec.factory,
            "layout": spec.layout, "training": spec.training, "format": spec.source_format, "code": code,
            "files": [file_sha256(p) for p in (spec.file, spec.weights) if p is not None]}


def _backend(backend: Backend) -> dict[str, Any]:
    return {"name": backend.name, "revision": backend.revision, "versions": backend.versions()}
