"""The built-in backends against the real runtimes (torch, TorchScript, ONNX Runtime) on a tiny model."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_models  # noqa: E402
from conftest import TINY_X  # noqa: E402
from convert_helper import convert_with, request_for  # noqa: E402


import torch  # noqa: E402

from bench_matrix import hardware  # noqa: E402
from bench_matrix.backend import Backend, Session  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402
from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend  # noqa: E402
from bench_matrix_backends.pytorch import PyTorchBackend  # noqa: E402
from bench_matrix_backends.torchscript import TorchScriptBackend  # noqa: E402

BACKENDS = {"pytorch": PyTorchBackend(), "torchscript": TorchScriptBackend(), "onnxruntime": OnnxRuntimeBackend()}


X = TINY_X
# The calibration set covers the test inputs, so that int8 results are compared for rounding only, not for
# clipping outputs beyond the calibrated range (that is what the benchmark's accuracy metric measures).
CALIBRATION = np.concatenate([X, tiny_models.images(24, 1)])


def _source(path: Path, fmt: str, framework: str = "pytorch") -> SourceModel:
    factory = "tiny_models:tiny" if fmt == "state_dict" else None
    return SourceModel(name="tiny", framework=framework, format=fmt, path=path,
                       sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                       inputs=(TensorSpec("input", tiny_models.INPUT_SHAPE),), factory=factory,
                       python_path=(str(TESTS),))


def _convert(backend: Backend, source: SourceModel, out: Path, kind: str = "none", precision: str = "fp32",
             target: str = "cpu", shared_dir: Path | None = None, **options: Any) -> dict[str, Any]:
    return convert_with(CALIBRATION, backend, source, out, kind, precision, target, shared_dir, **options)


def _build(backend: Backend, source: SourceModel, out: Path, kind: str = "none", precision: str = "fp32",
           threads: int = 1, **options: Any) -> tuple[dict[str, Any], Session]:
    meta = _convert(backend, source, out, kind, precision, **options)
    return meta, backend.load(out, meta, "cpu", precision, threads)


def _predict(session: Session, x: np.ndarray) -> np.ndarray:
    """The one output of the tiny model for images `x`."""
    (out,) = session.predict({"input": x})
    return out


def _quantised_ops(backend: str, out: Path) -> bool:
    """Whether the artifact really computes in int8 (not a float model that happens to be close)."""
    if backend == "onnxruntime":
        import onnx

        ops = {n.op_type for n in onnx.load(str(out / "model.onnx")).graph.node}
        return bool(ops & {"QuantizeLinear", "DynamicQuantizeLinear", "MatMulInteger"})
    return "quantized::" in str(torch.jit.load(str(out / "model.pt")).inlined_graph)


def _atol(precision: str, reference: np.ndarray) -> float:
    """fp32: the same arithmetic up to summation order. fp16: a 10-bit mantissa (relative rounding 4.9e-4 per
    operation) through a few layers, so 1% of the largest output. int8: every quantised tensor is off by up to
    half a step (its calibrated range / 255, or / 127 for 7-bit values) and so is the output itself, which
    came to under 5% of the outputs' spread across inputs here; 10% of that spread is the bound (an int8
    model that had lost the input's influence would be off by about 100%)."""
    if precision == "int8":
        return 0.1 * float(reference.std(axis=0).min())
    return {"fp32": 1e-5, "fp16": 1e-2}[precision] * float(np.abs(reference).max())


CPU_CASES = [
    ("pytorch", "none", "fp32", {}),
    ("torchscript", "none", "fp32", {}),
    ("torchscript", "ptq_dynamic", "int8", {}),
    ("torchscript", "ptq_dynamic", "int8", {"per_channel": True}),
    ("torchscript", "ptq_static", "int8", {}),
    ("torchscript", "ptq_static", "int8", {"per_channel": True, "calibration_samples": 10}),
    ("onnxruntime", "none", "fp32", {}),
    ("onnxruntime", "none", "fp16", {}),
    ("onnxruntime", "ptq_dynamic", "int8", {"per_channel": True}),
    ("onnxruntime", "ptq_static", "int8", {}),
    ("onnxruntime", "ptq_static", "int8", {"per_channel": True, "method": "percentile"}),
    ("onnxruntime", "ptq_static", "int8", {"method": "percentile", "calibration_samples": 30}),
]


