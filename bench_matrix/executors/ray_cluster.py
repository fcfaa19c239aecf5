"""The Ray executor: the driver probes every node and runs every job as a Ray task, what it reads shipped
through the object store; a node runs one rounds job (a model's cells, timed together) at a time (the
`bench_matrix_timing` resource)."""

from __future__ import annotations

import logging
import os
import time
import warnings
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import UserError
from bench_matrix.executors import ray_tasks
from bench_matrix.executors.base import Ended, Executor, Limits, Phase, Tick, Work
from bench_matrix.executors.local import PROBE_TIMEOUT_S
from bench_matrix.executors.ray_tasks import NodeEnded, Shipment
from bench_matrix.executors.shipping import pack
from bench_matrix.jobs import Job
from bench_matrix.jobs.results import MeasuredGroup
from bench_matrix.matrix.spec import Matrix, file_kind
from bench_matrix.measure import env as environment
from bench_matrix.placement import Probed
from bench_matrix.plan import probe_job
from bench_matrix.sources.onnx_file import external_data_files
from bench_matrix.workspace import Workspace

TIMING = "bench_matrix_timing"
MEASURE_SHARE = 0.6  # more than half of a node's 1: two measurements never share a node
JOB_SHARE = 0.01  # any other job: up to 40 fit beside one measurement (CPUs permitting)
GPU_SHARE = 0.01  # tasks of cells on a CUDA device see the node's GPU (Ray hides GPUs from tasks asking none)
MAX_ATTEMPTS = 3  # work whose task or node is lost runs again, elsewhere if need be, this many times in all
INSTALL = "pip install 'bench-matrix[ray]'"
NO_USAGE_STATS = "RAY_USAGE_STATS_ENABLED"  # "0": Ray sends no usage statistics from clusters it starts


@dataclass
class _Flight:
    """Work in flight: its attempt, its node, and when its task was submitted."""

    work: Work
    attempt: int
    node: str | None = None
    submitted: float = 0.0


