"""The closed-loop section's margins, from stored records only: each cell's margins on each margin circuit
beside the baseline's and their ratio, how far apart the cells are, and a plot of every margin per cell."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.report.analysis.summary import ModelSummary
from bench_matrix.report.render.columns import DASH, METHOD, Column
from bench_matrix.report.render.plots import Plot
from bench_matrix.report.render.sections import Block
from bench_matrix.store import CellRecord
from bench_matrix.workload.driving.margins import OUTCOMES

TITLES = {"latency": "Latency margin ms", "speed": "Speed margin ×", "perception": "Perception margin"}
NOTES = {"latency": "the largest delay, in ms, each brain step may take (lock-step: exact) with the lap "
                    "still completed without leaving the road",
         "speed": "the largest factor on every commanded speed the lap survives",
         "perception": "the strongest camera perturbation the lap survives (0 to 1: its strength)"}
INTRO = ("Margins: how far each cell is from failing, each found by bisection on its own lock-step laps "
         "(docs/closed-loop.md, Margins): a–b: the largest value passed, a, and the next value of the "
         "search's grid, b, one resolution above, failed; ≥ the limit when it never failed; none when even "
         "the unchanged lap failed. × baseline: the cell's margin ÷ the fp32 baseline's on the same circuit.")
PLOT_INCHES = (4.0, 0.35)  # a panel's width, and the height per bar


@dataclass(frozen=True)
class MarginRow:
    """One cell's margins on one circuit, with the baseline's on the same circuit (None: none stored)."""

    record: CellRecord
    circuit: str
    margins: dict[str, dict[str, Any]]
    baseline: dict[str, dict[str, Any]] | None
    is_baseline: bool


def margin_rows(model: ModelSummary) -> list[MarginRow]:
    """Every ok cell's margins, in the results table's order, then circuit."""
    base = _searched(model.baseline) if model.baseline is not None and model.baseline.status == "ok" else {}
    return [MarginRow(row.record, circuit, margins, base.get(circuit), row.is_baseline)
            for row in model.rows for circuit, margins in _searched(row.record).items()]


def kinds(rows: list[MarginRow]) -> list[str]:
    """The margins searched for any row, in the order latency, speed, perception."""
    return [kind for kind in TITLES if any(kind in row.margins for row in rows)]


def shown(answer: dict[str, Any] | None) -> str:
    """A margin as the table shows it: passed–failed, ≥ the limit, or none."""
    if not isinstance(answer, dict) or answer.get("outcome") not in OUTCOMES:
        return DASH
    if answer["outcome"] == "fails_at_start":
        return "none"
    if answer["outcome"] == "passes_at_limit":
        return f"≥ {answer['value']:g}"
    return f"{answer['value']:g}–{answer['failed_at']:g}"


def ratio(answer: dict[str, Any] | None, base: dict[str, Any] | None) -> str:
    """The cell's margin ÷ the baseline's, ≥ or ≤ where one side is only a lower bound; — where unknown."""
    value, reference = _value(answer), _value(base)
    if value is None or reference is None or reference <= 0:
        return DASH
    above, below = _at_limit(answer), _at_limit(base)
    if above and below:
        return DASH
    return ("≥ " if above else "≤ " if below else "") + f"{value / reference:.2f}"


def spread_lines(rows: list[MarginRow]) -> list[str]:
    """Per circuit and margin, how far apart the cells are, or that the search could not tell them apart."""
    lines = []
    for circuit in dict.fromkeys(row.circuit for row in rows):
        for kind in kinds(rows):
            answers = [(row.record.cell.label, row.margins.get(kind)) for row in rows
                       if row.circuit == circuit]
            values = [(label, value) for label, a in answers if (value := _value(a)) is not None]
            if len(values) < 2:
                continue
            resolution = max(a.get("resolution", 0) for _, a in answers if isinstance(a, dict))
            low, high = min(v for _, v in values), max(v for _, v in values)
            lines.append(f"{circuit}, {kind}: every cell's margin is {low:g}: alike to within the search's "
                         f"resolution, {resolution:g}" if low == high else
                         f"{circuit}, {kind}: from {low:g} ({_holding(values, low)}) to {high:g} "
                         f"({_holding(values, high)}), resolution {resolution:g}")
    return lines


def _holding(values: list[tuple[str, float]], value: float) -> str:
    """The cells whose margin is `value`: their names, or how many when more than two."""
    names = [label for label, found in values if found == value]
    return " and ".join(names) if len(names) <= 2 else f"{len(names)} cells"


def columns(rows: list[MarginRow]) -> list[Column]:
    """The margins table's columns: the cell, the circuit, each margin searched and its ratio, the cost."""
    found = [METHOD, Column("Circuit", "the circuit searched on.", lambda row: row.circuit, "")]
    for kind in kinds(rows):
        found += [Column(TITLES[kind], NOTES[kind], lambda row, k=kind: shown(row.margins.get(k)), "margin"),
                  Column("× baseline", f"{kind} margin ÷ the baseline's", lambda row, k=kind: ratio(
                      row.margins.get(k), (row.baseline or {}).get(k)), "margin")]
    return [*found, Column("Laps", "laps the searches drove.", lambda row: str(_total(row, "laps")), "cost"),
            Column("Search s", "wall seconds of the searches.", lambda row: f"{_total(row, 'wall_s'):.0f}",
                   "cost")]


