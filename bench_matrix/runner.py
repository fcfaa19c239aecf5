"""Run a plan: prepare data and models, hand each cell to an executor (each job in its own process), store
each result as it ends."""

from __future__ import annotations

import base64
import re
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import StepError, UserError
from bench_matrix.executors import CellResult, CellWork, Executor
from bench_matrix.executors.local import LocalExecutor
from bench_matrix.jobs import ConvertJob, DatasetJob, FinetuneJob, MeasureJob, ModelJob, PreparedData
from bench_matrix.launcher import Outcome, run_job
from bench_matrix.matrix.load import suggest
from bench_matrix.measure import env as environment
from bench_matrix.plan import ModelPlan, Plan
from bench_matrix.progress import RunProgress
from bench_matrix.sources import SourceModel
from bench_matrix.store import CellRecord, ResultStore
from bench_matrix.workspace import Workspace, digest

PREPARE_TIMEOUT_S = 4 * 3600.0


@dataclass(frozen=True)
class Filters:
    """Cell selection from the command line: each key keeps cells whose value is in the set."""

    values: dict[str, frozenset[str]] = field(default_factory=dict)

    def keep(self, cell: Cell) -> bool:
        return all(getattr(cell, key) in allowed for key, allowed in self.values.items())

    def check(self, cells: list[Cell]) -> None:
        """A filter value that no cell of the matrix has is a typo: say so, with what exists."""
        for key, wanted in self.values.items():
            present = sorted({getattr(c, key) for c in cells})
            for value in sorted(wanted - set(present)):
                raise UserError(f"--{key} {value}: no cell of the matrix has this {key}; it has "
                                f"{', '.join(present)}{suggest(value, present)}")


@dataclass(frozen=True)
class Shard:
    """Shard `index` of `count` (1-based): a contiguous block of the chosen cells sorted by key, so every
    machine given the same matrix and filters computes the same partition."""

    index: int = 1
    count: int = 1

    @classmethod
    def parse(cls, text: str) -> "Shard":
        """`I/N` with 1 <= I <= N; a UserError naming --shard and what is allowed otherwise."""
        found = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
        index, count = (int(found[1]), int(found[2])) if found else (0, 0)
        if not found or count < 1 or not 1 <= index <= count:
            raise UserError(f"--shard {text}: give I/N, this machine's shard I of N shards, whole numbers "
                            f"with 1 <= I <= N (e.g. --shard 1/4 ... --shard 4/4)")
        return cls(index, count)

    def select(self, cells: list[CellPlan]) -> list[CellPlan]:
        ordered = sorted(cells, key=lambda p: p.cell.key)
        n = len(ordered)
        begin, end = (self.index - 1) * n // self.count, self.index * n // self.count
        mine = {p.cell.key for p in ordered[begin:end]}
        return [p for p in cells if p.cell.key in mine]


@dataclass
class PreparedModel:
    """A model ready for its cells: its source, its data and its reference outputs."""

    source: SourceModel
    data: PreparedData
    reference: Path


