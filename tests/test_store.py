"""ResultStore: records survive reconnection, replace by cell, round-trip their JSON."""

from __future__ import annotations

from bench_matrix.cell import Cell
from bench_matrix.store import CellRecord, ResultStore

CELL = Cell("m", "pytorch", "onnxruntime", "none", "fp32", "cpu")


def test_put_get_replace_and_persist(tmp_path):
    path = tmp_path / "r.sqlite"
    store = ResultStore(path)
    store.put(CellRecord(CELL, "failed", reason="boom", fingerprint="f1"))
    store.put(CellRecord(CELL, "ok", metrics={"latency_ms": {"p50": 1.5}}, env={"host": "h"}, fingerprint="f2"))
    store.put(CellRecord(Cell("m", "pytorch", "pytorch", "none", "fp32", "cpu"), "skipped", reason="no GPU"))
    store.put_fact("model:m", "info", {"params": 3})
    store.close()

    again = ResultStore(path)  # a new process sees everything that was committed
    record = again.get(CELL)
    assert record.status == "ok" and record.reason is None and record.fingerprint == "f2"
    assert record.metrics["latency_ms"]["p50"] == 1.5
    assert [r.cell.backend for r in again.records()] == ["onnxruntime", "pytorch"]
    assert again.facts("model:m") == {"info": {"params": 3}}
    assert again.get(Cell("x", "pytorch", "pytorch", "none", "fp32", "cpu")) is None
    doc = record.to_json()
    assert set(doc) >= {"cell", "status", "reason", "metrics", "artifact_path", "env", "started_at", "finished_at"}
    assert doc["cell"] == {"model": "m", "framework": "pytorch", "backend": "onnxruntime", "strategy": "none",
                           "precision": "fp32", "target": "cpu"}
