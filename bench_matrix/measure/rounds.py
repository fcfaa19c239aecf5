"""Statistics over interleaved rounds (docs/metrics.md §5): every session process of every cell is timed once
per round, so a cell's uncertainty comes from how its per-round medians spread (slow drift widens it) and
from how its processes differ (pooled over the model's cells); its speed-up against the baseline is paired,
round by round (drift both cells shared cancels)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from statistics import fmean

import numpy as np

# two-sided 95 % quantiles of Student's t by degrees of freedom; beyond 30, 1.96 + 2.5 / df (within 0.2 %)
T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228,
       2.201, 2.179, 2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086,
       2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)

RERUN = math.sqrt(2)  # a rerun's figure has the same uncertainty as this one: their difference sqrt(2) times
PRIOR_DOF = 4  # the model's pooled process spread counts as this many degrees of freedom beside a cell's own
STRAY = 0.15  # a window this far (log) above the fastest of its own and NEAR rounds either side, or APART
APART = 0.25  # above the cell's fastest, and SPREADS times the windows' own spread, strayed: work no counter
SPREADS = 5  # sees (the SMT sibling's other VM) slowed such by 30-70 % (metrics.md §5), slow drift less
NEAR = 2
FIT_STEPS = 50  # alternating means a round-and-process fit takes (it converges geometrically)
STEPS = 8  # successive windows of one process it takes to tell a strayed window from the cell's own spread
# a median's standard error is this × σ/√n (normal calls; σ from the IQR: ÷ 1.349)
MEDIAN_SE = math.sqrt(math.pi / 2)

Slot = tuple[int, int]  # (round, process): one window of one of a cell's session processes


def t95(df: float) -> float:
    """Student's t two-sided 95 % quantile for `df` >= 1 degrees of freedom (a fractional df rounds down)."""
    whole = max(int(df), 1)
    return T95[whole - 1] if whole <= len(T95) else 1.96 + 2.5 / whole


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


@dataclass(frozen=True)
class Spread:
    """How a cell's session processes differ for their lifetime: the variance of that effect on the log
    level (an estimate: below 0 where the windows' own noise explains all of it), its degrees of freedom."""

    variance: float
    dof: float

    @property
    def relative(self) -> float:
        """One process's typical distance from the cell's level (0.013 = 1.3 %)."""
        return math.sqrt(max(self.variance, 0.0))


def process_spread(levels: Mapping[Slot, float]) -> Spread | None:
    """A cell's process spread (a random effect) from its log levels by slot: variance of each process's mean
    offset from round means (shared drift cancels) less window noise; None under 2 processes or rounds."""
    means = _round_means(levels)
    offsets = _offsets(levels, means)
    rounds = len(means)
    residual_dof = len(levels) - rounds - len(offsets) + 1
    if len(offsets) < 2 or rounds < 2 or residual_dof < 1:
        return None
    residuals = [y - means[r] - offsets[j] for (r, j), y in levels.items()]
    noise = float(np.sum(np.square(residuals))) / residual_dof  # a window's own, beyond its round and process
    between = float(np.sum(np.square(list(offsets.values())))) / (len(offsets) - 1)
    per_process = len(levels) / len(offsets)  # windows each process has, on average
    return Spread(between - noise / per_process, len(offsets) - 1)


def pooled(spreads: Iterable[Spread | None]) -> Spread | None:
    """The spreads of a model's cells pooled, weighted by their degrees of freedom; None without any."""
    found = [s for s in spreads if s is not None]
    dof = sum(s.dof for s in found)
    return Spread(sum(s.variance * s.dof for s in found) / dof, dof) if dof else None


def moderated(own: Spread | None, model: Spread | None) -> Spread | None:
    """A cell's own process spread drawn towards the model's pooled one, which counts as at most PRIOR_DOF
    degrees of freedom (a moderated variance, as limma's, Smyth 2004)."""
    if own is None or model is None:
        return own or model
    prior = min(PRIOR_DOF, model.dof)
    return Spread((prior * model.variance + own.dof * own.variance) / (prior + own.dof), prior + own.dof)


def _process_part(levels: Mapping[Slot, float], model: Spread | None) -> list[tuple[float, float]]:
    """The processes' part of a cell level's variance (its moderated spread ÷ its processes), with its
    degrees of freedom; none with one process, or where the spread is not above 0."""
    own, processes = moderated(process_spread(levels), model), len({j for _, j in levels})
    return [(own.variance / processes, own.dof)] if own and processes > 1 and own.variance > 0 else []


