"""How a job tells the process that started it which phase it is in: one line per phase on the pipe that
$BENCH_MATRIX_PHASE_FD names (written by jobs, read by the local executor's process protocol)."""

from __future__ import annotations

import os
import time

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


class Epochs:
    """Training's progress as phases: after each epoch, its number, the loss and about how long is left."""

    def __init__(self, total: int, what: str = "train"):
        self.total, self.what, self.begin = total, what, time.monotonic()

    def ended(self, done: int, loss: float) -> None:
        """Epoch `done` (1-based) ended with mean loss `loss`."""
        left = (time.monotonic() - self.begin) / done * (self.total - done)
        phase(f"{self.what} · epoch {done}/{self.total} · loss {loss:.4g} · about {left:.0f} s left")


def waiting(message: str) -> None:
    """Tell the parent we wait for the timing lock (`timing_slot`'s on_wait): its time limit stops counting
    until the next `phase()`, which the job sends once it holds the slot."""
    phase(WAITING_MARK + message)
