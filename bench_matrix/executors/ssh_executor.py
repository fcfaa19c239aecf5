"""The SSH executor: every job but measuring runs here (the local executor); each model's rounds job runs on
an SSH device that can run its cells, with what it reads shipped there once by content, one rounds job per
device at a time. Devices are checked (login, versions) when it opens and probed before the run (`probes`)."""

from __future__ import annotations

import selectors
import shutil
import tempfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

from bench_matrix.cell import CellPlan
from bench_matrix.errors import UserError
from bench_matrix.executors.base import Ended, Executor, Limits, Phase, Tick, Work
from bench_matrix.executors.local import PROBE_TIMEOUT_S, LocalExecutor
from bench_matrix.executors.ssh_flight import Flight
from bench_matrix.executors.ssh_link import Device, Link, Unreachable
from bench_matrix.matrix.spec import Matrix
from bench_matrix.measure import env as environment
from bench_matrix.placement import Probed
from bench_matrix.plan import probe_job
from bench_matrix.workspace import Workspace


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
        self.able: dict[str, list[str]] = {}  # cell key -> the devices that can measure it
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

    def probes(self, matrix: Matrix, cells: list[CellPlan]) -> dict[str, Probed]:
        """Probe every reachable device; those that cannot measure (unreachable, probe failed) come first."""
        job = replace(probe_job(matrix, [p.cell for p in cells], self.workspace), measure_only=True)
        limits = Limits(self.workspace.log("probe"), PROBE_TIMEOUT_S)
        probed: dict[str, Probed] = {}
        for name, host in self.hostnames.items():
            ended = Flight(Work(job, limits), self.links[name], host, lambda _: None).wait()
            if ended.ok:
                probed[name] = Probed(name, host, ended.result)
            else:
                self.down[name] = f"device {name} cannot measure: probing it failed: {ended.error}"
        down = {name: Probed(name, self.hostnames.get(name, name), failed=why, down=True)
                for name, why in self.down.items()}
        return {**down, **probed}

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
        able = self.able.get(key) or list(self.links)
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
