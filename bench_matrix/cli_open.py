"""What the commands open, one way for all: a matrix (its warnings said) and the workspace; a run's results
store, executor and plan (`run`, `compare --remeasure`); the results store a command reads."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix import __version__
from bench_matrix.workspace import Workspace

if TYPE_CHECKING:
    from bench_matrix.executors.base import Executor
    from bench_matrix.matrix.spec import Matrix
    from bench_matrix.plan import Plan
    from bench_matrix.store import ResultStore


def load(matrix: Path, workspace: Path) -> tuple[Matrix, Workspace]:
    """The matrix file loaded (its warnings on stderr), and the workspace."""
    from bench_matrix.matrix.load import load_matrix
    from bench_matrix.registry import available

    loaded = load_matrix(matrix, backends=list(available()))
    warn(loaded.warnings)
    return loaded, Workspace(workspace)


def warn(warnings: tuple[str, ...]) -> None:
    """A matrix's warnings (retired keys it still uses), on stderr."""
    from rich.console import Console

    console = Console(stderr=True)
    for warning in warnings:
        console.print("[yellow]warning:[/] ", end="", highlight=False)
        console.print(warning, markup=False, highlight=False, soft_wrap=True)


def local(ws: Workspace) -> Executor:
    """This machine's executor."""
    from bench_matrix.executors import open_executor

    return open_executor("local", ws)


def open_store(matrix: Matrix, ws: Workspace, results: Path | None, console: Any) -> ResultStore:
    """The results store a run writes (`results`, else the workspace's), where the results go said."""
    from bench_matrix.store import ResultStore

    if results is None:
        ws.root.mkdir(parents=True, exist_ok=True)  # checked writable before
    store = ResultStore(results or ws.results, label="--results" if results else "results file")
    console.print(f"[bold]bench-matrix {__version__}[/] · {matrix.path} · results in {results or ws.results}",
                  highlight=False)
    return store


@contextmanager
def open_run(matrix: Matrix, ws: Workspace, store: ResultStore | None = None,
             executor: Callable[[Workspace], Executor] = local) -> Iterator[tuple[Plan, Executor]]:
    """A run's plan and executor: the matrix remembered in the store it writes (None: it stores nothing), the
    executor opened, every cell planned; the store and the executor closed after."""
    from bench_matrix.cli_verdict import remember
    from bench_matrix.executors.local import probe
    from bench_matrix.plan import resolve

    running = None
    try:
        if store is not None:
            remember(store, matrix)
        running = executor(ws)
        yield resolve(matrix, ws, probe), running
    finally:
        if store is not None:
            store.close()
        if running is not None:
            running.close()


def results_file(args: argparse.Namespace) -> Path:
    """The results store a command reads: --results, else the workspace's."""
    return args.results or args.workspace / "results.sqlite"
