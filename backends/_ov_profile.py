"""OpenVINO's per-layer profile: the model compiled again with PERF_COUNT, its infer request's profiling info
summed per layer over the calls."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from bench_matrix.plugin import OperatorTime, Profile, kind_of

if TYPE_CHECKING:
    import openvino as ov

PERF_COUNT = {"PERF_COUNT": True}  # openvino.properties.enable_profiling(): per-layer counters on every infer
# the exec_type's last part (jit_avx512_I8, brgconv_avx512_bf16, brgemm_avx512_f32), lower-cased -> precision
SUFFIX_PRECISIONS = {"f32": "fp32", "f16": "fp16", "bf16": "bf16", "i8": "int8", "u8": "int8"}


def ov_profile(compiled: "ov.CompiledModel", tensors: dict[str, "ov.Tensor"], calls: int) -> Profile:
    """`tensors` (graph input name -> bound tensor) inferred once unprofiled, then `calls` times by a request
    of `compiled` (compiled with PERF_COUNT), each call's executed layers summed."""
    request = compiled.create_infer_request()
    for name, tensor in tensors.items():
        request.set_tensor(name, tensor)
    request.infer()
    found: dict[str, OperatorTime] = {}
    for _ in range(calls):
        request.infer()
        for layer in request.get_profiling_info():
            _add(found, layer)
    return Profile(tuple(found.values()), calls)


def _add(found: dict[str, OperatorTime], layer: Any) -> None:
    """Add a layer's real time to its operator in `found`; layers that did not run (fused, no-ops) are left."""
    ms = layer.real_time.total_seconds() * 1000
    if layer.status != layer.Status.EXECUTED or ms <= 0:
        return
    before = found.get(layer.node_name)
    found[layer.node_name] = OperatorTime(layer.node_name, layer.node_type, kind_of(layer.node_type),
                                          precision(layer.exec_type), (before.ms if before else 0.0) + ms)


def precision(exec_type: str) -> str:
    """The precision of a kernel by its name's last part (jit_avx512_I8: int8); other when it names none."""
    return SUFFIX_PRECISIONS.get(exec_type.rpartition("_")[2].lower(), "other")
