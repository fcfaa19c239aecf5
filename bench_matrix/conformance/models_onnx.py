"""The kit's ONNX models, written with onnx.helper (no other framework needed), and their outputs as ONNX's
own reference implementation (onnx.reference) computes them."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench_matrix.conformance.models import CHANNELS, CLASSES, FEATURES, HEAD, HIDDEN, SIDE, TOKENS, \
    VOCABULARY, WIDE, batch_norm_statistics
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs

if TYPE_CHECKING:
    import onnx

OPSET = 17
TRUNK_OUT = 8 * 3 * 3


def _weights(rng: np.random.Generator, *shape: int) -> np.ndarray:
    """He-initialised weights: fan-in is every axis but the first."""
    return (rng.standard_normal(shape) * np.sqrt(2 / np.prod(shape[1:]))).astype(np.float32)


def _dense(rng: np.random.Generator, suffix: str, inputs: int, outputs: int) -> dict[str, np.ndarray]:
    """A Gemm's weights w<suffix> (outputs, inputs; used with transB) and zero biases b<suffix>."""
    return {f"w{suffix}": _weights(rng, outputs, inputs), f"b{suffix}": np.zeros(outputs, np.float32)}


def _model(nodes: list, inputs: list, outputs: dict[str, int],
           weights: dict[str, np.ndarray]) -> "onnx.ModelProto":
    """A checked opset-17 model; `outputs`: each output's name and width (float32, batch axis dynamic)."""
    import onnx
    from onnx import helper, numpy_helper

    graph = helper.make_graph(nodes, "conformance", inputs,
                              [helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, ["N", width])
                               for name, width in outputs.items()],
                              [numpy_helper.from_array(array, name) for name, array in weights.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=8)
    onnx.checker.check_model(model)
    return model


def image_net(weights: dict[str, np.ndarray]) -> "onnx.ModelProto":
    """Two strided convolutions, the first with a BatchNorm, and a dense head: `image` (N, 3, 16, 16) ->
    `output`."""
    import onnx
    from onnx import helper

    image = helper.make_tensor_value_info("image", onnx.TensorProto.FLOAT, ["N", CHANNELS, SIDE, SIDE])
    nodes = [helper.make_node("Conv", ["image", "w1", "b1"], ["c1"], strides=[2, 2]),
             helper.make_node("BatchNormalization", ["c1", "bn_weight", "bn_bias", "bn_running_mean",
                                                     "bn_running_var"], ["n1"]),
             helper.make_node("Relu", ["n1"], ["r1"]),
             helper.make_node("Conv", ["r1", "w2", "b2"], ["c2"], strides=[2, 2]),
             helper.make_node("Relu", ["c2"], ["r2"]), helper.make_node("Flatten", ["r2"], ["flat"]),
             helper.make_node("Gemm", ["flat", "w3", "b3"], ["g3"], transB=1),
             helper.make_node("Relu", ["g3"], ["hidden"]),
             helper.make_node("Gemm", ["hidden", "w4", "b4"], ["output"], transB=1)]
    return _model(nodes, [image], {"output": len(weights["b4"])}, weights)


def multi_io(weights: dict[str, np.ndarray]) -> "onnx.ModelProto":
    """features (N, 6) and ids int64 (N, 5) -> speed (N, 2), angle (N, 2): the ids' mean embedding beside the
    features, one hidden layer, two heads."""
    import onnx
    from onnx import helper

    inputs = [helper.make_tensor_value_info("features", onnx.TensorProto.FLOAT, ["N", FEATURES]),
              helper.make_tensor_value_info("ids", onnx.TensorProto.INT64, ["N", TOKENS])]
    nodes = [helper.make_node("Gather", ["embedding", "ids"], ["embedded"]),
             helper.make_node("ReduceMean", ["embedded"], ["pooled"], axes=[1], keepdims=0),
             helper.make_node("Concat", ["features", "pooled"], ["joined"], axis=1),
             helper.make_node("Gemm", ["joined", "w1", "b1"], ["g1"], transB=1),
             helper.make_node("Relu", ["g1"], ["hidden"]),
             helper.make_node("Gemm", ["hidden", "w_speed", "b_speed"], ["speed"], transB=1),
             helper.make_node("Gemm", ["hidden", "w_angle", "b_angle"], ["angle"], transB=1)]
    return _model(nodes, inputs, {"speed": HEAD, "angle": HEAD}, weights)


def factory(name: str) -> None:
    return None  # an ONNX file holds the whole model


def save(name: str, folder: Path) -> Path:
    """The model with seeded He-initialised weights, zero biases and the kit's BatchNorm statistics, saved as
    an .onnx file."""
    import onnx

    rng = np.random.default_rng(0)
    if name == "multi_io":
        model = multi_io({"embedding": rng.standard_normal((VOCABULARY, 4)).astype(np.float32),
                          **_dense(rng, "1", FEATURES + 4, WIDE), **_dense(rng, "_speed", WIDE, HEAD),
                          **_dense(rng, "_angle", WIDE, HEAD)})
    else:
        model = image_net({"w1": _weights(rng, 8, CHANNELS, 3, 3), "b1": np.zeros(8, np.float32),
                           "w2": _weights(rng, 8, 8, 3, 3), "b2": np.zeros(8, np.float32),
                           **_dense(rng, "3", TRUNK_OUT, HIDDEN),
                           **_dense(rng, "4", HIDDEN, 2 if name == "regression" else CLASSES),
                           **{f"bn_{key}": values for key, values in batch_norm_statistics(8).items()}})
    path = folder / f"{name}.onnx"
    onnx.save(model, str(path))
    return path


def reference(source: SourceModel, inputs: Inputs) -> list[np.ndarray]:
    """The graph's outputs, in order, by onnx.reference."""
    from onnx.reference import ReferenceEvaluator

    outputs = ReferenceEvaluator(str(source.path)).run(None, dict(inputs))
    return [np.asarray(out, dtype=np.float32) for out in outputs]
