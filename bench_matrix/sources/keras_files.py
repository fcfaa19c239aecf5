"""What a Keras model file may hold before tf_keras reads it. tf_keras' safe mode refuses Lambda bytecode, but
a config may name any module to import and any function in it for a Lambda layer to call, and a SavedModel's
graphs may hold any TensorFlow operation: both are checked here."""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from typing import Any

from bench_matrix.sources import ModelFileError

PYTHON_OPS = frozenset({"PyFunc", "PyFuncStateless", "EagerPyFunc"})
# Checkpoint operations: allowed only in the save and restore functions TensorFlow writes, which nothing else
# may call (TensorFlow 2's loader restores variables itself and never runs them).
SAVER_OPS = frozenset({"SaveV2", "Save", "SaveSlices", "RestoreV2", "Restore", "RestoreSlice",
                       "MergeV2Checkpoints"})
FILE_OPS = frozenset({
    "WriteFile", "ReadFile", "MatchingFiles", "ImmutableConst", "FileSystemSetConfiguration", "RecordInput",
    "CreateSummaryFileWriter", "CreateSummaryDbWriter", "SummaryWriter", "DatasetToTFRecord",
    "ExperimentalDatasetToTFRecord", "SaveDataset", "SaveDatasetV2", "DistributedSave", "LoadDataset",
    "SnapshotDataset", "SnapshotDatasetV2", "SnapshotDatasetReader", "SnapshotNestedDatasetReader",
    "SnapshotChunkDataset", "ListSnapshotChunksDataset", "TFRecordDataset", "TFRecordDatasetV2",
    "FixedLengthRecordDataset", "FixedLengthRecordDatasetV2", "TextLineDataset", "MatchingFilesDataset",
    "ExperimentalMatchingFilesDataset", "SqlDataset", "ExperimentalSqlDataset", "TFRecordReader",
    "TFRecordReaderV2", "TextLineReader", "TextLineReaderV2", "WholeFileReader", "WholeFileReaderV2",
    "FixedLengthRecordReader", "FixedLengthRecordReaderV2", "LMDBReader", "InitializeTableFromTextFile",
    "InitializeTableFromTextFileV2", "LoadAndRemapMatrix", "DecodeProtoV2", "EncodeProto", "DebugIdentity",
    "DebugIdentityV2", "DebugIdentityV3", "DebugNanCount", "DebugNumericSummary", "DebugNumericSummaryV2"})
SAVER_FUNCTION = re.compile(r"__inference__traced_(save|restore)_\d+\Z")
RESAVE = "save the model with Keras 2 (tf_keras), of built-in layers only (no Lambda, no custom objects)"


def check_keras_file(path: Path, label: str) -> None:
    """ModelFileError when a .keras, .h5 or SavedModel holds something tf_keras would import, call or run
    unsafely. What is checked follows what tf_keras reads (a .keras name on an HDF5 file is read as .h5)."""
    import h5py

    if path.is_dir():
        try:
            problem, configs, lambdas_refused = saved_model_problem(path), _saved_model_configs(path), False
        except Exception as exc:  # OSError, DecodeError: a damaged saved_model.pb or keras_metadata.pb
            text = str(exc).strip().splitlines()[0][:300] if str(exc).strip() else ""
            raise ModelFileError(f"{label}: is not a readable SavedModel: {type(exc).__name__}: {text}; "
                                 f"{RESAVE}") from None
        if problem:
            raise refuse(label, problem)
    elif path.name.endswith(".keras") and zipfile.is_zipfile(path):
        configs, lambdas_refused = [_keras_config(path)], True
    elif h5py.is_hdf5(path):
        configs, lambdas_refused = [_h5_config(path)], True
    else:
        what = "the file is empty" if path.stat().st_size == 0 else "it is neither a zip archive nor HDF5"
        raise ModelFileError(f"{label}: is not a Keras model file (.keras or .h5): {what}; {RESAVE}")
    for config in configs:
        if problem := config_problem(config, lambdas_refused):
            raise refuse(label, problem)


def refuse(label: str, problem: str) -> ModelFileError:
    """The error for a Keras model file bench-matrix will not load, because of what it holds."""
    return ModelFileError(f"{label}: bench-matrix loads Keras models in safe mode and refuses this one: "
                          f"{problem} (loading or running it could run code or touch files as the file "
                          f"dictates); {RESAVE}")


def _keras_config(path: Path) -> Any:
    """config.json of a .keras archive (None when tf_keras itself will say what is wrong)."""
    try:
        with zipfile.ZipFile(path) as archive:
            return json.loads(archive.read("config.json"))
    except (zipfile.BadZipFile, KeyError, ValueError, OSError, RecursionError):
        return None


