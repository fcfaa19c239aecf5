"""Expand a matrix into cell plans: axes product, exclude, include, each strategy resolved into its conversion and
training steps, validity and machine probes."""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from bench_matrix.cell import Cell, CellPlan, TrainingKey, Ruling, RulingKey
from bench_matrix.matrix.schema import STRATEGY_KINDS
from bench_matrix.strategy import QAT_KINDS
from bench_matrix.matrix.spec import Matrix
from bench_matrix.strategy import StrategySpec

@dataclass(frozen=True)
class Expansion:
    """Every planned cell plus how many combinations `exclude` removed."""

    cells: tuple[CellPlan, ...]
    excluded: int

    def by_state(self, state: str) -> list[CellPlan]:
        return [p for p in self.cells if p.state == state]


def conversion_step(strategy: StrategySpec) -> StrategySpec:
    """The post-training step a backend performs, with its options (kind 'none' when there is none)."""
    leaves = [strategy] if not strategy.steps else [leaf for step in strategy.steps for leaf in _leaves(step)]
    steps = [s for s in leaves if s.kind and STRATEGY_KINDS[s.kind]["stage"] == "conversion"]
    return steps[-1] if steps else StrategySpec(name="none", kind="none")


def _leaves(strategy: StrategySpec) -> list[StrategySpec]:
    return [leaf for step in strategy.steps for leaf in _leaves(step)] if strategy.steps else [strategy]


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


def ruling_key(matrix: Matrix, cell: Cell) -> RulingKey:
    step = backend_kind(matrix.strategies[cell.strategy])
    training = training_key(matrix, cell)
    return (cell.backend, cell.framework, step.kind or "none", cell.precision, cell.target,
            matrix.model(cell.model).source_format, json.dumps(step.options, sort_keys=True),
            json.dumps(training) if training else "")


def training_key(matrix: Matrix, cell: Cell) -> TrainingKey | None:
    """(framework, source format, steps as JSON, task) when the cell's strategy fine-tunes the model, else None."""
    steps = training_steps(matrix.strategies[cell.strategy])
    if not steps:
        return None
    model = matrix.model(cell.model)
    return (cell.framework, model.source_format, json.dumps([s.to_dict() for s in steps]), matrix.task_of(model))


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


def rule(matrix: Matrix, cells: list[Cell], excluded: int, rulings: Mapping[RulingKey, Ruling],
          trainers: Mapping[TrainingKey, Ruling] | None = None,
          baselines: Mapping[str, str] | None = None) -> Expansion:
    """Rule on each candidate (invalid: no trainer, backend does not do it; skip; run) and resolve its steps
    and its baseline cell (`baselines`: framework -> the backend computing its fp32 reference)."""
    planned = []
    for cell in cells:
        strategy = matrix.strategies[cell.strategy]
        key = training_key(matrix, cell)
        training = (trainers or {}).get(key) if key else None
        state, reason = _state(cell, key, training, rulings[ruling_key(matrix, cell)])
        backend = (baselines or {}).get(cell.framework)
        baseline = Cell(cell.model, cell.framework, backend, "none", "fp32", "cpu") if backend else None
        planned.append(CellPlan(cell, state, reason, step=backend_kind(strategy), training=training_steps(strategy),
                                trainer=training.by if training else None, baseline=baseline))
    return Expansion(cells=tuple(planned), excluded=excluded)


def _state(cell: Cell, key: TrainingKey | None, training: Ruling | None,
           ruling: Ruling) -> tuple[str, str | None]:
    if key and training is None:
        return "invalid", f"strategy {cell.strategy} fine-tunes the model; no installed trainer judged it"
    if training and training.invalid:
        return "invalid", training.invalid
    if ruling.invalid:
        return "invalid", ruling.invalid
    if ruling.skip or (training and training.skip):
        return "skip", "; ".join(r for r in (ruling.skip, training and training.skip) if r)
    return "run", None


def _included(matrix: Matrix, fixed: dict[str, str], backends: list[str]) -> list[Cell]:
    """An include entry fixes some keys; the others range over their axis."""
    models = [m for m in matrix.models if fixed.get("model", m.name) == m.name
              and fixed.get("framework", m.framework) == m.framework]
    axis = {"backend": backends, **{k: list(v) for k, v in matrix.axes.items()}}
    options = [[fixed[k]] if k in fixed else axis[k] for k in ("backend", "strategy", "precision", "target")]
    return [Cell(m.name, m.framework, *combo) for m in models for combo in itertools.product(*options)]
