"""The report's "Verdict" section, shared by the terminal, Markdown and HTML reports: each model's
requirements, the recommended cell per model and target, and the cells closest to passing where none
passes."""

from __future__ import annotations

from collections.abc import Sequence

from bench_matrix.ranking import FIGURES
from bench_matrix.report.analysis.recommend import Recommendation
from bench_matrix.report.analysis.summary import ModelSummary, emulated
from bench_matrix.report.render.columns import EMULATED, sig
from bench_matrix.verdict import UNCERTAIN, figure

INTRO = ("Each ok cell is judged against its model's requirements: pass; fail, naming each requirement "
         "missed and by how much; or uncertain, where a timed figure's 95 % interval straddles its limit. "
         "For each model and target, the recommended cell is the best passing one by the objective "
         "(docs/results.md §8).")
HEADERS = (("Model", "the model"), ("Target", "where its cells ran"),
           ("Recommended", "the best passing cell by the objective"),
           ("Objective", "the recommended cell's figure the objective ranks by (p50: with its speed-up "
                         "paired against the baseline)"),
           ("Runner-up", "the next passing cell by the objective"),
           ("Best vs runner-up", "how many times better the recommended cell is on the objective, with the "
            "95 % interval of that ratio (paired speed-ups: their intervals combined): distinguishable when "
            "it excludes 1, else a tie"),
           ("Passing", "ok cells that pass, of every cell that ran (those that failed to run counted, and "
                       "said, too)"))
NUMERIC = [False, False, False, True, False, False, True]
NOT_DECLARED = ("add `requirements:` to the matrix (docs/matrix.md) or try `--require KEY=VALUE`, e.g. "
                "`--require p50_ms=50 --require max_drop=5%`")
DASH = "—"
NONE_PASSES = "none passes"


def judged(models: Sequence[ModelSummary]) -> list[ModelSummary]:
    """The models judged against requirements."""
    return [model for model in models if model.requirements is not None]


def requirement_lines(models: Sequence[ModelSummary]) -> list[str]:
    """One line per model: its requirements and where they came from, or that it has none."""
    lines = []
    for model in models:
        if model.requirements is None:
            lines.append(f"{model.name}: no requirements ({model.requirements_from}): {NOT_DECLARED}")
        else:
            lines.append(f"{model.name}: {model.requirements.describe()} (from {model.requirements_from})")
    return lines


def rows(models: Sequence[ModelSummary]) -> list[list[str]]:
    """The recommendation table's rows: one per judged model and target."""
    several = len({r.host for m in models for r in m.recommendations}) > 1
    return [_row(r, several) for model in judged(models) for r in model.recommendations]


def closest_lines(models: Sequence[ModelSummary]) -> list[str]:
    """For each model and target where no cell passes: the cells closest to passing and what each misses."""
    lines = []
    for model in judged(models):
        for found in model.recommendations:
            if found.best is not None:
                continue
            if not found.closest:
                lines.append(f"{found.model} on {found.target}: no cell passes; every cell failed to run")
                continue
            cells = "; ".join(f"{c.record.cell.label} ({c.verdict.short()})" for c in found.closest)
            lines.append(f"{found.model} on {found.target}: no cell passes; closest: {cells}")
    return lines


def open_lines(models: Sequence[ModelSummary]) -> list[str]:
    """The answers the verdict leaves open, one line each: a recommended cell not told apart from its
    runner-up, and each uncertain cell not already listed among the closest to passing."""
    lines = []
    for model in judged(models):
        closest = {c.record.cell.key for found in model.recommendations for c in found.closest}
        lines += [_tie(found) for found in model.recommendations if found.distinguishable is False]
        lines += [f"{model.name}: {row.record.cell.label} is {row.verdict.short()}" for row in model.rows
                  if row.verdict is not None and row.verdict.status == UNCERTAIN
                  and row.record.cell.key not in closest]
    return lines


def _tie(found: Recommendation) -> str:
    """A recommendation whose ratio to its runner-up has an interval that holds 1."""
    low, high = found.ratio_ci
    return (f"{found.model} on {found.target}: the recommended {found.best.cell.label} is not told apart "
            f"from the runner-up {found.runner_up.cell.label} ({found.ratio:.2f}×, 95 % interval "
            f"{low:.2f}–{high:.2f}×): either will do, or more timing_budget_s may tell them apart")


def _row(found: Recommendation, several: bool) -> list[str]:
    target = found.target + (f" ({found.host})" if several else "")
    passing = found.passing_text
    if found.best is None:
        return [found.model, target, NONE_PASSES, DASH, DASH, DASH, passing]
    runner = found.runner_up.cell.label if found.runner_up is not None else DASH
    return [found.model, target, found.best.cell.label, _objective(found), runner, _versus(found), passing]


def _objective(found: Recommendation) -> str:
    """The recommended cell's figure the objective ranks by: p50 (with its paired speed-up), p99, size or
    throughput."""
    m = found.best.metrics
    value = figure(FIGURES[found.objective], m)[0]
    if value is None:
        return DASH
    unit = {"p50": "ms", "p99": "ms", "size": "MiB", "throughput": "samples/s"}[found.objective]
    timed = found.objective in ("p50", "p99", "throughput") and emulated(found.best)
    text = f"{found.objective} {sig(value, 3)}{EMULATED if timed else ''} {unit}"
    speedup = m.speedup.value if m.speedup is not None else None
    return text + (f" ({speedup:.2f}×)" if found.objective == "p50" and speedup else "")


def _versus(found: Recommendation) -> str:
    if found.runner_up is None or found.ratio is None:
        return DASH
    if found.ratio_ci is None:
        return f"{found.ratio:.2f}× (no interval: judged by value)"
    low, high = found.ratio_ci
    word = "distinguishable" if found.distinguishable else "a tie"
    return f"{found.ratio:.2f}× ({low:.2f}–{high:.2f}×): {word}"
