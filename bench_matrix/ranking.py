"""Cells ranked by a model's objective (docs/results.md §8), and how many times better one is than another,
with the interval of that ratio; the report's recommendation and the rounds' leaders both rank so."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Protocol

from bench_matrix.measurement import Measurement
from bench_matrix.verdict import figure

FIGURES = {"p50": "p50_ms", "p99": "p99_ms", "size": "size_mib", "throughput": "throughput_sps"}


class Ranked(Protocol):
    """A cell to rank: its key, its figures, and whether it is the model's baseline (its speed-up is 1)."""

    @property
    def key(self) -> str: ...

    @property
    def metrics(self) -> Measurement: ...

    @property
    def baseline(self) -> bool: ...


def rank(cells: Sequence[Ranked], objective: str) -> list[Ranked]:
    """Best first by the objective: p50 by the paired speed-up where every cell has one, else by p50; p99 and
    size lowest first; throughput highest first; ties by cell key."""
    score = _score(objective, speedups(cells))
    return sorted(cells, key=lambda c: (score(c), c.key))


def compare(best: Ranked, other: Ranked, objective: str, paired: bool) -> tuple[float | None, float | None]:
    """How many times better `best` is than `other` on the objective, and the log-scale half-width of that
    ratio's 95 % interval (both half-widths in quadrature; 0 for sizes; None where a figure has none)."""
    if objective == "p50" and paired:
        (a, ha), (b, hb) = speedup(best), speedup(other)
        return a / b, math.hypot(ha, hb)
    (a, ia), (b, ib) = (figure(FIGURES[objective], c.metrics) for c in (best, other))
    if not a or not b or a < 0 or b < 0:
        return None, None
    ratio = a / b if objective == "throughput" else b / a
    if objective == "size":
        return ratio, 0.0
    halves = [_log_half(value, interval) for value, interval in ((a, ia), (b, ib))]
    return ratio, None if None in halves else math.hypot(*halves)


def speedups(cells: Iterable[Ranked]) -> bool:
    """Whether every cell has a paired speed-up (the baseline's is 1)."""
    return all(c.baseline or speedup(c)[0] > 0 for c in cells)


def speedup(c: Ranked) -> tuple[float, float]:
    """The cell's paired speed-up and its interval's half-width on the log scale; the baseline's is (1, 0)."""
    if c.baseline:
        return 1.0, 0.0
    found = c.metrics.speedup
    value = found.value if found is not None and isinstance(found.value, int | float) else 0.0
    if value <= 0:
        return 0.0, 0.0
    interval = found.ci if found is not None and found.ci is not None and len(found.ci) == 2 else None
    half = _log_half(value, interval)
    if half is None:
        half = math.log1p(found.ci_half) if isinstance(found.ci_half, int | float) else 0.0
    return float(value), half


def _score(objective: str, paired: bool) -> Callable[[Ranked], float]:
    def read(key: str, c: Ranked) -> float:
        value = figure(key, c.metrics)[0]
        return math.inf if value is None else value
    if objective == "p50" and paired:
        return lambda c: -speedup(c)[0]
    if objective == "throughput":
        return lambda c: -read("throughput_sps", c)
    return lambda c: read(FIGURES[objective], c)


def _log_half(value: float | None, interval: Sequence[float] | None) -> float | None:
    """The larger side of `interval` around `value` on the log scale, or None."""
    if value is None or value <= 0 or interval is None or min(interval) <= 0:
        return None
    return max(math.log(interval[1] / value), math.log(value / interval[0]), 0.0)
