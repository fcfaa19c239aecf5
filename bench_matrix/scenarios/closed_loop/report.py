"""The closed-loop section of a report, from stored records only: the study's simulation table (one row per
cell, circuit and timing mode) beside offline columns, the cells that were not driven, trajectory plot names."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bench_matrix.measurement import Measurement
from bench_matrix.report.analysis.summary import ModelSummary, figure, number
from bench_matrix.report.render.columns import DASH, fixed, mib, sig
from bench_matrix.report.render.html_parts import esc, table
from bench_matrix.store import CellRecord

MODE_NAMES = {"lock_step": "lock-step", "real_time": "real-time"}
INTRO = ("Each cell's own artifact drove laps in the built-in simulator (docs/closed-loop.md defines every "
         "figure): lock-step waits for the model; real-time charges the world clock with the model's "
         "measured time, so a slow model acts late.")


@dataclass(frozen=True)
class Lap:
    """One stored lap: the cell, the circuit, the timing mode and the lap's metrics."""

    record: CellRecord
    circuit: str
    mode: str
    metrics: dict[str, Any]

    def value(self, *path: str) -> float | None:
        found: Any = self.metrics
        for key in path:
            found = found.get(key) if isinstance(found, dict) else None
        return number(found)


@dataclass(frozen=True)
class LapColumn:
    """One column of the simulation table: header, footnote, renderer, and whether the terminal shows it."""

    header: str
    note: str
    render: Callable[[Lap], str]
    numeric: bool = True
    terminal: bool = True


def _stop(lap: Lap) -> str:
    if "failed" in lap.metrics:
        return "failed: " + str(lap.metrics["failed"])
    return str(lap.metrics.get("stop_reason") or DASH).replace("_", " ")


def _offline(read: Callable[[Measurement], Any], render: Callable[[float | None], str]
             ) -> Callable[[Lap], str]:
    return lambda lap: render(figure(lap.record, read))


def _lap(*path: str, render: Callable[[float | None], str]) -> Callable[[Lap], str]:
    return lambda lap: render(lap.value(*path))


def _digits(n: int) -> Callable[[float | None], str]:
    return lambda value: sig(value, n)


def _decimals(n: int) -> Callable[[float | None], str]:
    return lambda value: fixed(value, n)


COLUMNS: tuple[LapColumn, ...] = (
    LapColumn("Method", "backend, strategy and precision of the cell that drove.",
              lambda lap: lap.record.cell.label, numeric=False),
    LapColumn("Circuit", "the circuit driven.", lambda lap: lap.circuit, numeric=False),
    LapColumn("Mode", "lock-step (the world waits for the model) or real-time (the world advances by the "
              "model's measured time).", lambda lap: MODE_NAMES.get(lap.mode, lap.mode), numeric=False),
    LapColumn("Completed %", "share of the reference lap's checkpoint gates crossed in order (never above "
              "100).", _lap("completed_pct", render=_decimals(1))),
    LapColumn("Lap s", "simulated seconds to cross the finish line; — when the lap was not completed.",
              _lap("lap_time_s", render=_decimals(2)), terminal=False),
    LapColumn("Avg speed m/s", "distance driven ÷ simulated time.",
              _lap("avg_speed_mps", render=_decimals(2))),
    LapColumn("Deviation MAE m", "mean distance, in metres, from the car to the reference line (the "
              "circuit's centreline) over every physics step.", _lap("deviation_mae_m", render=_digits(3))),
    LapColumn("Max dev m", "largest distance from the reference line, in metres.",
              _lap("deviation_max_m", render=_decimals(2)), terminal=False),
    LapColumn("Off road s", "simulated seconds with the car's centre beyond the road's edge.",
              _lap("off_road_s", render=_decimals(2)), terminal=False),
    LapColumn("Departures", "times the car left the road.", _lap("road_departures", render=_decimals(0))),
    LapColumn("Brain Hz", "brain steps achieved per simulated second (lock-step: the brain period's rate).",
              _lap("brain_hz", render=_decimals(1))),
    LapColumn("Inference ms", "mean wall time of one inference at batch 1 while driving, in milliseconds.",
              _lap("inference_ms", "mean", render=_digits(3))),
    LapColumn("Inference p99 ms", "99th percentile of that time.",
              _lap("inference_ms", "p99", render=_digits(3)), terminal=False),
    LapColumn("RTF", "real-time factor: simulated seconds ÷ wall seconds of the lap (above 1: faster than "
              "real time).", _lap("rtf", render=_decimals(2))),
    LapColumn("Suddenness", "mean L2 distance between consecutive normalised [v, w] commands.",
              _lap("suddenness", render=_digits(3)), terminal=False),
    LapColumn("Score", "driving score: completed % × 0.8 ^ road departures.",
              _lap("driving_score", render=_decimals(1))),
    LapColumn("Stop", "why the lap ended: lap completed, off road (too long in one go), stuck, time limit.",
              _stop, numeric=False),
    LapColumn("MSE", "offline: the cell's test MSE on the normalised labels.",
              _offline(lambda m: m.task.mse, render=_digits(4))),
    LapColumn("p50 ms", "offline: the cell's median latency at batch 1.",
              _offline(lambda m: m.latency and m.latency.p50, render=_digits(3))),
    LapColumn("Size MiB", "offline: the artifact's size on disk.",
              _offline(lambda m: m.size.bytes, render=mib),
              terminal=False),
)


