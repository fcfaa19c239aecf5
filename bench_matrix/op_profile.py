"""A session's per-operator profile from its runtime's own profiler: each operator's runtime op type, its kind
in a vocabulary shared by every runtime, the precision it ran at and its time (docs/metrics.md, Profiles)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# the normalised kinds of operator, the same for every runtime
KINDS = ("conv", "matmul", "pool", "activation", "quant", "reshape", "other")
PRECISIONS = ("fp32", "fp16", "bf16", "int8", "other")
# (word in the lower-cased op type, kind), the first found decides: tf.data's datasets (TensorSliceDataset,
# ConcatenateDataset) are other whatever they name, "convert" before "conv", "matmul" before
# "quant" (DynamicQuantizeMatMul is a MatMul, so is quantized::linear); reshape covers layout copies (Reorder,
# Transpose, Concat). torch's ops: aten::addmm, aten::mm, aten::bmm, aten::linear and
# mkldnn::_linear_pointwise are matmul ("::linear" and "_linear", not "linear": ONNX's DequantizeLinear is
# quant, QLinearAdd other); aten::clamp_min is eager ReLU's work, OpenVINO's Maximum (with 0) ReLU's on ARM;
# aten::view and aten::_unsafe_view reshape
KIND_WORDS = (("dataset", "other"), ("convert", "quant"), ("conv", "conv"),
              *((word, "matmul") for word in ("matmul", "gemm", "fullyconnected", "innerproduct", "addmm",
                                              "bmm", "::mm", "::linear", "_linear")),
              ("pool", "pool"), ("quant", "quant"),
              *((word, "activation") for word in ("relu", "sigmoid", "tanh", "elu", "clip", "clamp",
                                                  "softmax", "swish", "mish", "hardsigmoid", "silu",
                                                  "maximum")),
              *((word, "reshape") for word in ("reshape", "reorder", "transpose", "flatten", "squeeze",
                                               "concat", "gather", "slice", "split", "copy", "pad", "view",
                                               "permute", "contiguous")))


def kind_of(op_type: str) -> str:
    """The kind (KINDS) of a runtime's op type, by the first of KIND_WORDS it contains; other when none."""
    lowered = op_type.lower()
    return next((kind for word, kind in KIND_WORDS if word in lowered), "other")


@dataclass(frozen=True)
class OperatorTime:
    """One operator of a profile: its name, the runtime's op type, its kind (KINDS), the precision it ran at
    (PRECISIONS) and its total time over the profiled calls, ms."""

    name: str
    op_type: str
    kind: str
    precision: str
    ms: float


@dataclass(frozen=True)
class Profile:
    """What a session's profiler saw over `calls` calls of one batch; `reason` says why there is none."""

    operators: tuple[OperatorTime, ...] = ()
    calls: int = 0
    reason: str | None = None

    @property
    def total_ms(self) -> float:
        """Every operator's time over the calls, ms."""
        return math.fsum(op.ms for op in self.operators)

    def problem(self) -> str | None:
        """Why the profile is no result: its reason, no operator, or times not finite, negative or all 0."""
        if self.reason or not self.operators or self.calls < 1:
            return self.reason or "the profiler reported no operator"
        times = [op.ms for op in self.operators]
        if not all(math.isfinite(t) and t >= 0 for t in times):
            return "the profiler reported a time that is not a finite, non-negative number"
        return None if any(times) else "the profiler reported zero time for every operator"

    def fields(self) -> dict[str, Any]:
        """The record's `profile_*` fields: per-inference times, or the reason alone."""
        if problem := self.problem():
            return {"profile_reason": problem}
        return {"profile_calls": self.calls, "profile_ms": round(self.total_ms / self.calls, 6),
                "profile_operators": [{"name": op.name, "op_type": op.op_type, "kind": op.kind,
                                       "precision": op.precision, "ms": round(op.ms / self.calls, 6)}
                                      for op in self.operators]}