@pytest.mark.parametrize(("name", "kind", "precision", "options"), CPU_CASES,
                         ids=["-".join([c[0], c[1], c[2], *c[3]]) for c in CPU_CASES])
def test_cpu_combination_matches_eager_fp32(name: str, kind: str, precision: str, options: dict[str, Any],
                                            source: SourceModel, reference: np.ndarray, tmp_path: Path) -> None:
    backend = BACKENDS[name]
    assert backend.invalid_reason("pytorch", kind, precision, "cpu") is None
    assert backend.probe("cpu", precision) is None
    meta, session = _build(backend, source, tmp_path, kind, precision, **options)
    got = _predict(session, X)
    assert got.dtype == np.float32 and got.shape == reference.shape
    np.testing.assert_allclose(got, reference, rtol=0, atol=_atol(precision, reference))
    artifact = meta["source"]["path"] if name == "pytorch" else meta["file"]
    assert [p.name for p in tmp_path.iterdir()] == [artifact]  # the artifact's files and nothing else
    assert name == "pytorch" or _quantised_ops(name, tmp_path) == (precision == "int8")
    if precision == "fp16":
        import onnx

        weights = onnx.load(str(tmp_path / artifact)).graph.initializer
        assert any(w.data_type == onnx.TensorProto.FLOAT16 for w in weights)
    if kind == "ptq_static":
        assert meta["quantization"]["calibration_samples"] == options.get("calibration_samples", 40)


def test_quantising_leaves_the_source_untouched(source: SourceModel, reference: np.ndarray, tmp_path: Path) -> None:
    before = {k: v.clone() for k, v in source.load().state_dict().items()}
    firsts = {}
    for name in ("torchscript", "onnxruntime"):
        for kind in ("ptq_dynamic", "ptq_static"):
            _, session = _build(BACKENDS[name], source, tmp_path / name / kind / "1", kind, "int8")
            firsts[name, kind] = _predict(session, X)
    for (name, kind), first in firsts.items():  # a second conversion is independent of the first
        _, session = _build(BACKENDS[name], source, tmp_path / name / kind / "2", kind, "int8")
        np.testing.assert_array_equal(_predict(session, X), first)
    after = source.load().state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert hashlib.sha256(source.path.read_bytes()).hexdigest() == source.sha256
    _, session = _build(BACKENDS["pytorch"], source, tmp_path / "eager")
    np.testing.assert_array_equal(_predict(session, X), reference)


def test_pytorch_artifact_is_self_contained(source: SourceModel, reference: np.ndarray, tmp_path: Path) -> None:
    copy = tmp_path / "elsewhere" / "weights.pt"
    copy.parent.mkdir()
    copy.write_bytes(source.path.read_bytes())
    meta = _convert(BACKENDS["pytorch"], _source(copy, "state_dict"), tmp_path / "artifact")
    copy.unlink()
    assert [p.name for p in (tmp_path / "artifact").iterdir()] == ["weights.pt"]
    session = BACKENDS["pytorch"].load(tmp_path / "artifact", meta, "cpu", "fp32", 1)
    np.testing.assert_array_equal(_predict(session, X), reference)


@pytest.mark.parametrize("name", ["pytorch", "torchscript"])
def test_torch_thread_count_is_honoured(name: str, source: SourceModel, tmp_path: Path) -> None:
    meta = _convert(BACKENDS[name], source, tmp_path)
    for threads in (2, 1):
        session = BACKENDS[name].load(tmp_path, meta, "cpu", "fp32", threads)
        assert torch.get_num_threads() == threads
        assert session.info() == {"device": "cpu", "threads": threads, "interop_threads": 1}


def test_onnxruntime_exports_a_source_once_for_all_modes(source: SourceModel, reference: np.ndarray,
                                                         tmp_path: Path) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    backend = BACKENDS["onnxruntime"]
    _convert(backend, source, tmp_path / "fp32", shared_dir=shared)
    assert (shared / "fp32.onnx").is_file()
    # The source file is gone: the int8 conversion can only have used the kept export.
    gone = SourceModel(**{**source.__dict__, "path": tmp_path / "missing.pt"})
    meta = _convert(backend, gone, tmp_path / "int8", "ptq_dynamic", "int8", shared_dir=shared)
    session = backend.load(tmp_path / "int8", meta, "cpu", "int8", 1)
    assert np.abs(_predict(session, X) - reference).max() < 0.1


