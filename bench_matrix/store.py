"""ResultStore: an SQLite file of runs, the cell records each run wrote (appended as each cell ends, never
overwritten by a later run), the raw latencies of ok records, and facts about models and data."""

from __future__ import annotations

import errno
import json
import os
import shutil
import sqlite3
import uuid
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bench_matrix.cell import Cell
from bench_matrix.errors import UserError
from bench_matrix.measure.stats import unpack_samples
from bench_matrix.measurement import Measurement
from bench_matrix.store_format import (
    RECORD_COLUMNS,
    RUN_COLUMNS,
    STORE_VERSION,
    create_tables,
    file_problem,
    is_format_1,
    migrate_format_1,
    schema_problem,
    tables,
)

Status = Literal["ok", "skipped", "failed"]
_SELECT_RECORD = f"SELECT id, {', '.join(RECORD_COLUMNS)} FROM records"
_CELL_ORDER = "model, backend, strategy, precision, target, host"
# newest first among the records of one cell on one host
_NEWEST = "COALESCE(finished_at, started_at, '') DESC, id DESC"
_KEYS_A_QUERY = 500  # below SQLite's smallest limit on a statement's variables (999)
_TRIAL_BYTES = 1 << 20  # what a trial write puts beside the store to tell a full disk from a failing one
_NO_ROOM = {errno.ENOSPC: "is full", errno.EDQUOT: "is over your disk quota"}


@dataclass
class CellRecord:
    """The stored outcome of one cell in one run; `to_json` is the record format of `report --format json`."""

    cell: Cell
    status: Status
    reason: str | None = None
    metrics: Measurement = field(default_factory=Measurement)  # a dict given is read as its JSON
    artifact_path: str | None = None
    env: dict[str, Any] = field(default_factory=dict)
    started_at: str | None = None
    finished_at: str | None = None
    fingerprint: str = ""
    matrix: str = ""
    run_id: int | None = None  # the run that wrote it; None until stored
    id: int | None = None  # its row in the store; None until stored

    def __post_init__(self) -> None:
        if not isinstance(self.metrics, Measurement):
            self.metrics = Measurement.from_json(self.metrics)

    @property
    def host(self) -> str | None:
        """The machine the record was measured (or skipped) on."""
        return self.env.get("host")

    def to_json(self) -> dict[str, Any]:
        return {"cell": self.cell.as_dict(), "host": self.host, "status": self.status, "reason": self.reason,
                "metrics": self.metrics.to_json(), "artifact_path": self.artifact_path, "env": self.env,
                "started_at": self.started_at, "finished_at": self.finished_at,
                "fingerprint": self.fingerprint, "matrix": self.matrix, "run": self.run_id, "record": self.id}


@dataclass(frozen=True)
class RunInfo:
    """One `bench-matrix run`: what it ran, where, when, with which versions, and its optional user label."""

    id: int
    uid: str
    matrix: str
    host: str
    label: str | None
    started_at: str
    finished_at: str | None
    versions: dict[str, Any]
    summary: dict[str, Any]

    @property
    def name(self) -> str:
        return f"run {self.id}" + (f" ({self.label})" if self.label else "")


