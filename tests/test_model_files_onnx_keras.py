"""Hostile and broken ONNX and Keras model files: nothing in them runs (external data stays inside the
model's folder, no Lambda or foreign objects, no graph that touches files or Python), and each refusal names
the file."""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from model_file_helpers import load_source, make_source, payload_code, refused, rewrite_zip

pytestmark = pytest.mark.filterwarnings("ignore:You are saving your model as an HDF5 file")


def _onnx_model(path: Path, location: str | None = None) -> Path:
    """A one-MatMul ONNX model (N,2) -> (N,2); with `location`, its weights are external data there."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    weights = numpy_helper.from_array(np.eye(2, dtype=np.float32), "w")
    if location is not None:
        weights.ClearField("raw_data")
        weights.data_location = TensorProto.EXTERNAL
        entry = weights.external_data.add()
        entry.key, entry.value = "location", location
    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 2])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 2])], [weights])
    onnx.save(helper.make_model(graph), str(path))
    return path


@pytest.mark.parametrize(("location", "expected"), [
    ("../outside/secret.bin", "climbs out of the model's directory"),
    ("ABSOLUTE", "which is not a relative path"),
    ("link.bin", "which is a symbolic link"),
    ("pipe.bin", "which is not a regular file"),
    ("missing.bin", "which cannot be found"),
])
def test_onnx_external_data_outside_the_model_directory_is_refused(location: str, expected: str,
                                                                   tmp_path: Path) -> None:
    (tmp_path / "outside").mkdir()
    (tmp_path / "model").mkdir()
    secret = tmp_path / "outside" / "secret.bin"
    secret.write_bytes(np.full(4, 7, np.float32).tobytes())
    (tmp_path / "model" / "link.bin").symlink_to(secret)
    os.mkfifo(tmp_path / "model" / "pipe.bin")  # reading it would block: it must not be opened
    location = str(secret) if location == "ABSOLUTE" else location
    path = _onnx_model(tmp_path / "model" / "m.onnx", location)
    refused(make_source(path, "onnx", "onnx"), expected, "inside the model's directory",
            f"{path}: tensor 'w' keeps its data in external file '{location}'")


def test_onnx_external_data_inside_the_model_directory_is_read(tmp_path: Path) -> None:
    (tmp_path / "w.bin").write_bytes(np.full(4, 3, np.float32).tobytes())
    model = load_source(make_source(_onnx_model(tmp_path / "m.onnx", "w.bin"), "onnx", "onnx"))
    assert np.frombuffer(model.graph.initializer[0].raw_data, np.float32).tolist() == [3.0] * 4


@pytest.mark.parametrize(("content", "expected"), [
    (lambda good: good[: len(good) // 2], "Wire format was corrupt"),
    (lambda good: b"", "the file is empty"),
    (lambda good: b"PK\x03\x04" + good, "it is a zip archive (a PyTorch .pt/.pt2 or Keras .keras file?)"),
    (lambda good: b"\x89HDF\r\n\x1a\n" + bytes(64), "it is an HDF5 file (a Keras .h5 file?)"),
])
def test_broken_onnx_files_are_named(content: Callable[[bytes], bytes], expected: str,
                                     tmp_path: Path) -> None:
    path = tmp_path / "m.onnx"
    path.write_bytes(content(_onnx_model(tmp_path / "good.onnx").read_bytes()))
    refused(make_source(path, "onnx", "onnx"), f"{path}: is not a valid ONNX model: ", expected,
            "export the model")


@pytest.fixture(scope="module")
def keras_module() -> Any:
    pytest.importorskip("tensorflow")
    from bench_matrix.sources.tensorflow import keras

    return keras()


def _keras_model(k: Any, middle: Any) -> Any:
    return k.Sequential([k.layers.Input((4,)), middle, k.layers.Dense(2)])


@pytest.mark.parametrize("name", ["lambda.keras", "lambda.h5", "hdf5_named.keras"])
def test_keras_lambda_layers_are_refused(name: str, keras_module: Any, tmp_path: Path) -> None:
    marker, path = tmp_path / "marker", tmp_path / name
    writes = eval(f"lambda t: ({payload_code(marker)}, t)[1]")  # noqa: S307 - Keras stores it as bytecode
    model = _keras_model(keras_module, keras_module.layers.Lambda(writes, name="writer"))
    model.save(tmp_path / "saved.h5" if name.startswith("hdf5") else path)
    if name.startswith("hdf5"):  # an HDF5 file named .keras: tf_keras reads it as .h5
        (tmp_path / "saved.h5").rename(path)
    marker.unlink()  # building the model called the lambda
    refused(make_source(path, "keras", "tensorflow"), f"{path}: bench-matrix loads Keras models in safe mode",
            "layer 'writer' is a Lambda layer")
    assert not marker.exists()


@pytest.mark.parametrize(("activation", "expected"), [
    ({"module": "os", "class_name": "function", "config": "system", "registered_name": "system"},
     "object 'function' comes from module 'os', which is not Keras"),
    ({"module": "tf_keras.src.backend", "class_name": "function", "config": "tf.print"},
     "object 'tf.print' of module 'tf_keras.src.backend' is not a Keras object"),
])
def test_keras_configs_naming_objects_outside_keras_are_refused(activation: dict, expected: str,
                                                                keras_module: Any, tmp_path: Path) -> None:
    saved, hostile = tmp_path / "plain.keras", tmp_path / "hostile.keras"
    _keras_model(keras_module, keras_module.layers.Dense(3, activation="relu")).save(saved)
    relu, named = b'"activation": "relu"', b'"activation": ' + json.dumps(activation).encode()
    rewrite_zip(saved, hostile, lambda n, d: d.replace(relu, named), {})
    assert relu not in zipfile.ZipFile(hostile).read("config.json")
    refused(make_source(hostile, "keras", "tensorflow"), f"{hostile}: ", expected)


def _writes_file(t: Any, path: str) -> Any:
    """A layer body whose graph holds a WriteFile operation."""
    import tensorflow as tf

    with tf.control_dependencies([tf.io.write_file(path, "pwned")]):
        return tf.identity(t)


def _calls_python(t: Any, path: str) -> Any:
    """A layer body whose graph calls back into Python (tf.py_function)."""
    import tensorflow as tf

    result = tf.py_function(lambda x: (Path(path).write_text("pwned"), x)[1], [t], tf.float32)
    return tf.ensure_shape(result, t.shape)


@pytest.mark.parametrize(("body", "expected"), [
    (_writes_file, "calls operation WriteFile, which reads or writes files"),
    (_calls_python, "calls operation EagerPyFunc, which runs Python code"),
])
def test_keras_saved_models_whose_graphs_touch_files_or_python_are_refused(body: Callable, expected: str,
                                                                           keras_module: Any,
                                                                           tmp_path: Path) -> None:
    marker, path = tmp_path / "marker", tmp_path / "saved_model"
    layer = keras_module.layers.Lambda(body, arguments={"path": str(marker)})
    _keras_model(keras_module, layer).save(path, save_format="tf")
    marker.unlink(missing_ok=True)
    refused(make_source(path, "saved_model", "tensorflow"), expected,
            f"{path}: bench-matrix loads Keras models in safe mode")
    assert not marker.exists()
