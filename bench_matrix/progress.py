"""Progress while a matrix runs: cells done of total, current cell and phase, elapsed, estimate; outside a
terminal (a CI log), one line per step and phase instead, with the time since the run began."""

from __future__ import annotations

import re
import time

from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)

from bench_matrix.cell import Cell
from bench_matrix.measurement import Interference, Measurement, TaskMetrics
from bench_matrix.store import CellRecord


LATER_ROUND = re.compile(r"round (?!1$)\d+$")  # a log gets "round 1" of a model's rounds, not each one


class RunProgress:
    """A progress bar redrawn only on events and idle ticks, never while a cell measures; lines in a log."""

    def __init__(self, console: Console, total: int):
        self.console, self._plain, self._begin = console, not console.is_terminal, time.monotonic()
        self._progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                  TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                                  console=console, auto_refresh=False, transient=True)
        self._task = self._progress.add_task("starting", total=max(total, 1))
        self._current = ""

    def __enter__(self) -> "RunProgress":
        self._progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._progress.stop()

    def step(self, text: str) -> None:
        """A preparation step (dataset, training) or a cell began."""
        self._current = text
        self._progress.update(self._task, description=text)
        self._progress.refresh()
        self._line(text)

    @property
    def current(self) -> str:
        """The step begun last."""
        return self._current

    def phase(self, name: str, step: str | None = None) -> None:
        """A phase of `step` (by default the current one: a job running elsewhere reports after later steps
        began) began, or its job waits for the timing lock (naming the holder)."""
        under = self._current if step is None else step
        self._progress.update(self._task, description=f"{under} · {escape(name)}")
        self._progress.refresh()
        if not LATER_ROUND.match(name):
            self._line(f"{under} · {name}")

    def _line(self, text: str) -> None:
        """Outside a terminal, where the bar is not drawn: the line, after the seconds since the start."""
        if self._plain:
            self.console.print(f"[{time.monotonic() - self._begin:7.1f} s] {text}", markup=False,
                               highlight=False, soft_wrap=True)

    def tick(self) -> None:
        self._progress.refresh()

    def finished(self, record: CellRecord) -> None:
        """Print the finished cell's key figures above the bar."""
        self._progress.console.print(describe(record))
        self._progress.advance(self._task)
        self._progress.refresh()

    def already_stored(self, cell: Cell) -> None:
        """A cell another run stored while this one prepared it: said above the bar, and counted done."""
        self._progress.console.print(f"[dim]=[/] {escape(f'{cell.model} · {cell.label}')}: already stored "
                                     f"(measured by another run meanwhile)")
        self._progress.advance(self._task)
        self._progress.refresh()

    def skipped(self, records: list[CellRecord]) -> None:
        """One line per distinct reason, naming the backends and targets it concerns."""
        groups: dict[str, list[Cell]] = {}
        for record in records:
            groups.setdefault(record.reason or "", []).append(record.cell)
        for reason, cells in groups.items():
            backends = ", ".join(dict.fromkeys(c.backend for c in cells))
            targets = ", ".join(dict.fromkeys(c.target for c in cells))
            self._progress.console.print(f"[yellow]–[/] skipped {len(cells)} cell(s) of {escape(backends)} "
                                         f"on {escape(targets)}: {escape(reason)}")
        self._progress.refresh()


def _accuracy(task: TaskMetrics) -> str:
    """The task's headline accuracy figure: MSE, top-1, or the cosine similarity to the baseline."""
    if task.mse is not None:
        return f"MSE {task.mse:.4g}"
    if task.top1 is not None:
        return f"top-1 {task.top1:.1%}"
    return "" if task.cosine is None else f"cosine {task.cosine:.6f}"


def _disturbed(interference: Interference | None) -> str:
    """A mark for a cell whose timing stayed disturbed by other work after its re-measurements."""
    if not (interference and interference.flagged):  # none in records stored before it was measured
        return ""
    reason = interference.reason
    return f"  [yellow]~ disturbed{f': {escape(reason)}' if reason else ''}[/]"


def _within(metrics: Measurement) -> str:
    """The p50 interval's larger side, relative: ' ±1.2 %'."""
    latency = metrics.latency
    interval = latency.p50_ci if latency is not None else None
    if not interval or not latency.p50:
        return ""
    return f" ±{max(interval[1] - latency.p50, latency.p50 - interval[0]) / latency.p50:.1%}"


def _speedup(metrics: Measurement) -> str:
    """The paired speed-up against the baseline with its interval: '  3.1× ±2.0 %'."""
    found = metrics.speedup
    if found is None or found.value is None:
        return ""
    if found.ci_half is None:
        return f"  {found.value:.3g}×"
    return f"  {found.value:.3g}× ±{found.ci_half:.1%}"


def _calibration(metrics: Measurement) -> str:
    """A warning for a cell calibrated on fewer samples than its strategy asked for."""
    calibration = metrics.others.get("calibration") or {}
    if calibration.get("used", 0) >= calibration.get("asked", 0):
        return ""
    return (f"  [yellow]! calibrated on {calibration['used']} of the {calibration['asked']} samples asked for: "
            f"the calibration split has no more (enlarge dataset.split.calibration)[/]")


def describe(record: CellRecord) -> str:
    """One line: status mark, cell, and its headline numbers or reason."""
    cell: Cell = record.cell
    name = f"{cell.model} · {cell.label}"
    if record.status == "ok":
        m = record.metrics
        return (f"[green]✓[/] {name}  p50 {m.latency.p50:.3g} ms{_within(m)}  p99 {m.latency.p99:.3g} ms"
                f"  {m.throughput.sps:.0f} samples/s{_speedup(m)}  {_accuracy(m.task)}"
                f"  {m.size.bytes / 2**20:.2f} MiB{_disturbed(m.interference)}{_calibration(m)}")
    lines = (record.reason or "").strip().splitlines()
    mark = "[yellow]–[/] skipped" if record.status == "skipped" else "[red]✗[/] failed"
    return f"{mark} {escape(name)}: {escape(lines[0] if lines else '')}"
