"""The recommendation for each model and target (docs/results.md §8): the best passing cell by the
objective, the runner-up and whether their interval tells them apart; when nothing passes, the cells closest
to passing."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from bench_matrix.measurement import Measurement
from bench_matrix.ranking import compare, rank, speedups
from bench_matrix.store import CellRecord
from bench_matrix.verdict import FAIL, PASS, UNCERTAIN, Verdict

CLOSEST = 3  # cells listed as closest to passing when none passes


@dataclass(frozen=True)
class Candidate:
    """An ok cell with its verdict; `baseline`: the model's baseline cell (its paired speed-up is 1)."""

    record: CellRecord
    verdict: Verdict
    baseline: bool = False

    @property
    def key(self) -> str:
        return self.record.cell.key

    @property
    def metrics(self) -> Measurement:
        return self.record.metrics


@dataclass(frozen=True)
class Recommendation:
    """Per model, target (and host): best passing cell by `objective`, runner-up, `ratio` times better, 95 %
    `ratio_ci` (`distinguishable`: excludes 1; None: none), `closest` (none passes), `failed` (unjudged)."""

    model: str
    target: str
    host: str | None
    objective: str
    passing: int
    judged: int
    best: CellRecord | None = None
    runner_up: CellRecord | None = None
    ratio: float | None = None
    ratio_ci: tuple[float, float] | None = None
    distinguishable: bool | None = None
    closest: tuple[Candidate, ...] = ()
    failed: int = 0

    @property
    def passing_text(self) -> str:
        """'9 of 11, 2 failed': the passing cells of every cell that ran here, failed ones included."""
        said = f"{self.passing} of {self.judged + self.failed}"
        return said + (f", {self.failed} failed" if self.failed else "")

    def to_json(self) -> dict[str, Any]:
        return {"model": self.model, "target": self.target, "host": self.host, "objective": self.objective,
                "cell": _key(self.best), "runner_up": _key(self.runner_up),
                "distinguishable": self.distinguishable,
                "ratio": self.ratio, "ratio_ci": list(self.ratio_ci) if self.ratio_ci else None,
                "passing": self.passing, "judged": self.judged, "failed": self.failed,
                "closest": [{"cell": c.record.cell.key, **c.verdict.to_json()} for c in self.closest]}


def recommend(model: str, candidates: Sequence[Candidate], failed: Iterable[CellRecord], objective: str
              ) -> tuple[Recommendation, ...]:
    """One recommendation per target and host the model's cells ran on (ok or failed), in that order."""
    groups: dict[tuple[str, str | None], list[Candidate]] = {}
    failures: dict[tuple[str, str | None], int] = {}
    for record in failed:
        groups.setdefault(where := (record.cell.target, record.host), [])
        failures[where] = failures.get(where, 0) + 1
    for candidate in candidates:
        groups.setdefault((candidate.record.cell.target, candidate.record.host), []).append(candidate)
    return tuple(_group(model, *where, groups[where], objective, failures.get(where, 0))
                 for where in sorted(groups, key=lambda g: (g[0], g[1] or "")))


def _group(model: str, target: str, host: str | None, found: list[Candidate], objective: str, failed: int
           ) -> Recommendation:
    passing = [c for c in found if c.verdict.status == PASS]
    made = Recommendation(model, target, host, objective, len(passing), len(found), failed=failed)
    if not passing:
        return replace(made, closest=closest(found))
    ranked = rank(passing, objective)
    if len(ranked) == 1:
        return replace(made, best=ranked[0].record)
    ratio, half = compare(ranked[0], ranked[1], objective, speedups(passing))
    known = ratio is not None and half is not None
    return replace(made, best=ranked[0].record, runner_up=ranked[1].record, ratio=ratio,
                   ratio_ci=(ratio * math.exp(-half), ratio * math.exp(half)) if known else None,
                   distinguishable=abs(math.log(ratio)) > half if known else None)


def closest(found: Sequence[Candidate]) -> tuple[Candidate, ...]:
    """The cells closest to passing: uncertain first, then fewest requirements missed, then the smallest
    miss."""
    def distance(c: Candidate) -> tuple[int, int, float, str]:
        misses = [check.miss for check in c.verdict.failed]
        return (c.verdict.status != UNCERTAIN, len(misses), sum(misses), c.record.cell.key)
    return tuple(sorted((c for c in found if c.verdict.status in (FAIL, UNCERTAIN)), key=distance)[:CLOSEST])


def _key(record: CellRecord | None) -> str | None:
    return None if record is None else record.cell.key
