"""Drive a run: hand every job the chosen cells need to an executor (each model's dataset and preparation,
each fine-tuning once, then each cell's conversion and measurement) and store each record as its cell ends."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from bench_matrix.cell import CellPlan
from bench_matrix.errors import StepError, UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Work
from bench_matrix.jobs import ConvertJob, DatasetJob, FinetuneJob, MeasureJob, ModelJob, RoundsJob
from bench_matrix.jobs.results import PreparedData, PreparedModel
from bench_matrix.measure import env as environment
from bench_matrix.measure.machine_lock import store_lock
from bench_matrix.measurement import Measurement
from bench_matrix.placement import place
from bench_matrix.plan import ModelPlan, Plan
from bench_matrix.progress import RunProgress
from bench_matrix.selection import Filters, Shard
from bench_matrix.sources import SourceModel
from bench_matrix.store import CellRecord, ResultStore
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
    """A converted cell waiting for its model's rounds: its plan, measure job, start and machine."""

    plan: CellPlan
    job: MeasureJob
    started: str
    where: Any


@dataclass
class Converting:
    """A model's cells while they convert: the cells still converting, and the converted ones."""

    ready: Ready
    pending: set[str]
    measuring: list[Measuring] = field(default_factory=list)


class Runner:
    """Runs the jobs of the chosen cells through an executor, what they share once, and writes each record as
    soon as its cell ends."""

    def __init__(self, plan: Plan, workspace: Workspace, store: ResultStore, executor: Executor,
                 progress_console: Any, label: str | None = None, shard: Shard = Shard()):
        self.plan, self.matrix, self.ws, self.store = plan, plan.matrix, workspace, store
        self.executor, self.console, self.label, self.shard = executor, progress_console, label, shard
        self.host, self.run_id = environment.host_name(), None
        self.counts: dict[str, int] = {}
        self.progress: RunProgress
        self._handlers: dict[Work, Callable[[Ended], None]] = {}
        self._shared: dict[Any, list[Callable[[Ended], None]] | Ended] = {}  # waiting for it, or how it ended
        self._converting: dict[str, Converting] = {}
        self.force = False
        self._held: dict[str, list[int]] = {}  # model -> [its store lock, its rounds jobs not stored yet]
        self._deferred: list[Converting] = []  # waiting for a busy store lock until this run holds none

    def run(self, filters: Filters, force: bool) -> dict[str, int]:
        filters.check([p.cell for p in self.plan.cells])
        chosen = [p for p in self.plan.cells if p.state != "invalid" and filters.keep(p.cell)]
        if not chosen:
            raise UserError("no cell of the matrix matches the filters (see `bench-matrix plan`)")
        chosen = self.shard.select(chosen)
        chosen, able = place(self.matrix, chosen, self.executor.probes(self.matrix, chosen))
        self.executor.place(able)
        todo = [p for p in chosen if p.state == "run" and (force or not self._done(p))]
        self.force = force
        self.counts = {"ok": 0, "skipped": 0, "failed": 0,
                       "cached": len([p for p in chosen if p.state == "run"]) - len(todo)}
        begin = time.monotonic()
        self.ws.sweep()
        run = self.store.begin_run(str(self.matrix.path), self.host, environment.run_versions(), self.label,
                                   _now())
        self.run_id = run.id
        completed = False
        try:
            self._run_cells(chosen, todo)
            completed = True
        finally:
            wall_s = round(time.monotonic() - begin, 1)
            summary = {"wall_s": wall_s, "counts": self.counts, "completed": completed}
            self.store.end_run(run.id, _now(), {**summary, **self._shard_summary()})
            self.ws.sweep()
            for lock, _ in self._held.values():
                os.close(lock)
        return self.counts

    def _shard_summary(self) -> dict[str, str]:
        return {"shard": f"{self.shard.index}/{self.shard.count}"} if self.shard.count > 1 else {}

    def _done(self, p: CellPlan) -> bool:
        return self.store.is_done(p.cell, p.fingerprint, self.executor.hosts())

    def _run_cells(self, chosen: list[CellPlan], todo: list[CellPlan]) -> None:
        with RunProgress(self.console, len(todo)) as self.progress:
            skipped = [p for p in chosen if p.state == "skip" and not self._done(p)]  # keep a GPU box's ok
            records = [self._record(p, "skipped", p.reason, _now()) for p in skipped]
            for p, record in zip(skipped, records):
                if not self._skipped_before(p):
                    self.store.put(record)
            self.progress.skipped(records)
            self.counts["skipped"] = len(skipped)
            for model in self.matrix.models:
                cells = [p for p in todo if p.cell.model == model.name]
                if cells:
                    self._prepare_data(self.plan.models[model.name], cells)
            self._drain(wait=True)

    def _submit(self, work: Work, then: Callable[[Ended], None]) -> None:
        """Hand work to the executor; `then` takes how it ended (at once when the executor ran it already).
        Its phases show under the step it was handed over in, whatever steps began since."""
        self._handlers[work] = then
        step = self.progress.current
        self.executor.submit(work, lambda name: self.progress.phase(name, step), self.progress.tick)
        self._drain(wait=False)

    def _drain(self, wait: bool) -> None:
        for ended in self.executor.ended(wait):
            self._handlers.pop(ended.work)(ended)

    def _once(self, key: Any, work: Work, then: Callable[[Ended], None], step: str | None = None) -> None:
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
            self._submit(work, lambda ended: self._shared_ended(key, ended))

    def _shared_ended(self, key: Any, ended: Ended) -> None:
        waiting, self._shared[key] = self._shared[key], ended
        for then in waiting:
            then(ended)

    def _prepare_data(self, model: ModelPlan, cells: list[CellPlan]) -> None:
        """The model's dataset, prepared once per run (synthetic data: once per set of inputs; once per set of
        arrays passed as they are); then the model."""
        inputs = model.inputs if model.dataset.kind == "synthetic" else None
        key = digest({"dataset": model.dataset, "inputs": [i.to_dict() for i in inputs or ()],
                      **({"as_is": model.as_is} if model.as_is else {})})
        work = Work(DatasetJob(self.ws, model.dataset, inputs or (), model.as_is),
                    Limits(self.ws.log("dataset"), PREPARE_TIMEOUT_S))
        self._once(key, work, lambda ended: self._prepare_model(model, cells, ended), "preparing dataset")

    def _prepare_model(self, model: ModelPlan, cells: list[CellPlan], data: Ended) -> None:
        if not data.ok:
            error = UserError if data.user_error else StepError
            raise error(f"dataset: {data.error}" + ("" if data.user_error else
                                                   f"\n(full log: {self.ws.log('dataset')})"))
        prepared: PreparedData = data.result
        name = "info" if model.dataset == self.matrix.dataset else f"info:{prepared.fingerprint}"
        self._fact("dataset", name, prepared.info)
        if model.baseline is None:
            why = f"no installed backend computes the fp32 baseline of {model.spec.framework} models"
            self._model_failed(model, cells, why)
            return
        self.progress.step(f"preparing model {model.spec.name}")
        job = ModelJob(self.ws, model.spec, model.inputs, model.task, prepared, self.matrix.settings,
                       model.baseline, model.described)
        self._submit(Work(job, Limits(model.log, PREPARE_TIMEOUT_S)),
                     lambda ended: self._start_cells(model, prepared, cells, ended))

    def _model_failed(self, model: ModelPlan, cells: list[CellPlan], why: str | None) -> None:
        reason = f"preparing model {model.spec.name} failed: {why}"
        for p in cells:
            started = _now()
            self.progress.step(f"{model.spec.name} · {p.cell.label}")
            self._finished(self._record(p, "failed", reason, started))

    def _start_cells(self, model: ModelPlan, data: PreparedData, cells: list[CellPlan], ended: Ended) -> None:
        if not ended.ok:
            self._model_failed(model, cells, ended.error)
            return
        ready = Ready(model, data, ended.result)
        self._fact(f"model:{model.spec.name}", "info", ready.prepared.info)
        self._converting[model.spec.name] = Converting(ready, {p.cell.key for p in cells})
        for p in cells:
            self._start_cell(p, ready)

    def _start_cell(self, p: CellPlan, ready: Ready) -> None:
        """Convert the cell; fine-tuned first (once per model and strategy) when its strategy says so."""
        started = _now()
        self.progress.step(f"{ready.model.spec.name} · {p.cell.label}")
        if not p.training:
            self._convert(p, ready, ready.prepared.source, None, started)
            return
        job = FinetuneJob(self.ws, ready.prepared.source, p.training, p.trainer, ready.model.task, ready.data,
                          ready.model.spec.layout, self.matrix.settings.seed)
        work = Work(job, Limits(self._log(p), PREPARE_TIMEOUT_S))
        self._once((p.cell.model, p.cell.strategy), work, lambda tuned: self._tuned(p, ready, started, tuned))

    def _tuned(self, p: CellPlan, ready: Ready, started: str, tuned: Ended) -> None:
        if not tuned.ok:
            self._finished(self._record(p, "failed", f"finetune: {tuned.error}", started, env=tuned.env))
            self._settled(p, [])
            return
        self._convert(p, ready, tuned.result.source, tuned.result.facts, started)

    def _convert(self, p: CellPlan, ready: Ready, source: SourceModel, facts: dict | None,
                 started: str) -> None:
        """Convert the cell's source; it is measured with the model's other cells once all are converted."""
        model, settings = ready.model, self.matrix.settings
        job = ConvertJob(self.ws, p.cell, p.step, source, ready.data, model.spec.layout, settings,
                         self.matrix.backend_options.get(p.cell.backend, {}))
        self._submit(Work(job, self._limits(p)),
                     lambda ended: self._converted(p, ready, source, facts, started, ended))

    def _converted(self, p: CellPlan, ready: Ready, source: SourceModel, facts: dict | None, started: str,
                   ended: Ended) -> None:
        if not ended.ok:
            reason = f"{ended.jobs[-1].name}: {ended.error}"
            self._finished(self._record(p, "failed", reason, started, env=ended.env))
            self._settled(p, [])
            return
        model, settings = ready.model, self.matrix.settings
        job = MeasureJob(self.ws, p.cell, model.task, ended.result, source, ready.data, model.spec.layout,
                         settings, ready.prepared.reference, self.matrix.metrics, facts, p.scenarios)
        self._settled(p, [Measuring(p, job, started, ended.where)])

    def _settled(self, p: CellPlan, measuring: list[Measuring]) -> None:
        """A cell's conversion ended; once all of its model's have, its converted cells are claimed to be
        measured."""
        converting = self._converting[p.cell.model]
        converting.pending.discard(p.cell.key)
        converting.measuring.extend(measuring)
        if not converting.pending:
            self._claim(converting)

    def _claim(self, converting: Converting) -> None:
        """Measure a model's converted cells holding its store lock (one run at a time measures a model into a
        store: unless --force, those another run stored meanwhile are already stored). A busy lock is waited
        for only while this run holds none (two runs each waiting for the other's would wait for ever)."""
        model = converting.ready.model.spec.name
        if self.force or not converting.measuring:
            self._submit_rounds(converting.ready.model, converting.measuring)
            return
        lock = store_lock(self.store.path, model, not self._held, lambda: self.progress.step(
            f"{model} · waiting for another run measuring it into {self.store.path}"))
        if lock is None:
            self._deferred.append(converting)
            return
        measuring = [m for m in converting.measuring if not self._stored_meanwhile(m)]
        by_machine = {m.where for m in measuring}
        self._held[model] = [lock, len(by_machine)]
        if by_machine:
            self._submit_rounds(converting.ready.model, measuring)
        else:
            self._unlock(model)

    def _stored_meanwhile(self, m: Measuring) -> bool:
        """Whether another run stored the cell while this one converted it (counted, and said, already
        stored)."""
        if not self._done(m.plan):
            return False
        self.counts["cached"] += 1
        self.progress.already_stored(m.plan.cell)
        return True

    def _release(self, model: str) -> None:
        """One of a model's rounds jobs is stored; after the last, its store lock is released."""
        self._held[model][1] -= 1
        if self._held[model][1] == 0:
            self._unlock(model)

    def _unlock(self, model: str) -> None:
        """Release a model's store lock; holding none, claim a model deferred for a busy one."""
        os.close(self._held.pop(model)[0])
        if not self._held and self._deferred:
            self._claim(self._deferred.pop(0))

    def _submit_rounds(self, model: ModelPlan, measuring: list[Measuring]) -> None:
        """A model's converted cells measured together, in rounds, one rounds job per machine holding their
        artifacts."""
        by_machine: dict[Any, list[Measuring]] = {}
        for m in measuring:
            by_machine.setdefault(m.where, []).append(m)
        baseline = model.baseline
        for where, group in by_machine.items():
            job = self._rounds(group, baseline)
            limits = Limits(self._log(group[0].plan), self.matrix.settings.timeout_s,
                            self.matrix.settings.threads)
            self.progress.step(f"{model.spec.name} · measuring {len(group)} cells in rounds")
            self._submit(Work(job, limits, on=where), lambda ended, group=group: self._measured(group, ended))

    def _rounds(self, group: list[Measuring], baseline: Any) -> RoundsJob:
        """The rounds job of a model's cells on one machine, paired against their baseline if among them, for
        the answers its requirements ask."""
        keys = {m.plan.cell.key for m in group}
        return RoundsJob(self.ws, tuple(m.job for m in group), tuple(self._log(m.plan).name for m in group),
                         baseline.key if baseline is not None and baseline.key in keys else None,
                         requirements=self.matrix.requirements.of(group[0].plan.cell.model))

    def _measured(self, group: list[Measuring], ended: Ended) -> None:
        results = {c.key: c for c in ended.result.cells} if ended.ok else {}
        for m in group:
            artifact = str(m.job.converted.model)
            found = results.get(m.job.id)
            if found is None or found.measured is None:
                why = found.error if found is not None else ended.error
                self._finished(self._record(m.plan, "failed", f"measure: {why}", m.started, env=ended.env,
                                            artifact=artifact))
                continue
            measured = found.measured
            self._finished(self._record(m.plan, "ok", None, m.started, metrics=measured.metrics,
                                        env=measured.env, artifact=artifact), measured.samples)
        if not self.force:
            self._release(group[0].plan.cell.model)

    def _fact(self, kind: str, name: str, value: Any) -> None:
        self.store.put_fact(kind, name, value)

    def _limits(self, p: CellPlan) -> Limits:
        """A cell job's log, time limit and threads."""
        return Limits(self._log(p), self.matrix.settings.timeout_s, self.matrix.settings.threads)

    def _log(self, p: CellPlan) -> Path:
        return p.log or self.ws.cell_log(p.cell.key)

    def _finished(self, record: CellRecord, samples: dict[str, bytes] | None = None) -> None:
        self.store.put(record, samples)
        self.progress.finished(record)
        self.counts[record.status] += 1

    def _skipped_before(self, p: CellPlan) -> bool:
        """Whether the judging host's newest record of a cell to skip already skips it for the same reason."""
        record = self.store.latest(p.cell, p.judged_on or self.host)
        return record is not None and (record.status, record.reason, record.fingerprint) == (
            "skipped", p.reason, p.fingerprint)

    def _record(self, p: CellPlan, status: str, reason: str | None, started: str,
                metrics: Measurement | None = None, env: dict | None = None, artifact: str | None = None
                ) -> CellRecord:
        return CellRecord(cell=p.cell, status=status, reason=reason, metrics=metrics or Measurement(),
                          artifact_path=artifact, env=env or _judged_env(p), started_at=started,
                          finished_at=_now(), fingerprint=p.fingerprint, matrix=str(self.matrix.path),
                          run_id=self.run_id)


def _judged_env(p: CellPlan) -> dict:
    """This machine's facts, stored under the host that judged the cell (a device that skipped it)."""
    env = environment.capture()
    return {**env, "host": p.judged_on} if p.judged_on else env


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
