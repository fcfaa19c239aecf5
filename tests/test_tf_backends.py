"""The TensorFlow-side backends (tensorflow, keras_predict, tftrt) against real TensorFlow on a tiny Keras model."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("tensorflow")  # the module probes TF-TRT at import (a GPU machine may have torch alone)
TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_keras  # noqa: E402
from convert_helper import convert_with  # noqa: E402
from test_profile import by_kind, profiled_shares  # noqa: E402

from bench_matrix import hardware  # noqa: E402
from bench_matrix.backend import Backend, Session  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.tensorflow import keras, tensorflow  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402
from bench_matrix_backends._tf import probe_tftrt  # noqa: E402
from bench_matrix_backends.tensorflow import KerasPredictBackend, TensorFlowBackend  # noqa: E402
from bench_matrix_backends.tftrt import SignatureSession, TFTRTBackend, engine_ops, export_serving  # noqa: E402

BACKENDS: dict[str, Backend] = {"tensorflow": TensorFlowBackend(), "keras_predict": KerasPredictBackend(),
                                "tftrt": TFTRTBackend()}
FORMATS = {"keras": "tiny.keras", "h5": "tiny.h5", "saved_model": "tiny_saved_model"}
X = tiny_keras.images(32, 7)
CALIBRATION = np.concatenate([X, tiny_keras.images(24, 8)])
TFTRT_MISSING = probe_tftrt()
# tf.profiler's op events add up to at most the profiled calls' wall time (they do not nest, and one inter-op
# thread runs them one at a time) and, at batch 32, to at least 20 % of it in the best of three profiles
# (measured 58-64 % on 2 busy cores: the rest is the eager call of the concrete function around its ops)
TF_SHARE = (0.2, 1.0)

pytestmark = pytest.mark.filterwarnings("ignore:You are saving your model as an HDF5 file")


def _source(path: Path, fmt: str) -> SourceModel:
    return SourceModel(name="tiny", framework="tensorflow", format=fmt, path=path, sha256="not checked here",
                       inputs=(TensorSpec("input", tiny_keras.INPUT_SHAPE),))


@pytest.fixture(scope="module")
def sources(tmp_path_factory: pytest.TempPathFactory) -> dict[str, SourceModel]:
    """The tiny model trained once and saved as .keras, .h5 and a Keras SavedModel directory."""
    root = tmp_path_factory.mktemp("keras")
    model = _source(tiny_keras.save_trained(root / FORMATS["keras"]), "keras").load()
    model.save(root / FORMATS["h5"])
    model.save(root / FORMATS["saved_model"])  # no suffix: tf_keras writes a SavedModel directory
    assert (root / FORMATS["saved_model"] / "keras_metadata.pb").is_file()
    return {fmt: _source(root / name, fmt) for fmt, name in FORMATS.items()}


@pytest.fixture(scope="module")
def reference(sources: dict[str, SourceModel]) -> np.ndarray:
    """The Keras model's own outputs, which follow its input (a check against them is not vacuous)."""
    y = sources["keras"].load()(X, training=False).numpy()
    assert y.std(axis=0).min() > 0.1
    return y


def _convert(backend: Backend, source: SourceModel, out: Path, kind: str = "none", precision: str = "fp32",
             target: str = "cpu", **options: Any) -> dict[str, Any]:
    return convert_with(CALIBRATION, backend, source, out, kind, precision, target, **options)


def _predict(session: Session, x: np.ndarray) -> np.ndarray:
    """The one output of the tiny model for images `x`."""
    (out,) = session.predict({"input": x})
    return out


def _predict_batches(session: Session) -> np.ndarray:
    """Outputs for X fed in batches of 1, 5 and 26 (one tf.function serves every batch size)."""
    return np.concatenate([_predict(session, X[:1]), _predict(session, X[1:6]), _predict(session, X[6:])])


