"""`compare --remeasure`: the artifacts both sides of a comparison measured, timed again on this machine in
the same interleaved rounds, each new artifact's speed-up paired against its base one (docs/results.md §2)."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bench_matrix.cell import CellPlan
from bench_matrix.executors.base import Ended, Executor, Limits, Work
from bench_matrix.jobs import MeasureJob, ReferenceJob, RoundsJob
from bench_matrix.jobs.results import Converted, Measured, PreparedData
from bench_matrix.plan import ModelPlan, Plan
from bench_matrix.progress import RunProgress
from bench_matrix.runner import PREPARE_TIMEOUT_S, Converting, Measuring, Ready, Runner
from bench_matrix.store import CellRecord
from bench_matrix.workspace import Workspace

BASE, NEW = "base", "new"
TWIN_PROCESSES = 4  # at least this many session processes a side: how two processes of one artifact differ
# (about 1 % here) is then estimated with 3 degrees of freedom a side, not 1, and averages out by √4


@dataclass(frozen=True)
class Twins:
    """The artifact folders (base, new) of each cell ok on both sides, and why others cannot be remeasured."""

    folders: dict[str, tuple[Path, Path]]
    missing: dict[str, str] = field(default_factory=dict)


@dataclass
class Remeasured:
    """Each remeasured cell's two measurements by side (the new one's speed-up is against its base twin), and
    why the others were not remeasured."""

    measured: dict[str, dict[str, Measured]] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)


def twins(base: Iterable[CellRecord], new: Iterable[CellRecord]) -> Twins:
    """The cells ok on both sides whose two artifacts are on this machine."""
    before = {r.cell.key: r for r in base if r.status == "ok"}
    found = Twins({})
    for record in new:
        other = before.get(record.cell.key)
        if record.status != "ok" or other is None:
            continue
        folders = [_folder(r) for r in (other, record)]
        lacking = [f"{side}'s {r.artifact_path or '(none recorded)'}" for side, r, folder
                   in zip((BASE, NEW), (other, record), folders) if folder is None]
        if lacking:
            found.missing[record.cell.key] = f"artifact not on this machine: {', '.join(lacking)}"
        else:
            found.folders[record.cell.key] = (folders[0], folders[1])  # type: ignore[assignment]
    return found


def _converted(folder: Path) -> Converted:
    """An artifact's folder as a cached conversion."""
    return Converted(folder, json.loads((folder / "manifest.json").read_text()), True)


def _folder(record: CellRecord) -> Path | None:
    """The converted artifact's folder (holding the model and its manifest), if it is here."""
    folder = Path(record.artifact_path).parent if record.artifact_path else None
    return folder if folder is not None and (folder / "manifest.json").is_file() else None


