"""ResultStore: SQLite file holding one record per cell (written as each cell ends), the raw latencies of
each ok cell, and run facts."""

from __future__ import annotations

import json
import os
import sqlite3
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.measure.stats import unpack_samples
from bench_matrix.workspace import not_regular

STORE_VERSION = 1  # PRAGMA user_version of a results file; 0 (unset) is the same; `samples` is an added table
SQLITE_MAGIC = b"SQLite format 3\0"
Status = Literal["ok", "skipped", "failed"]
_SCHEMA = """
CREATE TABLE IF NOT EXISTS results (
    key TEXT PRIMARY KEY, fingerprint TEXT NOT NULL, matrix TEXT NOT NULL,
    model TEXT NOT NULL, framework TEXT NOT NULL, backend TEXT NOT NULL, strategy TEXT NOT NULL,
    precision TEXT NOT NULL, target TEXT NOT NULL, status TEXT NOT NULL, reason TEXT,
    metrics TEXT NOT NULL, artifact_path TEXT, env TEXT NOT NULL, started_at TEXT, finished_at TEXT
);
CREATE TABLE IF NOT EXISTS facts (scope TEXT NOT NULL, name TEXT NOT NULL, value TEXT NOT NULL,
                                  PRIMARY KEY (scope, name));
CREATE TABLE IF NOT EXISTS samples (key TEXT NOT NULL, series TEXT NOT NULL, data BLOB NOT NULL,
                                    PRIMARY KEY (key, series));
"""


@dataclass
class CellRecord:
    """The stored outcome of one cell; `to_json` is the record format of `report --format json`."""

    cell: Cell
    status: Status
    reason: str | None = None
    metrics: dict[str, Any] = field(default_factory=dict)
    artifact_path: str | None = None
    env: dict[str, Any] = field(default_factory=dict)
    started_at: str | None = None
    finished_at: str | None = None
    fingerprint: str = ""
    matrix: str = ""

    @property
    def host(self) -> str | None:
        """The machine the record was measured (or skipped) on."""
        return self.env.get("host")

    def to_json(self) -> dict[str, Any]:
        return {"cell": self.cell.as_dict(), "host": self.host, "status": self.status, "reason": self.reason,
                "metrics": self.metrics, "artifact_path": self.artifact_path, "env": self.env,
                "started_at": self.started_at, "finished_at": self.finished_at,
                "fingerprint": self.fingerprint, "matrix": self.matrix}


class ResultStore:
    """A results database; every write is committed at once so an interrupted run loses nothing.

    `readonly` opens an existing store without changing it; `label` names the file in messages."""

    def __init__(self, path: str | Path, readonly: bool = False, label: str = "results file"):
        self.path, self._label = Path(path), label
        problem = _file_problem(self.path, readonly)
        if problem:
            raise UserError(f"{label} {self.path}: {problem}")
        with self._errors("cannot open it", "check the path and the permissions of its folder"):
            self._db = (sqlite3.connect(f"{self.path.absolute().as_uri()}?mode=ro", uri=True, timeout=30)
                        if readonly else sqlite3.connect(self.path, timeout=30))
        try:
            with self._errors("not a bench-matrix results store"):
                problem = _schema_problem(self._db)
                self._empty = readonly and not _tables(self._db)  # an empty file, read: no results
                if not problem and not readonly:
                    self._db.execute("PRAGMA journal_mode=WAL")
                    self._db.executescript(_SCHEMA + f"PRAGMA user_version = {STORE_VERSION};")
            if problem:
                raise UserError(f"{label} {self.path}: {problem}")
        except UserError:
            self._db.close()
            raise

    @contextmanager
    def _errors(self, doing: str, hint: str = "repair or move the file away, or choose another results file"
                ) -> Iterator[None]:
        """SQLite's errors (damaged file, disk full, locked) as a UserError naming the file."""
        try:
            yield
        except sqlite3.Error as error:
            raise UserError(f"{self._label} {self.path}: {doing} ({error}); {hint}") from None

    def close(self) -> None:
        self._db.close()

    def put(self, record: CellRecord, samples: Mapping[str, bytes] | None = None) -> None:
        """Write a record; with `samples` (series name -> stats.pack_samples bytes) replace its raw latencies
        in the same transaction. Without, an ok record keeps the stored ones; any other status drops them."""
        c = record.cell
        with self._errors("cannot write a result"), self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO results VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (c.key, record.fingerprint, record.matrix, c.model, c.framework, c.backend, c.strategy,
                 c.precision, c.target, record.status, record.reason, json.dumps(record.metrics),
                 record.artifact_path, json.dumps(record.env), record.started_at, record.finished_at))
            if samples is not None or record.status != "ok":
                self._db.execute("DELETE FROM samples WHERE key = ?", (c.key,))
            self._db.executemany("INSERT INTO samples VALUES (?,?,?)",
                                 [(c.key, series, blob) for series, blob in (samples or {}).items()])

    def samples(self, cell: Cell, series: str = "latency_ms") -> np.ndarray | None:
        """The cell's raw per-iteration latencies in ms (float32, in timing order) of `series` ("latency_ms",
        or "latency_ms_e2e" on a GPU); None when none are stored (older stores, skipped or failed cells)."""
        if self._empty or "samples" not in _tables(self._db):
            return None
        with self._errors("cannot read results"):
            row = self._db.execute("SELECT data FROM samples JOIN results USING (key) WHERE key = ? AND "
                                   "series = ? AND status = 'ok'", (cell.key, series)).fetchone()
        return unpack_samples(row[0]) if row else None

    def get(self, cell: Cell) -> CellRecord | None:
        if self._empty:
            return None
        with self._errors("cannot read results"):
            row = self._db.execute(f"SELECT {_COLUMNS} FROM results WHERE key = ?", (cell.key,)).fetchone()
        return _record(row) if row else None

    def records(self) -> list[CellRecord]:
        if self._empty:
            return []
        with self._errors("cannot read results"):
            rows = self._db.execute(f"SELECT {_COLUMNS} FROM results ORDER BY model, backend, strategy, "
                                    "precision, target").fetchall()
        return [_record(r) for r in rows]

    def put_fact(self, scope: str, name: str, value: Any) -> None:
        with self._errors("cannot write a result"), self._db:
            self._db.execute("INSERT OR REPLACE INTO facts VALUES (?,?,?)", (scope, name, json.dumps(value)))

    def facts(self, scope: str) -> dict[str, Any]:
        if self._empty:
            return {}
        with self._errors("cannot read results"):
            rows = self._db.execute("SELECT name, value FROM facts WHERE scope = ?", (scope,)).fetchall()
        return {name: json.loads(value) for name, value in rows}


