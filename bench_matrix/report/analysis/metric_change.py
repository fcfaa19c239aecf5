"""How one metric of one cell changed between the two sides of a `compare`: the sides, the change, and the
judges of p50, p99, throughput, size and accuracy (their rules: compare.py's docstring)."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import fisher_exact, mannwhitneyu

from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE
from bench_matrix.measurement import Measurement, Speedup
from bench_matrix.report.analysis.summary import disturbed_phases, emulated, figure
from bench_matrix.store import CellRecord

BETTER, WORSE, UNCHANGED, NOT_COMPARABLE = "better", "worse", "unchanged", "not comparable"
VERDICTS = (BETTER, WORSE, UNCHANGED, NOT_COMPARABLE)
UNPAIRED = ("its twins shared fewer than 2 rounds free of windows a neighbour slowed: the machine was too "
            "busy to pair them; remeasure when it is quieter, or with more `timing_budget_s`")


@dataclass(frozen=True)
class Side:
    """One side of a comparison ("run 3", "other.sqlite"): its records (at most one per cell key), their raw
    latencies in ms (series "latency_ms") by cell key, and the task of each model where known."""

    label: str
    records: Sequence[CellRecord]
    samples: Mapping[str, np.ndarray]
    tasks: Mapping[str, str] = field(default_factory=dict)
    batches: Mapping[str, np.ndarray] = field(default_factory=dict)  # throughput's batch durations, ms


@dataclass(frozen=True)
class MetricChange:
    """One metric of one cell on both sides: the values, the change, its threshold, the verdict and why it is
    not comparable (`why`); `p_value` for latency metrics whose samples were tested."""

    metric: str  # one of METRICS (compare.py)
    name: str  # what it is in the record: "latency_ms.p50", "throughput_sps", "size_bytes", "mse", ...
    base: float | None
    new: float | None
    change: float | None
    relative: bool  # change as a fraction of the base value, else an absolute difference
    threshold: float
    verdict: str
    p_value: float | None = None
    why: str | None = None


@dataclass(frozen=True)
class Pair:
    """The two sides and their records of one cell key (None where a side lacks it)."""

    base: Side
    new: Side
    before: CellRecord | None
    after: CellRecord | None
    tasks: Mapping[str, str]
    twin: Speedup | None = None  # remeasured: base time ÷ new time, paired by round

    def roles(self) -> tuple[tuple[str, Side, CellRecord | None], ...]:
        return ("base", self.base, self.before), ("new", self.new, self.after)

    def both(self) -> tuple[CellRecord, CellRecord]:
        """The two records, for a cell present on both sides."""
        assert self.before is not None and self.after is not None
        return self.before, self.after


def _task(side: Side, record: CellRecord, tasks: Mapping[str, str]) -> str:
    """The model's task: the side's own, the caller's, else told by which headline metric the record has."""
    known = side.tasks.get(record.cell.model) or tasks.get(record.cell.model)
    if known:
        return known
    present = [task for task in ("classification", "regression", "none")
               if figure(record, lambda m: m.task.figure(HEADLINE[task])) is not None]
    return present[0] if present else "regression"


def timing_changes(pair: Pair, limits: Mapping[str, float], alpha: float) -> tuple[MetricChange, ...]:
    """p50, p99 and throughput; not comparable where a side was timed on an emulated device."""
    sides = [role for role, _, record in pair.roles() if record is not None and emulated(record)]
    if not sides:
        p50 = _twinned(pair, limits) or _paired(pair, limits) or _latency(pair, "p50", limits, alpha)
        return p50, _latency(pair, "p99", limits, alpha), _throughput(pair, limits, alpha)
    why = f"timed on an emulated device in {' and '.join(sides)}: not the board's speed"
    timed = (("p50", "latency_ms.p50", lambda m: m.latency and m.latency.p50, "lower"),
             ("p99", "latency_ms.p99", lambda m: m.latency and m.latency.p99, "lower"),
             ("throughput", "throughput_sps", lambda m: m.throughput.sps, "higher"))
    return tuple(_MetricJudge(metric, name, *_values(pair, name, read)[:2], True, limits[metric], direction)
                 .not_comparable(why) for metric, name, read, direction in timed)


