"""The Ray executor: the driver (this process) probes every node, ships the shared preparation through the
object store, and runs each cell's conversion and measurement as Ray tasks, each job still in its own process
on the node. A node measures one cell at a time: every node offers the resource `bench_matrix_timing: 1`, a
measurement takes more than half of it, a conversion a sliver (so conversions overlap, and only go to
bench-matrix nodes); the measurement runs on the node holding the artifact (node affinity)."""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from bench_matrix.cell import Cell, CellPlan
from bench_matrix.errors import UserError
from bench_matrix.executors import ray_tasks
from bench_matrix.executors.base import CellResult, CellWork, Executor, Phase, Tick
from bench_matrix.jobs.probe import devices
from bench_matrix.launcher import Outcome
from bench_matrix.matrix.expand import Verdict, plan as judge, training_key, verdict_key
from bench_matrix.measure import env as environment
from bench_matrix.plan import Plan
from bench_matrix.sources import SourceModel
from bench_matrix.sources.onnx_file import external_data_files
from bench_matrix.workspace import Workspace

TIMING = "bench_matrix_timing"
MEASURE_SHARE = 0.6  # more than half of a node's 1: two measurements never share a node
CONVERT_SHARE = 0.01  # beside one measurement, up to 40 conversions fit (CPUs permitting)
GPU_SHARE = 0.01  # tasks of cells on a CUDA device see the node's GPU (Ray hides GPUs from tasks asking none)
MAX_ATTEMPTS = 3  # a cell whose task or node is lost runs again, elsewhere if need be, this many times in all
INSTALL = "pip install 'bench-matrix[ray]'"
NO_USAGE_STATS = "RAY_USAGE_STATS_ENABLED"  # "0": Ray sends no usage statistics from clusters it starts


@dataclass
class _Flight:
    """A task in flight: its cell, its stage (convert, measure), attempt, node and when it was submitted."""

    work: CellWork
    stage: str
    attempt: int
    submitted: float
    node: str | None = None
    job: Any = None  # the measurement job, once converted
    log: str = ""  # the cell's log on its node, once converted
    timing: dict[str, float] | None = None  # the conversion's, once converted


