"""Drive the measurement of chosen cells: each model's dataset and preparation once, then its cells' measure
jobs (what they are: `CellJobs`) timed together in rounds, each outcome handed to where it goes (`Outlet`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Protocol

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import StepError, UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Work
from bench_matrix.jobs import DatasetJob, MeasureJob, ModelJob, RoundsJob
from bench_matrix.jobs.results import PreparedData, PreparedModel
from bench_matrix.plan import ModelPlan, Plan
from bench_matrix.progress import RunProgress
from bench_matrix.workspace import Workspace, digest

PREPARE_TIMEOUT_S = 4 * 3600.0


@dataclass(frozen=True)
class Ready:
    """A model ready for its cells: its plan, its dataset, its source and reference outputs."""

    model: ModelPlan
    data: PreparedData
    prepared: PreparedModel


@dataclass(frozen=True)
class Measuring:
    """A cell's measure job waiting for its model's rounds: its plan, measure job, start and machine."""

    plan: CellPlan
    job: MeasureJob
    started: str
    where: Any


Made = Callable[[CellPlan, list[Measuring]], None]  # a cell's measure jobs are made (none: it failed before)
Measure = Callable[[list[Measuring]], None]  # measure these jobs in rounds


class Outlet(Protocol):
    """Where a run's outcomes go: the store for `run` (run.py), each cell's twins by side for `compare
    --remeasure` (remeasure.py)."""

    def fact(self, kind: str, name: str, value: Any) -> None:
        """What preparing a dataset or a model found out."""

    def failed(self, p: CellPlan, reason: str, started: str, env: dict | None = None) -> None:
        """A cell failed before it was measured."""

    def claim(self, model: str, measuring: list[Measuring], measure: Measure) -> None:
        """A model's measure jobs are made: `measure` those still to measure, now or once that may start."""

    def rounds_ended(self, group: list[Measuring], ended: Ended) -> None:
        """How a rounds job of the group ended."""


class CellJobs(Protocol):
    """What a model's cells are measured by: each one's measure jobs (run.py: converted first; remeasure.py:
    the two stored artifacts), and the rounds job timing them on one machine."""

    def start(self, ready: Ready, cells: list[CellPlan], work: Dispatch, made: Made) -> None:
        """Make each cell's measure jobs, what they need submitted to `work` first; pass them to `made`."""

    def rounds(self, group: list[Measuring], baseline: Cell | None) -> RoundsJob:
        """The rounds job of a model's measure jobs on one machine, paired against the model's baseline."""


class Dispatch:
    """Hands work to the executor and calls back with how it ended; shared preparation goes once per run."""

    def __init__(self, executor: Executor, progress: RunProgress):
        self.executor, self.progress = executor, progress
        self._handlers: dict[Work, Callable[[Ended], None]] = {}
        self._shared: dict[Any, list[Callable[[Ended], None]] | Ended] = {}  # waiting for it, or how it ended

    def submit(self, work: Work, then: Callable[[Ended], None]) -> None:
        """Hand work to the executor; `then` takes how it ended (at once when the executor ran it already).
        Its phases show under the step it was handed over in, whatever steps began since."""
        self._handlers[work] = then
        step = self.progress.current
        self.executor.submit(work, lambda name: self.progress.phase(name, step), self.progress.tick)
        self.drain(wait=False)

    def drain(self, wait: bool) -> None:
        """Call back for the work ended so far, or (`wait`) for all work still due."""
        for ended in self.executor.ended(wait):
            self._handlers.pop(ended.work)(ended)

    def once(self, key: Any, work: Work, then: Callable[[Ended], None], step: str | None = None) -> None:
        """Shared preparation, run once per run: `then` takes how it ended, at once if it has, else when it
        does."""
        known = self._shared.get(key)
        if isinstance(known, Ended):
            then(known)
        elif known is not None:
            known.append(then)
        else:
            self._shared[key] = [then]
            if step:
                self.progress.step(step)
            self.submit(work, lambda ended: self._shared_ended(key, ended))

    def _shared_ended(self, key: Any, ended: Ended) -> None:
        waiting, self._shared[key] = self._shared[key], ended
        for then in waiting:
            then(ended)


@dataclass
class Gathering:
    """A model's cells while their measure jobs are made: the cells still pending, and the jobs made."""

    ready: Ready
    pending: set[str]
    measuring: list[Measuring] = field(default_factory=list)


