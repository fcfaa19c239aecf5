"""The report's noise line, said once per report in every format, and its JSON: what analysis/noise.py
found, in words."""

from __future__ import annotations

import statistics
from collections.abc import Callable
from typing import Any

from bench_matrix.report.analysis.noise import MORE_BUDGET, Noise

DEVICE_CHECK = "bench-matrix device check"


def noise_line(found: Noise, code: Callable[[str], str] = lambda name: f"`{name}`") -> str:
    """The noise line; `code` formats a setting or a command."""
    spreads = (f"the window-to-window spread was {_span(found.spreads)} (median "
               f"{_percent(statistics.median(found.spreads))}, {len(found.spreads)} cells)")
    widths = ""
    if found.reached:
        widths = (f"; the widths reached ±{_span(found.reached)}; {MORE_BUDGET}× the "
                  f"{code('timing_budget_s')} would bring the widest to about "
                  f"±{_percent(found.widest_with_more)}")
    return f"Noise: {spreads}{widths}. How noisy this machine is: {code(DEVICE_CHECK)}."


def noise_json(found: Noise) -> dict[str, Any]:
    return {"window_spread": _summary(found.spreads), "reached": _summary(found.reached),
            "more_budget": MORE_BUDGET, "widest_with_more": found.widest_with_more,
            "device_check": DEVICE_CHECK, "line": noise_line(found)}


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
