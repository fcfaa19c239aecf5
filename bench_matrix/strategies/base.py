"""What a trainer is: the training kinds it implements for one framework, and finetune (source -> new source)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from bench_matrix.strategy import QAT_KINDS
from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs, TensorSpec

__all__ = ["QAT_KINDS", "FineTuneRequest", "FineTuned", "Trainer", "training_arrays", "weight_stats"]


@dataclass(frozen=True)
class FineTuneRequest:
    """Everything a trainer needs: the pristine source, the training steps in order, data, and where to write."""

    source: SourceModel
    steps: tuple[StrategySpec, ...]  # the strategy's training steps, in order (one, unless a combination)
    out_dir: Path  # write the fine-tuned model's file(s) here, and nothing else
    # fraction -> (inputs, labels): the first part of the shuffled training split, preprocessed like evaluation
    # data; one array per named model input; labels (N, columns) float32 for regression, (N,) int64 classes
    train: Callable[[float], tuple[Inputs, np.ndarray]]
    threads: int
    seed: int
    task: str = "regression"  # regression (MSE loss) or classification (cross-entropy on the logits)


@dataclass(frozen=True)
class FineTuned:
    """A fine-tuned model: its file in out_dir, its SourceModel format, and facts worth recording."""

    file: str
    format: str
    facts: dict[str, Any] = field(default_factory=dict)  # epochs, samples, final loss, sparsity, clusters, ...


class Trainer(ABC):
    """Fine-tunes models of one framework with one or more training kinds; knows nothing of the runner."""

    name: ClassVar[str]
    description: ClassVar[str]
    framework: ClassVar[str]
    kinds: ClassVar[tuple[str, ...]]  # training kinds from STRATEGY_KINDS it implements
    revision: ClassVar[int] = 1  # raise it when the procedure changes: cached fine-tuned models are then redone

    def versions(self) -> dict[str, str]:
        """Versions of the libraries it uses (in the fine-tuned model's cache key and in each record's env)."""
        return {}

    def probe(self) -> str | None:
        """Why this machine cannot fine-tune with this trainer, or None."""
        return None

    def steps_reason(self, steps: tuple[StrategySpec, ...], source_format: str,
                     task: str = "regression") -> str | None:
        """Why it cannot apply these steps (in this order, with these options) to this source format for this
        task, or None."""
        if task == "none":
            return "fine-tuning needs labels; the task is none"
        missing = [s.kind for s in steps if s.kind not in self.kinds]
        return f"{self.name} does not implement {', '.join(missing)}" if missing else None

    def output_format(self, steps: tuple[StrategySpec, ...], source_format: str) -> str:
        """The SourceModel format of the fine-tuned model these steps produce (what the backend will convert)."""
        return source_format

    @abstractmethod
    def finetune(self, request: FineTuneRequest) -> FineTuned:
        """Fine-tune a fresh copy of request.source with request.steps; write the result into request.out_dir."""


def training_arrays(inputs: Inputs, labels: np.ndarray, specs: tuple[TensorSpec, ...],
                    task: str) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
    """The training split's named inputs in the model's input order, and labels typed for the task's loss:
    int64 class ids (classification) or float32 columns (regression)."""
    if missing := [s.name for s in specs if s.name not in inputs]:
        raise ValueError(f"the training data has no input {', '.join(missing)} (it has {', '.join(inputs)})")
    if task not in ("regression", "classification"):
        raise ValueError(f"fine-tuning needs labels of a regression or classification task; the task is {task}")
    if task == "classification":
        return tuple(inputs[s.name] for s in specs), labels.astype(np.int64).reshape(len(labels))
    return tuple(inputs[s.name] for s in specs), labels.astype(np.float32).reshape(len(labels), -1)


def weight_stats(kernels: list[np.ndarray]) -> dict[str, Any]:
    """Sparsity (fraction of exact zeros) over all kernels, and the most distinct values any one kernel holds."""
    total = sum(k.size for k in kernels)
    zeros = sum(int(np.count_nonzero(k == 0)) for k in kernels)
    return {"sparsity": zeros / total if total else 0.0,
            "clusters": max((len(np.unique(k)) for k in kernels), default=0), "weight_tensors": len(kernels)}
