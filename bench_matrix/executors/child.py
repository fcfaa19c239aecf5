"""The child side of the local executor's process protocol: `python -m bench_matrix.executors.child JOB.pickle
RESULT.json` runs one job and writes its result as JSON (its phases reach the parent through phases.py)."""

from __future__ import annotations

import atexit
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
from bench_matrix.named import resolve

def die_with_parent() -> None:
    """Ask Linux to kill this process when the parent dies, so a killed run leaves nothing measuring."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() == 1:  # the parent is already gone
        os._exit(1)


def main(argv: list[str]) -> int:
    die_with_parent()
    job = pickle.loads(Path(argv[0]).read_bytes())  # written by our own parent process, never user input
    result_path = Path(argv[1])
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    try:
        result = {"ok": True, "value": to_json(resolve(type(job).function)(job))}
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
