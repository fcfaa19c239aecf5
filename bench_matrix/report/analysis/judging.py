"""Verdicts and recommendations joined to a report when it is made (docs/results.md §8): each model's
requirements come from the matrix its newest record came from, as that file says now (so changing them needs
no re-run), else as the run stored them; or from --matrix; --require goes over them."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from bench_matrix.matrix.require import read_file
from bench_matrix.matrix.requirements import Declared
from bench_matrix.report.analysis.recommend import Candidate, recommend
from bench_matrix.report.analysis.summary import ModelSummary, Report
from bench_matrix.store import CellRecord
from bench_matrix.verdict import judge

SCOPE = "requirements"  # facts: name = the matrix path records carry; value = where it is, what it declares


@dataclass(frozen=True)
class Judging:
    """Where requirements come from besides each record's matrix: `matrix` (--matrix) instead of it, and
    `overrides` (--require, as requirements data) over whatever was found."""

    matrix: Path | None = None
    overrides: Mapping[str, Any] = field(default_factory=dict)


def stored(matrix: Path, declared: Declared) -> dict[str, Any]:
    """The fact a run stores for its matrix: where the file is, and the requirements it declared."""
    return {"path": str(matrix.resolve()), "declared": declared.to_json()}


def judged(report: Report, facts: Mapping[str, Any], judging: Judging) -> Report:
    """The report with each model's requirements, its ok cells' verdicts and its recommendations; models
    without requirements are left unjudged."""
    found: dict[str, tuple[Declared, str]] = {}
    models = []
    for model in report.models:
        matrix = _matrix_of(model)
        if matrix not in found:
            found[matrix] = _declared(matrix, facts, judging)
        models.append(judge_model(model, *found[matrix], judging.overrides))
    return replace(report, models=tuple(models))


def judge_model(model: ModelSummary, declared: Declared, source: str, overrides: Mapping[str, Any]
                ) -> ModelSummary:
    """The model judged against its requirements in `declared` (with `overrides` over them), if it has any."""
    requirements = declared.of(model.name, overrides)
    if not requirements.data:
        return replace(model, requirements_from=source)
    baseline = model.accuracy_baseline
    rows = tuple(replace(row, verdict=judge(row.record.metrics, requirements, model.task, baseline,
                                            model.implausible.get(row.record.cell.key)))
                 for row in model.rows)
    candidates = [Candidate(row.record, row.verdict, row.is_baseline) for row in rows]
    found = recommend(model.name, candidates, model.failed, requirements.objective)
    where = source + (" and --require" if overrides else "")
    return replace(model, rows=rows, requirements=requirements, requirements_from=where,
                   recommendations=found)


def unmet(report: Report) -> list[str]:
    """'MODEL on TARGET' for each model and target without a passing cell (the --check gate)."""
    found = [r for model in report.models for r in model.recommendations]
    several = len({r.host for r in found}) > 1
    return [f"{r.model} on {r.target}" + (f" ({r.host})" if several else "") for r in found if r.best is None]


def _matrix_of(model: ModelSummary) -> str:
    """The matrix the model's newest record came from."""
    records: list[CellRecord] = [*(row.record for row in model.rows), *model.skipped, *model.failed]
    newest = max(records, key=lambda r: (r.finished_at or r.started_at or "", r.id or 0))
    return newest.matrix


def _declared(matrix: str, facts: Mapping[str, Any], judging: Judging) -> tuple[Declared, str]:
    """The requirements to judge records of `matrix` by, and where they were read."""
    if judging.matrix is not None:
        return read_file(judging.matrix), f"--matrix {judging.matrix}"
    fact = facts.get(matrix)
    if not isinstance(fact, Mapping):
        return Declared(), f"none stored for {matrix or 'these records'}"
    path = Path(str(fact.get("path", "")))
    if path.is_file():
        return read_file(path), matrix
    return Declared.from_json(fact.get("declared") or {}), f"the run's copy of {matrix}: {path} is gone"