class Remeasure(Runner):
    """A run's preparation of each model (dataset, source, reference outputs), then its cells' two artifacts
    timed in its rounds instead of converted; nothing is stored."""

    def __init__(self, plan: Plan, workspace: Workspace, executor: Executor, console: Any, found: Twins):
        super().__init__(plan, workspace, None, executor, console)  # type: ignore[arg-type]
        self.twins, self.result = found, Remeasured(missing=dict(found.missing))
        self.references: dict[str, dict[str, Path | None]] = {}  # model -> side -> its own baseline's outputs

    def remeasure(self) -> Remeasured:
        """Time every cell's twins; the measurements, and why any could not be taken."""
        plans = {p.cell.key: p for p in self.plan.cells}
        chosen = [plans[key] for key in self.twins.folders if key in plans and plans[key].state == "run"]
        for key in self.twins.folders:
            if key not in plans:
                self.result.missing[key] = f"not a cell of {self.matrix.path}"
            elif plans[key].state != "run":
                self.result.missing[key] = f"{plans[key].state}: {plans[key].reason}"
        with RunProgress(self.console, 0) as self.progress:
            for model in self.matrix.models:
                cells = [p for p in chosen if p.cell.model == model.name]
                if cells:
                    self._prepare_data(self.plan.models[model.name], cells)
            self._drain(wait=True)
        return self.result

    def _start_cells(self, model: ModelPlan, data: PreparedData, cells: list[CellPlan], ended: Ended) -> None:
        """First each side's reference: the outputs of its own baseline's artifact (none where the baseline is
        not remeasured: that side's fidelity is not scored), then the cells."""
        baseline = model.baseline
        folders = self.twins.folders.get(baseline.key) if baseline is not None and ended.ok else None
        found = self.references.setdefault(model.spec.name, {})
        if folders is None:
            Runner._start_cells(self, model, data, cells, ended)
            return

        def kept(side: str, done: Ended) -> None:
            found[side] = done.result.outputs if done.ok else None
            if len(found) == len(folders):
                Runner._start_cells(self, model, data, cells, ended)

        for side, folder in zip((BASE, NEW), folders):
            job = ReferenceJob(self.ws, baseline, _converted(folder), ended.result.source, data,
                               model.spec.layout, self.matrix.settings)
            self._submit(Work(job, Limits(model.log, PREPARE_TIMEOUT_S)),
                         lambda done, side=side: kept(side, done))

    def _start_cell(self, p: CellPlan, ready: Ready) -> None:
        """Both artifacts of the cell, as they are (no fine-tuning, no conversion), each scored against its
        side's own baseline."""
        model, settings = ready.model, self.matrix.settings
        processes = max(settings.processes, TWIN_PROCESSES)  # and as many rounds as the run's processes had:
        settings = replace(settings, processes=processes,  # the budget grows with the processes
                           timing_budget_s=settings.timing_budget_s * processes / settings.processes)
        measuring = []
        references = self.references.get(model.spec.name, {})
        for side, folder in zip((BASE, NEW), self.twins.folders[p.cell.key]):
            job = MeasureJob(self.ws, p.cell, model.task, _converted(folder), ready.prepared.source,
                             ready.data, model.spec.layout, settings, references.get(side),
                             self.matrix.metrics, side=side)
            measuring.append(Measuring(p, job, "", None))
        self._settled(p, measuring)

    def _claim(self, converting: Converting) -> None:
        """A comparison stores nothing: its twins are measured without a store's lock."""
        self._submit_rounds(converting.ready.model, converting.measuring)

    def _rounds(self, group: list[Measuring], baseline: Any) -> RoundsJob:
        """Twins side by side (so a memory budget seldom parts them), each new one paired against its base."""
        group.sort(key=lambda m: (m.plan.cell.key, m.job.side))
        ids = {m.job.id for m in group}
        base = f"{baseline.key}@{BASE}" if baseline is not None else None
        return RoundsJob(self.ws, tuple(m.job for m in group),
                         tuple(self.ws.cell_log(m.job.id).name for m in group), base if base in ids else None,
                         tuple((m.job.id, f"{m.plan.cell.key}@{BASE}") for m in group if m.job.side == NEW))

    def _measured(self, group: list[Measuring], ended: Ended) -> None:
        results = {c.key: c for c in ended.result.cells} if ended.ok else {}
        for m in group:
            found = results.get(m.job.id)
            if found is not None and found.measured is not None:
                self.result.measured.setdefault(m.plan.cell.key, {})[m.job.side] = found.measured
            else:
                why = found.error if found is not None else ended.error
                self.result.missing[m.plan.cell.key] = f"measure ({m.job.side}): {why}"
        for m in group:
            if m.plan.cell.key in self.result.missing:
                self.result.measured.pop(m.plan.cell.key, None)

    def _fact(self, kind: str, name: str, value: Any) -> None:
        """A comparison stores nothing."""

    def _finished(self, record: CellRecord, samples: dict[str, bytes] | None = None) -> None:
        self.result.missing[record.cell.key] = record.reason or record.status