class RayExecutor(Executor):
    """Cells as Ray tasks on the nodes of a cluster; results come back as each cell ends."""

    def __init__(self, workspace: Workspace, address: str | None):
        try:
            import ray
        except ImportError:
            raise UserError(f"--executor ray needs Ray, which is not installed here: {INSTALL}") from None
        self.ray, self.workspace = ray, workspace
        _connect(ray, address or os.environ.get("RAY_ADDRESS") or None)
        self.nodes = _timing_nodes(ray.nodes(), address)
        self.hostnames: dict[str, str] = {}  # node id -> host, from the probes
        self._able: dict[str, list[str]] = {}  # cell key -> nodes that can run it
        self._devices: dict[tuple[str, str], str] = {}  # (backend, target) -> its device, as the nodes probed
        self._shipped: dict[str, ray_tasks.Shipment] = {}
        self._flights: dict[Any, _Flight] = {}
        self._ended: list[CellResult] = []
        tasks = (ray_tasks.probe_node, ray_tasks.convert_on_node, ray_tasks.measure_on_node)
        self._remote = {fn.__name__: ray.remote(fn) for fn in tasks}

    def decide(self, plan: Plan, cells: list[CellPlan]) -> list[CellPlan]:
        """Probe every node; a cell runs where a node can run it, else is skipped with each node's reason."""
        states = self._probe(plan, cells)
        decided = []
        for p in cells:
            if p.state != "run" and p.state != "skip":
                decided.append(p)
                continue
            judged = {node: states[node][p.cell] for node in self.nodes}
            self._able[p.cell.key] = [n for n, (state, _) in judged.items() if state == "run"]
            decided.append(replace(p, state="run", reason=None) if self._able[p.cell.key] else
                           replace(p, state="skip", reason=self._reasons(judged)))
        return decided

    def _probe(self, plan: Plan, cells: list[CellPlan]) -> dict[str, dict[Any, tuple[str, str | None]]]:
        """Each node's judgement (state, reason) of each cell, from a probe task pinned to the node."""
        matrix = plan.matrix
        keys = tuple(sorted({verdict_key(matrix, p.cell) for p in cells}))
        training = tuple(sorted({k for p in cells if (k := training_key(matrix, p.cell))}))
        names = tuple(sorted({k[0] for k in keys}))
        probe = self._remote["probe_node"]
        refs = {node: probe.options(num_cpus=0, num_gpus=gpus, scheduling_strategy=self._on(node)).remote(
                    names, keys, training) for node, gpus in self.nodes.items()}
        states = {}
        for node, ref in refs.items():
            try:
                probed = self.ray.get(ref)
            except self.ray.exceptions.RayError as exc:  # the node died or cannot run tasks
                probed = {"host": node[:8], "error": f"{type(exc).__name__}: {exc}"}
            self.hostnames[node] = probed["host"]
            if probed["error"]:
                failed = f"probing the node failed: {probed['error']}"
                states[node] = {p.cell: ("skip", failed) for p in cells}
                continue
            value = probed["value"]
            self._devices.update(devices(value["backends"]))
            verdicts = {tuple(json.loads(k)): Verdict(**v) for k, v in value["verdicts"].items()}
            trainers = {tuple(json.loads(k)): Verdict(**v) for k, v in value["trainers"].items()}
            expansion = judge(matrix, [p.cell for p in cells], 0, verdicts, trainers)
            states[node] = {q.cell: (q.state, q.reason) for q in expansion.cells}
        return states

    def _reasons(self, judged: dict[str, tuple[str, str | None]]) -> str:
        """Why no node can run a cell: each distinct reason, after the hosts it concerns."""
        by_reason: dict[str, list[str]] = {}
        for node, (_, reason) in judged.items():
            by_reason.setdefault(reason or "not valid there", []).append(self.hostnames.get(node, node[:8]))
        return "; ".join(f"{', '.join(sorted(set(hosts)))}: {reason}" for reason, hosts in by_reason.items())

    def hosts(self) -> set[str]:
        return set(self.hostnames.values()) or {environment.host_name()}

    def submit(self, work: CellWork, on_phase: Phase, tick: Tick) -> None:
        self._convert(work, attempt=1)

    def _convert(self, work: CellWork, attempt: int) -> None:
        shipments = {str(p): self._ship(p, work.convert.source) for p in _needed(work)}
        node = self._placement(work)
        options = self._options(work, CONVERT_SHARE, self._on(node) if node else "DEFAULT")
        now = time.time()
        ref = self._remote["convert_on_node"].options(**options).remote(work, shipments, now)
        self._flights[ref] = _Flight(work, "convert", attempt, now, node)

    def _measure(self, flight: _Flight, timeout_s: float) -> None:
        options = self._options(flight.work, MEASURE_SHARE, self._on(flight.node))
        flight.submitted, flight.stage = time.time(), "measure"
        ref = self._remote["measure_on_node"].options(**options).remote(flight.job, flight.log, timeout_s,
                                                                        flight.submitted)
        self._flights[ref] = flight

    def _options(self, work: CellWork, share: float, strategy: Any) -> dict[str, Any]:
        return {"num_cpus": 1, "num_gpus": gpu_share(self._devices, work.plan.cell),
                "resources": {TIMING: share}, "max_retries": 0, "scheduling_strategy": strategy}

    def _placement(self, work: CellWork) -> str | None:
        """None (Ray's choice) when every node can run the cell; else the able node with the fewest tasks."""
        able = self._able.get(work.plan.cell.key, list(self.nodes))
        if set(able) >= set(self.nodes):
            return None
        busy = {n: 0 for n in able}
        for flight in self._flights.values():
            if flight.node in busy:
                busy[flight.node] += 1
        return min(able, key=lambda n: busy[n])

    def _on(self, node: str | None) -> Any:
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        return NodeAffinitySchedulingStrategy(node_id=node, soft=False)

    def _ship(self, path: Path, source: SourceModel) -> ray_tasks.Shipment:
        """The path's content in the object store (the source model's with its external data), put there once
        per run."""
        if str(path) not in self._shipped:
            beside = external_data_files(path) if path == source.path and source.format == "onnx" else []
            key, data = ray_tasks.pack(path, beside)
            self._shipped[str(path)] = ray_tasks.Shipment(key, path.name, self.ray.put(data))
        return self._shipped[str(path)]

    def results(self, wait: bool) -> Iterator[CellResult]:
        while self._flights or self._ended:
            if self._flights:
                ready, _ = self.ray.wait(list(self._flights), num_returns=1 if wait else len(self._flights),
                                         timeout=None if wait else 0)
                for ref in ready:
                    self._advance(ref, self._flights.pop(ref))
            while self._ended:
                yield self._ended.pop(0)
            if not wait:
                return

    def _advance(self, ref: Any, flight: _Flight) -> None:
        """A task ended: measure a converted cell, or end the cell; a lost task runs again or fails."""
        try:
            value = self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as exc:  # our code raised on the node: no retry
            self._ended.append(self._failed(flight, f"{flight.stage} on the Ray node failed: {exc}"))
            return
        except self.ray.exceptions.RayError as exc:  # the worker, its node or an object was lost
            self._lost(flight, f"{type(exc).__name__}: {str(exc).strip().splitlines()[0]}")
            return
        if flight.stage == "convert":
            self._converted(flight, value)
        else:
            self._measured(flight, value)

    def _converted(self, flight: _Flight, value: dict[str, Any]) -> None:
        flight.node, flight.timing = value["node"], value["timing"]
        self.hostnames.setdefault(value["node"], value["host"])
        if value["error"]:
            self._ended.append(CellResult(flight.work, error=f"convert: {value['error']}", env=value["env"]))
            return
        flight.job, flight.log = value["job"], value["log"]
        used = value["timing"]["ship_s"] + value["timing"]["job_s"]
        self._measure(flight, max(flight.work.convert.settings.timeout_s - used, 1.0))

    def _measured(self, flight: _Flight, value: dict[str, Any]) -> None:
        outcome, artifact = value["outcome"], str(flight.job.artifact_dir / "model")
        if not outcome.ok:
            self._ended.append(CellResult(flight.work, error=f"measure: {outcome.error}", artifact=artifact,
                                          env=value["env"], placement=flight.node))
            return
        measured = dict(outcome.value)
        measured["env"] = {**measured["env"], "ray": self._placement_facts(flight, value["timing"])}
        self._ended.append(CellResult(flight.work, measured=measured, artifact=artifact,
                                      again=replace(flight.job, closed_loop=None), placement=flight.node))

    def _placement_facts(self, flight: _Flight, measured: dict[str, float]) -> dict[str, Any]:
        """Where the cell ran and what Ray added: waiting to be scheduled, shipping, returning results."""
        converted = flight.timing or {}
        returned = max(time.time() - measured["ended"], 0.0)
        return {"node_id": flight.node, "attempt": flight.attempt,
                "scheduled_s": round(converted.get("scheduled_s", 0.0) + measured["scheduled_s"], 4),
                "ship_s": round(converted.get("ship_s", 0.0), 4), "returned_s": round(returned, 4),
                "convert_s": round(converted.get("job_s", 0.0), 4), "measure_s": round(measured["job_s"], 4)}

    def _lost(self, flight: _Flight, why: str) -> None:
        """Run a lost cell again from its conversion, on the nodes still alive, or fail it."""
        alive = {n["NodeID"] for n in self.ray.nodes() if n.get("Alive")}
        self.nodes = {n: gpus for n, gpus in self.nodes.items() if n in alive}
        self._able = {key: [n for n in able if n in alive] for key, able in self._able.items()}
        if flight.attempt < MAX_ATTEMPTS and self._able.get(flight.work.plan.cell.key, self.nodes):
            self._convert(flight.work, flight.attempt + 1)
            return
        tries = f"{flight.attempt} attempts" if flight.attempt > 1 else "1 attempt; no node left to retry on"
        reason = f"{flight.stage}: lost on the Ray cluster ({tries}); last: {why}"
        self._ended.append(self._failed(flight, reason))

    def _failed(self, flight: _Flight, reason: str) -> CellResult:
        env = environment.capture()
        if flight.node in self.hostnames:
            env["host"] = self.hostnames[flight.node]
        return CellResult(flight.work, error=reason, env=env, placement=flight.node)

    def measure_again(self, result: CellResult, on_phase: Phase, tick: Tick) -> Outcome:
        job = result.again
        options = self._options(result.work, MEASURE_SHARE, self._on(result.placement))
        ref = self._remote["measure_on_node"].options(**options).remote(job, str(job.workspace.cell_log(
            result.work.plan.cell.key)), job.settings.timeout_s, time.time())
        try:
            return self.ray.get(ref)["outcome"]
        except self.ray.exceptions.RayError as exc:
            return Outcome(error=f"measure on the Ray node failed: {type(exc).__name__}: {exc}")

    def close(self) -> None:
        for ref in self._flights:
            self.ray.cancel(ref, force=True)
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


def _needed(work: CellWork) -> list[Path]:
    """The driver's files a cell's jobs read: its source model, its dataset splits, its reference outputs."""
    paths = [work.convert.source.path, work.convert.data.directory, work.measure.reference]
    return [p for p in dict.fromkeys(paths) if p is not None]


def _timing_nodes(nodes: list[dict[str, Any]], address: str | None) -> dict[str, float]:
    """The alive nodes offering the timing resource, with their GPU counts; a UserError when there is none."""
    found = {n["NodeID"]: n["Resources"].get("GPU", 0) for n in nodes
             if n.get("Alive") and n["Resources"].get(TIMING, 0) >= 1}
    if not found:
        where = f" at {address}" if address else ""
        raise UserError(f"no node of the Ray cluster{where} offers the resource {TIMING}; start each node "
                        f"with ray start --resources='{{\"{TIMING}\": 1}}' (docs/running.md)")
    return found
