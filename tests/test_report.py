"""The report layer on a hand-made store: comparisons, Markdown pages, JSON, CSV, missing data and empty stores."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.report import load, write_report
from bench_matrix.report.render.export import CSV_COLUMNS
from bench_matrix.store import CellRecord, ResultStore, Status

MIB = 2**20
ENV = {"host": "bench-1", "os": "Linux 6.8", "cpu": "Test CPU", "cores": 8, "memory_gb": 31.3, "gpus": [],
       "python": "3.11.9", "libraries": {"torch": "2.4.0", "onnxruntime": "1.18.0"}, "bench_matrix": "0.1.0",
       "runtime": {"providers": ["CPUExecutionProvider"]}}
# the launcher's reason format: the error first, then the traceback lines that locate it
TRACEBACK = "RuntimeError: int8 | kernel missing\n  File \"convert.py\", line 3, in convert\n    raise RuntimeError"


def _metrics(p50: float, size_mib: float, mse: float) -> dict[str, Any]:
    return {"size_bytes": int(size_mib * MIB), "size_gzip_bytes": int(size_mib * MIB * 0.9), "params": 1000,
            "mse": mse, "mae": mse * 5, "mse_per_output": [mse], "max_abs_diff_vs_baseline": 1e-6,
            "latency_ms": {"mean": p50 * 1.1, "p50": p50, "p90": p50 * 1.5, "p99": p50 * 2, "std": 0.1,
                           "min": p50 * 0.9, "n": 200},
            "throughput_sps": 1000 / p50 * 8, "batch_size": 32, "peak_rss_mb": 250.5, "convert_s": 1.5,
            "load_s": 0.2, "threads": 4, "artifact_cached": False, "session": {"providers": ["CPUExecutionProvider"]}}


def _record(cell: Cell, status: Status = "ok", reason: str | None = None, metrics: dict[str, Any] | None = None,
            env: dict[str, Any] | None = None) -> CellRecord:
    return CellRecord(cell=cell, status=status, reason=reason, metrics=metrics or {}, env=ENV if env is None else env,
                      started_at="2024-05-01T10:00:00", finished_at="2024-05-01T10:00:05", fingerprint="f",
                      matrix="matrix.yaml", run_id=1)


def new_store(path: Path) -> ResultStore:
    """A new store holding run 1 (of matrix.yaml on bench-1), which `_record`'s records belong to."""
    store = ResultStore(path)
    store.begin_run("matrix.yaml", "bench-1", {"bench_matrix": "0.1.0"}, started_at="2024-05-01T10:00:00")
    return store


PILOT_BASE = Cell("pilotnet", "pytorch", "pytorch", "none", "fp32", "cpu")
PILOT_ORT = Cell("pilotnet", "pytorch", "onnxruntime", "none", "fp32", "cpu")
PILOT_PTQ = Cell("pilotnet", "pytorch", "onnxruntime", "ptq_dynamic", "int8", "cpu")
PILOT_CUDA = Cell("pilotnet", "pytorch", "onnxruntime", "none", "fp16", "cuda")
PILOT_TS = Cell("pilotnet", "pytorch", "torchscript", "ptq_static", "int8", "cpu")
TINY_BASE = Cell("tiny", "pytorch", "pytorch", "none", "fp32", "cpu")
TINY_ORT = Cell("tiny", "pytorch", "onnxruntime", "none", "fp32", "cpu")


@pytest.fixture
def store_path(tmp_path: Path) -> Path:
    path = tmp_path / "results.sqlite"
    store = new_store(path)
    other_env = {**ENV, "host": "bench-2", "libraries": {"torch": "2.5.0", "onnxruntime": "1.18.0"}}
    for record in (
        _record(PILOT_BASE, metrics=_metrics(2.0, 4.0, 0.0123)),
        _record(PILOT_ORT, metrics=_metrics(1.0, 2.0, 0.0124)),
        _record(PILOT_PTQ, metrics={"latency_ms": {"p50": 0.5}, "sparsity": 0.5, "clusters": 16, "finetune_s": 12.0}),
        _record(PILOT_CUDA, "skipped", "no NVIDIA GPU on this machine (no driver: nvidia-smi not found)"),
        _record(PILOT_TS, "failed", TRACEBACK),
        _record(TINY_BASE, metrics=_metrics(0.4, 0.1, 0.05), env=other_env),
        _record(TINY_ORT, "failed", "onnx export failed", env=other_env),
    ):
        store.put(record)
    store.put_fact("model:pilotnet", "info", {
        "framework": "pytorch", "source": "builtin pilotnet", "params": 252219, "baseline_key": PILOT_BASE.key,
        "test_mse": 0.0123, "mean_predictor_mse": 0.0615, "test_samples": 1000,
        "training": {"epochs": 10, "train_s": 42.0}})
    store.end_run(1, "2024-05-01T10:01:00", {"wall_s": 60.0, "counts": {"ok": 4, "skipped": 1, "failed": 2}})
    store.close()
    return path


