"""PyTorch, TorchScript and ONNX Runtime on models with several named inputs (float features and int64 token ids)
and several outputs (a dict), against the module's own outputs; model IO read from ONNX and torch.export files."""

from __future__ import annotations

import hashlib
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_models  # noqa: E402
from convert_helper import convert_with  # noqa: E402

import torch  # noqa: E402

from bench_matrix.backend import Backend  # noqa: E402
from bench_matrix.sources import ModelFileError, SourceModel  # noqa: E402
from bench_matrix.sources.model_io import read_inputs  # noqa: E402
from bench_matrix.tensors import Inputs, TensorSpec  # noqa: E402
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend  # noqa: E402
from bench_matrix_backends.pytorch import PyTorchBackend  # noqa: E402
from bench_matrix_backends.torchscript import TorchScriptBackend  # noqa: E402

BACKENDS: dict[str, Backend] = {"pytorch": PyTorchBackend(), "torchscript": TorchScriptBackend(),
                                "onnxruntime": OnnxRuntimeBackend()}
TOKENS = tiny_models.token_data(24, 2)
TOKEN_SPECS = (TensorSpec("features", (tiny_models.FEATURES,)), TensorSpec("ids", (tiny_models.TOKENS,), "int64"))
IMAGES = {"image": tiny_models.images(24, 2)}
IMAGE_SPECS = (TensorSpec("image", tiny_models.INPUT_SHAPE),)
# The calibration data covers the test inputs: int8 results then differ by rounding only.
CALIBRATION = {"two_inputs": {k: np.concatenate([v, tiny_models.token_data(40, 1)[k]]) for k, v in TOKENS.items()},
               "two_outputs": {"image": np.concatenate([IMAGES["image"], tiny_models.images(40, 1)])}}
MODELS = {"two_inputs": (TOKEN_SPECS, TOKENS), "two_outputs": (IMAGE_SPECS, IMAGES)}
TRAINED = {"two_inputs": tiny_models.two_inputs, "two_outputs": tiny_models.fitted_two_outputs}
CASES = [("pytorch", "none", "fp32"), ("torchscript", "none", "fp32"), ("torchscript", "ptq_dynamic", "int8"),
         ("torchscript", "ptq_static", "int8"), ("onnxruntime", "none", "fp32"), ("onnxruntime", "none", "fp16"),
         ("onnxruntime", "ptq_dynamic", "int8"), ("onnxruntime", "ptq_static", "int8")]


def _source(path: Path, fmt: str, inputs: tuple[TensorSpec, ...], factory: str | None = None,
            framework: str = "pytorch") -> SourceModel:
    return SourceModel(name=path.stem, framework=framework, format=fmt, path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(), inputs=inputs, factory=factory,
                       python_path=(str(TESTS),))


@pytest.fixture(scope="module", params=list(MODELS))
def model(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, SourceModel]:
    """Each test model as a state_dict source (factory + weights)."""
    name = request.param
    path = tmp_path_factory.mktemp(name) / f"{name}.pt"
    torch.save(TRAINED[name]().state_dict(), path)
    return name, _source(path, "state_dict", MODELS[name][0], f"tiny_models:{name}")


def _expected(name: str, inputs: Inputs) -> list[np.ndarray]:
    """The module's own outputs: a tensor, or a dict's values by sorted key (the order sessions fetch in)."""
    module = TRAINED[name]()
    with torch.inference_mode():
        out = module(*(torch.from_numpy(a) for a in inputs.values()))
    return [out.numpy()] if isinstance(out, torch.Tensor) else [out[k].numpy() for k in sorted(out)]


def _atol(precision: str, expected: np.ndarray) -> float:
    """As in test_backends: fp32 summation order; fp16 1% of the largest output; int8 10% of the outputs' spread
    across inputs (a model that had lost an input's influence would be off by about 100%)."""
    if precision == "int8":
        return 0.1 * float(expected.std(axis=0).min())
    return {"fp32": 1e-5, "fp16": 1e-2}[precision] * float(np.abs(expected).max())


