"""tf.profiler's per-op profile of a TensorFlow session on the CPU: its trace's op events (`node:OpType` on
the host plane) summed per node over the calls."""

from __future__ import annotations

import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench_matrix.plugin import OperatorTime, Profile, kind_of, tensorflow

OP_EVENT = re.compile(r"([^:\s]+):(\w+)")  # an op's event: its node name (no colon in it), ':', its type
HOST_PLANE = "/host:CPU"
GPU_REASON = ("tf.profiler's host events of a GPU cell are kernel launches, not the kernels' run time, and "
              "its device planes are not attributed to operators yet")


def tf_profile(call: Callable[[], Any], calls: int, precision: str) -> Profile:
    """`call` run once unprofiled, then `calls` times under tf.profiler tracing into a temporary folder
    (removed with the trace); every op but a Quantized* one is put at `precision` (the trace names no
    dtypes)."""
    tf = tensorflow()
    from tensorflow.tsl.profiler.protobuf import xplane_pb2

    call()
    with tempfile.TemporaryDirectory(prefix="bench-matrix-tf-profile-") as folder:
        tf.profiler.experimental.start(folder)
        try:
            for _ in range(calls):
                call()
        finally:
            tf.profiler.experimental.stop()
        space = xplane_pb2.XSpace()
        space.ParseFromString(next(Path(folder).rglob("*.xplane.pb")).read_bytes())
    return Profile(operators(space, precision), calls)


def operators(space: Any, precision: str) -> tuple[OperatorTime, ...]:
    """Each node's summed event durations (ps) on the host plane, in ms: the executor's op events, which do
    not nest (the TraceMe of an op kernel's Compute)."""
    found: dict[tuple[str, str], float] = {}
    for plane in space.planes:
        if plane.name != HOST_PLANE:
            continue
        for line in plane.lines:
            for event in line.events:
                if match := OP_EVENT.fullmatch(plane.event_metadata[event.metadata_id].name):
                    found[match.groups()] = found.get(match.groups(), 0.0) + event.duration_ps / 1e9
    return tuple(OperatorTime(name, op_type, kind_of(op_type), op_precision(op_type, precision), ms)
                 for (name, op_type), ms in found.items())


def op_precision(op_type: str, precision: str) -> str:
    """int8 for a Quantized* op (QuantizedConv2D, QuantizedMatMul), else the cell's `precision`."""
    return "int8" if "Quantized" in op_type else precision
