"""The openvino backend against real OpenVINO and NNCF: PyTorch, ONNX and Keras sources at fp32 (forced) and
int8, several inputs and outputs, its options read back, device probing, telemetry off, and a matrix run."""

from __future__ import annotations

import dataclasses
import functools
import gc
import hashlib
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

if importlib.util.find_spec("openvino") is None or importlib.util.find_spec("nncf") is None:
    # not importorskip: a plain `import openvino` would start its telemetry (see test_telemetry_never_starts)
    pytest.skip("openvino and nncf are not installed: pip install 'bench-matrix[openvino]'",
                allow_module_level=True)
TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_models  # noqa: E402
from conftest import TINY_X, cli, matrix_text  # noqa: E402
from convert_helper import request_for  # noqa: E402

import torch  # noqa: E402

from bench_matrix.backend import Session  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.model_io import read_inputs  # noqa: E402
from bench_matrix.tensors import Inputs, TensorSpec  # noqa: E402
from bench_matrix_backends import _nncf  # noqa: E402
from bench_matrix_backends._openvino import openvino  # noqa: E402
from bench_matrix_backends.openvino import OpenVinoBackend  # noqa: E402

BACKEND = OpenVinoBackend()
X = TINY_X
# The calibration set covers the test inputs: int8 results then differ from fp32 by rounding, not clipping.
CALIBRATION = np.concatenate([X, tiny_models.images(24, 1)])


def _source(path: Path, fmt: str, framework: str, inputs: tuple[TensorSpec, ...],
            factory: str | None = None) -> SourceModel:
    return SourceModel(name=path.stem, framework=framework, format=fmt, path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(), inputs=inputs, factory=factory,
                       python_path=(str(TESTS),))


def _build(source: SourceModel, out: Path, kind: str = "none", precision: str = "fp32", threads: int = 1,
           calibration: np.ndarray | Inputs = CALIBRATION, options: dict[str, Any] | None = None,
           **step_options: Any) -> tuple[dict[str, Any], Session]:
    """Convert as the runner would (the meta must be JSON) and load on the CPU."""
    out.mkdir(parents=True, exist_ok=True)
    request = request_for(calibration, source, out, kind, precision, **step_options)
    meta = BACKEND.convert(dataclasses.replace(request, options=options or {}))
    json.dumps(meta)
    return meta, BACKEND.load(out, meta, "cpu", precision, threads)


def _constant_types(artifact: Path) -> set[str]:
    """The element types of the IR's constants (its weights)."""
    model = openvino().Core().read_model(str(artifact / "model.xml"))
    return {op.get_element_type().get_type_name() for op in model.get_ops()
            if op.get_type_name() == "Constant"}


@pytest.fixture(scope="module")
def onnx_source(source: SourceModel, tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    """The fitted tiny model exported to an ONNX file with a dynamic batch axis."""
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    torch.onnx.export(source.load(), torch.from_numpy(X[:2]), str(path), dynamo=False, input_names=["input"],
                      output_names=["y"], dynamic_axes={"input": {0: "n"}, "y": {0: "n"}})
    return _source(path, "onnx", "onnx", read_inputs("onnx", "onnx", path))


@pytest.mark.parametrize("framework", ["pytorch", "onnx"])
def test_fp32_matches_the_source_and_is_computed_in_fp32(framework: str, source: SourceModel,
                                                         onnx_source: SourceModel, reference: np.ndarray,
                                                         tmp_path: Path) -> None:
    meta, session = _build(source if framework == "pytorch" else onnx_source, tmp_path)
    (got,) = session.predict({"input": X})
    assert got.dtype == np.float32 and got.shape == reference.shape
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)
    assert session.info()["inference_precision"] == "f32"  # never the CPU's bf16 default
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.bin", "model.xml"]
    assert _constant_types(tmp_path) <= {"f32", "i64", "i32"}  # fp32 weights kept fp32, not halved
    assert meta["export"] == ("as given" if framework == "onnx" else "torch.onnx (opset 17)")


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_half_precisions_run_where_probed_and_never_fall_back(precision: str, source: SourceModel,
                                                              reference: np.ndarray, tmp_path: Path) -> None:
    reason = BACKEND.probe("cpu", precision)
    request = request_for(CALIBRATION, source, tmp_path, "none", precision)
    meta = BACKEND.convert(request)
    if reason:  # this CPU lacks it: OpenVINO would silently compute in f32 (bf16 on a bf16 CPU); load refuses
        assert "OPTIMIZATION_CAPABILITIES are" in reason and f"{precision} needs" in reason
        hint = {"bf16": "bf16", "fp16": "f16"}[precision]
        fallback = rf"precision {hint} but the compiled model computes in (?!{hint}\b)\w+"
        with pytest.raises(ValueError, match=fallback):
            BACKEND.load(tmp_path, meta, "cpu", precision, 1)
        return
    session = BACKEND.load(tmp_path, meta, "cpu", precision, 1)
    (got,) = session.predict({"input": X})
    np.testing.assert_allclose(got, reference, rtol=0, atol=2e-2 * float(np.abs(reference).max()))
    assert session.info()["inference_precision"] == {"bf16": "bf16", "fp16": "f16"}[precision]


