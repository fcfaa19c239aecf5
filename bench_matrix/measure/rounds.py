"""Statistics over interleaved rounds (docs/metrics.md §5): every cell is timed once per round, so a cell's
uncertainty comes from how its per-round medians spread (slow drift widens it) and its speed-up against the
baseline is paired, round by round (drift both cells shared cancels)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

# two-sided 95 % quantiles of Student's t by degrees of freedom; beyond 30, 1.96 + 2.5 / df (within 0.2 %)
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
       2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
       2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


RERUN = math.sqrt(2)  # a rerun's figure has the same uncertainty as this one: their difference sqrt(2) times


def t95(df: int) -> float:
    """Student's t two-sided 95 % quantile for `df` >= 1 degrees of freedom."""
    return T95[df - 1] if df <= len(T95) else 1.96 + 2.5 / df


@dataclass(frozen=True)
class Interval:
    """A figure, its 95 % interval [low, high] and the number of rounds it comes from."""

    value: float
    low: float
    high: float
    rounds: int

    @property
    def half_width(self) -> float:
        """The interval's larger distance from the value, relative to it (0.02 = ±2 %)."""
        return max(self.high - self.value, self.value - self.low) / self.value

    def as_dict(self) -> dict[str, float | int | list[float]]:
        return {"value": self.value, "ci": [self.low, self.high], "ci_half": round(self.half_width, 6),
                "rounds": self.rounds}


def log_interval(value: float, per_round: Iterable[float], spread: float = 1.0) -> Interval | None:
    """`value` with the 95 % interval of a t-interval on the logs of its per-round estimates (ratios and
    times are multiplicative), `spread` times as wide, shifted to `value`; None with fewer than 2 rounds or a
    non-positive figure."""
    logs = np.log(np.asarray([x for x in per_round], dtype=np.float64)) if value > 0 else np.array([])
    if logs.size < 2 or not np.all(np.isfinite(logs)):
        return None
    half = spread * t95(logs.size - 1) * float(logs.std(ddof=1)) / math.sqrt(logs.size)
    return Interval(value, value * math.exp(-half), value * math.exp(half), int(logs.size))


def medians_by_round(series: Mapping[int, np.ndarray]) -> dict[int, float]:
    """The median of each round's kept window."""
    return {r: float(np.median(values)) for r, values in series.items() if len(values)}


def p50_interval(series: Mapping[int, np.ndarray]) -> Interval | None:
    """The pooled median of every round's window with the interval a rerun's would fall in: that of the
    per-round medians, RERUN times as wide."""
    if not series:
        return None
    pooled = float(np.median(np.concatenate([np.asarray(v, dtype=np.float64) for v in series.values()])))
    return log_interval(pooled, medians_by_round(series).values(), RERUN)


def level_width(p50: Interval) -> float:
    """How precisely the run knows its own p50: the half-width of `p50_interval`'s interval ÷ RERUN (what the
    rounds' target applies to)."""
    return p50.half_width / RERUN


def speedup(baseline: Mapping[int, float], cell: Mapping[int, float]) -> Interval | None:
    """Baseline time ÷ cell time, paired by round: the geometric mean of the per-round ratios over the rounds
    both have, with its interval (None with fewer than 2 such rounds)."""
    rounds = sorted(set(baseline) & set(cell))
    ratios = [baseline[r] / cell[r] for r in rounds if cell[r] > 0 and baseline[r] > 0]
    if len(ratios) < 2:
        return None
    return log_interval(float(np.exp(np.mean(np.log(ratios)))), ratios)


def rate_interval(rates: Mapping[int, float], samples: float, seconds: float) -> Interval | None:
    """A throughput: `samples` ÷ `seconds` over every kept window, with the interval a rerun's would fall in
    (from the per-round rates, as for the p50)."""
    return log_interval(samples / seconds, rates.values(), RERUN) if seconds > 0 else None
