"""The latency scenario's timed figures, made where the rounds ran (the executor's process) from a cell's
windows: pooled percentiles, intervals from the rounds, the paired speed-up, and why a figure is marked
(docs/metrics.md §5)."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from bench_matrix.measure.interference import Limits
from bench_matrix.measure.rounds import Interval, Level, Slot, Spread, level_width, moderated, p50_interval
from bench_matrix.measure.rounds import log_levels, process_spread, rate_interval, steady, window_spread
from bench_matrix.measure.schedule import LATENCY, RoundsSettings, Timed, Window, paired, rates
from bench_matrix.measure.stats import latency_summary, pack_samples

E2E, THROUGHPUT = "latency_e2e", "throughput"
MANY_ROUNDS_T = 1.96  # the 95 % t-quantile the intervals tend to as rounds are added
SERIES = {LATENCY: "latency_ms", E2E: "latency_ms_e2e"}  # latency kinds -> their record field
SAMPLED = {LATENCY: "latency_ms", E2E: "latency_ms_e2e", THROUGHPUT: "batch_ms"}  # kind -> stored raw series


def figures(timed: Timed, baseline: Timed | None, settings: RoundsSettings, limits: Limits,
            spreads: Mapping[str, Spread | None]) -> dict[str, Any]:
    """The cell's timed record fields from its rounds (`baseline`: for the paired speed-up, None for itself or
    none; `spreads`: the model's pooled process spread by kind); cheap every round: medians cached."""
    series = {kind: found for kind in SAMPLED if (found := timed.series(kind))}
    fields: dict[str, Any] = {name: _latency(series[kind], spreads.get(kind), timed.levels(kind))
                              for kind, name in SERIES.items() if kind in series}
    fields.update(_throughput(timed.windows(THROUGHPUT), spreads.get(THROUGHPUT)))
    model = spreads.get(LATENCY)
    ratio = paired(baseline, timed, model) if baseline is not None and baseline is not timed else None
    if ratio is not None:
        fields["speedup"] = _rounded(ratio.as_dict())
    fields["rounds"], reached = _rounds(timed, settings, series.get(LATENCY, {}), model, ratio)
    fields["interference"] = _interference(timed, settings, limits, reached)
    return fields


def raw_samples(timed: Timed) -> dict[str, bytes]:
    """The record's raw series: every kept window's calls of each sampled kind, packed (once, at the end)."""
    return {name: pack_samples(np.concatenate(list(found.values())) * 1e6)
            for kind, name in SAMPLED.items() if (found := timed.series(kind))}


def _rounds(timed: Timed, settings: RoundsSettings, series: dict[Slot, np.ndarray], model: Spread | None,
            ratio: Interval | None) -> tuple[dict[str, Any], Width | None]:
    """The record's `rounds` (count, why stopped, precision asked, width reached: wider of p50 and speed-up,
    open answer, processes and spread, window-to-window spread, `strayed` windows), width reached, floor."""
    every = log_levels(timed.medians(LATENCY))
    levels = steady(every)
    own, noise = moderated(process_spread(levels), model), window_spread(levels)
    processes = len({j for _, j in timed.windows(LATENCY)})
    p50 = p50_interval(series, model, timed.levels(LATENCY))
    spread = own.relative if own else 0.0
    widths = [Width(level_width(p50), _floor(processes, own), spread) if p50 else None,
              Width(ratio.half_width, _floor(processes, own, model), spread) if ratio else None]
    reached = max((w for w in widths if w is not None), key=lambda w: w.reached, default=None)
    return ({"rounds": timed.rounds(), "stop": timed.stop, "target": settings.target, "asked": settings.asked,
             "reached": round(reached.reached, 6) if reached else None, "open": timed.open,
             "window_spread": round(noise, 6) if noise is not None else None, "window_s": settings.window_s,
             "processes": processes, "visits": round(timed.visits(), 3), "strayed": len(every) - len(levels),
             "process_spread": round(spread, 6) if own else None,
             "model_spread": round(model.relative, 6) if model else None}, reached)


@dataclass(frozen=True)
class Width:
    """An interval's half-width reached (as the rounds' target counts it), and how narrow more rounds could
    make it: what the processes' lifetime differences (the cell's `spread`, relative) alone leave."""

    reached: float
    floor: float
    spread: float


