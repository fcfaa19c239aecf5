"""The profile section of a report, from stored records only: per profiled cell, its profiled time, the
profiler's overhead and its time's shares by operator kind × precision (docs/metrics.md, Profiles)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from bench_matrix.op_profile import KINDS, PRECISIONS
from bench_matrix.report.analysis.summary import ModelSummary, Row, number
from bench_matrix.report.render.columns import DASH, Column, fixed, sig
from bench_matrix.report.render.html_parts import esc, table
from bench_matrix.report.render.sections import Section

INTRO = ("Each cell's test sample ran under its runtime's own profiler after the rounds (docs/metrics.md, "
         "Profiles): its time by operator kind and the precision each operator ran at, as shares of the "
         "profiled time.")
SHARE_NOTE = "share of the profiled time in operators of that kind (docs/metrics.md) run at that precision."
FLOAT_IN_INT8 = "float in int8 %"
FLOATS = ("fp32", "fp16", "bf16")
METHOD = Column("Method", "backend, strategy and precision of the cell.", lambda row: row.record.cell.label,
                "")


def profiled(model: ModelSummary) -> list[Row]:
    """The ok cells' rows with a profile, in the results table's order."""
    return [row for row in model.rows if isinstance(row.record.metrics.others.get("profile_operators"), list)]


def shares(row: Row) -> dict[tuple[str, str], float]:
    """The share of the cell's profiled time in each (kind, precision)."""
    found: dict[tuple[str, str], float] = {}
    for op in row.record.metrics.others["profile_operators"]:
        key = (op["kind"], op["precision"])
        found[key] = found.get(key, 0.0) + op["ms"]
    total = math.fsum(found.values())
    return {key: ms / total for key, ms in found.items()} if total > 0 else {}


def overhead(row: Row) -> float | None:
    """Profiled time per inference ÷ the timed p50 (batch 1); None where either is missing or not finite."""
    p50, ms = number(row.record.metrics.latency.p50), number(row.record.metrics.others.get("profile_ms"))
    ratio = ms / p50 if p50 and ms is not None else None
    return ratio if ratio is not None and math.isfinite(ratio) else None


def float_share(row: Row) -> float | None:
    """An int8 cell's share of time in operators that ran in floating point (None for other precisions)."""
    if row.record.cell.precision != "int8":
        return None
    return math.fsum(share for (_, precision), share in shares(row).items() if precision in FLOATS)


def _percent(value: float | None) -> str:
    return DASH if value is None else f"{100 * value:.1f}"


def columns(rows: list[Row]) -> list[Column]:
    """Method, time, overhead, a share column per (kind, precision) a row has, and int8 cells' fp32 share."""
    found = {key for row in rows for key in shares(row)}
    pairs = [(k, p) for k in KINDS for p in PRECISIONS if (k, p) in found]
    int8 = any(row.record.cell.precision == "int8" for row in rows)
    return [METHOD,
            Column("Profiled ms", "sum of the operators' times per inference under the profiler.",
                   lambda row: sig(number(row.record.metrics.others.get("profile_ms")), 3), "profile"),
            Column("Overhead ×", "profiled ms ÷ the timed p50: how much the profiler slowed the cell.",
                   lambda row: fixed(overhead(row), 2), "profile"),
            *(Column(f"{k} {p} %", f"share of the profiled time in {k} operators run at {p}.",
                     lambda row, key=(k, p): _percent(shares(row).get(key, 0.0)), "profile")
              for k, p in pairs),
            *([Column(FLOAT_IN_INT8, "an int8 cell's share of time in operators that ran in floating "
                                     "point (fp32, fp16 or bf16).",
                      lambda row: _percent(float_share(row)), "profile")] if int8 else [])]


def reasons(model: ModelSummary) -> list[str]:
    """Each ok cell's reason it has no profile, where it was asked for one."""
    return [f"{row.record.cell.label}: {row.record.metrics.others['profile_reason']}" for row in model.rows
            if isinstance(row.record.metrics.others.get("profile_reason"), str)]


def markdown_lines(model: ModelSummary, table: Callable[[list[str], list[bool], list[list[str]]], str],
                   escape: Callable[[str], str]) -> list[str]:
    """The model page's "Where the time goes" section (empty when no cell has a profile)."""
    found = profiled(model)
    if not found:
        return []
    shown = columns(found)
    return ["## Where the time goes", "", escape(INTRO), "",
            table([escape(c.header) for c in shown], [c.numeric for c in shown],
                  [[escape(c.render(row)) for c in shown] for row in found]),
            "", "Columns:", "", *(f"- **{escape(c.header)}**: {escape(c.note)}" for c in shown[:3]),
            f"- **KIND PRECISION %**: {escape(SHARE_NOTE)}",
            *(f"- **{escape(c.header)}**: {escape(c.note)}" for c in shown if c.header == FLOAT_IN_INT8), "",
            *(f"Not profiled: {escape(line)}" for line in reasons(model)), ""]


def html_parts(model: ModelSummary) -> list[str]:
    """The HTML page's section: the profile table."""
    found = profiled(model)
    if not found:
        return []
    shown = columns(found)
    return ["<h3>Where the time goes</h3>", f"<p>{esc(INTRO)}</p>",
            table([(c.header, c.note) for c in shown], [c.numeric for c in shown],
                  [[c.render(row) for c in shown] for row in found]),
            *(f"<p>Not profiled: {esc(line)}</p>" for line in reasons(model))]


def print_terminal(model: ModelSummary, console: Any) -> None:
    """Print the profile table, if a cell has a profile."""
    from rich.table import Table

    found = profiled(model)
    if not found:
        return
    shown = columns(found)
    table = Table(title=f"{model.name}: where the time goes (profiled)", title_justify="left")
    for column in shown:
        table.add_column(column.header, justify="right" if column.numeric else "left")
    for row in found:
        table.add_row(*(c.render(row) for c in shown))
    console.print(table)
    for line in reasons(model):
        console.print(f"not profiled: {line}")


SECTION = Section(markdown_lines, html_parts, print_terminal)  # the profile scenario's section of a report
