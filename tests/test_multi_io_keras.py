"""The Keras-side backends (tensorflow, keras_predict, tflite, onnxruntime through tf2onnx, TF-TRT's serving
export) on a Keras model with two named inputs (float features, int64 token ids) and two outputs."""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("tensorflow")
TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_keras  # noqa: E402
from convert_helper import convert_with  # noqa: E402

from bench_matrix.backend import Backend  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.model_io import read_inputs  # noqa: E402
from bench_matrix.sources.tensorflow import tensorflow  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend  # noqa: E402
from bench_matrix_backends.tensorflow import KerasPredictBackend, TensorFlowBackend  # noqa: E402
from bench_matrix_backends.tflite import TFLiteBackend  # noqa: E402
from bench_matrix_backends.tftrt import SignatureSession, export_serving  # noqa: E402

BACKENDS: dict[str, Backend] = {"tensorflow": TensorFlowBackend(), "keras_predict": KerasPredictBackend(),
                                "tflite": TFLiteBackend(), "onnxruntime": OnnxRuntimeBackend()}
SPECS = (TensorSpec("features", (tiny_keras.FEATURES,)), TensorSpec("ids", (tiny_keras.TOKENS,), "int64"))
INPUTS = tiny_keras.token_data(24, 2)
# The calibration data covers the test inputs: int8 results then differ by rounding only.
CALIBRATION = {k: np.concatenate([v, tiny_keras.token_data(40, 1)[k]]) for k, v in INPUTS.items()}
CASES = [("tensorflow", "none", "fp32", {}), ("keras_predict", "none", "fp32", {}), ("tflite", "none", "fp32", {}),
         ("tflite", "none", "fp16", {}), ("tflite", "ptq_dynamic", "int8", {}), ("tflite", "ptq_static", "int8", {}),
         ("tflite", "ptq_static", "int8", {"io": "int8"}), ("onnxruntime", "none", "fp32", {}),
         ("onnxruntime", "ptq_static", "int8", {})]


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    path = tmp_path_factory.mktemp("keras") / "two.keras"
    tiny_keras.two_inputs_two_outputs().save(path)
    return SourceModel(name="two", framework="tensorflow", format="keras", path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(), inputs=SPECS)


@pytest.fixture(scope="module")
def expected(source: SourceModel) -> list[np.ndarray]:
    """The Keras model's own outputs, in its output order (zeta, alpha)."""
    outputs = source.load()([INPUTS["features"], INPUTS["ids"]], training=False)
    assert [o.shape[1] for o in outputs] == [1, 2]
    return [o.numpy() for o in outputs]


def _atol(precision: str, expected: np.ndarray) -> float:
    """fp32: summation order; fp16 weights: 2e-3 of the largest output (as in test_tflite); int8: 10% of the
    outputs' spread across inputs (a model that had lost an input's influence would be off by about 100%)."""
    if precision == "int8":
        return 0.1 * float(expected.std(axis=0).min())
    return {"fp32": 1e-5, "fp16": 2e-3}[precision] * max(1.0, float(np.abs(expected).max()))


def test_keras_model_says_its_inputs(source: SourceModel) -> None:
    assert read_inputs("tensorflow", "keras", source.path) == SPECS


@pytest.mark.parametrize(("backend", "kind", "precision", "options"), CASES,
                         ids=["-".join([c[0], c[1], c[2], *c[3].values()]) for c in CASES])
def test_every_output_of_every_input_matches_keras(backend: str, kind: str, precision: str, options: dict[str, Any],
                                                   source: SourceModel, expected: list[np.ndarray],
                                                   tmp_path: Path) -> None:
    meta = convert_with(CALIBRATION, BACKENDS[backend], source, tmp_path, kind, precision, **options)
    session = BACKENDS[backend].load(tmp_path, meta, "cpu", precision, 1)
    for n in (24, 1):  # a batch, and a single sample (a TFLite interpreter per batch size)
        got = session.predict({name: array[:n] for name, array in INPUTS.items()})
        assert [g.shape for g in got] == [e[:n].shape for e in expected] and all(g.dtype == np.float32 for g in got)
        for g, e in zip(got, expected):
            assert e.std(axis=0).min() > 0.1  # outputs that follow the inputs: the check is not vacuous
            np.testing.assert_allclose(g, e[:n], rtol=0, atol=_atol(precision, e))


def test_tflite_int8_io_quantises_the_float_input_only(source: SourceModel, tmp_path: Path) -> None:
    meta = convert_with(CALIBRATION, BACKENDS["tflite"], source, tmp_path, "ptq_static", "int8", io="int8")
    assert meta["inputs"] == ["features", "ids"] and meta["outputs"] == ["zeta", "alpha"]
    session = BACKENDS["tflite"].load(tmp_path, meta, "cpu", "int8", 1)
    info = session.info()
    assert [i["dtype"] for i in info["input"]] == ["int8", "int64"] and "scale" not in info["input"][1]
    assert [o["dtype"] for o in info["output"]] == ["int8", "int8"]
    features, ids = (array for _, array in session.prepare(INPUTS).inputs)
    assert features.dtype == np.int8 and ids.dtype == np.int64
    np.testing.assert_array_equal(ids, INPUTS["ids"])


def test_tftrt_serving_export_takes_every_input_and_returns_every_output(source: SourceModel,
                                                                         expected: list[np.ndarray],
                                                                         tmp_path: Path) -> None:
    """The CPU-runnable half of TF-TRT on the two-input model: its SavedModel signature and the session on it."""
    tf = tensorflow()
    export_serving(source.load(), SPECS, tmp_path / "serving")
    loaded = tf.saved_model.load(str(tmp_path / "serving"))
    function = loaded.signatures["serving_default"]
    assert sorted(function.structured_input_signature[1]) == ["input_0", "input_1"]
    assert sorted(function.structured_outputs) == ["output_0", "output_1"]
    got = SignatureSession(loaded, "/CPU:0", {}).predict(INPUTS)
    for g, e in zip(got, expected, strict=True):
        np.testing.assert_allclose(g, e, rtol=0, atol=1e-5)


def test_onnxruntime_quantisation_writes_nothing_where_it_runs(source: SourceModel, tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """ONNX Runtime's symbolic shape inference gives up on tf2onnx's int64 gathers and saves its partial model in the
    working directory; the backend runs it in a temporary one, and falls back to ONNX's shape inference."""
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    convert_with(CALIBRATION, BACKENDS["onnxruntime"], source, tmp_path / "out", "ptq_dynamic", "int8")
    assert list(here.iterdir()) == []