def _floor(processes: int, *spreads: Spread | None) -> float:
    """The half-width the processes' parts alone give (each spread ÷ the processes; the baseline's taken as
    the model's), at the t-quantile of many rounds."""
    parts = [s.variance / processes for s in spreads if s is not None and s.variance > 0 and processes > 1]
    return MANY_ROUNDS_T * math.sqrt(sum(parts))


def _latency(series: dict[Slot, np.ndarray], model: Spread | None, levels: Mapping[Slot, Level]
             ) -> dict[str, Any]:
    """Percentiles of every kept window pooled; the interval a rerun's p50 falls in, from the spread of the
    per-round medians (the windows' `levels`) and of the processes."""
    summary = latency_summary(np.concatenate(list(series.values())) * 1e6)
    interval = p50_interval(series, model, levels)
    if interval is not None:
        summary.update(p50_ci=[interval.low, interval.high],
                       p50_ci_rel=(interval.high - interval.low) / summary["p50"])
    return {**summary, "rounds": len({r for r, _ in series})}


def _throughput(windows: dict[Slot, Window], model: Spread | None) -> dict[str, Any]:
    """Samples per second over the throughput windows, with the interval of the per-window rates."""
    if not windows:
        return {}
    batches = sum(len(w.durations_ms) for w in windows.values())
    seconds = sum(float(w.durations_ms.sum()) for w in windows.values()) / 1e3
    samples = sum(w.samples * len(w.durations_ms) for w in windows.values())
    interval = rate_interval(rates(windows), samples, seconds, model)
    found: dict[str, Any] = {"throughput_sps": samples / seconds, "throughput_batches": batches}
    if interval is not None:
        found["throughput_ci"] = [interval.low, interval.high]
    return found


def _interference(timed: Timed, settings: RoundsSettings, limits: Limits,
                  reached: Width | None) -> dict[str, Any]:
    """Flagged when over `settings.disturbed_share` of a kind's windows were disturbed; each kind's windows,
    those dropped, and why a figure is marked (disturbed, or its interval wider than the target)."""
    phases = {}
    for kind in (*SERIES, THROUGHPUT):
        total, dropped = timed.count(kind)
        if not total:
            continue
        why = Counter(w.disturbed for w in timed.dropped.get(kind, {}).values()).most_common(1)
        disturbed = (f"{dropped} of {total} windows disturbed (limit {settings.disturbed_share:.0%}): "
                     f"{why[0][0]}" if dropped > settings.disturbed_share * total else None)
        phases[kind] = {"windows": total, "dropped": dropped, "disturbed": disturbed,
                        "wide": _wide(timed, settings, reached) if kind == LATENCY else None}
    reasons = [f"{kind}: {phase['disturbed']}" for kind, phase in phases.items() if phase["disturbed"]]
    return {"flagged": bool(reasons), "reason": " | ".join(reasons) or None, "limits": asdict(limits),
            "phases": phases}


def _wide(timed: Timed, settings: RoundsSettings, reached: Width | None) -> str | None:
    """Why latency figures stayed wider than the user's target and what would narrow them (not for a cell
    leaving the rounds narrow: its final width pools every cell's process spread); None if no target asked."""
    narrow = timed.stop == "width" or (reached is not None and reached.reached <= settings.target)
    if not settings.asked or narrow:
        return None
    width = f"±{reached.reached:.1%}" if reached is not None else "no interval"
    ended = {"budget": "the time budget was spent", "rounds": "the most rounds were run"}.get(timed.stop,
                                                                                              timed.stop)
    return (f"known to {width} after {timed.rounds()} rounds (target ±{100 * settings.target:g}%; "
            f"{ended}){_narrower(reached, settings.target)}")


def _narrower(reached: Width | None, target: float) -> str:
    """What would reach the target: more rounds (about how many times as many: the rounds' part of the
    width shrinks as 1/√rounds) or, where the processes' part alone is wider, more processes."""
    if reached is None:
        return ""
    if reached.floor >= target:
        return (f": its processes differed by {reached.spread:.1%}, which alone keeps it wider than "
                f"±{reached.floor:.1%} however many rounds; more processes a cell (`processes`) would "
                "narrow it")
    times = (reached.reached ** 2 - reached.floor ** 2) / (target ** 2 - reached.floor ** 2)
    if times < 1.1:
        return ": a few more rounds would reach it (`timing_budget_s`)"
    return f": about {times:.1f} times the rounds would reach it (`timing_budget_s`)"


def _rounded(found: dict[str, Any]) -> dict[str, Any]:
    return {k: [round(x, 6) for x in v] if isinstance(v, list) else v for k, v in found.items()}
