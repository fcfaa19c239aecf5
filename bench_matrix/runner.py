"""Run a plan: prepare data and models, run each cell in its own processes, store each result as it ends."""

from __future__ import annotations

import base64
import time
from dataclasses import dataclass, field, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import StepError, UserError
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


@dataclass
class PreparedModel:
    """A model ready for its cells: its source, its data and its reference outputs."""

    source: SourceModel
    data: PreparedData
    reference: Path


class Runner:
    """Runs the runnable cells of a plan one at a time and writes each record as soon as it ends."""

    def __init__(self, plan: Plan, workspace: Workspace, store: ResultStore | None, progress_console: Any,
                 label: str | None = None):
        self.plan, self.matrix, self.ws, self.store = plan, plan.matrix, workspace, store
        self.console, self.label, self.host = progress_console, label, environment.host_name()
        self.run_id: int | None = None
        self._datasets: dict[str, PreparedData] = {}
        self._again: dict[Cell, tuple[CellRecord, MeasureJob]] = {}  # ok cells and their measure job
        self._samples: dict[Cell, dict[str, bytes]] = {}  # raw latencies of a measured cell, until stored

    def run(self, filters: Filters, force: bool) -> dict[str, int]:
        filters.check([p.cell for p in self.plan.cells])
        chosen = [p for p in self.plan.cells if p.state != "invalid" and filters.keep(p.cell)]
        if not chosen:
            raise UserError("no cell of the matrix matches the filters (see `bench-matrix plan`)")
        todo = [p for p in chosen if p.state == "run" and (force or not self.is_done(p))]
        counts = {"ok": 0, "skipped": 0, "failed": 0,
                  "cached": len([p for p in chosen if p.state == "run"]) - len(todo)}
        begin = time.monotonic()
        run = self.store.begin_run(str(self.matrix.path), self.host, environment.run_versions(), self.label, _now())
        self.run_id = run.id
        completed = False
        try:
            self._run_cells(chosen, todo, counts)
            completed = True
        finally:
            self.store.end_run(run.id, _now(), {"wall_s": round(time.monotonic() - begin, 1), "counts": counts,
                                                "completed": completed})
        return counts

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
                    for record in self._run_model(self.plan.models[model.name], cells, progress):
                        counts[record.status] += 1
            for number in range(2, self.matrix.settings.passes + 1):
                self._pass(number, progress)

    def _run_model(self, model: ModelPlan, cells: list[CellPlan], progress: RunProgress):
        prepared = self._prepare(model, progress)
        for p in cells:
            started = _now()
            progress.step(f"{model.spec.name} · {p.cell.label}")
            if not prepared.ok:
                reason = f"preparing model {model.spec.name} failed: {prepared.error}"
                record = self._record(p, "failed", reason, started)
            else:
                record = self._run_cell(p, model, prepared.value, progress, started)
            self.store.put(record, self._samples.pop(p.cell, None))
            progress.finished(record)
            yield record

    def _pass(self, number: int, progress: RunProgress) -> None:
        """Measure every ok cell once more (fresh process, same artifact); keep the pass with the lowest p50."""
        settings = self.matrix.settings
        for cell, (record, job) in self._again.items():
            progress.step(f"pass {number}/{settings.passes} · {cell.model} · {cell.label}")
            measured = run_job(job, self.ws.jobs, self.ws.cell_log(cell.key), settings.timeout_s,
                               settings.threads, progress.phase, progress.tick)
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

    def _run_cell(self, p: CellPlan, model: ModelPlan, prepared: PreparedModel, progress: RunProgress,
                  started: str) -> CellRecord:
        settings, cell, log = self.matrix.settings, p.cell, p.log
        source, facts = prepared.source, None
        if p.training:  # fine-tune first (all cores, cached): a new source model
            job = FinetuneJob(self.ws, source, p.training, p.trainer, model.task, prepared.data,
                              model.spec.layout, settings.seed)
            tuned = run_job(job, self.ws.jobs, log, PREPARE_TIMEOUT_S, on_phase=progress.phase, tick=progress.tick)
            if not tuned.ok:
                return self._record(p, "failed", f"finetune: {tuned.error}", started)
            source, facts = SourceModel.from_dict(tuned.value["source"]), tuned.value["facts"]
        deadline = time.monotonic() + settings.timeout_s
        convert = ConvertJob(self.ws, cell, p.step, source, prepared.data, model.spec.layout, settings,
                             self.matrix.backend_options.get(cell.backend, {}))
        converted = run_job(convert, self.ws.jobs, log, settings.timeout_s, settings.threads, progress.phase,
                            progress.tick)
        if not converted.ok:
            return self._record(p, "failed", f"convert: {converted.error}", started)
        artifact = converted.value["artifact_dir"] + "/model"
        job = MeasureJob(self.ws, cell, model.task, Path(converted.value["artifact_dir"]),
                         converted.value["manifest"], converted.value["cached"], source, prepared.data,
                         model.spec.layout, settings, prepared.reference, self.matrix.metrics,
                         facts, closed_loop=p.closed_loop)
        measured = run_job(job, self.ws.jobs, log, max(deadline - time.monotonic(), 1.0), settings.threads,
                           progress.phase, progress.tick)
        if not measured.ok:
            return self._record(p, "failed", f"measure: {measured.error}", started, artifact=artifact)
        metrics = {**measured.value["metrics"], "latency_passes_p50": [measured.value["metrics"]["latency_ms"]["p50"]]}
        self._samples[cell] = _samples(measured.value)
        record = self._record(p, "ok", None, started, metrics=metrics, env=measured.value["env"], artifact=artifact)
        self._again[cell] = (record, replace(job, closed_loop=None))  # later passes time; they do not drive
        return record

    def is_done(self, p: CellPlan) -> bool:
        """Whether this host's newest record of the cell is an ok one of the same fingerprint, every pass made."""
        record = self.store.latest(p.cell, self.host) if self.store else None
        return (record is not None and record.status == "ok" and record.fingerprint == p.fingerprint
                and len(record.metrics.get("latency_passes_p50", [0])) >= self.matrix.settings.passes)

    def _skipped_before(self, p: CellPlan) -> bool:
        """Whether this host's newest record of a cell to skip already skips it for the same reason."""
        record = self.store.latest(p.cell, self.host)
        return record is not None and (record.status, record.reason, record.fingerprint) == (
            "skipped", p.reason, p.fingerprint)

    def _record(self, p: CellPlan, status: str, reason: str | None, started: str, metrics: dict | None = None,
                env: dict | None = None, artifact: str | None = None) -> CellRecord:
        return CellRecord(cell=p.cell, status=status, reason=reason, metrics=metrics or {}, artifact_path=artifact,
                          env=env or environment.capture(), started_at=started, finished_at=_now(),
                          fingerprint=p.fingerprint, matrix=str(self.matrix.path), run_id=self.run_id)


def _samples(measured: dict[str, Any]) -> dict[str, bytes]:
    """The packed raw latencies a measure job returned (base64 in its JSON), by series."""
    return {series: base64.b64decode(text) for series, text in (measured.get("samples") or {}).items()}


def _disturbance(metrics: dict[str, Any]) -> tuple[bool, float]:
    """How a pass ranks: unflagged before flagged, then the lower p50 (interference only adds time)."""
    return bool((metrics.get("interference") or {}).get("flagged")), metrics["latency_ms"]["p50"]


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
