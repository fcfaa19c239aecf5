"""Run a matrix: plan it, prepare data and models, run each cell in its own processes, store each result."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from bench_matrix import __version__, data
from bench_matrix.backends.registry import available
from bench_matrix.cell import Cell, PlannedCell
from bench_matrix.errors import StepError, UserError
from bench_matrix.launcher import Outcome, run_job
from bench_matrix.matrix.load import suggest
from bench_matrix.matrix.expand import Expansion, TrainingKey, Verdict, combinations, plan, training_key, verdict_key
from bench_matrix.matrix.spec import Matrix, ModelSpec
from bench_matrix.measure import env as environment
from bench_matrix.progress import RunProgress
from bench_matrix.store import CellRecord, ResultStore
from bench_matrix.workspace import Workspace, digest, file_sha256

PREPARE_TIMEOUT_S = 4 * 3600.0
PROBE_TIMEOUT_S = 300.0


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
class Planned:
    """The expansion plus what the probe learned about each backend."""

    expansion: Expansion
    backends: dict[str, Any]
    trainers: dict[TrainingKey, Verdict] = field(default_factory=dict)  # which trainer applies each fine-tuning

    def baseline_backend(self, framework: str) -> str | None:
        return next((n for n, b in self.backends.items() if framework in b.get("baseline_for", [])), None)


def resolve(matrix: Matrix, workspace: Workspace) -> Planned:
    """Expand the matrix and judge every combination in a child process (imports stay out of the parent)."""
    installed = list(available())
    cells, excluded = combinations(matrix, installed)
    keys = sorted({verdict_key(matrix, c) for c in cells})
    training = sorted({k for c in cells if (k := training_key(matrix, c))})
    names = sorted(set(installed) | {k[0] for k in keys})
    outcome = run_job({"mode": "probe", "backends": names, "keys": keys, "training": training},
                      workspace.root / "jobs", workspace.logs / "probe.log", PROBE_TIMEOUT_S)
    if not outcome.ok:
        raise UserError(f"probing the installed backends failed: {outcome.error}")
    verdicts = {tuple(json.loads(k)): Verdict(**v) for k, v in outcome.value["verdicts"].items()}
    trainers = {tuple(json.loads(k)): Verdict(**v) for k, v in outcome.value["trainers"].items()}
    return Planned(plan(matrix, cells, excluded, verdicts, trainers), outcome.value["backends"], trainers)


class Runner:
    """Runs the runnable cells of a plan one at a time and writes each record as soon as it ends."""

    def __init__(self, matrix: Matrix, workspace: Workspace, store: ResultStore, progress_console: Any):
        self.matrix, self.ws, self.store, self.console = matrix, workspace, store, progress_console
        self.dataset_fingerprint = data.fingerprint(matrix.dataset)
        self.libraries = environment.library_versions()  # an upgraded runtime makes stored results stale
        self._dataset: dict[str, Any] | None = None
        self._hashes: dict[Path, str] = {}
        self._again: dict[Cell, tuple[CellRecord, dict[str, Any]]] = {}  # ok cells and their measure job

    def run(self, planned: Planned, filters: Filters, force: bool) -> dict[str, int]:
        filters.check([p.cell for p in planned.expansion.cells])
        chosen = [p for p in planned.expansion.cells if p.state != "invalid" and filters.keep(p.cell)]
        if not chosen:
            raise UserError("no cell of the matrix matches the filters (see `bench-matrix plan`)")
        todo = [p for p in chosen if p.state == "run" and (force or not self.is_done(p.cell))]
        counts = {"ok": 0, "skipped": 0, "failed": 0, "cached": len([p for p in chosen if p.state == "run"]) - len(todo)}
        begin, started = time.monotonic(), _now()
        with RunProgress(self.console, len(todo) * self.matrix.settings.passes) as progress:
            skipped = [self._record(p.cell, "skipped", p.reason, _now()) for p in chosen
                       if p.state == "skip" and not self.is_done(p.cell)]  # keep a current ok result (e.g. from a GPU box)
            for record in skipped:
                self.store.put(record)
            progress.skipped(skipped)
            counts["skipped"] = len(skipped)
            for model in self.matrix.models:
                cells = [p for p in todo if p.cell.model == model.name]
                if cells:
                    for record in self._run_model(model, cells, planned, progress):
                        counts[record.status] += 1
            for number in range(2, self.matrix.settings.passes + 1):
                self._pass(number, progress)
        self.store.put_fact("run", "last", {"matrix": str(self.matrix.path), "started_at": started,
                                            "finished_at": _now(), "wall_s": round(time.monotonic() - begin, 1),
                                            "counts": counts})
        return counts

    def _run_model(self, model: ModelSpec, cells: list[PlannedCell], planned: Planned, progress: RunProgress):
        prepared = self._prepare(model, planned, progress)
        for p in cells:
            started = _now()
            progress.step(f"{model.name} · {p.cell.label}")
            if not prepared.ok:
                record = self._record(p.cell, "failed", f"preparing model {model.name} failed: {prepared.error}", started)
            else:
                record = self._run_cell(p.cell, model, prepared.value, planned, progress, started)
            self.store.put(record)
            progress.finished(record)
            yield record

    def _pass(self, number: int, progress: RunProgress) -> None:
        """Measure every ok cell once more (fresh process, same artifact); keep the pass with the lowest p50."""
        settings = self.matrix.settings
        for cell, (record, job) in self._again.items():
            progress.step(f"pass {number}/{settings.passes} · {cell.model} · {cell.label}")
            log = self.ws.logs / f"{cell.key.replace('/', '__')}.log"
            measured = run_job(job, self.ws.root / "jobs", log, settings.timeout_s, settings.threads,
                               progress.phase, progress.tick)
            passes = record.metrics["latency_passes_p50"]
            if measured.ok:
                new = measured.value["metrics"]
                passes.append(new["latency_ms"]["p50"])
                if new["latency_ms"]["p50"] < record.metrics["latency_ms"]["p50"]:
                    record.metrics, record.env = {**new, "latency_passes_p50": passes}, measured.value["env"]
            else:
                record.metrics["latency_passes_failed"] = record.metrics.get("latency_passes_failed", 0) + 1
            record.finished_at = _now()
            self.store.put(record)
            progress.finished(record)

    def _prepare(self, model: ModelSpec, planned: Planned, progress: RunProgress) -> Outcome:
        settings, common = self.matrix.settings, {"workspace": str(self.ws.root)}
        if self._dataset is None:
            progress.step("preparing dataset")
            outcome = self._job({"mode": "prepare_dataset", "dataset": self.matrix.dataset, **common},
                                "dataset", PREPARE_TIMEOUT_S, progress)
            if not outcome.ok:
                error = UserError if outcome.user_error else StepError
                raise error(f"dataset: {outcome.error}" + ("" if outcome.user_error else
                                                          f"\n(full log: {self.ws.logs / 'dataset.log'})"))
            self._dataset = outcome.value
            self.store.put_fact("dataset", "info", outcome.value["info"])
        baseline = planned.baseline_backend(model.framework)
        if baseline is None:
            return Outcome(error=f"no installed backend computes the fp32 baseline of {model.framework} models")
        progress.step(f"preparing model {model.name}")
        outcome = self._job({"mode": "prepare_model", "model": model, "dataset_dir": self._dataset["dir"],
                             "dataset_info": self._dataset["info"], "preprocess": self.matrix.dataset.preprocess,
                             "settings": settings, "baseline_backend": baseline, **common},
                            f"model-{model.name}", PREPARE_TIMEOUT_S, progress)
        if outcome.ok:
            self.store.put_fact(f"model:{model.name}", "info", outcome.value["info"])
        return outcome

    def _run_cell(self, cell: Cell, model: ModelSpec, prepared: dict[str, Any], planned: Planned,
                  progress: RunProgress, started: str) -> CellRecord:
        settings = self.matrix.settings
        job = {"cell": cell, "source": prepared["source"], "strategy": self.matrix.strategies[cell.strategy],
               "dataset_dir": self._dataset["dir"], "dataset_info": self._dataset["info"],
               "preprocess": self.matrix.dataset.preprocess, "layout": model.layout, "settings": settings,
               "workspace": str(self.ws.root), "reference": prepared["reference"]}
        log = self.ws.logs / f"{cell.key.replace('/', '__')}.log"
        if key := training_key(self.matrix, cell):  # fine-tune first (all cores, cached): a new source model
            tuned = run_job({**job, "mode": "finetune", "trainer": planned.trainers[key].by}, self.ws.root / "jobs",
                            log, PREPARE_TIMEOUT_S, on_phase=progress.phase, tick=progress.tick)
            if not tuned.ok:
                return self._record(cell, "failed", f"finetune: {tuned.error}", started)
            job = {**job, "source": tuned.value["source"], "finetune": tuned.value["facts"]}
        deadline = time.monotonic() + settings.timeout_s
        converted = run_job({**job, "mode": "convert"}, self.ws.root / "jobs", log, settings.timeout_s,
                            settings.threads, progress.phase, progress.tick)
        if not converted.ok:
            return self._record(cell, "failed", f"convert: {converted.error}", started)
        measured = run_job({**job, **converted.value, "mode": "measure"}, self.ws.root / "jobs", log,
                           max(deadline - time.monotonic(), 1.0), settings.threads, progress.phase, progress.tick)
        if not measured.ok:
            return self._record(cell, "failed", f"measure: {measured.error}", started,
                                artifact=converted.value["artifact_dir"] + "/model")
        metrics = {**measured.value["metrics"], "latency_passes_p50": [measured.value["metrics"]["latency_ms"]["p50"]]}
        record = self._record(cell, "ok", None, started, metrics=metrics, env=measured.value["env"],
                              artifact=converted.value["artifact_dir"] + "/model")
        self._again[cell] = (record, {**job, **converted.value, "mode": "measure"})
        return record

    def _job(self, job: dict[str, Any], log_name: str, timeout: float, progress: RunProgress) -> Outcome:
        return run_job(job, self.ws.root / "jobs", self.ws.logs / f"{log_name}.log", timeout,
                       on_phase=progress.phase, tick=progress.tick)

    def is_done(self, cell: Cell) -> bool:
        record = self.store.get(cell)
        return (record is not None and record.status == "ok" and record.fingerprint == self.fingerprint(cell)
                and len(record.metrics.get("latency_passes_p50", [0])) >= self.matrix.settings.passes)

    def fingerprint(self, cell: Cell) -> str:
        """Everything that determines a cell's result; a stored record with another fingerprint is stale."""
        model = self.matrix.model(cell.model)
        files = [self._file_hash(p) for p in (model.file, model.weights) if p is not None]
        return digest({"cell": cell.key, "model": asdict(model), "files": files, "dataset": self.dataset_fingerprint,
                       "libraries": self.libraries,
                       "strategy": self.matrix.strategies[cell.strategy].to_dict(),
                       "settings": {k: v for k, v in self.matrix.settings.to_dict().items()
                                    if k not in ("timeout_s", "passes")},  # neither changes what is measured
                       "version": __version__})

    def _file_hash(self, path: Path) -> str:
        """Content hash of a model file, computed once per run (fingerprints are asked for per cell)."""
        if path not in self._hashes:
            self._hashes[path] = file_sha256(path)
        return self._hashes[path]

    def _record(self, cell: Cell, status: str, reason: str | None, started: str, metrics: dict | None = None,
                env: dict | None = None, artifact: str | None = None) -> CellRecord:
        return CellRecord(cell=cell, status=status, reason=reason, metrics=metrics or {}, artifact_path=artifact,
                          env=env or environment.capture(), started_at=started, finished_at=_now(),
                          fingerprint=self.fingerprint(cell), matrix=str(self.matrix.path))


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")
