"""The child side of the local executor's process protocol: `python -m bench_matrix.executors.child JOB.pickle
RESULT.json` runs one job and writes its result as JSON (its phases reach the parent through phases.py);
`... child --serve JOB.pickle` keeps a measure job's session and answers the parent's commands on the
connection $BENCH_MATRIX_SESSION_FD names (sessions.py is the other side)."""

from __future__ import annotations

import atexit
import json
import os
import pickle
import resource
import signal
import sys
import traceback
import warnings
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from bench_matrix.errors import UserError
from bench_matrix.executors.codec import to_json
from bench_matrix.named import resolve

SESSION_FD = "BENCH_MATRIX_SESSION_FD"  # names the connection a served session talks to its parent on


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
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    if argv[0] == "--serve":
        return serve(_job(argv[1]), Connection(int(os.environ[SESSION_FD])))
    job = _job(argv[0])
    result_path = Path(argv[1])
    try:
        result = {"ok": True, "value": to_json(resolve(type(job).function)(job))}
        code = 0
    except Exception as exc:  # everything a job raises is reported to the parent as the cell's reason
        result, code = _failure(exc), 1
    tmp = result_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, default=str))
    os.replace(tmp, result_path)
    return code


def serve(job: Any, parent: Connection) -> int:
    """Open the job's session, say it is ready (its kinds of window and resident memory), then evaluate it and
    time windows until told to finish; the result or the failure is the last message."""
    try:
        served = resolve(type(job).function)(job)
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        _send(parent, {"ok": True, "kinds": list(served.kinds), "rss_mb": rss_mb})
        while (command := json.loads(parent.recv_bytes()))["do"] != "finish":
            if command["do"] == "evaluate":
                _send(parent, {"ok": True, "fields": served.evaluate()})
                continue
            window = served.window(command["kind"], command["seconds"])
            _send(parent, {"ok": True, "samples": window.samples, "disturbed": window.disturbed,
                           "interference": window.interference})
            parent.send_bytes(window.durations_ms.astype("<f8").tobytes())
        _send(parent, {"ok": True, "value": to_json(served.finish())})
        return 0
    except EOFError:  # the parent is gone or gave up on us
        return 1
    except Exception as exc:
        _send(parent, _failure(exc))
        return 1


def _job(path: str) -> Any:
    return pickle.loads(Path(path).read_bytes())  # written by our own parent process, never user input


def _failure(exc: Exception) -> dict[str, Any]:
    """The failure as the parent reads it; the traceback goes to the log (stderr) too."""
    traceback.print_exc()
    return {"ok": False, "user_error": isinstance(exc, UserError),
            "error": f"{type(exc).__name__}: {exc}" if not isinstance(exc, UserError) else str(exc),
            "traceback": traceback.format_exc()}


def _send(parent: Connection, message: dict[str, Any]) -> None:
    parent.send_bytes(json.dumps(message, default=str).encode())


def exit_now(code: int) -> None:
    """End the process once its result is written: exit handlers run (they remove private caches), the
    interpreter's teardown of TensorFlow's or torch's modules does not (0.4-0.7 s per process)."""
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    exit_now(main(sys.argv[1:]))