_COLUMNS = ("model, framework, backend, strategy, precision, target, status, reason, metrics, artifact_path, "
            "env, started_at, finished_at, fingerprint, matrix")


def _record(row: tuple) -> CellRecord:
    (model, framework, backend, strategy, precision, target, status, reason, metrics, artifact, env,
     started, finished, fingerprint, matrix) = row
    return CellRecord(cell=Cell(model, framework, backend, strategy, precision, target), status=status,
                      reason=reason, metrics=json.loads(metrics), artifact_path=artifact, env=json.loads(env),
                      started_at=started, finished_at=finished, fingerprint=fingerprint, matrix=matrix)


def _file_problem(path: Path, readonly: bool) -> str | None:
    """Why `path` cannot be a results file (opened read-only: must exist and hold an SQLite database)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file" if readonly else _folder_problem(path.parent)
    except OSError as error:
        return f"cannot look at it: {error.strerror}"
    kind = not_regular(mode)
    if kind == "a directory":
        return f"is a directory; give a file name such as {path / 'results.sqlite'}"
    if kind:
        return f"is {kind}, not a results file"
    try:
        with open(path, "rb") as file:
            header = file.read(len(SQLITE_MAGIC))
    except OSError as error:
        return f"cannot read it: {error.strerror}"
    if header and header != SQLITE_MAGIC:
        return "not a bench-matrix results store: it is not an SQLite database; choose another file"
    if not readonly and not os.access(path, os.W_OK):
        return "the file is read-only; make it writable or choose another file"
    return None


def _folder_problem(folder: Path) -> str | None:
    if not folder.is_dir():
        return f"the folder {folder} does not exist; create it or choose another path"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"cannot create it: the folder {folder} is not writable"
    return None


def _tables(db: sqlite3.Connection) -> set[str]:
    return {name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


def _schema_problem(db: sqlite3.Connection) -> str | None:
    """Why an open SQLite database is not a results store this version can use, or None."""
    version = db.execute("PRAGMA user_version").fetchone()[0]
    if version > STORE_VERSION:
        return (f"written by a newer bench-matrix (results format {version}; this one reads "
                f"{STORE_VERSION}): upgrade bench-matrix or choose another results file")
    tables = _tables(db)
    if tables and "results" not in tables:
        return (f"an SQLite database, but not a bench-matrix results store (its tables: "
                f"{', '.join(sorted(tables))}); choose another file")
    columns = {row[1] for row in db.execute("PRAGMA table_info(results)")}
    missing = [c for c in _COLUMNS.replace(" ", "").split(",") if c not in columns] if columns else []
    if missing:
        return (f"written by an older bench-matrix (its results table lacks {', '.join(missing)}); move it "
                f"away or choose another results file, and run again")
    check = db.execute("PRAGMA quick_check").fetchone()[0]
    return None if check == "ok" else f"the database is damaged ({check}); restore it or choose another file"
