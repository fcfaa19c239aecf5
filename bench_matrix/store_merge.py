"""Merging results stores (from several machines, or shards of one matrix) into one: runs, records, raw
samples and facts are copied with new ids; a run already present (same uid) is not copied twice."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from bench_matrix.errors import UserError
from bench_matrix.store import ResultStore


@dataclass(frozen=True)
class MergeCount:
    """What one source store gave: runs and records copied, runs already present, facts kept from the
    target."""

    source: Path
    runs: int
    records: int
    runs_present: int
    facts_differing: tuple[str, ...]


def merge(sources: Sequence[Path], into: Path) -> list[MergeCount]:
    """Copy every run of each source into the store `into` (created if missing); sources are only read."""
    target_path = Path(into).resolve()
    for source in sources:
        if Path(source).resolve() == target_path:
            raise UserError(f"merge: {source} is also the --into store; give the sources and a different "
                            f"target (it may exist: runs are added to it)")
    target = ResultStore(into, label="--into")
    try:
        return [_merge_one(source, target) for source in sources]
    finally:
        target.close()


def _merge_one(source_path: Path, target: ResultStore) -> MergeCount:
    source = ResultStore(source_path, readonly=True, label="store")
    try:
        present = {run.uid for run in target.runs()}
        runs = records = 0
        for run in source.runs():
            if run.uid in present:
                continue
            with target.atomic():  # an interrupted merge leaves no partial run behind
                copy = target.begin_run(run.matrix, run.host, run.versions, run.label, run.started_at,
                                        run.uid)
                target.end_run(copy.id, run.finished_at, run.summary)
                for record in source.records(run.id):
                    samples = source.samples_of(record.id)
                    record.run_id, record.id = copy.id, None
                    target.put(record, samples)
                    records += 1
            runs += 1
        present = len(source.runs()) - runs
        return MergeCount(Path(source_path), runs, records, present, _merge_facts(source, target))
    finally:
        source.close()


def _merge_facts(source: ResultStore, target: ResultStore) -> tuple[str, ...]:
    """Copy the facts the target lacks; name those it holds with a different value (the target's are kept)."""
    differing = []
    for scope, name, value in source.all_facts():
        held = target.facts(scope)
        if name not in held:
            target.put_fact(scope, name, value)
        elif held[name] != value:
            differing.append(f"{scope} {name}")
    return tuple(differing)
