"""The stream section of a report, from stored records only: one row per cell that served the stream, its
rate, misses, drops, jitter and latency under the stream (docs/stream.md defines every figure)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from bench_matrix.report.analysis.summary import ModelSummary, Row, number
from bench_matrix.report.render.columns import DASH, METHOD, Column, fixed, sig
from bench_matrix.report.render.sections import Block, Section

INTRO = ("Each cell's own artifact served frames arriving on a fixed clock (docs/stream.md defines every "
         "figure): a frame is due by the next frame's arrival; with policy skip the frames that arrive while "
         "a call runs are dropped, with queue they wait.")


def _column(header: str, note: str, key: str, render: Callable[[float | None], str]) -> Column:
    """A numeric column of the stream's stored figure `key`."""
    return Column(header, note, lambda row: render(number(_stream(row).get(key))), "stream")


def _stream(row: Row) -> dict[str, Any]:
    return row.record.metrics.others["stream"]


def _digits(value: float | None) -> str:
    return sig(value, 3)


def _plain(value: float | None) -> str:
    return DASH if value is None else f"{value:g}"


def _percent(value: float | None) -> str:
    return DASH if value is None else f"{100 * value:.1f}"


COLUMNS: tuple[Column, ...] = (
    METHOD,
    Column("Policy", "skip: frames arriving while a call runs are dropped; queue: they wait.",
           lambda row: str(_stream(row).get("policy", DASH)), ""),
    _column("Rate Hz", "the frames' rate asked for.", "rate_hz", _plain),
    _column("Achieved Hz", "completed calls ÷ the stream's span (its duration, or until the last call ended "
            "if later).", "achieved_hz", lambda v: fixed(v, 1)),
    _column("Frames", "frames that arrived.", "frames", _plain),
    _column("Missed", "calls that ended after their deadline (the next frame's arrival).", "missed", _plain),
    _column("Missed %", "missed ÷ completed calls.", "miss_share", _percent),
    _column("Dropped", "frames never served (skip: they arrived while a call ran).", "dropped", _plain),
    _column("Jitter p50 ms", "median of |interval between consecutive completions − period|.",
            "jitter_p50_ms", _digits),
    _column("Jitter p99 ms", "99th percentile of that deviation.", "jitter_p99_ms", _digits),
    _column("Latency p50 ms", "median service time of a call under the stream.", "latency_p50_ms", _digits),
    _column("Latency p99 ms", "99th percentile of the service time.", "latency_p99_ms", _digits),
    _column("E2E p50 ms", "median time from a frame's arrival to its call's end (queue: with the wait).",
            "e2e_p50_ms", _digits),
    _column("E2E p99 ms", "99th percentile of that time.", "e2e_p99_ms", _digits),
)
TERMINAL_LEFT_OUT = ("Frames", "E2E p50 ms")


def streamed(model: ModelSummary) -> list[Row]:
    """The ok cells' rows that served the stream, in the results table's order."""
    return [row for row in model.rows if isinstance(row.record.metrics.others.get("stream"), dict)]


def blocks(model: ModelSummary) -> list[Block]:
    """The model's "Stream" block (none when no cell served it); the terminal leaves TERMINAL_LEFT_OUT out."""
    found = streamed(model)
    brief = [c for c in COLUMNS if c.header not in TERMINAL_LEFT_OUT]
    return [Block("Stream", INTRO, COLUMNS, found, brief=brief)] if found else []


SECTION = Section(blocks)  # the stream scenario's section of a report
