"""The tflite backend against real TensorFlow Lite: every mode on a tiny trained Keras model, sizes, options."""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_keras  # noqa: E402
from convert_helper import convert_with  # noqa: E402

from bench_matrix.backend import Session  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.tensorflow import keras, tensorflow  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402
from bench_matrix_backends.tflite import TFLiteBackend, interpreter_class  # noqa: E402

BACKEND = TFLiteBackend()
X = tiny_keras.images(32, 2)
# The calibration set covers the test inputs, so that int8 results are compared for rounding only, not for
# clipping beyond the calibrated range (that is what the benchmark's accuracy metric measures).
CALIBRATION = np.concatenate([X, tiny_keras.images(24, 1)])
# mode -> (strategy kind, precision, strategy options)
MODES: dict[str, tuple[str, str, dict[str, Any]]] = {
    "fp32": ("none", "fp32", {}), "fp16": ("none", "fp16", {}), "dynamic_range": ("ptq_dynamic", "int8", {}),
    "integer_float_fallback": ("ptq_static", "int8", {}), "full_integer": ("ptq_static", "int8", {"io": "int8"})}
Build = Callable[[str], tuple[Path, dict[str, Any]]]


def _source(path: Path, input_shape: tuple[int, ...]) -> SourceModel:
    return SourceModel(name=path.stem, framework="tensorflow", format="keras", path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(), inputs=(TensorSpec("input", input_shape),))


def _convert(source: SourceModel, out: Path, kind: str, precision: str, calibration: np.ndarray = CALIBRATION,
             **options: Any) -> dict[str, Any]:
    out.mkdir(parents=True)
    return convert_with(calibration, BACKEND, source, out, kind, precision, **options)


def _predict(session: Session, x: np.ndarray) -> np.ndarray:
    """The one output of a single-input model for `x`."""
    (out,) = session.predict({"input": x})
    return out


def _load(out: Path, meta: dict[str, Any], precision: str = "fp32", threads: int = 1) -> Session:
    return BACKEND.load(out, meta, "cpu", precision, threads)


