"""`compare`: per cell of two sets of records, the change of p50, p99, throughput, size and the task's
accuracy metric, each judged better / worse / unchanged / not comparable (metric_change.py judges each one).
Pure functions over stored results.

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
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from bench_matrix.errors import UserError
from bench_matrix.measurement import Speedup
from bench_matrix.report.analysis.metric_change import (
    BETTER,
    NOT_COMPARABLE,
    UNCHANGED,
    VERDICTS,
    WORSE,
    MetricChange,
    Pair,
    Side,
    accuracy_change,
    size_change,
    timing_changes,
)
from bench_matrix.report.analysis.summary import disturbed_phases, headline
from bench_matrix.store import CellRecord

METRICS = ("p50", "p99", "throughput", "size", "accuracy")
# Default thresholds: beyond these a change counts (timed metrics also need significance). Unchanged cells
# measured twice on our shared 2-core machines move by up to ~15 % (p50, throughput) and more at p99
# (docs/results.md §3, benchmarks/compare_noise.py); tighten them on a quiet, dedicated machine.
DEFAULT_THRESHOLDS = {"p50": 0.20, "p99": 0.50, "throughput": 0.20, "size": 0.01}
# With --remeasure, p50 is the new artifact's time ÷ its base twin's paired by round: its interval does the
# work (a few % wide), and a change counts beyond this (benchmarks/gate_rates.py measured what it catches).
REMEASURED_P50 = 0.05
DEFAULT_ACCURACY_THRESHOLDS = {"relative": 0.05, "absolute": 0.005}  # error metrics / fraction metrics
ALPHA = 0.05
TEST = "Mann-Whitney U (two-sided) for p50 and throughput, Fisher's exact test on the slowest 1 % for p99"
# The cell's verdict is the first of these that any of its metrics has.
_CELL_ORDER = (WORSE, NOT_COMPARABLE, BETTER, UNCHANGED)
_THRESHOLD = re.compile(r"\s*([a-z0-9]+)\s*=\s*([0-9]*\.?[0-9]+(?:e[-+]?[0-9]+)?)\s*(%?)\s*", re.IGNORECASE)


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
        pair = Pair(base, new, before.get(key), after.get(key), tasks or {}, (twins or {}).get(key))
        cells.append(_compare_cell(key, pair, limits, alpha))
    return Comparison(base.label, new.label, tuple(cells), limits, alpha, remeasured=twins is not None)


def _by_key(records: Iterable[CellRecord]) -> dict[str, CellRecord]:
    found: dict[str, CellRecord] = {}
    for record in records:
        if record.cell.key in found:
            raise ValueError(f"two records of cell {record.cell.key} on one side of a comparison")
        found[record.cell.key] = record
    return found


def _compare_cell(key: str, pair: Pair, limits: Mapping[str, float], alpha: float) -> CellComparison:
    record = pair.before or pair.after
    assert record is not None
    cell = record.cell
    why = _cell_problem(pair)
    if why:
        return CellComparison(key, cell.model, cell.label, (), NOT_COMPARABLE, why, _disturbed(pair))
    changes = (*timing_changes(pair, limits, alpha), size_change(pair, limits), accuracy_change(pair, limits))
    found = {c.verdict for c in changes}
    verdict = next((v for v in _CELL_ORDER if v in found), UNCHANGED)
    return CellComparison(key, cell.model, cell.label, changes, verdict, None, _disturbed(pair))


def _cell_problem(pair: Pair) -> str | None:
    """Why none of the cell's metrics can be compared: on one side only, or not ok on a side."""
    if pair.after is None or pair.before is None:
        return "only in base" if pair.after is None else "only in new"
    for role, _, record in pair.roles():
        if record is not None and record.status != "ok":
            reason = headline(record.reason)
            return f"{record.status} in {role}" + (f": {reason}" if reason else "")
    return None


def _disturbed(pair: Pair) -> tuple[str, ...]:
    """One note per side whose record was flagged for interference: its disturbed phases and why."""
    notes = []
    for role, _, record in pair.roles():
        phases = disturbed_phases(record) if record is not None else {}
        if phases:
            notes.append(f"{role}: " + " | ".join(f"{name}: {why}" for name, why in phases.items()))
    return tuple(notes)