@pytest.mark.filterwarnings("ignore:All inputs of this cat operator")  # FX int8: the embedding stays float
@pytest.mark.parametrize(("backend", "kind", "precision"), CASES, ids=["-".join(c) for c in CASES])
def test_every_output_of_every_input_matches_the_module(backend: str, kind: str, precision: str,
                                                        model: tuple[str, SourceModel], tmp_path: Path) -> None:
    name, source = model
    inputs = MODELS[name][1]
    meta = convert_with(CALIBRATION[name], BACKENDS[backend], source, tmp_path, kind, precision)
    session = BACKENDS[backend].load(tmp_path, meta, "cpu", precision, 1)
    expected = _expected(name, inputs)
    got = session.predict(inputs)
    assert [g.shape for g in got] == [e.shape for e in expected] and all(g.dtype == np.float32 for g in got)
    for g, e in zip(got, expected):
        assert e.std(axis=0).min() > 0.1  # outputs that follow the inputs: the check is not vacuous
        np.testing.assert_allclose(g, e, rtol=0, atol=_atol(precision, e))
    if backend == "onnxruntime":
        assert meta["inputs"] == {spec.name: spec.name for spec in source.inputs}
        _assert_graph_io(tmp_path / meta["file"], source.inputs, len(expected))


def _assert_graph_io(path: Path, specs: tuple[TensorSpec, ...], outputs: int) -> None:
    """The ONNX graph takes the source's inputs by name and dtype (int64 ids stay int64 when quantised), with a
    dynamic batch axis, and returns output_0.. ."""
    import onnx

    model = onnx.load(str(path))
    inputs = [i for i in model.graph.input if i.name not in {t.name for t in model.graph.initializer}]
    assert [(i.name, onnx.helper.tensor_dtype_to_np_dtype(i.type.tensor_type.elem_type).name) for i in inputs] == [
        (s.name, s.dtype) for s in specs]
    assert all(i.type.tensor_type.shape.dim[0].dim_param for i in inputs)
    assert [o.name for o in model.graph.output] == [f"output_{i}" for i in range(outputs)]


def test_int8_static_quantises_the_float_path_only(model: tuple[str, SourceModel], tmp_path: Path) -> None:
    """The token ids feed the calibration unquantised; the dense layers behind them are int8."""
    import onnx

    name, source = model
    meta = convert_with(CALIBRATION[name], BACKENDS["onnxruntime"], source, tmp_path, "ptq_static", "int8")
    assert meta["quantization"]["calibration_samples"] == 64
    graph = onnx.load(str(tmp_path / meta["file"])).graph
    quantised = {n.input[0] for n in graph.node if n.op_type == "QuantizeLinear"}
    assert "ids" not in quantised and (name != "two_inputs" or "features" in quantised)


def test_torch_float_casts_leave_integer_inputs_alone(model: tuple[str, SourceModel], tmp_path: Path) -> None:
    name, source = model
    meta = convert_with(CALIBRATION[name], BACKENDS["pytorch"], source, tmp_path)
    prepared = BACKENDS["pytorch"].load(tmp_path, meta, "cpu", "fp32", 1).prepare(MODELS[name][1])
    assert [t.dtype for t in prepared] == [getattr(torch, s.dtype) for s in source.inputs]


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """two_inputs as a torch.export program with a dynamic batch axis."""
    path = tmp_path_factory.mktemp("exported") / "two_inputs.pt2"
    example = tuple(torch.from_numpy(a[:4]) for a in TOKENS.values())
    batch = torch.export.Dim("batch")
    torch.export.save(torch.export.export(tiny_models.two_inputs(), example,
                                          dynamic_shapes=({0: batch}, {0: batch})), str(path))
    return path


def test_torch_export_program_says_its_inputs(exported: Path, tmp_path: Path) -> None:
    inputs = read_inputs("pytorch", "torch_export", exported)
    assert inputs == TOKEN_SPECS
    source = _source(exported, "torch_export", inputs)
    expected = _expected("two_inputs", TOKENS)[0]
    for backend in ("pytorch", "onnxruntime"):
        meta = convert_with(CALIBRATION["two_inputs"], BACKENDS[backend], source, tmp_path / backend)
        (got,) = BACKENDS[backend].load(tmp_path / backend, meta, "cpu", "fp32", 1).predict(TOKENS)
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5)