@pytest.fixture(scope="module")
def source(tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    """The tiny model fitted to colour balance, so that its outputs follow its input."""
    path = tiny_keras.save_trained(tmp_path_factory.mktemp("source") / "tiny.keras")
    return _source(path, tiny_keras.INPUT_SHAPE)


@pytest.fixture(scope="module")
def model(source: SourceModel) -> Any:
    return source.load()


@pytest.fixture(scope="module")
def reference(model: Any) -> np.ndarray:
    y = model(X, training=False).numpy()
    assert y.std(axis=0).min() > 0.2  # the outputs do follow the input
    return y


@pytest.fixture(scope="module")
def build(source: SourceModel, tmp_path_factory: pytest.TempPathFactory) -> Build:
    """Converts the tiny model in a mode once per module: mode -> (artifact directory, meta)."""
    built: dict[str, tuple[Path, dict[str, Any]]] = {}

    def get(mode: str) -> tuple[Path, dict[str, Any]]:
        if mode not in built:
            kind, precision, options = MODES[mode]
            out = tmp_path_factory.mktemp("artifacts") / mode
            built[mode] = out, _convert(source, out, kind, precision, **options)
        return built[mode]

    return get


def _tensors(session: Session) -> list[dict[str, Any]]:
    return session.prepare({"input": X[:1]}).interpreter.get_tensor_details()


def _dynamic_range_atol(model: Any) -> float:
    """Dynamic range: only the 72x16 dense kernel W1 is int8 (per output channel, step s_w = max|W1[:, j]| / 127)
    and its input a is quantised at run time, per sample (step at most s_a = max|a| / 127). With each rounding
    error uniform over +-step/2 (variance step^2 / 12) and independent, output k's error has variance
    s_a^2/12 * sum_i (W1 D W2)_ik^2 + sum_i a_i^2 * sum_j s_wj^2/12 * (D W2)_jk^2, D the ReLU mask; the bound is
    5 standard deviations of the worst output (the all-errors-aligned bound, 0.47, would test nothing)."""
    k = keras()
    a = k.Model(model.inputs, model.layers[3].output)(X).numpy()  # the flattened input of the int8 layer
    active = k.Model(model.inputs, model.layers[4].output)(X).numpy() > 0
    w1, w2 = model.layers[4].kernel.numpy(), model.layers[5].kernel.numpy()
    s_a, s_w = np.abs(a).max(axis=1, keepdims=True) / 127, np.abs(w1).max(axis=0) / 127
    paths = w2[None] * active[:, :, None]  # (sample, hidden unit, output): how each unit reaches each output
    var_a = s_a ** 2 / 12 * (np.einsum("ij,njk->nik", w1, paths) ** 2).sum(axis=1)
    var_w = (a ** 2).sum(axis=1, keepdims=True) / 12 * np.einsum("j,njk->nk", s_w ** 2, paths ** 2)
    return 5 * float(np.sqrt(var_a + var_w).max()) + 1e-5  # + float32 summation-order noise


def _output_step(session: Session) -> float:
    """The scale of the model's int8 output tensor (before the float-fallback model dequantises it)."""
    shape = list(session.prepare({"input": X[:1]}).interpreter.get_output_details()[0]["shape"])
    (scale,) = [d["quantization"][0] for d in _tensors(session) if d["dtype"] == np.int8 and list(d["shape"]) == shape]
    return scale


def _atol(mode: str, session: Session, model: Any, reference: np.ndarray) -> float:
    """fp32: the same arithmetic up to summation order. fp16: only the weights are float16 (each rounded by at most
    2^-11 = 4.9e-4 of itself) and the arithmetic stays float32; a layer's output moves by at most 2^-11 of the
    sum of its terms' magnitudes, and four weighted layers compound that: 2e-3 (4 x 2^-11) of the largest output
    (observed: 6e-4). Integer modes: six int8 activation tensors lie on the path (input, batch norm, two
    convolutions, dense, output), each rounded by at most half its step; min/max calibration maps each layer's
    range onto the next one's, so each rounding moves the output by about half an output step or less, and
    per-channel weight rounding (1/254 of a channel's largest weight) adds a fraction of a step: 3 output steps
    in all (observed: about 1)."""
    if mode in ("integer_float_fallback", "full_integer"):
        return 3 * _output_step(session)
    if mode == "dynamic_range":
        return _dynamic_range_atol(model)
    return {"fp32": 1e-5, "fp16": 2e-3 * float(np.abs(reference).max())}[mode]


@pytest.mark.parametrize("mode", list(MODES))
def test_mode_matches_keras(mode: str, build: Build, model: Any, reference: np.ndarray) -> None:
    kind, precision, options = MODES[mode]
    assert BACKEND.invalid_reason("tensorflow", kind, precision, "cpu") is None
    assert BACKEND.option_reason(StrategySpec(kind, kind, options), "keras") is None
    assert BACKEND.probe("cpu", precision) is None
    out, meta = build(mode)
    assert [p.name for p in out.iterdir()] == ["model.tflite"] and meta["mode"] == mode  # the artifact alone
    session = _load(out, meta, precision)
    atol = _atol(mode, session, model, reference)
    assert atol < 0.1 * reference.std(axis=0).min()  # a model that had lost the input would fail it
    batch = _predict(session, X)
    assert batch.dtype == np.float32 and batch.shape == reference.shape
    np.testing.assert_allclose(batch, reference, rtol=0, atol=atol)
    singles = np.concatenate([_predict(session, X[i:i + 1]) for i in range(4)])
    np.testing.assert_allclose(singles, reference[:4], rtol=0, atol=atol)
    dtypes = {np.dtype(d["dtype"]).name for d in _tensors(session)}
    assert ("float16" in dtypes) == (mode == "fp16") and ("int8" in dtypes) == (precision == "int8")
    if kind == "ptq_static":
        assert meta["quantization"]["calibration_samples"] == len(CALIBRATION)


def test_dynamic_range_quantises_the_large_dense_kernel_only(build: Build) -> None:
    """The bound in _dynamic_range_atol rests on this: smaller weight tensors stay float in this mode."""
    session = _load(*build("dynamic_range"), "int8")
    int8 = [(list(d["shape"]), len(d["quantization_parameters"]["scales"]))
            for d in _tensors(session) if d["dtype"] == np.int8]
    assert int8 == [([16, 72], 16)]  # one scale per output channel


def test_full_integer_io_is_int8_and_dequantised(build: Build, reference: np.ndarray) -> None:
    session = _load(*build("full_integer"), "int8")
    info = session.info()
    assert info["input"]["dtype"] == info["output"]["dtype"] == "int8"
    assert info["input"]["scale"] > 0 and info["output"]["scale"] > 0
    prepared = session.prepare({"input": X})
    assert prepared.inputs[0][1].dtype == np.int8  # quantised outside the timed call
    (raw,) = session.execute(prepared)
    assert raw.dtype == np.int8
    step = info["output"]["scale"]
    # Read as numbers without dequantising, the int8 outputs are off by dozens of units, not a few steps.
    assert np.abs(raw.astype(np.float32) - reference).mean() > 100 * step
    np.testing.assert_allclose(session.fetch([raw])[0], reference, rtol=0, atol=3 * step)


def test_float_models_keep_float_io(build: Build) -> None:
    for mode in ("fp32", "integer_float_fallback"):
        info = _load(*build(mode), "int8").info()
        assert info["input"] == info["output"] == {"dtype": "float32"}


def test_sessions_keep_one_interpreter_per_batch_size(build: Build, reference: np.ndarray) -> None:
    session = _load(*build("full_integer"), "int8", threads=2)
    assert session.info()["threads"] == 2
    slices = {1: slice(9, 10), 5: slice(3, 8), 32: slice(0, 32)}
    prepared = {n: session.prepare({"input": X[s]}) for n, s in slices.items()}
    assert len({id(p.interpreter) for p in prepared.values()}) == 3
    assert session.prepare({"input": X[20:21]}).interpreter is prepared[1].interpreter  # made once, reused
    atol = 3 * session.info()["output"]["scale"]
    for n in (32, 1, 5, 1, 32, 5, 5):  # interleaved, as the harness times them
        (got,) = session.fetch(session.execute(prepared[n]))
        assert got.shape == (n, 2)
        np.testing.assert_allclose(got, reference[slices[n]], rtol=0, atol=atol)
    with pytest.raises(ValueError, match="shape"):
        session.prepare({"input": np.zeros((2, 8, 8, 3), np.float32)})


def test_interpreter_is_litert_when_installed(build: Build) -> None:
    from ai_edge_litert.interpreter import Interpreter

    name = f"ai_edge_litert {version('ai-edge-litert')}"
    assert interpreter_class() == (Interpreter, name)
    assert _load(*build("fp32")).info()["interpreter"] == name
    assert BACKEND.versions()["ai-edge-litert"] == version("ai-edge-litert")


def test_no_op_profiler_is_reachable_and_the_profile_says_why(build: Build) -> None:
    session = _load(*build("fp32"))
    profile = session.profile(session.prepare({"input": X[:1]}), 5)
    assert profile.operators == () and profile.fields() == {"profile_reason": profile.reason}
    assert profile.reason.startswith("ai_edge_litert ") and "--enable_op_profiling" in profile.reason


@pytest.mark.filterwarnings("ignore:.*tf.lite.Interpreter is deprecated")
def test_tensorflow_interpreter_is_the_fallback(build: Build, reference: np.ndarray,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ai_edge_litert", None)  # `import ai_edge_litert` now raises ImportError
    monkeypatch.setitem(sys.modules, "ai_edge_litert.interpreter", None)
    tf = tensorflow()
    name = f"tensorflow.lite {tf.__version__}"
    assert interpreter_class() == (tf.lite.Interpreter, name)
    session = _load(*build("full_integer"), "int8")
    assert session.info()["interpreter"] == name
    np.testing.assert_allclose(_predict(session, X), reference, rtol=0, atol=3 * session.info()["output"]["scale"])


def test_conversion_is_deterministic(build: Build, source: SourceModel, tmp_path: Path) -> None:
    out, meta = build("full_integer")
    assert _convert(source, tmp_path / "again", "ptq_static", "int8", io="int8") == meta
    assert (tmp_path / "again" / "model.tflite").read_bytes() == (out / "model.tflite").read_bytes()


def test_quantised_files_are_smaller(tmp_path: Path) -> None:
    """On a model whose size is its weights (83 k parameters), not the file's fixed overhead."""
    k = keras()
    k.utils.set_random_seed(0)
    path = tmp_path / "dense.keras"
    k.Sequential([k.layers.Input((64,)), k.layers.Dense(256, activation="relu"),
                  k.layers.Dense(256, activation="relu"), k.layers.Dense(2)]).save(path)
    source = _source(path, (64,))
    calibration = np.random.default_rng(0).standard_normal((32, 64)).astype(np.float32)
    sizes = {}
    for mode in ("fp32", "fp16", "dynamic_range", "integer_float_fallback"):
        kind, precision, options = MODES[mode]
        _convert(source, tmp_path / mode, kind, precision, calibration, **options)
        sizes[mode] = (tmp_path / mode / "model.tflite").stat().st_size
    assert 0.45 < sizes["fp16"] / sizes["fp32"] < 0.55, sizes  # 2 bytes a weight instead of 4
    assert sizes["dynamic_range"] / sizes["fp32"] < 0.3, sizes  # 1 byte a weight
    assert sizes["integer_float_fallback"] / sizes["fp32"] < 0.3, sizes


@pytest.mark.parametrize(("kind", "options", "fmt", "words"), [
    ("ptq_static", {"method": "entropy"}, "keras", ["min/max", "'entropy'"]),
    ("ptq_static", {"method": "percentile"}, "h5", ["min/max", "'percentile'"]),
    ("ptq_static", {"per_channel": False}, "keras", ["per output channel", "per_channel: false"]),
    ("ptq_dynamic", {"per_channel": False}, "saved_model", ["per output channel", "per_channel: false"]),
    ("none", {}, "onnx", ["Keras", "'onnx'"]),
])
def test_unavailable_options_are_explained(kind: str, options: dict[str, Any], fmt: str, words: list[str]) -> None:
    reason = BACKEND.option_reason(StrategySpec(kind, kind, options), fmt)
    assert reason and all(w in reason for w in words), reason


@pytest.mark.parametrize("options", [{"io": "int8"}, {"io": "float"}, {"per_channel": True, "method": "minmax"},
                                     {"calibration_samples": 10}])
def test_available_options_are_accepted(options: dict[str, Any]) -> None:
    assert BACKEND.option_reason(StrategySpec("ptq_static", "ptq_static", options), "h5") is None


@pytest.mark.parametrize(("combo", "words"), [
    (("pytorch", "none", "fp32", "cpu"), ["tflite", "tensorflow", "pytorch"]),
    (("tensorflow", "none", "fp16", "cuda"), ["none", "fp16", "cuda"]),
    (("tensorflow", "none", "int8", "cpu"), ["none", "int8"]),
    (("tensorflow", "ptq_dynamic", "fp16", "cpu"), ["ptq_dynamic", "fp16"]),
])
def test_unsupported_combinations_are_explained(combo: tuple[str, str, str, str], words: list[str]) -> None:
    reason = BACKEND.invalid_reason(*combo)
    assert reason and all(w in reason for w in words), reason


def test_convert_refuses_before_loading(tmp_path: Path) -> None:
    missing = SourceModel(name="missing", framework="tensorflow", format="keras", path=tmp_path / "missing.keras",
                          sha256="", inputs=(TensorSpec("input", tiny_keras.INPUT_SHAPE),))
    with pytest.raises(ValueError, match="does not implement none at int8"):
        _convert(missing, tmp_path / "out", "none", "int8")
    assert not any((tmp_path / "out").iterdir())
