"""The closed-loop scenario: cells selected by the matrix's `closed_loop` section drive laps in the built-in
simulator with their loaded session (docs/closed-loop.md)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from bench_matrix.matrix.spec import LabelSpec, Matrix
from bench_matrix.cell import Planned
from bench_matrix.matrix.load import Loading
from bench_matrix.scenarios.base import Scenario
from bench_matrix.scenarios.closed_loop.section import closed_loop, drive_problem
from bench_matrix.scenarios.closed_loop.spec import SCHEMA, ClosedLoopSpec, MarginsSpec

MARGIN_FIGURES = {"latency_margin_ms": "latency", "speed_margin": "speed", "perception_margin": "perception"}

if TYPE_CHECKING:
    from bench_matrix.cell import Cell
    from bench_matrix.measurement import Measurement


@dataclass(frozen=True)
class ClosedLoopPlan(Planned):
    """The closed-loop part of a cell: the laps to drive and how the model's outputs become raw [v, w] (its
    dataset's label normalisation), or why its model cannot drive (`skip`)."""

    name = "closed_loop"
    function = "bench_matrix.scenarios.closed_loop.drive:drive_all"
    spec: ClosedLoopSpec
    labels: LabelSpec
    skip: str | None = None
    margins: MarginsSpec | None = None  # the margins this cell searches (None: none)

    def fingerprint(self) -> dict[str, Any]:
        searched = {"margins": self.margins.search_dict()} if self.margins else {}
        return {"drive": self.spec.drive_dict(), "skip": self.skip, **searched}

    def describe(self) -> str:
        """Circuits × modes, or why the cell cannot drive."""
        from rich.markup import escape

        if self.skip:
            return f"[yellow]not driven:[/] {escape(self.skip)}"
        laps = f"{', '.join(c.name for c in self.spec.circuits)} × {', '.join(self.spec.modes)}"
        margins = ", ".join(m.kind for m in self.margins.searches) if self.margins else ""
        return f"{laps}; margins: {margins}" if margins else laps

    def timed(self) -> bool:
        """Real-time laps run on the wall clock."""
        return not self.skip and "real_time" in self.spec.modes


class ClosedLoop(Scenario):
    """Laps in the built-in driving simulator, after the latency scenario, with the same session."""

    name = "closed_loop"
    title = "closed loop"
    schema = SCHEMA
    requirements = {"completed_pct": ("min", "completed % of the cell's worst lap"),
                    "deviation_mae_m": ("max", "mean deviation from the reference line of the worst lap, m"),
                    "brain_hz": ("min", "achieved brain rate of the slowest lap, Hz"),
                    **{figure: ("min", f"{kind} margin on the cell's hardest margin circuit")
                       for figure, kind in MARGIN_FIGURES.items()}}
    section = "bench_matrix.scenarios.closed_loop.trajectories:SECTION"

    def read(self, data: dict[str, Any], loading: Loading) -> ClosedLoopSpec:
        return closed_loop(data, loading)

    def plan(self, section: ClosedLoopSpec, matrix: Matrix, cell: Cell) -> ClosedLoopPlan | None:
        """The cell's laps when the section selects it (with why its model cannot drive, if so)."""
        if not section.selection.selects(cell.as_dict()):
            return None
        model = matrix.model(cell.model)
        dataset = matrix.dataset_of(model)
        margins = section.margins
        searched = margins if margins and margins.selection.selects(cell.as_dict()) else None
        return ClosedLoopPlan(section, dataset.labels, drive_problem(model, dataset, matrix.task_of(model)),
                              searched)

    def figure(self, key: str, metrics: Measurement) -> float | None:
        """The worst lap's figure (every circuit and mode), or the smallest margin of every margin circuit;
        None when a lap lacks it (it failed) or none ran, or a margin was not searched or failed at once."""
        if key in MARGIN_FIGURES:
            return smallest_margin(metrics.others.get("closed_loop_margins"), MARGIN_FIGURES[key])
        driven = metrics.others.get("closed_loop")
        laps = [lap for modes in driven.values() if isinstance(modes, dict) for lap in modes.values()
                ] if isinstance(driven, dict) else []
        values = [lap.get(key) if isinstance(lap, dict) else None for lap in laps]
        if not values or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
            return None
        return float(max(values) if self.requirements[key][0] == "max" else min(values))


def smallest_margin(searched: Any, kind: str) -> float | None:
    """The smallest `kind` margin over the circuits searched (a lower bound where it passed at the limit);
    None when a circuit lacks it or failed even unchanged."""
    answers = [margins.get(kind) for margins in searched.values() if isinstance(margins, dict)
               ] if isinstance(searched, dict) else []
    values = [a.get("value") if isinstance(a, dict) else None for a in answers]
    if not values or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return None
    return float(min(values))
