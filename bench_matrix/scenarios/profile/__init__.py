"""The profile scenario: cells selected by the matrix's `profile` section run one test sample under their
runtime's own profiler after the rounds (Session.profile); per operator its kind, precision and time go into
the record (docs/metrics.md, Profiles)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from bench_matrix.cell import Planned
from bench_matrix.matrix.load import Loading
from bench_matrix.scenarios.base import Scenario
from bench_matrix.scenarios.profile.spec import SCHEMA, ProfileSpec

if TYPE_CHECKING:
    from bench_matrix.cell import Cell
    from bench_matrix.matrix.spec import Matrix

AT = ("profile",)


@dataclass(frozen=True)
class ProfilePlan(Planned):
    """The profile part of a cell: how many calls are profiled."""

    name = "profile"
    function = "bench_matrix.scenarios.profile.run:run_profile"
    spec: ProfileSpec

    def fingerprint(self) -> dict[str, Any]:
        return {"profile": {"calls": self.spec.calls}}

    def describe(self) -> str:
        return f"{self.spec.calls} calls"

    def timed(self) -> bool:
        """Operator times are wall-clock figures: profiled under the timing lock, like the rounds."""
        return True


class Profiling(Scenario):
    """Per-operator profiles from the runtime's own profiler, after the latency scenario."""

    name = "profile"
    title = "profile"
    schema = SCHEMA
    section = "bench_matrix.scenarios.profile.plots:SECTION"

    def read(self, data: dict[str, Any], loading: Loading) -> ProfileSpec:
        """The typed section; a selector naming no axis value goes to `loading.report`."""
        return ProfileSpec(data.get("calls", ProfileSpec.calls), loading.selection(AT, data))

    def plan(self, section: ProfileSpec, matrix: Matrix, cell: Cell) -> ProfilePlan | None:
        """The cell's profile when the section selects it."""
        return ProfilePlan(section) if section.selection.selects(cell.as_dict()) else None
