"""The report's sentences shared by the terminal, Markdown and HTML reports: table captions, the model's
and the run's lines, the accuracy headline, and cells grouped by their reason."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from bench_matrix.measurement import RoundsFacts
from bench_matrix.report.analysis.summary import ModelSummary, Report, emulated, metric, number, p50
from bench_matrix.report.render.columns import DASH, DELTA_NAMES, EMULATED, fixed, percent, sig, times
from bench_matrix.store import CellRecord
from bench_matrix.tensors import axes_text, shape_text

NO_REASON = "(no reason stored)"


@dataclass(frozen=True)
class ReasonGroup:
    """Cells that share one reason (a skip's full text, or a failure's headline), in cell-key order."""

    reason: str
    records: tuple[CellRecord, ...]


def by_reason(records: Iterable[CellRecord], reason_of: Callable[[CellRecord], str]) -> list[ReasonGroup]:
    """One group per distinct `reason_of(record)` ("" counts as NO_REASON), largest first, then by reason."""
    groups: dict[str, list[CellRecord]] = {}
    for record in sorted(records, key=lambda r: (r.cell.key, r.host or "")):
        groups.setdefault(reason_of(record).strip() or NO_REASON, []).append(record)
    ordered = sorted(groups.items(), key=lambda item: (-len(item[1]), item[0]))
    return [ReasonGroup(reason, tuple(found)) for reason, found in ordered]


def skip_reason(record: CellRecord) -> str:
    """A skipped cell's full reason, blank lines and surrounding spaces dropped."""
    return "\n".join(line.strip() for line in (record.reason or "").splitlines() if line.strip())


def caption(model: ModelSummary) -> str:
    """What the results table shows, how it was timed and how its rows are ordered."""
    batches = ", ".join(map(str, model.batch_sizes)) or DASH
    threads = ", ".join(map(str, model.threads)) or DASH
    return (f"{emulated_line(model)}Rows are the ok cells, baseline first, then fastest p50 first. Latency "
            f"at batch 1; throughput at batch size {batches}; {threads} thread(s). {timing_line(model)} "
            f"{rerun_line(model)}Speed-up = baseline time ÷ cell time, paired by round (± its 95 % interval; "
            "older records: baseline p50 ÷ cell p50; >1× = faster); "
            "size ratio = baseline size ÷ cell size (>1× = smaller); "
            "↑ = higher is better, ↓ = lower is better.")


def emulated_line(model: ModelSummary) -> str:
    """What the table's timings are where an emulated device measured cells (else nothing): not a board's."""
    found = sorted({why for row in model.rows if (why := emulated(row.record))})
    if not found:
        return ""
    count = sum(emulated(row.record) is not None for row in model.rows)
    return (f"Timings marked (emu), {count} of {len(model.rows)} cells, come from an emulated device "
            f"({'; '.join(found)}): what runs there and how accurately, not how fast the board is. ")


def timing_line(model: ModelSummary) -> str:
    """How the model's cells were timed, in one sentence (docs/metrics.md §5)."""
    facts = [r.record.metrics.rounds for r in model.rows if r.record.metrics.rounds is not None]
    if not facts:
        return "Timed one cell after another (records from before the interleaved rounds)."
    counts = sorted(f.rounds for f in facts if f.rounds is not None) or [0]
    windows = sorted({f.window_s for f in facts if f.window_s is not None})
    length = f"{windows[0]:g} s" if len(windows) == 1 else "short"
    span = f"{counts[0]}" if counts[0] == counts[-1] else f"{counts[0]}–{counts[-1]}"
    stopped = sum(f.stop == "budget" for f in facts)
    budget = f"; {stopped} stopped by the time budget" if stopped else ""
    repeats = max((f.visits or 1.0) for f in facts)
    baseline = f" (the baseline {repeats:.1f} times a round)" if repeats >= 1.05 else ""
    return (f"Timed in {span} interleaved rounds of {length} windows, {_processes(facts)}, each round in a "
            f"fresh random order{baseline}{budget}; p50 intervals from the per-round medians (they hold "
            f"while the machine keeps this run's speed).")


