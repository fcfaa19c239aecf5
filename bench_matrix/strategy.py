"""A strategy as the matrix declares it: one kind with its options, or named steps applied in order; the value
backends, trainers and cells share."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

QAT_KINDS = ("qat", "cqat", "pqat", "pcqat")  # training kinds whose result carries learned int8 ranges


@dataclass(frozen=True)
class StrategySpec:
    """A strategy: one kind with its options, or a combination of named steps."""

    name: str
    kind: str | None
    options: dict[str, Any] = field(default_factory=dict)
    steps: tuple["StrategySpec", ...] = ()

    def kinds(self) -> tuple[str, ...]:
        """Kinds applied in order (a single kind, or each step's kinds)."""
        if self.steps:
            return tuple(k for step in self.steps for k in step.kinds())
        return (self.kind,) if self.kind else ()

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind, "options": dict(sorted(self.options.items())),
                "steps": [s.to_dict() for s in self.steps]}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "StrategySpec":
        return cls(name=data["name"], kind=data["kind"], options=dict(data.get("options") or {}),
                   steps=tuple(cls.from_dict(s) for s in data.get("steps") or ()))
