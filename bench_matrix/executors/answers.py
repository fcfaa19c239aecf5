"""What a model's rounds are for (docs/metrics.md §5): each cell's verdict against the model's requirements
and the recommendation by its objective, judged on its figures so far (its accuracy, size and memory measured
before its rounds). A cell whose verdict is uncertain, and the leader with the cells not yet told apart from
it, keep the budget; the others leave once their figures reach the loose precision."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any

from bench_matrix.jobs import RoundsJob
from bench_matrix.matrix.requirements import Requirements
from bench_matrix.measure.interference import LIMITS
from bench_matrix.measure.schedule import LATENCY, RoundsSettings, Timed, spread
from bench_matrix.measurement import Measurement
from bench_matrix.ranking import Ranked, compare, rank, speedups
from bench_matrix.registry import scenarios
from bench_matrix.scenarios.timed import SAMPLED, THROUGHPUT, figures
from bench_matrix.verdict import PASS, UNCERTAIN, judge

APART = 1.5  # the leader leaves once its ratio to a cell is beyond 1.5 times the 95 % interval's half-width:
# judged after every round, a 95 % interval alone would part two equal cells by chance


@dataclass(frozen=True)
class Entry:
    """A cell as the rounds know it so far, to rank (bench_matrix.ranking.Ranked)."""

    key: str
    metrics: Measurement
    baseline: bool


class OpenAnswers:
    """The answers still open among a model's cells of `task` (`baseline`: its key; `references`: a cell's
    speed-up paired against another); `evaluated`: each cell's pre-rounds fields, filled as sessions open."""

    def __init__(self, requirements: Requirements, task: str, baseline: str | None, settings: RoundsSettings,
                 evaluated: Mapping[str, dict[str, Any]], references: Mapping[str, str] | None = None):
        self.requirements, self.task, self.baseline = known(requirements), task, baseline
        self.references, self.settings, self.evaluated = dict(references or {}), settings, evaluated

    @classmethod
    def of(cls, job: RoundsJob, settings: RoundsSettings, evaluated: Mapping[str, dict[str, Any]]
           ) -> OpenAnswers:
        """The answers a rounds job's requirements ask."""
        return cls(job.requirements or Requirements(), job.cells[0].task, job.baseline, settings, evaluated,
                   dict(job.references))

    def open(self, timed: Mapping[str, Timed], live: Collection[str]) -> dict[str, str]:
        """Uncertain verdicts; the leader by the objective with the cells it is not yet told apart from."""
        entries = self._entries(timed)
        base = entries.get(self.baseline) if self.baseline else None
        verdicts = {key: judge(e.metrics, self.requirements, self.task, base and base.metrics)
                    for key, e in entries.items()}
        found = {key: verdict.short() for key, verdict in verdicts.items() if verdict.status == UNCERTAIN}
        candidates = [entries[key] for key, v in verdicts.items() if v.status in (PASS, UNCERTAIN)]
        objective, paired = self.requirements.objective, speedups(candidates)
        leader, *others = rank(candidates, objective) or [None]
        close = [c.key for c in others if not _apart(leader, c, objective, paired)]
        if leader is not None and close:
            found[leader.key] = f"leads by {objective}; not yet told apart from {close[0]}"
            found.update({key: f"not yet told apart from the leader {leader.key}" for key in close
                          if key not in found})
        return {key: why for key, why in found.items() if key in live}

    def _entries(self, timed: Mapping[str, Timed]) -> dict[str, Entry]:
        """Every cell evaluated and timed so far, with its figures as its record would have them now."""
        spreads = {kind: spread(timed.values(), kind, rate=kind == THROUGHPUT) for kind in SAMPLED}
        found = {}
        for key, cell in timed.items():
            if key not in self.evaluated or not cell.series(LATENCY) or cell.failed:
                continue
            reference = timed.get(self.references.get(key, self.baseline or ""))
            fields = figures(cell, reference if reference is not cell else None, self.settings, LIMITS,
                             spreads)
            found[key] = Entry(key, Measurement.from_json({**self.evaluated[key], **fields}),
                               key == self.baseline)
        return found


def known(requirements: Requirements) -> Requirements:
    """The requirements the rounds can judge: every one but a scenario's (its scenarios run after them)."""
    names = {scenario.name for scenario in scenarios()}
    limits = tuple(limit for limit in requirements.limits if limit.key.partition(".")[0] not in names)
    return Requirements(limits, requirements.objective, requirements.data)


def _apart(leader: Ranked, other: Ranked, objective: str, paired: bool) -> bool:
    """Whether more rounds cannot change which of the two leads: their ratio is beyond APART times its
    interval's half-width, or it has no interval (more rounds cannot give it one)."""
    ratio, half = compare(leader, other, objective, paired)
    return ratio is None or half is None or abs(math.log(ratio)) > APART * half
