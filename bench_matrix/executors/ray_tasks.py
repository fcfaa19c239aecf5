"""What runs on a Ray node: probe the node, unpack the shared preparation shipped through the object store
into the node's own workspace, convert a cell and measure it, each job in its own process
(`launcher.run_job`).

Imported by Ray workers by reference; it imports Ray only inside the functions that need it."""

from __future__ import annotations

import dataclasses
import io
import os
import shutil
import tarfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.executors.base import CellWork
from bench_matrix.executors.local import convert_cell, measure_cell
from bench_matrix.jobs import MeasureJob, ProbeJob
from bench_matrix.launcher import run_job
from bench_matrix.measure import env as environment
from bench_matrix.workspace import Workspace, digest

NODE_WORKSPACE_VARIABLE = "BENCH_MATRIX_NODE_WORKSPACE"
PROBE_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class Shipment:
    """A file or folder of the driver's (dataset splits, model source, reference outputs) in the object store,
    packed as tar; `key` names its content, so a node unpacks it once."""

    key: str
    name: str
    ref: Any  # ray.ObjectRef of the tar bytes; fetched only by a node that lacks the content


def node_workspace() -> Workspace:
    """This node's workspace: $BENCH_MATRIX_NODE_WORKSPACE, else ~/.cache/bench-matrix/node."""
    root = os.environ.get(NODE_WORKSPACE_VARIABLE, "").strip()
    return Workspace(Path(root) if root else Path.home() / ".cache" / "bench-matrix" / "node")


def pack(path: Path, beside: Sequence[Path] = ()) -> tuple[str, bytes]:
    """A file or folder, with the files `beside` it that it reads (an ONNX model's external data), as tar
    bytes, and the key of its content (names, sizes, modification times)."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path, *beside]
    stats = [(str(f.relative_to(path if path.is_dir() else path.parent)), f.stat().st_size,
              f.stat().st_mtime_ns) for f in files]
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(path, arcname=path.name)
        for extra in beside:
            tar.add(extra, arcname=str(extra.relative_to(path.parent)))
    return digest({"path": str(path), "files": stats}), buffer.getvalue()


def unpack(shipments: dict[str, Shipment], ws: Workspace) -> dict[str, str]:
    """Each shipment in the node's workspace (fetched from the object store only when missing); the driver's
    path -> the node's path."""
    import ray

    moved = {}
    for driver_path, shipment in shipments.items():
        final = ws.root / "shipped" / shipment.key
        if not final.is_dir():
            tmp = final.with_name(f"{final.name}.tmp{os.getpid()}")
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            with tarfile.open(fileobj=io.BytesIO(ray.get(shipment.ref)), mode="r") as tar:
                tar.extractall(tmp, filter="data")
            try:
                tmp.rename(final)
            except OSError:  # another task on this node unpacked it first
                shutil.rmtree(tmp, ignore_errors=True)
        moved[driver_path] = str(final / shipment.name)
    return moved


def relocate(value: Any, moved: dict[str, str], ws: Workspace) -> Any:
    """`value` (a job, or anything in it) with the driver's paths replaced by the node's and every workspace
    by the node's."""
    if isinstance(value, Workspace):
        return ws
    if isinstance(value, Path):
        return Path(_moved(str(value), moved))
    if isinstance(value, str):
        return _moved(value, moved)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{f.name: relocate(getattr(value, f.name), moved, ws)
                                             for f in dataclasses.fields(value) if f.init})
    if isinstance(value, (tuple, list)):
        return type(value)(relocate(v, moved, ws) for v in value)
    if isinstance(value, dict):
        return {k: relocate(v, moved, ws) for k, v in value.items()}
    return value


def _moved(text: str, moved: dict[str, str]) -> str:
    for old, new in moved.items():
        if text == old or text.startswith(old + "/"):
            return new + text[len(old):]
    return text


def probe_node(names: tuple[str, ...], keys: tuple, training: tuple) -> dict[str, Any]:
    """The node's host and its probe: backends described, verdicts per combination, trainers."""
    ws = node_workspace()
    outcome = run_job(ProbeJob(ws, names, keys, training), ws.jobs, ws.log("probe"), PROBE_TIMEOUT_S)
    return {"host": environment.host_name(), "error": outcome.error, "value": outcome.value}


def convert_on_node(work: CellWork, shipments: dict[str, Shipment], submitted: float) -> dict[str, Any]:
    """Unpack what the cell needs, convert it here; the measurement job of its artifact (or the error), this
    node's id and host, and how long shipping and the job took."""
    import ray

    begin, ws = time.time(), node_workspace()
    moved = unpack(shipments, ws)
    work = dataclasses.replace(relocate(work, moved, ws), log=ws.cell_log(work.plan.cell.key))
    unpacked = time.time()
    converted, job = convert_cell(work, _quiet, _quiet)
    return {"node": ray.get_runtime_context().get_node_id(), "host": environment.host_name(),
            "error": converted.error, "job": job, "log": str(work.log),
            "env": None if job else environment.capture(),
            "timing": {"scheduled_s": begin - submitted, "ship_s": unpacked - begin,
                       "job_s": time.time() - unpacked, "ended": time.time()}}


def measure_on_node(job: MeasureJob, log: str, timeout_s: float, submitted: float) -> dict[str, Any]:
    """Measure an artifact converted on this node; the outcome and how long it waited to be scheduled."""
    begin = time.time()
    outcome = measure_cell(job, Path(log), timeout_s, _quiet, _quiet)
    return {"host": environment.host_name(), "outcome": outcome,
            "env": None if outcome.ok else environment.capture(),
            "timing": {"scheduled_s": begin - submitted, "job_s": time.time() - begin, "ended": time.time()}}


def _quiet(*_: Any) -> None:
    """Phases and ticks of a job on a node: nobody watches them there."""
