"""Where a run's jobs execute: each in its own process on this machine (local), as tasks on a Ray cluster, or
here with measurement on SSH devices. The interface is executors/base.py; importing this package imports no
executor."""

from __future__ import annotations

from typing import TYPE_CHECKING

from bench_matrix.errors import UserError

if TYPE_CHECKING:
    from bench_matrix.executors.base import Executor
    from bench_matrix.executors.ssh_executor import SshOptions
    from bench_matrix.workspace import Workspace

EXECUTORS = ("local", "ray", "ssh")


def open_executor(kind: str, workspace: Workspace, address: str | None = None,
                  ssh: SshOptions | None = None) -> Executor:
    """The executor `kind` names (`--executor`); Ray is imported only when asked for."""
    if ssh is not None and ssh.devices and kind != "ssh":
        raise UserError("--device names an SSH device; use it with --executor ssh")
    if kind == "ssh":
        from bench_matrix.executors.ssh_executor import SshExecutor

        return SshExecutor(workspace, ssh)
    if kind == "local":
        if address is not None:
            raise UserError("--address names a Ray cluster; use it with --executor ray")
        from bench_matrix.executors.local import LocalExecutor

        return LocalExecutor(workspace)
    if kind == "ray":
        from bench_matrix.executors.ray_cluster import RayExecutor

        return RayExecutor(workspace, address)
    raise UserError(f"--executor {kind}: unknown executor; choose one of {', '.join(EXECUTORS)}")
