"""The stream scenario: cells selected by the matrix's `stream` section serve frames arriving on a fixed clock
with their loaded session; the achieved rate, deadline misses, drops and jitter go into the record
(docs/stream.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from bench_matrix.cell import Planned
from bench_matrix.matrix.load import Loading
from bench_matrix.scenarios.base import Scenario
from bench_matrix.scenarios.stream.section import stream
from bench_matrix.scenarios.stream.spec import REQUIREMENTS, SCHEMA, StreamSpec

if TYPE_CHECKING:
    from bench_matrix.cell import Cell
    from bench_matrix.matrix.spec import Matrix
    from bench_matrix.measurement import Measurement


@dataclass(frozen=True)
class StreamPlan(Planned):
    """The stream part of a cell: its rate, duration and policy."""

    name = "stream"
    function = "bench_matrix.scenarios.stream.run:run_stream"
    spec: StreamSpec

    def fingerprint(self) -> dict[str, Any]:
        return {"stream": self.spec.stream_dict()}

    def describe(self) -> str:
        """Rate × duration, policy."""
        return f"{self.spec.rate_hz:g} Hz × {self.spec.duration_s:g} s, {self.spec.policy}"

    def timed(self) -> bool:
        return True


class Stream(Scenario):
    """Frames on a fixed clock served by the cell's session, after the latency scenario."""

    name = "stream"
    title = "stream"
    schema = SCHEMA
    requirements = REQUIREMENTS
    section = "bench_matrix.scenarios.stream.report:SECTION"

    def read(self, data: dict[str, Any], loading: Loading) -> StreamSpec:
        return stream(data, loading)

    def plan(self, section: StreamSpec, matrix: Matrix, cell: Cell) -> StreamPlan | None:
        """The cell's stream when the section selects it."""
        return StreamPlan(section) if section.selection.selects(cell.as_dict()) else None

    def figure(self, key: str, metrics: Measurement) -> float | None:
        """The stream's stored figure `key`; None when the cell has none (it did not stream, or too few
        calls completed)."""
        found = metrics.others.get("stream")
        value = found.get(key) if isinstance(found, dict) else None
        real = isinstance(value, int | float) and not isinstance(value, bool)
        return float(value) if real and math.isfinite(value) else None