def _mse(session: Session, x: np.ndarray, y: np.ndarray) -> float:
    (got,) = session.predict({"input": x})
    return float(((got - y) ** 2).mean())


def test_int8_error_stays_close_to_fp32(source: SourceModel, tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """On held-out images of the fitted model's task, int8 adds under 10 % to fp32's MSE. NNCF's own default
    ranges (the mean of each item's min and max), fed one sample per item as its examples do, clip so much
    that the same check fails by far."""
    x = tiny_models.images(256, 7)
    y = tiny_models.colour_balance(x)
    calibration = tiny_models.images(100, 8)
    _, fp32 = _build(source, tmp_path / "fp32")
    meta, int8 = _build(source, tmp_path / "int8", "ptq_static", "int8", calibration=calibration)
    assert _mse(int8, x, y) <= 1.1 * _mse(fp32, x, y)
    assert meta["quantization"]["calibration_samples"] == 100 and meta["weights"] == "int8"
    assert "i8" in _constant_types(tmp_path / "int8") and int8.info()["inference_precision"] == "f32"
    monkeypatch.setitem(_nncf.RANGES, "minmax", "MEAN_MINMAX")
    monkeypatch.setattr(_nncf, "ITEM", 1)
    _, default = _build(source, tmp_path / "default", "ptq_static", "int8", calibration=calibration)
    assert _mse(default, x, y) > 2 * _mse(fp32, x, y)


def _expected(module: torch.nn.Module, inputs: Inputs) -> list[np.ndarray]:
    """The module's own outputs: a tensor, or a dict's values by sorted key."""
    with torch.inference_mode():
        out = module(*(torch.from_numpy(a) for a in inputs.values()))
    return [out.numpy()] if isinstance(out, torch.Tensor) else [out[k].numpy() for k in sorted(out)]


TOKEN_SPECS = (TensorSpec("features", (tiny_models.FEATURES,)),
               TensorSpec("ids", (tiny_models.TOKENS,), "int64"))
TOKENS = tiny_models.token_data(24, 2)
# As CALIBRATION: the test inputs among the calibration samples.
MULTI = {"two_inputs": (TOKEN_SPECS, TOKENS, {k: np.concatenate([v, tiny_models.token_data(40, 1)[k]])
                                              for k, v in TOKENS.items()}),
         "two_outputs": ((TensorSpec("image", tiny_models.INPUT_SHAPE),), {"image": X},
                         {"image": CALIBRATION})}
TRAINED = {"two_inputs": tiny_models.two_inputs, "two_outputs": tiny_models.fitted_two_outputs}


@functools.cache
def _trained(name: str) -> torch.nn.Module:
    """Each multi-input or multi-output module, made (fitted) once for the module's tests."""
    return TRAINED[name]()


@pytest.mark.parametrize("precision", ["fp32", "int8"])
@pytest.mark.parametrize("name", list(MULTI))
def test_every_input_is_bound_by_name_and_every_output_returned(name: str, precision: str,
                                                                tmp_path: Path) -> None:
    specs, inputs, calibration = MULTI[name]
    module = _trained(name)
    torch.save(module.state_dict(), tmp_path / "m.pt")
    source = _source(tmp_path / "m.pt", "state_dict", "pytorch", specs, f"tiny_models:{name}")
    kind = "ptq_static" if precision == "int8" else "none"
    _, session = _build(source, tmp_path / "out", kind, precision, calibration=calibration)
    prepared = session.prepare(dict(reversed(inputs.items())))  # bound by name, not by position
    assert {k: a.dtype.name for k, a in prepared.arrays.items()} == {s.name: s.dtype for s in specs}
    got = session.fetch(session.execute(prepared))
    expected = _expected(module, inputs)
    assert [g.shape for g in got] == [e.shape for e in expected]
    for g, e in zip(got, expected):
        atol = 1e-5 if precision == "fp32" else 0.1 * float(e.std(axis=0).min())
        np.testing.assert_allclose(g, e, rtol=0, atol=atol)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_keras_model_through_tf2onnx(precision: str, tmp_path: Path) -> None:
    pytest.importorskip("tf2onnx")
    import tiny_keras

    path = tmp_path / "two.keras"
    tiny_keras.two_inputs_two_outputs().save(path)
    specs = (TensorSpec("features", (tiny_keras.FEATURES,)), TensorSpec("ids", (tiny_keras.TOKENS,), "int64"))
    source = _source(path, "keras", "tensorflow", specs)
    inputs = tiny_keras.token_data(24, 2)
    expected = [o.numpy() for o in source.load()([inputs["features"], inputs["ids"]], training=False)]
    kind = "ptq_static" if precision == "int8" else "none"
    calibration = {k: np.concatenate([v, tiny_keras.token_data(40, 1)[k]]) for k, v in inputs.items()}
    meta, session = _build(source, tmp_path / "out", kind, precision, calibration=calibration)
    got = session.predict(inputs)
    assert meta["export"] == "tf2onnx (opset 17)" and [g.shape[1] for g in got] == [1, 2]  # zeta, alpha
    for g, e in zip(got, expected):
        atol = 1e-5 if precision == "fp32" else 0.1 * float(e.std(axis=0).min())
        np.testing.assert_allclose(g, e, rtol=0, atol=atol)


def test_options_are_applied_at_compile_and_read_back(source: SourceModel, tmp_path: Path) -> None:
    _, default = _build(source, tmp_path / "default")
    assert default.info() == {"device": "CPU", "device_name": default.info()["device_name"],
                              "execution_devices": ["CPU"], "inference_precision": "f32",
                              "performance_hint": "LATENCY", "streams": 1, "threads": 1, "pinning": True,
                              "compiled_shapes": 1}  # batch 1, compiled by load
    options = {"hint": "throughput", "streams": 2, "pinning": False}
    meta, chosen = _build(source, tmp_path / "chosen", threads=2, options=options)
    assert meta["options"] == options
    info = chosen.info()
    in_force = (info["performance_hint"], info["streams"], info["threads"], info["pinning"])
    assert in_force == ("THROUGHPUT", 2, 2, False)


def test_outputs_stay_finite_once_the_source_is_gone(source: SourceModel, reference: np.ndarray,
                                                     tmp_path: Path) -> None:
    """The artifact owns its weights: nothing of the source (file, module, export) is needed after convert."""
    copy = tmp_path / "copy.pt"
    copy.write_bytes(source.path.read_bytes())
    request = request_for(CALIBRATION, dataclasses.replace(source, path=copy), tmp_path / "out")
    (tmp_path / "out").mkdir()
    meta = BACKEND.convert(request)
    del request
    copy.unlink()
    gc.collect()
    session = BACKEND.load(tmp_path / "out", meta, "cpu", "fp32", 1)
    first = session.prepare({"input": X[:1]})
    batch = session.prepare({"input": X})
    (got,) = session.fetch(session.execute(batch))
    (single,) = session.fetch(session.execute(first))
    assert np.isfinite(got).all() and session.info()["compiled_shapes"] == 2  # batches of 1 and 16
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)
    np.testing.assert_allclose(single, reference[:1], rtol=0, atol=1e-5)  # each batch has its own request
    session.execute(session.prepare({"input": X[::-1].copy()}))
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)  # fetched outputs are copies


