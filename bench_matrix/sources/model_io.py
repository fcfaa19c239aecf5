"""What a model file says about its inputs: their names, sample shapes (free axes as None) and dtypes, read with
the same safe loaders that load the model, for the planner to use where the matrix declares no `inputs:`.

ONNX files, torch.export programs (.pt2) and Keras models (.keras, .h5, SavedModel) say it all. A TorchScript
archive names forward's arguments but keeps no shape (tracing stores no example), and a factory's state_dict
says nothing: for those the matrix declares the inputs (or the dataset's arrays give them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench_matrix.sources import ModelFileError, SourceModel
from bench_matrix.tensors import DTYPES, TensorSpec

KERAS_FORMATS = ("keras", "h5", "saved_model")
Stated = tuple[str, list[int | None], str]  # an input as a file states it: name, dims (batch first), dtype
# How to give each kind of model file a dynamic batch axis.
DYNAMIC_BATCH = {
    "onnx": "torch.onnx.export(..., dynamic_axes={{'{name}': {{0: 'batch'}}}}), or tf2onnx with a None batch",
    "torch_export": "torch.export.export(..., dynamic_shapes=...) with torch.export.Dim('batch') on axis 0",
}


@dataclass(frozen=True)
class FileInputs:
    """A model file's inputs (without the batch axis) and the size of each fixed batch axis, by input."""

    inputs: tuple[TensorSpec, ...]
    fixed_batch: dict[str, int]


def read_inputs(framework: str, source_format: str, path: Path) -> tuple[TensorSpec, ...] | None:
    """The model's inputs in order as the file states them (without the batch axis), or None when the file
    does not say; ModelFileError when the file is unsafe, unreadable or takes a dtype bench-matrix cannot feed."""
    read = read_file(framework, source_format, path)
    return None if read is None else read.inputs


def read_file(framework: str, source_format: str, path: Path) -> FileInputs | None:
    """The model's inputs and fixed batch sizes as the file states them, or None when it does not say."""
    if source_format == "onnx":
        stated = onnx_inputs(path)
    elif source_format == "torch_export":
        stated = export_inputs(path)
    elif framework == "tensorflow" and source_format in KERAS_FORMATS:
        stated = keras_inputs(path, source_format)
    else:
        return None
    specs = tuple(_spec(path, name, dims, dtype) for name, dims, dtype in stated)
    return FileInputs(specs, {name: dims[0] for name, dims, _ in stated if dims[0]})


def batch_problem(file: str, source_format: str, fixed: dict[str, int], batch_size: int) -> str | None:
    """Why a model whose inputs have these fixed batch sizes cannot run at batch 1 (latency) and at
    `batch_size` (settings.batch_size: throughput and accuracy), naming its `file` and what to do; or None."""
    name, batch = next(iter(fixed.items()), ("", None))
    if batch is None or batch == batch_size == 1:
        return None
    how = DYNAMIC_BATCH.get(source_format, "keras.Input(shape=...) without batch_size").format(name=name)
    export = f"export the model with a dynamic batch axis ({how})"
    said = f"{file}: the model's input '{name}' has a fixed batch size of {batch}, but"
    if batch == 1:
        return (f"{said} the throughput batch (settings.batch_size, also the batch of the accuracy pass) is "
                f"{batch_size}; {export}, or set settings.batch_size: 1")
    return (f"{said} bench-matrix runs every model at batch 1 (latency) and at settings.batch_size "
            f"({batch_size}); {export}")


def onnx_inputs(path: Path) -> list[Stated]:
    """Every graph input that is not an initializer, read without its external data."""
    import onnx

    from bench_matrix.sources.onnx_file import parse_onnx

    model = parse_onnx(path, str(path))
    initializers = {init.name for init in model.graph.initializer}
    specs = []
    for value in (i for i in model.graph.input if i.name not in initializers):
        tensor = value.type.tensor_type
        if not value.type.HasField("tensor_type"):
            raise ModelFileError(f"{path}: input '{value.name}' is not a tensor (a sequence or map); "
                                 f"bench-matrix feeds tensors only")
        dims = [d.dim_value if d.HasField("dim_value") and d.dim_value > 0 else None for d in tensor.shape.dim]
        bfloat16 = tensor.elem_type == onnx.TensorProto.BFLOAT16
        dtype = "bfloat16" if bfloat16 else onnx.helper.tensor_dtype_to_np_dtype(tensor.elem_type).name
        specs.append((value.name, dims, dtype))
    return specs


def export_inputs(path: Path) -> list[Stated]:
    """The user inputs of a torch.export program: their names, and shapes and dtypes of the traced example
    (symbolic dimensions, such as a dynamic batch, as None)."""
    from bench_matrix.sources.pytorch import load_program, quiet_torch

    with quiet_torch(captured=True):
        program = load_program(path.read_bytes(), str(path))
    names = program.graph_signature.user_inputs
    values = {n.name: n.meta.get("val") for n in program.graph.nodes if n.op == "placeholder"}
    specs = []
    for name in names:
        value = values.get(name)
        if value is None or not hasattr(value, "shape"):
            raise ModelFileError(f"{path}: input '{name}' of the exported program is not a tensor; "
                                 f"bench-matrix feeds tensors only")
        dims = [d if isinstance(d, int) else None for d in value.shape]
        specs.append((name, dims, str(value.dtype).removeprefix("torch.")))
    return specs


def keras_inputs(path: Path, source_format: str) -> list[Stated]:
    """`model.inputs` of a Keras model, loaded in safe mode: the input layers' names, shapes and dtypes."""
    model = SourceModel(name=path.stem, framework="tensorflow", format=source_format, path=path, sha256="",
                        inputs=()).load()
    return [(name, list(tensor.shape), tensor.dtype.name) for name, tensor in zip(_keras_input_names(model),
                                                                                    model.inputs)]


def _keras_input_names(model: Any) -> list[str]:
    names = getattr(model, "input_names", None)
    return list(names) if names else [t.name.split(":")[0] for t in model.inputs]


def _spec(path: Path, name: str, dims: list[int | None], dtype: str) -> TensorSpec:
    """One input's spec, its first (batch) axis dropped; ModelFileError for a scalar or an unfeedable dtype."""
    if not dims:
        raise ModelFileError(f"{path}: input '{name}' is a scalar; bench-matrix feeds batches, so every input "
                             f"needs a batch axis first")
    if dtype not in DTYPES:
        raise ModelFileError(f"{path}: input '{name}' takes {dtype}; bench-matrix feeds {', '.join(DTYPES)}")
    return TensorSpec(name, tuple(dims[1:]), dtype)
