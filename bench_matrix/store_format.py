"""The results file's format: its tables, the checks that a file is a store this version can use, and the
migration of stores written by earlier releases (format 1: one overwritten record per cell, no runs)."""

from __future__ import annotations

import json
import os
import sqlite3
import uuid
from pathlib import Path

from bench_matrix.workspace import not_regular

STORE_VERSION = 2  # PRAGMA user_version; 0 or 1 with a `results` table: format 1, migrated on open
SQLITE_MAGIC = b"SQLite format 3\0"
MIGRATED_LABEL = "migrated from results format 1"
RECORD_COLUMNS = ("run_id", "key", "host", "fingerprint", "matrix", "model", "framework", "backend",
                  "strategy", "precision", "target", "status", "reason", "metrics", "artifact_path", "env",
                  "started_at", "finished_at")
RUN_COLUMNS = ("uid", "matrix", "host", "label", "started_at", "finished_at", "versions", "summary")
SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY, uid TEXT NOT NULL UNIQUE, matrix TEXT NOT NULL, host TEXT NOT NULL, label TEXT,
    started_at TEXT NOT NULL, finished_at TEXT, versions TEXT NOT NULL, summary TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS records (
    id INTEGER PRIMARY KEY, run_id INTEGER NOT NULL REFERENCES runs (id), key TEXT NOT NULL,
    host TEXT NOT NULL, fingerprint TEXT NOT NULL, matrix TEXT NOT NULL, model TEXT NOT NULL,
    framework TEXT NOT NULL, backend TEXT NOT NULL, strategy TEXT NOT NULL, precision TEXT NOT NULL,
    target TEXT NOT NULL, status TEXT NOT NULL, reason TEXT, metrics TEXT NOT NULL, artifact_path TEXT,
    env TEXT NOT NULL, started_at TEXT, finished_at TEXT
);
CREATE INDEX IF NOT EXISTS records_by_cell ON records (key, host);
CREATE INDEX IF NOT EXISTS records_by_run ON records (run_id);
CREATE TABLE IF NOT EXISTS samples (record_id INTEGER NOT NULL REFERENCES records (id), series TEXT NOT NULL,
                                    data BLOB NOT NULL, PRIMARY KEY (record_id, series));
CREATE TABLE IF NOT EXISTS facts (scope TEXT NOT NULL, name TEXT NOT NULL, value TEXT NOT NULL,
                                  PRIMARY KEY (scope, name));