def rerun_line(model: ModelSummary) -> str:
    """How far other runs on the same hosts put the same artifacts' p50s, and how many of them this run's p50
    intervals held; "" when no other run timed them (report/analysis/reruns.py)."""
    if not model.reruns:
        return ""
    moves = sorted(r.move for r in model.reruns)
    largest = max(model.reruns, key=lambda r: abs(r.move))
    span = f"{moves[0]:+.1%}" if len(moves) == 1 else f"{moves[0]:+.1%} to {moves[-1]:+.1%}"
    who, how = (("Another run", "the median over its cells") if len(moves) == 1 else
                (f"{len(moves)} other runs", "each the median over a run's cells; in the largest move"))
    return (f"{who} on the same host timed these artifacts: p50s {span} off this run's ({how}, "
            f"{largest.alike} of {largest.cells} cells the same way){_held(model)}. ")


def _held(model: ModelSummary) -> str:
    """How many of the other runs' p50s this run's intervals held, and why they may not."""
    held, intervals = (sum(r.held for r in model.reruns), sum(r.intervals for r in model.reruns))
    if not intervals:
        return ""
    said = f"; this run's p50 intervals held {held} of {intervals}"
    return said if held >= 0.9 * intervals else (
        f"{said}: a machine's speed can move between runs, which intervals from inside one run cannot see; "
        "the paired speed-ups cancel what the cells share")


def _processes(facts: list[RoundsFacts]) -> str:
    """How many session processes timed each cell and how far they differed; "per cell" for one."""
    processes = max((f.processes or 1) for f in facts)
    spread = max((f.model_spread for f in facts if f.model_spread is not None), default=None)
    if processes < 2 or spread is None:
        return "per cell"
    differed = (f"they differed by {spread:.1%}, in the intervals" if spread >= 0.0005
                else "they differed by no more than their windows' own noise")
    return f"each cell in {processes} processes ({differed})"


def baseline_note(model: ModelSummary) -> str | None:
    """Why the comparisons are missing when the baseline cell did not produce a result, else None."""
    if model.baseline is not None and model.baseline.status == "ok":
        return None
    delta = DELTA_NAMES.get(model.task, "the fidelity figures")
    missing = f"speed-up, size ratio and {delta} are not available"
    if model.accuracy_baseline is not None:
        missing = (f"speed-up and size ratio are not available; {delta} is against its test metrics from "
                   f"where the model was prepared")
    if not model.baseline_key:
        return f"No baseline is recorded for this model (its preparation never finished): {missing}."
    state = "is not in the store" if model.baseline is None else model.baseline.status
    return f"Baseline cell {model.baseline_key} {state}: {missing}."


def model_line(model: ModelSummary, code: Callable[[str], str]) -> str:
    """Framework, source, parameters and training of the model; `code` marks literal text (paths, keys)."""
    info = model.info
    parts = [f"framework {model.framework}"]
    if info.get("source"):
        parts.append(f"source {code(str(info['source']))}")
    params = number(info.get("params"))
    if params is not None:
        parts.append(f"{int(params):,} parameters")
    training = info.get("training") if isinstance(info.get("training"), dict) else None
    if training:
        epochs, train_s = training.get("epochs"), number(training.get("train_s"))
        parts.append(f"trained {epochs if epochs is not None else DASH} epochs in {sig(train_s, 3)} s")
    elif "training" in info:
        parts.append("not trained by bench-matrix")
    parts.append(f"baseline {code(model.baseline_key)}")
    return " · ".join(parts + _timed_inputs(info))


def _timed_inputs(info: dict) -> list[str]:
    """The shapes the model's inputs were timed at, per sample, with the open axes synthetic data gave the
    default length; none for records prepared before they were stored."""
    timed, defaulted = info.get("timed_inputs"), info.get("defaulted_axes") or {}
    if not isinstance(timed, list) or not timed:
        return []
    shapes = ", ".join(f"{i['name']} {shape_text(i['shape'])} {i['dtype']}" for i in timed)
    notes = [f"{name}: {axes_text(axes)} open in the model, given synthetic data's default length"
             for name, axes in defaulted.items()]
    return [f"inputs timed at {shapes} per sample" + (f" ({'; '.join(notes)})" if notes else "")]


def accuracy_line(model: ModelSummary) -> str:
    """How good the baseline is on its own, by the model's task, so the reader can tell whether it learned."""
    if model.task == "classification":
        return top1_line(model)
    if model.task == "regression":
        return mse_line(model)
    return "No labels: fidelity against the fp32 baseline only."