def blocks(model: ModelSummary) -> list[Block]:
    """The margins block with how far apart the cells are; none when no margin was searched."""
    rows = margin_rows(model)
    if not rows:
        return []
    lines = spread_lines(rows) + unsearched(model)
    return [Block("Closed-loop margins", INTRO, columns(rows), rows, lines, level=3)]


def unsearched(model: ModelSummary) -> list[str]:
    """A line naming the cells that drove laps but had no margin searched (the matrix left them out)."""
    names = [row.record.cell.label for row in model.rows
             if isinstance(row.record.metrics.others.get("closed_loop"), dict) and not _searched(row.record)]
    return [f"Not searched: {', '.join(names)} (they drove their laps; the matrix's closed_loop.margins "
            "cells and exclude left them out)"] if names else []


def margin_plots(model: ModelSummary, folder: Path) -> list[Plot]:
    """One plot of every margin per cell and circuit, the baseline's bars hatched; none without margins."""
    rows = margin_rows(model)
    if not rows:
        return []
    path = folder / f"margins-{model.name}.png"
    margin_figure(rows).savefig(path, dpi=80, metadata={"Software": None})
    return [Plot("margins", f"Closed-loop margins: {model.name}", path,
                 f"Each cell's closed-loop margins on each circuit, the baseline's hatched")]


def margin_figure(rows: list[MarginRow]) -> Any:
    """A panel per margin: a bar per cell and circuit to its margin, a whisker over the resolution (where
    the margin lies), ▶ past the limit, × where even the unchanged lap failed."""
    from matplotlib.figure import Figure

    shown_kinds = kinds(rows)
    figure = Figure(figsize=(PLOT_INCHES[0] * len(shown_kinds), 1.2 + PLOT_INCHES[1] * len(rows)))
    labels = [f"{row.record.cell.label} · {row.circuit}" for row in rows]
    for k, kind in enumerate(shown_kinds):
        axes = figure.add_subplot(1, len(shown_kinds), k + 1)
        for y, row in enumerate(rows):
            _bar(axes, y, row.margins.get(kind), row.is_baseline)
        axes.set_yticks(range(len(rows)), labels if k == 0 else [""] * len(rows), fontsize=7)
        axes.invert_yaxis()
        axes.set_title(TITLES[kind], fontsize=9)
    figure.tight_layout()
    return figure


def _bar(axes: Any, y: int, answer: dict[str, Any] | None, baseline: bool) -> None:
    value = _value(answer)
    if value is None:
        if isinstance(answer, dict) and answer.get("outcome") == "fails_at_start":
            axes.plot([answer.get("start", 0.0)], [y], "x", color="#d62728")
        return
    axes.barh(y, value, color="#7f7f7f" if baseline else "#1f77b4", hatch="//" if baseline else None,
              edgecolor="black", linewidth=0.4)
    if _at_limit(answer):
        axes.plot([value], [y], ">", color="black", markersize=5)
    else:
        axes.errorbar([value + answer["resolution"] / 2], [y], xerr=[answer["resolution"] / 2], fmt="none",
                      ecolor="black", capsize=2, linewidth=0.8)


def _searched(record: CellRecord) -> dict[str, dict[str, dict[str, Any]]]:
    found = record.metrics.others.get("closed_loop_margins")
    return {c: m for c, m in found.items() if isinstance(m, dict)} if isinstance(found, dict) else {}


def _value(answer: dict[str, Any] | None) -> float | None:
    value = answer.get("value") if isinstance(answer, dict) else None
    return float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None


def _at_limit(answer: dict[str, Any] | None) -> bool:
    return isinstance(answer, dict) and answer.get("outcome") == "passes_at_limit"


def _total(row: MarginRow, key: str) -> float:
    return sum(a.get(key, 0) for a in row.margins.values() if isinstance(a, dict))