def _phase_disturbed(pair: Pair, phase: str) -> str | None:
    """Why a timed phase cannot be compared: flagged for interference on a side (every attempt disturbed)."""
    sides = [role for role, _, record in pair.roles()
             if record is not None and phase in disturbed_phases(record)]
    return f"{phase} measured under interference in {' and '.join(sides)} (re-run it on a quiet machine)" \
        if sides else None


def _values(pair: Pair, name: str, read: Callable[[Measurement], Any]
            ) -> tuple[float | None, float | None, str | None]:
    """A figure (`name`, as `read`) of both records, and why it cannot be compared when a side lacks it (or it
    is not finite)."""
    base, new = (_finite(figure(record, read)) for record in pair.both())
    missing = [role for role, value in (("base", base), ("new", new)) if value is None]
    return base, new, f"no {name} in {' and '.join(missing)}" if missing else None


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _latency(pair: Pair, which: str, limits: Mapping[str, float], alpha: float) -> MetricChange:
    """p50 or p99: worse or better only when the samples differ significantly and beyond the threshold."""
    base, new, why = _values(pair, f"latency_ms.{which}", lambda m: m.latency and getattr(m.latency, which))
    judge = _MetricJudge(which, f"latency_ms.{which}", base, new, True, limits[which], "lower")
    if why:
        return judge.not_comparable(why)
    samples = {role: side.samples.get(record.cell.key) for role, side, record in pair.roles() if record}
    lacking = [role for role, values in samples.items() if values is None or len(values) == 0]
    if lacking:
        return judge.not_comparable(f"no raw latency samples in {' and '.join(lacking)}")
    disturbed = _phase_disturbed(pair, "latency")
    if disturbed:
        return judge.not_comparable(disturbed)
    before, after = (np.asarray(samples[role], np.float64) for role in ("base", "new"))
    p_value = _tail_p_value(before, after) if which == "p99" else _shift_p_value(before, after)
    return judge.judged(significant=p_value < alpha, p_value=p_value)


def _paired(pair: Pair, limits: Mapping[str, float]) -> MetricChange | None:
    """p50 judged on the speed-ups paired by round, where both records have one (else None): changed when
    their intervals tell them apart and beyond the p50 threshold."""
    found = [record.metrics.speedup for record in pair.both()]
    if any(s is None or s.value is None or s.ci_half is None for s in found):
        return None
    base, new = found
    judge = _MetricJudge("p50", "speedup.value", base.value, new.value, True, limits["p50"], "higher")
    spread = math.hypot(math.log1p(base.ci_half), math.log1p(new.ci_half))
    apart = abs(math.log(new.value / base.value)) > spread
    return judge.judged(significant=apart)


def _twinned(pair: Pair, limits: Mapping[str, float]) -> MetricChange | None:
    """p50 of a remeasured cell, judged on the new artifact's time ÷ its base twin's in the same rounds (the
    new p50 shown: the base's times that ratio): changed when its interval excludes 1, past the threshold."""
    twin = pair.twin
    base = figure(pair.before, lambda m: m.latency and m.latency.p50) if pair.before else None
    if twin is None or base is None:
        return None
    judge = _MetricJudge("p50", "latency_ms.p50 (paired)", base, base / twin.value if twin.value else None,
                         True, limits["p50_remeasured"], "lower")
    if twin.value is None or not twin.ci:
        return judge.not_comparable(UNPAIRED)
    return judge.judged(significant=not twin.ci[0] <= 1.0 <= twin.ci[-1])


def _shift_p_value(before: np.ndarray, after: np.ndarray) -> float:
    """Mann-Whitney U, two-sided: whether one sample's values tend to be larger than the other's."""
    p_value = float(mannwhitneyu(before, after, alternative="two-sided").pvalue)
    return 1.0 if math.isnan(p_value) else p_value


