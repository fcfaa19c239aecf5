"""Trajectory plots of the closed-loop laps, from stored records only: per driven cell one PNG with a panel
per circuit showing the road, the reference line and the path driven in each timing mode."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.report.analysis.summary import ModelSummary
from bench_matrix.report.render.plots import Plot
from bench_matrix.report.render.sections import Section
from bench_matrix.scenarios.closed_loop import margin_report as margins
from bench_matrix.scenarios.closed_loop.report import MODE_NAMES, blocks, driven_records, plot_name
from bench_matrix.store import CellRecord

PANEL_INCHES = 4.0
DPI = 80
COLOURS = {"lock_step": "#1f77b4", "real_time": "#d62728"}
ROAD, REFERENCE = "#c8c8c8", "#555555"


def trajectory_plots(model: ModelSummary, folder: Path) -> list[Plot]:
    """One plot per driven cell of the model, in the results table's order."""
    return [Plot("trajectory", f"Closed-loop trajectories: {r.cell.label}", write_cell_plot(r, folder),
                 f"Driven paths of {r.cell.label} over the reference line") for r in driven_records(model)]


def write_cell_plot(record: CellRecord, folder: Path) -> Path:
    """Write one driven cell's plot into `folder` under its `plot_name`; return its path."""
    path = folder / plot_name(record)
    cell_figure(record).savefig(path, dpi=DPI, metadata={"Software": None})
    return path


def cell_figure(record: CellRecord) -> Any:
    """The figure of one cell: a panel per circuit it drove."""
    from matplotlib.figure import Figure

    laps = record.metrics.others["closed_loop"]
    circuits = record.metrics.others.get("closed_loop_circuits") or {}
    columns = min(len(laps), 3)
    rows = -(-len(laps) // columns)
    figure = Figure(figsize=(PANEL_INCHES * columns, PANEL_INCHES * rows + 0.4))
    figure.suptitle(record.cell.key, fontsize=9)
    for k, (name, modes) in enumerate(laps.items()):
        axes = figure.add_subplot(rows, columns, k + 1)
        _panel(axes, name, circuits.get(name) or {}, modes)
    figure.tight_layout()
    return figure


def _panel(axes: Any, name: str, circuit: dict[str, Any], modes: dict[str, Any]) -> None:
    reference = circuit.get("reference") or {}
    if reference.get("x"):
        x, y = np.asarray(reference["x"]), np.asarray(reference["y"])
        _road(axes, x, y, float(circuit.get("lane_width_m") or 0.0) / 2)
        axes.plot(np.append(x, x[0]), np.append(y, y[0]), "--", color=REFERENCE, linewidth=0.8,
                  label="reference line")
        axes.plot(x[:1], y[:1], "o", color="black", markersize=4)
    done = []
    for mode, lap in modes.items():
        path = lap.get("trajectory") or {}
        if not path.get("x"):
            continue
        colour = COLOURS.get(mode, "black")
        axes.plot(path["x"], path["y"], color=colour, linewidth=1.2, label=MODE_NAMES.get(mode, mode))
        axes.plot(path["x"][-1:], path["y"][-1:], "x", color=colour, markersize=7)
        done.append(f"{MODE_NAMES.get(mode, mode)} {lap.get('completed_pct', 0):.0f} %")
    axes.set_title(f"{name}: " + ", ".join(done), fontsize=8)
    axes.set_aspect("equal")
    axes.set_axis_off()
    axes.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, frameon=False)


def _road(axes: Any, x: np.ndarray, y: np.ndarray, half_width: float) -> None:
    """The road as a grey ring between the centreline's offsets half a road width either side."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as Outline

    tx, ty = np.roll(x, -1) - np.roll(x, 1), np.roll(y, -1) - np.roll(y, 1)
    norm = np.hypot(tx, ty)
    nx, ny = -ty / norm * half_width, tx / norm * half_width
    left = np.stack([x + nx, y + ny], 1)
    right = np.stack([x - nx, y - ny], 1)[::-1]
    vertices = np.concatenate([left, left[:1], right, right[:1]])
    codes = ([Outline.MOVETO] + [Outline.LINETO] * (len(x) - 1) + [Outline.CLOSEPOLY]) * 2
    axes.add_patch(PathPatch(Outline(vertices, codes), facecolor=ROAD, edgecolor="none"))


SECTION = Section(lambda model: blocks(model) + margins.blocks(model),
                  lambda model, folder: trajectory_plots(model, folder) + margins.margin_plots(model, folder))
