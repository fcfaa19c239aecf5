"""The verdict in the `bench-matrix` commands: `--require` on run and report, `--matrix` and the `--check`
gate on report, the requirements a run stores, and the verdict a run prints when it ends."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.errors import UserError

if TYPE_CHECKING:
    from bench_matrix.matrix.spec import Matrix
    from bench_matrix.report import Judging
    from bench_matrix.report.analysis.summary import Report
    from bench_matrix.store import ResultStore

REQUIRE_HELP = ("a requirement over the matrix's, KEY=VALUE: p50_ms=50, max_drop=5%%, top1.min=0.9, "
                "objective=size (docs/matrix.md, requirements); repeatable")


def add_require(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--require", action="append", default=[], metavar="KEY=VALUE", help=REQUIRE_HELP)


def add_report_options(parser: argparse.ArgumentParser) -> None:
    add_require(parser)
    parser.add_argument("--matrix", type=Path, help="judge every model by the requirements of this matrix "
                                                    "file (default: those of the matrix its records came "
                                                    "from)")
    parser.add_argument("--check", action="store_true", help="exit 1 when some model and target has no cell "
                                                              "that passes its requirements (a CI gate)")


def judging(args: argparse.Namespace) -> Judging:
    """The report's --matrix and --require, checked (exit 2 for a mistake)."""
    from bench_matrix.matrix.require import parse_require
    from bench_matrix.report import Judging

    if args.matrix is not None and not args.matrix.is_file():
        raise UserError(f"--matrix {args.matrix}: no such file; give the matrix file whose requirements to "
                        f"use")
    return Judging(args.matrix, parse_require(args.require))


def gate(report: Report, errors: Any) -> int:
    """The --check verdict: 1 (naming them) when some judged model and target has no passing cell, else 0."""
    from bench_matrix.report.analysis.judging import unmet

    judged = [m for m in report.models if m.requirements is not None]
    if not judged:
        raise UserError("--check: no model has requirements to check; add `requirements:` to the matrix or "
                        "give --require KEY=VALUE")
    missing = unmet(report)
    left = [m.name for m in report.models if m.requirements is None]
    if left:
        errors.print(f"check: not checked (no requirements): {', '.join(left)}", highlight=False,
                     markup=False)
    if missing:
        errors.print(f"check failed: no cell passes the requirements for {'; '.join(missing)}",
                     highlight=False, markup=False, soft_wrap=True)
        return 1
    count = sum(len(m.recommendations) for m in judged)
    errors.print(f"check passed: each of {count} model and target(s) has a passing cell", highlight=False,
                 markup=False)
    return 0


def remember(store: ResultStore, matrix: Matrix) -> None:
    """Store where the matrix is and what it requires: the report reads it again from there, else uses
    this."""
    from bench_matrix.report.analysis.judging import SCOPE, stored

    store.put_fact(SCOPE, str(matrix.path), stored(matrix.path, matrix.requirements))


def print_run_verdict(results: Path, matrix: Matrix, overrides: dict[str, Any], console: Any) -> None:
    """The Verdict section for the matrix's models, after a run (with its --require)."""
    from bench_matrix.report import Judging, View, load_judged
    from bench_matrix.report.render.terminal import print_verdict

    names = frozenset(m.name for m in matrix.models)
    try:
        stored = load_judged(results, View(only={"model": names}), Judging(overrides=overrides))
    except UserError:  # nothing of this matrix is stored
        return
    if any(m.requirements is not None for m in stored.report.models):
        print_verdict(stored.report.models, console)
