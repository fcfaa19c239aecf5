"""Pure computation behind the Pareto chart: each ok cell's point and which points are Pareto-optimal
(render/pareto_layout.py places them on the chart).

Dominance is judged on latency and accuracy only, the two axes of the chart; size is shown as marker area and
not judged. A cell is dominated when another is at least as fast and at least as accurate and strictly better
in one of the two; cells with equal latency and accuracy do not dominate each other, so both stay optimal."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE
from bench_matrix.report.analysis.summary import ModelSummary, figure, metric, p50
from bench_matrix.store import CellRecord


@dataclass(frozen=True)
class Point:
    """One ok cell on the chart; `number` (from 1, in the results table's row order) names it on the chart."""

    number: int
    record: CellRecord
    latency_ms: float
    accuracy: float
    size_bytes: float | None
    ci: tuple[float, float] | None
    optimal: bool
    verdict: str | None = None  # pass, fail or uncertain against the model's requirements; None: none given
    recommended: bool = False  # the recommended cell of its target


def accuracy_metric(model: ModelSummary) -> tuple[str, bool]:
    """The model's headline accuracy metric and whether higher is better."""
    name = HEADLINE.get(model.task, HEADLINE["none"])
    return name, DIRECTIONS.get(name) == "higher"


def points(model: ModelSummary) -> tuple[list[Point], list[CellRecord]]:
    """The chart's points, numbered in row order with the optimal ones marked, and the ok cells left out
    because they lack a finite p50 latency or accuracy."""
    name, higher = accuracy_metric(model)
    kept, left_out = [], []
    for row in model.rows:
        latency, accuracy = p50(row.record), metric(row.record, name)
        if latency is None or accuracy is None or not math.isfinite(latency) or not math.isfinite(accuracy):
            left_out.append(row.record)
        else:
            kept.append((row.record, latency, accuracy))
    optimal = pareto_optimal([(latency, accuracy) for _, latency, accuracy in kept], higher)
    verdicts = {id(row.record): row.verdict.status for row in model.rows if row.verdict is not None}
    best = {id(r.best) for r in model.recommendations if r.best is not None}
    found = [Point(number=k + 1, record=record, latency_ms=latency, accuracy=accuracy,
                   size_bytes=figure(record, lambda m: m.size.bytes), ci=_interval(record),
                   optimal=optimal[k], verdict=verdicts.get(id(record)), recommended=id(record) in best)
             for k, (record, latency, accuracy) in enumerate(kept)]
    return found, left_out


def _interval(record: CellRecord) -> tuple[float, float] | None:
    latency = record.metrics.latency
    interval = latency.p50_ci if latency is not None else None
    if isinstance(interval, list | tuple) and len(interval) == 2 and all(
            isinstance(v, int | float) and math.isfinite(v) for v in interval):
        return float(interval[0]), float(interval[1])
    return None


def pareto_optimal(pairs: Sequence[tuple[float, float]], higher_is_better: bool) -> list[bool]:
    """For each (latency, accuracy) pair, whether no other pair dominates it (see the module's docstring)."""
    sign = 1.0 if higher_is_better else -1.0
    scored = [(latency, sign * accuracy) for latency, accuracy in pairs]
    return [not any(_dominates(other, point) for other in scored) for point in scored]


def _dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether `a` (latency, accuracy scored higher-is-better) is as good as `b` in both and better in one."""
    return a[0] <= b[0] and a[1] >= b[1] and (a[0] < b[0] or a[1] > b[1])