def _console() -> Console:
    return Console(record=True, width=240, color_system=None)


def test_speedup_size_ratio_and_mse_delta(store_path: Path) -> None:
    report = load(store_path).report
    pilot = report.models[0]
    rows = {row.record.cell.key: row for row in pilot.rows}
    assert [row.record.cell for row in pilot.rows][:2] == [PILOT_BASE, PILOT_PTQ]  # baseline first, then by p50
    assert rows[PILOT_BASE.key].is_baseline and rows[PILOT_BASE.key].speedup == pytest.approx(1.0)
    assert rows[PILOT_ORT.key].speedup == pytest.approx(2.0)
    assert rows[PILOT_ORT.key].size_ratio == pytest.approx(2.0)
    assert rows[PILOT_ORT.key].mse_delta == pytest.approx(0.0001)
    assert rows[PILOT_PTQ.key].speedup == pytest.approx(4.0) and rows[PILOT_PTQ.key].size_ratio is None
    # within one runtime: ORT dynamic int8 (0.5 ms) against ORT fp32 (1.0 ms)
    assert rows[PILOT_PTQ.key].speedup_own_fp32 == pytest.approx(2.0)
    assert rows[PILOT_ORT.key].speedup_own_fp32 == pytest.approx(1.0)
    assert pilot.best is not None and pilot.best.record.cell == PILOT_PTQ
    assert [r.cell for r in pilot.skipped] == [PILOT_CUDA] and [r.cell for r in pilot.failed] == [PILOT_TS]
    assert report.counts == {"ok": 4, "skipped": 1, "failed": 2}


def test_markdown_pages(store_path: Path, tmp_path: Path) -> None:
    out = tmp_path / "reports"
    paths = write_report(store_path, "md", out, _console())
    assert paths == [out / "index.md", out / "pilotnet.md", out / "tiny.md"]
    index = (out / "index.md").read_text()
    assert "[pilotnet](pilotnet.md)" in index and "[tiny](tiny.md)" in index
    assert "Run 1 of 1 in the store: matrix matrix.yaml on bench-1" in index and "Host**: bench-1 / bench-2" in index
    assert "> - library versions differ between cells: torch (2.4.0, 2.5.0)" in index
    page = (out / "pilotnet.md").read_text()
    # size ratio 2×; not fine-tuned: dashes in the fine-tuning columns this model's table has
    assert "| onnxruntime none fp32 | 2.00 | 1.80 | 2.00× | — | — | — | 0.01240 | +1.00e-04 |" in page
    assert "Sparsity" not in (out / "tiny.md").read_text()  # no fine-tuned cell: no such columns
    assert "| 1.00 | 1.50 | 2.00 | 8000 | 250.5 | 2.00× |" in page  # speed-up 2×
    assert "| pytorch none fp32 (baseline) |" in page
    assert "ratio 0.200 (below 1" in page
    missing = "| onnxruntime ptq_dynamic int8 | — | — | — | 0.500 | 16 | 12 | — | — | — | — | 0.500 | — | — | — | — | 4.00× |"
    assert missing in page  # missing metrics render as dashes
    table = [line for line in page.split("## Results")[1].split("## Skipped")[0].splitlines() if line.startswith("|")]
    assert len(table) == 5 and len({line.replace("\\|", "").count("|") for line in table}) == 1
    assert "no NVIDIA GPU on this machine" in page  # skipped reason
    assert "RuntimeError: int8 \\| kernel missing" not in page.split("## Failed")[0]
    assert "<code>pilotnet/torchscript/ptq_static/int8/cpu</code>: RuntimeError: int8 | kernel missing" in page
    assert 'File "convert.py", line 3' in page  # the full failure text
    assert "onnx export failed" in (out / "tiny.md").read_text()
    first = [p.read_bytes() for p in paths]
    write_report(store_path, "md", out, _console())
    assert [p.read_bytes() for p in paths] == first  # deterministic


