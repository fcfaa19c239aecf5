"""Expand a matrix into planned cells: axes product, exclude, include, validity and machine probes."""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from bench_matrix.cell import Cell, PlannedCell
from bench_matrix.matrix.schema import STRATEGY_KINDS
from bench_matrix.matrix.spec import Matrix, StrategySpec

# (backend, framework, conversion kind, precision, target, source format, conversion options as JSON):
# everything a backend needs to judge a combination before any model is loaded
VerdictKey = tuple[str, str, str, str, str, str, str]
# (framework, source format, training steps as JSON): what a trainer needs to judge a fine-tuning strategy
TrainingKey = tuple[str, str, str]
QAT_KINDS = ("qat", "cqat", "pqat", "pcqat")  # training kinds whose result carries learned int8 ranges


@dataclass(frozen=True)
class Verdict:
    """A backend's answer for one combination: not valid (why), or valid but not runnable here (why)."""

    invalid: str | None = None
    skip: str | None = None
    by: str | None = None  # for a fine-tuning strategy: the trainer that will apply it


@dataclass(frozen=True)
class Expansion:
    """Every planned cell plus how many combinations `exclude` removed."""

    cells: tuple[PlannedCell, ...]
    excluded: int

    def by_state(self, state: str) -> list[PlannedCell]:
        return [p for p in self.cells if p.state == state]


def conversion_step(strategy: StrategySpec) -> StrategySpec:
    """The post-training step a backend performs, with its options (kind 'none' when there is none)."""
    leaves = [strategy] if not strategy.steps else [leaf for step in strategy.steps for leaf in _leaves(step)]
    steps = [s for s in leaves if s.kind and STRATEGY_KINDS[s.kind]["stage"] == "conversion"]
    return steps[-1] if steps else StrategySpec(name="none", kind="none")


def _leaves(strategy: StrategySpec) -> list[StrategySpec]:
    return [leaf for step in strategy.steps for leaf in _leaves(step)] if strategy.steps else [strategy]


def training_kinds(strategy: StrategySpec) -> list[str]:
    return [k for k in strategy.kinds() if STRATEGY_KINDS[k]["stage"] == "training"]


def training_steps(strategy: StrategySpec) -> tuple[StrategySpec, ...]:
    """The fine-tuning steps of a strategy, in order, each with its own options."""
    leaves = [strategy] if not strategy.steps else [leaf for step in strategy.steps for leaf in _leaves(step)]
    return tuple(s for s in leaves if s.kind and STRATEGY_KINDS[s.kind]["stage"] == "training")


def backend_kind(strategy: StrategySpec) -> StrategySpec:
    """What the backend is asked to do: the conversion step, or for a quantisation-aware-trained model with no
    conversion step, its QAT kind (the model carries its learned int8 ranges)."""
    step = conversion_step(strategy)
    if step.kind == "none":
        qat = [s for s in training_steps(strategy) if s.kind in QAT_KINDS]
        if qat:
            return StrategySpec(name=qat[-1].kind, kind=qat[-1].kind)
    return step


def verdict_key(matrix: Matrix, cell: Cell) -> VerdictKey:
    step = backend_kind(matrix.strategies[cell.strategy])
    return (cell.backend, cell.framework, step.kind or "none", cell.precision, cell.target,
            matrix.model(cell.model).source_format, json.dumps(step.options, sort_keys=True))


def training_key(matrix: Matrix, cell: Cell) -> TrainingKey | None:
    """(framework, source format, steps as JSON) when the cell's strategy fine-tunes the model, else None."""
    steps = training_steps(matrix.strategies[cell.strategy])
    if not steps:
        return None
    return (cell.framework, matrix.model(cell.model).source_format, json.dumps([s.to_dict() for s in steps]))


def combinations(matrix: Matrix, installed: Iterable[str]) -> tuple[list[Cell], int]:
    """Candidate cells (axes product minus exclude, plus include) and the number excluded."""
    backends = list(matrix.axes.get("backend") or installed)
    frameworks = matrix.axes.get("framework")
    cells: dict[Cell, None] = {}
    excluded = 0
    for model in matrix.models:
        if frameworks and model.framework not in frameworks:
            continue
        for backend, strategy, precision, target in itertools.product(
                backends, matrix.axes["strategy"], matrix.axes["precision"], matrix.axes["target"]):
            cell = Cell(model.name, model.framework, backend, strategy, precision, target)
            if any(sel.matches(cell.as_dict()) for sel in matrix.exclude):
                excluded += 1
            else:
                cells.setdefault(cell)
    for selector in matrix.include:
        for cell in _included(matrix, dict(selector.values), backends):
            cells.setdefault(cell)
    return list(cells), excluded


def plan(matrix: Matrix, cells: list[Cell], excluded: int, verdicts: Mapping[VerdictKey, Verdict],
         trainers: Mapping[TrainingKey, Verdict] | None = None) -> Expansion:
    """Judge each candidate: invalid (no trainer, backend does not do it), skip, or run."""
    planned = []
    for cell in cells:
        key = training_key(matrix, cell)
        training = (trainers or {}).get(key) if key else None
        verdict = verdicts[verdict_key(matrix, cell)]
        if key and training is None:
            planned.append(PlannedCell(cell, "invalid", f"strategy {cell.strategy} fine-tunes the model; no "
                                                        f"installed trainer judged it"))
        elif training and training.invalid:
            planned.append(PlannedCell(cell, "invalid", training.invalid))
        elif verdict.invalid:
            planned.append(PlannedCell(cell, "invalid", verdict.invalid))
        elif verdict.skip or (training and training.skip):
            planned.append(PlannedCell(cell, "skip", "; ".join(r for r in (verdict.skip, training and training.skip)
                                                               if r)))
        else:
            planned.append(PlannedCell(cell, "run"))
    return Expansion(cells=tuple(planned), excluded=excluded)


def _included(matrix: Matrix, fixed: dict[str, str], backends: list[str]) -> list[Cell]:
    """An include entry fixes some keys; the others range over their axis."""
    models = [m for m in matrix.models if fixed.get("model", m.name) == m.name
              and fixed.get("framework", m.framework) == m.framework]
    axis = {"backend": backends, **{k: list(v) for k, v in matrix.axes.items()}}
    options = [[fixed[k]] if k in fixed else axis[k] for k in ("backend", "strategy", "precision", "target")]
    return [Cell(m.name, m.framework, *combo) for m in models for combo in itertools.product(*options)]
