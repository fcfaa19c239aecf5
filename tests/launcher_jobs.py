"""Typed jobs for the launcher tests, run in a child process through their `module:function` modes."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Any, ClassVar

from bench_matrix.worker import phase


@dataclass(frozen=True)
class AbortJob:
    mode: ClassVar[str] = "launcher_jobs:abort"


@dataclass(frozen=True)
class FailJob:
    mode: ClassVar[str] = "launcher_jobs:fail"


@dataclass(frozen=True)
class SleepJob:
    seconds: float
    mode: ClassVar[str] = "launcher_jobs:sleep"


@dataclass(frozen=True)
class EchoJob:
    value: Any
    mode: ClassVar[str] = "launcher_jobs:echo"


def abort(job: AbortJob):
    print("about to abort", flush=True)
    sys.stdout.flush()
    os.abort()


def fail(job: FailJob):
    raise ValueError("bad model")


def sleep(job: SleepJob):
    phase("measure")
    time.sleep(job.seconds)


def echo(job: EchoJob):
    phase("convert")
    phase("measure")
    return job.value
