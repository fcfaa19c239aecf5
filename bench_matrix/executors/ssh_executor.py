"""The SSH executor: every job but measuring runs here (the local executor); each model's rounds job runs on
an SSH device that can run its cells, with what it reads shipped there once by content, one rounds job per
device at a time. Devices are checked (login, versions) when it opens and probed in `decide`."""

from __future__ import annotations

import selectors
import shutil
import tempfile
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from bench_matrix.cell import CellPlan
from bench_matrix.errors import UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Phase, Tick, Work
from bench_matrix.executors.local import PROBE_TIMEOUT_S, LocalExecutor
from bench_matrix.executors.ssh_flight import Flight
from bench_matrix.executors.ssh_link import Device, Link, Unreachable
from bench_matrix.jobs import ProbeJob
from bench_matrix.matrix.expand import judge, training_key, verdict_key
from bench_matrix.measure import env as environment
from bench_matrix.plan import Plan
from bench_matrix.workspace import Workspace

Judged = tuple[str, str | None]  # a device's state of a cell (run, skip, invalid) and why


@dataclass(frozen=True)
class SshOptions:
    """What `run --executor ssh` is given: the devices, their workspace, an ssh config file."""

    devices: tuple[Device, ...]
    workspace: str
    config: Path | None = None


class SshExecutor(Executor):
    """Measurement on SSH devices, everything else here."""

    def __init__(self, workspace: Workspace, options: SshOptions | None):
        if options is None or not options.devices:
            raise UserError("--executor ssh needs at least one --device [user@]host[:port]")
        self.local, self.workspace = LocalExecutor(workspace), workspace
        self._control = Path(tempfile.mkdtemp(prefix="bm-ssh-"))
        self.links = {d.name: Link(d, options.workspace, options.config, self._control)
                      for d in options.devices}
        self.hostnames: dict[str, str] = {}  # device -> the host its records carry
        self.down: dict[str, str] = {}  # device -> why it cannot measure (unreachable, or its probe failed)
        self.failed_on: set[str] = set()  # the devices in `down` that cells were given to
        self._able: dict[str, list[str]] = {}  # cell key -> the devices that can measure it
        self._flights: list[Flight] = []  # running or queued, in order
        self._ended: list[Ended] = []
        try:
            for name, link in self.links.items():
                self._hello(name, link)
        except BaseException:
            self.close()
            raise

    def _hello(self, name: str, link: Link) -> None:
        """Log in to the device and compare versions: a UserError when it cannot serve; unreachable noted."""
        try:
            self.hostnames[name] = link.hello()["host"]
        except Unreachable as exc:
            self.down[name] = f"device {name} is unreachable: {exc}"

    def decide(self, plan: Plan, cells: list[CellPlan]) -> list[CellPlan]:
        """Probe every reachable device; a cell runs on the devices that can run it (else on one that cannot
        measure, unreachable or its probe failed, where it fails), or is skipped with each device's
        reason."""
        probed = {name: self._probe(name, plan, cells) for name in self.hostnames}
        states = {name: found for name, found in probed.items() if found is not None}
        decided = []
        for p in cells:
            if p.state not in ("run", "skip"):
                decided.append(p)
                continue
            judged = {name: found[p.cell] for name, found in states.items()}
            able = [name for name, (state, _) in judged.items() if state == "run"] or list(self.down)
            self._able[p.cell.key] = able
            decided.append(replace(p, state="run", reason=None, judged_on=self._judge(able)) if able else
                           replace(p, state="skip", reason=_reasons(judged), judged_on=self._judge(judged)))
        return decided

    def _judge(self, devices: Iterable[str]) -> str | None:
        """The host a cell's records not measured there are stored under: the first of its devices' hosts."""
        first = min(devices, default=None)
        return None if first is None else self.hostnames.get(first, first)

    def _probe(self, name: str, plan: Plan, cells: list[CellPlan]) -> dict[Any, Judged] | None:
        """The device's judgement (state, reason) of each cell, from the probe job run there; None when the
        probe failed (the device is noted as one that cannot measure)."""
        matrix = plan.matrix
        keys = tuple(sorted({verdict_key(matrix, p.cell) for p in cells}))
        training = tuple(sorted({k for p in cells if (k := training_key(matrix, p.cell))}))
        job = ProbeJob(self.workspace, tuple(sorted({k[0] for k in keys})), keys, training, measure_only=True)
        flight = Flight(Work(job, Limits(self.workspace.log("probe"), PROBE_TIMEOUT_S)), self.links[name],
                        self.hostnames[name], lambda _: None)
        ended = flight.wait()
        if not ended.ok:
            self.down[name] = f"device {name} cannot measure: probing it failed: {ended.error}"
            return None
        expansion = judge(matrix, [p.cell for p in cells], 0, ended.result.verdicts, ended.result.trainers)
        return {q.cell: (q.state, q.reason) for q in expansion.cells}

    def hosts(self) -> set[str]:
        return set(self.hostnames.values()) | set(self.down) or {environment.host_name()}

    def submit(self, work: Work, on_phase: Phase, tick: Tick) -> None:
        job = work.job
        cell = job.placed()
        if not job.timed:
            ended = self.local.run(work, on_phase, tick)
            self._ended.append(replace(ended, where=self._placement(cell.key) if cell else None))
            return
        device = work.on or self._placement(cell.key)
        if device in self.down:
            self._ended.append(self._failed(work, device, self.down[device]))
            return
        self._flights.append(Flight(work, self.links[device], self.hostnames[device], on_phase))
        self._start_next(device)

    def _placement(self, key: str) -> str:
        """The device to measure a cell on: of those that can, the one with the fewest models waiting or
        measuring."""
        able = self._able.get(key) or list(self.links)
        given = Counter(f.link.device.name for f in self._flights)
        return min(able, key=lambda name: given[name])

    def _start_next(self, device: str) -> None:
        """Start the device's first waiting rounds job, unless one runs there."""
        mine = [f for f in self._flights if f.link.device.name == device]
        if mine and not any(f.running for f in mine):
            mine[0].start()

    def ended(self, wait: bool) -> Iterator[Ended]:
        while self._flights or self._ended:
            for flight in list(self._flights):
                if flight.running and (ended := flight.poll()) is not None:
                    self._flights.remove(flight)
                    self._ended.append(ended)
                    self._start_next(flight.link.device.name)
            while self._ended:
                yield self._ended.pop(0)
            if self._flights:
                self._read(wait)
            if not wait:
                return

    def _read(self, wait: bool) -> None:
        """Read what the running jobs wrote (phases, their ends): waiting until one does, or (not `wait`)
        what is there now."""
        with selectors.DefaultSelector() as selector:
            for flight in self._flights:
                if flight.waiting:
                    selector.register(flight, selectors.EVENT_READ)
            if selector.get_map():
                for key, _ in selector.select(None if wait else 0):
                    key.fileobj.read()

    def lost(self) -> dict[str, str]:
        return {device: self.down[device] for device in sorted(self.failed_on)}

    def _failed(self, work: Work, device: str, reason: str) -> Ended:
        self.failed_on.add(device)
        env = {**environment.capture(), "host": self.hostnames.get(device, device)}
        return Ended(work, (work.job,), (), reason, env=env, where=device)

    def close(self) -> None:
        for flight in self._flights:
            flight.stop()
        self._flights.clear()
        for link in self.links.values():
            link.close()
        shutil.rmtree(self._control, ignore_errors=True)


def _reasons(judged: dict[str, Judged]) -> str:
    """Why no device can run a cell: each distinct reason, after the devices it concerns."""
    by_reason: dict[str, list[str]] = {}
    for name, (_, reason) in judged.items():
        by_reason.setdefault(reason or "not valid there", []).append(name)
    return "; ".join(f"{', '.join(sorted(names))}: {reason}" for reason, names in by_reason.items())
