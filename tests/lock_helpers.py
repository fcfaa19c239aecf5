"""Real processes contending for the machine's timing slot: a launcher job that waits for it, and a script
(`python lock_helpers.py HOLDER SECONDS`) that holds it, printing `held` once it has it and then a JSON line
with its window and the waiting messages it got."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from typing import ClassVar

from bench_matrix.measure.machine_lock import timing_slot
from bench_matrix.worker import phase, waiting


@dataclass(frozen=True)
class SlotJob:
    """Load, then hold the timing slot for `hold_s` seconds, reporting the wait to the launcher."""

    hold_s: float
    mode: ClassVar[str] = "lock_helpers:hold_slot"


def hold_slot(job: SlotJob) -> dict:
    phase("load")
    with timing_slot("lock job", on_wait=waiting) as window:
        phase("measure")
        time.sleep(job.hold_s)
    return window.as_dict()


def main(holder: str, seconds: float) -> None:
    messages: list[str] = []
    with timing_slot(holder, on_wait=messages.append) as window:
        print("held", flush=True)
        time.sleep(seconds)
    print(json.dumps({"window": window.as_dict(), "messages": messages}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
