"""The `bench-matrix` command: run, plan, report, backends, schema; runs, compare and merge (cli_history);
init and run of a model file (cli_auto); device check (cli_device); what they open, one way (cli_open)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from pathlib import Path

from bench_matrix import __version__
from bench_matrix.cli_auto import add_init, add_model_options
from bench_matrix.cli_device import add_device_command, add_device_options, ssh_options
from bench_matrix.cli_history import add_commands
from bench_matrix.cli_open import load, open_run, open_store, results_file
from bench_matrix.cli_verdict import add_report_options, add_require
from bench_matrix.errors import MatrixError, UserError
from bench_matrix.workspace import DEFAULT_ROOT, Workspace

FILTER_KEYS = ("model", "backend", "strategy", "precision", "target")
VIEW_KEYS = ("host", "model", "backend")  # report's filters (bench_matrix.report.VIEW_KEYS, without its imports)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from rich.console import Console

    console, errors = Console(), Console(stderr=True)
    if not console.is_terminal:  # logs and pipes: wide enough that tables do not fold every cell
        console = Console(width=max(console.width, 160))
    try:
        _check_paths(args)
        return args.handler(args, console)
    except MatrixError as exc:
        errors.print(f"[bold red]error:[/] {len(exc.problems)} problem(s) in the matrix file:", highlight=False)
        for problem in exc.problems:
            errors.print(f"  {problem}", markup=False, highlight=False, soft_wrap=True)
        return exc.exit_code
    except UserError as exc:
        errors.print("[bold red]error:[/] ", end="", highlight=False)
        errors.print(str(exc), markup=False, highlight=False, soft_wrap=True)
        return exc.exit_code
    except KeyboardInterrupt:
        errors.print("\n[yellow]interrupted.[/] Every finished cell is saved; run the same command again to "
                     "resume where it stopped.", highlight=False)
        return 130


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bench-matrix", description="Measure size, accuracy and speed of every "
                                     "framework x strategy x precision x target combination in a matrix file.")
    parser.add_argument("--version", action="version", version=f"bench-matrix {__version__}")
    parser.add_argument("--workspace", type=Path, default=DEFAULT_ROOT,
                        help="cache, logs and default results live here (default: %(default)s)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the matrix (finished cells are kept; a re-run resumes)")
    run.add_argument("matrix", type=Path, help="a matrix .yaml, or a model file (.onnx, .pt, .pt2, .keras, "
                                               ".h5) or SavedModel folder: its automatic matrix")
    run.add_argument("--results", type=Path, help="SQLite results file (default: WORKSPACE/results.sqlite)")
    run.add_argument("--force", action="store_true", help="re-run cells that already have a stored result")
    run.add_argument("--label", help="a name for this run in the store's history, e.g. a git commit "
                                     "(`compare` and `report --run` accept it)")
    run.add_argument("--executor", choices=("local", "ray", "ssh"), default="local",
                     help="where cells run: this machine, a Ray cluster, or converted here and measured on "
                          "SSH devices (docs/running.md, docs/devices.md; default: local)")
    run.add_argument("--address", help="the Ray cluster to use (HOST:6379, ray://HOST:10001 or auto; "
                                       "default: $RAY_ADDRESS, else a Ray started on this machine)")
    run.add_argument("--shard", help="I/N: run only shard I of N of the chosen cells (one per machine of a "
                                     "batch scheduler; `merge` their stores)")
    add_device_options(run)
    add_require(run)
    add_model_options(run)
    _filters(run)
    run.set_defaults(handler=_run)

    plan = sub.add_parser("plan", help="expand the matrix and show what run would do with each cell")
    plan.add_argument("matrix", type=Path, help="a matrix .yaml, or a model file or SavedModel folder: the "
                                                "automatic matrix `run` would run")
    plan.add_argument("--results", type=Path, help="mark cells already stored in this results file "
                                                   "(default: WORKSPACE/results.sqlite)")
    plan.add_argument("--all", action="store_true", dest="show_all",
                      help="list every combination that is not valid, one row each")
    add_model_options(plan)
    _filters(plan)
    plan.set_defaults(handler=_plan)

    report = sub.add_parser("report", help="tables in the terminal and Markdown pages from stored results")
    report.add_argument("--results", type=Path, help="SQLite results file (default: WORKSPACE/results.sqlite)")
    report.add_argument("--format", choices=("table", "md", "html", "json", "csv"), default="table",
                        help="table: terminal tables, Markdown pages and report.html; md, html: only those "
                             "(default: %(default)s)")
    report.add_argument("--out", type=Path, default=Path("reports"), help="directory for pages (default: %(default)s)")
    report.add_argument("--run", help="the records of one run (its id, its label, `latest` or `previous`) instead "
                                      "of the newest record of each cell")
    _filters(report, VIEW_KEYS, "records of")
    add_report_options(report)
    report.set_defaults(handler=_report)

    backends = sub.add_parser("backends", help="installed backends, what they support, what this machine can run")
    backends.set_defaults(handler=_backends)

    schema = sub.add_parser("schema", help="print the JSON Schema of matrix files, with what the installed "
                                           "backends and metric plugins declare")
    schema.add_argument("--builtin", action="store_true",
                        help="the built-in schema only (docs/matrix.schema.json), without installed plugins")
    schema.set_defaults(handler=_schema)
    add_commands(sub)
    add_device_command(sub)
    add_init(sub)
    return parser


def _filters(parser: argparse.ArgumentParser, keys: tuple[str, ...] = FILTER_KEYS,
             what: str = "cells with") -> None:
    """A repeatable `--KEY` option for each of `keys`, helped as 'only WHAT this KEY'."""
    group = parser.add_argument_group("filters (repeat an option or separate values with commas)")
    for key in keys:
        group.add_argument(f"--{key}", action="append", metavar=key.upper(), help=f"only {what} this {key}")


def _values(args: argparse.Namespace, keys: tuple[str, ...]) -> dict[str, frozenset[str]]:
    """The values of repeatable, comma-separated options, by key."""
    values = {}
    for key in keys:
        given = getattr(args, key)
        if given:
            values[key] = frozenset(v.strip() for item in given for v in item.split(",") if v.strip())
            if not values[key]:
                raise UserError(f"--{key} {','.join(given)!r}: give at least one {key} (several: separate "
                                f"them with commas)")
    return values


def _selected(args: argparse.Namespace):
    from bench_matrix.selection import Filters

    return Filters(_values(args, FILTER_KEYS))


def _check_paths(args: argparse.Namespace) -> None:
    """Check --workspace, --results and --out before anything runs: one message naming the option and path."""
    if args.command in ("schema", "merge", "compare"):
        return
    if args.command not in ("report", "runs") or args.results is None:
        _check_folder("--workspace", args.workspace, "for caches, logs and results")
    if args.command in ("plan", "report", "runs"):
        _check_results(args)
    if args.command == "report" and args.format != "json":
        _check_folder("--out", args.out, "the report's pages are written to")


def _check_folder(option: str, folder: Path, purpose: str) -> None:
    """A folder the command writes into: not a file; it, or the nearest folder it would be made in, is
    writable."""
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{option} {folder}: is a file; {option} names a folder ({purpose})")
    existing = next(p for p in (folder, *folder.absolute().parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"{option} {folder}: cannot write there ({existing} is not a writable folder)")


def _check_results(args: argparse.Namespace) -> None:
    """plan and report only read a results file: an explicit one must exist, any existing one be a store."""
    from bench_matrix.store import ResultStore

    path = results_file(args)
    label = "--results" if args.results else "results file"
    if (args.results or args.command == "runs") and not os.path.lexists(path):
        raise UserError(f"--results {path}: no such file; `bench-matrix run MATRIX --results {path}` "
                        f"writes one")
    if os.path.lexists(path):
        ResultStore(path, readonly=True, label=label).close()


def _run(args: argparse.Namespace, console) -> int:
    from bench_matrix.cli_auto import matrix_of
    from bench_matrix.cli_verdict import print_run_verdict
    from bench_matrix.matrix.require import parse_require
    from bench_matrix.plan_view import show_inputs
    from bench_matrix.run import run
    from bench_matrix.selection import Shard

    shard = Shard.parse(args.shard) if args.shard is not None else Shard()
    given, args.matrix = args.matrix, matrix_of(args, console)
    matrix, ws = load(args.matrix, args.workspace)
    filters, overrides = _selected(args), parse_require(args.require)
    store = open_store(matrix, ws, args.results, console)
    with open_run(matrix, ws, store, lambda ws: _connect(args, console, ws)) as (plan, executor):
        show_inputs(console, plan, filters, automatic=args.matrix != given)
        counts = run(plan, ws, store, executor, console, filters, args.force, args.label, shard)
    invalid = len(plan.by_state("invalid"))
    console.print(f"[bold]done:[/] {counts['ok']} ok, {counts['skipped']} skipped, {counts['failed']} failed, "
                  f"{counts['cached']} already stored" + (f"; {invalid} combinations are not valid "
                                                          f"(`bench-matrix plan` says why)" if invalid else ""))
    print_run_verdict(results_file(args), matrix, overrides, console)
    console.print("Next: [bold]bench-matrix report[/]", highlight=False)
    for why in executor.lost().values():
        console.print(f"{why}; the cells given to it failed", style="red", markup=False, highlight=False)
    return 1 if executor.lost() else 0


def _connect(args: argparse.Namespace, console, ws: Workspace):
    """The executor --executor names, connected to while the console says so."""
    from bench_matrix.executors import open_executor

    connecting = {"ray": "connecting to the Ray cluster (or starting one here) …",
                  "ssh": "logging in to the devices …"}.get(args.executor)
    with console.status(connecting) if connecting else contextlib.nullcontext():
        return open_executor(args.executor, ws, args.address, ssh_options(args, args.device))


def _plan(args: argparse.Namespace, console) -> int:
    from bench_matrix.cli_auto import matrix_of
    from bench_matrix.executors.local import probe
    from bench_matrix.plan import resolve
    from bench_matrix.plan_view import show_plan

    given, args.matrix = args.matrix, matrix_of(args, console)
    matrix, ws = load(args.matrix, args.workspace)
    filters = _selected(args)
    show_plan(console, resolve(matrix, ws, probe), ws, filters, args.results, args.show_all,
              automatic=args.matrix != given)
    return 0


def _report(args: argparse.Namespace, console) -> int:
    from rich.console import Console

    from bench_matrix.cli_verdict import gate, judging
    from bench_matrix.report import View, load_judged, write_stored

    results = results_file(args)
    view = View(args.run, _values(args, VIEW_KEYS))
    stored = load_judged(results, view, judging(args), with_samples=args.format in ("table", "md", "html"))
    write_stored(stored, args.format, args.out, console)
    return gate(stored.report, Console(stderr=True)) if args.check else 0


def _backends(args: argparse.Namespace, console) -> int:
    from bench_matrix.plan_view import show_backends
    from bench_matrix.workspace import Workspace

    show_backends(console, Workspace(args.workspace))
    return 0


def _schema(args: argparse.Namespace, console) -> int:
    from bench_matrix.matrix.extended import installed_schema, schema_json

    if args.builtin:
        sys.stdout.write(schema_json())
        return 0
    from bench_matrix.measure.metric_plugins import metric_names
    from bench_matrix.registry import vocabulary

    sys.stdout.write(schema_json(installed_schema(vocabulary(), metric_names())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
