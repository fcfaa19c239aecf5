"""Records that cannot be right, from their stored figures: each fails its verdict naming why, is listed in
every report format, and is never recommended, however small or fast it is."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.report.analysis.judging import Judging, judged
from bench_matrix.report.analysis.plausible import implausible
from bench_matrix.report.analysis.summary import Report, summarize
from bench_matrix.report.render import html, markdown
from bench_matrix.report.render.terminal import print_report
from bench_matrix.store import CellRecord

PARAMS = 252_236
BASELINE = Cell("m", "onnx", "onnxruntime", "none", "fp32", "cpu")


def record(backend: str, precision: str, strategy: str = "none", **metrics: Any) -> CellRecord:
    cell = Cell("m", "onnx", backend, strategy, precision, "cpu")
    figures = {"params": PARAMS, "size_bytes": PARAMS * 4, "snr_db": 120.0, "outputs_sha256": cell.key,
               "latency_ms": {"p50": 1.0, "p99": 2.0}, "mse": 0.05, **metrics}
    return CellRecord(cell=cell, status="ok", metrics=figures, env={"host": "h"})


def report(*records: CellRecord, **requirements: Any) -> Report:
    infos = {"m": {"framework": "onnx", "baseline_key": BASELINE.key, "task": "regression"}}
    return judged(summarize(list(records), infos, {}), {}, Judging(overrides=requirements))


def test_each_kind_of_impossible_record_is_found_and_the_plausible_ones_are_not() -> None:
    baseline = record("onnxruntime", "fp32", snr_db=300.0, outputs_sha256="fp32")
    pointer = record("openvino", "int8", size_bytes=27, snr_db=30.0)
    fake = record("tflite", "int8", size_bytes=PARAMS, outputs_sha256="fp32")
    views = record("openvino", "fp32", snr_db=25.0)
    fine = [record("tflite", "fp16", size_bytes=PARAMS * 2, snr_db=65.0),
            record("onnxruntime", "fp16", size_bytes=PARAMS * 2, outputs_sha256="fp32"),  # a Suspect note
            record("tflite", "int8", "ptq_static", size_bytes=PARAMS, snr_db=30.0),
            record("pytorch", "fp32", "prune", snr_db=25.0),  # fine-tuned: not the baseline's weights
            record("onnxruntime", "int8", "ptq_dynamic", size_bytes=PARAMS // 2 + 1, snr_db=30.0)]
    found = implausible([baseline, pointer, fake, views, *fine])
    assert set(found) == {pointer.cell.key, fake.cell.key, views.cell.key}, found
    assert found[pointer.cell.key].startswith("its artifact is 27 bytes, but its 252,236 parameters take "
                                              "252,236 at int8")
    assert found[fake.cell.key] == ("its outputs are bit-identical to onnxruntime none fp32's: int8 was not "
                                    "applied")
    assert "25.0 dB SNR to the baseline's, where float noise stays above 60 dB" in found[views.cell.key]


def test_an_impossible_record_fails_its_verdict_is_listed_everywhere_and_is_not_recommended(tmp_path: Path
                                                                                         ) -> None:
    baseline = record("onnxruntime", "fp32")
    honest = record("onnxruntime", "int8", "ptq_static", size_bytes=PARAMS, snr_db=30.0)
    pointer = record("openvino", "int8", "ptq_static", size_bytes=27, snr_db=30.0)
    made = report(baseline, honest, pointer, objective="size", p50_ms=10)
    (model,) = made.models
    (found,) = model.recommendations
    assert found.best is honest and found.passing == 2, found
    verdict = next(row.verdict for row in model.rows if row.record is pointer)
    assert verdict.status == "fail", verdict.short()
    assert verdict.short().startswith("fail: implausible: its artifact is 27 bytes"), verdict.short()
    assert verdict.to_json()["failed"][0]["requirement"] == "plausible"
    said = "openvino ptq_static int8: its artifact is 27 bytes"
    console = Console(record=True, width=400, file=io.StringIO())
    print_report(made, console)
    assert f"Implausible: {said}" in console.export_text()
    assert f"> **Implausible:** {said}" in markdown.model_page(model, [], tmp_path)
    assert f"<strong>Implausible:</strong> {said}" in "".join(html._notes(model))
