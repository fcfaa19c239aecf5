"""How noisy the machine was during a report's rounds (docs/results.md §9): the window-to-window spread the
rounds measured, the widths they reached, and what more budget would buy (render/noise_line.py says it)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from bench_matrix.report.analysis.summary import Report, number

MORE_BUDGET = 4  # times the timing budget the line prices: widths shrink as 1/√rounds, so 4× halves them


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
