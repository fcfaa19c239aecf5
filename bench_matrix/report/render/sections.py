"""A scenario's part of each model's report (its Section, from stored records only), found through the
scenario that names it: the report owns this interface and draws its Blocks in every format."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from bench_matrix.named import resolve
from bench_matrix.registry import scenarios
from bench_matrix.report.analysis.summary import ModelSummary
from bench_matrix.report.render.columns import Column
from bench_matrix.report.render.plots import Plot


@dataclass(frozen=True)
class Block:
    """A titled part of a section: an intro, a table of items (each column renders one), lines after it;
    the terminal shows `brief`'s columns where given."""

    title: str
    intro: str
    columns: Sequence[Column]
    items: Sequence[Any]
    lines: Sequence[str] = ()
    level: int = 2  # its heading's: ## in Markdown, <h3> in HTML
    brief: Sequence[Column] | None = None

    def notes(self) -> list[tuple[str, str]]:
        """(headers, note) of the columns, those sharing a note together: 'a, b' and their note."""
        shared: dict[str, list[str]] = {}
        for column in self.columns:
            shared.setdefault(column.note, []).append(column.header.replace("\n", " "))
        return [(", ".join(headers), note) for note, headers in shared.items()]


@dataclass(frozen=True)
class Section:
    """A scenario's section of a model's report: its blocks and its plots (none by default)."""

    blocks: Callable[[ModelSummary], list[Block]] = lambda model: []
    plots: Callable[[ModelSummary, Path], list[Plot]] = lambda model, folder: []


def section_blocks(model: ModelSummary) -> list[Block]:
    """Every section's blocks of a model, in the scenarios' order."""
    return [block for section in sections() for block in section.blocks(model)]


def section_plots(model: ModelSummary, folder: Path) -> list[Plot]:
    """Every section's plots of a model with results, drawn into `folder`."""
    return [plot for section in sections() for plot in section.plots(model, folder)] if model.rows else []


@cache
def sections() -> tuple[Section, ...]:
    """The report section of each registered scenario that has one, in the scenarios' order."""
    return tuple(resolve(scenario.section) for scenario in scenarios() if scenario.section)
