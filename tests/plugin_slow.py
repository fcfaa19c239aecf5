"""A third-party backend for the real-time closed-loop and the compare tests: ONNX Runtime with a fixed delay
added to every inference, an artificially slowed brain (as a slow target would be) or a planted regression,
and for the interrupted-run tests a gate that holds every session after a run's first cell's; installed as a
.dist-info with an entry point, like tests/plugin_npu.py."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.plugin import Session
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend

# from about 0.2 s on, the late commands visibly worsen the driving (docs/closed-loop.md); $SLOW_ORT_DELAY_MS
# sets another delay (0: none)
DELAY_S = float(os.environ.get("SLOW_ORT_DELAY_MS", "250")) / 1e3
# a directory: the first cell's sessions load at once, each later one writes GATE/waiting-PID and waits for
# GATE/open; $SLOW_ORT_GATE_PASSING: how many pass at once (the processes of a cell)
GATE = os.environ.get("SLOW_ORT_GATE")
PASSING = int(os.environ.get("SLOW_ORT_GATE_PASSING", "2"))


class SlowOrtBackend(OnnxRuntimeBackend):
    """ONNX Runtime's conversion and session, every execute DELAY_S slower."""

    name = "slow_ort"
    description = "test plugin: ONNX Runtime plus a fixed delay per inference"
    baseline_for = ()

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        if GATE:
            _pass(Path(GATE))
        return SlowSession(super().load(artifact_dir, meta, target, precision, threads))


def _pass(gate: Path) -> None:
    """Through the gate: at once for the first PASSING sessions that come (a cell's processes: 2 by default),
    once GATE/open exists for the others."""
    for number in range(PASSING):
        try:
            os.close(os.open(gate / f"passed-{number}", os.O_CREAT | os.O_EXCL))
            return
        except FileExistsError:
            continue
    (gate / f"waiting-{os.getpid()}").touch()
    deadline = time.monotonic() + 600  # a test that failed before opening it leaves no child behind for ever
    while not (gate / "open").exists() and time.monotonic() < deadline:
        time.sleep(0.05)


class SlowSession(Session):
    """Another session, each execute preceded by a sleep of DELAY_S."""

    def __init__(self, inner: Session):
        self._inner = inner

    def prepare(self, inputs: dict[str, np.ndarray]) -> Any:
        return self._inner.prepare(inputs)

    def execute(self, prepared: Any) -> Any:
        if DELAY_S:
            time.sleep(DELAY_S)
        return self._inner.execute(prepared)

    def fetch(self, outputs: Any) -> list[np.ndarray]:
        return self._inner.fetch(outputs)

    def info(self) -> dict[str, Any]:
        return {**self._inner.info(), "added_delay_ms": DELAY_S * 1e3}
