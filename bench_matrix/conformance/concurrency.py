"""How many of a process's threads run at once while a session executes: the runtime's own threads, counted by
the operating system, whatever info() says (Linux: /proc/self/task)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

TASKS = Path("/proc/self/task")
SAMPLE_S, SAMPLING_S = 0.001, 0.2  # how often the threads are looked at, and for how long
# Before sampling, until this many looks in a row find no other thread running (at most SETTLE_S): threads of
# sessions run before (ONNX Runtime's pool spins for a while after its work, longer on a busy machine)
# must not count against this one.
QUIET_LOOKS, SETTLE_S = 20, 2.0


def _running(own: str) -> int:
    """The threads of this process (but `own`) running or waiting for a core (state R)."""
    found = 0
    for task in TASKS.iterdir():
        if task.name == own:
            continue
        try:
            stat = (task / "stat").read_text()
        except (FileNotFoundError, ProcessLookupError):
            continue
        found += stat.rsplit(")", 1)[1].split()[0] == "R"
    return found


def settle() -> None:
    """Wait until no other thread of this process runs for QUIET_LOOKS looks in a row, or SETTLE_S passed."""
    own, quiet, end = str(threading.get_native_id()), 0, time.perf_counter() + SETTLE_S
    while quiet < QUIET_LOOKS and time.perf_counter() < end:
        quiet = quiet + 1 if _running(own) == 0 else 0
        time.sleep(SAMPLE_S)


def oversubscribed(run: Callable[[], object], threads: int) -> float | None:
    """The share of samples in which more than `threads` threads ran while `run` was called again and again
    (SAMPLING_S), or None where the system does not tell."""
    if not TASKS.is_dir():
        return None
    settle()
    counts: list[int] = []
    stop = threading.Event()

    def sample() -> None:
        own = str(threading.get_native_id())
        while not stop.is_set():
            counts.append(_running(own))
            time.sleep(SAMPLE_S)

    monitor = threading.Thread(target=sample, daemon=True)
    monitor.start()
    end = time.perf_counter() + SAMPLING_S
    try:
        while time.perf_counter() < end:
            run()
    finally:
        stop.set()
        monitor.join()
    return sum(count > threads for count in counts) / len(counts) if counts else None
