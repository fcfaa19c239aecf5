"""The history commands of `bench-matrix`: runs (list a store's runs), compare (two runs or stores, as a CI
gate) and merge (stores of several machines or shards into one)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from bench_matrix.errors import UserError

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


def default_store(args: argparse.Namespace) -> Path:
    return args.results or args.workspace / "results.sqlite"


def _runs(args: argparse.Namespace, console) -> int:
    from rich.table import Table

    from bench_matrix.store import ResultStore

    label = "--results" if args.results else "results file"
    store = ResultStore(default_store(args), readonly=True, label=label)
    try:
        runs = store.runs()
    finally:
        store.close()
    table = Table(title=f"runs in {default_store(args)}")
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
    base, new = (side(spec, default_store(args)) for spec in (args.base, args.new))
    twins = None
    if args.remeasure:
        from bench_matrix.cli_remeasure import remeasured

        base, new, twins = remeasured(base, new, args.matrix, args.workspace)
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


def side(spec: str, store_path: Path):
    """One side of a comparison (with its models' tasks): a run of `store_path`, a store file or
    STORE@RUN."""
    from bench_matrix.report import View, load
    from bench_matrix.report.analysis.metric_change import Side

    path, run = _split(spec, store_path)
    loaded = load(path, View(run=run), with_samples=True)
    hosts = sorted({r.host or "unknown" for r in loaded.records})
    if len(hosts) > 1:
        raise UserError(f"{spec}: the store {path} holds records of {len(hosts)} hosts ({', '.join(hosts)}); "
                        f"name one run of it as {path}@RUN (`bench-matrix runs --results {path}` lists them)")
    samples = {r.cell.key: loaded.samples[r.id] for r in loaded.records if r.id in loaded.samples}
    batches = {r.cell.key: loaded.batches[r.id] for r in loaded.records if r.id in loaded.batches}
    label = f"{path}@{run}" if run and path != store_path else (f"run {run}" if run else str(path))
    tasks = {m.name: m.task for m in loaded.report.models}
    return Side(label=label, records=loaded.records, samples=samples, tasks=tasks, batches=batches)


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