def test_a_fixed_batch_is_calibrated_and_fed_as_it_is(source: SourceModel, reference: np.ndarray,
                                                      tmp_path: Path) -> None:
    path = tmp_path / "fixed.onnx"
    torch.onnx.export(source.load(), torch.from_numpy(X[:1]), str(path), dynamo=False, input_names=["input"])
    fixed = _source(path, "onnx", "onnx", read_inputs("onnx", "onnx", path))
    meta, session = _build(fixed, tmp_path / "int8", "ptq_static", "int8", calibration_samples=10)
    assert meta["batch"] == 1 and meta["quantization"]["calibration_samples"] == 10
    (got,) = session.predict({"input": X[:1]})
    np.testing.assert_allclose(got, reference[:1], rtol=0, atol=0.1 * float(reference.std(axis=0).min()))
    with pytest.raises(ValueError, match=r"input input takes \[1,3,16,16\], not \(16, 3, 16, 16\)"):
        session.prepare({"input": X})


@pytest.mark.parametrize(("target", "words"), [
    ("intel_gpu", ["OpenVINO 2026.4.1", "GPU plugin runs Intel integrated and discrete GPUs"]),
    ("intel_npu", ["OpenVINO 2026.4.1", "NPU plugin runs the NPU of Intel Core Ultra processors"]),
])
def test_absent_devices_are_probed_with_the_reason(target: str, words: list[str]) -> None:
    device = {"intel_gpu": "GPU", "intel_npu": "NPU"}[target]
    if any(d.startswith(device) for d in openvino().Core().available_devices):
        pytest.skip(f"this machine has an OpenVINO {device}")
    for precision in ("fp32", "int8"):
        reason = BACKEND.probe(target, precision)
        assert reason is not None and all(w in reason for w in words), reason
    assert BACKEND.probe("cpu", "fp32") is None and BACKEND.probe("cpu", "int8") is None


