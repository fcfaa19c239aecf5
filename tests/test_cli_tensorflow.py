"""The TensorFlow side end to end through the CLI: Keras files in, every TFLite mode, ORT via tf2onnx, TF-TRT skip."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import FAST_SETTINGS, TESTS, cli

pytestmark = pytest.mark.slow

BACKENDS = ["tensorflow", "keras_predict", "tflite", "tftrt", "onnxruntime"]
STRATEGIES = ("strategies:\n  ptq_static: {kind: ptq_static, calibration_samples: 24}\n"
              "  ptq_full_int8: {kind: ptq_static, io: int8, calibration_samples: 24}\n")


def _keras_project(root: Path, *save_as: str) -> Path:
    """data.npz (uint8 16x16x3 images, their red and green means as labels) and a Keras model trained on it,
    saved under each name in `save_as`."""
    x, y, model = _trained_keras()
    np.savez(root / "data.npz", x=x, y=y)
    for name in save_as:
        model.save(root / name)
    return root


@functools.cache
def _trained_keras() -> tuple[np.ndarray, np.ndarray, Any]:
    """The images, their labels and the Keras model trained on them: trained once per test session."""
    sys.path.insert(0, str(TESTS))
    import tiny_keras

    from bench_matrix.sources.tensorflow import keras

    rng = np.random.default_rng(0)
    x = (rng.random((96, 1, 1, 3)) * rng.integers(0, 256, size=(96, 16, 16, 3))).astype(np.uint8)
    y = (np.stack([x[..., 0].mean(axis=(1, 2)), x[..., 1].mean(axis=(1, 2))], axis=1) / 255.0).astype(np.float32)
    k = keras()
    k.utils.set_random_seed(0)
    model = tiny_keras.tiny()
    model.compile(optimizer=k.optimizers.Adam(3e-3), loss="mse")
    model.fit(x[:48] / np.float32(255), y[:48], epochs=40, batch_size=16, verbose=0)
    return x, y, model


def _matrix(model_file: str, backends: list[str], strategies: list[str], precisions: list[str],
            targets: list[str]) -> str:
    return (f"models:\n  - {{name: tiny, framework: tensorflow, file: {model_file}}}\n"
            f"dataset: {{npz: data.npz, split: {{train: 0.5, calibration: 0.25, test: 0.25}}}}\n"
            + STRATEGIES +
            f"axes: {{backend: {backends}, strategy: {strategies}, precision: {precisions}, target: {targets}}}\n"
            + FAST_SETTINGS)


def _records(project: Path) -> dict[str, dict]:
    out = cli(project, "report", "--format", "json")
    assert out.returncode == 0, out.stderr
    return {"/".join(r["cell"][k] for k in ("backend", "strategy", "precision", "target")): r
            for r in json.loads(out.stdout)["records"]}


@pytest.fixture(scope="module")
def keras_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict]:
    project = _keras_project(tmp_path_factory.mktemp("keras"), "tiny.keras")
    (project / "m.yaml").write_text(_matrix("tiny.keras", BACKENDS, ["none", "ptq_dynamic", "ptq_static",
                                                                    "ptq_full_int8"],
                                            ["fp32", "fp16", "int8"], ["cpu", "tensorrt"])
                                     # ONNX Runtime's fp16 and dynamic int8 of a Keras source: the kit's cases
                                     + "exclude: [{backend: onnxruntime, precision: fp16},"
                                       " {backend: onnxruntime, strategy: ptq_dynamic}]\n")
    run = cli(project, "run", "m.yaml", timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "0 failed" in run.stdout, run.stdout
    return _records(project)


def test_every_tensorflow_backend_runs_a_keras_file(keras_run):
    ok = {key for key, r in keras_run.items() if r["status"] == "ok"}
    assert ok == {"tensorflow/none/fp32/cpu", "keras_predict/none/fp32/cpu",
                  "tflite/none/fp32/cpu", "tflite/none/fp16/cpu", "tflite/ptq_dynamic/int8/cpu",
                  "tflite/ptq_static/int8/cpu", "tflite/ptq_full_int8/int8/cpu",
                  "onnxruntime/none/fp32/cpu", "onnxruntime/ptq_static/int8/cpu"}
    baseline = keras_run["tensorflow/none/fp32/cpu"]["metrics"]
    assert baseline["max_abs_diff_vs_baseline"] == 0.0
    # Same weights, same arithmetic up to float rounding: the fp32 conversions reproduce the Keras outputs.
    for key in ("keras_predict/none/fp32/cpu", "tflite/none/fp32/cpu", "onnxruntime/none/fp32/cpu"):
        m = keras_run[key]["metrics"]
        assert m["max_abs_diff_vs_baseline"] < 1e-4, key
        assert m["mse"] == pytest.approx(baseline["mse"], rel=1e-3), key
    for r in keras_run.values():
        if r["status"] == "ok":
            assert r["env"]["backend_versions"].get("tensorflow") or r["env"]["backend_versions"].get("tensorflow-cpu")


def test_tflite_full_integer_outputs_are_dequantised(keras_run):
    full = keras_run["tflite/ptq_full_int8/int8/cpu"]
    fallback = keras_run["tflite/ptq_static/int8/cpu"]["metrics"]
    session = full["metrics"]["session"]
    assert session["input"]["dtype"] == "int8" and session["output"]["dtype"] == "int8"
    step = session["output"]["scale"]
    # The full-integer model is the float-fallback model plus quantised input and output tensors: its distance
    # from the fp32 outputs may exceed the float-fallback model's by at most the input rounding's effect and
    # half an output step. Allow one whole output step, and never more than 5 % of the label range (1.0).
    assert full["metrics"]["max_abs_diff_vs_baseline"] <= fallback["max_abs_diff_vs_baseline"] + step
    assert full["metrics"]["max_abs_diff_vs_baseline"] < 0.05
    # Raw int8 codes read as floats would be off by orders of magnitude (the study's MSE of 28157).
    assert full["metrics"]["mse"] < 10 * keras_run["tflite/none/fp32/cpu"]["metrics"]["mse"] + 1e-3
    assert "ai_edge_litert" in full["env"]["runtime"]["interpreter"]


def test_quantised_tflite_files_are_smaller(keras_run):
    size = {key: r["metrics"]["size_bytes"] for key, r in keras_run.items() if key.startswith("tflite/")}
    assert size["tflite/ptq_dynamic/int8/cpu"] < size["tflite/none/fp16/cpu"] < size["tflite/none/fp32/cpu"]


def test_tftrt_is_skipped_with_the_precise_reason(keras_run):
    for precision, strategy in (("fp32", "none"), ("fp16", "none"), ("int8", "ptq_static")):
        record = keras_run[f"tftrt/{strategy}/{precision}/tensorrt"]
        assert record["status"] == "skipped"
        assert "not a TensorRT build" in record["reason"]


def test_saved_model_directory_and_h5_are_model_files(tmp_path):
    project = _keras_project(tmp_path, "tiny_savedmodel", "tiny.h5")
    (tmp_path / "m.yaml").write_text(
        "models:\n  - {name: sm, framework: tensorflow, file: tiny_savedmodel}\n"
        "  - {name: h5, framework: tensorflow, file: tiny.h5}\n"
        "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "axes: {backend: [tensorflow, tflite], strategy: [none], precision: [fp32], target: [cpu]}\n"
        # tflite converts any Keras source alike (from_keras_model); tensorflow copies a SavedModel directory
        "exclude: [{model: sm, backend: tflite}, {model: h5, backend: tensorflow}]\n" + FAST_SETTINGS)
    run = cli(project, "run", "m.yaml", timeout=600)
    assert run.returncode == 0 and "2 ok, 0 skipped, 0 failed" in run.stdout, run.stdout + run.stderr


def test_unsafe_or_wrong_keras_inputs_are_refused(tmp_path):
    from bench_matrix.sources.tensorflow import keras

    k = keras()
    model = k.Sequential([k.layers.Input((16, 16, 3)), k.layers.Lambda(lambda t: t * 2.0), k.layers.Flatten(),
                          k.layers.Dense(2)])
    model.save(tmp_path / "lambda.keras")
    _keras_project(tmp_path, "tiny.keras")
    (tmp_path / "notamodel").mkdir()
    bad = ("models:\n  - {name: a, framework: pytorch, file: tiny.keras}\n"
           "  - {name: b, framework: tensorflow, file: notamodel}\n"
           "dataset: {npz: data.npz}\naxes: {strategy: [none], precision: [fp32], target: [cpu]}\n")
    (tmp_path / "bad.yaml").write_text(bad)
    out = cli(tmp_path, "plan", "bad.yaml")
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "'tiny.keras' is a tensorflow model file, but framework is 'pytorch'" in out.stderr
    assert "directory without saved_model.pb" in out.stderr

    (tmp_path / "m.yaml").write_text(_matrix("lambda.keras", ["tensorflow", "tflite"], ["none"], ["fp32"], ["cpu"]))
    run = cli(tmp_path, "run", "m.yaml")
    assert run.returncode == 0 and "0 ok, 0 skipped, 2 failed" in run.stdout, run.stdout + run.stderr
    for record in _records(tmp_path).values():
        assert record["status"] == "failed" and "lambda.keras" in record["reason"]
        assert "safe mode" in record["reason"]