def window_spread(levels: Mapping[Slot, float]) -> float | None:
    """How much one window's level differs from the next one's of the same process, as a relative SD: the
    MAD of successive rounds' log differences × 1.4826 ÷ √2 (slow drift cancels); None under 3 windows."""
    steps = _steps(levels)
    if len(steps) < 2:
        return None
    return 1.4826 * float(np.median(np.abs(steps - np.median(steps)))) / math.sqrt(2)


def _steps(levels: Mapping[Slot, float]) -> np.ndarray:
    """Successive rounds' log differences within each process."""
    ordered = sorted(levels.items())
    return np.asarray([b - a for process in sorted({j for _, j in levels})
                       for a, b in itertools.pairwise([y for (_, j), y in ordered if j == process])])


def log_levels(values: Mapping[Slot, float]) -> dict[Slot, float]:
    """The logarithms of positive finite values by slot (times and ratios are multiplicative)."""
    return {slot: math.log(v) for slot, v in values.items() if v > 0 and math.isfinite(v)}


def steady(levels: Mapping[Slot, float], rate: bool = False) -> dict[Slot, float]:
    """Log levels (times; `rate`s: samples/s) less windows a neighbour slowed: STRAY over the fastest within
    NEAR rounds, or APART over the cell's fastest (each ≥ SPREADS window spreads); needs STEPS steps."""
    if len(_steps(levels)) < STEPS:
        return dict(levels)
    sign = -1.0 if rate else 1.0
    by_round: dict[int, float] = {}
    for (r, _), y in levels.items():
        by_round[r] = min(by_round.get(r, math.inf), sign * y)
    fastest = {r: min(by_round.get(near, math.inf) for near in range(r - NEAR, r + NEAR + 1))
               for r in by_round}
    local = {slot: sign * y - fastest[slot[0]] for slot, y in levels.items()}
    overall = {slot: sign * y - min(sign * v for v in levels.values()) for slot, y in levels.items()}
    # the windows' own spread: the MAD of how far those within STRAY are above their fastest (the slowed
    # ones, or a step between the two kinds, would swell any spread that counts them)
    near = np.asarray([distance for distance in local.values() if distance <= STRAY])
    noise = SPREADS * 1.4826 * float(np.median(np.abs(near - np.median(near))))
    return {slot: y for slot, y in levels.items()
            if local[slot] <= max(STRAY, noise) and overall[slot] <= max(APART, noise)}


def level_interval(value: float, levels: Mapping[Slot, float], model: Spread | None,
                   spread: float = 1.0, noise: float = 0.0) -> Interval | None:
    """`value`, its log level's 95 % interval ×`spread`: rounds' part (round means' spread, ≥ `noise`, a
    window level's variance) plus processes' (moderated spread ÷ processes); None: < 2 rounds or value ≤ 0."""
    means = _round_means(levels)
    if value <= 0 or len(means) < 2:
        return None
    observed = float(np.var(list(means.values()), ddof=1))
    by_rounds = (max(observed, noise) / len(means), len(means) - 1)
    return _interval(value, [by_rounds, *_process_part(levels, model)], spread, len(means))


def paired_interval(baseline: Mapping[Slot, float], cell: Mapping[Slot, float],
                    model: Spread | None) -> Interval | None:
    """Baseline ÷ cell from their log levels, paired by round (geometric mean of per-round mean ratios over
    shared rounds), with the rounds' part and both cells' process parts; None below 2 such rounds."""
    base, mine = _round_means(baseline), _round_means(cell)
    ratios = [base[r] - mine[r] for r in sorted(set(base) & set(mine))]
    if len(ratios) < 2:
        return None
    parts = [(float(np.var(ratios, ddof=1)) / len(ratios), len(ratios) - 1),
             *_process_part(baseline, model), *_process_part(cell, model)]
    return _interval(math.exp(float(np.mean(ratios))), parts, 1.0, len(ratios))


@dataclass(frozen=True)
class Level:
    """A window's median and that median's own variance on the log scale ((MEDIAN_SE·σ/√n ÷ median)², σ from
    the IQR; None under 4 calls): computed once a window, not every round."""

    median: float
    noise: float | None