@pytest.mark.parametrize("fmt", list(FORMATS))
@pytest.mark.parametrize("name", ["tensorflow", "keras_predict"])
def test_native_backends_reproduce_keras(name: str, fmt: str, sources: dict[str, SourceModel],
                                         reference: np.ndarray, tmp_path: Path) -> None:
    backend = BACKENDS[name]
    assert backend.invalid_reason("tensorflow", "none", "fp32", "cpu") is None
    assert backend.probe("cpu", "fp32") is None
    meta = _convert(backend, sources[fmt], tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == [FORMATS[fmt]]  # the source as it is, and nothing else
    session = backend.load(tmp_path, meta, "cpu", "fp32", 1)
    got = _predict_batches(session)
    assert got.dtype == np.float32 and got.shape == reference.shape
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)
    np.testing.assert_allclose(_predict(session, X), reference, rtol=0, atol=1e-5)  # a batch of 32
    info = session.info()
    assert info["call_path"] == ("tf.function" if name == "tensorflow" else "model.predict")
    assert info["device"] == "/CPU:0" and {"intra_op_threads", "inter_op_threads"} <= set(info)
    if name == "tensorflow":
        assert info["output_device"].endswith("CPU:0")
        assert [t.dtype for t in session.prepare({"input": X[:2]})] == [tensorflow().float32]


def test_tensorflow_profile_has_the_models_ops_within_its_calls(sources: dict[str, SourceModel],
                                                                tmp_path: Path) -> None:
    backend = BACKENDS["tensorflow"]
    session = backend.load(tmp_path, _convert(backend, sources["keras"], tmp_path), "cpu", "fp32", 1)
    profile, _ = profiled_shares(session, {"input": X}, TF_SHARE)
    kinds = by_kind(profile)
    assert kinds["conv"] == {"fp32"} and kinds["matmul"] == {"fp32"}, kinds


def test_saved_model_artifact_is_self_contained(sources: dict[str, SourceModel], reference: np.ndarray,
                                                tmp_path: Path) -> None:
    copy = tmp_path / "elsewhere" / "model_dir"
    shutil.copytree(sources["saved_model"].path, copy)
    meta = _convert(BACKENDS["tensorflow"], _source(copy, "saved_model"), tmp_path / "artifact")
    shutil.rmtree(copy)
    session = BACKENDS["tensorflow"].load(tmp_path / "artifact", meta, "cpu", "fp32", 1)
    np.testing.assert_allclose(_predict(session, X), reference, rtol=0, atol=1e-5)


