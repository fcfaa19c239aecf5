"""Real processes contending for the machine's timing slot: a launcher job that waits for it, and a script
(`python lock_helpers.py HOLDER SECONDS`, or `until-told` instead of SECONDS: until its stdin ends) that holds
it, printing `held` once it has it and then a JSON line with its window and the waiting messages it got."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from bench_matrix.measure.machine_lock import timing_slot
from bench_matrix.phases import phase, waiting


@dataclass(frozen=True)
class SlotJob:
    """Load, then hold the timing slot for `hold_s` seconds, reporting the wait to the launcher."""

    hold_s: float
    function: ClassVar[str] = "lock_helpers:hold_slot"
    result: ClassVar[type] = dict


def hold_slot(job: SlotJob) -> dict:
    phase("load")
    with timing_slot("lock job", on_wait=waiting) as window:
        phase("measure")
        time.sleep(job.hold_s)
    return window.as_dict()


UNTIL_TOLD = "until-told"


def main(holder: str, hold: str) -> None:
    messages: list[str] = []
    with timing_slot(holder, on_wait=messages.append) as window:
        print("held", flush=True)
        if hold == UNTIL_TOLD:
            sys.stdin.read()
        else:
            time.sleep(float(hold))
    print(json.dumps({"window": window.as_dict(), "messages": messages}), flush=True)


def start_holder(holder: str, seconds: float | None = None, env: dict[str, str] | None = None
                 ) -> subprocess.Popen:
    """This script holding the slot for `seconds` (None: until `release`); returns once it holds it."""
    hold = UNTIL_TOLD if seconds is None else str(seconds)
    proc = subprocess.Popen([sys.executable, __file__, holder, hold], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def release(proc: subprocess.Popen, after_s: float = 0.0) -> None:
    """Let a holder started until told go: now, or `after_s` seconds from now (from a timer thread)."""
    if after_s:
        timer = threading.Timer(after_s, release, (proc,))
        timer.daemon = True
        timer.start()
    elif proc.stdin is not None and not proc.stdin.closed:
        proc.stdin.close()


def flock_waiters(path: Path) -> int:
    """How many processes are blocked waiting for a `flock` on `path` (/proc/locks marks them `->`)."""
    info = path.stat()
    ident = f"{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}:{info.st_ino}"
    with open("/proc/locks") as locks:
        rows = [line.split() for line in locks]
    return sum(1 for row in rows if len(row) > 2 and row[1] == "->" and row[-3] == ident)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
