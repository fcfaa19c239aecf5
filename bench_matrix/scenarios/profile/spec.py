"""The profile section's type and its fragment of the matrix schema (validated before it is read)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bench_matrix.matrix.schema import SELECTION
from bench_matrix.matrix.spec import Selection

MAX_CALLS = 10_000


@dataclass(frozen=True)
class ProfileSpec:
    """The `profile` section: which cells run their test sample under the runtime's own profiler after their
    rounds, and how many calls are profiled."""

    calls: int = 20
    selection: Selection = Selection()


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
