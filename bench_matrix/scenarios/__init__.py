"""Scenarios: what a measure job measures with a loaded session (base.py). `latency` runs for every cell;
those listed here are selected per cell by their own top-level matrix section."""

from __future__ import annotations

from functools import cache

from bench_matrix.named import resolve
from bench_matrix.scenarios.base import Scenario

SELECTABLE = ("bench_matrix.scenarios.closed_loop:ClosedLoop", "bench_matrix.scenarios.stream:Stream")


@cache
def selectable() -> tuple[Scenario, ...]:
    """One instance of each selectable scenario, in matrix order."""
    return tuple(resolve(entry)() for entry in SELECTABLE)
