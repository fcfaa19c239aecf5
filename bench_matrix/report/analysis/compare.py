"""`compare`: per cell of two sets of records, the change of p50, p99, throughput, size and the task's
accuracy metric, each judged better / worse / unchanged / not comparable. Pure functions over stored results.

A timed metric changes only when the change is BOTH significant (p < alpha) and beyond its threshold:
airspeed velocity's rule. p50: Mann-Whitney U, two-sided, on the raw latencies; p99: Fisher's exact test on
how many of each side's latencies lie above the pooled 99th percentile; throughput: Mann-Whitney U on the
batch durations (threshold alone for records from before they were stored). The samples are autocorrelated
timing series, not independent draws, so with thousands of them almost any shift is "significant": the
threshold does the real work; the test stops a few noisy samples from passing for a change. A timed phase
flagged for interference on either side (every attempt disturbed), or timed on an emulated device (qemu-user),
is not comparable: it cannot gate. Where
both records have a speed-up paired by round against their baseline (docs/metrics.md §5), p50 is judged on it
instead: drift of the machine between the two runs cancels in it, and it changes when the two speed-ups'
95 % intervals tell them apart (the difference of their logarithms beyond both half-widths combined), beyond
the p50 threshold. With `--remeasure` both sides' artifacts were timed again here in the same rounds, and p50
is judged on the new artifact's time ÷ its base twin's, paired by round: changed when its interval excludes 1,
beyond 5 % (REMEASURED_P50) unless the user gave a p50 threshold. Size and accuracy (deterministic) are
judged by their threshold alone.

Changes are relative ((new - base) / base) for p50, p99, throughput, size and error metrics where lower is
better (mse); absolute (new - base) for fractions where higher is better (top1, cosine_similarity). A
threshold is in its change's unit: a fraction of the base value, or an absolute difference.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import fisher_exact, mannwhitneyu

from bench_matrix.errors import UserError
from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE
from bench_matrix.measurement import Measurement, Speedup
from bench_matrix.report.analysis.summary import disturbed_phases, emulated, figure, headline
from bench_matrix.store import CellRecord

METRICS = ("p50", "p99", "throughput", "size", "accuracy")
# Default thresholds: beyond these a change counts (timed metrics also need significance). Unchanged cells
# measured twice on our shared 2-core machines move by up to ~15 % (p50, throughput) and more at p99
# (docs/results.md §3, benchmarks/compare_noise.py); tighten them on a quiet, dedicated machine.
DEFAULT_THRESHOLDS = {"p50": 0.20, "p99": 0.50, "throughput": 0.20, "size": 0.01}
# With --remeasure, p50 is the new artifact's time ÷ its base twin's paired by round: its interval does the
# work (a few % wide), and a change counts beyond this (benchmarks/gate_rates.py measured what it catches).
REMEASURED_P50 = 0.05
UNPAIRED = ("its twins shared fewer than 2 rounds free of windows a neighbour slowed: the machine was too "
            "busy to pair them; remeasure when it is quieter, or with more `timing_budget_s`")
DEFAULT_ACCURACY_THRESHOLDS = {"relative": 0.05, "absolute": 0.005}  # error metrics / fraction metrics
ALPHA = 0.05
TEST = "Mann-Whitney U (two-sided) for p50 and throughput, Fisher's exact test on the slowest 1 % for p99"
BETTER, WORSE, UNCHANGED, NOT_COMPARABLE = "better", "worse", "unchanged", "not comparable"
VERDICTS = (BETTER, WORSE, UNCHANGED, NOT_COMPARABLE)
# The cell's verdict is the first of these that any of its metrics has.
_CELL_ORDER = (WORSE, NOT_COMPARABLE, BETTER, UNCHANGED)
_THRESHOLD = re.compile(r"\s*([a-z0-9]+)\s*=\s*([0-9]*\.?[0-9]+(?:e[-+]?[0-9]+)?)\s*(%?)\s*", re.IGNORECASE)


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

    metric: str  # one of METRICS
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
class CellComparison:
    """One cell key on both sides: its metrics (none when it is on one side only or not ok on one), its
    verdict (the first of worse, not comparable, better, unchanged that a metric has) and notes."""

    key: str
    model: str
    label: str
    metrics: tuple[MetricChange, ...]
    verdict: str
    why: str | None = None  # why the whole cell is not comparable ("only in base", "failed in new")
    disturbed: tuple[str, ...] = ()  # "base: latency: why" for each side flagged for interference


@dataclass(frozen=True)
class Comparison:
    """Every cell of both sides (by model, then key) and the thresholds, alpha and test that judged them."""

    base: str
    new: str
    cells: tuple[CellComparison, ...]
    thresholds: Mapping[str, float]  # p50, p99, throughput, size, accuracy_relative, accuracy_absolute
    alpha: float
    test: str = TEST
    remeasured: bool = False  # the timed figures are from timing both sides' artifacts again, in rounds

    @property
    def regressions(self) -> list[tuple[str, str]]:
        """(cell key, metric) of every metric judged worse: a CI gate fails when this is not empty."""
        return [(c.key, m.metric) for c in self.cells for m in c.metrics if m.verdict == WORSE]

    def counts(self) -> dict[str, int]:
        """How many cells got each verdict."""
        return {verdict: sum(c.verdict == verdict for c in self.cells) for verdict in VERDICTS}


def parse_threshold(text: str) -> tuple[str, float]:
    """("p50", 0.1) from "p50=10%"; a plain number is the change itself ("accuracy=0.002"); else UserError."""
    match = _THRESHOLD.fullmatch(text)
    name = match.group(1).lower() if match else ""
    if not match or name not in METRICS:
        raise UserError(f"--threshold {text!r}: write METRIC=N% or METRIC=N (the change as a fraction, or "
                        f"for top1 and cosine_similarity an absolute difference), METRIC one of "
                        f"{', '.join(METRICS)}; e.g. --threshold p50=10% --threshold accuracy=0.002")
    value = float(match.group(2)) / (100 if match.group(3) else 1)
    if not math.isfinite(value):
        raise UserError(f"--threshold {text!r}: the value must be a finite number")
    return name, value


def effective_thresholds(thresholds: Mapping[str, float] | None) -> dict[str, float]:
    """The defaults overridden by `thresholds` (keys of METRICS; "accuracy" sets both accuracy kinds)."""
    given = dict(thresholds or {})
    unknown = sorted(set(given) - set(METRICS))
    if unknown:
        raise ValueError(f"unknown threshold metric(s) {', '.join(unknown)}; allowed: {', '.join(METRICS)}")
    merged = {**DEFAULT_THRESHOLDS, **{k: v for k, v in given.items() if k != "accuracy"}}
    for kind, default in DEFAULT_ACCURACY_THRESHOLDS.items():
        merged[f"accuracy_{kind}"] = given.get("accuracy", default)
    return merged


def compare(base: Side, new: Side, thresholds: Mapping[str, float] | None = None, alpha: float = ALPHA,
            tasks: Mapping[str, str] | None = None, twins: Mapping[str, Speedup] | None = None) -> Comparison:
    """Compare every cell key of `base` and `new`; `tasks` (model -> task) is used where a side has none;
    `twins`: each remeasured cell's base time ÷ new time, paired by round (then the sides are remeasured)."""
    limits = effective_thresholds(thresholds)
    limits["p50_remeasured"] = limits["p50"] if "p50" in (thresholds or {}) else REMEASURED_P50
    before, after = _by_key(base.records), _by_key(new.records)
    cells = []
    for key in sorted(set(before) | set(after), key=lambda k: ((before.get(k) or after[k]).cell.model, k)):
        pair = _Pair(base, new, before.get(key), after.get(key), tasks or {}, (twins or {}).get(key))
        cells.append(_compare_cell(key, pair, limits, alpha))
    return Comparison(base.label, new.label, tuple(cells), limits, alpha, remeasured=twins is not None)


