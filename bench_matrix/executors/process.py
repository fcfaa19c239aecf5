"""The parent side of the local executor's process protocol: run one job in a child process (child.py) with a
time limit, not counting its waits for the machine's timing lock; no polling while it measures."""

from __future__ import annotations

import json
import os
import pickle
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.errors import UserError
from bench_matrix.phases import PHASE_FD, WAITING_MARK
from bench_matrix.executors.codec import from_json

LONGEST_WAIT_S = 1e9  # ~31 years: a longer (or infinite) limit waits as long; keeps every timer representable
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "TF_NUM_INTRAOP_THREADS")


@dataclass(frozen=True)
class ProcessEnded:
    """How a child ended: its job's typed result, or why it failed (one line; the traceback is in the log)."""

    result: Any = None
    error: str | None = None
    user_error: bool = False

    @property
    def ok(self) -> bool:
        return self.error is None


def run_in_process(job: Any, workdir: Path, log: Path, timeout_s: float, threads: int | None = None,
                   on_phase: Callable[[str], None] = lambda _: None,
                   tick: Callable[[], None] = lambda: None) -> ProcessEnded:
    """Start `python -m bench_matrix.executors.child` on `job` (its class names the function that runs it and
    its result's type); kill its process group at `timeout_s`, not counting waits for the timing lock."""
    if not timeout_s > 0:  # also NaN
        raise UserError(f"a time limit must be a positive number of seconds, got {timeout_s!r} "
                        f"(settings.timeout_s)")
    workdir.mkdir(parents=True, exist_ok=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    stem = f"job-{os.getpid()}-{time.monotonic_ns()}"
    job_path, result_path = workdir / f"{stem}.pickle", workdir / f"{stem}.json"
    job_path.write_bytes(pickle.dumps(job))
    read_fd, write_fd = os.pipe()
    proc = _start(job, job_path, result_path, log, threads, write_fd)
    deadline = _Deadline(min(timeout_s, LONGEST_WAIT_S))
    try:
        timed_out, last_phase = _wait(proc, read_fd, deadline, on_phase, tick)
    except BaseException:  # Ctrl-C or any error in the parent: never leave a child measuring
        kill_group(proc)
        raise
    finally:
        os.close(read_fd)
    try:
        if timed_out:
            waited = (f", not counting {deadline.waited_s:.0f} s waiting for the timing lock"
                      if deadline.waited_s else "")
            return ProcessEnded(error=f"timed out after {timeout_s:g} s (in phase '{last_phase}'{waited}); "
                                      f"raise settings.timeout_s if this cell needs longer. Log: {log}")
        return _ended(job, proc, result_path, log, last_phase)
    finally:
        job_path.unlink(missing_ok=True)
        result_path.unlink(missing_ok=True)


def _start(job: Any, job_path: Path, result_path: Path, log: Path, threads: int | None,
           write_fd: int) -> subprocess.Popen:
    """The child, in its own session, its output appended to the log, its phases written to `write_fd`."""
    proc = start_child(job, [str(job_path), str(result_path)], log, threads, {PHASE_FD: str(write_fd)},
                       (write_fd,))
    os.close(write_fd)
    return proc


def start_child(job: Any, args: list[str], log: Path, threads: int | None, variables: dict[str, str],
                fds: tuple[int, ...]) -> subprocess.Popen:
    """`python -m bench_matrix.executors.child ARGS` in its own session, its output appended to the log, with
    these environment variables and file descriptors."""
    env = {**os.environ, **variables, "PYTHONUNBUFFERED": "1"}
    if threads is not None:
        env.update({name: str(threads) for name in THREAD_VARIABLES})
    else:  # every core (training): waiting OpenMP threads sleep, so one busy core does not stall each step
        env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    with open(log, "ab") as log_file:
        log_file.write(f"\n=== {type(job).function} {time.strftime('%Y-%m-%d %H:%M:%S')} ===\n".encode())
        log_file.flush()
        return subprocess.Popen([sys.executable, "-m", "bench_matrix.executors.child", *args],
                                stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT,
                                pass_fds=fds, env=env, start_new_session=True)


def _ended(job: Any, proc: subprocess.Popen, result_path: Path, log: Path, last_phase: str) -> ProcessEnded:
    """How a child that was not timed out ended: its typed result, its error, or how it died."""
    if result_path.is_file():
        result = json.loads(result_path.read_text())
        if result["ok"]:
            return ProcessEnded(result=from_json(type(job).result, result["value"]))
        if result.get("user_error"):  # the user's mistake: the message alone says what to fix
            return ProcessEnded(error=result["error"], user_error=True)
        return ProcessEnded(error=error_reason(result["error"], result.get("traceback", ""), log))
    return ProcessEnded(error=f"the process died ({describe_exit(proc.returncode)}) in phase '{last_phase}'; "
                              f"the last line of {log}: {last_line(log)}")


class _Deadline:
    """A job's time limit, paused while the job waits for the machine's timing lock (another run's timing)."""

    def __init__(self, limit_s: float):
        self.left_s = limit_s  # as of counting_since
        self.counting_since = time.monotonic()
        self.paused_at: float | None = None
        self.waited_s = 0.0

    def remaining(self) -> float | None:
        """Seconds left; None while paused."""
        return None if self.paused_at is not None else self.left_s - (time.monotonic() - self.counting_since)

    def pause(self) -> None:
        if self.paused_at is None:
            self.paused_at = time.monotonic()
            self.left_s -= self.paused_at - self.counting_since

    def resume(self) -> None:
        if self.paused_at is not None:
            self.counting_since = time.monotonic()
            self.waited_s += self.counting_since - self.paused_at
            self.paused_at = None


def _wait(proc: subprocess.Popen, read_fd: int, deadline: _Deadline, on_phase: Callable[[str], None],
          tick: Callable[[], None]) -> tuple[bool, str]:
    """Block on the child's exit and phase lines; tick once a second except while it measures or waits for the
    timing lock (then another run measures: no timer at all, the child's reminders wake us)."""
    pidfd = os.pidfd_open(proc.pid)
    watched, phase, pending = [pidfd, read_fd], "start", b""
    try:
        while True:
            remaining = deadline.remaining()
            if remaining is not None and remaining <= 0:
                kill_group(proc)
                return True, phase
            wait = remaining if phase == "measure" or remaining is None else min(remaining, 1.0)
            ready, _, _ = select.select(watched, [], [], wait)
            if read_fd in ready:
                chunk = os.read(read_fd, 4096)
                if not chunk:  # no phase can end a wait any more
                    watched.remove(read_fd)
                    deadline.resume()
                *lines, pending = (pending + chunk).split(b"\n")
                for line in lines:
                    phase = _phase(line.decode(errors="replace"), deadline)
                    on_phase(phase)
            if pidfd in ready:
                proc.wait()
                return False, phase
            if not ready:
                tick()
    finally:
        os.close(pidfd)


def _phase(line: str, deadline: _Deadline) -> str:
    """The phase a line names; a waiting line pauses the deadline, any other resumes it."""
    if line.startswith(WAITING_MARK):
        deadline.pause()
        return line[len(WAITING_MARK):]
    deadline.resume()
    return line


def kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def describe_exit(code: int | None) -> str:
    if code is not None and code < 0:
        try:
            return f"killed by signal {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def error_reason(error: str, trace: str, log: Path) -> str:
    """One line: the library the error was raised in (its innermost frame's package), the error's first line,
    and where the traceback is."""
    frames = re.findall(r'File "([^"]+)", line \d+', trace)
    lines = error.strip().splitlines()
    first = lines[0] if lines else "(no message)"
    where = f"{_library(Path(frames[-1]))}: " if frames else ""
    return f"{where}{first} (traceback: {log})"


def _library(path: Path) -> str:
    """The installed package a source file belongs to (torch, onnxruntime, ...), or its module's name."""
    parts = path.parts
    for folder in ("site-packages", "dist-packages"):
        if folder in parts[:-1]:
            return parts[parts.index(folder) + 1].removesuffix(".py")
    if "bench_matrix" in parts:
        return "bench-matrix"
    return f"{path.stem} backend" if "backends" in parts else path.stem


def last_line(log: Path) -> str:
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1] if lines else "(empty)"
