"""Hostile and broken model files: nothing in them runs, and each refusal names the user's file and why."""

from __future__ import annotations

import io
import json
import os
import sys
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import torch

from conftest import TESTS, cli

sys.path.insert(0, str(TESTS))
import tiny_models  # noqa: E402

from bench_matrix.errors import UserError  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.onnx_file import load_onnx  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:You are saving your model as an HDF5 file")
X = torch.from_numpy(tiny_models.images(4, 5))
MODEL_JSON = "models/model.json"


class Payload:
    """Unpickling this writes `marker`: what a hostile pickle in a user's file would do."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self) -> tuple[Any, ...]:
        return exec, (f"import pathlib; pathlib.Path({self.marker!r}).write_text('pwned')",)


def _pickle(marker: Path) -> bytes:
    buffer = io.BytesIO()
    torch.save(Payload(marker), buffer)
    return buffer.getvalue()


def _source(path: Path, fmt: str, framework: str = "pytorch", **extra: Any) -> SourceModel:
    return SourceModel(name="m", framework=framework, format=fmt, path=path, sha256="not checked here",
                       input_shape=tiny_models.INPUT_SHAPE, **extra)


def _factory_source(path: Path, factory: str = "tiny_models:tiny", where: Path = TESTS) -> SourceModel:
    return _source(path, "state_dict", factory=factory, python_path=(str(where),))


def _refused(source: SourceModel, *expected: str) -> None:
    """Loading `source` raises a UserError whose message holds each expected text, and no unsafe advice."""
    with pytest.raises(UserError) as caught:
        _load(source)
    message = str(caught.value)
    assert all(text in message for text in expected), message
    assert "weights_only=False" not in message and "Traceback" not in message


def _load(source: SourceModel) -> Any:
    """The source's framework object; for ONNX, the model as bench-matrix reads it."""
    return load_onnx(source.path, source.label) if source.framework == "onnx" else source.load()


def _rewrite(src: Path, dst: Path, change: Callable[[str, bytes], bytes], extra: dict[str, bytes]) -> Path:
    """Copy a zip archive entry by entry through `change` (names below a torch archive's root folder),
    adding `extra` entries."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        root = zin.namelist()[0].split("/")[0] if src.suffix == ".pt2" else ""
        for info in zin.infolist():
            zout.writestr(info.filename, change(info.filename.removeprefix(f"{root}/"), zin.read(info)))
        for name, data in extra.items():
            zout.writestr(f"{root}/{name}", data)
    return dst


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, torch.nn.Module]:
    """tiny_models.fitted() exported with a dynamic batch (its shapes are then sympy expressions), saved."""
    module = tiny_models.fitted()
    path = tmp_path_factory.mktemp("exported") / "tiny.pt2"
    program = torch.export.export(module, (X,), dynamic_shapes=({0: torch.export.Dim("batch", max=64)},))
    torch.export.save(program, str(path))
    return path, module


def test_exported_program_loads_and_runs(exported: tuple[Path, torch.nn.Module]) -> None:
    path, module = exported
    with torch.no_grad():
        torch.testing.assert_close(_source(path, "torch_export").load()(X), module(X))


def _pickled_weight(name: str, data: bytes, marker: Path) -> bytes:
    if name == "data/weights/model_weights_config.json":
        config = json.loads(data)
        next(iter(config["config"].values()))["use_pickle"] = True
        return json.dumps(config).encode()
    return _pickle(marker) if name == "data/weights/weight_0" else data


def _in_program(old: bytes, new: Callable[[Path], bytes]) -> Callable[[str, bytes, Path], bytes]:
    """A change that replaces `old` in the program's JSON."""
    return lambda name, data, marker: data.replace(old, new(marker)) if name == MODEL_JSON else data


def _code(marker: Path) -> str:
    return f"__import__('pathlib').Path({str(marker)!r}).write_text('pwned')"


HOSTILE_EXPORTS = {  # how a real archive is changed, entries added to it, and what the refusal says
    "pickled_weight": (_pickled_weight, {}, "stores weight '0.weight' as a pickled object"),
    "pickled_sample_inputs": (lambda n, d, m: _pickle(m) if n == "data/sample_inputs/model.pt" else d, {},
                              "sample inputs (data/sample_inputs/model.pt) hold pickled objects"),
    "legacy_pickled_constants": (lambda n, d, m: d, {"data/constants/model.pt": b"TORCH"},
                                 "stores its constants as a pickle"),
    "shape_expression_code": (_in_program(b"Symbol(", lambda m: json.dumps(_code(m))[1:-1].encode() + b" or "
                                                                   b"Symbol("), {},
                              "is not plain arithmetic on symbols"),
    "file_operator": (_in_program(b"aten.relu.default", lambda m: b"aten.save.default"), {},
                      "operator torch.ops.aten.save.default, which reads or writes files"),
    "aot_compiled_code": (lambda n, d, m: d, {"data/aotinductor/model/model.so": b"\x7fELF"}, "AOTInductor"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE_EXPORTS))
