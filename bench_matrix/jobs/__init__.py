"""The jobs, as typed values: probe, prepare a dataset or a model, fine-tune, convert, measure; each class
names the function that runs it (`function`) and its result's type (`result`, jobs/results.py)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from bench_matrix.cell import Cell, Planned
from bench_matrix.jobs.results import (
    Converted,
    Finetuned,
    Measured,
    MeasuredGroup,
    PreparedData,
    PreparedModel,
    Probe,
    Reference,
)
from bench_matrix.cell import TrainingKey, RulingKey
from bench_matrix.matrix.requirements import Requirements
from bench_matrix.matrix.spec import DatasetSpec, ModelSpec, Settings
from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import TensorSpec
from bench_matrix.workspace import Workspace


@dataclass(frozen=True)
class Job:
    """What every job has: the workspace it reads and writes."""

    name: ClassVar[str]  # how a failure's reason names the job: 'convert: ...'
    function: ClassVar[str]  # 'module:function' that runs the job in its own process
    result: ClassVar[type]
    # timed: it owns the clock of the machine its cell is placed on, so it runs in the executor's own process
    # there (`function(job, workdir, logs, on_phase)`), the sessions it times in processes of their own
    timed: ClassVar[bool] = False
    workspace: Workspace

    def reads(self) -> tuple[Path, ...]:
        """The files and folders made elsewhere (by the user, or by an earlier job) that the job reads: the
        machine running it must hold them."""
        return ()

    def placed(self) -> Cell | None:
        """The cell whose machine must run the job (the plan places each cell); None: any machine."""
        return None

    def ships(self) -> tuple[Path, ...]:
        """What a machine other than this one needs to run the job: what it reads."""
        return self.reads()

    def datasets(self) -> set[Path]:
        """The prepared datasets among them of which that machine needs only the measured split."""
        return set()


@dataclass(frozen=True)
class ProbeJob(Job):
    """Describe backends, rule on combinations and fine-tunings, read the inputs model files declare and the
    parameters of factories' forward."""

    name = "probe"
    function = "bench_matrix.jobs.probe:probe"
    result = Probe
    backends: tuple[str, ...]
    keys: tuple[RulingKey, ...] | None = None  # None: every combination the backends declare
    training: tuple[TrainingKey, ...] = ()
    model_files: tuple[tuple[str, str, str], ...] = ()  # (framework, source format, path) of user model files
    factories: tuple[tuple[str, tuple[str, ...]], ...] = ()  # (factory, python_path) whose forward to read
    # a device's probe: conversion and fine-tuning happen where the run started, so only running is ruled on
    measure_only: bool = False

    def reads(self) -> tuple[Path, ...]:
        return tuple(Path(path) for _, _, path in self.model_files)


@dataclass(frozen=True)
class DatasetJob(Job):
    """Read, check, preprocess and split a dataset (synthetic: of these inputs; `as_is`: arrays already in the
    model's per-sample shapes, passed as they are)."""

    name = "dataset"
    function = "bench_matrix.jobs.prepare:prepare_dataset"
    result = PreparedData
    dataset: DatasetSpec
    inputs: tuple[TensorSpec, ...] = ()
    as_is: tuple[str, ...] = ()

    def reads(self) -> tuple[Path, ...]:
        return self.dataset.paths


@dataclass(frozen=True)
class ModelJob(Job):
    """Materialise a model's source (training a built-in), check it against the data, compute its
    reference."""

    name = "model"
    function = "bench_matrix.jobs.prepare:prepare_model"
    result = PreparedModel
    model: ModelSpec
    inputs: tuple[TensorSpec, ...] | None  # declared or read from the file; None: the dataset's
    task: str
    data: PreparedData
    settings: Settings
    baseline: Cell
    described: str  # how the report names the model's source (paths relative to the matrix file)

    def reads(self) -> tuple[Path, ...]:
        return tuple(p for p in (self.data.directory, self.model.file, self.model.weights) if p is not None)


