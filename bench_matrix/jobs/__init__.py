"""The jobs a worker process runs, as typed values: probe, prepare a dataset or a model, fine-tune, convert,
measure. Each names the function that runs it (`mode`); results come back as JSON-serialisable dicts."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from bench_matrix.cell import Cell, ClosedLoopPlan
from bench_matrix.matrix.expand import TrainingKey, VerdictKey
from bench_matrix.matrix.spec import DatasetSpec, ModelSpec, Preprocess, Settings, StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import TensorSpec
from bench_matrix.workspace import Workspace


@dataclass(frozen=True)
class PreparedData:
    """A prepared dataset: its cache directory and its info (inputs, task, label columns or classes, counts)."""

    directory: Path
    info: dict[str, Any]
    preprocess: Preprocess


@dataclass(frozen=True)
class Job:
    """What every job has: the workspace it reads and writes."""

    mode: ClassVar[str]  # 'module:function' that runs the job in the worker
    workspace: Workspace


@dataclass(frozen=True)
class ProbeJob(Job):
    """Describe backends, judge combinations and fine-tunings, read the inputs model files declare and the
    parameters of factories' forward."""

    mode = "bench_matrix.jobs.probe:probe"
    backends: tuple[str, ...]
    keys: tuple[VerdictKey, ...] | None = None  # None: every combination the backends declare
    training: tuple[TrainingKey, ...] = ()
    model_files: tuple[tuple[str, str, str], ...] = ()  # (framework, source format, path) of user model files
    factories: tuple[tuple[str, tuple[str, ...]], ...] = ()  # (factory, python_path) whose forward to read


@dataclass(frozen=True)
class DatasetJob(Job):
    """Read, check, preprocess and split a dataset (synthetic: of these inputs)."""

    mode = "bench_matrix.jobs.prepare:prepare_dataset"
    dataset: DatasetSpec
    inputs: tuple[TensorSpec, ...] = ()


@dataclass(frozen=True)
class ModelJob(Job):
    """Materialise a model's source (training a built-in), check it against the data, compute its reference."""

    mode = "bench_matrix.jobs.prepare:prepare_model"
    model: ModelSpec
    inputs: tuple[TensorSpec, ...] | None  # declared or read from the file; None: the dataset's
    task: str
    data: PreparedData
    settings: Settings
    baseline: Cell
    described: str  # how the report names the model's source (paths relative to the matrix file)


@dataclass(frozen=True)
class FinetuneJob(Job):
    """Fine-tune the pristine source with a strategy's training steps (cached by content)."""

    mode = "bench_matrix.jobs.prepare:finetune"
    source: SourceModel
    steps: tuple[StrategySpec, ...]
    trainer: str
    task: str
    data: PreparedData
    layout: str
    seed: int


@dataclass(frozen=True)
class ConvertJob(Job):
    """Convert a source into a cell's artifact (cached by content)."""

    mode = "bench_matrix.jobs.cell:convert"
    cell: Cell
    step: StrategySpec
    source: SourceModel
    data: PreparedData
    layout: str
    settings: Settings
    options: dict[str, Any]


@dataclass(frozen=True)
class MeasureJob(Job):
    """Load an artifact, time it, evaluate it against the labels and the baseline's outputs (and drive laps
    with it when `closed_loop` says so)."""

    mode = "bench_matrix.jobs.cell:measure"
    cell: Cell
    task: str
    artifact_dir: Path
    manifest: dict[str, Any]
    cached: bool
    source: SourceModel
    data: PreparedData
    layout: str
    settings: Settings
    reference: Path | None
    metrics: tuple[str, ...] = ()
    finetune: dict[str, Any] | None = None
    closed_loop: ClosedLoopPlan | None = None  # laps to drive with the loaded session, after the evaluation
