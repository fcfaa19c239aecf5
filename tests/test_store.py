"""ResultStore: runs and their records (appended, never overwritten), the newest record per cell and host,
raw samples, formats refused or migrated."""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import signal
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.measure.stats import pack_samples
from bench_matrix.measurement import Measurement
from bench_matrix.store import CellRecord, ResultStore
from bench_matrix.store_format import MIGRATED_LABEL, STORE_VERSION

CELL = Cell("m", "pytorch", "onnxruntime", "none", "fp32", "cpu")
OTHER = Cell("m", "pytorch", "pytorch", "none", "fp32", "cpu")
FORMAT_1 = Path(__file__).parent / "data" / "store-format-1.sqlite"  # written by bench-matrix 0.1.0 at 400c4f7


def _record(cell: Cell, run: int, status: str = "ok", host: str = "h", finished: str = "2026-01-01T00:00:00",
            **fields) -> CellRecord:
    return CellRecord(cell, status, env={"host": host}, finished_at=finished, run_id=run, **fields)


def test_runs_append_records_and_the_newest_of_each_cell_and_host_is_shown(tmp_path):
    path = tmp_path / "r.sqlite"
    store = ResultStore(path)
    first = store.begin_run("m.yaml", "h", {"torch": "2"}, label="abc123", started_at="2026-01-01T00:00:00")
    store.put(_record(CELL, first.id, "failed", reason="boom", fingerprint="f1"))
    store.put(_record(OTHER, first.id, "skipped", reason="no GPU"))
    store.end_run(first.id, "2026-01-01T00:01:00", {"counts": {"ok": 0}})
    second = store.begin_run("m.yaml", "h", {}, started_at="2026-01-02T00:00:00")
    store.put(_record(CELL, second.id, metrics={"latency_ms": {"p50": 1.5}}, fingerprint="f2",
                      finished="2026-01-02T00:00:05"))
    store.put(_record(CELL, second.id, host="gpu-box", finished="2026-01-02T00:00:06"))
    store.close()

    again = ResultStore(path, readonly=True)  # a new process sees everything that was committed
    assert [(r.cell.backend, r.host, r.status) for r in again.records()] == [
        ("onnxruntime", "gpu-box", "ok"), ("onnxruntime", "h", "ok"), ("pytorch", "h", "skipped")]
    assert [(r.status, r.reason) for r in again.records(first.id)] == [("failed", "boom"), ("skipped", "no GPU")]
    assert again.latest(CELL, "h").fingerprint == "f2" and again.latest(OTHER, "gpu-box") is None
    run = again.find_run("abc123")
    assert (run.id, run.label, run.versions, run.finished_at, run.summary) == (
        1, "abc123", {"torch": "2"}, "2026-01-01T00:01:00", {"counts": {"ok": 0}})
    assert [again.find_run(s).id for s in ("latest", "previous", "2")] == [2, 1, 2]
    with pytest.raises(UserError, match=r"no run 'nope'; name a run by its id, its label, `latest` or `previous` "
                                        r"\(its runs, newest last: run 1 \(abc123\), run 2;"):
        again.find_run("nope")
    doc = again.latest(CELL, "h").to_json()
    assert doc["run"] == 2 and doc["host"] == "h" and doc["cell"]["backend"] == "onnxruntime"
    again.close()


def test_a_record_needs_its_run(tmp_path):
    store = ResultStore(tmp_path / "r.sqlite")
    with pytest.raises(ValueError, match="has no run"):
        store.put(CellRecord(CELL, "ok"))
    store.close()


def test_read_only_open_changes_nothing(tmp_path):
    path = tmp_path / "r.sqlite"
    store = ResultStore(path)
    store.put(_record(CELL, store.begin_run("m.yaml", "h", {}).id))
    store.close()
    before = path.read_bytes()
    reader = ResultStore(path, readonly=True, label="--results")
    assert [r.status for r in reader.records()] == ["ok"]
    with pytest.raises(UserError, match=r"--results .*r.sqlite: cannot write a result \(attempt to write"):
        reader.put(_record(CELL, 1, "failed"))
    reader.close()
    assert path.read_bytes() == before