@dataclass(frozen=True)
class ReferenceJob(Job):
    """The fp32 outputs of a baseline's converted artifact on the test split: the reference of one side of a
    comparison, whose source may have changed since (compare --remeasure)."""

    name = "reference"
    function = "bench_matrix.jobs.prepare:reference_outputs"
    result = Reference
    baseline: Cell
    converted: Converted
    source: SourceModel
    data: PreparedData
    layout: str
    settings: Settings

    def reads(self) -> tuple[Path, ...]:
        return self.converted.directory, self.data.directory


@dataclass(frozen=True)
class FinetuneJob(Job):
    """Fine-tune the pristine source with a strategy's training steps (cached by content)."""

    name = "finetune"
    function = "bench_matrix.jobs.prepare:finetune"
    result = Finetuned
    source: SourceModel
    steps: tuple[StrategySpec, ...]
    trainer: str
    task: str
    data: PreparedData
    layout: str
    seed: int

    def reads(self) -> tuple[Path, ...]:
        return self.source.path, self.data.directory

    def placed(self) -> Cell:
        return self.cell


@dataclass(frozen=True)
class ConvertJob(Job):
    """Convert a source into a cell's artifact (cached by content)."""

    name = "convert"
    function = "bench_matrix.jobs.artifact:convert"
    result = Converted
    cell: Cell
    step: StrategySpec
    source: SourceModel
    data: PreparedData
    layout: str
    settings: Settings
    options: dict[str, Any]

    def reads(self) -> tuple[Path, ...]:
        return self.source.path, self.data.directory

    def placed(self) -> Cell:
        return self.cell


@dataclass(frozen=True)
class MeasureJob(Job):
    """One cell of a RoundsJob: its artifact, loaded in its own session process that the executor times in
    windows, then evaluated against labels and baseline outputs (latency) and its other scenarios."""

    name = "measure"
    function = "bench_matrix.jobs.measure:open_session"  # a Served session: windows on demand, then finish
    result = Measured
    cell: Cell
    task: str
    converted: Converted  # on the machine that runs this job
    source: SourceModel
    data: PreparedData
    layout: str
    settings: Settings
    reference: Path | None
    metrics: tuple[str, ...] = ()
    finetune: dict[str, Any] | None = None
    scenarios: tuple[Planned, ...] = ()  # run with the loaded session after the latency scenario
    side: str = ""  # which side of a comparison the artifact is (compare --remeasure); "" in a run

    def reads(self) -> tuple[Path, ...]:
        return tuple(p for p in (self.data.directory, self.reference) if p is not None)

    @property
    def id(self) -> str:
        """The session's name in its rounds: the cell key, with the side where there is one."""
        return f"{self.cell.key}@{self.side}" if self.side else self.cell.key


@dataclass(frozen=True)
class RoundsJob(Job):
    """Measure a model's cells in interleaved rounds (docs/metrics.md §5), the executor timing each cell's
    session in its own process; speed-ups paired against `baseline` (a cell's `id`), or by `references`."""

    name = "measure"
    function = "bench_matrix.executors.rounds:measure_in_rounds"
    result = MeasuredGroup
    timed = True
    cells: tuple[MeasureJob, ...]
    logs: tuple[str, ...]  # each cell's log file name, in the folder of the work's log
    baseline: str | None = None
    references: tuple[tuple[str, str], ...] = ()  # (id, the id its speed-up is paired against instead)
    requirements: Requirements | None = None  # what the rounds answer (None: every cell to one precision)

    def reads(self) -> tuple[Path, ...]:
        return tuple(dict.fromkeys(p for job in self.cells for p in job.reads()))

    def placed(self) -> Cell:
        """Its first cell's: a model's cells on one machine are timed together."""
        return self.cells[0].cell

    def ships(self) -> tuple[Path, ...]:
        """What it reads and the artifacts it measures."""
        return tuple(dict.fromkeys((*self.reads(), *(job.converted.directory for job in self.cells))))

    def datasets(self) -> set[Path]:
        return {job.data.directory for job in self.cells}
