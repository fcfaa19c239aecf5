"""Read a user's ONNX model: a checked protobuf, with external data read only from inside its directory."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bench_matrix.sources import ModelFileError

if TYPE_CHECKING:
    import onnx

ONNX_DOMAINS = ("", "ai.onnx.ml", "ai.onnx.preview", "ai.onnx.preview.training")  # ONNX's own operator sets
EXPORT = "export the model again (torch.onnx.export, tf2onnx) and give the .onnx file it writes"
EXTERNAL = ("keep external data files inside the model's directory and save the model with a relative "
            "location (onnx.save_model(model, path, save_as_external_data=True, location='weights.data'))")
# The first bytes of files often given an .onnx suffix by mistake.
MAGIC = ((b"PK\x03\x04", "a zip archive (a PyTorch .pt/.pt2 or Keras .keras file?)"),
         (b"\x89HDF", "an HDF5 file (a Keras .h5 file?)"), (b"\x89PNG", "a PNG image"),
         (b"\x80", "a Python pickle (a PyTorch file?)"))


def load_onnx(path: Path, label: str) -> "onnx.ModelProto":
    """The model in `path` with its external data read in; ModelFileError naming `label` when it is not a
    valid ONNX model or keeps data outside its directory."""
    model = parse_onnx(path, label)
    _check_operators(model, label)
    _load_external_data(model, path, label)
    return model


def parse_onnx(path: Path, label: str) -> "onnx.ModelProto":
    """The model in `path` without its external data (its graph, inputs and outputs); ModelFileError naming
    `label` when it is not a valid ONNX model."""
    import onnx
    from google.protobuf.message import DecodeError

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ModelFileError(f"{label}: cannot be read ({exc.strerror}: {exc.filename})") from None
    try:
        model = onnx.load_model_from_string(data)
    except (DecodeError, ValueError, RuntimeError) as exc:
        raise ModelFileError(f"{label}: is not a valid ONNX model: {_kind(data) or exc}; "
                             f"{EXPORT}") from None
    if not model.graph.node or not model.ir_version:
        what = "the file is empty" if not data else _kind(data) or "it holds no graph"
        raise ModelFileError(f"{label}: is not a valid ONNX model: {what}; {EXPORT}")
    return model


def external_data_files(path: Path) -> list[Path]:
    """The external data files the ONNX model in `path` reads (those it may read: inside its directory)."""
    from onnx.external_data_helper import ExternalDataInfo, uses_external_data

    base = path.parent.resolve()
    tensors = _tensors(parse_onnx(path, str(path)))
    locations = {ExternalDataInfo(t).location for t in tensors if uses_external_data(t)}
    readable = (location for location in locations if _location_problem(base, location) is None)
    return sorted(path.parent / location for location in readable)


def _check_operators(model: "onnx.ModelProto", label: str) -> None:
    """Refuse a node whose operator is in one of ONNX's own domains but not defined there at the opset the
    model imports: no runtime can run it."""
    import onnx

    versions = {_domain(o.domain): o.version for o in model.opset_import}
    local = {(f.domain, f.name) for f in model.functions}
    for node in model.graph.node:
        domain = _domain(node.domain)
        if domain not in ONNX_DOMAINS or domain not in versions or (node.domain, node.op_type) in local:
            continue
        try:
            onnx.defs.get_schema(node.op_type, versions[domain], domain)
        except onnx.defs.SchemaError:
            raise ModelFileError(_operator_problem(node, domain, versions[domain], label)) from None


def _operator_problem(node: "onnx.NodeProto", domain: str, version: int, label: str) -> str:
    """What is wrong with a node's operator, naming the user's file, the node and what to do."""
    import onnx

    where = f"{label}: node '{node.name}'" if node.name else f"{label}: a node"
    opset = f"operator set {domain or 'ai.onnx'}"
    if onnx.defs.has(node.op_type, domain):
        why = (f"which ONNX's {opset} does not define at version {version}, the one the model imports; "
               f"export the model again at an opset that has it")
    else:
        why = (f"which is not an ONNX operator ({opset}, onnx {onnx.__version__}), so no runtime can run it; "
               f"export the model again with standard ONNX operators only")
    return f"{where} uses operator {node.op_type}, {why} (torch.onnx.export, tf2onnx)"


def _domain(domain: str) -> str:
    return "" if domain == "ai.onnx" else domain


def _kind(data: bytes) -> str | None:
    """'it is a PNG image' when the bytes start like a known other kind of file."""
    return next((f"it is {what}" for magic, what in MAGIC if data.startswith(magic)), None)


def _load_external_data(model: "onnx.ModelProto", path: Path, label: str) -> None:
    """Read every external tensor's data, each from a regular file inside the model's directory."""
    from onnx.external_data_helper import ExternalDataInfo, load_external_data_for_tensor, uses_external_data

    base = path.parent.resolve()
    for tensor in _tensors(model):
        if not uses_external_data(tensor):
            continue
        location = ExternalDataInfo(tensor).location
        where = f"{label}: tensor '{tensor.name}' keeps its data in external file '{location}'"
        if problem := _location_problem(base, location):
            raise ModelFileError(f"{where}, {problem}; bench-matrix reads external data only from regular "
                                 f"files inside the model's directory ({base}): {EXTERNAL}")
        try:
            load_external_data_for_tensor(tensor, str(base))
        except Exception as exc:  # offset or length beyond the file, an unreadable file
            raise ModelFileError(f"{where}, which cannot be read: {type(exc).__name__}: {exc}; "
                                 f"{EXTERNAL}") from None


def _tensors(message: Any) -> Iterator[Any]:
    """Every TensorProto anywhere in an ONNX message: initializers, sparse tensors, attributes, subgraphs,
    functions (the model saved for the runtime must keep no reference to an external file)."""
    from google.protobuf.descriptor import FieldDescriptor
    from onnx import TensorProto

    if isinstance(message, TensorProto):
        yield message
    for field, value in message.ListFields():
        if field.type == FieldDescriptor.TYPE_MESSAGE:
            for item in value if field.is_repeated else [value]:
                yield from _tensors(item)


def _location_problem(base: Path, location: str) -> str | None:
    """Why an external-data location may not be read, or None."""
    parts = location.replace("\\", "/").split("/")
    if not location or os.path.isabs(location) or location.startswith(("/", "\\")) or ":" in parts[0]:
        return "which is not a relative path" if location else "which is empty"
    if ".." in parts:
        return "which climbs out of the model's directory ('..')"
    target = base / location
    try:
        mode = os.lstat(target).st_mode
    except OSError as exc:
        return f"which cannot be found ({exc.strerror})"
    if stat.S_ISLNK(mode):
        return "which is a symbolic link"
    if not stat.S_ISREG(mode):
        return "which is not a regular file"
    if not target.resolve().is_relative_to(base):
        return "which lies outside the model's directory"
    return None
