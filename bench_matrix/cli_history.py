"""The history commands of `bench-matrix`: runs (list a store's runs), compare (two runs or stores, as a CI
gate; with --remeasure, both sides' artifacts timed again here first) and merge (stores of several machines or
shards into one)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.cli_open import load, open_run, results_file
from bench_matrix.errors import UserError

if TYPE_CHECKING:
    from bench_matrix.jobs.results import Measured
    from bench_matrix.measurement import Speedup
    from bench_matrix.report.analysis.metric_change import Side
    from bench_matrix.store import CellRecord

COMPARE_FORMATS = ("table", "md", "json")
COUNTED = ("ok", "skipped", "failed")


def add_commands(sub: Any) -> None:
    runs = sub.add_parser("runs", help="list the runs a results store holds (id, label, host, matrix, times)")
    runs.add_argument("--results", type=Path, help="SQLite results file (default: WORKSPACE/results.sqlite)")
    runs.set_defaults(handler=_runs)

    compare = sub.add_parser("compare", help="compare two runs or stores cell by cell; exit 1 when a cell "
                                             "got significantly worse beyond its threshold (a CI gate)")
    for side in ("base", "new"):
        compare.add_argument(side, metavar=side.upper(),
                             help="a run of the results store (its id, its label, `latest` or `previous`), a "
                                  "store file (its newest record of each cell), or STORE@RUN")
    compare.add_argument("--results", type=Path, help="the store runs are looked up in (default: "
                                                      "WORKSPACE/results.sqlite)")
    compare.add_argument("--threshold", action="append", default=[], metavar="METRIC=LIMIT",
                         help="change that counts for a metric: p50, p99, throughput, size (relative, "
                              "e.g. 10%%), accuracy (relative for error metrics, absolute for fractions); "
                              "repeatable")
    compare.add_argument("--alpha", type=float, default=0.05,
                         help="significance level of the tests on the raw samples (default: %(default)s)")
    compare.add_argument("--remeasure", action="store_true",
                         help="time both sides' artifacts again here, interleaved in the same rounds, and "
                              "judge p50 on their paired ratio: a gate that holds on a busy machine "
                              "(docs/results.md)")
    compare.add_argument("--matrix", type=Path, help="with --remeasure: the matrix the cells come from "
                                                     "(default: the one the new side's records name)")
    compare.add_argument("--format", choices=COMPARE_FORMATS, default="table")
    compare.add_argument("--out", type=Path, help="also write the comparison to this file (Markdown, or JSON "
                                                  "with --format json)")
    compare.set_defaults(handler=_compare)

    merge = sub.add_parser("merge", help="combine results stores (other machines, shards) into one")
    merge.add_argument("sources", nargs="+", type=Path, metavar="STORE")
    merge.add_argument("--into", type=Path, required=True,
                       help="the store to add them to (created if missing)")
    merge.set_defaults(handler=_merge)


def _runs(args: argparse.Namespace, console) -> int:
    from rich.table import Table

    from bench_matrix.store import ResultStore

    label = "--results" if args.results else "results file"
    store = ResultStore(results_file(args), readonly=True, label=label)
    try:
        runs = store.runs()
    finally:
        store.close()
    table = Table(title=f"runs in {results_file(args)}")
    for column in ("id", "label", "host", "matrix", "started", "finished", *COUNTED, "wall s"):
        table.add_column(column, overflow="fold")
    for run in runs:
        counts = run.summary.get("counts") or {}
        ended = run.finished_at or "did not finish"
        table.add_row(str(run.id), run.label or "", run.host, run.matrix, run.started_at,
                      ended if run.summary.get("completed", True) else f"{ended} (interrupted)",
                      *(str(counts.get(s, "")) for s in COUNTED), str(run.summary.get("wall_s", "")))
    console.print(table)
    return 0


def _compare(args: argparse.Namespace, console) -> int:
    from bench_matrix.report.analysis.compare import compare, parse_threshold
    from bench_matrix.report.render.compare_view import comparison_json, comparison_markdown, print_comparison

    if not 0 < args.alpha < 1:
        raise UserError(f"--alpha {args.alpha}: give a significance level between 0 and 1, such as 0.05")
    thresholds = dict(parse_threshold(text) for text in args.threshold)
    base, new = (side(spec, results_file(args)) for spec in (args.base, args.new))
    twins = None
    if args.remeasure:
        base, new, twins = _remeasured(base, new, args.matrix, args.workspace)
    elif args.matrix:
        raise UserError("--matrix names the matrix to remeasure from: use it with --remeasure")
    result = compare(base, new, thresholds, args.alpha, twins=twins)
    if args.format == "json":
        import json

        sys.stdout.write(json.dumps(comparison_json(result), indent=2) + "\n")
    elif args.format == "md":
        sys.stdout.write(comparison_markdown(result))
    else:
        print_comparison(result, console)
    if args.out:
        import json

        text = json.dumps(comparison_json(result), indent=2) + "\n" if args.format == "json" else \
            comparison_markdown(result)
        args.out.write_text(text, encoding="utf-8")
    return 1 if result.regressions else 0


def side(spec: str, store_path: Path) -> Side:
    """One side of a comparison (with its models' tasks): a run of `store_path`, a store file or
    STORE@RUN."""
    from bench_matrix.report import View, load
    from bench_matrix.report.analysis.metric_change import Side

    path, run = _split(spec, store_path)
    stored = load(path, View(run=run), with_samples=True)
    hosts = sorted({r.host or "unknown" for r in stored.records})
    if len(hosts) > 1:
        raise UserError(f"{spec}: the store {path} holds records of {len(hosts)} hosts ({', '.join(hosts)}); "
                        f"name one run of it as {path}@RUN (`bench-matrix runs --results {path}` lists them)")
    samples = {r.cell.key: stored.samples[r.id] for r in stored.records if r.id in stored.samples}
    batches = {r.cell.key: stored.batches[r.id] for r in stored.records if r.id in stored.batches}
    label = f"{path}@{run}" if run and path != store_path else (f"run {run}" if run else str(path))
    tasks = {m.name: m.task for m in stored.report.models}
    return Side(label=label, records=stored.records, samples=samples, tasks=tasks, batches=batches)


def _split(spec: str, store_path: Path) -> tuple[Path, str | None]:
    """(store, run) of a side: `STORE@RUN`, an existing store file, or a run of the default store."""
    if "@" in spec:
        path, run = spec.rsplit("@", 1)
        return Path(path), run or None
    if Path(spec).is_file():
        return Path(spec), None
    if "/" in spec or spec.endswith((".sqlite", ".db")):
        raise UserError(f"{spec}: no such results store; give a run of {store_path} (its id, label, `latest` "
                        f"or `previous`), a store file, or STORE@RUN")
    return store_path, spec


def _merge(args: argparse.Namespace, console) -> int:
    from bench_matrix.store_merge import merge

    for count in merge(args.sources, args.into):
        line = (f"{count.source}: {count.runs} run(s), {count.records} record(s) added"
                + (f"; {count.runs_present} run(s) were already there" if count.runs_present else ""))
        console.print(line, highlight=False, markup=False, soft_wrap=True)
        if count.facts_differing:
            differing = ", ".join(count.facts_differing)
            console.print(f"  kept the target's facts where this store's differ: {differing}",
                          highlight=False, markup=False, soft_wrap=True)
    console.print(f"Next: bench-matrix report --results {args.into}", highlight=False, markup=False)
    return 0


def _remeasured(base: Side, new: Side, matrix: Path | None, workspace: Path
                ) -> tuple[Side, Side, dict[str, Speedup] | None]:
    """Both sides with their cells' artifacts timed again here, both in the same rounds (remeasure.py): the
    remeasured cells' figures and samples, and each one's base time ÷ new time (empty where not paired)."""
    from rich.console import Console

    from bench_matrix.measurement import Speedup
    from bench_matrix.remeasure import BASE, NEW, remeasure, twins

    console = Console(stderr=True)  # stdout carries the comparison
    found = twins(base.records, new.records)
    loaded, ws = load(matrix or _matrix_of(new), workspace)
    with open_run(loaded, ws) as (plan, executor):
        result = remeasure(plan, ws, executor, console, found)
    console.print(f"remeasured {len(result.measured)} cells here, both sides in the same rounds",
                  highlight=False)
    for key, why in sorted(result.missing.items()):
        console.print(f"not remeasured (judged on the stored samples): {key}: {why}", highlight=False,
                      markup=False, soft_wrap=True)
    ratios = {key: sides[NEW].metrics.speedup or Speedup() for key, sides in result.measured.items()}
    return (_side(base, {key: sides[BASE] for key, sides in result.measured.items()}),
            _side(new, {key: sides[NEW] for key, sides in result.measured.items()}),
            ratios or None)


def _matrix_of(side: Side) -> Path:
    """The one matrix file the side's records came from."""
    named = sorted({record.matrix for record in side.records if record.matrix})
    if len(named) != 1 or not Path(named[0]).is_file():
        found = ", ".join(named) or "none"
        raise UserError(f"--remeasure: the new side's records name the matrix file(s) {found}, not one "
                        f"that is here; give the matrix the cells come from with --matrix FILE")
    return Path(named[0])


def _side(side: Side, measured: Mapping[str, Measured]) -> Side:
    """The side with its remeasured cells' figures (no speed-up: the pairing is the twins') and samples."""
    from bench_matrix.measure.stats import unpack_samples

    records = [_record(r, measured[r.cell.key]) if r.cell.key in measured else r for r in side.records]
    samples, batches = dict(side.samples), dict(side.batches)
    for key, found in measured.items():
        samples[key] = unpack_samples(found.samples["latency_ms"])
        if "batch_ms" in found.samples:
            batches[key] = unpack_samples(found.samples["batch_ms"])
    label = f"{side.label} (remeasured)" if measured else side.label
    return replace(side, label=label, records=records, samples=samples, batches=batches)


def _record(record: CellRecord, found: Measured) -> CellRecord:
    return replace(record, metrics=replace(found.metrics, speedup=None), env=found.env)
