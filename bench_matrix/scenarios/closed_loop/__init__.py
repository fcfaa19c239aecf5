"""The closed-loop scenario: cells selected by the matrix's `closed_loop` section drive laps in the built-in
simulator with their loaded session (docs/closed-loop.md)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.matrix.spec import LabelSpec, Matrix
from bench_matrix.cell import Planned
from bench_matrix.scenarios.base import Loading, Scenario
from bench_matrix.scenarios.closed_loop.section import closed_loop, drive_problem
from bench_matrix.scenarios.closed_loop.spec import SCHEMA, ClosedLoopSpec

if TYPE_CHECKING:
    from bench_matrix.cell import Cell
    from bench_matrix.report.plots import Plot
    from bench_matrix.report.summary import ModelSummary


@dataclass(frozen=True)
class ClosedLoopPlan(Planned):
    """The closed-loop part of a cell: the laps to drive and how the model's outputs become raw [v, w] (its
    dataset's label normalisation), or why its model cannot drive (`skip`)."""

    name = "closed_loop"
    function = "bench_matrix.scenarios.closed_loop.drive:drive_all"
    spec: ClosedLoopSpec
    labels: LabelSpec
    skip: str | None = None

    def fingerprint(self) -> dict[str, Any]:
        return {"drive": self.spec.drive_dict(), "skip": self.skip}

    def describe(self) -> str:
        """Circuits × modes, or why the cell cannot drive."""
        from rich.markup import escape

        if self.skip:
            return f"[yellow]not driven:[/] {escape(self.skip)}"
        return f"{', '.join(c.name for c in self.spec.circuits)} × {', '.join(self.spec.modes)}"


class ClosedLoop(Scenario):
    """Laps in the built-in driving simulator, after the latency scenario, with the same session."""

    name = "closed_loop"
    title = "closed loop"
    schema = SCHEMA

    def read(self, data: dict[str, Any], loading: Loading) -> ClosedLoopSpec:
        return closed_loop(data, loading)

    def plan(self, section: ClosedLoopSpec, matrix: Matrix, cell: Cell) -> ClosedLoopPlan | None:
        """The cell's laps when the section selects it (with why its model cannot drive, if so)."""
        if not section.selects(cell.as_dict()):
            return None
        model = matrix.model(cell.model)
        dataset = matrix.dataset_of(model)
        return ClosedLoopPlan(section, dataset.labels, drive_problem(model, dataset, matrix.task_of(model)))

    def markdown(self, model: ModelSummary, table: Any, escape: Any) -> list[str]:
        from bench_matrix.scenarios.closed_loop import report

        return report.markdown_lines(model, table, escape)

    def html(self, model: ModelSummary) -> list[str]:
        from bench_matrix.scenarios.closed_loop import report

        return report.html_parts(model)

    def terminal(self, model: ModelSummary, console: Any) -> None:
        from bench_matrix.scenarios.closed_loop import report

        report.print_terminal(model, console)

    def plots(self, model: ModelSummary, folder: Path) -> list[Plot]:
        from bench_matrix.scenarios.closed_loop.trajectories import trajectory_plots

        return trajectory_plots(model, folder)
