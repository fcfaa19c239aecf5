"""The verdict and the recommendation on records made by hand: every requirement kind, drops against the fp32
baseline for each task, uncertain on straddling intervals, ties, and where requirements are read from."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import pytest

from bench_matrix.cell import Cell
from bench_matrix.errors import MatrixError, UserError
from bench_matrix.matrix.require import parse_require, read_file
from bench_matrix.matrix.requirements import Declared, Requirements
from bench_matrix.report.analysis.recommend import Candidate, recommend
from bench_matrix.store import CellRecord
from bench_matrix.verdict import FAIL, PASS, UNCERTAIN, judge

MIB = 2**20
BASE = Cell("m", "pytorch", "pytorch", "none", "fp32", "cpu")


def record(backend: str = "onnxruntime", precision: str = "int8", target: str = "cpu", **metrics: Any
           ) -> CellRecord:
    cell = Cell("m", "pytorch", backend, "ptq_static" if precision == "int8" else "none", precision, target)
    return CellRecord(cell=cell, status="ok", metrics=metrics, env={"host": "h"})


def timed(p50: float, ci: tuple[float, float] | None = None, speedup: tuple[float, float] | None = None,
          **more: Any) -> dict[str, Any]:
    """Metrics with a p50 (and its interval) and a paired speed-up (value, relative half-width)."""
    out: dict[str, Any] = {"latency_ms": {"p50": p50, "p99": p50 * 2, **({"p50_ci": list(ci)} if ci else {})}}
    if speedup:
        value, half = speedup
        out["speedup"] = {"value": value, "ci": [value / (1 + half), value * (1 + half)], "ci_half": half}
    return {**out, **more}


def status(requirements: dict[str, Any], cell: CellRecord, task: str = "regression",
           baseline: CellRecord | None = None) -> tuple[str, list[str]]:
    verdict = judge(cell.metrics, Requirements.from_data(requirements), task, baseline and baseline.metrics)
    return verdict.status, [c.text for c in (verdict.failed or verdict.uncertain)]


@pytest.mark.parametrize(("key", "limit", "metrics", "expected"), [
    ("p50_ms", 10, timed(8.0, (7.5, 8.5)), PASS),
    ("p50_ms", 10, timed(12.0, (11.0, 13.0)), FAIL),
    ("p50_ms", 10, timed(9.8, (9.0, 10.6)), UNCERTAIN),  # within, but its interval straddles the limit
    ("p50_ms", 10, timed(10.2, (9.5, 10.9)), UNCERTAIN),  # beyond, but so does its interval
    ("p50_ms", 10, timed(9.8), PASS),  # no interval: judged by value
    ("p99_ms", 10, timed(4.0), PASS),  # p99 = 8
    ("p99_ms", 10, timed(6.0, (5.0, 7.0)), FAIL),  # p99 = 12: no interval of its own
    ("throughput_sps", 100, {"throughput_sps": 120.0, "throughput_ci": [110.0, 130.0]}, PASS),
    ("throughput_sps", 100, {"throughput_sps": 104.0, "throughput_ci": [95.0, 113.0]}, UNCERTAIN),
    ("throughput_sps", 100, {"throughput_sps": 80.0, "throughput_ci": [75.0, 85.0]}, FAIL),
    ("size_mib", 2, {"size_bytes": int(1.5 * MIB)}, PASS),
    ("size_mib", 2, {"size_bytes": 3 * MIB}, FAIL),
    ("peak_rss_mib", 300, {"peak_rss_mb": 250.0}, PASS),
    ("peak_rss_mib", 300, {"peak_rss_mb": 350.0}, FAIL),
    ("p50_ms", 10, {"size_bytes": 10}, FAIL),  # not measured: fails
])
def test_each_speed_and_size_requirement(key: str, limit: float, metrics: dict, expected: str) -> None:
    found, texts = status({key: limit}, record(**metrics))
    assert found == expected, texts
    if expected == FAIL:
        assert texts and texts[0].startswith(key)


def test_a_failure_says_by_how_much_and_every_requirement_missed() -> None:
    found, texts = status({"p50_ms": 10, "size_mib": 1, "mse": {"max": 0.5}},
                          record(**timed(12.5, (12.0, 13.0)), size_bytes=2 * MIB, mse=0.2))
    assert found == FAIL and texts == ["p50_ms 12.5 > 10 (25 % over)", "size_mib 2 > 1 (100 % over)"]
    found, texts = status({"throughput_sps": 1000}, record(throughput_sps=975.0))
    assert texts == ["throughput_sps 975 < 1e+03 (2.5 % under)"]
    found, texts = status({"p50_ms": 10}, record(**timed(9.8, (9.0, 10.6))))
    assert texts == ["p50_ms 9.8, 95 % interval 9–10.6 straddles 10"]


@pytest.mark.parametrize(("bound", "value", "expected"), [
    ({"min": 0.9}, 0.95, PASS), ({"min": 0.9}, 0.85, FAIL), ({"max": 0.99}, 0.995, FAIL),
    ({"min": 0.5, "max": 0.99}, 0.9, PASS)])
def test_absolute_bounds_on_a_recorded_metric(bound: dict, value: float, expected: str) -> None:
    assert status({"top1": bound}, record(top1=value), "classification")[0] == expected


def test_bounds_on_a_metric_plugin_figure_and_on_closed_loop_laps() -> None:
    assert status({"steer.err": {"max": 0.1}}, record(**{"steer.err": 0.05}))[0] == PASS
    assert status({"steer.err": {"max": 0.1}}, record(**{"steer.err": 0.2}))[0] == FAIL
    laps = {"simple": {"lock_step": {"completed_pct": 100.0, "deviation_mae_m": 0.2, "brain_hz": 20.0},
                       "real_time": {"completed_pct": 85.0, "deviation_mae_m": 0.6, "brain_hz": 12.0}}}
    driven = record(closed_loop=laps)
    assert status({"closed_loop": {"completed_pct": 80, "deviation_mae_m": 0.7}}, driven)[0] == PASS
    found, texts = status({"closed_loop": {"completed_pct": 90, "brain_hz": 19}}, driven)  # the worst lap's
    assert found == FAIL and texts == ["closed_loop.completed_pct 85 < 90 (5.6 % under)",
                                       "closed_loop.brain_hz 12 < 19 (37 % under)"]
    failed_lap = record(closed_loop={"simple": {"lock_step": {"failed": "the brain commanded v=nan"}}})
    assert status({"closed_loop": {"completed_pct": 0}}, failed_lap) == (FAIL, ["closed_loop.completed_pct "
                                                                                "not measured"])
    assert status({"closed_loop": {"completed_pct": 0}}, record())[0] == FAIL  # not driven


@pytest.mark.parametrize(("task", "key", "base", "drop", "value", "expected"), [
    ("regression", "mse", 0.0100, "5%", 0.0104, PASS),  # MSE: a relative increase
    ("regression", "mse", 0.0100, "5%", 0.0106, FAIL),
    ("regression", "mse", 0.0100, 0.001, 0.0109, PASS),  # absolute increase
    ("regression", "mse", 0.0100, 0.001, 0.0112, FAIL),
    ("regression", "mse", 0.0100, "5%", 0.0050, PASS),  # better than the baseline
    ("classification", "top1", 0.80, "1%", 0.795, PASS),  # top-1: a relative decrease
    ("classification", "top1", 0.80, "1%", 0.790, FAIL),
    ("classification", "top1", 0.80, 0.02, 0.785, PASS),  # absolute: percentage points as a fraction
    ("classification", "top1", 0.80, 0.02, 0.775, FAIL),
    ("none", "cosine_similarity", 1.0, 0.001, 0.9995, PASS),  # no labels: a floor on cosine similarity
    ("none", "cosine_similarity", 1.0, 0.001, 0.998, FAIL),
    ("none", "cosine_similarity", 1.0, "0.1%", 0.998, FAIL),
])
def test_max_drop_against_the_fp32_baseline(task: str, key: str, base: float, drop: Any, value: float,
                                            expected: str) -> None:
    baseline = CellRecord(cell=BASE, status="ok", metrics={key: base})
    found, texts = status({"max_drop": drop}, record(**{key: value}), task, baseline)
    assert found == expected, texts
    if expected == FAIL:
        assert "vs the baseline's" in texts[0] and "max_drop" in texts[0]


def test_max_drop_without_a_baseline_result() -> None:
    assert status({"max_drop": "5%"}, record(mse=0.01))[0] == FAIL  # nothing to compare with
    assert status({"max_drop": 0.001}, record(cosine_similarity=0.9995), "none")[0] == PASS  # 1 = identical
    assert status({"max_drop": 0.001}, record(cosine_similarity=0.99), "none")[0] == FAIL
    assert status({"snr_db": {"min": 40}}, record(snr_db=35.0), "none")[0] == FAIL


def test_max_drop_on_a_device_without_the_baseline_uses_the_baselines_prepared_test_metrics() -> None:
    """The baseline skipped there (no torch on a Pi): its MSE as the model was prepared, on as many
    samples."""
    from bench_matrix.report.analysis.judging import Judging, judged
    from bench_matrix.report.analysis.summary import summarize

    skipped = CellRecord(cell=BASE, status="skipped", reason="torch is not installed", env={"host": "h"})
    cells = [record("onnxruntime", mse=0.0102, test_samples=200),
             record("openvino", mse=0.015, test_samples=200)]
    info = {"baseline_key": BASE.key, "test_metrics": {"mse": 0.01}, "test_samples": 200}
    model = judged(summarize([skipped, *cells], {"m": info}, {}), {}, Judging(overrides={"max_drop": "5%"}))
    from bench_matrix.report.render.text import baseline_note

    rows = {row.record.cell.backend: row for row in model.models[0].rows}
    verdicts = {backend: row.verdict for backend, row in rows.items()}
    assert verdicts["onnxruntime"].status == PASS and verdicts["openvino"].status == FAIL
    assert rows["onnxruntime"].mse_delta == pytest.approx(0.0002) and rows["openvino"].speedup is None
    note = baseline_note(model.models[0])
    assert "ΔMSE is against its test metrics from where the model was prepared" in note
    assert "vs the baseline's 0.01" in verdicts["openvino"].failed[0].text
    other = summarize([skipped, cells[0]], {"m": {**info, "test_samples": 800}}, {})  # not the same samples
    (row,) = judged(other, {}, Judging(overrides={"max_drop": "5%"})).models[0].rows
    assert "no baseline MSE" in row.verdict.failed[0].text


def candidates(*cells: tuple[CellRecord, dict[str, Any]], baseline: CellRecord | None = None
               ) -> list[Candidate]:
    found = [Candidate(baseline, judge(baseline.metrics, Requirements(), "regression", None), True)
             ] if baseline else []
    return found + [Candidate(cell, judge(cell.metrics, Requirements.from_data(req), "regression", None))
                    for cell, req in cells]


def test_recommended_cell_runner_up_and_whether_they_are_distinguishable() -> None:
    fast = record("openvino", **timed(1.0, speedup=(3.0, 0.02)))
    close = record("onnxruntime", **timed(1.02, speedup=(2.95, 0.02)))
    slow = record("tflite", **timed(2.0, speedup=(1.5, 0.02)))
    (tie,) = recommend("m", candidates((fast, {}), (close, {}), (slow, {})), [], "p50")
    assert (tie.best, tie.runner_up, tie.distinguishable) == (fast, close, False)  # 3.0 vs 2.95 ± 2 % each
    assert tie.ratio == pytest.approx(3.0 / 2.95) and tie.ratio_ci[0] < 1 < tie.ratio_ci[1]
    (apart,) = recommend("m", candidates((fast, {}), (slow, {})), [], "p50")
    assert (apart.best, apart.runner_up, apart.distinguishable) == (fast, slow, True)
    assert apart.ratio == pytest.approx(2.0) and apart.passing == 2 and apart.judged == 2
    base = CellRecord(cell=BASE, status="ok", metrics=timed(2.0), env={"host": "h"})
    (against,) = recommend("m", candidates((record(**timed(1.96, speedup=(1.02, 0.03))), {}), baseline=base),
                           [], "p50")
    assert against.best.cell.backend == "onnxruntime" and against.runner_up is base
    assert against.distinguishable is False  # 1.02 ± 3 % includes the baseline's 1


def test_other_objectives_rank_by_their_figure() -> None:
    small = record("tflite", size_bytes=MIB, p50=1, throughput_sps=500.0, throughput_ci=[490.0, 510.0],
                   **timed(3.0))
    quick = record("openvino", size_bytes=4 * MIB, throughput_sps=900.0, throughput_ci=[880.0, 920.0],
                   **timed(1.0))
    found = candidates((small, {}), (quick, {}))
    (size,) = recommend("m", found, [], "size")
    assert (size.best, size.ratio, size.distinguishable) == (small, 4.0, True)
    (rate,) = recommend("m", found, [], "throughput")
    assert rate.best is quick and rate.ratio == pytest.approx(1.8) and rate.distinguishable is True
    (p99,) = recommend("m", found, [], "p99")
    assert p99.best is quick and p99.distinguishable is None  # p99 has no interval: judged by value
    (p50,) = recommend("m", found, [], "p50")  # no paired speed-ups: by p50, intervals absent
    assert p50.best is quick and p50.ratio == pytest.approx(3.0) and p50.distinguishable is None


def test_when_nothing_passes_the_closest_cells_and_what_they_miss() -> None:
    two = record("tflite", **timed(30.0), size_bytes=9 * MIB)
    one = record("openvino", **timed(12.0), size_bytes=MIB)
    straddles = record("onnxruntime", **timed(10.2, (9.5, 10.9)), size_bytes=MIB)
    gpu = record("onnxruntime", target="cuda", **timed(1.0), size_bytes=MIB)
    req = {"p50_ms": 10, "size_mib": 4}
    found = recommend("m", candidates((two, req), (one, req), (straddles, req), (gpu, req)),
                      [CellRecord(cell=Cell("m", "pytorch", "tflite", "none", "fp32", "npu"),
                                  status="failed")],
                      "p50")
    by_target = {r.target: r for r in found}
    assert set(by_target) == {"cpu", "cuda", "npu"}
    cpu = by_target["cpu"]
    assert cpu.best is None and [c.record for c in cpu.closest] == [straddles, one, two]
    assert cpu.to_json()["cell"] is None
    assert cpu.to_json()["closest"][1]["failed"][0]["requirement"] == "p50_ms"
    assert by_target["cuda"].best is gpu and by_target["npu"].best is None and by_target["npu"].judged == 0


def test_a_models_own_requirements_override_the_matrix_and_require_overrides_both() -> None:
    declared = Declared(Requirements.from_data({"p50_ms": 10, "max_drop": "5%",
                                                "closed_loop": {"completed_pct": 100, "brain_hz": 19}}),
                        {"big": Requirements.from_data({"p50_ms": 50, "closed_loop": {"brain_hz": 10}})})
    assert declared.of("small").data["p50_ms"] == 10
    big = declared.of("big")
    assert big.data == {"p50_ms": 50, "max_drop": "5%", "closed_loop": {"completed_pct": 100, "brain_hz": 10}}
    tried = declared.of("big", parse_require(["p50_ms=20", "objective=size", "top1.min=0.5"]))
    assert tried.data["p50_ms"] == 20 and tried.objective == "size" and tried.data["top1"] == {"min": 0.5}
    assert Declared.from_json(declared.to_json()) == declared
    assert big.describe() == ("p50_ms ≤ 50, max_drop 5 %, closed_loop.completed_pct ≥ 100, "
                              "closed_loop.brain_hz ≥ 10; objective p50")


@pytest.mark.parametrize(("given", "message"), [
    (["p50=3"], "--require p50: unknown key 'p50'; allowed: "),
    (["p50_ms=fast"], "--require p50_ms: expected number, got str 'fast'"),
    (["max_drop=five"], "--require max_drop: give the largest loss"),
    (["top1.min=0.9", "top1.max=0.5"], "--require top1: min 0.9 is above max 0.5"),
    (["objective=speed"], "--require objective: 'speed' is not allowed; allowed: p50, p99, size, throughput"),
    (["p50_ms"], "write KEY=VALUE")])
def test_bad_require_options(given: list[str], message: str) -> None:
    with pytest.raises(UserError) as raised:
        parse_require(given)
    assert message in str(raised.value)


def test_requirements_read_alone_from_a_matrix_file_with_located_problems(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    path.write_text("models:\n  - name: a\n    requirements: {p50_ms: 5}\n  - name: b\n"
                    "dataset: {npz: gone.npz}\nrequirements:\n  max_drop: 2%\n  objective: size\n")
    found = read_file(path)  # the rest of the file is not checked: the report needs only this
    assert found.of("a").data == {"max_drop": "2%", "objective": "size", "p50_ms": 5}
    assert found.of("b").objective == "size"
    path.write_text("models:\n  - name: a\n    requirements:\n      p99: 5\nrequirements:\n  size_mb: 1\n")
    with pytest.raises(MatrixError) as raised:
        read_file(path)
    assert raised.value.problems == [
        f"{path}:4: models[0].requirements.p99: unknown key 'p99'; allowed: " + _allowed("p99_ms"),
        f"{path}:6: requirements.size_mb: unknown key 'size_mb'; allowed: " + _allowed("size_mib")]


def _allowed(close: str) -> str:
    keys = ("closed_loop, cosine_similarity, mae, max_abs_diff_vs_baseline, max_drop, mse, objective, "
            "p50_ms, p99_ms, peak_rss_mib, size_mib, snr_db, stream, throughput_sps, top1, top1_agreement, "
            "top5")
    return f"{keys}; did you mean '{close}'?"


def test_the_verdict_counts_the_cells_that_failed_to_run_in_every_format(tmp_path: Path) -> None:
    """'Passing 2 of 4, 2 failed': failed cells are counted beside the judged ones, in every format."""
    from rich.console import Console

    from bench_matrix.report.analysis.judging import Judging, judged
    from bench_matrix.report.analysis.summary import summarize
    from bench_matrix.report.render import html, markdown
    from bench_matrix.report.render.export import report_json
    from bench_matrix.report.render.terminal import print_verdict

    ok = [record("onnxruntime", **timed(1.0), size_bytes=MIB),
          record("openvino", **timed(2.0), size_bytes=MIB)]
    failed = [CellRecord(cell=Cell("m", "pytorch", backend, "none", "fp32", "cpu"), status="failed",
                         env={"host": "h"}) for backend in ("tflite", "torchscript")]
    report = judged(summarize([*ok, *failed], {}, {}), {}, Judging(overrides={"p50_ms": 10}))
    (found,) = report.models[0].recommendations
    assert (found.passing, found.judged, found.failed) == (2, 2, 2)
    said = "2 of 4, 2 failed"
    console = Console(record=True, width=250, file=io.StringIO())
    print_verdict(report.models, console)
    assert said in console.export_text()
    assert f"| {said} |" in "\n".join(markdown.verdict(report.models))
    assert f">{said}</td>" in "".join(html._verdict(report))
    assert json.loads(report_json([*ok, *failed], report))["recommendations"][0]["failed"] == 2