def _by_key(records: Iterable[CellRecord]) -> dict[str, CellRecord]:
    found: dict[str, CellRecord] = {}
    for record in records:
        if record.cell.key in found:
            raise ValueError(f"two records of cell {record.cell.key} on one side of a comparison")
        found[record.cell.key] = record
    return found


@dataclass(frozen=True)
class _Pair:
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


def _compare_cell(key: str, pair: _Pair, limits: Mapping[str, float], alpha: float) -> CellComparison:
    record = pair.before or pair.after
    assert record is not None
    cell = record.cell
    why = _cell_problem(pair)
    if why:
        return CellComparison(key, cell.model, cell.label, (), NOT_COMPARABLE, why, _disturbed(pair))
    changes = (*_timings(pair, limits, alpha), _size(pair, limits), _accuracy(pair, limits))
    found = {c.verdict for c in changes}
    verdict = next((v for v in _CELL_ORDER if v in found), UNCHANGED)
    return CellComparison(key, cell.model, cell.label, changes, verdict, None, _disturbed(pair))


def _timings(pair: _Pair, limits: Mapping[str, float], alpha: float) -> tuple[MetricChange, ...]:
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


def _cell_problem(pair: _Pair) -> str | None:
    """Why none of the cell's metrics can be compared: on one side only, or not ok on a side."""
    if pair.after is None or pair.before is None:
        return "only in base" if pair.after is None else "only in new"
    for role, _, record in pair.roles():
        if record is not None and record.status != "ok":
            reason = headline(record.reason)
            return f"{record.status} in {role}" + (f": {reason}" if reason else "")
    return None


