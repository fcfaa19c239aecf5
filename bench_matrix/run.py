"""`bench-matrix run`: the chosen cells through the runner, each converted (fine-tuned first where its
strategy says so) and then measured, and each record stored in the results store as soon as its cell ends."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Work
from bench_matrix.jobs import ConvertJob, FinetuneJob, MeasureJob, RoundsJob
from bench_matrix.matrix.spec import Matrix
from bench_matrix.measure import env as environment
from bench_matrix.measure.machine_lock import store_lock
from bench_matrix.measurement import Measurement
from bench_matrix.placement import place
from bench_matrix.plan import Plan
from bench_matrix.progress import RunProgress
from bench_matrix.runner import (PREPARE_TIMEOUT_S, Dispatch, Made, Measure, Measuring, Outlet, Ready, Runner,
                                 cell_log, now)
from bench_matrix.selection import Filters, Shard
from bench_matrix.sources import SourceModel
from bench_matrix.store import CellRecord, ResultStore
from bench_matrix.workspace import Workspace


def run(plan: Plan, workspace: Workspace, store: ResultStore, executor: Executor, console: Any,
        filters: Filters, force: bool, label: str | None = None, shard: Shard = Shard()) -> dict[str, int]:
    """Run the cells the filters and the shard choose, those stored already kept unless `force`; the counts
    of records by status, and of cells already stored."""
    filters.check([p.cell for p in plan.cells])
    chosen = [p for p in plan.cells if p.state != "invalid" and filters.keep(p.cell)]
    if not chosen:
        raise UserError("no cell of the matrix matches the filters (see `bench-matrix plan`)")
    chosen = shard.select(chosen)
    chosen, able = place(plan.matrix, chosen, executor.probes(plan.matrix, chosen))
    executor.place(able)
    todo = [p for p in chosen if p.state == "run"
            and (force or not store.is_done(p.cell, p.fingerprint, executor.hosts()))]
    begin = time.monotonic()
    workspace.sweep()
    host = environment.host_name()
    run_id = store.begin_run(str(plan.matrix.path), host, environment.run_versions(), label, now()).id
    progress = RunProgress(console, len(todo))
    outlet = StoreOutlet(store, plan.matrix, run_id, executor.hosts, host, progress, force)
    outlet.counts["cached"] = len([p for p in chosen if p.state == "run"]) - len(todo)
    completed = False
    try:
        with progress:
            outlet.skip([p for p in chosen if p.state == "skip"])
            Runner(plan, workspace, Dispatch(executor, progress), outlet,
                   Conversions(plan.matrix, workspace, outlet)).measure(todo)
        completed = True
    finally:
        wall_s = round(time.monotonic() - begin, 1)
        summary = {"wall_s": wall_s, "counts": outlet.counts, "completed": completed}
        shard_summary = {"shard": f"{shard.index}/{shard.count}"} if shard.count > 1 else {}
        store.end_run(run_id, now(), {**summary, **shard_summary})
        workspace.sweep()
        outlet.unlock_all()
    return outlet.counts


class Conversions:
    """A run's measure jobs: each cell fine-tuned where its strategy says (once per model and strategy), then
    converted, then measured against its model's reference; a step that fails is the cell's record."""

    def __init__(self, matrix: Matrix, workspace: Workspace, outlet: Outlet):
        self.matrix, self.ws, self.outlet = matrix, workspace, outlet

    def start(self, ready: Ready, cells: list[CellPlan], work: Dispatch, made: Made) -> None:
        for p in cells:
            self._start(p, ready, work, made)

    def _start(self, p: CellPlan, ready: Ready, work: Dispatch, made: Made) -> None:
        """One cell's way to its measure job: fine-tuned (where it is), converted, measured."""
        started, model, settings = now(), ready.model, self.matrix.settings
        work.progress.step(f"{model.spec.name} · {p.cell.label}")

        def failed(reason: str, env: dict | None) -> None:
            self.outlet.failed(p, reason, started, env)
            made(p, [])

        def convert(source: SourceModel, facts: dict | None) -> None:
            job = ConvertJob(self.ws, p.cell, p.step, source, ready.data, model.spec.layout, settings,
                             self.matrix.backend_options.get(p.cell.backend, {}))
            limits = Limits(cell_log(self.ws, p), settings.timeout_s, settings.threads)
            work.submit(Work(job, limits), lambda ended: converted(source, facts, ended))

        def converted(source: SourceModel, facts: dict | None, ended: Ended) -> None:
            if not ended.ok:
                failed(f"{ended.jobs[-1].name}: {ended.error}", ended.env)
                return
            job = MeasureJob(self.ws, p.cell, model.task, ended.result, source, ready.data, model.spec.layout,
                             settings, ready.prepared.reference, self.matrix.metrics, facts, p.scenarios)
            made(p, [Measuring(p, job, started, ended.where)])

        def tuned(ended: Ended) -> None:
            if ended.ok:
                convert(ended.result.source, ended.result.facts)
            else:
                failed(f"finetune: {ended.error}", ended.env)

        if not p.training:
            convert(ready.prepared.source, None)
            return
        job = FinetuneJob(self.ws, ready.prepared.source, p.training, p.trainer, model.task, ready.data,
                          model.spec.layout, settings.seed)
        work.once((p.cell.model, p.cell.strategy), Work(job, Limits(cell_log(self.ws, p), PREPARE_TIMEOUT_S)),
                  tuned)

    def rounds(self, group: list[Measuring], baseline: Cell | None) -> RoundsJob:
        """Paired against the baseline if it is among them, for the answers the model's requirements ask."""
        keys = {m.plan.cell.key for m in group}
        logs = tuple(cell_log(self.ws, m.plan).name for m in group)
        return RoundsJob(self.ws, tuple(m.job for m in group), logs,
                         baseline.key if baseline is not None and baseline.key in keys else None,
                         requirements=self.matrix.requirements.of(group[0].plan.cell.model))


