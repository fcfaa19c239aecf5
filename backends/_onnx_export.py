"""The fp32 ONNX model of a source (an ONNX file as it is, a PyTorch model through torch.onnx, a Keras model
through tf2onnx), and which graph input each of the source's named inputs feeds."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import TYPE_CHECKING

from bench_matrix.plugin import ConvertRequest, ModelFileError, SourceModel, load_onnx, tensorflow

from ._torch import example_tensors, flat_module, quiet_torch

if TYPE_CHECKING:
    import onnx

OPSET = 17


def fp32_model(request: ConvertRequest, tmp: Path) -> "onnx.ModelProto":
    """The fp32 ONNX model: the ONNX source as is, or a PyTorch or Keras source exported with a dynamic batch
    axis (once per source: the export is kept in request.shared_dir for the other modes)."""
    import onnx

    source = request.source
    if source.framework == "onnx":  # checked, external data read in from the model's directory only
        return load_onnx(source.path, source.label)
    kept = request.shared_dir / "fp32.onnx" if request.shared_dir else None
    if kept and kept.is_file():
        return onnx.load(str(kept))
    model = _keras_to_onnx(request) if source.framework == "tensorflow" else _torch_to_onnx(request, tmp)
    if kept:
        partial = tmp / "shared-fp32.onnx"
        onnx.save(model, str(partial))
        shutil.move(partial, kept)  # a rename where tmp is in the scratch folder: kept appears whole
    return model


def _torch_to_onnx(request: ConvertRequest, tmp: Path) -> "onnx.ModelProto":
    """A PyTorch source through the TorchScript-based exporter: inputs named as the source's, outputs output_0..
    in flat_outputs' order, the batch axis and every free axis dynamic."""
    import onnx
    import torch

    source = request.source
    path = tmp / "exported.onnx"
    example = example_tensors(source.inputs, "cpu", torch.float32, request.seed)
    with quiet_torch(captured=source.format == "torch_export"), torch.no_grad():
        module, outputs = flat_module(source.load(), example)
        if source.format == "torch_export":  # the TorchScript-based exporter cannot call .train() on it
            module = torch.jit.trace(module, example)
        names = [f"output_{i}" for i in range(outputs)]
        axes = {spec.name: {0: "batch", **{i + 1: f"{spec.name}_{i + 1}" for i, d in enumerate(spec.shape)
                                           if d is None}} for spec in source.inputs}
        torch.onnx.export(module, example, str(path), dynamo=False, opset_version=OPSET,
                          input_names=[spec.name for spec in source.inputs], output_names=names,
                          dynamic_axes={**axes, **{name: {0: "batch"} for name in names}})
    return onnx.load(str(path))


def _keras_to_onnx(request: ConvertRequest) -> "onnx.ModelProto":
    """A Keras model through tf2onnx, one signature entry per input (its dtype; the batch and free axes dynamic);
    the layout (NHWC) stays the model's own."""
    tf = tensorflow(request.threads)
    import tf2onnx

    signature = tuple(tf.TensorSpec((None, *spec.shape), tf.as_dtype(spec.dtype), name=spec.name)
                      for spec in request.source.inputs)
    model, _ = tf2onnx.convert.from_keras(request.source.load(), input_signature=signature, opset=OPSET)
    return model


def graph_feeds(model: "onnx.ModelProto", source: SourceModel) -> tuple[dict[str, str], int | None]:
    """Which graph input each source input feeds ({source name: graph name}, in the source's order: by name
    when the names are the graph's, else by position), and the graph's fixed batch size (None when dynamic)."""
    initializers = {init.name for init in model.graph.initializer}
    graph = [i for i in model.graph.input if i.name not in initializers]
    names = [i.name for i in graph]
    if len(graph) != len(source.inputs):
        declared = ", ".join(spec.describe() for spec in source.inputs)
        raise ModelFileError(f"{source.label}: the ONNX model has {len(graph)} inputs ({', '.join(names)}) but "
                             f"{len(source.inputs)} are declared ({declared}); declare one per graph input")
    wanted = [spec.name for spec in source.inputs]
    feeds = dict(zip(wanted, wanted if set(wanted) == set(names) else names))
    dims = graph[0].type.tensor_type.shape.dim
    return feeds, (dims[0].dim_value or None) if dims else None


def opset(model: "onnx.ModelProto") -> int:
    return next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