def test_onnxruntime_session_options_and_feed(source: SourceModel, reference: np.ndarray, tmp_path: Path) -> None:
    meta, session = _build(BACKENDS["onnxruntime"], source, tmp_path, threads=2)
    assert session.info() == {"providers": ["CPUExecutionProvider"], "threads": 2}
    assert meta["opset"] == 17 and meta["inputs"] == {"input": "input"}
    feed = session.prepare({"input": np.asfortranarray(X.astype(np.float64))})  # converted once, untimed
    assert feed["input"].dtype == np.float32 and feed["input"].flags.c_contiguous
    (got,) = session.fetch(session.execute(feed))
    np.testing.assert_allclose(got, reference, rtol=0, atol=1e-5)


@pytest.mark.filterwarnings("ignore:Specified provider")
@pytest.mark.parametrize("target", ["cuda", "tensorrt"])
def test_onnxruntime_refuses_silent_cpu_fallback(target: str, source: SourceModel, tmp_path: Path) -> None:
    import onnxruntime as ort

    provider = {"cuda": "CUDAExecutionProvider", "tensorrt": "TensorrtExecutionProvider"}[target]
    if provider in ort.get_available_providers() and not hardware.no_gpu_reason():
        pytest.skip(f"{provider} may really work here")
    fallback = f"asked ONNX Runtime for {provider}.*CPUExecutionProvider"
    if target == "tensorrt":  # its engines are built at conversion, so the conversion meets the fallback
        with pytest.raises(RuntimeError, match=fallback):
            _convert(BACKENDS["onnxruntime"], source, tmp_path, target=target)
        return
    meta = _convert(BACKENDS["onnxruntime"], source, tmp_path, target=target)
    with pytest.raises(RuntimeError, match=fallback):
        BACKENDS["onnxruntime"].load(tmp_path, meta, target, "fp32", 1)


@pytest.mark.parametrize(("name", "target"), [("pytorch", "cuda"), ("torchscript", "cuda"),
                                              ("onnxruntime", "cuda"), ("onnxruntime", "tensorrt")])
def test_gpu_probe_names_every_missing_piece(name: str, target: str) -> None:
    import onnxruntime as ort

    missing = []
    if reason := hardware.no_gpu_reason():
        missing.append(reason)
    if name != "onnxruntime" and torch.version.cuda is None:
        missing.append(f"torch {torch.__version__} is a CPU-only build")
    provider = {"cuda": "CUDAExecutionProvider", "tensorrt": "TensorrtExecutionProvider"}[target]
    if name == "onnxruntime" and provider not in ort.get_available_providers():
        missing += [f"has no {provider}", "onnxruntime-gpu"]
    got = BACKENDS[name].probe(target, "fp16")
    if not missing:
        pytest.skip("this machine has what the target needs")
    assert got and all(piece in got for piece in missing), got
    assert BACKENDS[name].probe("cpu", "fp32") is None


@pytest.mark.parametrize(("name", "combo", "words"), [
    ("torchscript", ("pytorch", "none", "fp16", "cpu"), ["torchscript", "none", "fp16", "cpu"]),
    ("pytorch", ("pytorch", "ptq_static", "int8", "cpu"), ["pytorch", "ptq_static", "int8"]),
    ("onnxruntime", ("pytorch", "ptq_dynamic", "int8", "tensorrt"), ["onnxruntime", "ptq_dynamic", "tensorrt"]),
    ("torchscript", ("onnx", "none", "fp32", "cpu"), ["torchscript", "onnx"]),
])
def test_unsupported_combinations_are_explained(name: str, combo: tuple[str, str, str, str],
                                                words: list[str]) -> None:
    reason = BACKENDS[name].invalid_reason(*combo)
    assert reason and all(w in reason for w in words), reason