class Runner:
    """Measures the chosen cells: each model prepared once, its cells' measure jobs made by `jobs`, then timed
    together, one rounds job per machine holding their artifacts; every outcome goes to `outlet`."""

    def __init__(self, plan: Plan, workspace: Workspace, work: Dispatch, outlet: Outlet, jobs: CellJobs):
        self.plan, self.matrix, self.ws = plan, plan.matrix, workspace
        self.work, self.progress, self.outlet, self.jobs = work, work.progress, outlet, jobs
        self._gathering: dict[str, Gathering] = {}

    def measure(self, cells: list[CellPlan]) -> None:
        """Measure the cells, model by model; returns once every job has ended."""
        for model in self.matrix.models:
            chosen = [p for p in cells if p.cell.model == model.name]
            if chosen:
                self._prepare_data(self.plan.models[model.name], chosen)
        self.work.drain(wait=True)

    def _prepare_data(self, model: ModelPlan, cells: list[CellPlan]) -> None:
        """The model's dataset, prepared once per run (synthetic data: once per set of inputs; once per set of
        arrays passed as they are); then the model."""
        inputs = model.inputs if model.dataset.kind == "synthetic" else None
        key = digest({"dataset": model.dataset, "inputs": [i.to_dict() for i in inputs or ()],
                      **({"as_is": model.as_is} if model.as_is else {})})
        work = Work(DatasetJob(self.ws, model.dataset, inputs or (), model.as_is),
                    Limits(self.ws.log("dataset"), PREPARE_TIMEOUT_S))
        self.work.once(key, work, lambda ended: self._prepare_model(model, cells, ended), "preparing dataset")

    def _prepare_model(self, model: ModelPlan, cells: list[CellPlan], data: Ended) -> None:
        if not data.ok:
            error = UserError if data.user_error else StepError
            raise error(f"dataset: {data.error}" + ("" if data.user_error else
                                                   f"\n(full log: {self.ws.log('dataset')})"))
        prepared: PreparedData = data.result
        name = "info" if model.dataset == self.matrix.dataset else f"info:{prepared.fingerprint}"
        self.outlet.fact("dataset", name, prepared.info)
        if model.baseline is None:
            why = f"no installed backend computes the fp32 baseline of {model.spec.framework} models"
            self._model_failed(model, cells, why)
            return
        self.progress.step(f"preparing model {model.spec.name}")
        job = ModelJob(self.ws, model.spec, model.inputs, model.task, prepared, self.matrix.settings,
                       model.baseline, model.described)
        self.work.submit(Work(job, Limits(model.log, PREPARE_TIMEOUT_S)),
                         lambda ended: self._start_cells(model, prepared, cells, ended))

    def _model_failed(self, model: ModelPlan, cells: list[CellPlan], why: str | None) -> None:
        reason = f"preparing model {model.spec.name} failed: {why}"
        for p in cells:
            started = now()
            self.progress.step(f"{model.spec.name} · {p.cell.label}")
            self.outlet.failed(p, reason, started)

    def _start_cells(self, model: ModelPlan, data: PreparedData, cells: list[CellPlan], ended: Ended) -> None:
        if not ended.ok:
            self._model_failed(model, cells, ended.error)
            return
        ready = Ready(model, data, ended.result)
        self.outlet.fact(f"model:{model.spec.name}", "info", ready.prepared.info)
        self._gathering[model.spec.name] = Gathering(ready, {p.cell.key for p in cells})
        self.jobs.start(ready, cells, self.work, self._made)

    def _made(self, p: CellPlan, measuring: list[Measuring]) -> None:
        """A cell's measure jobs are made; once all of its model's are, the outlet claims them."""
        gathering = self._gathering[p.cell.model]
        gathering.pending.discard(p.cell.key)
        gathering.measuring.extend(measuring)
        if not gathering.pending:
            model = gathering.ready.model
            self.outlet.claim(model.spec.name, gathering.measuring,
                              lambda chosen: self._rounds(model, chosen))

    def _rounds(self, model: ModelPlan, measuring: list[Measuring]) -> None:
        """A model's measure jobs timed together, in rounds, one rounds job per machine holding their
        artifacts."""
        by_machine: dict[Any, list[Measuring]] = {}
        for m in measuring:
            by_machine.setdefault(m.where, []).append(m)
        for where, group in by_machine.items():
            job = self.jobs.rounds(group, model.baseline)
            limits = Limits(cell_log(self.ws, group[0].plan), self.matrix.settings.timeout_s,
                            self.matrix.settings.threads)
            self.progress.step(f"{model.spec.name} · measuring {len(group)} cells in rounds")
            self.work.submit(Work(job, limits, on=where),
                             lambda ended, group=group: self.outlet.rounds_ended(group, ended))


def cell_log(ws: Workspace, p: CellPlan) -> Path:
    """The log of a cell's jobs."""
    return p.log or ws.cell_log(p.cell.key)


def now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