def window_level(values: np.ndarray) -> Level:
    """A window's `Level`, from one pass over its calls."""
    if len(values) < 4:
        return Level(float(np.median(values)), None)
    low, middle, high = (float(q) for q in np.percentile(values, (25, 50, 75)))
    noise = (MEDIAN_SE * (high - low) / 1.349 / math.sqrt(len(values)) / middle) ** 2 if middle > 0 else None
    return Level(middle, noise)


def medians(series: Mapping[Slot, np.ndarray]) -> dict[Slot, float]:
    """The median of each slot's kept window."""
    return {slot: float(np.median(values)) for slot, values in series.items() if len(values)}


def p50_interval(series: Mapping[Slot, np.ndarray], model: Spread | None = None,
                 levels: Mapping[Slot, Level] | None = None) -> Interval | None:
    """All windows' pooled median with a rerun's interval: `level_interval` of the steady window medians
    ×RERUN, ≥ the windows' own median error (rounds may agree to the ns); `levels`: known `Level`s."""
    if not series:
        return None
    pooled_median = float(np.median(np.concatenate([np.asarray(v, dtype=np.float64)
                                                    for v in series.values()])))
    levels = levels if levels is not None else {slot: window_level(v) for slot, v in series.items() if len(v)}
    steady_levels = steady(log_levels({slot: level.median for slot, level in levels.items()}))
    noises = [found for slot in steady_levels if (found := levels[slot].noise) is not None]
    return level_interval(pooled_median, steady_levels, model, RERUN, fmean(noises) if noises else 0.0)


def level_width(p50: Interval) -> float:
    """How precisely the run knows its own p50: the half-width of `p50_interval`'s interval ÷ RERUN (what the
    rounds' target applies to)."""
    return p50.half_width / RERUN


def speedup(baseline: Mapping[Slot, float], cell: Mapping[Slot, float],
            model: Spread | None = None) -> Interval | None:
    """Baseline time ÷ cell time from their per-window medians, paired by round (`paired_interval`)."""
    return paired_interval(steady(log_levels(baseline)), steady(log_levels(cell)), model)


def rate_interval(rates: Mapping[Slot, float], samples: float, seconds: float,
                  model: Spread | None = None) -> Interval | None:
    """A throughput: `samples` ÷ `seconds` over every kept window, with the interval a rerun's would fall in
    (from the per-window rates, as for the p50)."""
    return level_interval(samples / seconds, steady(log_levels(rates), rate=True), model, RERUN) \
        if seconds > 0 else None


def _round_means(levels: Mapping[Slot, float]) -> dict[int, float]:
    """Each round's mean level over the cell's processes; where a round lacks some, rounds and processes are
    fitted as two additive effects (alternating means), so a missing process does not move its round."""
    means = _plain_means(levels)
    if len({len(ys) for ys in _by_round(levels).values()}) <= 1:
        return means
    for _ in range(FIT_STEPS):
        offsets = _offsets(levels, means)
        middle = fmean(offsets.values())
        means = _plain_means({(r, j): y - offsets[j] + middle for (r, j), y in levels.items()})
    return means


def _by_round(levels: Mapping[Slot, float]) -> dict[int, list[float]]:
    by_round: dict[int, list[float]] = {}
    for (r, _), y in levels.items():
        by_round.setdefault(r, []).append(y)
    return by_round


def _plain_means(levels: Mapping[Slot, float]) -> dict[int, float]:
    return {r: fmean(ys) for r, ys in _by_round(levels).items()}


def _offsets(levels: Mapping[Slot, float], means: Mapping[int, float]) -> dict[int, float]:
    """Each process's mean distance from the means (`means`, by round) of the rounds it was timed in."""
    by_process: dict[int, list[float]] = {}
    for (r, j), y in levels.items():
        by_process.setdefault(j, []).append(y - means[r])
    return {j: fmean(d) for j, d in by_process.items()}


def _interval(value: float, parts: list[tuple[float, float]], spread: float, rounds: int) -> Interval:
    """`value` ± t·sqrt(Σ variances) on the log scale, the degrees of freedom Welch–Satterthwaite's."""
    variance = sum(v for v, _ in parts)
    denominator = sum(v * v / dof for v, dof in parts if dof > 0)
    dof = variance * variance / denominator if denominator > 0 else 1e9
    half = spread * t95(dof) * math.sqrt(variance)
    return Interval(value, value * math.exp(-half), value * math.exp(half), rounds)
