"""The profile section's type and its fragment of the matrix schema (validated before it is read)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bench_matrix.matrix.schema import SELECTION
from bench_matrix.matrix.spec import Selector

MAX_CALLS = 10_000


@dataclass(frozen=True)
class ProfileSpec:
    """The `profile` section: which cells run their test sample under the runtime's own profiler after their
    rounds, and how many calls are profiled."""

    calls: int = 20
    cells: tuple[Selector, ...] | None = None  # None: every cell
    exclude: tuple[Selector, ...] = ()

    def selects(self, cell: dict[str, str]) -> bool:
        """True when the cell (as a dict) is among `cells` and not excluded."""
        chosen = self.cells is None or any(s.matches(cell) for s in self.cells)
        return chosen and not any(s.matches(cell) for s in self.exclude)


SCHEMA: dict[str, Any] = {
    "type": "object", "additionalProperties": False,
    "description": "per-operator profiles from each runtime's own profiler, after the rounds "
                   "(docs/metrics.md)",
    "properties": {
        "calls": {"type": "integer", "minimum": 1, "maximum": MAX_CALLS,
                  "description": "profiled calls of one test sample, after one unprofiled call (default 20)"},
        **SELECTION,
    },
}
