"""The verdict on a cell's measurement against its model's requirements (docs/results.md §8): pass; fail,
naming each requirement missed and by how much; uncertain where a timed figure's 95 % interval straddles its
limit. The report judges stored records by it, the rounds their figures so far."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from bench_matrix.matrix.requirements import TIMED, Limit, Requirements
from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE
from bench_matrix.measurement import Measurement
from bench_matrix.registry import scenarios

PASS, FAIL, UNCERTAIN = "pass", "fail", "uncertain"
MIB = 2**20
HEADLINE_NAMES = {"mse": "MSE", "top1": "top-1", "cosine_similarity": "cosine similarity"}
PLAUSIBLE = Limit("plausible", "max", 0.0)  # what an implausible record fails (report/analysis/plausible.py)


@dataclass(frozen=True)
class Check:
    """One requirement judged on one cell: status, the cell's figure, the bound held to (max_drop: the
    baseline's figure moved by the drop), what it says, and how far off it is (a fraction of the bound)."""

    limit: Limit
    status: str
    value: float | None
    bound: float | None
    text: str
    miss: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return {"requirement": self.limit.key, "status": self.status, "value": self.value,
                "limit": self.bound, "text": self.text}


@dataclass(frozen=True)
class Verdict:
    """A cell's verdict: fail when a requirement is missed, else uncertain when one straddles, else pass."""

    status: str
    checks: tuple[Check, ...]

    @property
    def failed(self) -> tuple[Check, ...]:
        return tuple(c for c in self.checks if c.status == FAIL)

    @property
    def uncertain(self) -> tuple[Check, ...]:
        return tuple(c for c in self.checks if c.status == UNCERTAIN)

    def short(self) -> str:
        """'pass', or the status and what each requirement missed or straddled says."""
        if self.status == PASS:
            return PASS
        named = self.failed if self.status == FAIL else self.uncertain
        return f"{self.status}: " + "; ".join(c.text for c in named)

    def to_json(self) -> dict[str, Any]:
        return {"status": self.status, "failed": [c.to_json() for c in self.failed],
                "uncertain": [c.to_json() for c in self.uncertain]}


def judge(metrics: Measurement, requirements: Requirements, task: str, baseline: Measurement | None,
          implausible: str | None = None) -> Verdict:
    """The verdict on an ok cell of a model of `task` whose ok baseline cell measured `baseline` (None: none);
    a cell whose record cannot be right (`implausible`: why) fails whatever it meets."""
    checks = tuple(_check(limit, metrics, task, baseline) for limit in requirements.limits)
    if implausible:
        checks += (Check(PLAUSIBLE, FAIL, None, None, f"implausible: {implausible}", math.inf),)
    status = FAIL if any(c.status == FAIL for c in checks) else \
        UNCERTAIN if any(c.status == UNCERTAIN for c in checks) else PASS
    return Verdict(status, checks)


def figure(key: str, m: Measurement) -> tuple[float | None, tuple[float, float] | None]:
    """The figure requirement `key` bounds and, for p50_ms and throughput_sps, its 95 % interval."""
    if key == "p50_ms":
        return _number(m.latency and m.latency.p50), _interval(m.latency and m.latency.p50_ci)
    if key == "p99_ms":
        return _number(m.latency and m.latency.p99), None
    if key == "throughput_sps":
        return _number(m.throughput.sps), _interval(m.throughput.ci)
    if key == "size_mib":
        size = _number(m.size.bytes)
        return (None if size is None else size / MIB), None
    if key == "peak_rss_mib":
        return _number(m.memory.peak_rss_mb), None
    scenario, _, name = key.partition(".")
    for found in scenarios():
        if found.name == scenario and name in found.requirements:
            return _number(found.figure(name, m)), None
    return _number(m.figure(key)), None


def _check(limit: Limit, m: Measurement, task: str, baseline: Measurement | None) -> Check:
    if limit.bound == "drop":
        return _drop(limit, m, task, baseline)
    value, interval = figure(limit.key, m)
    interval = interval if limit.key in TIMED else None
    return bounded(limit, value, interval, limit.value, limit.bound, limit.key)


def bounded(limit: Limit, value: float | None, interval: tuple[float, float] | None, bound: float, side: str,
            name: str) -> Check:
    """`value` held to at most (`side` "max") or at least ("min") `bound`; with an `interval`, uncertain
    when it straddles the bound."""
    if value is None:
        return Check(limit, FAIL, None, bound, f"{name} not measured", math.inf)
    sign = 1.0 if side == "max" else -1.0
    over = sign * (value - bound)
    miss = over / abs(bound) if bound else over
    low, high = interval if interval is not None else (value, value)
    worst, best = (high, low) if side == "max" else (low, high)
    if sign * (worst - bound) <= 0:
        sign_text = "≤" if side == "max" else "≥"
        return Check(limit, PASS, value, bound, f"{name} {_g(value)} {sign_text} {_g(bound)}")
    if sign * (best - bound) > 0:
        word = "over" if side == "max" else "under"
        amount = f"{_percent(abs(miss))} {word}" if bound else f"{_g(abs(over))} {word}"
        return Check(limit, FAIL, value, bound, f"{name} {_g(value)} {'>' if side == 'max' else '<'} "
                                                f"{_g(bound)} ({amount})", max(miss, 0.0))
    return Check(limit, UNCERTAIN, value, bound, f"{name} {_g(value)}, 95 % interval {_g(low)}–{_g(high)} "
                                                 f"straddles {_g(bound)}", max(miss, 0.0))


def _drop(limit: Limit, m: Measurement, task: str, baseline: Measurement | None) -> Check:
    """The task's headline metric at most `limit` worse than the baseline's: for an error (MSE) a relative or
    absolute increase, for a score (top-1, cosine similarity) a relative or absolute decrease."""
    key = HEADLINE.get(task, HEADLINE["none"])
    name = HEADLINE_NAMES.get(key, key)
    base = _number(baseline.figure(key)) if baseline is not None else None
    if base is None and task == "none":
        base = 1.0  # fidelity to the fp32 outputs: 1 is identical
    if base is None:
        return Check(limit, FAIL, _number(m.figure(key)), None,
                     f"max_drop: no baseline {name} to compare with", math.inf)
    lower = DIRECTIONS[key] == "lower"
    step = abs(base) * limit.value if limit.relative else limit.value
    allowed = base + step if lower else base - step
    check = bounded(limit, _number(m.figure(key)), None, allowed, "max" if lower else "min", name)
    if check.value is None or check.status == PASS:
        return check
    change = check.value - base
    said = f"{change / abs(base) * 100:+.1f} %" if limit.relative and base else f"{change:+.3g}"
    most = f"{limit.value * 100:g} %" if limit.relative else f"{limit.value:g}"
    text = f"{name} {said} vs the baseline's {_g(base)} (max_drop {'+' if lower else '-'}{most})"
    return Check(limit, check.status, check.value, allowed, text, check.miss)


def _number(value: Any) -> float | None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    return float(value) if ok else None


def _interval(value: Sequence[float] | None) -> tuple[float, float] | None:
    if isinstance(value, list | tuple) and len(value) == 2 and all(_number(v) is not None for v in value):
        return float(value[0]), float(value[1])
    return None


def _percent(fraction: float) -> str:
    """'24 %', '2.5 %': whole percent from 10 %, else one decimal."""
    return f"{fraction * 100:.0f} %" if fraction >= 0.1 else f"{fraction * 100:.1f} %"


def _g(value: float) -> str:
    return f"{value:.3g}"
