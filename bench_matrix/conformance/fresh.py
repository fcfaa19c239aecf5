"""Load artifacts in a fresh process, as a cell's measure process does, and report each session's info()
and, on the CPU, how often more threads ran than asked while it executed: some runtimes (TensorFlow) set their
thread pools once per process, so only a fresh one shows whether `threads` is honoured. Run as
`python -m bench_matrix.conformance.fresh` with the jobs as JSON on stdin."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.executors.process import THREAD_VARIABLES


def infos(jobs: list[dict[str, Any]], threads: int, cwd: Path) -> dict[str, dict[str, Any]]:
    """Each job's {"info": ...} or {"error": ...} from one fresh process whose environment sets every thread
    variable to `threads`, as the runner's does."""
    env = {**os.environ, **{name: str(threads) for name in THREAD_VARIABLES}}
    done = subprocess.run([sys.executable, "-m", __name__], input=json.dumps(jobs), capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"the fresh process failed (exit {done.returncode}): {done.stderr[-2000:]}")
    return json.loads(done.stdout.splitlines()[-1])


def _info(job: dict[str, Any]) -> dict[str, Any]:
    """The job's session's info() and, given inputs (an .npz), its share of oversubscribed samples."""
    from bench_matrix.conformance.concurrency import oversubscribed
    from bench_matrix.registry import load_backend

    try:
        session = load_backend(job["backend"]).load(Path(job["artifact"]), job["meta"], job["target"],
                                                    job["precision"], job["threads"])
        found: dict[str, Any] = {"info": session.info()}
        if job.get("inputs"):
            with np.load(job["inputs"]) as stored:
                prepared = session.prepare(dict(stored))
            session.fetch(session.execute(prepared))  # warm-up
            found["oversubscribed"] = oversubscribed(lambda: session.fetch(session.execute(prepared)),
                                                     job["threads"])
        return found
    except Exception as exc:  # reported against the job's case, not raised
        return {"error": f"{type(exc).__name__}: {exc}"}


def main() -> None:
    jobs = json.load(sys.stdin)
    print(json.dumps({job["case"]: _info(job) for job in jobs}, default=str))


if __name__ == "__main__":
    main()
