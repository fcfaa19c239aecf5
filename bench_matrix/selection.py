"""Which cells a run takes: the filters of the command line, and this machine's shard of them."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import UserError
from bench_matrix.matrix.load import suggest


@dataclass(frozen=True)
class Filters:
    """Cell selection from the command line: each key keeps cells whose value is in the set."""

    values: dict[str, frozenset[str]] = field(default_factory=dict)

    def keep(self, cell: Cell) -> bool:
        return all(getattr(cell, key) in allowed for key, allowed in self.values.items())

    def check(self, cells: list[Cell]) -> None:
        """A filter value that no cell of the matrix has is a typo: say so, with what exists."""
        for key, wanted in self.values.items():
            present = sorted({getattr(c, key) for c in cells})
            for value in sorted(wanted - set(present)):
                raise UserError(f"--{key} {value}: no cell of the matrix has this {key}; it has "
                                f"{', '.join(present)}{suggest(value, present)}")


@dataclass(frozen=True)
class Shard:
    """Shard `index` of `count` (1-based): a contiguous block of the chosen cells sorted by key, so every
    machine given the same matrix and filters computes the same partition."""

    index: int = 1
    count: int = 1

    @classmethod
    def parse(cls, text: str) -> "Shard":
        """`I/N` with 1 <= I <= N; a UserError naming --shard and what is allowed otherwise."""
        found = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
        index, count = (int(found[1]), int(found[2])) if found else (0, 0)
        if not found or count < 1 or not 1 <= index <= count:
            raise UserError(f"--shard {text}: give I/N, this machine's shard I of N shards, whole numbers "
                            f"with 1 <= I <= N (e.g. --shard 1/4 ... --shard 4/4)")
        return cls(index, count)

    def select(self, cells: list[CellPlan]) -> list[CellPlan]:
        ordered = sorted(cells, key=lambda p: p.cell.key)
        n = len(ordered)
        begin, end = (self.index - 1) * n // self.count, self.index * n // self.count
        mine = {p.cell.key for p in ordered[begin:end]}
        return [p for p in cells if p.cell.key in mine]
