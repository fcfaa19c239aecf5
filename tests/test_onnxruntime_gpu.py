"""ONNX Runtime's CUDA and TensorRT side with the real onnxruntime package: provider options, the TensorRT
calibration table, probe reasons, fallback detection and the I/O-bound session. Most of it runs on a CPU-only
build; the tests marked gpu need an NVIDIA GPU (deselected without one) and their provider (skipped with the
probe's reason without it)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_models  # noqa: E402
from convert_helper import request_for  # noqa: E402
from bench_matrix_backends import _ort_gpu  # noqa: E402
from bench_matrix_backends._ort_gpu import CACHE_DIR, CALIBRATION_TABLE, EngineSpec  # noqa: E402
from bench_matrix_backends.onnxruntime import (  # noqa: E402
    METHODS,
    OnnxRuntimeBackend,
    calibration_feeds,
    feed_reader,
)

from bench_matrix import hardware  # noqa: E402
from bench_matrix.backend import ConvertRequest, Session  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402

BACKEND = OnnxRuntimeBackend()
CPU, CUDA, TRT = "CPUExecutionProvider", "CUDAExecutionProvider", "TensorrtExecutionProvider"
TRT_INT8 = BACKEND.probe("tensorrt", "int8")
TOLERANCE = {"fp32": 1e-5, "fp16": 1e-2}  # of the largest |output|: IEEE fp32's rounding, fp16's
OLD_GPU = hardware.Gpu("Tesla M60", "470.57.02", 8129, (5, 2))


X = tiny_models.images(16, 2)
# The first 30 samples cover X; the 10 after them reach 2.0, so a range above 1 means they were calibrated on.
CALIBRATION = np.concatenate([X, tiny_models.images(14, 1), 2 * tiny_models.images(10, 3)])


def _request(source: SourceModel, out: Path, kind: str = "none", precision: str = "fp32", target: str = "cpu",
             max_batch: int = 1, **options: Any) -> ConvertRequest:
    out.mkdir(parents=True, exist_ok=True)
    return request_for(CALIBRATION, source, out, kind, precision, target, None, max_batch, **options)


def _predict(session: Session, x: np.ndarray) -> np.ndarray:
    (out,) = session.predict({"input": x})
    return out


def _fp32_onnx(source: SourceModel, out: Path) -> Path:
    """The source exported by the backend (a dynamic batch axis, input 'input')."""
    BACKEND.convert(_request(source, out))
    return out / "model.onnx"


def _no_provider(provider: str, available: list[str]) -> str:
    return (f"the installed {_ort_gpu.package()} has no {provider} (it has {', '.join(available)}); "
            f"install onnxruntime-gpu in its place")


def _read_table(path: Path) -> dict[str, float]:
    """The calibration table as the TensorRT provider reads it: tensor name -> dynamic range."""
    from onnxruntime.quantization.CalTableFlatBuffers.TrtTable import TrtTable

    table = TrtTable.GetRootAs(path.read_bytes(), 0)
    return {table.Dict(i).Key().decode(): float(table.Dict(i).Value()) for i in range(table.DictLength())}


@pytest.mark.parametrize(("target", "precision", "expected"), [
    ("cpu", "fp32", [CPU]), ("cpu", "int8", [CPU]), ("cuda", "fp32", [(CUDA, {"use_tf32": "0"}), CPU]),
    ("cuda", "fp16", [(CUDA, {"use_tf32": "0"}), CPU])])
def test_cpu_and_cuda_provider_lists(target: str, precision: str, expected: list[str]) -> None:
    assert _ort_gpu.providers(target, precision) == expected


@pytest.mark.parametrize("precision", ["fp32", "fp16", "int8"])
def test_tensorrt_options_keep_engines_and_table_in_the_artifact(precision: str, tmp_path: Path) -> None:
    artifact = tmp_path / "artifact"
    spec = EngineSpec((("input", (3, 66, 200)),), 32, artifact / CACHE_DIR, precision == "int8", tmp_path / "timing")
    (name, options), (cuda, cuda_options), cpu = _ort_gpu.providers("tensorrt", precision, spec)
    expected = {"trt_fp16_enable": str(precision == "fp16"), "trt_int8_enable": str(precision == "int8"),
                "trt_engine_cache_enable": "True", "trt_engine_cache_path": str(artifact / CACHE_DIR),
                "trt_timing_cache_enable": "True", "trt_timing_cache_path": str(tmp_path / "timing"),
                "trt_profile_min_shapes": "input:1x3x66x200", "trt_profile_opt_shapes": "input:32x3x66x200",
                "trt_profile_max_shapes": "input:32x3x66x200"}
    if precision == "int8":
        expected |= {"trt_int8_calibration_table_name": CALIBRATION_TABLE,
                     "trt_int8_use_native_calibration_table": "False"}
    assert (name, cuda, cpu) == (TRT, CUDA, CPU)
    assert options == expected and cuda_options == {"use_tf32": "0"}
    with pytest.raises(ValueError, match="EngineSpec"):
        _ort_gpu.providers("tensorrt", precision)


def test_a_fixed_batch_model_gets_no_shape_profile(tmp_path: Path) -> None:
    options = _ort_gpu.tensorrt_options("fp16", EngineSpec((("image", (3, 16, 16)),), None, tmp_path, False))
    assert not any(key.startswith("trt_profile") for key in options)
    assert options["trt_timing_cache_enable"] == "False" and "trt_timing_cache_path" not in options


def test_load_finds_the_engines_where_the_artifact_was_moved(tmp_path: Path) -> None:
    """The build's options and the load's differ only in the cache's place and the timing cache, so that the
    provider's engine and profile files (named from the model's file name and graph, not its path) match."""
    built = EngineSpec((("input", (3, 16, 16)),), 8, tmp_path / "x.tmp1" / "model" / CACHE_DIR, True,
                       tmp_path / "timing")
    meta = {"inputs": {"input": "input"},
            "tensorrt": json.loads(json.dumps({**built.to_meta(), "engines": ["e.engine"]}))}
    final = tmp_path / "x" / "model"
    loaded = EngineSpec.at_load(final, meta)
    assert loaded.cache_dir == final / CACHE_DIR and loaded.timing_dir is None
    place = {"trt_engine_cache_path", "trt_timing_cache_enable", "trt_timing_cache_path"}
    build_options, load_options = (_ort_gpu.tensorrt_options("int8", s) for s in (built, loaded))
    assert {k: v for k, v in build_options.items() if k not in place} == \
           {k: v for k, v in load_options.items() if k not in place}
    assert load_options["trt_timing_cache_enable"] == "False"
    with pytest.raises(RuntimeError, match="no 'tensorrt' entry.*delete it"):
        EngineSpec.at_load(final, {"inputs": {"input": "input"}})
    assert loaded == EngineSpec((("input", (3, 16, 16)),), 8, final / CACHE_DIR, True)


@pytest.mark.parametrize("method", ["minmax", "percentile"])
def test_calibration_table_ranges_each_activation_from_the_calibration_split(method: str, source: SourceModel,
                                                                            tmp_path: Path) -> None:
    import onnx
    import onnxruntime as ort

    model = _fp32_onnx(source, tmp_path / "fp32")
    request = _request(source, tmp_path / "trt", "ptq_static", "int8", "tensorrt", method=method,
                       calibration_samples=30)
    cache = request.out_dir / CACHE_DIR
    cache.mkdir()
    feeds = calibration_feeds(request, request.step, {"input": "input"}, None)
    tensors = _ort_gpu.write_calibration_table(model, feed_reader(feeds), METHODS[method], cache)
    assert [p.name for p in cache.iterdir()] == [CALIBRATION_TABLE]  # only the file the provider reads
    table = _read_table(cache / CALIBRATION_TABLE)
    graph = onnx.load(str(model)).graph
    activations = {i.name for i in graph.input} | {o for node in graph.node for o in node.output}
    assert set(table) == activations and tensors == len(activations)
    fed = CALIBRATION[:30]
    np.testing.assert_array_equal(np.concatenate([f["input"] for f in feeds]), fed)
    outputs = ort.InferenceSession(str(model), providers=[CPU]).run(None, {"input": fed})[0]
    if method == "minmax":  # symmetric: the largest magnitude each tensor took on the samples fed
        assert table["input"] == float(np.abs(fed).max())
        assert table[graph.output[0].name] == pytest.approx(float(np.abs(outputs).max()), rel=1e-5)
    else:  # the 99.999th percentile of the magnitudes, at most the largest
        assert 0.5 * float(np.abs(fed).max()) < table["input"] <= float(np.abs(fed).max())
    assert all(value > 0 for value in table.values())


@pytest.mark.filterwarnings("ignore:Specified provider")
def test_tensorrt_engines_are_built_at_conversion_so_a_fallback_fails_it(source: SourceModel,
                                                                        tmp_path: Path) -> None:
    import onnxruntime as ort

    if TRT in ort.get_available_providers() and not hardware.no_gpu_reason():
        pytest.skip("TensorrtExecutionProvider may really work here")
    request = _request(source, tmp_path, "ptq_static", "int8", "tensorrt", max_batch=8)
    with pytest.raises(RuntimeError, match=f"asked ONNX Runtime for {TRT} \\(target tensorrt\\) but the session runs "
                                           f"on \\['{CPU}'\\].*install onnxruntime-gpu"):
        BACKEND.convert(request)
    # The table went into the artifact before the engine build was tried (on CPUs, at conversion).
    assert _read_table(tmp_path / CACHE_DIR / CALIBRATION_TABLE)["input"] == float(np.abs(CALIBRATION).max())


def test_fallback_message_says_what_to_fix() -> None:
    failed = _ort_gpu.fallback_message("cuda", [CPU], [CUDA, CPU])
    assert failed.startswith(f"asked ONNX Runtime for {CUDA} (target cuda) but the session runs on ['{CPU}']")
    assert f"has {CUDA} but it failed to initialise: check that the CUDA, cuDNN and TensorRT libraries" in failed
    missing = _ort_gpu.fallback_message("tensorrt", [CUDA, CPU], [CUDA, CPU])
    assert missing.endswith(f"has no {TRT}: install onnxruntime-gpu in its place")


# What onnxruntime-gpu 1.31.1 logged on a machine without CUDA's libraries (native stderr, colour codes included).
GPU_BUILD_LOG = [
    ("\x1b[1;31m2026-11-21 11:23:53.884905785 [E:onnxruntime:Default, provider_bridge_ort.cc:2458 operator()] "
     "/onnxruntime_src/onnxruntime/core/session/provider_bridge_ort.cc:2043 onnxruntime::Provider& "
     "onnxruntime::ProviderLibrary::Get() [ONNXRuntimeError] : 1 : FAIL : Failed to load library "
     "/site/onnxruntime/capi/libonnxruntime_providers_cuda.so with error: libcublasLt.so.13: cannot open shared "
     "object file: No such file or directory"),
    "\x1b[m",
    ("\x1b[0;93m2026-11-21 11:23:53.884971711 [W:onnxruntime:Default, onnxruntime_pybind_state.cc:1295 "
     "CreateExecutionProviderFactoryInstance] Failed to create CUDAExecutionProvider. Require cuDNN 9.* and CUDA "
     "13.*. Please install all dependencies as mentioned in the GPU requirements page.\x1b[m"),
]


def test_fallback_message_quotes_what_onnxruntime_said() -> None:
    said = _ort_gpu.ort_said(GPU_BUILD_LOG + GPU_BUILD_LOG)  # each line once
    assert said == [
        ("Failed to load library /site/onnxruntime/capi/libonnxruntime_providers_cuda.so with error: "
         "libcublasLt.so.13: cannot open shared object file: No such file or directory"),
        ("Failed to create CUDAExecutionProvider. Require cuDNN 9.* and CUDA 13.*. Please install all dependencies "
         "as mentioned in the GPU requirements page.")]
    message = _ort_gpu.fallback_message("cuda", [CPU], [TRT, CUDA, CPU], said)
    assert message.endswith(f"; ONNX Runtime said: {said[0]} | {said[1]}")
    assert _ort_gpu.ort_said(["2026-11-21 [W:onnxruntime:, graph.cc:5777] Removing initializer 'w'."]) == []


@pytest.mark.parametrize(("error", "fix"), [
    ("libcuda.so.1: cannot open shared object file: No such file or directory", "the NVIDIA driver's library"),
    ("libnvinfer.so.10: cannot open shared object file", "TensorRT 10's: pip install 'tensorrt-cu13-libs==10.*'"),
    ("libcudnn.so.9: cannot open shared object file", "cuDNN's: pip install 'onnxruntime-gpu[cudnn]'"),
    ("libcublasLt.so.13: cannot open shared object file", "CUDA 13.0's: pip install 'onnxruntime-gpu[cuda,cudnn]'"),
])
def test_a_library_the_provider_cannot_find_is_a_reason_with_its_fix(error: str, fix: str) -> None:
    """The loader's words (as onnxruntime-gpu 1.31.1's provider libraries gave them on a machine without CUDA)
    become the probe reason: which library is missing and what installs it."""
    soname = _ort_gpu._MISSING.search(f"OSError: /site/capi/libonnxruntime_providers_cuda.so: {error}").group(1)
    assert soname == error.split(":")[0]
    reason = _ort_gpu.missing_library_reason(CUDA, soname, "13.0")
    assert f"has {CUDA}, but its library needs {soname}, which is not installed: it is " in reason
    assert reason.endswith(fix) or fix in reason


def test_provider_libraries_are_not_checked_where_the_build_has_none() -> None:
    import onnxruntime as ort

    library = Path(ort.__file__).parent / "capi" / "libonnxruntime_providers_cuda.so"
    if library.exists():
        pytest.skip("a GPU build of onnxruntime is installed")
    assert _ort_gpu.library_reason(CUDA, None) is None


def test_sessions_never_fall_back_and_onnxruntime_log_is_collected(tmp_path: Path,
                                                                   capfd: pytest.CaptureFixture[str]) -> None:
    """Sessions are opened with ONNX Runtime's provider fallback off, and what its C++ logger writes to stderr is
    collected (here its warning about an unused initializer) and still passed on."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 3])
    unused = numpy_helper.from_array(np.ones(3, np.float32), "never_read")
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "relu", [x], [y], [unused])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=10),
              tmp_path / "relu.onnx")
    with _ort_gpu.native_log() as log:
        session = _ort_gpu.open_session(tmp_path / "relu.onnx", "cpu", "fp32", 1)
    assert any("Removing initializer 'never_read'" in line for line in log)
    assert "Removing initializer 'never_read'" in capfd.readouterr().err
    assert session._enable_fallback is False  # ONNX Runtime has no public getter for it


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads the process's mapped files (Linux)")
def test_tensorrt_libraries_of_the_pip_wheel_are_preloaded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The libraries in the tensorrt_libs package (TensorRT's pip wheel) that the provider needs are loaded before a
    GPU session opens, others in it are not. Stand-ins: copies of the zlib this Python already maps."""
    import zlib  # noqa: F401 - maps libz

    import onnxruntime as ort

    maps = Path("/proc/self/maps")
    libz = next(Path(line.split()[-1]) for line in maps.read_text().splitlines() if "/libz.so" in line)
    package = tmp_path / "tensorrt_libs"
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name in ("libnvinfer.so.10", "libnvonnxparser.so.10", "libcudla.so.1"):
        (package / name).write_bytes(libz.read_bytes())
    monkeypatch.syspath_prepend(str(tmp_path))
    _ort_gpu.preload_libraries(ort)
    mapped = maps.read_text()
    assert str(package / "libnvinfer.so.10") in mapped and str(package / "libnvonnxparser.so.10") in mapped
    assert str(package / "libcudla.so.1") not in mapped


def test_tensorrt_int8_refuses_per_channel(source: SourceModel, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="TensorRT int8 has no per_channel setting.*remove the option for target"):
        BACKEND.convert(_request(source, tmp_path, "ptq_static", "int8", "tensorrt", per_channel=True))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("inputs", "words"), [
    ((("image", (3, None, 16)),), "'image' has a free axis (shape (3, None, 16) per sample)"),
    ((("ids", (8,)), ("a:b", (8,))), "'a:b' cannot be named in the TensorRT provider's shape profiles")])
def test_tensorrt_refuses_inputs_its_profiles_cannot_state(inputs: Any, words: str) -> None:
    assert words in (_ort_gpu.profile_reason(inputs) or "")
    assert _ort_gpu.profile_reason((("ids", (8,)), ("mask", (8,)))) is None


def test_tensorrt_profiles_name_every_input(tmp_path: Path) -> None:
    spec = EngineSpec((("ids", (128,)), ("mask", (128,))), 8, tmp_path, False)
    options = _ort_gpu.tensorrt_options("fp16", spec)
    assert options["trt_profile_min_shapes"] == "ids:1x128,mask:1x128"
    assert options["trt_profile_max_shapes"] == "ids:8x128,mask:8x128"


def test_probe_on_this_machine_names_each_missing_piece() -> None:
    import onnxruntime as ort

    available = ort.get_available_providers()
    if not hardware.no_gpu_reason() or TRT in available or CUDA in available:
        pytest.skip("this machine has a GPU or a GPU build of onnxruntime")
    for target, provider in (("cuda", CUDA), ("tensorrt", TRT)):
        expected = [hardware.no_gpu_reason(), _no_provider(provider, available)]
        assert _ort_gpu.probe_reasons(target, "int8") == expected
        assert BACKEND.probe(target, "fp16") == "; ".join(expected)
    assert BACKEND.probe("cpu", "int8") is None


def test_probe_names_a_gpu_too_old_for_the_precision(monkeypatch: pytest.MonkeyPatch) -> None:
    import onnxruntime as ort

    monkeypatch.setattr(hardware, "gpus", lambda: (OLD_GPU,))
    gpu_build = [TRT, CUDA, CPU]
    assert _ort_gpu.gpu_reasons("tensorrt", "int8", gpu_build, None) == [
        f"Tesla M60 has compute capability 5.2; int8 on {TRT} needs 6.1 or newer"]
    assert _ort_gpu.gpu_reasons("cuda", "fp16", gpu_build, None) == [
        f"Tesla M60 has compute capability 5.2; fp16 on {CUDA} needs 6.0 or newer"]
    assert _ort_gpu.gpu_reasons("tensorrt", "fp32", gpu_build, None) == []
    # Through the backend, with the installed package: the provider if it lacks it, then the GPU, joined.
    available = ort.get_available_providers()
    missing = [] if TRT in available else [_no_provider(TRT, available)]
    assert BACKEND.probe("tensorrt", "int8") == "; ".join(
        [*missing, f"Tesla M60 has compute capability 5.2; int8 on {TRT} needs 6.1 or newer"])


def test_probe_names_a_driver_too_old_for_the_build(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hardware, "gpus", lambda: (OLD_GPU,))
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: (12, 4))
    reasons = _ort_gpu.gpu_reasons("cuda", "fp16", [CPU], "13.0")
    assert len(reasons) == 3
    assert f"has no {CUDA}" in reasons[0]
    assert "is built for CUDA 13.0, but the NVIDIA driver supports CUDA up to 12.4" in reasons[1]
    assert "compute capability 5.2" in reasons[2]
    assert _ort_gpu.gpu_reasons("cuda", "fp32", [CUDA, CPU], "12.8") == []  # a newer minor is compatible


def test_device_session_binds_the_batch_once_and_copies_the_output_back(source: SourceModel,
                                                                        tmp_path: Path) -> None:
    """The CUDA path's I/O binding, run on the CPU device of the real package: prepare binds an OrtValue and the
    output, execute reruns the binding, fetch copies the output to a float32 host array."""
    import onnxruntime as ort

    model = _fp32_onnx(source, tmp_path)
    session = _ort_gpu.open_session(model, "cpu", "fp32", 1)
    device = _ort_gpu.DeviceSession(session, {"input": "input"}, "cpu")
    expected = session.run(None, {"input": X})[0]
    prepared = device.prepare({"input": np.asfortranarray(X.astype(np.float64))})
    assert isinstance(prepared, ort.IOBinding)
    for _ in range(2):  # one binding serves every timed call
        (got,) = device.fetch(device.execute(prepared))
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(_predict(device, X[:3]), expected[:3])
    assert device.info() == {"providers": [CPU], "threads": 1, "io_binding": "cpu:0"}


def _cuda(precision: str) -> Any:
    """A CUDA provider case, skipped with the backend's own probe reason where it cannot run."""
    reason = BACKEND.probe("cuda", precision)
    skip = pytest.mark.skipif(reason is not None, reason=reason or "")
    return pytest.param(precision, marks=[pytest.mark.gpu, skip])


@pytest.mark.parametrize("precision", [_cuda("fp32"), _cuda("fp16")])
def test_cuda_provider_fp32_is_ieee_and_fp16_close(precision: str, source: SourceModel, reference: np.ndarray,
                                                  tmp_path: Path) -> None:
    """With use_tf32 at its default the provider's fp32 Conv and MatMul ran in TF32 on an H100 (1e-3 from the
    CPU's outputs, as far as fp16's); bench-matrix switches it off, and the session says so."""
    out = tmp_path / "model"
    meta = BACKEND.convert(_request(source, out, precision=precision, target="cuda"))
    session = BACKEND.load(out, json.loads(json.dumps(meta)), "cuda", precision, 1)
    info = session.info()
    assert info["providers"][0] == CUDA and info["io_binding"] == "cuda:0" and info["use_tf32"] == "0"
    atol = TOLERANCE[precision] * float(np.abs(reference).max())
    np.testing.assert_allclose(_predict(session, X), reference, rtol=0, atol=atol)


@pytest.mark.gpu
@pytest.mark.skipif(TRT_INT8 is not None, reason=TRT_INT8 or "")
def test_tensorrt_int8_engines_live_in_the_artifact(source: SourceModel, tmp_path: Path) -> None:
    import onnxruntime as ort

    built = tmp_path / "artifact.tmp1" / "model"
    meta = BACKEND.convert(_request(source, built, "ptq_static", "int8", "tensorrt", max_batch=8,
                                   calibration_samples=30))
    cache = built / CACHE_DIR
    engines = sorted(p.name for p in cache.glob("*.engine"))
    assert engines and engines == meta["tensorrt"]["engines"] and all("_int8" in e for e in engines)
    assert (cache / CALIBRATION_TABLE).is_file() and any(cache.glob("*.profile"))
    assert not any(cache.glob("*.timing"))  # the timing cache is build state, kept outside the artifact
    final = tmp_path / "artifact" / "model"  # moved as the runner moves a finished artifact
    final.parent.mkdir()
    built.rename(final)
    files = {p.name: p.stat().st_mtime_ns for p in (final / CACHE_DIR).iterdir()}
    session = BACKEND.load(final, json.loads(json.dumps(meta)), "tensorrt", "int8", 1)
    got = _predict(session, X[:8])  # batches 1..8: the engine's shape profile
    assert {p.name: p.stat().st_mtime_ns for p in (final / CACHE_DIR).iterdir()} == files  # loaded, not rebuilt
    assert session.info()["providers"][0] == TRT and session.info()["io_binding"] == "cuda:0"
    reference = ort.InferenceSession(str(final / "model.onnx"), providers=[CPU]).run(None, {"input": X[:8]})[0]
    np.testing.assert_allclose(got, reference, rtol=0, atol=0.1 * float(reference.std(axis=0).min()))
    single = session.prepare({"input": X[:1]})
    np.testing.assert_array_equal(session.fetch(session.execute(single))[0], _predict(session, X[:1]))


def test_gpu_requirements_pin_the_releases_of_the_lock() -> None:
    """`make setup-gpu` swaps ONNX Runtime's CPU build for the GPU build of the same release and keeps torch's pin,
    so CPU and GPU cells measure the same library versions."""
    def pins(name: str) -> dict[str, str]:
        lines = (TESTS.parent / name).read_text().splitlines()
        return {line.split("==")[0].split("[")[0].strip().lower(): line.split("==")[1].strip()
                for line in lines if "==" in line and not line.startswith("#")}

    lock, gpu = pins("requirements.lock"), pins("requirements-gpu.txt")
    assert gpu["onnxruntime-gpu"] == lock["onnxruntime"]
    assert gpu["torch"] == lock["torch"]
    assert "onnxruntime" not in gpu
