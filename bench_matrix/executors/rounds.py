"""A rounds job on this machine (docs/metrics.md §5): each cell's session loaded in `settings.processes`
processes of its own and evaluated in its first, the sessions timed in interleaved rounds under the machine's
timing lock (the scheduler owns the clock) for as long as the answers need, then each cell finished in its
first; the timed figures come from the rounds."""

from __future__ import annotations

import random
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from pathlib import Path
from typing import Any

from bench_matrix.executors.answers import OpenAnswers
from bench_matrix.executors.sessions import SessionProcess
from bench_matrix.jobs import RoundsJob
from bench_matrix.jobs.results import CellEnded, Measured, MeasuredGroup
from bench_matrix.measure import env as environment
from bench_matrix.measure.interference import LIMITS
from bench_matrix.measure.machine_lock import TimingWindow, timing_slot
from bench_matrix.measure.rounds import Spread
from bench_matrix.measure.schedule import (LATENCY, LOOSE, Rounds, RoundsSettings, SessionLost, Timed,
                                           measure_groups, spread)
from bench_matrix.measurement import Measurement
from bench_matrix.scenarios.timed import SAMPLED, THROUGHPUT, figures, raw_samples

DISTURBED_SHARE = 0.25  # more of a kind's windows disturbed than this marks the cell
EVERY = 0.02  # every cell's target where no requirements say what is open (compare --remeasure)


def rounds_settings(job: RoundsJob) -> RoundsSettings:
    """The scheduler's settings from the matrix's: the model's budget is its cells' share each; the target
    the user's `ci_target`, else the loose one where answers decide which cells keep the budget."""
    settings = job.cells[0].settings
    default = LOOSE if job.requirements is not None else EVERY
    return RoundsSettings(min_rounds=settings.min_rounds, budget_s=settings.timing_budget_s * len(job.cells),
                          target=settings.ci_target or default, disturbed_share=DISTURBED_SHARE,
                          window_s=settings.window_s, asked=settings.ci_target is not None)


def measure_in_rounds(job: RoundsJob, workdir: Path, logs: Path, on_phase: Callable[[str], None]
                      ) -> MeasuredGroup:
    """Open, time in rounds and finish the job's cells (sessions' logs under `logs`); each cell's result."""
    sessions = _Sessions(job, workdir, logs, on_phase, hold=lambda: _slot(job, [], on_phase))
    windows: list[TimingWindow] = []
    settings = rounds_settings(job)
    answers = OpenAnswers.of(job, settings, sessions.evaluated) if job.requirements is not None else None
    rounds = Rounds(settings, random.Random(), hold=lambda: _slot(job, windows, on_phase),
                    on_round=lambda n: on_phase(f"round {n + 1}"), references=dict(job.references),
                    answers=answers)
    memory_mb = job.cells[0].settings.memory_share * environment.available_memory_mb()
    try:
        timed = measure_groups(list(sessions.jobs), job.baseline, sessions.open, sessions.close, memory_mb,
                               rounds)
    except BaseException:  # Ctrl-C or any error here: never leave a session measuring
        sessions.kill()
        raise
    against = {key: timed.get(reference) for key, reference in job.references}
    base = timed.get(job.baseline) if job.baseline else None
    window = {"waited_s": round(sum(w.waited_s for w in windows), 3), "rounds": rounds.number,
              "rounds_s": round(sum((w.end or w.start) - w.start for w in windows), 3),
              "held": [[w.start, w.end] for w in windows]}
    spreads = {kind: spread(timed.values(), kind, rate=kind == THROUGHPUT) for kind in SAMPLED}
    return MeasuredGroup(tuple(_result(key, timed[key], against.get(key, base), sessions, settings,
                                       window, spreads)
                               for key in sessions.jobs))


class _Sessions:
    """The job's sessions: a cell's processes start together when the scheduler asks, the cell evaluated in
    the first; after its rounds it finishes there (scenarios run, under `hold` if one is timed), all close."""

    def __init__(self, job: RoundsJob, workdir: Path, logs: Path, on_phase: Callable[[str], None],
                 hold: Callable[[], AbstractContextManager]):
        self.jobs = {cell.id: cell for cell in job.cells}
        self.hold = hold
        self.logs = {cell.id: logs / name for cell, name in zip(job.cells, job.logs)}
        self.workdir, self.on_phase = workdir, on_phase
        self.processes = job.cells[0].settings.processes
        self.opened: dict[str, list[SessionProcess]] = {}
        self.finished: dict[str, Measured | SessionLost] = {}
        self.evaluated: dict[str, dict[str, Any]] = {}  # each cell's fields measured before its rounds

    def open(self, key: str) -> list[SessionProcess]:
        job = self.jobs[key]
        self.on_phase(f"loading {job.cell.label}" + (f" ({job.side})" if job.side else "")
                      + (f" in {self.processes} processes" if self.processes > 1 else ""))
        cell = self.opened.setdefault(key, [])  # each one kept as it starts: Ctrl-C meanwhile kills it too
        try:
            for j in range(self.processes):
                log = _log(self.logs[key], j)
                cell.append(SessionProcess(job, self.workdir, log, job.settings.timeout_s))
            for session in cell:
                session.ready()
            self.on_phase(f"evaluating {job.cell.label}")
            self.evaluated[key] = cell[0].evaluate()
        except SessionLost:
            for session in cell:
                session.kill()
            raise
        return cell

    def close(self, key: str, cell: list[SessionProcess]) -> None:
        """Finish the cell in its first process, then end them all."""
        job = self.jobs[key]
        self.on_phase(f"finishing {job.cell.label}")
        timed = any(planned.timed() for planned in job.scenarios)
        try:
            with self.hold() if timed else nullcontext():
                self.finished[key] = cell[0].finish()
        except SessionLost as lost:
            self.finished[key] = lost
        finally:
            for session in cell:
                session.close()

    def user_error(self, key: str) -> bool:
        return any(session.user_error for session in self.opened.get(key, ()))

    def kill(self) -> None:
        for cell in self.opened.values():
            for session in cell:
                session.kill()


def _log(path: Path, process: int) -> Path:
    """The log of a cell's `process` (0-based): the cell's own log for the first, `NAME.2.log` and so on."""
    return path if process == 0 else path.with_name(f"{path.stem}.{process + 1}{path.suffix}")


@contextmanager
def _slot(job: RoundsJob, windows: list[TimingWindow], on_phase: Callable[[str], None]) -> Iterator[None]:
    """The machine's timing slot for one group's rounds, its window kept for the records."""
    cell = job.cells[0]
    holder = f"{cell.workspace.root} · {cell.cell.model} · {len(job.cells)} cells in rounds"
    with timing_slot(holder, on_wait=lambda message: on_phase(f"waiting: {message}")) as window:
        windows.append(window)
        yield


def _result(key: str, timed: Timed, base: Timed | None, sessions: _Sessions, settings: RoundsSettings,
            window: dict, spreads: dict[str, Spread | None]) -> CellEnded:
    """The cell's measurement: its timed figures first, then what its session measured; or why it failed."""
    done, user_error = sessions.finished.get(key), sessions.user_error(key)
    if timed.failed or isinstance(done, SessionLost) or done is None:
        return CellEnded(key, error=timed.failed or str(done or "not measured"), user_error=user_error)
    if not timed.series(LATENCY):
        return CellEnded(key, error="no window was timed (its rounds stopped first)")
    fields = {**figures(timed, base, settings, LIMITS, spreads), "timing_window": window,
              **done.metrics.to_json()}
    return CellEnded(key, Measured(Measurement.from_json(fields), {**raw_samples(timed), **done.samples},
                                      done.env))
