"""The typed measurement: records of real runs and of older releases read in and written back identical."""

from __future__ import annotations

import json
import sqlite3
import sys
from contextlib import closing
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from conftest import cli, onnx_matrix_text  # noqa: E402

from bench_matrix.cell import Cell  # noqa: E402
from bench_matrix.executors import codec  # noqa: E402
from bench_matrix.jobs.results import Measured  # noqa: E402
from bench_matrix.measurement import Measurement  # noqa: E402
from bench_matrix.progress import describe  # noqa: E402
from bench_matrix.store import CellRecord, ResultStore  # noqa: E402

# a record of a release before intervals, interference, passes, rounds and fidelity metrics were stored
OLD = {"latency_ms": {"mean": 1.25, "p50": 1.2, "p90": 1.4, "p99": 1.9, "std": 0.1, "min": 1.0, "n": 200},
       "throughput_sps": 950.5, "batch_size": 8, "peak_rss_mb": 310.2, "mse": 0.0125, "mae": 0.08,
       "max_abs_diff_vs_baseline": 0.0, "test_samples": 50, "size_bytes": 2 ** 20, "files": 1, "params": 1234,
       "convert_s": 0.5, "artifact_cached": False, "load_s": 0.01, "threads": 1}


def test_records_of_a_real_run_read_back_to_identical_json(onnx_project: Path) -> None:
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32", "fp16"]))
    assert cli(onnx_project, "run", "m.yaml").returncode == 0
    path = onnx_project / "ws" / "results.sqlite"
    with closing(sqlite3.connect(path)) as db:
        stored = dict(db.execute("SELECT id, metrics FROM records WHERE status = 'ok'").fetchall())
    assert len(stored) == 2
    for text in stored.values():
        measurement = Measurement.from_json(json.loads(text))
        assert json.dumps(measurement.to_json()) == text
        assert measurement.latency.p50 > 0 and measurement.latency.p50_ci_rel is not None
        assert measurement.rounds.rounds >= 2 and measurement.size.bytes > 0
        assert measurement.rounds.stop in ("width", "budget") and measurement.passes.p50 is None
        assert codec.from_json(Measured, json.loads(json.dumps(codec.to_json(
            Measured(measurement, {}, {}))))).metrics == measurement  # the job's result, between processes
    records = ResultStore(path, readonly=True).records()
    assert {r.id: json.dumps(r.to_json()["metrics"]) for r in records if r.status == "ok"} == stored


def test_an_old_record_opens_with_its_newer_fields_absent(tmp_path: Path) -> None:
    measurement = Measurement.from_json(OLD)
    assert measurement.to_json() == OLD and list(measurement.to_json()) == list(OLD)
    assert measurement.latency.p50_ci is None and measurement.interference is None
    assert measurement.passes.p50 is None
    assert measurement.passes.made == 1 and measurement.task.figure("mse") == 0.0125
    assert measurement.task.cosine is None and measurement.memory.gpu_mb is None
    store = ResultStore(tmp_path / "results.sqlite")
    run = store.begin_run("m.yaml", "h", {})
    record = CellRecord(Cell("tiny", "onnx", "onnxruntime", "none", "fp32", "cpu"), "ok", metrics=OLD,
                        env={"host": "h"}, run_id=run.id)
    store.put(record)
    (read,) = store.records()
    assert read.metrics == measurement and json.dumps(read.to_json()["metrics"]) == json.dumps(OLD)
    assert "p50 1.2 ms" in describe(read)


def test_scenario_and_plugin_fields_keep_their_place() -> None:
    data = {"latency_ms": {"p50": 2.0, "extra": [1]}, "closed_loop": {"laps": []}, "steer.rmse": 0.5,
            "interference": {"flagged": True, "reason": "busy", "phases": {}}, "top1": 0.9}
    measurement = Measurement.from_json(data)
    assert json.dumps(measurement.to_json()) == json.dumps(data)
    assert measurement.others == {"closed_loop": {"laps": []}, "steer.rmse": 0.5}
    assert measurement.interference.flagged and measurement.task.top1 == 0.9
    changed = Measurement.from_json({**measurement.to_json(), "latency_passes_p50": [2.0], "top1": 0.8})
    assert list(changed.to_json()) == [*data, "latency_passes_p50"] and changed.task.top1 == 0.8
    assert changed.figure("top1") == 0.8 and changed.figure("steer.rmse") == 0.5
    assert changed.figure("throughput_sps") is None and changed.figure("no_such") is None
    assert changed != measurement and changed == Measurement.from_json(changed.to_json())