def test_unusable_static_options_are_refused() -> None:
    def reason(name: str, **options: Any) -> str:
        return BACKENDS[name].option_reason(StrategySpec("s", "ptq_static", options), "state_dict") or ""

    for name in ("torchscript", "onnxruntime"):
        assert "io: int8 is not available" in reason(name, io="int8")
    assert "minmax, not 'entropy'" in reason("torchscript", method="entropy")
    assert "minmax or percentile, not 'entropy'" in reason("onnxruntime", method="entropy")


@pytest.fixture(scope="module")
def torchscript_source(source: SourceModel, tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    path = tmp_path_factory.mktemp("scripted") / "tiny.ts.pt"
    torch.jit.trace(source.load(), torch.from_numpy(X[:2])).save(str(path))
    return _source(path, "torchscript")


@pytest.fixture(scope="module")
def torch_export_source(source: SourceModel, tmp_path_factory: pytest.TempPathFactory) -> SourceModel:
    path = tmp_path_factory.mktemp("exported") / "tiny.pt2"
    program = torch.export.export(source.load(), (torch.from_numpy(X[:4]),),
                                  dynamic_shapes=({0: torch.export.Dim("batch")},))
    torch.export.save(program, str(path))
    return _source(path, "torch_export")


@pytest.mark.parametrize("fmt", ["torchscript", "torch_export"])
@pytest.mark.parametrize("name", ["pytorch", "torchscript", "onnxruntime"])
def test_compiled_source_runs_as_is(name: str, fmt: str, request: pytest.FixtureRequest, reference: np.ndarray,
                                    tmp_path: Path) -> None:
    _, session = _build(BACKENDS[name], request.getfixturevalue(f"{fmt}_source"), tmp_path)
    np.testing.assert_allclose(_predict(session, X), reference, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("fmt", "kind"), [("torchscript", "ptq_dynamic"), ("torchscript", "ptq_static"),
                                           ("torch_export", "ptq_static")])
def test_compiled_source_cannot_be_quantised_by_torch(fmt: str, kind: str) -> None:
    what = "a TorchScript file" if fmt == "torchscript" else "a torch.export program"
    reason = BACKENDS["torchscript"].option_reason(StrategySpec(kind, kind), fmt)
    assert reason and f"is {what}; give it as factory + weights" in reason, reason


def test_onnx_file_source_in_onnxruntime(source: SourceModel, reference: np.ndarray, tmp_path: Path) -> None:
    path = tmp_path / "tiny.onnx"  # a fixed batch of 8 and its own input name, as a user's file may have
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        torch.onnx.export(source.load(), (torch.from_numpy(X[:8]),), str(path), dynamo=False, input_names=["image"])
    onnx_source = _source(path, "onnx", framework="onnx")
    backend = BACKENDS["onnxruntime"]
    assert backend.baseline_for == ("onnx",) and backend.invalid_reason("onnx", "ptq_static", "int8", "cpu") is None
    meta, session = _build(backend, onnx_source, tmp_path / "fp32")
    assert meta["inputs"] == {"input": "image"}  # the declared input feeds the graph's one input
    np.testing.assert_allclose(_predict(session, X[:8]), reference[:8], rtol=0, atol=1e-5)
    meta, session = _build(backend, onnx_source, tmp_path / "int8", "ptq_static", "int8", calibration_samples=20)
    assert meta["quantization"]["calibration_samples"] == 16  # whole batches of 8 only
    np.testing.assert_allclose(_predict(session, X[:8]), reference[:8], rtol=0, atol=_atol("int8", reference))


def test_listing_and_running_onnxruntime_never_import_torch(source: SourceModel, reference: np.ndarray,
                                                            tmp_path: Path) -> None:
    meta = _convert(BACKENDS["onnxruntime"], source, tmp_path, "ptq_static", "int8")
    np.save(tmp_path / "x.npy", X)
    script = f"""
import json, sys
from pathlib import Path
import numpy as np
sys.path.insert(0, {str(TESTS)!r})
import tiny_models
from bench_matrix_backends import onnxruntime, pytorch, torchscript
heavy = sorted(m for m in ("torch", "onnxruntime", "onnx") if m in sys.modules)
backend = onnxruntime.OnnxRuntimeBackend()
versions = backend.versions()
session = backend.load(Path({str(tmp_path)!r}), json.loads(sys.argv[1]), "cpu", "int8", 1)
y = session.predict({{"input": np.load({str(tmp_path / "x.npy")!r})}})[0]
print(json.dumps({{"heavy": heavy, "torch": "torch" in sys.modules, "versions": versions, "y": y.tolist()}}))
"""
    done = subprocess.run([sys.executable, "-c", script, json.dumps(meta)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["heavy"] == [] and result["torch"] is False
    assert {"onnxruntime", "onnx"} <= set(result["versions"])
    np.testing.assert_allclose(result["y"], reference, rtol=0, atol=_atol("int8", reference))


def test_tensorflow_backends_skip_where_tensorflow_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seen on a GPU machine with torch alone: the probes raised ModuleNotFoundError ("probing tensorflow for
    cuda/fp32 failed") and a TensorFlow model's preparation failed, instead of its cells being skipped."""
    import importlib.util

    from bench_matrix_backends.tensorflow import KerasPredictBackend, TensorFlowBackend
    from bench_matrix_backends.tflite import TFLiteBackend
    from bench_matrix_backends.tftrt import TFTRTBackend

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "tensorflow"
                        else find_spec(name, *a))
    for backend in (TensorFlowBackend(), KerasPredictBackend(), TFLiteBackend(), TFTRTBackend()):
        for target in sorted({t for support in backend.supports for t in support.targets}):
            reasons = [backend.probe(target, "fp32"), backend.probe_source("tensorflow", "keras")]
            assert "TensorFlow is not installed: pip install tensorflow-cpu" in str(reasons), backend.name


def test_onnxruntime_pre_processes_in_a_relative_scratch_directory(source: SourceModel, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """A run's scratch directory is relative to the project (.bench-matrix/tmp/...): the pre-quantisation pass,
    which works inside it, found none of its files there and every int8 cell went without it."""
    import dataclasses

    monkeypatch.chdir(tmp_path)
    (tmp_path / "scratch").mkdir()
    for kind in ("ptq_dynamic", "ptq_static"):
        request = request_for(X, source, tmp_path / kind, kind, "int8")
        (tmp_path / kind).mkdir()
        meta = BACKENDS["onnxruntime"].convert(dataclasses.replace(request, scratch_dir=Path("scratch")))
        assert meta["quantization"]["pre_process"] == {"applied": "full"}, meta["quantization"]


def test_onnxruntime_quantises_where_its_pre_processing_fails(source: SourceModel, reference: np.ndarray,
                                                              tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    """ONNX Runtime's optional pre-quantisation pass asserts inside its symbolic shape inference on some
    transformer graphs: the conversion goes on without that step, or without the pass, and says so."""
    from onnxruntime.quantization import shape_inference

    real = shape_inference.quant_pre_process
    failing = {"symbolic": True, "onnx": False}  # which of its shape inferences raise

    def asserting(fp32: str, out: str, skip_symbolic_shape: bool = False, **options: Any) -> None:
        if failing["onnx" if skip_symbolic_shape else "symbolic"]:
            raise AssertionError  # as onnxruntime/quantization/shape_inference.py's symbolic inference does
        real(fp32, out, skip_symbolic_shape=skip_symbolic_shape, **options)

    monkeypatch.setattr(shape_inference, "quant_pre_process", asserting)
    backend = BACKENDS["onnxruntime"]
    for kind in ("ptq_dynamic", "ptq_static"):
        meta = _convert(backend, source, tmp_path / kind, kind, "int8")
        done = meta["quantization"]["pre_process"]
        assert done == {"applied": "without symbolic shape inference",
                        "failed": "full: AssertionError: (no message)"}
        session = backend.load(tmp_path / kind, meta, "cpu", "int8", 1)
        assert np.abs(_predict(session, X) - reference).max() < 0.1
    failing["onnx"] = True  # both ways fail: no pass at all
    meta = _convert(backend, source, tmp_path / "none", "ptq_dynamic", "int8")
    assert meta["quantization"]["pre_process"]["applied"] == "none"
    assert np.abs(_predict(backend.load(tmp_path / "none", meta, "cpu", "int8", 1), X) - reference).max() < 0.1
