"""The work of one inference from a model's ONNX graph with inferred shapes: its FLOPs (2 per multiply-add of
Conv, ConvTranspose, Gemm and MatMul, and of their integer forms) and the bytes it must move at least
(weights once, each activation once): docs/metrics.md §17."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import onnx

CONV = ("Conv", "ConvInteger", "QLinearConv")
MATMUL = ("MatMul", "MatMulInteger", "QLinearMatMul")
GEMM = ("Gemm",)
QUANTISED_INPUTS = ("QLinearConv", "QLinearMatMul")  # (x, x_scale, x_zero, w, ...)
TRANSPOSED = ("ConvTranspose",)
Shape = tuple[tuple[int, ...], int]  # a tensor's dimensions and its element's size in bytes


@dataclass(frozen=True)
class Work:
    """FLOPs and bytes of one inference (batch 1), FLOPs by op type; `reason` says why there is no count."""

    flops: int = 0
    weight_bytes: int = 0
    activation_bytes: int = 0
    by_op: dict[str, int] = field(default_factory=dict)
    reason: str | None = None

    @property
    def bytes(self) -> int:
        return self.weight_bytes + self.activation_bytes

    def to_json(self) -> dict[str, Any]:
        """The conversion manifest's `work`: the counts, or the reason alone."""
        if self.reason:
            return {"reason": self.reason}
        return {"flops": self.flops, "bytes": self.bytes, "weight_bytes": self.weight_bytes,
                "activation_bytes": self.activation_bytes, "flops_by_op": dict(sorted(self.by_op.items()))}


def onnx_work(model: onnx.ModelProto, inputs: Iterable[Any]) -> Work:
    """The work of `model` at batch 1, each graph input shaped (1, *spec.shape) by its TensorSpec in
    `inputs` (by position); a free axis or a shape inference cannot tell is a reason, never a guess."""
    specs = list(inputs)
    if free := [s.name for s in specs if any(d is None for d in s.shape)]:
        return Work(reason=f"input {', '.join(free)} has a free axis: its length at inference is not known")
    try:
        inferred = _inferred(model, [(1, *s.shape) for s in specs])
    except Exception as exc:  # any: onnx's shape inference rejects what it cannot type
        return Work(reason=f"ONNX shape inference failed: {type(exc).__name__}: {exc}")
    return count(inferred)


def _inferred(model: onnx.ModelProto, shapes: Sequence[tuple[int, ...]]) -> onnx.ModelProto:
    """A copy of `model` with its graph inputs fixed to `shapes` and every value's shape inferred."""
    import onnx

    fixed = onnx.ModelProto()
    fixed.CopyFrom(model)
    weights = {init.name for init in fixed.graph.initializer}
    for value, shape in zip([i for i in fixed.graph.input if i.name not in weights], shapes):
        dims = value.type.tensor_type.shape.dim
        del dims[:]
        for length in shape:
            dims.add().dim_value = int(length)
    return onnx.shape_inference.infer_shapes(fixed, strict_mode=False, data_prop=True)


def count(model: onnx.ModelProto) -> Work:
    """FLOPs and bytes of a graph whose values have static shapes (onnx_work infers them)."""
    graph = model.graph
    weights = {init.name: _tensor_shape(init) for init in graph.initializer}  # by dims: no data is read
    shapes = _shapes(graph, weights)
    by_op: dict[str, int] = {}
    for node in graph.node:
        flops = node_flops(node, shapes)
        if flops is None:
            return Work(reason=f"{node.op_type} node {node.name or node.output[0]}: its shapes are not known")
        if flops:
            by_op[node.op_type] = by_op.get(node.op_type, 0) + flops
    moved = [graph.input[k].name for k in range(len(graph.input))] + [o for n in graph.node for o in n.output]
    unknown = [name for name in moved if name and name not in weights and name not in shapes]
    if unknown:
        return Work(reason=f"the shape of {unknown[0]} is not known")
    activations = sum(_size(shapes[name]) for name in dict.fromkeys(moved) if name and name not in weights)
    constants = sum(_constant_bytes(node) for node in graph.node if node.op_type == "Constant")
    return Work(sum(by_op.values()), sum(map(_size, weights.values())) + constants, activations, by_op)


def node_flops(node: onnx.NodeProto, shapes: dict[str, Shape]) -> int | None:
    """2 × the multiply-adds of a Conv, ConvTranspose, Gemm or MatMul (float or integer form); 0 for any
    other op; None where a shape it needs is not known."""
    if node.op_type not in CONV + MATMUL + GEMM + TRANSPOSED:
        return 0
    data, weight = (node.input[0], node.input[3]) if node.op_type in QUANTISED_INPUTS else node.input[:2]
    out = node.output[0]
    if any(name not in shapes for name in (data, weight, out)):
        return None
    x, w, y = shapes[data][0], shapes[weight][0], shapes[out][0]
    if node.op_type in CONV:  # each output element: C_in/group × kernel multiply-adds
        return 2 * math.prod(y) * math.prod(w[1:])
    if node.op_type in TRANSPOSED:  # each input element: C_out/group × kernel multiply-adds
        return 2 * math.prod(x) * math.prod(w[1:])
    if node.op_type in GEMM:
        trans_a = next((a.i for a in node.attribute if a.name == "transA"), 0)
        return 2 * math.prod(y) * (x[0] if trans_a else x[-1])
    return 2 * math.prod(y) * x[-1]  # MatMul: every output element a K-long dot product


def _shapes(graph: onnx.GraphProto, weights: dict[str, Shape]) -> dict[str, Shape]:
    """Each value's static shape and element size (values with an unknown dimension left out)."""
    found = dict(weights)
    for value in [*graph.input, *graph.value_info, *graph.output]:
        tensor = value.type.tensor_type
        dims = [d.dim_value if d.HasField("dim_value") else None for d in tensor.shape.dim]
        if tensor.HasField("shape") and None not in dims and tensor.elem_type:
            found.setdefault(value.name, (tuple(dims), _itemsize(tensor.elem_type)))
    return found


def _tensor_shape(tensor: onnx.TensorProto) -> Shape:
    return tuple(tensor.dims), _itemsize(tensor.data_type)


def _itemsize(elem_type: int) -> int:
    from onnx import helper

    return helper.tensor_dtype_to_np_dtype(elem_type).itemsize


def _size(shape: Shape) -> int:
    return math.prod(shape[0]) * shape[1]


def _constant_bytes(node: onnx.NodeProto) -> int:
    value = next((a.t for a in node.attribute if a.name == "value" and a.HasField("t")), None)
    return _size(_tensor_shape(value)) if value is not None else 0