class StoreOutlet:
    """A run's records, each put in the store as its cell ends, and counted; a model is measured holding its
    store lock (one run at a time measures a model into a store) unless `force`."""

    def __init__(self, store: ResultStore, matrix: Matrix, run_id: int, hosts: Callable[[], set[str]],
                 host: str, progress: RunProgress, force: bool):
        self.store, self.matrix, self.run_id, self.hosts, self.host = store, matrix, run_id, hosts, host
        self.progress, self.force = progress, force
        self.counts = {"ok": 0, "skipped": 0, "failed": 0, "cached": 0}
        self._held: dict[str, list[int]] = {}  # model -> [its store lock, its rounds jobs not stored yet]
        self._deferred: list[tuple[str, list[Measuring], Measure]] = []  # for a busy lock, till it holds none

    def fact(self, kind: str, name: str, value: Any) -> None:
        self.store.put_fact(kind, name, value)

    def skip(self, skipped: list[CellPlan]) -> None:
        """The cells to skip, not stored already (a GPU box's ok is kept): stored unless skipped before for
        the same reason."""
        skipped = [p for p in skipped if not self._done(p)]
        records = [self._record(p, "skipped", p.reason, now()) for p in skipped]
        for p, record in zip(skipped, records):
            if not self._skipped_before(p):
                self.store.put(record)
        self.progress.skipped(records)
        self.counts["skipped"] = len(skipped)

    def failed(self, p: CellPlan, reason: str, started: str, env: dict | None = None) -> None:
        self._finished(self._record(p, "failed", reason, started, env=env))

    def claim(self, model: str, measuring: list[Measuring], measure: Measure) -> None:
        """Measure a model's cells under its store lock (unless --force), skipping those another run stored
        meanwhile; wait on a busy lock only while holding none (else two runs could deadlock)."""
        if self.force or not measuring:
            measure(measuring)
            return
        lock = store_lock(self.store.path, model, not self._held, lambda: self.progress.step(
            f"{model} · waiting for another run measuring it into {self.store.path}"))
        if lock is None:
            self._deferred.append((model, measuring, measure))
            return
        measuring = [m for m in measuring if not self._stored_meanwhile(m)]
        by_machine = {m.where for m in measuring}  # the runner's rounds jobs: one per machine
        self._held[model] = [lock, len(by_machine)]
        if by_machine:
            measure(measuring)
        else:
            self._unlock(model)

    def rounds_ended(self, group: list[Measuring], ended: Ended) -> None:
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

    def unlock_all(self) -> None:
        """Release the store locks still held (the run stopped)."""
        for lock, _ in self._held.values():
            os.close(lock)

    def _done(self, p: CellPlan) -> bool:
        return self.store.is_done(p.cell, p.fingerprint, self.hosts())

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
            self.claim(*self._deferred.pop(0))

    def _finished(self, record: CellRecord, samples: dict[str, bytes] | None = None) -> None:
        self.store.put(record, samples)
        self.progress.finished(record)
        self.counts[record.status] += 1

    def _skipped_before(self, p: CellPlan) -> bool:
        """Whether the ruling host's newest record of a cell to skip already skips it for the same reason."""
        record = self.store.latest(p.cell, p.ruled_on or self.host)
        return record is not None and (record.status, record.reason, record.fingerprint) == (
            "skipped", p.reason, p.fingerprint)

    def _record(self, p: CellPlan, status: str, reason: str | None, started: str,
                metrics: Measurement | None = None, env: dict | None = None, artifact: str | None = None
                ) -> CellRecord:
        return CellRecord(cell=p.cell, status=status, reason=reason, metrics=metrics or Measurement(),
                          artifact_path=artifact, env=env or _ruled_env(p), started_at=started,
                          finished_at=now(), fingerprint=p.fingerprint, matrix=str(self.matrix.path),
                          run_id=self.run_id)


def _ruled_env(p: CellPlan) -> dict:
    """This machine's facts, stored under the host that ruled on the cell (a device that skipped it)."""
    env = environment.capture()
    return {**env, "host": p.ruled_on} if p.ruled_on else env
