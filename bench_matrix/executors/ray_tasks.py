"""What runs on a Ray node: unpack what a job reads into the node's workspace, run the job there with the
local executor, pack what it made for jobs elsewhere (Ray is imported only inside functions)."""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench_matrix.executors.base import Limits, Work
from bench_matrix.executors.local import LocalExecutor
from bench_matrix.executors.shipping import SHIPPED, extract, named_back, pack, relocate, shipped_folder
from bench_matrix.jobs import Job
from bench_matrix.measure import env as environment
from bench_matrix.workspace import Workspace

NODE_WORKSPACE_VARIABLE = "BENCH_MATRIX_NODE_WORKSPACE"


@dataclass(frozen=True)
class Shipment:
    """A file or folder (dataset splits, model source, reference outputs) in the object store, packed as tar;
    `key` names its content, so a node unpacks it once."""

    key: str
    name: str
    ref: Any  # ray.ObjectRef of the tar bytes (or of a task's packed outputs); fetched only when missing
    member: str | None = None  # in a task's packed outputs: the entry holding this tar


@dataclass(frozen=True)
class NodeEnded:
    """How a job ended on a node: the node and its host, the job's result (paths as the driver names them) or
    why it failed, the outputs it packed (path -> content key and name) and how long each part took."""

    node: str
    host: str
    result: Any = None
    error: str | None = None
    user_error: bool = False
    env: dict[str, Any] | None = None  # where it failed
    made: dict[str, tuple[str, str]] = field(default_factory=dict)
    timing: dict[str, float] = field(default_factory=dict)


def node_workspace() -> Workspace:
    """This node's workspace: $BENCH_MATRIX_NODE_WORKSPACE, else ~/.cache/bench-matrix/node."""
    root = os.environ.get(NODE_WORKSPACE_VARIABLE, "").strip()
    return Workspace(Path(root) if root else Path.home() / ".cache" / "bench-matrix" / "node")


def unpack(shipments: dict[str, Shipment], ws: Workspace) -> dict[str, str]:
    """Each shipment in the node's workspace (fetched from the object store only when missing); the driver's
    path -> the node's path."""
    import ray

    moved = {}
    for driver_path, shipment in shipments.items():
        final = shipped_folder(ws, shipment.key)
        if not final.is_dir():
            data = ray.get(shipment.ref)
            extract(data if shipment.member is None else data[shipment.member], final, ws)
        moved[driver_path] = str(final / shipment.name)
    return moved


def run_on_node(job: Job, limits: Limits, shipments: dict[str, Shipment],
                submitted: float) -> tuple[NodeEnded, dict[str, bytes]]:
    """Unpack what the job reads, run it here (log: the node's own, same name), pack the files its result
    names that it made; how it ended, and those packed files (the task's second return)."""
    import ray

    begin, ws = time.time(), node_workspace()
    ws.sweep()  # what a killed run left on this node
    moved = unpack(shipments, ws)
    here = relocate(job, moved, ws)
    unpacked = time.time()
    ended = LocalExecutor(ws).run(Work(here, dataclasses.replace(limits, log=ws.logs / limits.log.name)))
    back = {new: old for old, new in moved.items()}
    made = {str(p): pack(p) for p in (ended.result.files() if ended.ok else ()) if not _shipped(p, ws)}
    node_ended = NodeEnded(ray.get_runtime_context().get_node_id(), environment.host_name(),
                           result=relocate(ended.result, back, ws) if ended.ok else None,
                           error=named_back(ended.error, back), user_error=ended.user_error, env=ended.env,
                           made={path: (key, Path(path).name) for path, (key, _) in made.items()},
                           timing={"scheduled_s": begin - submitted, "ship_s": unpacked - begin,
                                   "job_s": time.time() - unpacked, "ended": time.time()})
    return node_ended, {path: data for path, (_, data) in made.items()}


def _shipped(path: Path, ws: Workspace) -> bool:
    """Whether the path is a copy of something shipped here (its origin is known; it needs no new packing)."""
    return path.is_relative_to(ws.root / SHIPPED)