def _disturbed(pair: _Pair) -> tuple[str, ...]:
    """One note per side whose record was flagged for interference: its disturbed phases and why."""
    notes = []
    for role, _, record in pair.roles():
        phases = disturbed_phases(record) if record is not None else {}
        if phases:
            notes.append(f"{role}: " + " | ".join(f"{name}: {why}" for name, why in phases.items()))
    return tuple(notes)


def _phase_disturbed(pair: _Pair, phase: str) -> str | None:
    """Why a timed phase cannot be compared: flagged for interference on a side (every attempt disturbed)."""
    sides = [role for role, _, record in pair.roles() if record is not None and phase in disturbed_phases(record)]
    return f"{phase} measured under interference in {' and '.join(sides)} (re-run it on a quiet machine)" \
        if sides else None


def _values(pair: _Pair, name: str, read: Callable[[Measurement], Any]
            ) -> tuple[float | None, float | None, str | None]:
    """A figure (`name`, as `read`) of both records, and why it cannot be compared when a side lacks it (or it
    is not finite)."""
    base, new = (_finite(figure(record, read)) for record in pair.both())
    missing = [role for role, value in (("base", base), ("new", new)) if value is None]
    return base, new, f"no {name} in {' and '.join(missing)}" if missing else None


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _latency(pair: _Pair, which: str, limits: Mapping[str, float], alpha: float) -> MetricChange:
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


def _paired(pair: _Pair, limits: Mapping[str, float]) -> MetricChange | None:
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


def _twinned(pair: _Pair, limits: Mapping[str, float]) -> MetricChange | None:
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
    """Fisher's exact test, two-sided, on how many samples of each side lie above the pooled 99th percentile:
    whether the slowest 1 % come from one side more than chance allows (a shift of the median does not
    count; a handful of samples never reaches significance)."""
    tail = np.percentile(np.concatenate([before, after]), 99)
    above = [int(np.sum(before > tail)), int(np.sum(after > tail))]
    if sum(above) == 0:
        return 1.0
    table = [[above[0], len(before) - above[0]], [above[1], len(after) - above[1]]]
    return float(fisher_exact(table, alternative="two-sided").pvalue)


def _throughput(pair: _Pair, limits: Mapping[str, float], alpha: float) -> MetricChange:
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


def _size(pair: _Pair, limits: Mapping[str, float]) -> MetricChange:
    base, new, why = _values(pair, "size_bytes", lambda m: m.size.bytes)
    judge = _MetricJudge("size", "size_bytes", base, new, True, limits["size"], "lower")
    return judge.not_comparable(why) if why else judge.judged()


def _accuracy(pair: _Pair, limits: Mapping[str, float]) -> MetricChange:
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

