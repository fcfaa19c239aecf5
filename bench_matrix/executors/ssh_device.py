"""What an SSH device runs: `python -m bench_matrix.executors.ssh_device WORKSPACE COMMAND`, its answer as
JSON on stdout. `hello`: its versions and environment; `missing KEY...`: the shipped contents it lacks;
`run`: a job on stdin (pickled, with the contents it lacks), run here with the local executor, the typed
result written through the codec. Its stdin stays open while the job runs: when it closes (the run was
interrupted, the connection dropped) the job is stopped as by Ctrl-C, its processes killed."""

from __future__ import annotations

import json
import os
import pickle
import signal
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from bench_matrix import __version__
from bench_matrix.executors.base import Work
from bench_matrix.executors.codec import to_json
from bench_matrix.executors.local import LocalExecutor
from bench_matrix.executors.shipping import extract, named_back, relocate, shipped_folder
from bench_matrix.executors.ssh_link import PHASE
from bench_matrix.measure import env as environment
from bench_matrix.workspace import Workspace

STOP_GRACE_S = 60  # after its stdin closed, the job has this long to clean up before the process exits


def hello() -> dict[str, Any]:
    """This device's Python, bench-matrix and environment."""
    return {"python": sys.version.split()[0], "bench_matrix": __version__, "host": environment.host_name(),
            "env": environment.capture()}


def missing(ws: Workspace, keys: list[str]) -> list[str]:
    """The shipped contents (by key) this device does not hold yet."""
    return [key for key in keys if not shipped_folder(ws, key).is_dir()]


def run(ws: Workspace, request: dict[str, Any]) -> dict[str, Any]:
    """Unpack what was shipped, run the job here with its paths moved into this workspace; how it ended, its
    result naming the sender's paths again."""
    ws.sweep()  # what a killed run left here
    for key, data in request["payloads"].items():
        extract(data, shipped_folder(ws, key), ws)
    moved = {path: str(shipped_folder(ws, key) / name) for path, (key, name) in request["files"].items()}
    job, limits = relocate(request["job"], moved, ws), request["limits"]
    limits = replace(limits, log=ws.logs / limits.log.name)
    limits.log.parent.mkdir(parents=True, exist_ok=True)
    ended = LocalExecutor(ws).run(Work(job, limits), on_phase=_phase)
    back = {new: old for old, new in moved.items()}
    return {"ok": ended.ok, "value": to_json(relocate(ended.result, back, ws)) if ended.ok else None,
            "error": named_back(ended.error, back), "user_error": ended.user_error, "env": ended.env}


def _phase(text: str) -> None:
    print(f"{PHASE}{text}", file=sys.stderr, flush=True)


def _stop_when_closed(fd: int) -> None:
    """Watch stdin (its file descriptor: no buffer's lock held at exit): once it closes, interrupt the main
    thread (which kills the job's processes), and exit if that has not ended it within the grace."""
    def watch() -> None:
        while os.read(fd, 1 << 16):
            pass
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
        time.sleep(STOP_GRACE_S)
        os._exit(130)

    threading.Thread(target=watch, daemon=True).start()


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def main(argv: list[str]) -> int:
    ws, command = Workspace(Path(argv[0]).expanduser()), argv[1]
    answer = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())  # anything else printed goes to stderr
    for signum in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _interrupt)
    if command == "hello":
        result: Any = hello()
    elif command == "missing":
        result = missing(ws, argv[2:])
    else:
        request = pickle.load(sys.stdin.buffer)
        _stop_when_closed(sys.stdin.fileno())
        try:
            result = run(ws, request)
        except KeyboardInterrupt:
            return 130
    json.dump(result, answer)
    answer.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
