"""One job on an SSH device: what it reads shipped (only the contents the device lacks), the job run there by
`ssh_device run`, its phases followed, its typed result read back; a dropped connection retries it once."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from bench_matrix import data
from bench_matrix.executors.base import Ended, Phase, Work
from bench_matrix.executors.codec import from_json
from bench_matrix.executors.shipping import pack
from bench_matrix.executors.ssh_link import PHASE, Link, Unreachable
from bench_matrix.jobs import Job
from bench_matrix.jobs.results import MeasuredGroup
from bench_matrix.matrix.spec import file_kind
from bench_matrix.measure import env as environment
from bench_matrix.sources.onnx_file import external_data_files

ATTEMPTS = 2  # a job whose connection dropped runs once more
STOP_WAIT_S = 15  # how long a stopped job's ssh gets to end before it is killed


def shipped_paths(job: Job) -> tuple[Path, ...]:
    """What the device must hold to run the job (`Job.ships`) that is here."""
    return tuple(p for p in job.ships() if p.exists())


class Flight:
    """A job on a device: started, its stderr read as it comes (phases; its end), stopped on the way out."""

    def __init__(self, work: Work, link: Link, host: str, on_phase: Phase):
        self.work, self.link, self.host, self.on_phase = work, link, host, on_phase
        self.attempt = 0
        self.lost: str | None = None  # why the connection dropped, when it did
        self.failure: str | None = None  # why shipping failed on the device itself
        self.proc: subprocess.Popen | None = None
        self.stderr = bytearray()  # what the job's ssh wrote to stderr so far
        self.relayed = 0  # how much of it was read as whole lines (phases passed on)
        self.closed = False  # its stderr reached its end: ssh has ended
        self.facts: dict[str, Any] = {}

    @property
    def running(self) -> bool:
        return self.attempt > 0

    @property
    def name(self) -> str:
        return self.link.device.name

    def start(self) -> None:
        """Ship what the device lacks and start the job there (a dropped connection: noted in `lost`)."""
        self.attempt, self.lost, self.closed = self.attempt + 1, None, False
        self.stderr, self.relayed = bytearray(), 0
        self.out = tempfile.TemporaryFile()
        begin = time.time()
        try:
            request = self._request()
        except Unreachable as exc:
            self.lost = str(exc)
            return
        except RuntimeError as exc:
            self.failure = str(exc)
            return
        if self.facts["shipped_files"]:
            self.on_phase(f"{self.name}: shipping {self.facts['shipped_files']} files "
                          f"({self.facts['shipped_bytes'] / 2**20:.1f} MiB)")
        self.proc = self.link.start(self.out)
        try:
            pickle.dump(request, self.proc.stdin)
            self.proc.stdin.flush()  # kept open: closing it stops the job on the device
        except BrokenPipeError:
            pass  # ssh ended: its stderr says why
        self.begin = time.time()
        self.facts["ship_s"] = round(self.begin - begin, 3)

    def _request(self) -> dict[str, Any]:
        """The job, and each file it needs: its content key and name, and the content the device lacks."""
        job = self.work.job
        datasets = job.datasets()
        packed = {str(p): pack(p, _beside(p), data.measured if p in datasets else lambda name: True)
                  for p in shipped_paths(job)}
        keys = sorted({key for key, _ in packed.values()})
        lacking = set(self.link.call("missing", *keys)) if keys else set()
        payloads = {key: data for key, data in packed.values() if key in lacking}
        self.facts.update({"attempt": self.attempt, "shipped_files": len(payloads),
                           "shipped_bytes": sum(len(data) for data in payloads.values()),
                           "reused_files": len(keys) - len(payloads)})
        return {"job": job, "limits": self.work.limits, "payloads": payloads,
                "files": {path: (key, Path(path).name) for path, (key, _) in packed.items()}}

    @property
    def waiting(self) -> bool:
        """Whether the job runs on the device: its end is known by reading its stderr (`read`)."""
        return self.running and self.lost is None and self.failure is None and not self.closed

    def fileno(self) -> int:
        return self.proc.stderr.fileno()

    def read(self) -> None:
        """Read what the job's ssh wrote to stderr (blocks until it writes or ends), passing its phases on."""
        data = os.read(self.fileno(), 65536)
        if not data:
            self.proc.stderr.close()
            self.proc.wait()
            self.closed = True
            return
        self.stderr += data
        complete = self.stderr.rfind(b"\n") + 1
        for line in bytes(self.stderr[self.relayed:complete]).decode(errors="replace").splitlines():
            if line.startswith(PHASE):
                self.on_phase(f"{self.name}: {line[len(PHASE):]}")
        self.relayed = max(self.relayed, complete)

    def poll(self) -> Ended | None:
        """How the job ended, or None while it runs (or runs again after its connection dropped)."""
        if self.failure is not None:
            return self._failed(self.failure)
        if self.lost is None:
            if not self.closed:
                return None
            ended = self._answer()
            if ended is not None:
                return ended
        if self.attempt < ATTEMPTS:
            self.start()
            return None
        return self._failed(f"the connection to device {self.name} dropped ({self.attempt} attempts); "
                            f"last: {self.lost}")

    def wait(self) -> Ended:
        """Run the job to its end."""
        self.start()
        try:
            while (ended := self.poll()) is None:
                if self.waiting:
                    self.read()
        finally:
            self.stop()
        return ended

    def _answer(self) -> Ended | None:
        """The ended job's typed result or error; None when the connection dropped (noted in `lost`)."""
        stderr = self.stderr.decode(errors="replace")
        if self.proc.returncode != 0:
            failure = self.link.failure(self.proc.returncode, stderr)
            if isinstance(failure, Unreachable):
                self.lost = str(failure)
                return None
            return self._failed(str(failure))
        self.out.seek(0)
        answer, job = json.loads(self.out.read()), self.work.job
        if not answer["ok"]:
            return Ended(self.work, (job,), (), f"on device {self.name}: {answer['error']}",
                         answer["user_error"], answer["env"], self.name)
        self.facts["job_s"] = round(time.time() - self.begin, 3)
        return Ended(self.work, (job,), (self._placed(from_json(type(job).result, answer["value"])),),
                     where=self.name)

    def _placed(self, result: Any) -> Any:
        """A rounds job's result with where and how each cell was measured (`env.ssh`)."""
        if not isinstance(result, MeasuredGroup):
            return result
        facts = {"device": self.name, **self.facts}
        return replace(result, cells=tuple(
            replace(c, measured=replace(c.measured, env={**c.measured.env, "ssh": facts}))
            if c.measured else c for c in result.cells))

    def _failed(self, reason: str) -> Ended:
        env = {**environment.capture(), "host": self.host}
        return Ended(self.work, (self.work.job,), (), reason, env=env, where=self.name)

    def stop(self) -> None:
        """Stop the job: its stdin closed (the device kills its processes), then ssh itself if need be."""
        if self.proc is None:
            return
        try:
            self.proc.stdin.close()
        except BrokenPipeError:
            pass
        try:
            self.proc.wait(STOP_WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stderr.close()


def _beside(path: Path) -> list[Path]:
    """The files an ONNX model file reads beside it (its external data)."""
    return external_data_files(path) if path.is_file() and file_kind(path) == ("onnx", "onnx") else []