def _h5_config(path: Path) -> Any:
    """The model_config attribute of a legacy .h5 file (None when tf_keras itself will say what is wrong)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            text = f.attrs.get("model_config")
        return json.loads(text.decode() if isinstance(text, bytes) else text) if text is not None else None
    except (OSError, ValueError, TypeError, RecursionError):
        return None


def config_problem(config: Any, lambdas_refused: bool) -> str | None:
    """The first Lambda layer (or, in a SavedModel, one that names a function), object from a module outside
    Keras, or dotted name (which reaches past a module's own objects) in a Keras config."""
    stack = [config]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            stack.extend(item)
            continue
        if not isinstance(item, dict):
            continue
        kind, inner, module = item.get("class_name"), item.get("config"), item.get("module")
        if kind == "__lambda__" or (kind == "Lambda" and isinstance(inner, dict) and (
                lambdas_refused or inner.get("function_type") != "lambda")):
            name = inner.get("name") if isinstance(inner, dict) else None
            return f"layer '{name}' is a Lambda layer (it calls a Python function the file names or holds)"
        if kind is not None and isinstance(module, str) and not _keras_module(module):
            return f"object '{kind}' comes from module '{module}', which is not Keras"
        named = inner if kind == "function" else kind
        if kind is not None and module is not None and isinstance(named, str) and "." in named:
            return f"object '{named}' of module '{module}' is not a Keras object"
        stack.extend(item.values())
    return None


def _keras_module(module: str) -> bool:
    return module in ("keras", "tf_keras", "builtins") or module.startswith(("keras.", "tf_keras."))


def saved_model_problem(directory: Path) -> str | None:
    """Why the SavedModel's graphs may not run, or None: TensorFlow 1 format (its loader runs graph nodes),
    operations that call Python or touch files, checkpoint operations outside TensorFlow's save functions."""
    from tensorflow.python.saved_model import loader_impl

    saved = loader_impl.parse_saved_model(str(directory))
    if len(saved.meta_graphs) != 1 or not saved.meta_graphs[0].HasField("object_graph_def"):
        return "it is a TensorFlow 1 SavedModel (not written by Keras 2)"
    meta = saved.meta_graphs[0]
    functions = {f.signature.name: f for f in meta.graph_def.library.function}
    savers = {name for name in functions if SAVER_FUNCTION.match(name)}
    for name, function in functions.items():
        for node in function.node_def:
            if problem := _node_problem(node, name in savers, savers):
                return f"its graph function '{name}' {problem}"
    for node in meta.graph_def.node:
        if problem := _node_problem(node, False, set()):
            return f"its graph {problem}"
    used = {f for n in meta.object_graph_def.nodes
            for f in (*n.function.concrete_functions, n.bare_concrete_function.concrete_function_name)}
    if called := sorted(used & savers):
        return f"its objects call checkpoint function '{called[0]}'"
    return None


def _node_problem(node: Any, in_saver: bool, savers: set[str]) -> str | None:
    """Why a graph node may not run: what it calls, or the saver function it calls from outside the saver."""
    if node.op in PYTHON_OPS:
        return f"calls operation {node.op}, which runs Python code"
    if node.op in FILE_OPS or (node.op in SAVER_OPS and not in_saver):
        return f"calls operation {node.op}, which reads or writes files"
    stream = node.attr["output_stream"].s if "output_stream" in node.attr else b""
    if node.op == "PrintV2" and stream.startswith(b"file:"):
        return f"calls operation PrintV2 into file {stream.decode(errors='replace')}"
    called = {node.op} | {a.func.name for a in node.attr.values()} | {
        f.name for a in node.attr.values() for f in a.list.func}
    if savers and (saver := sorted(called & savers)):
        return f"calls checkpoint function '{saver[0]}'"
    return None


def _saved_model_configs(directory: Path) -> list[Any]:
    """The Keras configs of a SavedModel's layers: keras_metadata.pb, or the older per-object metadata."""
    from tensorflow.python.saved_model import loader_impl
    from tf_keras.protobuf import saved_metadata_pb2

    texts: list[str] = []
    metadata = directory / "keras_metadata.pb"
    if metadata.is_file():
        parsed = saved_metadata_pb2.SavedMetadata()
        parsed.ParseFromString(metadata.read_bytes())
        texts = [node.metadata for node in parsed.nodes]
    else:
        nodes = loader_impl.parse_saved_model(str(directory)).meta_graphs[0].object_graph_def.nodes
        texts = [n.user_object.metadata for n in nodes if n.WhichOneof("kind") == "user_object"]
    configs = []
    for text in texts:
        try:
            configs.append(json.loads(text) if text else None)
        except (ValueError, RecursionError):
            configs.append(None)
    return configs