def _tail_p_value(before: np.ndarray, after: np.ndarray) -> float:
    """Two-sided Fisher's exact test on each side's samples above the pooled 99th percentile: whether the
    slowest 1 % favour one side beyond chance (not a median shift; a handful never reaches significance)."""
    tail = np.percentile(np.concatenate([before, after]), 99)
    above = [int(np.sum(before > tail)), int(np.sum(after > tail))]
    if sum(above) == 0:
        return 1.0
    table = [[above[0], len(before) - above[0]], [above[1], len(after) - above[1]]]
    return float(fisher_exact(table, alternative="two-sided").pvalue)


def _throughput(pair: Pair, limits: Mapping[str, float], alpha: float) -> MetricChange:
    """Samples per second: tested on the batch durations where both sides stored them (Mann-Whitney U),
    judged by the threshold alone for records from before they were kept."""
    base, new, why = _values(pair, "throughput_sps", lambda m: m.throughput.sps)
    judge = _MetricJudge("throughput", "throughput_sps", base, new, True, limits["throughput"], "higher")
    why = why or _phase_disturbed(pair, "throughput")
    if why:
        return judge.not_comparable(why)
    batches = [side.batches.get(record.cell.key) for _, side, record in pair.roles() if record]
    if any(b is None or len(b) == 0 for b in batches):
        return judge.judged()
    p_value = _shift_p_value(*(np.asarray(b, np.float64) for b in batches))
    return judge.judged(significant=p_value < alpha, p_value=p_value)


def size_change(pair: Pair, limits: Mapping[str, float]) -> MetricChange:
    base, new, why = _values(pair, "size_bytes", lambda m: m.size.bytes)
    judge = _MetricJudge("size", "size_bytes", base, new, True, limits["size"], "lower")
    return judge.not_comparable(why) if why else judge.judged()


def accuracy_change(pair: Pair, limits: Mapping[str, float]) -> MetricChange:
    """The task's headline metric: relative change for error metrics, absolute for fractions (see module)."""
    tasks = [_task(side, record, pair.tasks) for _, side, record in pair.roles() if record]
    name = HEADLINE.get(tasks[0], HEADLINE["regression"])
    relative = DIRECTIONS[name] == "lower"
    threshold = limits["accuracy_relative" if relative else "accuracy_absolute"]
    if tasks[0] != tasks[1]:
        judge = _MetricJudge("accuracy", name, None, None, relative, threshold, DIRECTIONS[name])
        return judge.not_comparable(f"different task: {tasks[0]} in base, {tasks[1]} in new")
    base, new, why = _values(pair, name, lambda m: m.task.figure(name))
    judge = _MetricJudge("accuracy", name, base, new, relative, threshold, DIRECTIONS[name])
    return judge.not_comparable(why) if why else judge.judged()


@dataclass(frozen=True)
class _MetricJudge:
    """The facts needed to judge one metric; `judged` applies its threshold (and significance, if tested)."""

    metric: str
    name: str
    base: float | None
    new: float | None
    relative: bool
    threshold: float
    direction: str  # "lower" or "higher" is better

    def not_comparable(self, why: str) -> MetricChange:
        return self._result(None, NOT_COMPARABLE, None, why)

    def judged(self, significant: bool = True, p_value: float | None = None) -> MetricChange:
        assert self.base is not None and self.new is not None
        if self.relative and self.base <= 0:
            if self.new == self.base:
                return self._result(0.0, UNCHANGED, p_value, None)
            return self._result(None, NOT_COMPARABLE, p_value, f"{self.name} is {self.base:g} in base: no "
                                                                 f"relative change")
        change = (self.new - self.base) / self.base if self.relative else self.new - self.base
        if not significant or abs(change) <= self.threshold:
            return self._result(change, UNCHANGED, p_value, None)
        improved = (change < 0) == (self.direction == "lower")
        return self._result(change, BETTER if improved else WORSE, p_value, None)

    def _result(self, change: float | None, verdict: str, p_value: float | None, why: str | None
                ) -> MetricChange:
        return MetricChange(self.metric, self.name, self.base, self.new, change, self.relative,
                            self.threshold, verdict, p_value, why)