class ResultStore:
    """A results database, every write committed at once (an interrupted run loses nothing); `readonly` opens
    an existing store unchanged (an older format migrated in memory); `label` names the file in messages."""

    def __init__(self, path: str | Path, readonly: bool = False, label: str = "results file"):
        self.path, self._label = Path(path), label
        problem = file_problem(self.path, readonly)
        if problem:
            raise UserError(f"{label} {self.path}: {problem}")
        with self._errors("cannot open it", "check the path and the permissions of its folder"):
            self._db = (sqlite3.connect(f"{self.path.absolute().as_uri()}?mode=ro", uri=True, timeout=30,
                                        isolation_level=None)
                        if readonly else sqlite3.connect(self.path, timeout=30, isolation_level=None))
        try:
            with self._errors("not a bench-matrix results store"):
                self._open(readonly)
        except UserError:
            self._db.close()
            raise

    def _open(self, readonly: bool) -> None:
        problem = schema_problem(self._db)
        if problem:
            raise UserError(f"{self._label} {self.path}: {problem}")
        self._empty = readonly and not tables(self._db)  # an empty file, read: no results
        if readonly and is_format_1(self._db):
            memory = sqlite3.connect(":memory:", isolation_level=None)
            self._db.backup(memory)
            self._db.close()
            self._db = memory
        if not readonly or is_format_1(self._db):
            if not readonly:
                self._db.execute("PRAGMA journal_mode=WAL")
            with self._transaction():
                if is_format_1(self._db):
                    migrate_format_1(self._db)
                create_tables(self._db)
                self._db.execute(f"PRAGMA user_version = {STORE_VERSION}")

    @contextmanager
    def _transaction(self) -> Iterator[None]:
        """One atomic write (BEGIN IMMEDIATE: concurrent writers wait for each other, up to the timeout);
        nested in `atomic`, part of the enclosing one."""
        if self._db.in_transaction:
            yield
            return
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            if self._db.in_transaction:  # SQLite rolls back by itself on some errors (a full disk)
                self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    @contextmanager
    def atomic(self) -> Iterator[None]:
        """Several writes that land together or not at all."""
        with self._errors("cannot write a result"), self._transaction():
            yield

    @contextmanager
    def _errors(self, doing: str, hint: str = "repair or move the file away, or choose another results file"
                ) -> Iterator[None]:
        """SQLite's errors (damaged file, disk full, locked) as a UserError naming the file."""
        try:
            yield
        except sqlite3.Error as error:
            raise UserError(f"{self._label} {self.path}: {doing} ({error}); "
                            f"{no_room(error, self.path.absolute().parent) or hint}") from None

    def close(self) -> None:
        self._db.close()

    def begin_run(self, matrix: str, host: str, versions: Mapping[str, Any], label: str | None = None,
                  started_at: str = "", uid: str | None = None) -> RunInfo:
        """Record the start of a run; its records are written with its id."""
        values = (uid or uuid.uuid4().hex, matrix, host, label, started_at, None, json.dumps(dict(versions)),
                  "{}")
        with self._errors("cannot write a result"), self._transaction():
            cursor = self._db.execute(f"INSERT INTO runs ({', '.join(RUN_COLUMNS)}) VALUES (?,?,?,?,?,?,?,?)",
                                      values)
        return self.run(cursor.lastrowid)

    def end_run(self, run_id: int, finished_at: str | None, summary: Mapping[str, Any]) -> None:
        with self._errors("cannot write a result"), self._transaction():
            self._db.execute("UPDATE runs SET finished_at = ?, summary = ? WHERE id = ?",
                             (finished_at, json.dumps(dict(summary)), run_id))

    def put(self, record: CellRecord, samples: Mapping[str, bytes] | None = None) -> int:
        """Append a record to its run (`record.run_id`) or update it (a later pass), giving its id; `samples`
        (series -> stats.pack_samples bytes) replace its raw latencies, else only an ok one keeps them."""
        if record.run_id is None:
            raise ValueError(f"record of {record.cell.key} has no run")
        c = record.cell
        values = {"run_id": record.run_id, "key": c.key, "host": record.host or "unknown",
                  "fingerprint": record.fingerprint, "matrix": record.matrix, **c.as_dict(),
                  "status": record.status, "reason": record.reason,
                  "metrics": json.dumps(record.metrics.to_json()),
                  "artifact_path": record.artifact_path, "env": json.dumps(record.env),
                  "started_at": record.started_at, "finished_at": record.finished_at}
        row = [values[name] for name in RECORD_COLUMNS]
        with self._errors("cannot write a result"), self._transaction():
            if record.id is None:
                record.id = self._db.execute(f"INSERT INTO records ({', '.join(RECORD_COLUMNS)}) VALUES "
                                             f"({', '.join('?' * len(row))})", row).lastrowid
            else:
                self._db.execute(f"UPDATE records SET {', '.join(f'{n} = ?' for n in RECORD_COLUMNS)} "
                                 f"WHERE id = ?", (*row, record.id))
            if samples is not None or record.status != "ok":
                self._db.execute("DELETE FROM samples WHERE record_id = ?", (record.id,))
            self._db.executemany("INSERT INTO samples VALUES (?,?,?)",
                                 [(record.id, series, blob) for series, blob in (samples or {}).items()])
        return record.id

    def samples(self, record: CellRecord, series: str = "latency_ms") -> np.ndarray | None:
        """The record's raw per-iteration latencies in ms (float32, in timing order) of `series`
        ("latency_ms", or "latency_ms_e2e" on a GPU); None when none are stored (skipped or failed cells)."""
        if self._empty or record.id is None:
            return None
        with self._errors("cannot read results"):
            row = self._db.execute("SELECT data FROM samples WHERE record_id = ? AND series = ?",
                                   (record.id, series)).fetchone()
        return unpack_samples(row[0]) if row else None

    def latest(self, cell: Cell, host: str) -> CellRecord | None:
        """The newest record of `cell` measured (or skipped) on `host`, from any run."""
        rows = self._select(f"{_SELECT_RECORD} WHERE key = ? AND host = ? ORDER BY {_NEWEST} LIMIT 1",
                            (cell.key, host))
        return rows[0] if rows else None

    def latest_on(self, cell: Cell, hosts: set[str]) -> CellRecord | None:
        """The newest record of `cell` on any of `hosts`, from any run."""
        found = [r for host in sorted(hosts) if (r := self.latest(cell, host))]
        return max(found, key=lambda r: (r.finished_at or r.started_at or "", r.id or 0), default=None)

    def is_done(self, cell: Cell, fingerprint: str, hosts: set[str]) -> bool:
        """Whether the newest record of the cell on `hosts` is an ok one of this fingerprint."""
        record = self.latest_on(cell, hosts)
        return record is not None and record.status == "ok" and record.fingerprint == fingerprint

    def records(self, run: int | None = None) -> list[CellRecord]:
        """The records of one run, or (by default) the newest record of every cell on every host."""
        if run is not None:
            return self._select(f"{_SELECT_RECORD} WHERE run_id = ? ORDER BY {_CELL_ORDER}", (run,))
        newest = (f"SELECT *, ROW_NUMBER() OVER (PARTITION BY key, host ORDER BY {_NEWEST}) AS newness "
                  f"FROM records")
        return self._select(f"SELECT id, {', '.join(RECORD_COLUMNS)} FROM ({newest}) WHERE newness = 1 "
                            f"ORDER BY {_CELL_ORDER}", ())

    def ok_records(self, keys: Iterable[str]) -> list[CellRecord]:
        """Every ok record of these cells, from every run and host, oldest first."""
        wanted = sorted(set(keys))
        chunks = [wanted[i:i + _KEYS_A_QUERY] for i in range(0, len(wanted), _KEYS_A_QUERY)]
        found = [r for chunk in chunks for r in self._select(
            f"{_SELECT_RECORD} WHERE status = 'ok' AND key IN ({', '.join('?' * len(chunk))})", tuple(chunk))]
        return sorted(found, key=lambda r: r.id or 0)

    def _select(self, query: str, parameters: tuple) -> list[CellRecord]:
        if self._empty:
            return []
        with self._errors("cannot read results"):
            return [_record(row) for row in self._db.execute(query, parameters).fetchall()]

    def runs(self) -> list[RunInfo]:
        """Every run, oldest first."""
        if self._empty:
            return []
        with self._errors("cannot read results"):
            rows = self._db.execute(f"SELECT id, {', '.join(RUN_COLUMNS)} FROM runs "
                                    f"ORDER BY started_at, id").fetchall()
        return [_run(row) for row in rows]

    def run(self, run_id: int) -> RunInfo:
        return self.find_run(str(run_id))

    def find_run(self, spec: str) -> RunInfo:
        """A run by id, `latest`, `previous` (the one before the latest) or label (its newest run)."""
        runs = self.runs()
        text = spec.strip()
        found = ([r for r in runs if str(r.id) == text] if text.isdigit() else
                 runs[-1:] if text == "latest" else runs[-2:-1] if text == "previous" else
                 [r for r in runs if r.label == text][-1:])
        if not found:
            held = ", ".join(r.name for r in runs[-8:]) or "none"
            raise UserError(f"{self._label} {self.path}: no run {spec!r}; name a run by its id, its label, "
                            f"`latest` or `previous` (its runs{', newest last' if runs else ''}: {held}; "
                            f"`bench-matrix runs` lists them all)")
        return found[0]

    def put_fact(self, scope: str, name: str, value: Any) -> None:
        with self._errors("cannot write a result"), self._transaction():
            self._db.execute("INSERT OR REPLACE INTO facts VALUES (?,?,?)", (scope, name, json.dumps(value)))

    def facts(self, scope: str) -> dict[str, Any]:
        if self._empty:
            return {}
        with self._errors("cannot read results"):
            rows = self._db.execute("SELECT name, value FROM facts WHERE scope = ?", (scope,)).fetchall()
        return {name: json.loads(value) for name, value in rows}

    def all_facts(self) -> list[tuple[str, str, Any]]:
        """Every fact as (scope, name, value)."""
        if self._empty:
            return []
        with self._errors("cannot read results"):
            rows = self._db.execute("SELECT scope, name, value FROM facts ORDER BY scope, name").fetchall()
        return [(scope, name, json.loads(value)) for scope, name, value in rows]

    def samples_of(self, record_id: int) -> dict[str, bytes]:
        """Every stored series of a record, packed (as `put` takes them)."""
        with self._errors("cannot read results"):
            rows = self._db.execute("SELECT series, data FROM samples WHERE record_id = ?", (record_id,))
            return {series: bytes(data) for series, data in rows.fetchall()}