def test_table_prints_tables_and_writes_markdown(store_path: Path, tmp_path: Path) -> None:
    console = _console()
    paths = write_report(store_path, "table", tmp_path / "reports", console)
    text = console.export_text()
    assert len(paths) == 4 and all(p.is_file() for p in paths) and paths[-1].name == "report.html"
    assert "onnxruntime none fp32" in text and "2.00×" in text
    assert "no NVIDIA GPU on this machine" in text
    assert "RuntimeError: int8 | kernel missing" in text and "convert.py" not in text  # failed: the error line only
    assert "mean-predictor MSE 0.0615" in text and "bench-1 / bench-2" in text
    narrow = Console(record=True, width=80, color_system=None)
    write_report(store_path, "table", tmp_path / "reports", narrow)
    text = narrow.export_text()
    assert "pilotnet: size" in text and "pilotnet: speed" in text and "…" not in text  # split, not truncated


def test_json_is_the_records(store_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert write_report(store_path, "json", tmp_path, _console()) == []
    data = json.loads(capsys.readouterr().out)["records"]
    assert len(data) == 7
    assert set(data[0]) == {"cell", "status", "reason", "metrics", "artifact_path", "env", "started_at",
                            "finished_at", "fingerprint", "matrix", "host", "run", "record"}
    assert {d["run"] for d in data} == {1} and len({d["record"] for d in data}) == 7
    assert {d["cell"]["model"] for d in data} == {"pilotnet", "tiny"}


def test_csv_one_flat_row_per_record(store_path: Path, tmp_path: Path) -> None:
    (path,) = write_report(store_path, "csv", tmp_path / "out", _console())
    assert path == tmp_path / "out" / "results.csv"
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 7 and tuple(rows[0]) == CSV_COLUMNS
    for column in ("latency_p50_ms", "latency_p90_ms", "latency_p99_ms", "size_mib", "size_gzip_mib", "mse",
                   "throughput_sps", "speedup_vs_baseline", "size_ratio_vs_baseline"):
        assert column in CSV_COLUMNS
    ort = next(r for r in rows if r["key"] == PILOT_ORT.key)
    assert float(ort["speedup_vs_baseline"]) == 2.0 and float(ort["size_mib"]) == 2.0 and ort["threads"] == "4"
    assert (ort["host"], ort["run"]) == ("bench-1", "1")
    tuned = next(r for r in rows if r["key"] == PILOT_PTQ.key)
    assert (tuned["sparsity"], tuned["clusters"], tuned["finetune_s"]) == ("0.5", "16", "12")
    assert ort["sparsity"] == ""
    failed = next(r for r in rows if r["key"] == PILOT_TS.key)
    assert failed["status"] == "failed" and failed["reason"] == "RuntimeError: int8 | kernel missing"
    assert failed["latency_p50_ms"] == "" and failed["speedup_vs_baseline"] == ""


def test_model_without_facts_or_baseline(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    store = new_store(path)
    store.put(_record(PILOT_ORT, metrics={"latency_ms": {"p50": 1.0}}, env={}))
    store.put(_record(PILOT_BASE, "failed", None, env={}))
    store.close()
    paths = write_report(path, "md", tmp_path / "md", _console())
    page = paths[1].read_text()
    assert "No baseline is recorded for this model" in page  # no facts: nothing is guessed
    assert "Baseline test MSE — vs mean-predictor MSE —." in page
    assert "no environment stored" in page and "(no reason stored)" in page
    write_report(path, "table", tmp_path / "md", _console())


@pytest.mark.parametrize("fmt", ["table", "md", "json", "csv"])
def test_missing_and_empty_store(tmp_path: Path, fmt: str) -> None:
    missing = tmp_path / "missing.sqlite"
    with pytest.raises(UserError, match=r"bench-matrix run MATRIX"):
        write_report(missing, fmt, tmp_path, _console())
    assert not missing.exists()
    ResultStore(tmp_path / "empty.sqlite").close()
    with pytest.raises(UserError, match=r"holds no results.*bench-matrix run MATRIX"):
        write_report(tmp_path / "empty.sqlite", fmt, tmp_path, _console())


def test_unknown_format(store_path: Path, tmp_path: Path) -> None:
    with pytest.raises(UserError, match="table, md, html, json, csv"):
        write_report(store_path, "pdf", tmp_path, _console())


def test_report_imports_no_framework(store_path: Path, tmp_path: Path) -> None:
    code = ("import sys\nfrom rich.console import Console\nfrom bench_matrix.report import write_report\n"
            f"write_report({str(store_path)!r}, 'table', {str(tmp_path / 'r')!r}, Console(file=sys.stderr))\n"
            "heavy = [m for m in ('torch', 'onnxruntime', 'tensorflow') if m in sys.modules]\n"
            "assert not heavy, heavy\n")
    root = Path(__file__).resolve().parents[1]
    result = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                            env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"}, check=False)
    assert result.returncode == 0, result.stderr


def test_not_a_store(tmp_path: Path) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("not sqlite, just text that is long enough to have a header " * 4)
    with pytest.raises(UserError, match="not a bench-matrix results store"):
        write_report(path, "md", tmp_path, _console())


def test_unsteady_latency_of_a_record_before_interference_was_measured_is_marked(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    store = new_store(path)
    store.put(_record(PILOT_BASE, metrics={"latency_ms": {"p50": 2.0}, "latency_stability": 0.01}, env={}))
    store.put(_record(PILOT_ORT, metrics={"latency_ms": {"p50": 1.0}, "latency_stability": 0.3}, env={}))
    store.close()
    page = write_report(path, "md", tmp_path / "md", _console())[1].read_text()
    assert "| 1.00 ~ |" in page and "| 2.00 |" in page
    drifted = "onnxruntime none fp32: latency: chunk medians drifted by 30% (limit 5%)"
    assert f"> **Wide (~):** {drifted}" in page and "> **Disturbed" not in page


WHY = "other processes took 45% of the measuring CPU(s) (limit 10%)"
DRIFT = "chunk medians drifted by 12% (limit 5%)"


def _attempt(other_share: float, unsteady: str | None = None) -> dict[str, Any]:
    return {"wall_s": 2.0, "other_share": other_share, "machine_share": other_share / 2, "steal_share": 0.0,
            "preemptions_per_s": 3.0, "disturbed": WHY if other_share > 0.1 else None, "unsteady": unsteady}


def _timed(p50: float, latency: dict[str, Any]) -> dict[str, Any]:
    """Metrics with a confidence interval and an interference record holding these latency attempts."""
    kept = latency["attempts"][latency["kept"]]
    metrics = _metrics(p50, 1.0, 0.01)
    metrics["latency_ms"].update(p50_ci=[p50 * 0.99, p50 * 1.03], p50_ci_rel=0.04)
    metrics["interference"] = {
        "flagged": bool(kept["disturbed"]), "reason": f"latency: {WHY}" if kept["disturbed"] else None,
        "phases": {"latency": latency, "throughput": {"attempts": [_attempt(0.0)], "kept": 0}}}
    return metrics


def test_a_cell_flagged_for_interference_is_marked_in_every_format(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    store = new_store(path)
    clean = {"attempts": [_attempt(0.45), _attempt(0.01)], "kept": 1}  # re-measured, then clean
    store.put(_record(PILOT_BASE, metrics=_timed(2.0, clean)))
    store.put(_record(PILOT_ORT, metrics=_timed(1.0, {"attempts": [_attempt(0.45)] * 3, "kept": 2})))
    unsteady = [_attempt(0.45), _attempt(0.0, DRIFT), _attempt(0.0, DRIFT)]
    store.put(_record(PILOT_PTQ, metrics=_timed(0.5, {"attempts": unsteady, "kept": 1})))
    store.close()
    page = write_report(path, "md", tmp_path / "md", _console())[1].read_text()
    reason = f"{WHY} (3 attempts, none clean)"
    assert f"> **Disturbed (~):** onnxruntime none fp32: latency: {reason}" in page
    drifting = f"onnxruntime ptq_dynamic int8: latency: {DRIFT} (3 attempts, none clean)"
    assert f"> **Wide (~):** {drifting}" in page
    assert "| 1.00 ~ | 2.0 | 1.50 ~ | 2.00 ~ | 8000 |" in page  # latency figures marked, throughput clean
    assert "| 0.500 ~ | 2.0 | 0.750 ~ | 1.00 ~ | 16000 |" in page
    assert "| 2.00 | 2.0 | 3.00 | 4.00 | 4000 |" in page  # re-measured clean: no mark; CI ±2 %
    assert "p50 CI ±%" in page
    console = _console()
    write_report(path, "table", tmp_path / "md", console)
    assert f"Disturbed (~): onnxruntime none fp32: latency: {reason}" in console.export_text()
    (csv_path,) = write_report(path, "csv", tmp_path / "csv", _console())
    with csv_path.open(newline="") as handle:
        rows = {row["key"]: row for row in csv.DictReader(handle)}
    flagged, clean, drifting = rows[PILOT_ORT.key], rows[PILOT_BASE.key], rows[PILOT_PTQ.key]
    assert (flagged["interference_flagged"], flagged["interference_reason"]) == ("true", f"latency: {reason}")
    assert (clean["interference_flagged"], clean["interference_reason"]) == ("false", "")
    assert drifting["interference_flagged"] == "false"  # unsteady, not disturbed
    assert float(clean["latency_p50_ci_low_ms"]) == pytest.approx(1.98)
    assert float(clean["latency_p50_ci_high_ms"]) == pytest.approx(2.06)


def test_the_environment_names_every_backends_libraries_plugins_included():
    from bench_matrix.report.analysis.summary import environment
    from bench_matrix.store import CellRecord

    cell = Cell("m", "onnx", "openvino", "none", "fp32", "npu")
    env = {"host": "h", "libraries": {"numpy": "2.0"}, "backend_versions": {"openvino": "2025.1"}}
    libraries = dict(environment([CellRecord(cell=cell, status="ok", env=env)]).libraries)
    assert libraries == {"numpy": ("2.0",), "openvino": ("2025.1",)}


def test_the_environment_shows_the_cpu_frequency_policy_in_one_line_and_warns_when_it_differs():
    from bench_matrix.report.analysis.summary import environment
    from bench_matrix.store import CellRecord

    hidden = {"scaling_driver": "not exposed", "scaling_governor": "not exposed", "boost": "not exposed",
              "intel_no_turbo": "not exposed"}
    shown = {"scaling_driver": "acpi-cpufreq", "scaling_governor": {"0": "performance", "1": "performance"},
             "boost": "1", "intel_no_turbo": "not exposed"}
    cells = [Cell("m", "onnx", "onnxruntime", "none", p, "cpu") for p in ("fp32", "fp16")]
    found = environment([CellRecord(cell=c, status="ok", env={"cpu_frequency": state})
                         for c, state in zip(cells, (hidden, shown))])
    assert dict(found.fields)["CPU frequency"] == ("driver acpi-cpufreq, governor performance, boost 1",
                                                   "not exposed by this machine")
    assert any(w.startswith("CPU frequency differs") for w in found.warnings)


@pytest.mark.parametrize("facts, said", [
    ([{"rounds": 9, "stop": "budget", "window_s": 0.1, "processes": 2, "model_spread": 0.0123}],
     "Timed in 9 interleaved rounds of 0.1 s windows, each cell in 2 processes (they differed by 1.2%, in "
     "the intervals), each round in a fresh random order; 1 stopped by the time budget;"),
    ([{"rounds": 5, "stop": "width", "window_s": 0.1, "processes": 2, "model_spread": 0.0},
      {"rounds": 8, "stop": "width", "window_s": 0.1, "processes": 2, "model_spread": 0.0}],
     "Timed in 5–8 interleaved rounds of 0.1 s windows, each cell in 2 processes (they differed by no more "
     "than their windows' own noise), each round in a fresh random order; p50"),
    ([{"rounds": 8, "stop": "budget", "window_s": 0.1, "processes": 2, "visits": 2.625, "model_spread": 0.0},
      {"rounds": 8, "stop": "budget", "window_s": 0.1, "processes": 2, "visits": 1.0, "model_spread": 0.0}],
     "noise), each round in a fresh random order (the baseline 2.6 times a round); 2 stopped by the time"),
    ([{"rounds": 9, "stop": "budget", "window_s": 0.2}],  # records from before the processes
     "Timed in 9 interleaved rounds of 0.2 s windows, per cell, each round"),
])
def test_the_caption_says_how_the_cells_were_timed(facts: list[dict], said: str) -> None:
    from types import SimpleNamespace

    from bench_matrix.measurement import Measurement
    from bench_matrix.report.render.text import timing_line

    rows = [SimpleNamespace(record=SimpleNamespace(metrics=Measurement.from_json({"rounds": f})))
            for f in facts]
    assert said in timing_line(SimpleNamespace(rows=rows))
