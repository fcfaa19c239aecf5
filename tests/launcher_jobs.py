"""Typed jobs for the process tests, each run in a child process by the `module:function` its class names."""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass
from typing import Any, ClassVar

from bench_matrix.phases import phase


@dataclass(frozen=True)
class AbortJob:
    function: ClassVar[str] = "launcher_jobs:abort"
    result: ClassVar[Any] = Any


@dataclass(frozen=True)
class FailJob:
    function: ClassVar[str] = "launcher_jobs:fail"
    result: ClassVar[Any] = Any


@dataclass(frozen=True)
class SleepJob:
    seconds: float
    function: ClassVar[str] = "launcher_jobs:sleep"
    result: ClassVar[Any] = Any


@dataclass(frozen=True)
class EchoJob:
    value: Any
    function: ClassVar[str] = "launcher_jobs:echo"
    result: ClassVar[Any] = Any


@dataclass(frozen=True)
class EnvJob:
    names: tuple[str, ...]
    function: ClassVar[str] = "launcher_jobs:env"
    result: ClassVar[Any] = Any


def env(job: EnvJob):
    return {name: os.environ.get(name) for name in job.names}


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
