"""Where a run's cells execute: one process per job on this machine (local), or as tasks on a Ray cluster."""

from __future__ import annotations

from bench_matrix.errors import UserError
from bench_matrix.executors.base import CellResult, CellWork, Executor
from bench_matrix.workspace import Workspace

EXECUTORS = ("local", "ray")

__all__ = ["EXECUTORS", "CellResult", "CellWork", "Executor", "open_executor"]


def open_executor(kind: str, workspace: Workspace, address: str | None = None) -> Executor:
    """The executor `kind` names (`--executor`); Ray is imported only when asked for."""
    if kind == "local":
        if address is not None:
            raise UserError("--address names a Ray cluster; use it with --executor ray")
        from bench_matrix.executors.local import LocalExecutor

        return LocalExecutor(workspace)
    if kind == "ray":
        from bench_matrix.executors.ray_cluster import RayExecutor

        return RayExecutor(workspace, address)
    raise UserError(f"--executor {kind}: unknown executor; choose one of {', '.join(EXECUTORS)}")
