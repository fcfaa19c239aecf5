"""The renderings of a `compare` result: rich tables for the terminal, Markdown and JSON; every one names the
test, its alpha and the thresholds, and ends with the count of cells per verdict."""

from __future__ import annotations

import html
import math
import re
from collections.abc import Callable, Iterator
from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from bench_matrix.report.analysis.compare import METRICS, CellComparison, Comparison
from bench_matrix.report.analysis.metric_change import BETTER, NOT_COMPARABLE, WORSE, MetricChange
from bench_matrix.report.render.columns import DASH, mib, sig, times

DISTURBED_MARK = " ~"  # after the verdict of a cell flagged for interference on a side
_STYLES = {BETTER: "green", WORSE: "bold red", NOT_COMPARABLE: "yellow"}
_HEADERS = {"p50": "p50 ms", "p99": "p99 ms", "throughput": "Throughput /s", "size": "Size MiB"}
_FORMATS: dict[str, Callable[[float | None], str]] = {
    "p50": lambda v: sig(v, 3), "p99": lambda v: sig(v, 3), "throughput": lambda v: sig(v, 4),
    "size": mib, "accuracy": lambda v: sig(v, 4)}


def summary_line(comparison: Comparison) -> str:
    """"2 better, 1 worse, 5 unchanged, 0 not comparable" (cells)."""
    counts = comparison.counts()
    return ", ".join(f"{counts[v]} {v}" for v in (BETTER, WORSE, "unchanged", NOT_COMPARABLE))


def method_line(comparison: Comparison) -> str:
    """How the verdicts were reached: the test, alpha and every threshold."""
    limits = comparison.thresholds
    return (f"Timed metrics: {comparison.test}, on the raw samples; a change counts when p < "
            f"{comparison.alpha:g} and it is beyond its threshold; p50 on the speed-up paired by round "
            f"where both sides have one (×: its 95 % intervals apart)" + _remeasured(comparison) + ". Size "
            f"and accuracy: threshold only. "
            f"Thresholds: p50 {_percent(limits['p50'])}, p99 {_percent(limits['p99'])}, throughput "
            f"{_percent(limits['throughput'])}, size {_percent(limits['size'])}, accuracy "
            f"{_percent(limits['accuracy_relative'])} relative for error metrics (mse), "
            f"{limits['accuracy_absolute']:g} absolute for fractions (top1, cosine_similarity).")


def _remeasured(comparison: Comparison) -> str:
    if not comparison.remeasured:
        return ""
    return ("; remeasured: both sides' artifacts timed again on this machine in the same interleaved rounds, "
            "p50 judged on the new time ÷ the base time paired by round (its 95 % interval excludes 1, "
            f"beyond {_percent(comparison.thresholds['p50_remeasured'])})")


def title_line(comparison: Comparison) -> str:
    return f"Comparing {comparison.base} (base) → {comparison.new} (new)"


def change_text(change: MetricChange) -> str:
    """"1.20 → 1.50 (+25.0 %)"; "(n/c)" instead of the change when it is not comparable."""
    # p50 judged on the speed-up
    render = times if change.name == "speedup.value" else _FORMATS[change.metric]
    shown = f"{render(change.base)} → {render(change.new)}"
    if change.verdict == NOT_COMPARABLE:
        return f"{shown} (n/c)"
    return f"{shown} ({_change(change)})"


def notes(cell: CellComparison) -> list[str]:
    """Why the cell or its metrics are not comparable, and which side was disturbed (~)."""
    found = [cell.why] if cell.why else [f"{m.metric}: {m.why}" for m in cell.metrics if m.why]
    return found + [f"disturbed (~) in {line}" for line in cell.disturbed]


def by_model(comparison: Comparison) -> Iterator[tuple[str, list[CellComparison]]]:
    """The cells grouped by model, in the comparison's order."""
    groups: dict[str, list[CellComparison]] = {}
    for cell in comparison.cells:
        groups.setdefault(cell.model, []).append(cell)
    yield from groups.items()


def headers(cells: list[CellComparison]) -> list[str]:
    """Cell, the five metrics (accuracy named after the model's metric) and the verdict."""
    names = sorted({m.name for c in cells for m in c.metrics if m.metric == "accuracy"})
    accuracy = f"Accuracy ({', '.join(names)})" if names else "Accuracy"
    return ["Cell", *(_HEADERS.get(m, accuracy) for m in METRICS), "Verdict"]