class RayExecutor(Executor):
    """Jobs as Ray tasks on the nodes of a cluster; work comes back as each piece ends."""

    def __init__(self, workspace: Workspace, address: str | None):
        try:
            import ray
        except ImportError:
            raise UserError(f"--executor ray needs Ray, which is not installed here: {INSTALL}") from None
        self.ray, self.workspace = ray, workspace
        _connect(ray, address or os.environ.get("RAY_ADDRESS") or None)
        self.nodes = _timing_nodes(ray.nodes(), address)
        self.hostnames: dict[str, str] = {}  # node id -> host, from the probes
        self.able: dict[str, list[str]] = {}  # cell key -> nodes that can run it
        self._devices: dict[tuple[str, str], str] = {}  # (backend, target) -> its device, as the nodes probed
        self._shipped: dict[str, Shipment] = {}  # a path as the driver names it -> its content in the store
        self._flights: dict[Any, tuple[_Flight, Any]] = {}  # task ref -> its flight, ref of its packed files
        self._ended: list[Ended] = []
        self._remote = ray.remote(ray_tasks.run_on_node)

    def probes(self, matrix: Matrix, cells: list[CellPlan]) -> dict[str, Probed]:
        """Probe every node, with a task pinned to it: reasons name its host, the records of cells it skips
        carry this machine's."""
        job = probe_job(matrix, [p.cell for p in cells], self.workspace)
        limits = Limits(self.workspace.log("probe"), PROBE_TIMEOUT_S)
        refs = {node: self._remote.options(num_cpus=0, num_gpus=gpus, num_returns=2, name="probe_on_node",
                                           scheduling_strategy=self._on(node))
                .remote(job, limits, {}, time.time()) for node, gpus in self.nodes.items()}
        probed = {}
        for node, (ref, _) in refs.items():
            try:
                ended = self.ray.get(ref)
            except self.ray.exceptions.RayError as exc:  # the node died or cannot run tasks
                ended = NodeEnded(node, node[:8], error=f"{type(exc).__name__}: {exc}")
            self.hostnames[node] = ended.host
            failed = f"probing the node failed: {ended.error}" if ended.error else None
            probed[node] = Probed(ended.host, None, None if failed else ended.result, failed)
            self._devices.update({} if failed else ended.result.devices())
        return probed

    def hosts(self) -> set[str]:
        return set(self.hostnames.values()) or {environment.host_name()}

    def submit(self, work: Work, on_phase: Phase, tick: Tick) -> None:
        self._start(work, attempt=1)

    def _start(self, work: Work, attempt: int) -> None:
        self._launch(_Flight(work, attempt, node=work.on or self._placement(work.job)))

    def _launch(self, flight: _Flight) -> None:
        """Submit the flight's job as a task, with what it reads shipped."""
        job = flight.work.job
        cell = job.placed()
        shipments = {str(path): self._ship(path) for path in job.reads()}
        options = {"num_cpus": 1, "num_gpus": gpu_share(self._devices, cell) if cell else 0,
                   "resources": {TIMING: MEASURE_SHARE if job.timed else JOB_SHARE},
                   "max_retries": 0, "num_returns": 2, "name": f"{job.name}_on_node",
                   "scheduling_strategy": self._on(flight.node) if flight.node else "DEFAULT"}
        flight.submitted = time.time()
        ref, files = self._remote.options(**options).remote(job, flight.work.limits, shipments,
                                                            flight.submitted)
        self._flights[ref] = (flight, files)

    def _placement(self, job: Job) -> str | None:
        """None (Ray's choice) when every node can run the job; else the able node with the fewest tasks."""
        able = self._able_nodes(job)
        if set(able) >= set(self.nodes):
            return None
        busy = Counter(flight.node for flight, _ in self._flights.values())
        return min(able, key=lambda n: busy[n])

    def _able_nodes(self, job: Job) -> list[str]:
        cell = job.placed()
        return self.able.get(cell.key, list(self.nodes)) if cell else list(self.nodes)

    def _on(self, node: str | None) -> Any:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        return NodeAffinitySchedulingStrategy(node_id=node, soft=False)

    def _ship(self, path: Path) -> Shipment:
        """The path's content in the object store (an ONNX model's with its external data): put there once per
        run from this machine, unless a node made it and packed it already."""
        if str(path) not in self._shipped:
            beside = external_data_files(path) if file_kind(path) == ("onnx", "onnx") else []
            key, data = pack(path, beside)
            self._shipped[str(path)] = Shipment(key, path.name, self.ray.put(data))
        return self._shipped[str(path)]

    def ended(self, wait: bool) -> Iterator[Ended]:
        while self._flights or self._ended:
            if self._flights:
                ready, _ = self.ray.wait(list(self._flights), num_returns=1 if wait else len(self._flights),
                                         timeout=None if wait else 0)
                for ref in ready:
                    self._advance(ref, *self._flights.pop(ref))
            while self._ended:
                yield self._ended.pop(0)
            if not wait:
                return

    def _advance(self, ref: Any, flight: _Flight, files: Any) -> None:
        """A task ended: run the job that follows, or end the work; lost work runs again or fails."""
        try:
            ended: NodeEnded = self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as exc:  # our code raised on the node: no retry
            self._ended.append(self._failed(flight, f"failed on the Ray node: {exc}"))
            return
        except self.ray.exceptions.RayError as exc:  # the worker, its node or an object was lost
            self._lost(flight, f"{type(exc).__name__}: {str(exc).strip().splitlines()[0]}")
            return
        flight.node = ended.node
        self.hostnames.setdefault(ended.node, ended.host)
        for path, (key, name) in ended.made.items():
            self._shipped[path] = Shipment(key, name, files, member=path)
        if ended.error:
            self._ended.append(Ended(flight.work, (flight.work.job,), (), ended.error, ended.user_error,
                                     ended.env, ended.node))
        else:
            self._ended.append(Ended(flight.work, (flight.work.job,), (self._placed(flight, ended),),
                                     where=ended.node))

    def _placed(self, flight: _Flight, ended: NodeEnded) -> Any:
        """A rounds job's result with where each cell ran and what Ray added (`env.ray`): waiting to be
        scheduled, shipping, measuring, returning; other results as they came."""
        if not isinstance(ended.result, MeasuredGroup):
            return ended.result
        facts = {"node_id": ended.node, "attempt": flight.attempt,
                 "scheduled_s": round(ended.timing["scheduled_s"], 4),
                 "ship_s": round(ended.timing["ship_s"], 4), "measure_s": round(ended.timing["job_s"], 4),
                 "returned_s": round(max(time.time() - ended.timing["ended"], 0.0), 4)}
        return replace(ended.result, cells=tuple(
            replace(c, measured=replace(c.measured, env={**c.measured.env, "ray": facts}))
            if c.measured else c
            for c in ended.result.cells))

    def _lost(self, flight: _Flight, why: str) -> None:
        """Run lost work again, on the nodes still alive (work pinned to a node: on it, while it lives), or
        fail it."""
        alive = {n["NodeID"] for n in self.ray.nodes() if n.get("Alive")}
        self.nodes = {n: gpus for n, gpus in self.nodes.items() if n in alive}
        self.able = {key: [n for n in able if n in alive] for key, able in self.able.items()}
        where = [flight.work.on] if flight.work.on else self._able_nodes(flight.work.job)
        if flight.attempt < MAX_ATTEMPTS and set(where) & alive:
            self._start(flight.work, flight.attempt + 1)
            return
        tries = f"{flight.attempt} attempts" if flight.attempt > 1 else "1 attempt; no node left to retry on"
        self._ended.append(self._failed(flight, f"lost on the Ray cluster ({tries}); last: {why}"))

    def _failed(self, flight: _Flight, reason: str) -> Ended:
        env = environment.capture()
        if flight.node in self.hostnames:
            env["host"] = self.hostnames[flight.node]
        return Ended(flight.work, (flight.work.job,), (), reason, env=env, where=flight.node)

    def close(self) -> None:
        """Disconnect: Ray kills a departed driver's tasks. No `ray.cancel` first: after a Ctrl-C in
        `ray.wait`, Ray 2.52 aborts on one (exit 1, 'Tried to complete task that was not pending')."""
        self._flights.clear()
        self.ray.shutdown()


