"""Task-aware reports on hand-made stores: a classifier's top-1 columns and a label-free model's fidelity
columns, in the Markdown pages, the terminal tables and the CSV."""

from __future__ import annotations

import csv
import re
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console
from test_report import _record, new_store

from bench_matrix.cell import Cell
from bench_matrix.report import load, write_report

MIB = 2**20
NET_BASE = Cell("net", "pytorch", "pytorch", "none", "fp32", "cpu")
NET_INT8 = Cell("net", "pytorch", "onnxruntime", "ptq_static", "int8", "cpu")
ENC_BASE = Cell("encoder", "onnx", "onnxruntime", "none", "fp32", "cpu")
ENC_INT8 = Cell("encoder", "onnx", "onnxruntime", "ptq_dynamic", "int8", "cpu")


def _metrics(p50: float, **accuracy: Any) -> dict[str, Any]:
    return {"size_bytes": 4 * MIB, "size_gzip_bytes": 3 * MIB,
            "latency_ms": {"p50": p50, "p90": p50, "p99": p50}, "throughput_sps": 100.0, "peak_rss_mb": 300.0,
            **accuracy}


@pytest.fixture
def store_path(tmp_path: Path) -> Path:
    path = tmp_path / "results.sqlite"
    store = new_store(path)
    store.put(_record(NET_BASE, metrics=_metrics(2.0, top1=0.85, top5=0.99, top1_agreement=1.0,
                                                 max_abs_diff_vs_baseline=0.0, cosine_similarity=1.0,
                                                 snr_db=300.0)))
    store.put(_record(NET_INT8, metrics=_metrics(1.0, top1=0.8375, top5=0.98, top1_agreement=0.9625,
                                                 max_abs_diff_vs_baseline=0.25, cosine_similarity=0.9991,
                                                 snr_db=31.2, **{"f1.macro": 0.81})))
    store.put(_record(ENC_BASE, metrics=_metrics(4.0, max_abs_diff_vs_baseline=0.0, cosine_similarity=1.0,
                                                 snr_db=300.0)))
    store.put(_record(ENC_INT8, metrics=_metrics(2.0, max_abs_diff_vs_baseline=0.031,
                                                 cosine_similarity=0.9987654, snr_db=28.44)))
    store.put_fact("model:net", "info", {"framework": "pytorch", "baseline_key": NET_BASE.key,
                                         "task": "classification", "majority_top1": 0.4, "test_samples": 800})
    store.put_fact("model:encoder", "info",
                   {"framework": "onnx", "baseline_key": ENC_BASE.key, "task": "none"})
    store.close()
    return path


