"""The parent side of a served session (child.py --serve): a cell's artifact loaded once in its own process,
then timed windows on demand and a finish; every wait is bounded, and a crash, hang or error ends only this
cell (SessionLost, with the reason and the log's tail)."""

from __future__ import annotations

import json
import os
import pickle
import socket
import subprocess
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.executors.child import SESSION_FD
from bench_matrix.executors.codec import from_json
from bench_matrix.executors.process import describe_exit, error_reason, kill_group, last_line, start_child
from bench_matrix.jobs import MeasureJob
from bench_matrix.jobs.results import Measured
from bench_matrix.measure.schedule import SessionLost, Window

WINDOW_LIMIT_S = 120.0  # a window that has not come back by then (plus 20 × its length) hangs


class SessionProcess:
    """A measure job's session in its own process, started; `ready` waits for its load, `window` and `finish`
    talk to it, `close` ends it (`kill` at once)."""

    def __init__(self, job: MeasureJob, workdir: Path, log: Path, timeout_s: float):
        self.job, self.log, self.timeout_s = job, log, timeout_s
        self.user_error = False
        workdir.mkdir(parents=True, exist_ok=True)
        log.parent.mkdir(parents=True, exist_ok=True)
        self._path = workdir / f"session-{os.getpid()}-{time.monotonic_ns()}.pickle"
        self._path.write_bytes(pickle.dumps(job))
        ours, theirs = socket.socketpair()
        self._conn = Connection(ours.detach())
        self.proc: subprocess.Popen = start_child(job, ["--serve", str(self._path)], log,
                                                  job.settings.threads, {SESSION_FD: str(theirs.fileno())},
                                                  (theirs.fileno(),))
        theirs.close()
        self.kinds: tuple[str, ...] = ()
        self.rss_mb = 0.0

    def ready(self) -> None:
        """Wait until the session is loaded and warmed up (its kinds of window, its memory); SessionLost, the
        process ended, when it fails."""
        try:
            ready = self._receive(self.timeout_s, "loading")
        except SessionLost:
            self.close()
            raise
        self.kinds, self.rss_mb = tuple(ready["kinds"]), float(ready["rss_mb"])

    def window(self, kind: str) -> Window:
        seconds = self.job.settings.window_s
        self._send({"do": "window", "kind": kind, "seconds": seconds})
        head = self._receive(WINDOW_LIMIT_S + 20 * seconds, f"a {kind} window")
        durations = np.frombuffer(self._raw(WINDOW_LIMIT_S, f"a {kind} window"), dtype="<f8")
        return Window(kind, durations, head["samples"], head["disturbed"], head["interference"])

    def evaluate(self) -> dict[str, Any]:
        """Evaluate the session before its rounds: its record's fields besides the timed ones; SessionLost on
        failure."""
        self._send({"do": "evaluate"})
        return self._receive(self.timeout_s, "evaluating")["fields"]

    def finish(self) -> Measured:
        """Finish the session: its record's fields and its scenarios run (within the cell's time limit);
        SessionLost on failure."""
        self._send({"do": "finish"})
        return from_json(Measured, self._receive(self.timeout_s, "finishing")["value"])

    def kill(self) -> None:
        kill_group(self.proc)
        self.close()

    def close(self) -> None:
        """End the process (at once when it has not ended by itself) and remove its job file."""
        self._conn.close()
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            kill_group(self.proc)
        self._path.unlink(missing_ok=True)

    def _send(self, message: dict[str, Any]) -> None:
        try:
            self._conn.send_bytes(json.dumps(message).encode())
        except OSError:
            raise self._lost("waiting for a command") from None

    def _receive(self, timeout_s: float, doing: str) -> dict[str, Any]:
        message = json.loads(self._raw(timeout_s, doing))
        if not message["ok"]:
            self.user_error = bool(message.get("user_error"))
            text = message["error"] if self.user_error else error_reason(message["error"],
                                                                         message.get("traceback", ""), self.log)
            raise SessionLost(text)
        return message

    def _raw(self, timeout_s: float, doing: str) -> bytes:
        """The next message's bytes; SessionLost when the process ends or does not answer in time."""
        try:
            if self._conn.poll(timeout_s):
                return self._conn.recv_bytes()
        except (EOFError, OSError):
            raise self._lost(doing) from None
        kill_group(self.proc)
        raise SessionLost(f"timed out after {timeout_s:g} s {doing}; raise settings.timeout_s if this cell "
                          f"needs longer. Log: {self.log}")

    def _lost(self, doing: str) -> SessionLost:
        try:
            code = self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            kill_group(self.proc)
            code = self.proc.returncode
        return SessionLost(f"the process died ({describe_exit(code)}) {doing}; the last line of {self.log}: "
                           f"{last_line(self.log)}")