def no_room(error: sqlite3.Error, folder: Path) -> str | None:
    """What to do when SQLite failed for want of room in `folder` (SQLITE_FULL, or an I/O error that a trial
    write there confirms: ENOSPC, EDQUOT); None for any other error."""
    code = getattr(error, "sqlite_errorcode", 0) & 0xFF  # the primary code of an extended one
    if code not in (sqlite3.SQLITE_FULL, sqlite3.SQLITE_IOERR):
        return None
    why = _trial_write(folder) or ("is full" if code == sqlite3.SQLITE_FULL else None)
    if why is None:
        return None
    free = shutil.disk_usage(folder).free / 1e6
    return (f"the disk holding {folder} {why} ({free:.0f} MB free); the store is intact (a write lands whole "
            f"or not at all): free space there, or choose a results file on another disk (--results), "
            f"and run again: finished cells are kept")


def _trial_write(folder: Path) -> str | None:
    """Why a small file cannot be written in `folder` for want of room ('is full', ...); None if it can."""
    path = folder / f".bench-matrix-trial-{os.getpid()}"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, bytes(_TRIAL_BYTES))
            os.fsync(fd)
        finally:
            os.close(fd)
            path.unlink()
    except OSError as exc:
        return _NO_ROOM.get(exc.errno)
    return None


def _record(row: tuple) -> CellRecord:
    values = dict(zip(("id", *RECORD_COLUMNS), row))
    cell = Cell(*(values[k] for k in ("model", "framework", "backend", "strategy", "precision", "target")))
    return CellRecord(cell=cell, status=values["status"], reason=values["reason"],
                      metrics=Measurement.from_json(json.loads(values["metrics"])),
                      artifact_path=values["artifact_path"],
                      env=json.loads(values["env"]), started_at=values["started_at"],
                      finished_at=values["finished_at"], fingerprint=values["fingerprint"],
                      matrix=values["matrix"], run_id=values["run_id"], id=values["id"])


def _run(row: tuple) -> RunInfo:
    values = dict(zip(("id", *RUN_COLUMNS), row))
    return RunInfo(**{**values, "versions": json.loads(values["versions"]),
                      "summary": json.loads(values["summary"])})
