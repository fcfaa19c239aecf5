"""ResultStore: SQLite file holding one record per cell (written as each cell ends) and run facts."""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from bench_matrix.cell import Cell

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

    def to_json(self) -> dict[str, Any]:
        return {"cell": self.cell.as_dict(), "status": self.status, "reason": self.reason,
                "metrics": self.metrics, "artifact_path": self.artifact_path, "env": self.env,
                "started_at": self.started_at, "finished_at": self.finished_at,
                "fingerprint": self.fingerprint, "matrix": self.matrix}


class ResultStore:
    """A results database; every write is committed at once so an interrupted run loses nothing."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.path, timeout=30)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        self._db.close()

    def put(self, record: CellRecord) -> None:
        c = record.cell
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO results VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (c.key, record.fingerprint, record.matrix, c.model, c.framework, c.backend, c.strategy,
                 c.precision, c.target, record.status, record.reason, json.dumps(record.metrics),
                 record.artifact_path, json.dumps(record.env), record.started_at, record.finished_at))

    def get(self, cell: Cell) -> CellRecord | None:
        row = self._db.execute(f"SELECT {_COLUMNS} FROM results WHERE key = ?", (cell.key,)).fetchone()
        return _record(row) if row else None

    def records(self) -> list[CellRecord]:
        rows = self._db.execute(f"SELECT {_COLUMNS} FROM results ORDER BY model, backend, strategy, "
                                "precision, target").fetchall()
        return [_record(r) for r in rows]

    def put_fact(self, scope: str, name: str, value: Any) -> None:
        with self._db:
            self._db.execute("INSERT OR REPLACE INTO facts VALUES (?,?,?)", (scope, name, json.dumps(value)))

    def facts(self, scope: str) -> dict[str, Any]:
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
