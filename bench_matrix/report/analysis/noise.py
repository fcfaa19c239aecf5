"""How noisy the machine was during a report's rounds, said once per report (docs/results.md §9): the
window-to-window spread the rounds measured, the widths they reached, and what more budget would buy."""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bench_matrix.report.analysis.summary import Report, number

MORE_BUDGET = 4  # times the timing budget the line prices: widths shrink as 1/√rounds, so 4× halves them
DEVICE_CHECK = "bench-matrix device check"


@dataclass(frozen=True)
class Noise:
    """The spreads (relative, 0.012 = 1.2 %) of the ok cells that carry one, and the interval half-widths
    reached by those that carry one, each sorted."""

    spreads: tuple[float, ...]
    reached: tuple[float, ...]

    @property
    def widest_with_more(self) -> float | None:
        """The widest width reached, had the rounds had MORE_BUDGET times the budget."""
        return self.reached[-1] / math.sqrt(MORE_BUDGET) if self.reached else None

    def text(self, code: Callable[[str], str] = lambda name: f"`{name}`") -> str:
        """The noise line; `code` formats a setting or a command."""
        spreads = (f"the window-to-window spread was {_span(self.spreads)} (median "
                   f"{_percent(statistics.median(self.spreads))}, {len(self.spreads)} cells)")
        widths = ""
        if self.reached:
            widths = (f"; the widths reached ±{_span(self.reached)}; {MORE_BUDGET}× the "
                      f"{code('timing_budget_s')} would bring the widest to about "
                      f"±{_percent(self.widest_with_more)}")
        return f"Noise: {spreads}{widths}. How noisy this machine is: {code(DEVICE_CHECK)}."

    def to_json(self) -> dict[str, Any]:
        return {"window_spread": _summary(self.spreads), "reached": _summary(self.reached),
                "more_budget": MORE_BUDGET, "widest_with_more": self.widest_with_more,
                "device_check": DEVICE_CHECK, "line": self.text()}


def noise(report: Report) -> Noise | None:
    """The report's noise over its ok cells; None when no cell's rounds measured a window spread."""
    facts = [row.record.metrics.rounds.to_json() for model in report.models for row in model.rows
             if row.record.metrics.rounds is not None]
    spreads = _sorted(fact.get("window_spread") for fact in facts)
    if not spreads:
        return None
    return Noise(spreads, _sorted(fact.get("reached") for fact in facts))


def _sorted(values: Any) -> tuple[float, ...]:
    return tuple(sorted(v for v in map(number, values) if v is not None and math.isfinite(v) and v >= 0))


def _summary(values: tuple[float, ...]) -> dict[str, Any] | None:
    if not values:
        return None
    return {"low": values[0], "median": statistics.median(values), "high": values[-1], "cells": len(values)}


def _span(values: tuple[float, ...]) -> str:
    """'0.8–3.1 %', or '1.2 %' when they are all one."""
    low, high = _percent(values[0]), _percent(values[-1])
    return low if low == high else f"{low.removesuffix(' %')}–{high}"


def _percent(fraction: float | None) -> str:
    return "—" if fraction is None else f"{fraction * 100:.1f} %"
