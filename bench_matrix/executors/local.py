"""The local executor: each cell's conversion and measurement run one after the other on this machine, each
in its own process (`launcher.run_job`). The Ray executor's tasks run cells with these same functions."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

from bench_matrix.executors.base import CellResult, CellWork, Executor, Phase, Tick
from bench_matrix.jobs import MeasureJob
from bench_matrix.launcher import Outcome, run_job
from bench_matrix.measure import env as environment
from bench_matrix.workspace import Workspace


def convert_cell(work: CellWork, on_phase: Phase, tick: Tick) -> tuple[Outcome, MeasureJob | None]:
    """Convert the cell's source; the outcome and the measurement job of the artifact it made."""
    settings = work.convert.settings
    converted = run_job(work.convert, work.convert.workspace.jobs, work.log, settings.timeout_s,
                        settings.threads, on_phase, tick)
    if not converted.ok:
        return converted, None
    value = converted.value
    return converted, replace(work.measure, artifact_dir=Path(value["artifact_dir"]),
                              manifest=value["manifest"], cached=value["cached"])


def measure_cell(job: MeasureJob, log: Path, timeout_s: float, on_phase: Phase, tick: Tick) -> Outcome:
    """Load, time and evaluate an artifact in its own process."""
    return run_job(job, job.workspace.jobs, log, timeout_s, job.settings.threads, on_phase, tick)


def run_cell(work: CellWork, on_phase: Phase, tick: Tick) -> CellResult:
    """Convert, then measure within what is left of the cell's time limit."""
    deadline = time.monotonic() + work.convert.settings.timeout_s
    converted, job = convert_cell(work, on_phase, tick)
    if job is None:
        return CellResult(work, error=f"convert: {converted.error}", env=environment.capture())
    artifact = str(job.artifact_dir / "model")
    measured = measure_cell(job, work.log, max(deadline - time.monotonic(), 1.0), on_phase, tick)
    if not measured.ok:
        return CellResult(work, error=f"measure: {measured.error}", artifact=artifact,
                          env=environment.capture())
    return CellResult(work, measured=measured.value, artifact=artifact, again=replace(job, closed_loop=None))


class LocalExecutor(Executor):
    """One cell at a time on this machine."""

    def __init__(self, workspace: Workspace):
        self.workspace = workspace
        self._ended: list[CellResult] = []

    def hosts(self) -> set[str]:
        return {environment.host_name()}

    def submit(self, work: CellWork, on_phase: Phase, tick: Tick) -> None:
        self._ended.append(run_cell(work, on_phase, tick))

    def results(self, wait: bool) -> Iterator[CellResult]:
        while self._ended:
            yield self._ended.pop(0)

    def measure_again(self, result: CellResult, on_phase: Phase, tick: Tick) -> Outcome:
        job = result.again
        assert job is not None
        return measure_cell(job, result.work.log, job.settings.timeout_s, on_phase, tick)
