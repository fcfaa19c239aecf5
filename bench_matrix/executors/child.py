"""The child side of the local executor's process protocol: `python -m bench_matrix.executors.child JOB.pickle
RESULT.json` runs one job and writes its result as JSON; `phase` and `waiting` tell the parent where it is."""

from __future__ import annotations

import atexit
import importlib
import json
import os
import pickle
import signal
import sys
import traceback
import warnings
from pathlib import Path

from bench_matrix.errors import UserError
from bench_matrix.executors.codec import to_json

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


def die_with_parent() -> None:
    """Ask Linux to kill this process when the parent dies, so a killed run leaves nothing measuring."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() == 1:  # the parent is already gone
        os._exit(1)


def _function(job: object):
    """The function that runs a job: its class's 'module:function'."""
    module, _, name = type(job).function.partition(":")
    return getattr(importlib.import_module(module), name)


def main(argv: list[str]) -> int:
    die_with_parent()
    job = pickle.loads(Path(argv[0]).read_bytes())  # written by our own parent process, never user input
    result_path = Path(argv[1])
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    try:
        result = {"ok": True, "value": to_json(_function(job)(job))}
        code = 0
    except Exception as exc:  # everything a job raises is reported to the parent as the cell's reason
        traceback.print_exc()
        result = {"ok": False, "user_error": isinstance(exc, UserError),
                  "error": f"{type(exc).__name__}: {exc}" if not isinstance(exc, UserError) else str(exc),
                  "traceback": traceback.format_exc()}
        code = 1
    tmp = result_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, default=str))
    os.replace(tmp, result_path)
    return code


def exit_now(code: int) -> None:
    """End the process once its result is written: exit handlers run (they remove private caches), the
    interpreter's teardown of TensorFlow's or torch's modules does not (0.4-0.7 s per process)."""
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    exit_now(main(sys.argv[1:]))
