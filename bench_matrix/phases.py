"""How a job tells the process that started it which phase it is in: one line per phase on the pipe that
$BENCH_MATRIX_PHASE_FD names (written by jobs, read by the local executor's process protocol)."""

from __future__ import annotations

import os

PHASE_FD = "BENCH_MATRIX_PHASE_FD"  # names the pipe the child writes its phase lines to
WAITING_MARK = "waiting:"  # a phase line starting with it: the job waits for the machine's timing lock


def phase(name: str) -> None:
    """Tell the parent which phase began (it stays silent while we measure); one line per phase."""
    fd = os.environ.get(PHASE_FD)
    if fd:
        try:
            os.write(int(fd), f"{' '.join(name.split())}\n".encode())
        except OSError:
            pass


def waiting(message: str) -> None:
    """Tell the parent we wait for the timing lock (`timing_slot`'s on_wait): its time limit stops counting
    until the next `phase()`, which the job sends once it holds the slot."""
    phase(WAITING_MARK + message)