def test_onnx_file_says_its_inputs_and_feeds_them_by_name(tmp_path: Path) -> None:
    """Graph inputs with free axes (a dynamic batch, a dynamic sequence length) read as None; a source declaring
    the inputs in another order than the graph's still feeds each by its name."""
    path = tmp_path / "two_inputs.onnx"
    example = tuple(torch.from_numpy(a[:2]) for a in TOKENS.values())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(tiny_models.two_inputs(), example, str(path), dynamo=False, input_names=["features", "ids"],
                          dynamic_axes={"features": {0: "n"}, "ids": {0: "n", 1: "length"}})
    inputs = read_inputs("onnx", "onnx", path)
    assert inputs == (TensorSpec("features", (6,)), TensorSpec("ids", (None,), "int64"))
    reordered = _source(path, "onnx", inputs[::-1], framework="onnx")
    meta = convert_with(CALIBRATION["two_inputs"], BACKENDS["onnxruntime"], reordered, tmp_path / "artifact")
    assert meta["inputs"] == {"ids": "ids", "features": "features"}
    session = BACKENDS["onnxruntime"].load(tmp_path / "artifact", meta, "cpu", "fp32", 1)
    (got,) = session.predict({"ids": TOKENS["ids"], "features": TOKENS["features"]})
    np.testing.assert_allclose(got, _expected("two_inputs", TOKENS)[0], rtol=0, atol=1e-5)


def test_onnx_inputs_not_declared_one_for_one_are_refused(tmp_path: Path, source: SourceModel) -> None:
    path = tmp_path / "tiny.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(source.load(), (torch.from_numpy(IMAGES["image"][:2]),), str(path), dynamo=False)
    two = _source(path, "onnx", TOKEN_SPECS, framework="onnx")
    with pytest.raises(ModelFileError, match="the ONNX model has 1 inputs .* but 2 are declared"):
        convert_with(CALIBRATION["two_inputs"], BACKENDS["onnxruntime"], two, tmp_path / "out")


@pytest.mark.parametrize(("framework", "fmt"), [("pytorch", "state_dict"), ("pytorch", "torchscript")])
def test_files_that_do_not_say_their_inputs(framework: str, fmt: str, tmp_path: Path) -> None:
    assert read_inputs(framework, fmt, tmp_path / "any.pt") is None


def test_reading_inputs_of_a_damaged_file_names_it(tmp_path: Path) -> None:
    path = tmp_path / "broken.onnx"
    path.write_bytes(b"\x89PNG not a model")
    with pytest.raises(ModelFileError, match=f"{path}: is not a valid ONNX model: it is a PNG image"):
        read_inputs("onnx", "onnx", path)


def test_static_int8_of_a_buffer_sliced_by_the_sequence_length(tmp_path: Path) -> None:
    """torch.ao's FX tracer traces a buffer sliced by a traced size (BERT's position_ids[:, :seq_len]), which
    it sliced in Python before ('slice indices must be integers'): the int8 module follows the float one."""
    path = tmp_path / "positions.pt"
    torch.save(tiny_models.positions().state_dict(), path)
    ids = {"ids": TOKENS["ids"]}
    source = _source(path, "state_dict", (TOKEN_SPECS[1],), "tiny_models:positions")
    calibration = tiny_models.token_data(64, 1)["ids"]
    meta = convert_with(calibration, BACKENDS["torchscript"], source, tmp_path / "int8", "ptq_static", "int8")
    (got,) = BACKENDS["torchscript"].load(tmp_path / "int8", meta, "cpu", "int8", 1).predict(ids)
    with torch.inference_mode():
        expected = tiny_models.positions()(torch.from_numpy(ids["ids"])).numpy()
    assert expected.std(axis=0).min() > 0.01  # outputs that follow the ids: the check is not vacuous
    for column in range(expected.shape[1]):  # int8 rounding moves each output little against its spread
        assert np.corrcoef(got[:, column], expected[:, column])[0, 1] > 0.95