class Runner:
    """Prepares what the chosen cells share, hands each cell to an executor and writes each record as soon as
    the cell ends."""

    def __init__(self, plan: Plan, workspace: Workspace, store: ResultStore | None, progress_console: Any,
                 label: str | None = None, executor: Executor | None = None, shard: Shard = Shard()):
        self.plan, self.matrix, self.ws, self.store = plan, plan.matrix, workspace, store
        self.console, self.label, self.host = progress_console, label, environment.host_name()
        self.executor, self.shard = executor or LocalExecutor(workspace), shard
        self.run_id: int | None = None
        self._datasets: dict[str, PreparedData] = {}
        self._again: dict[Cell, tuple[CellRecord, CellResult]] = {}  # ok cells and how they were measured

    def run(self, filters: Filters, force: bool) -> dict[str, int]:
        filters.check([p.cell for p in self.plan.cells])
        chosen = [p for p in self.plan.cells if p.state != "invalid" and filters.keep(p.cell)]
        if not chosen:
            raise UserError("no cell of the matrix matches the filters (see `bench-matrix plan`)")
        chosen = self.executor.decide(self.plan, self.shard.select(chosen))
        todo = [p for p in chosen if p.state == "run" and (force or not self.is_done(p))]
        counts = {"ok": 0, "skipped": 0, "failed": 0,
                  "cached": len([p for p in chosen if p.state == "run"]) - len(todo)}
        begin = time.monotonic()
        run = self.store.begin_run(str(self.matrix.path), self.host, environment.run_versions(), self.label,
                                   _now())
        self.run_id = run.id
        completed = False
        try:
            self._run_cells(chosen, todo, counts)
            completed = True
        finally:
            summary = {"wall_s": round(time.monotonic() - begin, 1), "counts": counts, "completed": completed}
            self.store.end_run(run.id, _now(), {**summary, **self._shard_summary()})
        return counts

    def _shard_summary(self) -> dict[str, str]:
        return {"shard": f"{self.shard.index}/{self.shard.count}"} if self.shard.count > 1 else {}

    def _run_cells(self, chosen: list[CellPlan], todo: list[CellPlan], counts: dict[str, int]) -> None:
        with RunProgress(self.console, len(todo) * self.matrix.settings.passes) as progress:
            skipped = [p for p in chosen if p.state == "skip" and not self.is_done(p)]  # keep a GPU box's ok
            records = [self._record(p, "skipped", p.reason, _now()) for p in skipped]
            for p, record in zip(skipped, records):
                if not self._skipped_before(p):
                    self.store.put(record)
            progress.skipped(records)
            counts["skipped"] = len(skipped)
            for model in self.matrix.models:
                cells = [p for p in todo if p.cell.model == model.name]
                if cells:
                    self._run_model(self.plan.models[model.name], cells, progress, counts)
            self._collect(progress, counts, wait=True)
            for number in range(2, self.matrix.settings.passes + 1):
                self._pass(number, progress)

    def _run_model(self, model: ModelPlan, cells: list[CellPlan], progress: RunProgress,
                   counts: dict[str, int]) -> None:
        prepared = self._prepare(model, progress)
        for p in cells:
            started = _now()
            progress.step(f"{model.spec.name} · {p.cell.label}")
            if not prepared.ok:
                reason = f"preparing model {model.spec.name} failed: {prepared.error}"
                self._finished(self._record(p, "failed", reason, started), None, progress, counts)
                continue
            work = self._work(p, model, prepared.value, progress, started)
            if isinstance(work, CellRecord):
                self._finished(work, None, progress, counts)
            else:
                self.executor.submit(work, progress.phase, progress.tick)
            self._collect(progress, counts, wait=False)

    def _collect(self, progress: RunProgress, counts: dict[str, int], wait: bool) -> None:
        """Store the results the executor has (with `wait`: every one still due, each as it ends)."""
        for result in self.executor.results(wait):
            p = result.work.plan
            if not result.ok:
                record = self._record(p, "failed", result.error, result.work.started, env=result.env,
                                      artifact=result.artifact)
                self._finished(record, None, progress, counts)
                continue
            measured = result.measured
            metrics = measured["metrics"]
            metrics = {**metrics, "latency_passes_p50": [metrics["latency_ms"]["p50"]]}
            record = self._record(p, "ok", None, result.work.started, metrics=metrics, env=measured["env"],
                                  artifact=result.artifact)
            self._finished(record, _samples(measured), progress, counts)
            self._again[p.cell] = (record, result)

    def _finished(self, record: CellRecord, samples: dict[str, bytes] | None, progress: RunProgress,
                  counts: dict[str, int]) -> None:
        self.store.put(record, samples)
        progress.finished(record)
        counts[record.status] += 1

    def _pass(self, number: int, progress: RunProgress) -> None:
        """Measure every ok cell once more (fresh process, same artifact); keep the pass with the lowest
        p50."""
        for cell, (record, result) in self._again.items():
            progress.step(f"pass {number}/{self.matrix.settings.passes} · {cell.model} · {cell.label}")
            measured = self.executor.measure_again(result, progress.phase, progress.tick)
            passes, samples = record.metrics["latency_passes_p50"], None
            if measured.ok:
                new = measured.value["metrics"]
                passes.append(new["latency_ms"]["p50"])
                if _disturbance(new) < _disturbance(record.metrics):
                    laps = {k: v for k, v in record.metrics.items() if k.startswith("closed_loop")}
                    record.metrics = {**new, **laps, "latency_passes_p50": passes}
                    record.env = measured.value["env"]
                    samples = _samples(measured.value)
            else:
                record.metrics["latency_passes_failed"] = record.metrics.get("latency_passes_failed", 0) + 1
            record.finished_at = _now()
            self.store.put(record, samples)
            progress.finished(record)

    def _data(self, model: ModelPlan, progress: RunProgress) -> PreparedData:
        """The model's dataset, prepared once per run (synthetic data: once per set of inputs)."""
        inputs = model.inputs if model.dataset.kind == "synthetic" else None
        key = digest({"dataset": model.dataset, "inputs": [i.to_dict() for i in inputs or ()]})
        if key not in self._datasets:
            progress.step("preparing dataset")
            outcome = run_job(DatasetJob(self.ws, model.dataset, inputs or ()), self.ws.jobs,
                              self.ws.log("dataset"), PREPARE_TIMEOUT_S, on_phase=progress.phase,
                              tick=progress.tick)
            if not outcome.ok:
                error = UserError if outcome.user_error else StepError
                raise error(f"dataset: {outcome.error}" + ("" if outcome.user_error else
                                                          f"\n(full log: {self.ws.log('dataset')})"))
            info = outcome.value["info"]
            self._datasets[key] = PreparedData(Path(outcome.value["dir"]), info, model.dataset.preprocess)
            self.store.put_fact("dataset", "info" if model.dataset == self.matrix.dataset else
                                f"info:{info['fingerprint']}", info)
        return self._datasets[key]

    def _prepare(self, model: ModelPlan, progress: RunProgress) -> Outcome:
        prepared = self._data(model, progress)
        if model.baseline is None:
            return Outcome(error=f"no installed backend computes the fp32 baseline of {model.spec.framework} "
                                 f"models")
        progress.step(f"preparing model {model.spec.name}")
        job = ModelJob(self.ws, model.spec, model.inputs, model.task, prepared, self.matrix.settings,
                       model.baseline, model.described)
        outcome = run_job(job, self.ws.jobs, model.log, PREPARE_TIMEOUT_S, on_phase=progress.phase,
                          tick=progress.tick)
        if not outcome.ok:
            return outcome
        self.store.put_fact(f"model:{model.spec.name}", "info", outcome.value["info"])
        return Outcome(value=PreparedModel(SourceModel.from_dict(outcome.value["source"]), prepared,
                                           Path(outcome.value["reference"])))

    def _work(self, p: CellPlan, model: ModelPlan, prepared: PreparedModel, progress: RunProgress,
              started: str) -> CellWork | CellRecord:
        """The cell's jobs, after its fine-tuning (shared preparation: here, cached by content); a failed
        record when the fine-tuning fails."""
        settings, cell, source, facts = self.matrix.settings, p.cell, prepared.source, None
        if p.training:  # fine-tune first (all cores, cached): a new source model
            job = FinetuneJob(self.ws, source, p.training, p.trainer, model.task, prepared.data,
                              model.spec.layout, settings.seed)
            tuned = run_job(job, self.ws.jobs, p.log, PREPARE_TIMEOUT_S, on_phase=progress.phase,
                            tick=progress.tick)
            if not tuned.ok:
                return self._record(p, "failed", f"finetune: {tuned.error}", started)
            source, facts = SourceModel.from_dict(tuned.value["source"]), tuned.value["facts"]
        convert = ConvertJob(self.ws, cell, p.step, source, prepared.data, model.spec.layout, settings,
                             self.matrix.backend_options.get(cell.backend, {}))
        measure = MeasureJob(self.ws, cell, model.task, Path(), {}, False, source, prepared.data,
                             model.spec.layout, settings, prepared.reference, self.matrix.metrics, facts,
                             closed_loop=p.closed_loop)
        return CellWork(p, convert, measure, p.log or self.ws.cell_log(cell.key), started)

    def is_done(self, p: CellPlan) -> bool:
        """Whether the newest record of the cell on the executor's hosts is an ok one of the same fingerprint,
        every pass made."""
        record = self._latest(p.cell) if self.store else None
        return (record is not None and record.status == "ok" and record.fingerprint == p.fingerprint
                and len(record.metrics.get("latency_passes_p50", [0])) >= self.matrix.settings.passes)

    def _skipped_before(self, p: CellPlan) -> bool:
        """Whether this host's newest record of a cell to skip already skips it for the same reason."""
        record = self.store.latest(p.cell, self.host)
        return record is not None and (record.status, record.reason, record.fingerprint) == (
            "skipped", p.reason, p.fingerprint)

    def _latest(self, cell: Cell) -> CellRecord | None:
        """The newest record of the cell on any of the executor's hosts."""
        found = [r for host in sorted(self.executor.hosts()) if (r := self.store.latest(cell, host))]
        return max(found, key=lambda r: (r.finished_at or r.started_at or "", r.id or 0), default=None)

    def _record(self, p: CellPlan, status: str, reason: str | None, started: str, metrics: dict | None = None,
                env: dict | None = None, artifact: str | None = None) -> CellRecord:
        return CellRecord(cell=p.cell, status=status, reason=reason, metrics=metrics or {},
                          artifact_path=artifact, env=env or environment.capture(), started_at=started,
                          finished_at=_now(), fingerprint=p.fingerprint, matrix=str(self.matrix.path),
                          run_id=self.run_id)


def _samples(measured: dict[str, Any]) -> dict[str, bytes]:
    """The packed raw latencies a measure job returned (base64 in its JSON), by series."""
    return {series: base64.b64decode(text) for series, text in (measured.get("samples") or {}).items()}


def _disturbance(metrics: dict[str, Any]) -> tuple[bool, float]:
    """How a pass ranks: unflagged before flagged, then the lower p50 (interference only adds time)."""
    return bool((metrics.get("interference") or {}).get("flagged")), metrics["latency_ms"]["p50"]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
