"""The executor interface: the runner hands it cells ready to run (`CellWork`) and collects `CellResult`s as
each cell ends; the executor decides where each job's process runs."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.cell import CellPlan
from bench_matrix.jobs import ConvertJob, MeasureJob
from bench_matrix.launcher import Outcome
from bench_matrix.plan import Plan

Phase = Callable[[str], None]
Tick = Callable[[], None]


@dataclass(frozen=True)
class CellWork:
    """One cell ready to run: its conversion job and its measurement job (whose artifact the conversion
    fills in), with the cell's log and when the runner started it."""

    plan: CellPlan
    convert: ConvertJob
    measure: MeasureJob
    log: Path
    started: str


@dataclass
class CellResult:
    """How a cell ended: the measure job's value (metrics, samples, env), or the reason it failed."""

    work: CellWork
    measured: dict[str, Any] | None = None
    error: str | None = None
    artifact: str | None = None  # the artifact's model path, once converted
    again: MeasureJob | None = None  # the measurement job a later pass repeats
    env: dict[str, Any] | None = None  # where a failed cell ran (an ok one's env is measured["env"])
    placement: Any = None  # where the executor ran it, for later passes (a Ray node id; None locally)

    @property
    def ok(self) -> bool:
        return self.error is None


class Executor(ABC):
    """Runs cells' jobs, each in its own process, somewhere; the runner stores what comes back."""

    def decide(self, plan: Plan, cells: list[CellPlan]) -> list[CellPlan]:
        """The cells with their run/skip state as this executor's machines judge them (default: as
        planned)."""
        return cells

    @abstractmethod
    def hosts(self) -> set[str]:
        """The hosts whose stored records this executor's runs write (a cell done on one of them is done)."""

    @abstractmethod
    def submit(self, work: CellWork, on_phase: Phase, tick: Tick) -> None:
        """Start (or run) a cell; its result comes out of `results`."""

    @abstractmethod
    def results(self, wait: bool) -> Iterator[CellResult]:
        """Results of submitted cells as each ends: those ended so far, or (`wait`) every one still due."""

    @abstractmethod
    def measure_again(self, result: CellResult, on_phase: Phase, tick: Tick) -> Outcome:
        """Measure an ok cell once more, in a fresh process on the machine that holds its artifact."""

    def close(self) -> None:
        """Stop whatever still runs and let go of the machines."""