def test_an_empty_file_is_an_empty_store(tmp_path):
    path = tmp_path / "empty.sqlite"
    path.write_bytes(b"")
    reader = ResultStore(path, readonly=True)
    assert reader.records() == [] and reader.runs() == [] and reader.latest(CELL, "h") is None
    reader.close()
    assert path.read_bytes() == b""  # reading did not make it a store
    ResultStore(path).close()  # run takes it as a new store
    assert ResultStore(path, readonly=True).records() == []


def test_a_store_of_the_previous_release_is_migrated_with_nothing_lost(tmp_path):
    with closing(sqlite3.connect(FORMAT_1)) as db:
        old = {key: (status, metrics, env) for key, status, metrics, env in
               db.execute("SELECT key, status, metrics, env FROM results")}
        old_samples = dict(db.execute("SELECT key, data FROM samples"))
        last = db.execute("SELECT value FROM facts WHERE scope = 'run'").fetchone()[0]
    assert len(old) == 4 and len(old_samples) == 2 and '"wall_s": 12.0' in last
    path = tmp_path / "old.sqlite"
    shutil.copy(FORMAT_1, path)
    before = path.read_bytes()
    for readonly in (True, False):  # read-only: migrated in memory, the file left as it was
        store = ResultStore(path, readonly=readonly)
        records = store.records()
        assert {r.cell.key: (r.status, r.metrics.to_json(), r.env) for r in records} == {
            key: (status, json.loads(metrics), json.loads(env))
            for key, (status, metrics, env) in old.items()}
        assert {r.cell.key: store.samples_of(r.id).get("latency_ms") for r in records if r.status == "ok"} \
            == old_samples
        (run,) = store.runs()
        assert (run.label, run.host, run.matrix, run.summary["wall_s"]) == (MIGRATED_LABEL, "vm", "m.yaml", 12.0)
        assert {r.run_id for r in records} == {run.id} and store.facts("model:tiny")["info"]["params"] > 0
        store.close()
        if readonly:
            assert path.read_bytes() == before
    with closing(sqlite3.connect(path)) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == STORE_VERSION
        assert "results" not in {n for (n,) in db.execute("SELECT name FROM sqlite_master")}


def test_a_format_1_store_without_samples_migrates(tmp_path):
    path = tmp_path / "older.sqlite"
    shutil.copy(FORMAT_1, path)
    with closing(sqlite3.connect(path)) as db:
        db.execute("DROP TABLE samples")  # what bench-matrix wrote before raw samples were kept
        db.commit()
    store = ResultStore(path)
    assert len(store.records()) == 4 and all(store.samples(r) is None for r in store.records())
    store.close()


def test_stores_of_other_versions_are_refused_with_what_to_do(tmp_path):
    older, newer = tmp_path / "older.sqlite", tmp_path / "newer.sqlite"
    with closing(sqlite3.connect(older)) as db:
        db.execute("CREATE TABLE results (key TEXT PRIMARY KEY, model TEXT, status TEXT)")
    with pytest.raises(UserError, match=r"older.sqlite: written by an older bench-matrix \(its results table "
                                        r"lacks fingerprint, matrix, framework, .*\); move it away or choose"):
        ResultStore(older, readonly=True)
    ResultStore(newer).close()
    with closing(sqlite3.connect(newer)) as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == STORE_VERSION  # the format is recorded
        db.execute(f"PRAGMA user_version = {STORE_VERSION + 1}")
    for readonly in (True, False):
        with pytest.raises(UserError, match=rf"written by a newer bench-matrix \(results format "
                                            rf"{STORE_VERSION + 1}; this one reads {STORE_VERSION}\): upgrade"):
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
    run = store.begin_run("m.yaml", "h", {})
    durations = np.array([1_250_000, 1_300_000, 2_000_000, 1_100_000])
    record = _record(CELL, run.id, fingerprint="f")
    store.put(record, {"latency_ms": pack_samples(durations)})
    store.close()
    again = ResultStore(path, readonly=True)
    stored = again.latest(CELL, "h")
    assert again.samples(stored).tolist() == pytest.approx([1.25, 1.3, 2.0, 1.1])  # ms, in timing order
    assert again.samples(stored, "latency_ms_e2e") is None
    assert "samples" not in stored.to_json()["metrics"]  # records (and report json) stay small
    again.close()
    store = ResultStore(path)
    record.metrics = Measurement.from_json({"latency_passes_p50": [1.2, 1.4]})
    store.put(record)  # a later pass of the same run updates its record
    assert len(store.records(run.id)) == 1 and len(store.samples(record)) == 4  # and keeps its samples
    record.status = "failed"
    store.put(record)
    assert store.samples(record) is None  # a failed record has none
    store.close()


