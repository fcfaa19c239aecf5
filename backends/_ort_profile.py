"""ONNX Runtime's per-node profile: a second session with profiling on, its trace's Node events summed per
node."""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.plugin import OperatorTime, Profile, kind_of

if TYPE_CHECKING:
    import onnxruntime

# an input's element type in the trace's input_type_shape -> the precision a node with it runs at
ELEMENT_PRECISIONS = {"int8": "int8", "uint8": "int8", "float16": "fp16", "bfloat16": "bf16", "float": "fp32"}
INT8_OPS = ("QLinear", "Integer")  # QLinearConv, MatMulInteger, ConvInteger: int8 whatever their inputs


def ort_profile(open_profiled: Callable[[str], "onnxruntime.InferenceSession"], feeds: dict[str, Any],
                calls: int) -> Profile:
    """`feeds` run once unprofiled (its events dropped), then `calls` times, by a session `open_profiled`
    opens with profiling into a temporary folder (removed with its trace)."""
    with tempfile.TemporaryDirectory(prefix="bench-matrix-ort-profile-") as tmp:
        session = open_profiled(str(Path(tmp) / "profile"))
        for _ in range(calls + 1):
            session.run(None, feeds)
        events = json.loads(Path(session.end_profiling()).read_text())
    return Profile(operators(events), calls)


def operators(events: list[dict[str, Any]]) -> tuple[OperatorTime, ...]:
    """Each node's summed `dur` (µs) over the Node events after the first model run (the warm-up), in ms."""
    runs = sorted((e["ts"], e["dur"]) for e in events
                  if e.get("cat") == "Session" and e["name"] == "model_run")
    after = runs[0][0] + runs[0][1] if runs else 0
    found: dict[str, OperatorTime] = {}
    for event in events:
        if event.get("cat") != "Node" or event["ts"] < after or "op_name" not in event.get("args", {}):
            continue
        name, args = event["name"].removesuffix("_kernel_time"), event["args"]
        before = found.get(name)
        found[name] = OperatorTime(name, args["op_name"], kind_of(args["op_name"]), precision(args),
                                   (before.ms if before else 0.0) + event["dur"] / 1000)
    return tuple(found.values())


def precision(args: dict[str, Any]) -> str:
    """int8 for QLinear*/*Integer ops or an int8/uint8 input, else fp16, bf16 or fp32 by the inputs' types."""
    types = {element for entry in args.get("input_type_shape", []) for element in entry}
    if any(part in args["op_name"] for part in INT8_OPS):
        return "int8"
    return next((ELEMENT_PRECISIONS[t] for t in ELEMENT_PRECISIONS if t in types), "other")
