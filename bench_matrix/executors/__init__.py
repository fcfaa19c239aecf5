"""Where a run's jobs execute: each in its own process on this machine (local), or as tasks on a Ray cluster.
The interface is executors/base.py; importing this package imports neither executor."""

from __future__ import annotations

from typing import TYPE_CHECKING

from bench_matrix.errors import UserError

if TYPE_CHECKING:
    from bench_matrix.executors.base import Executor
    from bench_matrix.workspace import Workspace

EXECUTORS = ("local", "ray")


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