def laps(model: ModelSummary) -> list[Lap]:
    """Every stored lap of the model's ok cells, in the results table's order, then circuit and mode."""
    found = []
    for row in model.rows:
        driven = row.record.metrics.others.get("closed_loop")
        for circuit, modes in (driven.items() if isinstance(driven, dict) else ()):
            found += [Lap(row.record, circuit, mode, lap) for mode, lap in modes.items()
                      if isinstance(lap, dict)]
    return found


def not_driven(model: ModelSummary) -> list[tuple[CellRecord, str]]:
    """Cells the closed_loop section selected whose model cannot drive, with the reason."""
    return [(row.record, str(row.record.metrics.others["closed_loop_skipped"])) for row in model.rows
            if "closed_loop_skipped" in row.record.metrics.others]


def driven_records(model: ModelSummary) -> list[CellRecord]:
    """The ok cells that drove at least one lap, in the results table's order."""
    return [row.record for row in model.rows
            if isinstance(row.record.metrics.others.get("closed_loop"), dict)]


def plot_name(record: CellRecord) -> str:
    """File name of a cell's trajectory plot, next to the Markdown pages."""
    return "trajectory-" + re.sub(r"[^A-Za-z0-9_.+-]", "_", record.cell.key.replace("/", "__")) + ".png"


def markdown_lines(model: ModelSummary, table: Callable[[list[str], list[bool], list[list[str]]], str],
                   escape: Callable[[str], str]) -> list[str]:
    """The model page's "Closed loop" section (empty when no cell was selected for it): the simulation table,
    its column notes and the cells not driven (the trajectory plots are in the page's Plots section)."""
    found, skipped = laps(model), not_driven(model)
    if not found and not skipped:
        return []
    lines = ["## Closed loop", "", escape(INTRO), ""]
    if found:
        lines += [table([escape(c.header) for c in COLUMNS], [c.numeric for c in COLUMNS],
                        [[escape(c.render(lap)) for c in COLUMNS] for lap in found]),
                  "", "Columns:", "", *(f"- **{escape(c.header)}**: {escape(c.note)}" for c in COLUMNS), ""]
    lines += [f"- not driven: {escape(record.cell.label)}: {escape(reason)}" for record, reason in skipped]
    lines += [""] if skipped else []
    return lines


def html_parts(model: ModelSummary) -> list[str]:
    """The HTML page's section: the simulation table (every column) and the cells that could not drive."""
    found, skipped = laps(model), not_driven(model)
    if not found and not skipped:
        return []
    parts = ["<h3>Closed loop</h3>", f"<p>{esc(INTRO)}</p>"]
    if found:
        parts.append(table([(c.header, c.note) for c in COLUMNS], [c.numeric for c in COLUMNS],
                           [[c.render(lap) for c in COLUMNS] for lap in found]))
    parts += [f"<p>not driven: {esc(record.cell.label)}: {esc(reason)}</p>" for record, reason in skipped]
    return parts


def print_terminal(model: ModelSummary, console: Any) -> None:
    """Print the simulation table (the terminal's columns) and the cells not driven, if any."""
    found, skipped = laps(model), not_driven(model)
    if found:
        from rich.table import Table

        table = Table(title=f"{model.name}: closed loop", title_justify="left")
        shown = [c for c in COLUMNS if c.terminal]
        for column in shown:
            widest = max(len(column.render(lap)) for lap in found)
            table.add_column(column.header, justify="right" if column.numeric else "left", min_width=widest)
        for lap in found:
            table.add_row(*(column.render(lap) for column in shown))
        console.print(table)
    for record, reason in skipped:
        console.print(f"not driven: {record.cell.label}: {reason}", style="yellow", highlight=False,
                      markup=False)
