"""The verdict on the Pareto chart: cells that pass the requirements ringed in green, the recommended cell of
each target ringed twice; their legend entries and their marks in the cell key."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from bench_matrix.report.analysis.pareto import Point

GREEN = "#1a9641"
PASSES, RECOMMENDED = " ✓", " ★"
HEADER = "Verdict"


def draw(axes: Any, found: Sequence[Point], scale: float, area: Callable[[Point], float]) -> None:
    """A green ring around each passing cell (y values times `scale`), a second one around the recommended."""
    for chosen, grow, width in (([p for p in found if p.verdict == "pass"], 1.0, 1.3),
                                ([p for p in found if p.recommended], 2.2, 2.0)):
        if chosen:
            axes.scatter([p.latency_ms for p in chosen], [p.accuracy * scale for p in chosen],
                         s=[area(p) * (1.6 + grow) + 40 * grow for p in chosen], facecolors="none",
                         edgecolors=GREEN, linewidths=width, zorder=5)


def mark(point: Point) -> str:
    """The point's mark in the cell key: ★ recommended, ✓ passes, nothing otherwise."""
    return RECOMMENDED if point.recommended else PASSES if point.verdict == "pass" else ""


def note(found: Sequence[Point]) -> list[str]:
    """The key's note on the marks, when the cells were judged."""
    return [f"{PASSES.strip()} passes the requirements, {RECOMMENDED.strip()} recommended (green rings)"
            ] if any(p.verdict for p in found) else []


def legend_entries(found: Sequence[Point]) -> list[tuple[Any, str]]:
    """The legend's Verdict section, when the cells were judged."""
    from matplotlib.lines import Line2D

    if not any(p.verdict for p in found):
        return []
    ring = dict(linestyle="", marker="o", markerfacecolor="none", markeredgecolor=GREEN)
    return [(Line2D([], [], linestyle=""), HEADER),
            (Line2D([], [], markeredgewidth=1.3, markersize=9, **ring), "passes the requirements"),
            (Line2D([], [], markeredgewidth=2.0, markersize=13, **ring), "recommended (two rings)")]