def _row(page: str, start: str) -> list[str]:
    line = next(line for line in page.splitlines() if line.startswith(f"| {start}"))
    return [cell.strip() for cell in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def _header(page: str) -> list[str]:
    return _row(page, "Method")


def test_accuracy_delta_is_the_tasks_headline(store_path: Path) -> None:
    report = load(store_path).report
    encoder, net = report.models
    assert (net.task, encoder.task) == ("classification", "none")
    int8 = next(r for r in net.rows if r.record.cell == NET_INT8)
    assert int8.accuracy_delta == pytest.approx(-0.0125) and int8.mse_delta is None
    enc = next(r for r in encoder.rows if r.record.cell == ENC_INT8)
    assert enc.accuracy_delta == pytest.approx(0.9987654 - 1.0)


def test_classification_page(store_path: Path, tmp_path: Path) -> None:
    write_report(store_path, "md", tmp_path / "md", Console(record=True))
    page = (tmp_path / "md" / "net.md").read_text()
    header = _header(page)
    assert header[header.index("gzip MiB") + 2:header.index("p50 ms")] == [
        "Top-1 % ↑", "ΔTop-1 pp", "Top-5 % ↑", "Agreement % ↑", "max \\|Δ\\| vs base ↓", "f1.macro"]
    assert "MSE ↓" not in header and "Cosine ↑" not in header
    row = dict(zip(header, _row(page, "onnxruntime ptq_static int8"), strict=True))
    assert (row["Top-1 % ↑"], row["ΔTop-1 pp"], row["Top-5 % ↑"], row["Agreement % ↑"]) == \
        ("83.75", "-1.25", "98.00", "96.25")
    assert row["f1.macro"] == "0.8100" and row["Speed-up"] == "2.00×"
    base = dict(zip(header, _row(page, "pytorch none fp32 (baseline)"), strict=True))
    assert base["ΔTop-1 pp"] == "0.00" and base["f1.macro"] == "—"
    assert ("Baseline test top-1 85.00 % vs majority-class top-1 40.00 % (always predicting the most common "
            "training class; higher is better) on 800 test samples.") in page
    assert ("- **Top-1 % ↑**: share of test samples whose highest logit is their labelled class, in %; "
            "higher is better.") in page
    assert "metric plugin `f1`" in page
    index = (tmp_path / "md" / "index.md").read_text()
    assert _row(index, "[net]")[-1] == "top-1 85.00 % (majority 40.00 %)"
    assert _row(index, "[encoder]")[-1] == "lowest cosine 0.998765"


def test_label_free_page(store_path: Path, tmp_path: Path) -> None:
    write_report(store_path, "md", tmp_path / "md", Console(record=True))
    page = (tmp_path / "md" / "encoder.md").read_text()
    header = _header(page)
    assert header[header.index("gzip MiB") + 2:header.index("p50 ms")] == [
        "max \\|Δ\\| vs base ↓", "Cosine ↑", "SNR dB ↑"]
    assert _row(page, "onnxruntime ptq_dynamic int8")[4:7] == ["0.0310", "0.998765", "28.4"]
    assert _row(page, "onnxruntime none fp32 (baseline)")[4:7] == ["0", "1.000000", "300.0"]
    assert "No labels: fidelity against the fp32 baseline only." in page
    assert "300 = identical; higher is better." in page


def test_terminal_tables_show_the_task_columns(store_path: Path, tmp_path: Path) -> None:
    console = Console(record=True, width=240, color_system=None)
    write_report(store_path, "table", tmp_path / "md", console)
    text = console.export_text()
    assert "Top-1" in text and "83.75" in text and "-1.25" in text and "Baseline test top-1 85.00 %" in text
    assert "Cosine" in text and "0.998765" in text
    assert "No labels: fidelity against the fp32 baseline only." in text


def test_csv_has_the_task_metrics(store_path: Path, tmp_path: Path) -> None:
    (path,) = write_report(store_path, "csv", tmp_path / "out", Console(record=True))
    rows = {r["key"]: r for r in csv.DictReader(path.open(newline=""))}
    net = rows[NET_INT8.key]
    assert (net["task"], net["top1"], net["top5"], net["top1_agreement"]) == \
        ("classification", "0.8375", "0.98", "0.9625")
    assert float(net["accuracy_delta_vs_baseline"]) == pytest.approx(-0.0125)
    assert net["mse_delta_vs_baseline"] == ""
    enc = rows[ENC_INT8.key]
    assert (enc["task"], enc["cosine_similarity"], enc["snr_db"]) == ("none", "0.9987654", "28.44")
    assert enc["top1"] == ""


def test_old_store_without_a_task_reports_regression(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    store = new_store(path)
    store.put(_record(NET_BASE, metrics=_metrics(2.0, mse=0.5, mae=0.6, max_abs_diff_vs_baseline=0.0)))
    store.put_fact("model:net", "info", {"framework": "pytorch", "baseline_key": NET_BASE.key,
                                         "test_mse": 0.5, "mean_predictor_mse": 1.0})
    store.close()
    page = write_report(path, "md", tmp_path / "md", Console(record=True))[1].read_text()
    header = _header(page)
    assert header[header.index("gzip MiB") + 2:header.index("p50 ms")] == [
        "MSE ↓", "ΔMSE", "MAE ↓", "max \\|Δ\\| vs base ↓"]
    assert "Baseline test MSE 0.5000 vs mean-predictor MSE 1.000; ratio 0.500" in page


def test_missing_baseline_names_the_tasks_delta(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    store = new_store(path)
    store.put(_record(NET_INT8, metrics=_metrics(1.0, top1=0.8)))
    store.put_fact("model:net", "info", {"framework": "pytorch", "task": "classification"})
    store.close()
    page = write_report(path, "md", tmp_path / "md", Console(record=True))[1].read_text()
    assert "speed-up, size ratio and ΔTop-1 are not available" in page
    assert "Baseline test top-1 — % vs majority-class top-1 — %" in page
    store = new_store(path)
    store.put_fact("model:net", "info", {"framework": "pytorch", "task": "classification",
                                         "test_metrics": {"top1": 0.5}, "majority_top1": 0.25})
    store.close()
    page = write_report(path, "md", tmp_path / "md", Console(record=True))[1].read_text()
    assert "Baseline test top-1 50.00 % vs majority-class top-1 25.00 %" in page  # as the preparation measured
