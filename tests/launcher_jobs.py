"""Job functions for the launcher tests, run in a child process through `module:function` modes."""

from __future__ import annotations

import os
import sys
import time

from bench_matrix.worker import phase


def abort(job):
    print("about to abort", flush=True)
    sys.stdout.flush()
    os.abort()


def fail(job):
    raise ValueError("bad model")


def sleep(job):
    phase("measure")
    time.sleep(job["seconds"])


def echo(job):
    phase("convert")
    phase("measure")
    return job["value"]
