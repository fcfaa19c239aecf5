"""Pure computation behind the Pareto chart: each ok cell's point, which points are Pareto-optimal, the size
legend's reference sizes and a greedy placement of the point numbers that keeps them apart.

Dominance is judged on latency and accuracy only, the two axes of the chart; size is shown as marker area and
not judged. A cell is dominated when another is at least as fast and at least as accurate and strictly better
in one of the two; cells with equal latency and accuracy do not dominate each other, so both stay optimal."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE
from bench_matrix.report.analysis.summary import ModelSummary, figure, metric, p50
from bench_matrix.store import CellRecord

MIB = 2**20
RINGS = 8  # label candidate rings around a point, each one label height further out
ANGLES = tuple(math.radians(a) for a in (0, 180, 90, 270, 30, 150, 330, 210, 60, 120, 300, 240))


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


@dataclass(frozen=True)
class Box:
    """An axis-aligned rectangle (display pixels, y up)."""

    x0: float
    y0: float
    x1: float
    y1: float

    def overlaps(self, other: Box) -> bool:
        return self.x0 < other.x1 and other.x0 < self.x1 and self.y0 < other.y1 and other.y0 < self.y1

    def within(self, bounds: Box) -> bool:
        return bounds.x0 <= self.x0 and self.x1 <= bounds.x1 and bounds.y0 <= self.y0 and self.y1 <= bounds.y1

    def distance(self, x: float, y: float) -> float:
        """From (x, y) to the nearest point of the box (0 inside)."""
        return math.hypot(max(self.x0 - x, 0.0, x - self.x1), max(self.y0 - y, 0.0, y - self.y1))

    def hits_circle(self, x: float, y: float, radius: float) -> bool:
        return self.distance(x, y) < radius


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


def reference_sizes(sizes: Sequence[float]) -> list[float]:
    """Two or three round sizes in bytes (1, 2, 5 × 10^k MiB) spanning `sizes`, for the size legend."""
    low, high = min(sizes) / MIB, max(sizes) / MIB
    steps = [m * 10.0**k for k in range(-4, 7) for m in (1, 2, 5)]
    inside = [s for s in steps if low <= s <= high]
    if len(inside) > 3:
        inside = [inside[0], inside[len(inside) // 2], inside[-1]]
    if not inside:
        inside = [float(f"{high:.2g}")]
    return [s * MIB for s in inside]


def place_labels(anchors: Sequence[tuple[float, float]], radii: Sequence[float],
                 sizes: Sequence[tuple[float, float]], bounds: Box, gap: float) -> list[tuple[float, float]]:
    """The centre of each label of size (w, h) beside its marker (centre `anchors[i]`, radius `radii[i]`),
    chosen in order: the nearest candidate spot inside `bounds` clear of the labels placed so far and of every
    other marker; failing that, the one with the fewest collisions."""
    placed: list[Box] = []
    for i, ((x, y), radius, size) in enumerate(zip(anchors, radii, sizes)):
        others = [(ax, ay, r) for j, ((ax, ay), r) in enumerate(zip(anchors, radii)) if j != i]
        candidates = [_candidate(x, y, radius + gap + ring * size[1], angle, size)
                      for ring in range(RINGS) for angle in ANGLES]
        placed.append(_first_clear(candidates, lambda box: _collisions(box, placed, others, bounds)))
    return [((b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2) for b in placed]


def _first_clear(candidates: list[Box], collisions: Callable[[Box], tuple[bool, int, int]]) -> Box:
    """The first candidate without collisions, else the one with the fewest (the first of equals)."""
    best, best_key = candidates[0], collisions(candidates[0])
    for box in candidates:
        key = collisions(box)
        if key == (False, 0, 0):
            return box
        if key < best_key:
            best, best_key = box, key
    return best


def _candidate(x: float, y: float, distance: float, angle: float, size: tuple[float, float]) -> Box:
    """The label box whose corner (or edge) nearest the point lies `distance` from it in direction `angle`."""
    cos, sin = math.cos(angle), math.sin(angle)
    sx = 0.0 if abs(cos) < 1e-9 else math.copysign(1.0, cos)
    sy = 0.0 if abs(sin) < 1e-9 else math.copysign(1.0, sin)
    cx, cy = x + cos * distance + sx * size[0] / 2, y + sin * distance + sy * size[1] / 2
    return Box(cx - size[0] / 2, cy - size[1] / 2, cx + size[0] / 2, cy + size[1] / 2)


def _collisions(box: Box, placed: list[Box], markers: list[tuple[float, float, float]], bounds: Box
                ) -> tuple[bool, int, int]:
    """How bad a candidate is: outside the bounds, then labels hit, then markers hit."""
    return (not box.within(bounds), sum(box.overlaps(other) for other in placed),
            sum(box.hits_circle(x, y, r) for x, y, r in markers))
