"""A scenario's part of each model's report (its Section, from stored records only), found through the
scenario that names it: the report owns this interface, a scenario's report module makes one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from bench_matrix.named import resolve
from bench_matrix.registry import scenarios
from bench_matrix.report.analysis.summary import ModelSummary
from bench_matrix.report.render.plots import Plot


@dataclass(frozen=True)
class Section:
    """A scenario's section of a model's report: each format's part (none by default)."""

    markdown: Callable[[ModelSummary, Any, Any], list[str]] = lambda model, table, escape: []
    html: Callable[[ModelSummary], list[str]] = lambda model: []
    terminal: Callable[[ModelSummary, Any], None] = lambda model, console: None
    plots: Callable[[ModelSummary, Path], list[Plot]] = lambda model, folder: []


def section_plots(model: ModelSummary, folder: Path) -> list[Plot]:
    """Every section's plots of a model with results, drawn into `folder`."""
    return [plot for section in sections() for plot in section.plots(model, folder)] if model.rows else []


@cache
def sections() -> tuple[Section, ...]:
    """The report section of each registered scenario that has one, in the scenarios' order."""
    return tuple(resolve(scenario.section) for scenario in scenarios() if scenario.section)