def print_comparison(comparison: Comparison, console: Console) -> None:
    """Print the title, one table per model with its notes, the method and the summary."""
    console.print(Text(title_line(comparison), style="bold"))
    for model, cells in by_model(comparison):
        table = Table(title=model, title_justify="left")
        for header in headers(cells):
            table.add_column(header, justify="left" if header in ("Cell", "Verdict") else "right")
        for cell in cells:
            table.add_row(cell.label, *(_styled(cell, m) for m in METRICS),
                          Text(_verdict(cell), style=_STYLES.get(cell.verdict, "")))
        console.print(table)
        for cell in cells:
            for note in notes(cell):
                console.print(Text(f"{cell.label}: {note}", style="yellow"))
    console.print(Text(method_line(comparison), style="dim"))
    console.print(Text(summary_line(comparison), style="bold red" if comparison.regressions else "bold"))


def _styled(cell: CellComparison, metric: str) -> Text:
    change = _metric(cell, metric)
    return Text(DASH) if change is None else Text(change_text(change), style=_STYLES.get(change.verdict, ""))


def comparison_markdown(comparison: Comparison) -> str:
    """Markdown: a table per model (worse bold, better italic) with its notes, then the method and summary."""
    lines = [f"## {_escape(title_line(comparison))}"]
    for model, cells in by_model(comparison):
        lines += ["", f"### {_escape(model)}", "", *_markdown_table(cells)]
        cell_notes = [f"- {_escape(cell.label)}: {_escape(note)}" for cell in cells for note in notes(cell)]
        lines += ["", *cell_notes] if cell_notes else []
    lines += ["", method_line(comparison), "", f"**{summary_line(comparison)}**"]  # our own text: no escaping
    return "\n".join(lines) + "\n"


def _markdown_table(cells: list[CellComparison]) -> list[str]:
    names = headers(cells)
    rows = [[_escape(cell.label), *(_marked(cell, m) for m in METRICS),
             _emphasis(_verdict(cell), cell.verdict)] for cell in cells]
    align = [":---" if name in ("Cell", "Verdict") else "---:" for name in names]
    return ["| " + " | ".join(row) + " |" for row in [[_escape(n) for n in names], align, *rows]]


def _marked(cell: CellComparison, metric: str) -> str:
    change = _metric(cell, metric)
    return DASH if change is None else _emphasis(_escape(change_text(change)), change.verdict)


def _emphasis(text: str, verdict: str) -> str:
    return f"**{text}**" if verdict == WORSE else f"_{text}_" if verdict == BETTER else text


def comparison_json(comparison: Comparison) -> dict[str, Any]:
    """Every number, verdict and p-value, the thresholds, alpha and test; non-finite numbers become null."""
    return {"base": comparison.base, "new": comparison.new, "test": comparison.test,
            "alpha": comparison.alpha, "remeasured": comparison.remeasured,
            "thresholds": {k: _finite(v) for k, v in comparison.thresholds.items()},
            "summary": comparison.counts(),
            "regressions": [{"cell": key, "metric": metric} for key, metric in comparison.regressions],
            "cells": [_cell_json(cell) for cell in comparison.cells]}


def _cell_json(cell: CellComparison) -> dict[str, Any]:
    return {"key": cell.key, "model": cell.model, "label": cell.label, "verdict": cell.verdict,
            "why": cell.why,
            "disturbed": list(cell.disturbed),
            "metrics": {m.metric: {"name": m.name, "base": _finite(m.base), "new": _finite(m.new),
                                   "change": _finite(m.change), "change_kind": _kind(m),
                                   "threshold": _finite(m.threshold), "verdict": m.verdict,
                                   "p_value": _finite(m.p_value), "why": m.why}
                        for m in cell.metrics}}


def _metric(cell: CellComparison, metric: str) -> MetricChange | None:
    return next((m for m in cell.metrics if m.metric == metric), None)


def _verdict(cell: CellComparison) -> str:
    return cell.verdict + (DISTURBED_MARK if cell.disturbed else "")


def _change(change: MetricChange) -> str:
    if change.change is None:
        return DASH
    if change.relative:
        return f"{change.change * 100:+.1f} %"
    return f"{change.change:+.4g}"


def _kind(change: MetricChange) -> str:
    return "relative" if change.relative else "absolute"


def _percent(fraction: float) -> str:
    return f"{fraction * 100:g} %"


def _finite(value: float | None) -> float | None:
    return value if value is None or math.isfinite(value) else None


def _escape(text: str) -> str:
    """Text safe in a Markdown table cell or line: pipes, HTML, `*`, `_`, backquotes and brackets escaped."""
    return re.sub(r"([|*_`\\\[\]])", r"\\\1", html.escape(text, quote=False))
