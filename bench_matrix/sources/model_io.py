"""What a model file says about its inputs: their names, sample shapes (free axes as None) and dtypes, read with
the same safe loaders that load the model, for the planner to use where the matrix declares no `inputs:`.

ONNX files, torch.export programs (.pt2) and Keras models (.keras, .h5, SavedModel) say it all. A TorchScript
archive names forward's arguments but keeps no shape (tracing stores no example), and a factory's state_dict
says nothing: for those the matrix declares the inputs (or the dataset's arrays give them)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench_matrix.sources import ModelFileError, SourceModel
from bench_matrix.tensors import DTYPES, TensorSpec

KERAS_FORMATS = ("keras", "h5", "saved_model")


def read_inputs(framework: str, source_format: str, path: Path) -> tuple[TensorSpec, ...] | None:
    """The model's inputs in order as the file states them (without the batch axis), or None when the file
    does not say; ModelFileError when the file is unsafe, unreadable or takes a dtype bench-matrix cannot feed."""
    if source_format == "onnx":
        return onnx_inputs(path)
    if source_format == "torch_export":
        return export_inputs(path)
    if framework == "tensorflow" and source_format in KERAS_FORMATS:
        return keras_inputs(path, source_format)
    return None


def onnx_inputs(path: Path) -> tuple[TensorSpec, ...]:
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
        specs.append(_spec(path, value.name, dims, dtype))
    return tuple(specs)


def export_inputs(path: Path) -> tuple[TensorSpec, ...]:
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
        specs.append(_spec(path, name, dims, str(value.dtype).removeprefix("torch.")))
    return tuple(specs)


def keras_inputs(path: Path, source_format: str) -> tuple[TensorSpec, ...]:
    """`model.inputs` of a Keras model, loaded in safe mode: the input layers' names, shapes and dtypes."""
    model = SourceModel(name=path.stem, framework="tensorflow", format=source_format, path=path, sha256="",
                        inputs=()).load()
    return tuple(_spec(path, name, list(tensor.shape), tensor.dtype.name)
                 for name, tensor in zip(_keras_input_names(model), model.inputs))


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
