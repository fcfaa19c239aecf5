"""How far the other runs on the same host put the p50s of the same artifacts: what a rerun may move by,
which the p50 intervals (from inside one run) cannot see. Pure functions over stored records."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np

from bench_matrix.store import CellRecord


@dataclass(frozen=True)
class Rerun:
    """Another run that timed some of a model's shown artifacts, on their host and thread count."""

    run: int
    cells: int  # the shown cells it timed too
    move: float  # the median over them of (its p50 ÷ the shown p50) − 1
    alike: int  # of them, how many moved the same way as `move`
    held: int  # of them, how many p50s lay inside the shown record's p50 interval
    intervals: int  # of them, how many shown records have a p50 interval

    def to_json(self) -> dict[str, float | int]:
        return asdict(self)


def reruns(shown: Iterable[CellRecord], history: Iterable[CellRecord]) -> tuple[Rerun, ...]:
    """Per other run in `history`, by id, how its p50s of the shown records' artifacts compare with theirs."""
    now = {_identity(r): r for r in shown if _p50(r) and r.artifact_path}
    pairs: dict[int, dict[str, tuple[float, CellRecord]]] = {}
    for record in history:
        found = now.get(_identity(record))
        if found is None or record.run_id in (None, found.run_id) or not _p50(record):
            continue
        pairs.setdefault(record.run_id, {})[record.cell.key] = (_p50(record), found)
    return tuple(_rerun(run, list(found.values())) for run, found in sorted(pairs.items()))


def _p50(record: CellRecord) -> float | None:
    latency = record.metrics.latency
    value = latency.p50 if latency else None
    return value if isinstance(value, int | float) and math.isfinite(value) and value > 0 else None


def _identity(record: CellRecord) -> tuple[str, str | None, str | None, int | None]:
    return record.cell.key, record.host, record.artifact_path, record.metrics.setup.threads


def _rerun(run: int, pairs: list[tuple[float, CellRecord]]) -> Rerun:
    """The figures of one other run from its p50s paired with the shown records."""
    logs = [math.log(p50 / _p50(shown)) for p50, shown in pairs]
    move = float(np.median(logs))
    alike = sum(1 for x in logs if x * move > 0) if move else len(logs)
    intervals = [(p50, shown.metrics.latency.p50_ci) for p50, shown in pairs
                 if shown.metrics.latency.p50_ci and len(shown.metrics.latency.p50_ci) == 2]
    held = sum(1 for p50, (lo, hi) in intervals if lo <= p50 <= hi)
    return Rerun(run=run, cells=len(logs), move=math.expm1(move), alike=alike, held=held,
                 intervals=len(intervals))
