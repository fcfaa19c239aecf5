"""What each job returns, one frozen dataclass per job (the local executor carries them as JSON from the job's
process to its parent: executors/codec.py)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench_matrix.cell import TrainingKey, Ruling, RulingKey
from bench_matrix.matrix.spec import Preprocess
from bench_matrix.measurement import Measurement
from bench_matrix.sources import SourceModel
from bench_matrix.sources.forward_call import Parameter
from bench_matrix.tensors import TensorSpec


class Result:
    """What every result has: the files it names that later jobs read (they travel to other machines)."""

    def files(self) -> tuple[Path, ...]:
        return ()


@dataclass(frozen=True)
class Probe(Result):
    """Probe findings: backends, rulings (combinations, fine-tuning), model files' declared inputs (None:
    undeclared/unreadable) and fixed batch sizes (path -> input -> size), factories' forward parameters."""

    backends: dict[str, dict[str, Any]]
    rulings: dict[RulingKey, Ruling]
    trainers: dict[TrainingKey, Ruling]
    inputs: dict[str, tuple[TensorSpec, ...] | None] = field(default_factory=dict)
    forwards: dict[str, tuple[Parameter, ...] | None] = field(default_factory=dict)
    batches: dict[str, dict[str, int]] = field(default_factory=dict)

    def devices(self) -> dict[tuple[str, str], str]:
        """(backend, target) -> the device it runs on."""
        return {(name, target): device for name, info in self.backends.items()
                for target, device in info.get("devices", {}).items()}

    def baselines(self) -> dict[str, str]:
        """Framework -> the backend computing its models' fp32 baseline."""
        return {f: n for n, b in sorted(self.backends.items()) for f in b.get("baseline_for", [])}


@dataclass(frozen=True)
class PreparedData(Result):
    """The dataset job's result: the folder of the cached splits, their info (inputs, task, label columns or
    classes, counts) and the preprocessing loading applies."""

    directory: Path
    info: dict[str, Any]
    preprocess: Preprocess

    @property
    def fingerprint(self) -> str:
        return self.info["fingerprint"]

    def files(self) -> tuple[Path, ...]:
        return (self.directory,)


@dataclass(frozen=True)
class PreparedModel(Result):
    """The model job's result: the model's source, its facts for the store, its fp32 reference outputs."""

    source: SourceModel
    info: dict[str, Any]
    reference: Path

    def files(self) -> tuple[Path, ...]:
        return (self.source.path, self.reference)


@dataclass(frozen=True)
class Reference(Result):
    """The reference job's result: the fp32 outputs of a baseline's artifact on the test split."""

    outputs: Path

    def files(self) -> tuple[Path, ...]:
        return (self.outputs,)


@dataclass(frozen=True)
class Finetuned(Result):
    """The fine-tune job's result: the fine-tuned source and the trainer's facts."""

    source: SourceModel
    facts: dict[str, Any]

    def files(self) -> tuple[Path, ...]:
        return (self.source.path,)


@dataclass(frozen=True)
class Converted(Result):
    """The convert job's result: the artifact's folder (it stays on the machine that made it: the measurement
    runs there), its manifest, and whether it was cached."""

    directory: Path
    manifest: dict[str, Any]
    cached: bool

    @property
    def model(self) -> Path:
        return self.directory / "model"


@dataclass(frozen=True)
class Measured(Result):
    """The measure job's result: the cell's typed measurement, its raw latencies (stats.pack_samples bytes, by
    series) and the environment it was measured in."""

    metrics: Measurement
    samples: dict[str, bytes]
    env: dict[str, Any]


@dataclass(frozen=True)
class CellEnded(Result):
    """One cell of a rounds job: its measurement, or why it failed (and whether that is the user's to fix)."""

    key: str
    measured: Measured | None = None
    error: str | None = None
    user_error: bool = False


@dataclass(frozen=True)
class MeasuredGroup(Result):
    """The rounds job's result: each cell's, in the job's order."""

    cells: tuple[CellEnded, ...]
