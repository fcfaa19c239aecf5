"""Reports of stored results (never running anything): terminal tables, Markdown pages with plots, one HTML
file, JSON and CSV. This module loads the records and writes a report (what the commands call);
report.analysis computes its figures, report.render draws them."""

from __future__ import annotations

import sqlite3
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.errors import UserError
from bench_matrix.report.analysis.judging import SCOPE, Judging, judged
from bench_matrix.report.analysis.summary import Report, summarize
from bench_matrix.store import CellRecord, ResultStore, RunInfo

if TYPE_CHECKING:
    from rich.console import Console

FORMATS = ("table", "md", "html", "json", "csv")
VIEW_KEYS = ("host", "model", "backend")
__all__ = ["FORMATS", "VIEW_KEYS", "Judging", "Stored", "View", "load", "load_judged", "write_stored",
           "write_report"]


@dataclass(frozen=True)
class View:
    """Which records a report shows: one run's (`run`: id, label, latest, previous) or the newest of each cell
    on each host; then only those whose host, model and backend are in the given sets (empty: all)."""

    run: str | None = None
    only: Mapping[str, frozenset[str]] = field(default_factory=dict)

    def keep(self, record: CellRecord) -> bool:
        return all(_field(record, key) in allowed for key, allowed in self.only.items() if allowed)


@dataclass(frozen=True)
class Stored:
    """A report's material from a results store: the records a view selected, their summary, the ok ones' raw
    latencies and batch durations (ms) by record id, and the runs' stored requirements (by matrix path)."""

    records: list[CellRecord]
    report: Report
    samples: Mapping[int, np.ndarray]
    batches: Mapping[int, np.ndarray] = field(default_factory=dict)
    requirements: Mapping[str, Any] = field(default_factory=dict)


def _field(record: CellRecord, key: str) -> str:
    return (record.host or "unknown") if key == "host" else getattr(record.cell, key)


def load(store_path: str | Path, view: View = View(), with_samples: bool = False) -> Stored:
    """Read the records a view selects, with the facts of a store; UserError when it is missing or nothing
    is selected."""
    path = Path(store_path)
    hint = "run `bench-matrix run MATRIX` first to measure a matrix"
    if not path.is_file():
        raise UserError(f"no results store at {path}: {hint}")
    try:
        store = ResultStore(path, readonly=True)
    except sqlite3.DatabaseError as error:
        raise UserError(f"{path} is not a bench-matrix results store ({error}): {hint}") from None
    try:
        run = store.find_run(view.run) if view.run is not None else None
        every = store.records(run.id if run else None)
        if not every:
            raise UserError(f"{run.name} of {path} wrote no record: every cell it chose was already stored "
                            f"(`run --force` measures them again)" if run else
                            f"the results store {path} holds no results: {hint}")
        records = shown(every, view)
        infos = {name: store.facts(f"model:{name}").get("info") or {}
                 for name in {r.cell.model for r in records}}
        runs = store.runs()
        history = store.ok_records({r.cell.key for r in records if r.status == "ok"})
        ok = [r for r in records if with_samples and r.status == "ok"]
        samples, batches = ({r.id: store.samples(r, series) for r in ok}
                            for series in ("latency_ms", "batch_ms"))
        requirements = store.facts(SCOPE)
    finally:
        store.close()
    about = run_facts(run or runs[-1], len(runs)) if runs else {}
    return Stored(records, summarize(records, infos, about, history), _present(samples), _present(batches),
                  requirements)


def load_judged(store_path: str | Path, view: View = View(), judging: Judging = Judging(),
                with_samples: bool = False) -> Stored:
    """`load`, with each model judged against its requirements (report/analysis/judging.py)."""
    stored = load(store_path, view, with_samples)
    return replace(stored, report=judged(stored.report, stored.requirements, judging))


def _present(series: dict[int, np.ndarray | None]) -> dict[int, np.ndarray]:
    return {key: values for key, values in series.items() if values is not None}


def shown(records: list[CellRecord], view: View) -> list[CellRecord]:
    """The records a view keeps; a cell skipped on one host but measured on another shows only the
    measurement."""
    kept = [r for r in records if view.keep(r)]
    if not kept:
        wanted = "; ".join(f"--{k} {','.join(sorted(v))}" for k, v in view.only.items() if v)
        held = "; ".join(f"{k}s: {', '.join(sorted({_field(r, k) for r in records}))}" for k in VIEW_KEYS)
        raise UserError(f"no stored record matches {wanted}; the store holds {held}")
    measured = {r.cell.key for r in kept if r.status != "skipped"}
    return [r for r in kept if r.status != "skipped" or r.cell.key not in measured]


def run_facts(run: RunInfo, runs: int) -> dict:
    """What the report's run line says of the run shown (or the newest)."""
    return {"id": run.id, "label": run.label, "host": run.host, "matrix": run.matrix,
            "started_at": run.started_at, "finished_at": run.finished_at, "runs": runs, **run.summary}


def write_report(store_path: str | Path, fmt: str, out_dir: str | Path, console: Console,
                 view: View = View(), judging: Judging = Judging()) -> list[Path]:
    """Report the store in `fmt` (see FORMATS); return the files written (none for json, which goes to
    stdout)."""
    if fmt not in FORMATS:
        raise UserError(f"unknown report format '{fmt}'; choose one of: {', '.join(FORMATS)}")
    stored = load_judged(store_path, view, judging, with_samples=fmt in ("table", "md", "html"))
    return write_stored(stored, fmt, Path(out_dir), console)


def write_stored(stored: Stored, fmt: str, out: Path, console: Console) -> list[Path]:
    """Write a judged report in `fmt`; return the files written."""
    if fmt == "json":
        from bench_matrix.report.render.export import report_json
        sys.stdout.write(report_json(stored.records, stored.report))
        sys.stdout.flush()
        return []
    if fmt == "csv":
        from bench_matrix.report.render.export import write_csv
        paths = [write_csv(stored.records, stored.report, out / "results.csv")]
    else:
        paths = _pages(stored, fmt, out, console)
    if fmt == "table":
        console.print(f"Markdown report: {paths[0]} and {len(paths) - 2} model page(s); one file: "
                      f"{paths[-1]}", highlight=False, markup=False)
    else:
        for path in paths:
            console.print(str(path), highlight=False, markup=False, soft_wrap=True)
    return paths


def _pages(stored: Stored, fmt: str, out: Path, console: Console) -> list[Path]:
    """Plots, then the Markdown pages and/or the HTML file that embed them."""
    from bench_matrix.report.render.html import write_html
    from bench_matrix.report.render.markdown import write_pages
    from bench_matrix.report.render.plots import model_plots
    from bench_matrix.report.render.sections import section_plots

    out.mkdir(parents=True, exist_ok=True)
    plots = {m.name: [*model_plots(m, stored.samples, out / "plots"), *section_plots(m, out / "plots")]
             for m in stored.report.models}
    if fmt == "table":
        from bench_matrix.report.render.terminal import print_report
        print_report(stored.report, console)
    paths = write_pages(stored.report, out, plots) if fmt != "html" else []
    return [*paths, write_html(stored.report, plots, out / "report.html")] if fmt != "md" else paths