@pytest.mark.parametrize(("missing", "precision", "expected"), [
    ("openvino", "fp32", "openvino is not installed: pip install 'bench-matrix[openvino]'"),
    ("nncf", "int8", None),  # NNCF converts, running needs none: the int8 Support's convert_needs names it
    ("nncf", "fp32", None),
])
def test_missing_libraries_are_probed_without_importing(missing: str, precision: str, expected: str | None,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == missing else real(name, *a))
    assert BACKEND.probe("cpu", precision) == expected


@pytest.mark.parametrize(("options", "expected"), [
    ({"method": "entropy"},
     "OpenVINO static quantisation calibrates with minmax or percentile, not 'entropy'"),
    ({"io": "int8"}, "OpenVINO int8 models take and return float tensors: io: int8 is not available"),
])
def test_unusable_static_options_are_refused(options: dict[str, Any], expected: str, source: SourceModel,
                                             tmp_path: Path) -> None:
    assert expected in BACKEND.option_reason(StrategySpec("q", "ptq_static", options), "state_dict")
    with pytest.raises(ValueError, match=expected.split(":")[0]):
        BACKEND.convert(request_for(CALIBRATION, source, tmp_path, "ptq_static", "int8", **options))
    assert not any(tmp_path.iterdir())


def test_telemetry_never_starts(tmp_path: Path) -> None:
    """Importing OpenVINO and NNCF through the backend writes nothing to ~/intel; both use their stubs."""
    code = ("from bench_matrix_backends._openvino import openvino; ov = openvino(); import nncf; "
            "import openvino.tools.ovc.telemetry_utils as t; import nncf.telemetry.wrapper as w; "
            "print(t.tm.__name__, isinstance(w.telemetry, w.NNCFTelemetry))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "HOME": str(tmp_path)})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["openvino.tools.ovc.telemetry_stub", "False"]
    assert not (tmp_path / "intel").exists()


@pytest.mark.slow
def test_matrix_run_measures_openvino_beside_eager(tiny_project: Path) -> None:
    text = matrix_text(["pytorch", "openvino"], ["none", "ptq_static"], ["fp32", "bf16", "int8"],
                       ["cpu", "intel_npu"])
    (tiny_project / "m.yaml").write_text(text)
    run = cli(tiny_project, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    out = cli(tiny_project, "report", "--format", "json")
    found = {"/".join(r["cell"][k] for k in ("backend", "strategy", "precision", "target")): r
             for r in json.loads(out.stdout)["records"]}
    fp32, int8 = found["openvino/none/fp32/cpu"], found["openvino/ptq_static/int8/cpu"]
    assert fp32["status"] == "ok" and fp32["metrics"]["max_abs_diff_vs_baseline"] <= 1e-5
    assert fp32["metrics"]["session"]["inference_precision"] == "f32"
    assert int8["status"] == "ok" and int8["metrics"]["session"]["threads"] == 1
    assert "finds no Intel NPU" in found["openvino/none/fp32/intel_npu"]["reason"]
    bf16 = found["openvino/none/bf16/cpu"]
    assert bf16["status"] == ("skipped" if BACKEND.probe("cpu", "bf16") else "ok")
