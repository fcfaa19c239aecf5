"""ResultStore: records survive reconnection, replace by cell, round-trip their JSON."""

from __future__ import annotations

import os
import sqlite3
from contextlib import closing

import numpy as np
import pytest

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.measure.stats import pack_samples
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


def test_read_only_open_changes_nothing(tmp_path):
    path = tmp_path / "r.sqlite"
    store = ResultStore(path)
    store.put(CellRecord(CELL, "ok", fingerprint="f"))
    store.close()
    before = path.read_bytes()
    reader = ResultStore(path, readonly=True, label="--results")
    assert [r.status for r in reader.records()] == ["ok"]
    with pytest.raises(UserError, match=r"--results .*r.sqlite: cannot write a result \(attempt to write"):
        reader.put(CellRecord(CELL, "failed"))
    reader.close()
    assert path.read_bytes() == before


def test_an_empty_file_is_an_empty_store(tmp_path):
    path = tmp_path / "empty.sqlite"
    path.write_bytes(b"")
    reader = ResultStore(path, readonly=True)
    assert reader.records() == [] and reader.get(CELL) is None and reader.facts("run") == {}
    reader.close()
    assert path.read_bytes() == b""  # reading did not make it a store
    ResultStore(path).close()  # run takes it as a new store
    assert ResultStore(path, readonly=True).records() == []


def test_stores_of_other_versions_are_refused_with_what_to_do(tmp_path):
    older, newer = tmp_path / "older.sqlite", tmp_path / "newer.sqlite"
    with closing(sqlite3.connect(older)) as db:
        db.execute("CREATE TABLE results (key TEXT PRIMARY KEY, model TEXT, status TEXT)")
    with pytest.raises(UserError, match=r"older.sqlite: written by an older bench-matrix \(its results table "
                                        r"lacks framework, backend, .*\); move it away or choose another"):
        ResultStore(older, readonly=True)
    ResultStore(newer).close()
    with closing(sqlite3.connect(newer)) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1  # the format is recorded
        db.execute("PRAGMA user_version = 2")
    for readonly in (True, False):
        with pytest.raises(UserError, match=r"written by a newer bench-matrix \(results format 2; this one "
                                            r"reads 1\): upgrade bench-matrix"):
            ResultStore(newer, readonly=readonly)


@pytest.mark.parametrize("make, message", [
    (lambda p: p.mkdir(), r"is a directory; give a file name such as .*/results.sqlite"),
    (lambda p: os.mkfifo(p), "is a named pipe, not a results file"),
    (lambda p: p.write_text("key,status\n"), "not a bench-matrix results store: it is not an SQLite "),
])
def test_what_is_not_a_results_file_is_refused_unopened(tmp_path, make, message):
    make(tmp_path / "r.sqlite")
    for readonly in (True, False):
        with pytest.raises(UserError, match=rf"results file .*r.sqlite: {message}"):
            ResultStore(tmp_path / "r.sqlite", readonly=readonly)


def test_raw_samples_round_trip_and_follow_their_record(tmp_path):
    path = tmp_path / "r.sqlite"
    store = ResultStore(path)
    durations = np.array([1_250_000, 1_300_000, 2_000_000, 1_100_000])
    store.put(CellRecord(CELL, "ok", fingerprint="f"), {"latency_ms": pack_samples(durations)})
    store.close()
    again = ResultStore(path, readonly=True)
    assert again.samples(CELL).tolist() == pytest.approx([1.25, 1.3, 2.0, 1.1])  # ms, in timing order
    assert again.samples(CELL, "latency_ms_e2e") is None
    assert "samples" not in again.get(CELL).to_json()["metrics"]  # records (and report json) stay small
    again.close()
    store = ResultStore(path)
    store.put(CellRecord(CELL, "ok", fingerprint="f", metrics={"latency_passes_p50": [1.2, 1.4]}))
    assert len(store.samples(CELL)) == 4  # an ok record written without samples keeps the stored ones
    store.put(CellRecord(CELL, "failed", reason="boom"))
    assert store.samples(CELL) is None  # a failed record has none
    store.close()


def test_a_store_written_before_samples_opens_and_gains_the_table(tmp_path):
    path = tmp_path / "old.sqlite"
    store = ResultStore(path)
    store.put(CellRecord(CELL, "ok", fingerprint="f"))
    store.close()
    with closing(sqlite3.connect(path)) as db:
        db.execute("DROP TABLE samples")  # what bench-matrix wrote before raw samples were kept
        db.commit()
    reader = ResultStore(path, readonly=True)
    assert reader.get(CELL).status == "ok" and reader.samples(CELL) is None
    reader.close()
    writer = ResultStore(path)
    assert writer.samples(CELL) is None
    writer.put(CellRecord(CELL, "ok", fingerprint="g"), {"latency_ms": pack_samples(np.array([5_000_000]))})
    assert writer.samples(CELL).tolist() == [5.0]  # the table was added in place: same results format version
    writer.close()
    with closing(sqlite3.connect(path)) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1
