"""`bench-matrix device check` without a host: this machine's noise for timing (measure/noise.py), measured
on a tiny built-in ONNX model run by ONNX Runtime on one pinned thread, as a cell's session is."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from bench_matrix.measure.affinity import pin_threads
from bench_matrix.measure.noise import Check, check

WIDTH = 512  # the tiny model: four 512×512 MatMul + Relu layers on one sample (about 0.1 ms a call)


def tiny_session() -> Callable[[], Any]:
    """One call of the tiny model in an ONNX Runtime session with one thread."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    nodes, inits, name = [], [], "x"
    for k in range(4):
        inits.append(numpy_helper.from_array(rng.normal(0, 0.1, (WIDTH, WIDTH)).astype(np.float32), f"w{k}"))
        nodes += [helper.make_node("MatMul", [name, f"w{k}"], [f"m{k}"]),
                  helper.make_node("Relu", [f"m{k}"], [f"r{k}"])]
        name = f"r{k}"
    tensor = helper.make_tensor_value_info
    graph = helper.make_graph(nodes, "tiny", [tensor("x", TensorProto.FLOAT, [1, WIDTH])],
                              [tensor(name, TensorProto.FLOAT, [1, WIDTH])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = 1, 1
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    feed = {"x": rng.normal(0, 1, (1, WIDTH)).astype(np.float32)}
    return lambda: session.run(None, feed)


def window_of(call: Callable[[], Any]) -> Callable[[float], float]:
    """A window of `call`: calls until `seconds` have passed (at least one); their median, in ms."""
    def window(seconds: float) -> float:
        durations, end = [], time.perf_counter() + seconds
        while not durations or time.perf_counter() < end:
            start = time.perf_counter_ns()
            call()
            durations.append(time.perf_counter_ns() - start)
        return float(np.median(durations)) / 1e6
    return window


def check_here(seconds: float) -> Check:
    """Pin to one CPU, warm the tiny model up, then check."""
    pin_threads(1)
    call = tiny_session()
    for _ in range(200):
        call()
    return check(window_of(call), seconds)


def show(found: Check, console: Any, as_json: bool) -> None:
    """The check as a table (or JSON)."""
    if as_json:
        console.print_json(json.dumps(found.to_json()))
        return
    from rich.table import Table

    table = Table(title="this machine, for timing", title_justify="left", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("found")
    for name, value in found.rows():
        table.add_row(name, value)
    console.print(table)
