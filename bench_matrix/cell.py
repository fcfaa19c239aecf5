"""A cell: one model through one backend with one strategy, precision and target."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

PlanState = Literal["run", "skip", "invalid"]


@dataclass(frozen=True, order=True)
class Cell:
    """The coordinates of one measurement."""

    model: str
    framework: str
    backend: str
    strategy: str
    precision: str
    target: str

    @property
    def key(self) -> str:
        return "/".join((self.model, self.backend, self.strategy, self.precision, self.target))

    def as_dict(self) -> dict[str, str]:
        return asdict(self)

    @property
    def label(self) -> str:
        """Short method name for tables: backend strategy precision [target]."""
        parts = [self.backend, self.strategy, self.precision]
        return " ".join(parts + ([] if self.target == "cpu" else [self.target]))


@dataclass(frozen=True)
class PlannedCell:
    """A cell and what `run` will do with it: run it, skip it (why), or reject it as invalid (why)."""

    cell: Cell
    state: PlanState
    reason: str | None = None
