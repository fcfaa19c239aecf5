"""The machine's peak at a thread count, through ONNX Runtime: a compute-bound GEMM's FLOP/s at fp32 and int8
(MatMulInteger, where the CPU has int8 dot products) and streaming memory bandwidth (a large Add), and bf16
through OpenVINO (ONNX Runtime has no bf16 CPU kernel), each the fastest of its calls (metrics.md §17)."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# an N×N by N×N MatMul: 0.27 GFLOP a call, in cache and compute bound; calls this short are the likeliest to
# run uninterrupted on a busy machine (our 2-core VM under load: 108 GFLOP/s at 512, 51 at 1024)
GEMM_N = 512
STREAM_MIB = 128  # the Add's input: far beyond any CPU's caches
SECONDS = 0.6  # each kernel's time, at least 3 calls
Kernel = Callable[[], Any]


@dataclass(frozen=True)
class Peak:
    """The peaks at `threads`: FLOP/s by precision, bytes/s streamed, and why a precision has none."""

    threads: int
    flops: dict[str, float]
    bandwidth: float
    reasons: dict[str, str] = field(default_factory=dict)

    def fields(self) -> dict[str, Any]:
        """The record's `machine_*` fields."""
        return {"machine_threads": self.threads,
                "machine_flops": {name: round(value) for name, value in self.flops.items()},
                "machine_bandwidth": round(self.bandwidth), "machine_reasons": dict(self.reasons)}


def best_of(held: Mapping[str, Any], found: Mapping[str, Any]) -> dict[str, Any]:
    """Two peaks of one machine (`machine_*` fields) as one: each precision's and the bandwidth's higher of
    the two (other work only ever slows a measurement), disturbed only where both were, measurements added."""
    flops = dict(held["machine_flops"])
    for name, value in found["machine_flops"].items():
        flops[name] = max(flops.get(name, 0), value)
    reasons = {**held.get("machine_reasons", {}), **found.get("machine_reasons", {})}
    both_disturbed = held.get("machine_disturbed") and found.get("machine_disturbed")
    count = held.get("machine_measurements", 1) + found.get("machine_measurements", 1)
    return {**held, "machine_flops": flops,
            "machine_bandwidth": max(held["machine_bandwidth"], found["machine_bandwidth"]),
            "machine_reasons": {name: why for name, why in reasons.items() if name not in flops},
            "machine_disturbed": found["machine_disturbed"] if both_disturbed else None,
            "machine_measurements": count}


def best_rate(call: Kernel, amount: float, seconds: float, clock: Callable[[], float]) -> float:
    """`amount` ÷ the fastest of `call`'s calls over `seconds` (at least 3 calls, after one untimed)."""
    call()
    fastest, begin, calls = float("inf"), clock(), 0
    while calls < 3 or clock() - begin < seconds:
        start = clock()
        call()
        fastest = min(fastest, clock() - start)
        calls += 1
    if not fastest > 0:
        raise ValueError(f"a call took {fastest} s by the clock: no rate")
    return amount / fastest


def measure(threads: int, kernels: dict[str, tuple[Kernel | str, float]], seconds: float = SECONDS,
            clock: Callable[[], float] = time.perf_counter) -> Peak:
    """The peak from `kernels`: 'fp32', 'int8', 'bf16' (a call and its FLOPs, or why there is none) and
    'stream' (a call and its bytes)."""
    rates = {name: best_rate(call, amount, seconds, clock) for name, (call, amount) in kernels.items()
             if callable(call)}
    reasons = {name: call for name, (call, _) in kernels.items() if isinstance(call, str)}
    if "stream" not in rates or "fp32" not in rates:
        raise ValueError(f"no fp32 GEMM or stream kernel: {reasons}")
    return Peak(threads, {k: v for k, v in rates.items() if k != "stream"}, rates["stream"], reasons)


def ort_kernels(threads: int, flags: frozenset[str]) -> dict[str, tuple[Kernel | str, float]]:
    """This machine's kernels through ONNX Runtime at `threads` (`flags`: the CPU's, for int8 and bf16)."""
    n, gemm_flops = GEMM_N, 2.0 * GEMM_N ** 3
    rng = np.random.default_rng(0)
    fp32 = rng.normal(size=(n, n)).astype(np.float32)
    stream = np.ones(STREAM_MIB * 2 ** 20 // 4, np.float32)
    found: dict[str, tuple[Kernel | str, float]] = {
        "fp32": (_ort("MatMul", [fp32, fp32], threads), gemm_flops),
        "stream": (_ort("Add", [stream, np.float32(1)], threads), 2.0 * stream.nbytes)}  # read and write
    int8 = {"avx512_vnni", "avx_vnni", "amx_int8", "asimddp", "i8mm"} & flags
    found["int8"] = ((_ort("MatMulInteger", [rng.integers(0, 255, (n, n), np.uint8),
                                            rng.integers(-127, 127, (n, n), np.int8)], threads), gemm_flops)
                     if int8 else ("the CPU has no int8 dot-product instructions (VNNI, AMX, dotprod)", 0.0))
    found["bf16"] = (_bf16(fp32, threads, flags), gemm_flops)
    return found


def _bf16(fp32: np.ndarray, threads: int, flags: frozenset[str]) -> Kernel | str:
    """The GEMM at bf16 through OpenVINO's CPU plugin (ONNX Runtime's CPU provider has no bf16 MatMul), or why
    there is none: no bf16 instructions, no OpenVINO, or a plugin that would not compute it in bf16."""
    import importlib.util

    if not {"avx512_bf16", "amx_bf16", "bf16"} & flags:
        return "the CPU has no bf16 instructions (AVX-512 BF16, AMX, ARM bf16)"
    if importlib.util.find_spec("openvino") is None:
        return "measured through OpenVINO (ONNX Runtime's CPU provider has no bf16 MatMul), not installed"
    import openvino as ov
    import openvino.opset13 as ops

    x = ops.parameter(list(fp32.shape), np.float32, name="x")
    model = ov.Model([ops.matmul(x, ops.constant(fp32), False, False)], [x], "peak")
    compiled = ov.Core().compile_model(model, "CPU", {"INFERENCE_PRECISION_HINT": "bf16",
                                                      "INFERENCE_NUM_THREADS": threads,
                                                      "PERFORMANCE_HINT": "LATENCY"})
    if compiled.get_property("INFERENCE_PRECISION_HINT") != ov.Type.bf16:
        return "OpenVINO's CPU plugin would not compute in bf16 here"
    request = compiled.create_infer_request()
    return lambda: request.infer({0: fp32})


def _ort(op: str, arrays: list[Any], threads: int) -> Kernel:
    """One `op` node on `arrays` (the first a graph input, the rest weights) in a session of `threads`."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    weights = [numpy_helper.from_array(np.asarray(a), f"w{k}") for k, a in enumerate(arrays[1:])]
    kind = helper.np_dtype_to_tensor_dtype(arrays[0].dtype)
    out = TensorProto.INT32 if op == "MatMulInteger" else kind
    graph = helper.make_graph([helper.make_node(op, ["x", *(w.name for w in weights)], ["y"])], "peak",
                              [helper.make_tensor_value_info("x", kind, arrays[0].shape)],
                              [helper.make_tensor_value_info("y", out, None)], weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    feed = {"x": arrays[0]}
    return lambda: session.run(None, feed)
