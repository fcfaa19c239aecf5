"""The executor interface: the runner submits `Work` (a job, its limits and maybe the machine it must run on)
and takes an `Ended` back as each piece ends; it runs each job on a machine able to (placement.py decides)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.cell import CellPlan
from bench_matrix.jobs import Job

if TYPE_CHECKING:
    from bench_matrix.matrix.spec import Matrix
    from bench_matrix.placement import Probed

Phase = Callable[[str], None]
Tick = Callable[[], None]


@dataclass(frozen=True)
class Limits:
    """How a job's process runs: the log it writes to, its time limit and its threads (None: all cores)."""

    log: Path
    timeout_s: float
    threads: int | None = None


@dataclass(frozen=True, eq=False)
class Work:
    """A job to run, how, and where: `on` an earlier Ended's `where` (the machine holding its files), or
    any."""

    job: Job
    limits: Limits
    on: Any = None


@dataclass(frozen=True)
class Ended:
    """How work ended: the jobs that ran and the typed result of each that succeeded; when the last one
    failed, why, whether that is the user's to fix, and the environment it failed in; where the work ran."""

    work: Work
    jobs: tuple[Job, ...]
    results: tuple[Any, ...]
    error: str | None = None
    user_error: bool = False
    env: dict[str, Any] | None = None
    where: Any = None

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def result(self) -> Any:
        """The last job's result."""
        return self.results[-1]


class Executor(ABC):
    """Runs jobs, each in its own process, somewhere; the runner stores what comes back."""

    def probes(self, matrix: Matrix, cells: list[CellPlan]) -> dict[str, Probed]:
        """What the probe job found on each of its machines (none: only this one, which the plan probed)."""
        return {}

    def place(self, able: dict[str, list[str]]) -> None:
        """Take the machines able to run each cell (by key; placement.py): its jobs run on one of them."""
        self.able = able

    @abstractmethod
    def hosts(self) -> set[str]:
        """The hosts whose stored records this executor's runs write (a cell done on one of them is done)."""

    @abstractmethod
    def submit(self, work: Work, on_phase: Phase, tick: Tick) -> None:
        """Start (or run) a piece of work; how it ended comes out of `ended`."""

    @abstractmethod
    def ended(self, wait: bool) -> Iterator[Ended]:
        """Work as each piece ends: what has ended so far, or (`wait`) every piece still due."""

    def lost(self) -> dict[str, str]:
        """The machines that could not run the work given them (its cells failed), each with why."""
        return {}

    def close(self) -> None:
        """Stop whatever still runs and let go of the machines."""