"""
_FORMAT_1_COLUMNS = ("key", "fingerprint", "matrix", "model", "framework", "backend", "strategy",
                     "precision", "target", "status", "reason", "metrics", "artifact_path", "env",
                     "started_at", "finished_at")


def tables(db: sqlite3.Connection) -> set[str]:
    return {name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}


def create_tables(db: sqlite3.Connection) -> None:
    """The tables of this format, where missing (statement by statement: inside the caller's transaction)."""
    for statement in SCHEMA.split(";"):
        if statement.strip():
            db.execute(statement)


def is_format_1(db: sqlite3.Connection) -> bool:
    """A store of the first release: a `results` table (one record per cell) and no runs."""
    return db.execute("PRAGMA user_version").fetchone()[0] <= 1 and "results" in tables(db)


def file_problem(path: Path, readonly: bool) -> str | None:
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


def schema_problem(db: sqlite3.Connection) -> str | None:
    """Why an open SQLite database is not a results store this version can use or migrate, or None."""
    version = db.execute("PRAGMA user_version").fetchone()[0]
    if version > STORE_VERSION:
        return (f"written by a newer bench-matrix (results format {version}; this one reads "
                f"{STORE_VERSION}): upgrade bench-matrix or choose another results file")
    found = tables(db)
    table = "results" if is_format_1(db) else "records"
    if found and table not in found:
        return (f"an SQLite database, but not a bench-matrix results store (its tables: "
                f"{', '.join(sorted(found))}); choose another file")
    columns = {row[1] for row in db.execute(f"PRAGMA table_info({table})")}
    wanted = _FORMAT_1_COLUMNS if table == "results" else RECORD_COLUMNS
    missing = [c for c in wanted if c not in columns] if columns else []
    if missing:
        return (f"written by an older bench-matrix (its {table} table lacks {', '.join(missing)}); move it "
                f"away or choose another results file, and run again")
    check = db.execute("PRAGMA quick_check").fetchone()[0]
    return None if check == "ok" else f"the database is damaged ({check}); restore it or choose another file"


def migrate_format_1(db: sqlite3.Connection) -> None:
    """Turn a format-1 store into this format in one transaction: one run per host its records name (times and
    counts from its last-run facts), every record and its raw samples kept."""
    if "samples" in tables(db):
        db.execute("ALTER TABLE samples RENAME TO samples_v1")
    create_tables(db)
    last = _last_run_fact(db)
    rows = db.execute(f"SELECT {', '.join(_FORMAT_1_COLUMNS)} FROM results "
                      f"ORDER BY started_at, key").fetchall()
    runs: dict[str, int] = {}
    for row in rows:
        values = dict(zip(_FORMAT_1_COLUMNS, row))
        env = json.loads(values["env"] or "{}")
        host = str(env.get("host") or "unknown")
        if host not in runs:
            runs[host] = _migrated_run(db, host, env, last, [r for r in rows if _host(r) == host])
        cursor = db.execute(f"INSERT INTO records ({', '.join(RECORD_COLUMNS)}) VALUES "
                            f"({', '.join('?' * len(RECORD_COLUMNS))})",
                            [runs[host] if c == "run_id" else host if c == "host" else values[c]
                             for c in RECORD_COLUMNS])
        if "samples_v1" in tables(db):
            db.execute("INSERT INTO samples SELECT ?, series, data FROM samples_v1 WHERE key = ?",
                       (cursor.lastrowid, values["key"]))
    db.execute("DROP TABLE results")
    db.execute("DROP TABLE IF EXISTS samples_v1")
    db.execute("DELETE FROM facts WHERE scope = 'run' AND name = 'last'")
    db.execute(f"PRAGMA user_version = {STORE_VERSION}")


def _host(row: tuple) -> str:
    env = json.loads(row[_FORMAT_1_COLUMNS.index("env")] or "{}")
    return str(env.get("host") or "unknown")


def _last_run_fact(db: sqlite3.Connection) -> dict:
    if "facts" not in tables(db):
        return {}
    row = db.execute("SELECT value FROM facts WHERE scope = 'run' AND name = 'last'").fetchone()
    return json.loads(row[0]) if row else {}


def _migrated_run(db: sqlite3.Connection, host: str, env: dict, last: dict, rows: list[tuple]) -> int:
    """A run for the format-1 records of one host: the last-run facts where they exist, else the records'
    times."""
    started, finished = ([r[_FORMAT_1_COLUMNS.index(name)] for r in rows if r[_FORMAT_1_COLUMNS.index(name)]]
                         for name in ("started_at", "finished_at"))
    matrix = last.get("matrix") or rows[0][_FORMAT_1_COLUMNS.index("matrix")]
    versions = {"bench_matrix": env.get("bench_matrix"), **(env.get("libraries") or {})}
    summary = {"migrated_from_format": 1, **{k: last[k] for k in ("counts", "wall_s") if k in last}}
    begun = min(started, default=last.get("started_at") or "")
    ended = max(finished, default=last.get("finished_at"))
    # the same store migrated twice (read-only opens migrate in memory) gives the same run: merge adds it once
    uid = uuid.uuid5(uuid.NAMESPACE_URL, f"bench-matrix-format-1:{host}:{begun}:{ended}:{len(rows)}").hex
    cursor = db.execute(f"INSERT INTO runs ({', '.join(RUN_COLUMNS)}) VALUES (?,?,?,?,?,?,?,?)",
                        (uid, matrix, host, MIGRATED_LABEL, begun, ended, json.dumps(versions),
                         json.dumps(summary)))
    return cursor.lastrowid