def test_hostile_exported_programs_are_refused(case: str, exported: tuple[Path, torch.nn.Module],
                                               tmp_path: Path) -> None:
    change, extra, expected = HOSTILE_EXPORTS[case]
    marker = tmp_path / "marker"
    path = _rewrite(exported[0], tmp_path / "hostile.pt2", lambda n, d: change(n, d, marker),
                    {name: _pickle(marker) if data == b"TORCH" else data for name, data in extra.items()})
    _refused(_source(path, "torch_export"), f"{path}: ", expected, "torch.export.save")
    assert not marker.exists()


def test_guard_code_in_an_exported_program_never_runs(exported: tuple[Path, torch.nn.Module],
                                                      tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    code = json.dumps({"guards_code": [_code(marker)]})[1:-1].encode()
    guard = _in_program(b'"guards_code": []', lambda m: code)
    path = _rewrite(exported[0], tmp_path / "guarded.pt2", lambda n, d: guard(n, d, marker), {})
    assert _code(marker).encode() in zipfile.ZipFile(path).read(f"tiny/{MODEL_JSON}")
    with torch.no_grad():
        torch.testing.assert_close(_source(path, "torch_export").load()(X), exported[1](X))
    assert not marker.exists()


class WritesOnLoad(torch.nn.Module):
    """A TorchScript module whose __setstate__ (run by torch.jit.load) writes a file with ATen's save."""

    def __init__(self, marker: str):
        super().__init__()
        self.marker, self.weight = marker, torch.ones(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.weight

    @torch.jit.export
    def __getstate__(self) -> tuple[str, torch.Tensor, bool]:
        return self.marker, self.weight, self.training

    @torch.jit.export
    def __setstate__(self, state: tuple[str, torch.Tensor, bool]) -> None:
        torch.save([state[1]], state[0])
        self.marker, self.weight, self.training = state


def test_torchscript_loads_and_one_that_writes_files_is_refused(tmp_path: Path) -> None:
    module = tiny_models.fitted()
    torch.jit.save(torch.jit.script(module), str(tmp_path / "tiny.pt"))
    with torch.no_grad():
        torch.testing.assert_close(_source(tmp_path / "tiny.pt", "torchscript").load()(X), module(X))
    marker, hostile = tmp_path / "marker", tmp_path / "hostile.pt"
    torch.jit.save(torch.jit.script(WritesOnLoad(str(marker))), str(hostile))
    _refused(_source(hostile, "torchscript"), f"{hostile}: its TorchScript code",
             "calls operator 'save', which reads or writes files", "torch.jit.save")
    assert not marker.exists()


@pytest.mark.parametrize(("case", "expected"), [
    ("state_dict", "it is a torch.save file (a state_dict? give it as factory + weights"),
    ("truncated", "is not a TorchScript archive: RuntimeError: PytorchStreamReader failed reading zip"),
])
def test_torchscript_of_the_wrong_kind_is_named(case: str, expected: str, tmp_path: Path) -> None:
    path = tmp_path / "model.pt"
    torch.save(tiny_models.tiny().state_dict(), path)
    if case == "truncated":
        path.write_bytes(path.read_bytes()[:300])
    _refused(_source(path, "torchscript"), f"{path}: ", expected)


FACTORIES = '''
import torch
def raises():
    raise RuntimeError("boom in the factory")
def not_a_module():
    return {"weight": 1}
def bigger():
    return torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Linear(8, 2))
def wider():
    return torch.nn.Sequential(torch.nn.Linear(4, 16))
'''


@pytest.fixture(scope="module")
def factories(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Factory modules (one whose import fails) and two weights files, in a python_path folder."""
    root = tmp_path_factory.mktemp("factories")
    (root / "model_file_factories.py").write_text(FACTORIES)
    (root / "model_file_broken.py").write_text("import no_such_module_anywhere\n")
    torch.save(torch.nn.Sequential(torch.nn.Linear(4, 8)).state_dict(), root / "small.pt")
    torch.save({"encoder.weight": torch.ones(8, 4), "0.weight": torch.ones(8, 4)}, root / "other.pt")
    return root


@pytest.mark.parametrize(("factory", "expected"), [
    ("model_file_factories:raises", "factory 'model_file_factories:raises' failed: RuntimeError: boom"),
    ("model_file_factories:not_a_module", "factory 'model_file_factories:not_a_module' returned a dict, "
                                          "not a torch.nn.Module"),
    ("model_file_factories:absent", "module 'model_file_factories'"),
    ("model_file_broken:build", "importing module 'model_file_broken' failed: ModuleNotFoundError"),
])
def test_factory_failures_say_the_factory_failed(factory: str, expected: str, factories: Path) -> None:
    _refused(_factory_source(factories / "small.pt", factory, factories), expected)


def test_weights_that_do_not_match_the_factory_name_file_factory_and_keys(factories: Path) -> None:
    small, bigger = factories / "small.pt", "model_file_factories:bigger"
    _refused(_factory_source(small, bigger, factories), f"{small} (weights for factory '{bigger}')",
             "missing keys 1.weight, 1.bias")
    _refused(_factory_source(small), "missing keys 0.running_mean, 0.running_var, 0.num_batches_tracked, "
                                     "1.weight, 1.bias ... and 6 more")
    _refused(_factory_source(factories / "other.pt", bigger, factories),
             "missing keys 0.bias, 1.weight, 1.bias; unexpected keys encoder.weight; save model.state_dict()")
    _refused(_factory_source(small, "model_file_factories:wider", factories),
             "does not fit the module the factory builds: size mismatch for 0.weight")


@pytest.mark.parametrize(("case", "expected"), [
    ("pickled_object", "holds pickled objects other than tensors (it refers to exec), and bench-matrix will "
                       "not unpickle them"),
    ("whole_module", "(it refers to torch.nn.modules.container.Sequential)"),
    ("empty", "is not a weights file torch.load can read (the file is empty)"),
    ("truncated", "is not a weights file torch.load can read"),
])
def test_unsafe_or_unreadable_weights_are_refused(case: str, expected: str, tmp_path: Path) -> None:
    path, marker = tmp_path / "weights.pt", tmp_path / "marker"
    torch.save(tiny_models.tiny() if case == "whole_module" else tiny_models.tiny().state_dict(), path)
    if case == "pickled_object":
        path.write_bytes(_pickle(marker))
    elif case in ("empty", "truncated"):
        path.write_bytes(path.read_bytes()[:0 if case == "empty" else 200])
    _refused(_factory_source(path), f"{path}: ", expected, "torch.save(model.state_dict(), path)")
    assert not marker.exists()


def test_messages_about_a_fine_tuned_copy_name_the_users_file(tmp_path: Path) -> None:
    (tmp_path / "copy.pt").write_bytes(b"")
    source = _source(tmp_path / "copy.pt", "state_dict", factory="tiny_models:tiny",
                     python_path=(str(TESTS),), origin="/home/user/weights.pt")
    _refused(source, f"/home/user/weights.pt (fine-tuned copy {tmp_path / 'copy.pt'}): is not a weights file")
    assert SourceModel.from_dict(source.to_dict()) == source


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
    _refused(_source(path, "onnx", "onnx"), expected, "inside the model's directory",
             f"{path}: tensor 'w' keeps its data in external file '{location}'")


def test_onnx_external_data_inside_the_model_directory_is_read(tmp_path: Path) -> None:
    (tmp_path / "w.bin").write_bytes(np.full(4, 3, np.float32).tobytes())
    model = _load(_source(_onnx_model(tmp_path / "m.onnx", "w.bin"), "onnx", "onnx"))
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
    _refused(_source(path, "onnx", "onnx"), f"{path}: is not a valid ONNX model: ", expected,
             "export the model")


@pytest.mark.slow
def test_run_fails_broken_and_hostile_model_cells_naming_the_files(
        tiny_project: Path, exported: tuple[Path, torch.nn.Module]) -> None:
    marker = tiny_project / "marker"
    (tiny_project / "broken.onnx").write_bytes(b"\x08\x07garbage")
    _rewrite(exported[0], tiny_project / "hostile.pt2", lambda n, d: _pickled_weight(n, d, marker), {})
    (tiny_project / "m.yaml").write_text(
        "models:\n  - {name: broken, framework: onnx, file: broken.onnx}\n"
        "  - {name: hostile, framework: pytorch, file: hostile.pt2}\n"
        "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "axes: {backend: [onnxruntime], strategy: [none], precision: [fp32], target: [cpu]}\n"
        "settings: {timeout_s: 120}\n")
    run = cli(tiny_project, "run", "m.yaml")
    output = run.stdout + run.stderr
    assert run.returncode == 0 and "0 ok, 0 skipped, 2 failed" in output and "Traceback" not in output, output
    reasons = {r["cell"]["model"]: r["reason"]
               for r in json.loads(cli(tiny_project, "report", "--format", "json").stdout)}
    assert f"{tiny_project / 'broken.onnx'}: is not a valid ONNX model" in reasons["broken"]
    assert f"{tiny_project / 'hostile.pt2'}: it stores weight" in reasons["hostile"]
    assert "File \"" not in "".join(reasons.values()) and not marker.exists()


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
    writes = eval(f"lambda t: ({_code(marker)}, t)[1]")  # noqa: S307 - a lambda Keras stores as bytecode
    model = _keras_model(keras_module, keras_module.layers.Lambda(writes, name="writer"))
    model.save(tmp_path / "saved.h5" if name.startswith("hdf5") else path)
    if name.startswith("hdf5"):  # an HDF5 file named .keras: tf_keras reads it as .h5
        (tmp_path / "saved.h5").rename(path)
    marker.unlink()  # building the model called the lambda
    _refused(_source(path, "keras", "tensorflow"), f"{path}: bench-matrix loads Keras models in safe mode",
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
    _rewrite(saved, hostile, lambda n, d: d.replace(relu, named), {})
    assert relu not in zipfile.ZipFile(hostile).read("config.json")
    _refused(_source(hostile, "keras", "tensorflow"), f"{hostile}: ", expected)


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
    _refused(_source(path, "saved_model", "tensorflow"), expected,
             f"{path}: bench-matrix loads Keras models in safe mode")
    assert not marker.exists()