def mse_line(model: ModelSummary) -> str:
    """The baseline's test MSE beside the mean predictor's, so the reader can tell whether the model learned."""
    base = _ok_baseline(model)
    test = number(model.info.get("test_mse"))
    test = metric(base, "mse") if test is None and base is not None else test
    mean = number(model.info.get("mean_predictor_mse"))
    ratio = f"; ratio {sig(test / mean, 3)} (below 1 = better than predicting the training mean)" \
        if test is not None and mean else ""
    on = _on_samples(model)
    return f"Baseline test MSE {sig(test, 4)} vs mean-predictor MSE {sig(mean, 4)}{ratio}{on}."


def top1_line(model: ModelSummary) -> str:
    """The baseline's test top-1 beside always predicting the most common training class."""
    top1, majority = _baseline_top1(model), number(model.info.get("majority_top1"))
    return (f"Baseline test top-1 {percent(top1)} % vs majority-class top-1 {percent(majority)} % (always "
            f"predicting the most common training class; higher is better){_on_samples(model)}.")


def _baseline_top1(model: ModelSummary) -> float | None:
    """The fp32 model's test top-1 as its preparation measured it, else as its baseline cell did."""
    prepared = model.info.get("test_metrics")
    top1 = number(prepared.get("top1")) if isinstance(prepared, dict) else None
    base = _ok_baseline(model)
    return metric(base, "top1") if top1 is None and base is not None else top1


def _ok_baseline(model: ModelSummary) -> CellRecord | None:
    return model.baseline if model.baseline is not None and model.baseline.status == "ok" else None


def _on_samples(model: ModelSummary) -> str:
    samples = number(model.info.get("test_samples"))
    return f" on {int(samples):,} test samples" if samples is not None else ""


def headline_text(model: ModelSummary) -> str:
    """The model's accuracy in one short cell of the overview table (see HEADLINE_NOTE)."""
    if model.task == "regression":
        test, mean = number(model.info.get("test_mse")), number(model.info.get("mean_predictor_mse"))
        return f"MSE ÷ mean predictor {sig(test / mean, 3)}" if test is not None and mean else DASH
    if model.task == "classification":
        top1, majority = _baseline_top1(model), number(model.info.get("majority_top1"))
        return f"top-1 {percent(top1)} % (majority {percent(majority)} %)" if top1 is not None else DASH
    cosines = [c for c in (metric(r.record, "cosine_similarity") for r in model.rows) if c is not None]
    return f"lowest cosine {fixed(min(cosines), 6)}" if cosines else DASH


HEADLINE_NOTE = ("Accuracy: for regression, the baseline's test MSE ÷ that of always predicting the "
                 "training mean (below 1 = the model learned something); for classification, the baseline's "
                 "test top-1 beside always predicting the most common training class (higher is better); "
                 "without labels, the lowest cosine similarity of any cell's outputs to the fp32 baseline's "
                 "(1 = identical).")


def run_line(report: Report) -> str:
    """The run shown (or the newest of the store) and what the report holds."""
    held = report.counts
    stored = (f"Shown: {sum(held.values())} cells, {held['ok']} ok, {held['skipped']} skipped, "
              f"{held['failed']} failed.")
    run = report.run
    if not run:
        return stored
    counts = run.get("counts") or {}
    ran = ", ".join(f"{counts.get(s, 0)} {s}" for s in ("ok", "skipped", "failed")) if counts else "counts not stored"
    wall = number(run.get("wall_s"))
    name = f"Run {run.get('id', DASH)}" + (f" ({run['label']})" if run.get("label") else "")
    ended = run.get("finished_at") or "did not finish"
    stopped = "" if run.get("completed", True) else " (interrupted)"
    return (f"{name} of {run.get('runs', 1)} in the store: matrix {run.get('matrix') or DASH} on "
            f"{run.get('host') or DASH}, {run.get('started_at') or DASH} → {ended}{stopped} "
            f"({sig(wall, 3)} s): {ran}. {stored}")


def best_text(model: ModelSummary) -> tuple[str, str, str]:
    """(method, p50 ms, speed-up) of the model's fastest ok cell, dashes when there is none."""
    best = model.best
    if best is None:
        return DASH, DASH, DASH
    emu = EMULATED if emulated(best.record) else ""
    return best.record.cell.label, sig(p50(best.record), 3) + emu, times(best.speedup)
