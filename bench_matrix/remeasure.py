"""`compare --remeasure`: the artifacts both sides of a comparison measured, timed again on this machine in
the same interleaved rounds, each new artifact's speed-up paired against its base one (docs/results.md §2)."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.executors.base import Ended, Executor, Limits, Work
from bench_matrix.jobs import MeasureJob, ReferenceJob, RoundsJob
from bench_matrix.jobs.results import Converted, Measured
from bench_matrix.matrix.spec import Matrix
from bench_matrix.plan import Plan
from bench_matrix.progress import RunProgress
from bench_matrix.runner import PREPARE_TIMEOUT_S, Dispatch, Made, Measure, Measuring, Ready, Runner
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
    why the others were not remeasured: where the runner's outcomes go (nothing is stored)."""

    measured: dict[str, dict[str, Measured]] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)

    def fact(self, kind: str, name: str, value: Any) -> None:
        """A comparison stores nothing."""

    def failed(self, p: CellPlan, reason: str, started: str, env: dict | None = None) -> None:
        self.missing[p.cell.key] = reason

    def claim(self, model: str, measuring: list[Measuring], measure: Measure) -> None:
        """Twins are measured without a store's lock: nothing is stored."""
        measure(measuring)

    def rounds_ended(self, group: list[Measuring], ended: Ended) -> None:
        results = {c.key: c for c in ended.result.cells} if ended.ok else {}
        for m in group:
            found = results.get(m.job.id)
            if found is not None and found.measured is not None:
                self.measured.setdefault(m.plan.cell.key, {})[m.job.side] = found.measured
            else:
                why = found.error if found is not None else ended.error
                self.missing[m.plan.cell.key] = f"measure ({m.job.side}): {why}"
        for m in group:
            if m.plan.cell.key in self.missing:
                self.measured.pop(m.plan.cell.key, None)


def twins(base: Iterable[CellRecord], new: Iterable[CellRecord]) -> Twins:
    """The cells ok on both sides whose two artifacts are on this machine."""
    before = {r.cell.key: r for r in base if r.status == "ok"}
    found = Twins({})
    for record in new:
        other = before.get(record.cell.key)
        if record.status != "ok" or other is None:
            continue
        base_folder, new_folder = _folder(other), _folder(record)
        if base_folder is not None and new_folder is not None:
            found.folders[record.cell.key] = (base_folder, new_folder)
            continue
        lacking = [f"{side}'s {r.artifact_path or '(none recorded)'}" for side, r, folder
                   in zip((BASE, NEW), (other, record), (base_folder, new_folder)) if folder is None]
        found.missing[record.cell.key] = f"artifact not on this machine: {', '.join(lacking)}"
    return found


def _converted(folder: Path) -> Converted:
    """An artifact's folder as a cached conversion."""
    return Converted(folder, json.loads((folder / "manifest.json").read_text()), True)


def _folder(record: CellRecord) -> Path | None:
    """The converted artifact's folder (holding the model and its manifest), if it is here."""
    folder = Path(record.artifact_path).parent if record.artifact_path else None
    return folder if folder is not None and (folder / "manifest.json").is_file() else None


def remeasure(plan: Plan, workspace: Workspace, executor: Executor, console: Any, found: Twins) -> Remeasured:
    """A run's preparation of each model (dataset, source, reference outputs), then every cell's twins timed
    in its rounds; the measurements, and why any could not be taken."""
    result = Remeasured(missing=dict(found.missing))
    plans = {p.cell.key: p for p in plan.cells}
    chosen = [plans[key] for key in found.folders if key in plans and plans[key].state == "run"]
    for key in found.folders:
        if key not in plans:
            result.missing[key] = f"not a cell of {plan.matrix.path}"
        elif plans[key].state != "run":
            result.missing[key] = f"{plans[key].state}: {plans[key].reason}"
    with RunProgress(console, 0) as progress:
        twin_jobs = StoredTwins(plan.matrix, workspace, found.folders)
        Runner(plan, workspace, Dispatch(executor, progress), result, twin_jobs).measure(chosen)
    return result


class StoredTwins:
    """`compare --remeasure`'s measure jobs: each cell's two stored artifacts as they are (no fine-tuning, no
    conversion), each scored against its side's reference, timed side by side in one rounds job."""

    def __init__(self, matrix: Matrix, workspace: Workspace, folders: dict[str, tuple[Path, Path]]):
        self.matrix, self.ws, self.folders = matrix, workspace, folders

    def start(self, ready: Ready, cells: list[CellPlan], work: Dispatch, made: Made) -> None:
        """First each side's reference: the outputs of its own baseline's artifact (none where the baseline is
        not remeasured: that side's fidelity is not scored), then the cells."""
        model, baseline = ready.model, ready.model.baseline
        folders = self.folders.get(baseline.key) if baseline is not None else None
        if baseline is None or folders is None:
            self._cells(ready, cells, {}, made)
            return
        references: dict[str, Path | None] = {}

        def kept(side: str, done: Ended) -> None:
            references[side] = done.result.outputs if done.ok else None
            if len(references) == len(folders):
                self._cells(ready, cells, references, made)

        for side, folder in zip((BASE, NEW), folders):
            job = ReferenceJob(self.ws, baseline, _converted(folder), ready.prepared.source, ready.data,
                               model.spec.layout, self.matrix.settings)
            work.submit(Work(job, Limits(model.log, PREPARE_TIMEOUT_S)),
                        lambda done, side=side: kept(side, done))

    def _cells(self, ready: Ready, cells: list[CellPlan], references: dict[str, Path | None], made: Made
               ) -> None:
        """Both artifacts of each cell, each scored against its side's reference."""
        model, settings = ready.model, self.matrix.settings
        processes = max(settings.processes, TWIN_PROCESSES)  # and as many rounds as the run's processes had:
        settings = replace(settings, processes=processes,  # the budget grows with the processes
                           timing_budget_s=settings.timing_budget_s * processes / settings.processes)
        for p in cells:
            made(p, [Measuring(p, MeasureJob(self.ws, p.cell, model.task, _converted(folder),
                                             ready.prepared.source, ready.data, model.spec.layout, settings,
                                             references.get(side), self.matrix.metrics, side=side), "", None)
                     for side, folder in zip((BASE, NEW), self.folders[p.cell.key])])

    def rounds(self, group: list[Measuring], baseline: Cell | None) -> RoundsJob:
        """Twins side by side (so a memory budget seldom parts them), each new one paired against its base."""
        group.sort(key=lambda m: (m.plan.cell.key, m.job.side))
        ids = {m.job.id for m in group}
        base = f"{baseline.key}@{BASE}" if baseline is not None else None
        return RoundsJob(self.ws, tuple(m.job for m in group),
                         tuple(self.ws.cell_log(m.job.id).name for m in group), base if base in ids else None,
                         tuple((m.job.id, f"{m.plan.cell.key}@{BASE}") for m in group if m.job.side == NEW))
