"""`compare` on hand-made records and seeded latency samples: significance and thresholds, directions, cells
that cannot be compared, threshold parsing and the three renderings."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.measurement import Speedup
from bench_matrix.report.analysis.compare import DEFAULT_THRESHOLDS, TEST, compare, parse_threshold
from bench_matrix.report.analysis.metric_change import NOT_COMPARABLE, UNCHANGED, WORSE, Side
from bench_matrix.report.render.compare_view import comparison_json, comparison_markdown, print_comparison
from bench_matrix.store import CellRecord

ORT = Cell("pilotnet", "pytorch", "onnxruntime", "none", "fp32", "cpu")
PTQ = Cell("pilotnet", "pytorch", "onnxruntime", "ptq_dynamic", "int8", "cpu")
RESNET = Cell("resnet", "pytorch", "pytorch", "none", "fp32", "cpu")
DISTURBED = {"flagged": True, "reason": "latency: cpu busy",
             "phases": {"latency": {"attempts": [{"disturbed": "cpu busy"}], "kept": 0}}}


def _samples(median: float, spread: float = 0.02, n: int = 2000, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(median, spread * median, n).astype(np.float32)


def _record(cell: Cell, samples: np.ndarray | None = None, status: str = "ok", **metrics: Any) -> CellRecord:
    """A record with the latency figures of `samples`, default metrics set (None: dropped) by `metrics`."""
    values: dict[str, Any] = {"throughput_sps": 1000.0, "size_bytes": 4_000_000, "mse": 0.02}
    if samples is not None:
        p50, p99 = np.percentile(samples, [50, 99])
        values["latency_ms"] = {"p50": float(p50), "p99": float(p99), "n": len(samples)}
    values.update(metrics)
    reason = "RuntimeError: boom\n  File x" if status != "ok" else None
    return CellRecord(cell=cell, status=status, reason=reason,
                      metrics={k: v for k, v in values.items() if v is not None})


def _side(label: str, *pairs: tuple[CellRecord, np.ndarray | None], tasks: dict[str, str] | None = None
          ) -> Side:
    return Side(label, [record for record, _ in pairs],
                {record.cell.key: s for record, s in pairs if s is not None}, tasks or {})


def _pair(base: np.ndarray, new: np.ndarray, thresholds: dict[str, float] | None = None,
          base_metrics: dict[str, Any] | None = None, new_metrics: dict[str, Any] | None = None):
    before = _side("run 1", (_record(ORT, base, **(base_metrics or {})), base))
    after = _side("run 2", (_record(ORT, new, **(new_metrics or {})), new))
    return compare(before, after, thresholds)


def _metric(comparison, name: str):
    (cell,) = comparison.cells
    return next(m for m in cell.metrics if m.metric == name)


def test_a_shift_beyond_the_threshold_that_is_significant_is_worse() -> None:
    result = _pair(_samples(1.0, seed=1), _samples(1.3, seed=2))
    p50 = _metric(result, "p50")
    assert p50.verdict == "worse" and p50.p_value < 0.05
    assert p50.change == pytest.approx(0.3, abs=0.02)
    assert result.cells[0].verdict == "worse"
    assert ("pilotnet/onnxruntime/none/fp32/cpu", "p50") in result.regressions


def test_a_significant_speed_up_beyond_the_threshold_is_better() -> None:
    result = _pair(_samples(2.5, seed=1), _samples(1.0, seed=2))
    assert _metric(result, "p50").verdict == "better" and _metric(result, "p99").verdict == "better"
    assert result.cells[0].verdict == "better" and result.regressions == []


def test_the_same_distribution_twice_is_unchanged() -> None:
    result = _pair(_samples(1.0, seed=1), _samples(1.0, seed=2))
    assert [m.verdict for m in result.cells[0].metrics] == ["unchanged"] * 5
    assert result.cells[0].verdict == "unchanged" and result.regressions == []


def test_a_significant_shift_under_the_threshold_is_unchanged() -> None:
    result = _pair(_samples(1.0, 0.01, 5000, seed=1), _samples(1.03, 0.01, 5000, seed=2))
    p50 = _metric(result, "p50")
    assert p50.p_value < 0.05 and 0.02 < p50.change < DEFAULT_THRESHOLDS["p50"]
    assert p50.verdict == "unchanged"


def test_a_large_change_that_is_not_significant_is_unchanged() -> None:
    base = np.array([1.0, 2.0, 3.0, 4.0, 5.0], np.float32)
    new = np.array([1.5, 2.5, 4.5, 5.5, 6.0], np.float32)
    p50 = _metric(_pair(base, new), "p50")
    assert p50.change == pytest.approx(0.5) and p50.p_value >= 0.05
    assert p50.verdict == "unchanged"


def test_a_threshold_given_by_the_user_replaces_the_default() -> None:
    base, new = _samples(1.0, seed=1), _samples(1.7, seed=2)
    assert _metric(_pair(base, new, {"p50": 0.8}), "p50").verdict == "unchanged"
    assert _metric(_pair(base, new, {"p50": 0.8}), "p99").verdict == "worse"


@pytest.mark.parametrize(("base", "new", "verdict"), [(1000.0, 1300.0, "better"), (1000.0, 700.0, "worse"),
                                                      (1000.0, 1150.0, "unchanged")])
def test_throughput_is_judged_by_its_threshold_higher_being_better(base: float, new: float, verdict: str
                                                                    ) -> None:
    samples = _samples(1.0)
    result = _pair(samples, samples, base_metrics={"throughput_sps": base},
                   new_metrics={"throughput_sps": new})
    assert _metric(result, "throughput").verdict == verdict


@pytest.mark.parametrize(("new", "verdict"), [(4_080_000, "worse"), (3_920_000, "better"),
                                              (4_020_000, "unchanged")])
def test_size_is_judged_by_its_one_percent_threshold_in_both_directions(new: int, verdict: str) -> None:
    samples = _samples(1.0)
    result = _pair(samples, samples, new_metrics={"size_bytes": new})
    size = _metric(result, "size")
    assert size.verdict == verdict and size.change == pytest.approx(new / 4_000_000 - 1)


@pytest.mark.parametrize(("new", "verdict"), [(0.022, "worse"), (0.018, "better"), (0.0205, "unchanged")])
def test_mse_changes_relatively_and_lower_is_better(new: float, verdict: str) -> None:
    samples = _samples(1.0)
    accuracy = _metric(_pair(samples, samples, new_metrics={"mse": new}), "accuracy")
    assert accuracy.name == "mse" and accuracy.relative
    assert accuracy.verdict == verdict and accuracy.change == pytest.approx(new / 0.02 - 1)


@pytest.mark.parametrize(("new", "verdict"), [(0.91, "better"), (0.89, "worse"), (0.897, "unchanged")])
def test_top1_changes_absolutely_and_higher_is_better(new: float, verdict: str) -> None:
    samples = _samples(1.0)
    tasks = {"resnet": "classification"}
    before = _side("a", (_record(RESNET, samples, mse=None, top1=0.9), samples), tasks=tasks)
    after = _side("b", (_record(RESNET, samples, mse=None, top1=new), samples), tasks=tasks)
    accuracy = _metric(compare(before, after), "accuracy")
    assert accuracy.name == "top1" and not accuracy.relative
    assert accuracy.verdict == verdict and accuracy.change == pytest.approx(new - 0.9)


def test_the_task_comes_from_the_caller_or_from_the_metrics_a_record_has() -> None:
    samples = _samples(1.0)
    before = _side("a", (_record(RESNET, samples, mse=None, top1=0.9, cosine_similarity=1.0), samples))
    after = _side("b", (_record(RESNET, samples, mse=None, top1=0.8, cosine_similarity=0.99), samples))
    assert _metric(compare(before, after), "accuracy").name == "top1"
    assert _metric(compare(before, after, tasks={"resnet": "none"}), "accuracy").name == "cosine_similarity"


def test_an_accuracy_threshold_applies_to_both_kinds_of_change() -> None:
    samples = _samples(1.0)
    result = _pair(samples, samples, {"accuracy": 0.2}, new_metrics={"mse": 0.022})
    assert _metric(result, "accuracy").verdict == "unchanged"
    assert result.thresholds["accuracy_relative"] == result.thresholds["accuracy_absolute"] == 0.2


def test_missing_samples_or_metrics_are_not_comparable_with_the_reason() -> None:
    samples = _samples(1.0)
    before = _side("a", (_record(ORT, samples, size_bytes=None), samples))
    after = _side("b", (_record(ORT, samples), None))
    cell = compare(before, after).cells[0]
    why = {m.metric: (m.verdict, m.why) for m in cell.metrics}
    assert why["p50"] == ("not comparable", "no raw latency samples in new")
    assert why["size"] == ("not comparable", "no size_bytes in base")
    assert why["throughput"] == ("unchanged", None)
    assert cell.verdict == "not comparable"


def test_a_metric_worse_outranks_one_not_comparable_in_the_cell_verdict() -> None:
    samples = _samples(1.0)
    before = _side("a", (_record(ORT, samples), samples))
    after = _side("b", (_record(ORT, samples, size_bytes=8_000_000), None))
    cell = compare(before, after).cells[0]
    assert cell.verdict == "worse" and _metric(compare(before, after), "p50").verdict == "not comparable"


def test_different_tasks_and_failed_cells_are_not_comparable() -> None:
    samples = _samples(1.0)
    before = _side("a", (_record(ORT, samples), samples), (_record(PTQ, samples), samples),
                   tasks={"pilotnet": "regression"})
    after = _side("b", (_record(ORT, samples, top1=0.5), samples), (_record(PTQ, status="failed"), None),
                  tasks={"pilotnet": "classification"})
    ort, ptq = compare(before, after).cells
    assert _accuracy_why(ort) == "different task: regression in base, classification in new"
    assert ptq.verdict == "not comparable" and ptq.why == "failed in new: RuntimeError: boom"
    assert ptq.metrics == ()


def _accuracy_why(cell) -> str | None:
    return next(m.why for m in cell.metrics if m.metric == "accuracy")


def test_cells_on_one_side_only_are_listed_and_never_gate() -> None:
    samples = _samples(1.0)
    result = compare(_side("a", (_record(ORT, samples), samples), (_record(PTQ, samples), samples)),
                     _side("b", (_record(ORT, samples), samples), (_record(RESNET, samples), samples)))
    assert [(c.key, c.verdict, c.why) for c in result.cells] == [
        (ORT.key, "unchanged", None), (PTQ.key, "not comparable", "only in base"),
        (RESNET.key, "not comparable", "only in new")]
    assert result.regressions == []
    assert result.counts() == {"better": 0, "worse": 0, "unchanged": 1, "not comparable": 2}


def test_a_phase_measured_under_interference_cannot_gate_but_size_still_does() -> None:
    result = _pair(_samples(1.0, seed=1), _samples(1.5, seed=2), new_metrics={"interference": DISTURBED})
    cell = result.cells[0]
    assert cell.disturbed == ("new: latency: cpu busy (1 attempts, none clean)",)
    for name in ("p50", "p99"):
        assert _metric(result, name).verdict == "not comparable"
        assert _metric(result, name).why == ("latency measured under interference in new (re-run it on a quiet "
                                             "machine)")
    assert _metric(result, "throughput").verdict == "unchanged"  # its phase was clean
    assert cell.verdict == "not comparable" and result.regressions == []
    assert "not comparable ~" in comparison_markdown(result)
    bigger = _pair(_samples(1.0, seed=1), _samples(1.5, seed=2), new_metrics={"interference": DISTURBED,
                                                                              "size_bytes": 5_000_000})
    assert bigger.regressions == [(ORT.key, "size")]


@pytest.mark.parametrize(("text", "expected"), [("p50=10%", ("p50", 0.1)), ("size=1%", ("size", 0.01)),
                                                ("accuracy=0.002", ("accuracy", 0.002)),
                                                (" P99 = 2.5 % ", ("p99", 0.025))])
def test_thresholds_are_parsed(text: str, expected: tuple[str, float]) -> None:
    name, value = parse_threshold(text)
    assert name == expected[0] and value == pytest.approx(expected[1])


@pytest.mark.parametrize("text", ["p50", "latency=10%", "p50=ten%", "p50=-5%", "p50=10%%", ""])
def test_bad_thresholds_name_the_option_the_text_and_what_is_allowed(text: str) -> None:
    with pytest.raises(UserError) as error:
        parse_threshold(text)
    message = str(error.value)
    assert "--threshold" in message and repr(text) in message
    assert "p50, p99, throughput, size, accuracy" in message


def test_an_unknown_threshold_key_is_refused() -> None:
    with pytest.raises(ValueError, match="latency"):
        _pair(_samples(1.0), _samples(1.0), {"latency": 0.1})


def _two_models():
    fast, slow = _samples(1.0, seed=1), _samples(1.3, seed=2)
    before = _side("run 1", (_record(ORT, fast), fast), (_record(RESNET, fast, mse=None, top1=0.9), fast))
    after = _side("run 2", (_record(ORT, slow), slow),
                  (_record(RESNET, fast, mse=None, top1=0.9, throughput_sps=float("inf")), fast))
    return compare(before, after, alpha=0.01)


def test_json_holds_every_number_and_round_trips_without_nan() -> None:
    result = _two_models()
    data = json.loads(json.dumps(comparison_json(result), allow_nan=False))
    assert data["test"] == TEST and "Mann-Whitney U" in TEST and data["alpha"] == 0.01
    assert data["thresholds"]["p50"] == 0.2 and data["summary"]["worse"] == 1
    assert {"cell": ORT.key, "metric": "p50"} in data["regressions"]
    ort, resnet = data["cells"]
    assert ort["metrics"]["p50"]["p_value"] < 0.01 and ort["metrics"]["p50"]["change_kind"] == "relative"
    assert resnet["metrics"]["throughput"]["new"] is None
    assert resnet["metrics"]["accuracy"]["change_kind"] == "absolute"


def test_markdown_has_a_table_per_model_the_method_and_the_summary() -> None:
    text = comparison_markdown(_two_models())
    assert "## Comparing run 1 (base) → run 2 (new)" in text
    assert "### pilotnet" in text and "### resnet" in text and "| Accuracy (top1) |" in text
    assert "| **worse** |" in text and "Mann-Whitney U (two-sided)" in text and "p < 0.01" in text
    assert text.rstrip().endswith("**0 better, 1 worse, 0 unchanged, 1 not comparable**")


def test_the_terminal_table_shows_base_new_and_change_per_metric() -> None:
    console = Console(record=True, width=220)
    print_comparison(_two_models(), console)
    text = console.export_text()
    assert "Comparing run 1 (base) → run 2 (new)" in text and "(+30." in text
    assert "p < 0.01" in text and "0 better, 1 worse, 0 unchanged, 1 not comparable" in text
    assert "throughput: no throughput_sps in new" in text


def test_p99_counts_a_heavier_tail_not_a_few_outliers() -> None:
    base = _samples(1.0, seed=11)
    heavy = _samples(1.0, seed=12)
    heavy[::25] *= 3  # 4 % of the calls three times slower: the tail moved, the median did not
    result = _pair(base, heavy)
    assert _metric(result, "p99").verdict == "worse" and _metric(result, "p99").p_value < 1e-6
    assert _metric(result, "p50").verdict == "unchanged"
    few_base, few_new = _samples(1.0, n=20, seed=13), _samples(1.0, n=20, seed=14)
    few_new[-1] *= 5  # the p99 of 20 samples is their maximum: one outlier moves it 5x
    few = _pair(few_base, few_new)
    assert _metric(few, "p99").change > 1 and _metric(few, "p99").verdict == "unchanged"


def _throughput_side(label: str, rate: float, batches: np.ndarray) -> Side:
    record = _record(ORT, _samples(1.0, seed=15), throughput_sps=rate)
    return Side(label, [record], {ORT.key: _samples(1.0, seed=15)}, batches={ORT.key: batches})


def test_throughput_is_tested_on_the_batch_durations_where_stored() -> None:
    slower = compare(_throughput_side("a", 1000.0, _samples(8.0, n=60, seed=16)),
                     _throughput_side("b", 770.0, _samples(10.4, n=46, seed=17)))
    assert _metric(slower, "throughput").verdict == "worse" and _metric(slower, "throughput").p_value < 0.05
    noisy = compare(_throughput_side("a", 1000.0, np.array([8.0, 12.0, 6.0], np.float32)),
                    _throughput_side("b", 700.0, np.array([11.0, 7.0, 12.0], np.float32)))
    assert _metric(noisy, "throughput").change == pytest.approx(-0.3)
    assert _metric(noisy, "throughput").verdict == "unchanged"  # three batches each: not significant


def _speedup(value: float, half: float) -> dict[str, Any]:
    return {"value": value, "ci": [value / (1 + half), value * (1 + half)], "ci_half": half, "rounds": 9}


def test_p50_is_judged_on_the_paired_speedup_where_both_sides_have_one() -> None:
    slower_machine = (_samples(1.0, seed=1), _samples(1.3, seed=2))  # the whole machine 30 % slower in run 2
    held = _pair(*slower_machine, base_metrics={"speedup": _speedup(2.0, 0.02)},
                 new_metrics={"speedup": _speedup(2.02, 0.02)})
    p50 = _metric(held, "p50")
    assert p50.name == "speedup.value" and p50.verdict == "unchanged" and held.regressions == []
    assert _pair(*slower_machine).regressions  # without the paired figures the drift reads as a regression
    lost = _pair(_samples(1.0, seed=1), _samples(1.0, seed=2), base_metrics={"speedup": _speedup(2.0, 0.02)},
                 new_metrics={"speedup": _speedup(1.5, 0.02)})
    assert _metric(lost, "p50").verdict == "worse" and _metric(lost, "p50").change == pytest.approx(-0.25)
    vague = _pair(_samples(1.0, seed=1), _samples(1.0, seed=2), base_metrics={"speedup": _speedup(2.0, 0.3)},
                  new_metrics={"speedup": _speedup(1.5, 0.3)})
    assert _metric(vague, "p50").verdict == "unchanged"  # 25 % apart, but the intervals overlap
    one_side = _pair(_samples(1.0, seed=1), _samples(1.3, seed=2),
                     new_metrics={"speedup": _speedup(2.0, 0.02)})
    assert _metric(one_side, "p50").name == "latency_ms.p50"  # only one side paired: the raw samples judge
    console = Console(record=True, width=220)
    print_comparison(held, console)
    assert "2.00× → 2.02×" in console.export_text()


def _remeasured(ratio: float, half: float, thresholds: dict[str, float] | None = None):
    """A remeasured cell whose base time ÷ new time is `ratio` with a 95 % interval of ± `half` (relative)."""
    samples = _samples(1.0)
    before = _side("run 1", (_record(ORT, samples), samples))
    after = _side("run 2", (_record(ORT, samples), samples))
    twin = Speedup.from_json({"value": ratio, "ci": [ratio / (1 + half), ratio * (1 + half)],
                              "ci_half": half, "rounds": 10})
    return _metric(compare(before, after, thresholds, twins={ORT.key: twin}), "p50")


def test_a_remeasured_p50_gates_on_its_paired_interval_beyond_five_percent() -> None:
    assert _remeasured(1.0, 0.03).verdict == UNCHANGED  # unchanged, known to ±3 %
    assert _remeasured(1 / 1.03, 0.01).verdict == UNCHANGED  # a real +3 %: within 5 %
    slower = _remeasured(1 / 1.10, 0.03)  # +10 %, known to ±3 %: caught
    assert slower.verdict == WORSE and slower.threshold == 0.05 and slower.change == pytest.approx(0.10)
    assert _remeasured(1 / 1.10, 0.15).verdict == UNCHANGED  # +10 % but known only to ±15 %: cannot tell
    assert _remeasured(1 / 1.178, 0.03).verdict == WORSE  # the planted +17.8 % the 20 % default passed


def test_twins_the_rounds_could_not_pair_are_not_compared_on_their_samples() -> None:
    samples = _samples(1.0)
    before = _side("run 1", (_record(ORT, samples), samples))
    after = _side("run 2", (_record(ORT, _samples(1.3, seed=2)), _samples(1.3, seed=2)))  # a neighbour's 30 %
    p50 = _metric(compare(before, after, None, twins={ORT.key: Speedup()}), "p50")
    assert p50.verdict == NOT_COMPARABLE and "too busy to pair them" in p50.why


def test_a_p50_threshold_the_user_gives_still_decides_a_remeasured_cell() -> None:
    assert _remeasured(1 / 1.10, 0.03, {"p50": 0.2}).verdict == UNCHANGED
    assert _remeasured(1 / 1.03, 0.01, {"p50": 0.02}).verdict == WORSE