def test_ok_records_of_more_cells_than_one_query_may_name_come_back_oldest_first(tmp_path):
    store = ResultStore(tmp_path / "r.sqlite")
    run = store.begin_run("m.yaml", "h", {}).id
    cells = [Cell(f"m{i}", "pytorch", "onnxruntime", "none", "fp32", "cpu") for i in range(1200)]
    for cell in reversed(cells):  # the last cell's record is the oldest
        store.put(_record(cell, run))
    store.put(_record(cells[0], run, status="failed"))
    found = store.ok_records(c.key for c in cells[:1100])
    assert [r.cell for r in found] == list(reversed(cells[:1100])) and all(r.status == "ok" for r in found)
    store.close()


def _filled(tmp_path: Path) -> tuple[ResultStore, int]:
    """A store holding one run and one record; the run's id."""
    store = ResultStore(tmp_path / "r.sqlite")
    run = store.begin_run("m.yaml", "h", {})
    store.put(_record(CELL, run.id, "failed", reason="kept"))
    return store, run.id


def _intact(tmp_path: Path) -> None:
    store = ResultStore(tmp_path / "r.sqlite", readonly=True)
    assert [r.reason for r in store.records()] == ["kept"]
    store.close()


def test_a_full_disk_is_named_with_its_folder_and_the_store_is_left_intact(tmp_path):
    """SQLITE_FULL (what SQLite says when a write meets ENOSPC; here its page limit) is a full disk."""
    store, run = _filled(tmp_path)
    pages = store._db.execute("PRAGMA page_count").fetchone()[0]
    store._db.execute(f"PRAGMA max_page_count = {pages}")
    with pytest.raises(UserError) as error:
        store.put(_record(OTHER, run, "failed", reason="x" * 200_000))
    store.close()
    message = str(error.value)
    assert f"the disk holding {tmp_path} is full (" in message and "MB free); the store is intact" in message
    assert "--results" in message and "repair" not in message
    _intact(tmp_path)


def test_an_io_error_where_the_quota_is_spent_says_so(tmp_path, monkeypatch):
    """A write past the file size limit is a real SQLITE_IOERR; the trial write beside the store meets EDQUOT
    (injected), the error a write over the user's quota gets."""
    store, run = _filled(tmp_path)
    size = sum(p.stat().st_size for p in tmp_path.iterdir())

    def over_quota(fd: int, data: bytes) -> int:
        raise OSError(errno.EDQUOT, os.strerror(errno.EDQUOT))

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, hard))
    try:
        monkeypatch.setattr(os, "write", over_quota)
        with pytest.raises(UserError) as error:
            store.put(_record(OTHER, run, "failed", reason="x" * 200_000))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    monkeypatch.undo()
    store.close()
    message = str(error.value)
    assert "disk I/O error" in message and f"the disk holding {tmp_path} is over your disk quota" in message
    assert "repair" not in message and not list(tmp_path.glob(".bench-matrix-trial-*"))
    _intact(tmp_path)
