"""GPU cells in the report: the suspect flag for bit-identical outputs across precisions, end-to-end latency and
GPU memory columns, and their CSV fields (a hand-made store: no GPU needed)."""

from __future__ import annotations

import csv
from pathlib import Path

from rich.console import Console
from test_report import _metrics, _record, new_store

from bench_matrix.cell import Cell
from bench_matrix.report import load, write_report

BASE = Cell("pilotnet", "pytorch", "pytorch", "none", "fp32", "cpu")
CUDA32 = Cell("pilotnet", "pytorch", "pytorch", "none", "fp32", "cuda")
CUDA16 = Cell("pilotnet", "pytorch", "pytorch", "none", "fp16", "cuda")
TS32 = Cell("pilotnet", "pytorch", "torchscript", "none", "fp32", "cuda")
TRT16 = Cell("pilotnet", "pytorch", "onnxruntime", "none", "fp16", "tensorrt")


def _gpu(p50: float, e2e: float, sha: str) -> dict:
    return {**_metrics(p50, 4.0, 0.0123), "latency_ms_e2e": {"p50": e2e, "n": 200}, "peak_gpu_mem_mb": 612.0,
            "gpu_name": "NVIDIA H100 80GB HBM3", "outputs_sha256": sha}


def _store(tmp_path: Path, fp16_sha: str) -> Path:
    path = tmp_path / "results.sqlite"
    store = new_store(path)
    store.put(_record(BASE, metrics={**_metrics(2.0, 4.0, 0.0123), "outputs_sha256": "a" * 64}))
    store.put(_record(CUDA32, metrics=_gpu(0.30, 0.41, "b" * 64)))
    store.put(_record(TS32, metrics=_gpu(0.25, 0.36, "b" * 64)))  # same precision, same bits: legitimate
    store.put(_record(CUDA16, metrics=_gpu(0.31, 0.40, fp16_sha)))
    store.put(_record(TRT16, metrics=_gpu(0.12, 0.20, "c" * 64)))
    store.put_fact("model:pilotnet", "info", {"framework": "pytorch", "baseline_key": BASE.key})
    store.close()
    return path


def test_bit_identical_outputs_at_different_precisions_are_suspect(tmp_path: Path) -> None:
    report = load(_store(tmp_path, "b" * 64)).report
    (suspect,) = report.models[0].suspects
    assert "fp16 and fp32" in suspect and CUDA16.key in suspect and CUDA32.key in suspect and TS32.key in suspect
    assert BASE.key not in suspect and TRT16.key not in suspect
    console = Console(record=True, width=240, color_system=None)
    write_report(tmp_path / "results.sqlite", "table", tmp_path / "reports", console)
    assert "Suspect: outputs are bit-identical at fp16 and fp32" in console.export_text()
    assert "> **Suspect:** outputs are bit-identical at fp16 and fp32" in (tmp_path / "reports/pilotnet.md").read_text()


def test_distinct_outputs_are_not_suspect(tmp_path: Path) -> None:
    report = load(_store(tmp_path, "d" * 64)).report
    assert report.models[0].suspects == ()
    write_report(tmp_path / "results.sqlite", "md", tmp_path / "reports", Console(record=True))
    assert "Suspect" not in (tmp_path / "reports/pilotnet.md").read_text()


def test_end_to_end_latency_and_gpu_memory_columns(tmp_path: Path) -> None:
    write_report(_store(tmp_path, "d" * 64), "md", tmp_path / "reports", Console(record=True))
    page = (tmp_path / "reports/pilotnet.md").read_text()
    header = next(line for line in page.splitlines() if line.startswith("| Method"))
    assert "e2e p50 ms" in header and "GPU MiB" in header
    row = next(line for line in page.splitlines() if line.startswith("| onnxruntime none fp16 tensorrt"))
    assert "| 0.120 | 0.200 |" in row and "| 612 |" in row
    base = next(line for line in page.splitlines() if line.startswith("| pytorch none fp32 (baseline)"))
    assert base.count("—") >= 2  # a CPU cell has neither figure


def test_csv_carries_the_gpu_fields(tmp_path: Path) -> None:
    out = write_report(_store(tmp_path, "d" * 64), "csv", tmp_path / "reports", Console(record=True))
    rows = {r["key"]: r for r in csv.DictReader(out[0].open())}
    trt = rows[TRT16.key]
    assert (trt["latency_e2e_p50_ms"], trt["peak_gpu_mem_mb"]) == ("0.2", "612")
    assert trt["gpu_name"] == "NVIDIA H100 80GB HBM3" and trt["outputs_sha256"] == "c" * 64
    assert rows[BASE.key]["latency_e2e_p50_ms"] == "" and rows[BASE.key]["gpu_name"] == ""