def gpu_share(known: dict[tuple[str, str], str], cell: Cell) -> float:
    """The GPUs a cell's task asks Ray for: a share where its backend runs its target on CUDA, else none."""
    return GPU_SHARE if known.get((cell.backend, cell.target)) == "cuda" else 0


def _connect(ray: Any, address: str | None) -> None:
    """Join the cluster at `address`, or start a one-node cluster of this machine; Ray's own chatter off."""
    quiet = {"log_to_driver": False, "logging_level": logging.WARNING}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)  # Ray's notice about GPU visibility defaults
            if address:
                ray.init(address=address, **quiet)
            else:  # a cluster of our own: nothing reported to Ray's usage statistics service
                os.environ.setdefault(NO_USAGE_STATS, "0")
                ray.init(resources={TIMING: 1}, include_dashboard=False, **quiet)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise UserError(f"--address {address}: cannot connect to a Ray cluster there ({exc})") from None


def _timing_nodes(nodes: list[dict[str, Any]], address: str | None) -> dict[str, float]:
    """The alive nodes offering the timing resource, with their GPU counts; a UserError when there is none."""
    found = {n["NodeID"]: n["Resources"].get("GPU", 0) for n in nodes
             if n.get("Alive") and n["Resources"].get(TIMING, 0) >= 1}
    if not found:
        where = f" at {address}" if address else ""
        raise UserError(f"no node of the Ray cluster{where} offers the resource {TIMING}; start each node "
                        f"with ray start --resources='{{\"{TIMING}\": 1}}' (docs/running.md)")
    return found
