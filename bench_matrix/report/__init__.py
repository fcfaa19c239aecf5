"""Reports of stored results (never running anything): terminal tables, Markdown pages, JSON and CSV."""

from __future__ import annotations

import sqlite3
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from bench_matrix.errors import UserError
from bench_matrix.report.summary import Report, summarize
from bench_matrix.store import CellRecord, ResultStore

if TYPE_CHECKING:
    from rich.console import Console

FORMATS = ("table", "md", "json", "csv")
__all__ = ["FORMATS", "load", "write_report"]


def load(store_path: str | Path) -> tuple[list[CellRecord], Report]:
    """Read every record and the facts of a store; UserError when it is missing or holds no results."""
    path = Path(store_path)
    hint = "run `bench-matrix run MATRIX` first to measure a matrix"
    if not path.is_file():
        raise UserError(f"no results store at {path}: {hint}")
    try:
        store = ResultStore(path, readonly=True)
    except sqlite3.DatabaseError as error:
        raise UserError(f"{path} is not a bench-matrix results store ({error}): {hint}") from None
    try:
        records = store.records()
        if not records:
            raise UserError(f"the results store {path} holds no results: {hint}")
        infos = {name: store.facts(f"model:{name}").get("info") or {} for name in {r.cell.model for r in records}}
        run = store.facts("run").get("last") or {}
    finally:
        store.close()
    return records, summarize(records, infos, run)


def write_report(store_path: str | Path, fmt: str, out_dir: str | Path, console: Console) -> list[Path]:
    """Report the store in `fmt` (see FORMATS); return the files written (none for json, which goes to stdout)."""
    if fmt not in FORMATS:
        raise UserError(f"unknown report format '{fmt}'; choose one of: {', '.join(FORMATS)}")
    records, report = load(store_path)
    out = Path(out_dir)
    if fmt == "json":
        from bench_matrix.report.export import records_json
        sys.stdout.write(records_json(records))
        sys.stdout.flush()
        return []
    if fmt == "csv":
        from bench_matrix.report.export import write_csv
        paths = [write_csv(records, report, out / "results.csv")]
    else:
        from bench_matrix.report.markdown import write_pages
        if fmt == "table":
            from bench_matrix.report.terminal import print_report
            print_report(report, console)
        paths = write_pages(report, out)
    if fmt == "table":
        console.print(f"Markdown report: {paths[0]} and {len(paths) - 1} model page(s)", highlight=False, markup=False)
    else:
        for path in paths:
            console.print(str(path), highlight=False, markup=False, soft_wrap=True)
    return paths