def test_threads_are_pinned_in_a_fresh_process_and_listing_never_imports_tensorflow(
        sources: dict[str, SourceModel], reference: np.ndarray, tmp_path: Path) -> None:
    meta = _convert(BACKENDS["tensorflow"], sources["keras"], tmp_path)
    np.save(tmp_path / "x.npy", X)
    script = f"""
import json, sys
from pathlib import Path
import numpy as np
from bench_matrix_backends import tensorflow, tftrt
backends = [tensorflow.TensorFlowBackend(), tensorflow.KerasPredictBackend(), tftrt.TFTRTBackend()]
listed = {{b.name: [b.versions(), b.invalid_reason("tensorflow", "none", "fp32", "cpu")] for b in backends}}
imported = "tensorflow" in sys.modules
session = backends[0].load(Path({str(tmp_path)!r}), json.loads(sys.argv[1]), "cpu", "fp32", 1)
y = session.predict({{"input": np.load({str(tmp_path / "x.npy")!r})}})[0]
print(json.dumps({{"imported": imported, "listed": listed, "info": session.info(), "y": y.tolist()}}))
"""
    done = subprocess.run([sys.executable, "-c", script, json.dumps(meta)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["imported"] is False
    assert {"tensorflow", "tensorflow-cpu"} & set(result["listed"]["tensorflow"][0])
    assert result["info"]["intra_op_threads"] == 1 and result["info"]["inter_op_threads"] == 1
    np.testing.assert_allclose(result["y"], reference, rtol=0, atol=1e-5)


@pytest.mark.parametrize("suffix", [".keras", ".h5"])
def test_keras_files_with_python_lambdas_are_refused(suffix: str, tmp_path: Path) -> None:
    k = keras()
    model = k.Sequential([k.layers.Input(tiny_keras.INPUT_SHAPE), k.layers.Lambda(lambda t: t * 2.0)])
    path = tmp_path / f"lambda{suffix}"
    model.save(path)
    with pytest.raises(ValueError, match=f"{path}: .*safe mode.*Lambda"):
        _source(path, suffix[1:]).load()


def test_saved_model_not_written_by_keras_is_refused(tmp_path: Path) -> None:
    tf = tensorflow()

    class Doubler(tf.Module):
        @tf.function(input_signature=[tf.TensorSpec([None, *tiny_keras.INPUT_SHAPE], tf.float32)])
        def __call__(self, x: Any) -> Any:
            return x * 2.0

    tf.saved_model.save(Doubler(), str(tmp_path / "plain"))
    meta = _convert(BACKENDS["tensorflow"], _source(tmp_path / "plain", "saved_model"), tmp_path / "artifact")
    with pytest.raises(ValueError, match="plain: this SavedModel was not written by Keras"):
        BACKENDS["tensorflow"].load(tmp_path / "artifact", meta, "cpu", "fp32", 1)


def test_native_backends_refuse_what_they_do_not_do(sources: dict[str, SourceModel], tmp_path: Path) -> None:
    tensorflow_backend, predict = BACKENDS["tensorflow"], BACKENDS["keras_predict"]
    assert tensorflow_backend.baseline_for == ("tensorflow",) and predict.baseline_for == ()
    assert tensorflow_backend.invalid_reason("tensorflow", "none", "fp32", "cuda") is None
    assert "fp16 on cuda" in (tensorflow_backend.invalid_reason("tensorflow", "none", "fp16", "cuda") or "")
    assert "on cuda" in (predict.invalid_reason("tensorflow", "none", "fp32", "cuda") or "")
    assert "not pytorch" in (tensorflow_backend.invalid_reason("pytorch", "none", "fp32", "cpu") or "")
    with pytest.raises(ValueError, match="strategy kind 'ptq_dynamic' needs another backend"):
        _convert(tensorflow_backend, sources["keras"], tmp_path, "ptq_dynamic", "int8")
    assert list(tmp_path.iterdir()) == []


def test_tensorflow_gpu_probe_names_every_missing_piece() -> None:
    tf = tensorflow()
    missing = [reason] if (reason := hardware.no_gpu_reason()) else []
    if not tf.test.is_built_with_cuda():
        missing.append("is a CPU-only build")
    if not missing:
        pytest.skip("this machine has a GPU and a CUDA build of TensorFlow")
    got = BACKENDS["tensorflow"].probe("cuda", "fp32")
    assert got and all(piece in got for piece in missing), got
    assert BACKENDS["tensorflow"].probe("cpu", "fp32") is None


@pytest.mark.parametrize("precision", ["fp32", "fp16", "int8"])
def test_tftrt_probe_gives_the_precise_reason(precision: str) -> None:
    got = BACKENDS["tftrt"].probe("tensorrt", precision)
    tf = tensorflow()
    if not tf.sysconfig.get_build_info().get("is_tensorrt_build", False):
        assert got and "not a TensorRT build" in got, got
    if reason := hardware.no_gpu_reason():
        assert got and reason in got, got
    assert got == TFTRT_MISSING


def test_tftrt_probe_names_a_gpu_too_old_for_the_precision(monkeypatch: pytest.MonkeyPatch) -> None:
    old = hardware.Gpu("Tesla K80", "470.82.01", 11441, (3, 7))
    monkeypatch.setattr(hardware, "gpus", lambda: (old,))
    int8 = BACKENDS["tftrt"].probe("tensorrt", "int8")
    assert int8 and "Tesla K80 has compute capability 3.7; TF-TRT INT8 needs 6.1 or newer" in int8
    assert "compute capability" not in (BACKENDS["tftrt"].probe("tensorrt", "fp32") or "")


def test_tensorflow_probe_names_a_driver_too_old_for_its_cuda(monkeypatch: pytest.MonkeyPatch) -> None:
    tf = tensorflow()
    if not tf.test.is_built_with_cuda():
        pytest.skip(f"TensorFlow {tf.__version__} here is a CPU-only build: it has no CUDA version to compare")
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: (1, 0))
    got = BACKENDS["tensorflow"].probe("cuda", "fp32")
    assert got and "but the NVIDIA driver supports CUDA up to 1.0" in got


def test_tftrt_declares_tensorrt_only() -> None:
    backend = BACKENDS["tftrt"]
    for combo in (("none", "fp32"), ("none", "fp16"), ("ptq_static", "int8")):
        assert backend.invalid_reason("tensorflow", *combo, "tensorrt") is None
    on_cpu = backend.invalid_reason("tensorflow", "none", "fp32", "cpu")
    assert on_cpu and "does not implement none at fp32 on cpu" in on_cpu
    assert "not pytorch" in (backend.invalid_reason("pytorch", "none", "fp32", "tensorrt") or "")
    assert "ptq_dynamic" in (backend.invalid_reason("tensorflow", "ptq_dynamic", "int8", "tensorrt") or "")
    assert {"tensorflow", "tensorflow-cpu"} & set(backend.versions())


@pytest.mark.parametrize(("options", "words"), [
    ({}, None),
    ({"method": "entropy", "calibration_samples": 50}, None),
    ({"io": "int8"}, "io: int8 is not available"),
    ({"method": "minmax"}, "entropy calibrator (IInt8EntropyCalibrator2, fixed in TF-TRT), not 'minmax'"),
    ({"method": "percentile"}, "not 'percentile'; set method: entropy or leave the option out"),
    ({"per_channel": True}, "TF-TRT has no per_channel setting"),
])
def test_tftrt_static_options(options: dict[str, Any], words: str | None) -> None:
    reason = BACKENDS["tftrt"].option_reason(StrategySpec("s", "ptq_static", options), "keras")
    if words is None:
        assert reason is None
    else:
        assert reason and words in reason, reason
    assert BACKENDS["tftrt"].option_reason(StrategySpec("none", "none"), "h5") is None


def test_tftrt_serving_export_and_signature_session(sources: dict[str, SourceModel], reference: np.ndarray,
                                                    tmp_path: Path) -> None:
    """The CPU-runnable half of TF-TRT: the SavedModel it converts and the signature call that runs its output."""
    tf = tensorflow()
    export_serving(sources["h5"].load(), sources["h5"].inputs, tmp_path / "serving")
    loaded = tf.saved_model.load(str(tmp_path / "serving"))
    function = loaded.signatures["serving_default"]
    assert list(function.structured_input_signature[1]) == ["input"]
    assert list(function.structured_outputs) == ["output"]
    assert engine_ops(function.graph.as_graph_def()) == 0  # plain TensorFlow: no TensorRT engine in it
    session = SignatureSession(loaded, "/CPU:0", {"precision_mode": "FP32"})
    np.testing.assert_allclose(_predict_batches(session), reference, rtol=0, atol=1e-5)
    info = session.info()
    assert info["call_path"] == "SavedModel signature serving_default" and info["precision_mode"] == "FP32"


@pytest.mark.skipif(TFTRT_MISSING is not None, reason=f"TF-TRT cannot run here: {TFTRT_MISSING}")
@pytest.mark.parametrize(("kind", "precision", "atol"), [("none", "fp32", 1e-3), ("none", "fp16", 2e-2),
                                                         ("ptq_static", "int8", None)])
def test_tftrt_converts_and_runs_on_tensorrt(kind: str, precision: str, atol: float | None,
                                             sources: dict[str, SourceModel], reference: np.ndarray,
                                             tmp_path: Path) -> None:
    """fp32 may use TF32 tactics on Ampere and later; int8 is allowed 10% of the outputs' spread across inputs."""
    backend = BACKENDS["tftrt"]
    options = {"calibration_samples": 40} if kind == "ptq_static" else {}
    meta = _convert(backend, sources["keras"], tmp_path, kind, precision, "tensorrt", **options)
    assert meta["precision_mode"] == precision.upper() and meta["engine_ops"] > 0
    assert (tmp_path / "saved_model.pb").is_file()
    session = backend.load(tmp_path, meta, "tensorrt", precision, 1)
    tolerance = 0.1 * float(reference.std(axis=0).min()) if atol is None else atol * float(np.abs(reference).max())
    np.testing.assert_allclose(_predict_batches(session), reference, rtol=0, atol=tolerance)
    if kind == "ptq_static":
        assert meta["calibration"] == {"method": "entropy", "calibrator": "IInt8EntropyCalibrator2",
                                       "calibration_samples": 40, "batch": 1}
