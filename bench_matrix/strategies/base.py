"""What a trainer is: the training kinds it implements for one framework, and finetune (source -> new source)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from bench_matrix.matrix.expand import QAT_KINDS
from bench_matrix.matrix.spec import StrategySpec
from bench_matrix.sources import SourceModel

__all__ = ["QAT_KINDS", "FineTuneRequest", "FineTuned", "Trainer", "weight_stats"]


@dataclass(frozen=True)
class FineTuneRequest:
    """Everything a trainer needs: the pristine source, the training steps in order, data, and where to write."""

    source: SourceModel
    steps: tuple[StrategySpec, ...]  # the strategy's training steps, in order (one, unless a combination)
    out_dir: Path  # write the fine-tuned model's file(s) here, and nothing else
    train: Callable[[float], tuple[np.ndarray, np.ndarray]]  # fraction -> (x, y): the first part of the shuffled
    #                                                          training split, preprocessed like evaluation data
    threads: int
    seed: int


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

    def steps_reason(self, steps: tuple[StrategySpec, ...], source_format: str) -> str | None:
        """Why it cannot apply these steps (in this order, with these options) to this source format, or None."""
        missing = [s.kind for s in steps if s.kind not in self.kinds]
        return f"{self.name} does not implement {', '.join(missing)}" if missing else None

    @abstractmethod
    def finetune(self, request: FineTuneRequest) -> FineTuned:
        """Fine-tune a fresh copy of request.source with request.steps; write the result into request.out_dir."""


def weight_stats(kernels: list[np.ndarray]) -> dict[str, Any]:
    """Sparsity (fraction of exact zeros) over all kernels, and the most distinct values any one kernel holds."""
    total = sum(k.size for k in kernels)
    zeros = sum(int(np.count_nonzero(k == 0)) for k in kernels)
    return {"sparsity": zeros / total if total else 0.0,
            "clusters": max((len(np.unique(k)) for k in kernels), default=0), "weight_tensors": len(kernels)}
