"""The closed-loop section of a report, from stored records only: the study's simulation table (one row per
cell, circuit and timing mode) beside offline columns, the cells that were not driven, trajectory plot names."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bench_matrix.measurement import Measurement
from bench_matrix.report.analysis.summary import ModelSummary, figure, number
from bench_matrix.report.render.columns import DASH, Column, fixed, mib, sig
from bench_matrix.report.render.sections import Block
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


def _stop(lap: Lap) -> str:
    if "failed" in lap.metrics:
        return "failed: " + str(lap.metrics["failed"])
    return str(lap.metrics.get("stop_reason") or DASH).replace("_", " ")


def _offline(header: str, note: str, read: Callable[[Measurement], Any],
             render: Callable[[float | None], str]) -> Column:
    """A column of the cell's offline figure `read`."""
    return Column(header, note, lambda lap: render(figure(lap.record, read)), "offline")


def _lap(header: str, note: str, *path: str, render: Callable[[float | None], str]) -> Column:
    """A column of the lap's figure at `path`."""
    return Column(header, note, lambda lap: render(lap.value(*path)), "lap")


def _digits(n: int) -> Callable[[float | None], str]:
    return lambda value: sig(value, n)


def _decimals(n: int) -> Callable[[float | None], str]:
    return lambda value: fixed(value, n)


COLUMNS: tuple[Column, ...] = (
    Column("Method", "backend, strategy and precision of the cell that drove.",
           lambda lap: lap.record.cell.label, ""),
    Column("Circuit", "the circuit driven.", lambda lap: lap.circuit, ""),
    Column("Mode", "lock-step (the world waits for the model) or real-time (the world advances by the "
           "model's measured time).", lambda lap: MODE_NAMES.get(lap.mode, lap.mode), ""),
    _lap("Completed %", "share of the reference lap's checkpoint gates crossed in order (never above 100).",
         "completed_pct", render=_decimals(1)),
    _lap("Lap s", "simulated seconds to cross the finish line; — when the lap was not completed.",
         "lap_time_s", render=_decimals(2)),
    _lap("Avg speed m/s", "distance driven ÷ simulated time.", "avg_speed_mps", render=_decimals(2)),
    _lap("Deviation MAE m", "mean distance, in metres, from the car to the reference line (the circuit's "
         "centreline) over every physics step.", "deviation_mae_m", render=_digits(3)),
    _lap("Max dev m", "largest distance from the reference line, in metres.", "deviation_max_m",
         render=_decimals(2)),
    _lap("Off road s", "simulated seconds with the car's centre beyond the road's edge.", "off_road_s",
         render=_decimals(2)),
    _lap("Departures", "times the car left the road.", "road_departures", render=_decimals(0)),
    _lap("Brain Hz", "brain steps achieved per simulated second (lock-step: the brain period's rate).",
         "brain_hz", render=_decimals(1)),
    _lap("Inference ms", "mean wall time of one inference at batch 1 while driving, in milliseconds.",
         "inference_ms", "mean", render=_digits(3)),
    _lap("Inference p99 ms", "99th percentile of that time.", "inference_ms", "p99", render=_digits(3)),
    _lap("RTF", "real-time factor: simulated seconds ÷ wall seconds of the lap (above 1: faster than real "
         "time).", "rtf", render=_decimals(2)),
    _lap("Suddenness", "mean L2 distance between consecutive normalised [v, w] commands.", "suddenness",
         render=_digits(3)),
    _lap("Score", "driving score: completed % × 0.8 ^ road departures.", "driving_score",
         render=_decimals(1)),
    Column("Stop", "why the lap ended: lap completed, off road (too long in one go), stuck, time limit.",
           _stop, ""),
    _offline("MSE", "offline: the cell's test MSE on the normalised labels.", lambda m: m.task.mse,
             _digits(4)),
    _offline("p50 ms", "offline: the cell's median latency at batch 1.",
             lambda m: m.latency and m.latency.p50, _digits(3)),
    _offline("Size MiB", "offline: the artifact's size on disk.", lambda m: m.size.bytes, mib),
)
TERMINAL_LEFT_OUT = ("Lap s", "Max dev m", "Off road s", "Inference p99 ms", "Suddenness", "Size MiB")


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


def blocks(model: ModelSummary) -> list[Block]:
    """The model's "Closed loop" block (none when no cell was selected for it): the simulation table and the
    cells not driven (the trajectory plots are in the page's Plots section)."""
    found, skipped = laps(model), not_driven(model)
    brief = [c for c in COLUMNS if c.header not in TERMINAL_LEFT_OUT]
    lines = [f"not driven: {record.cell.label}: {reason}" for record, reason in skipped]
    return [Block("Closed loop", INTRO, COLUMNS, found, lines, brief=brief)] if found or skipped else []
