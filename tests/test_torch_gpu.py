"""The PyTorch backends on GPU targets: precisions declared per target, GPU probes, dtype plumbing, Torch-TensorRT.

Without an NVIDIA GPU the GPU-only tests are deselected (tests/conftest.py says so in one line); with one but
without a library they skip with the backend's own probe reason. Everything else runs on the CPU with the real
torch (bf16 on the CPU only checks the dtype plumbing; it is not a supported cell)."""

from __future__ import annotations

import importlib.util
import inspect
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import tiny_models  # noqa: E402
from convert_helper import convert_with, request_for  # noqa: E402
from test_backends import CALIBRATION, X  # noqa: E402

import torch  # noqa: E402

from bench_matrix import hardware  # noqa: E402
from bench_matrix import registry  # noqa: E402
from bench_matrix.backend import Backend  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix_backends import torch_tensorrt as trt_backend  # noqa: E402
from bench_matrix_backends._torch import TorchSession, place  # noqa: E402
from bench_matrix_backends.pytorch import PyTorchBackend  # noqa: E402
from bench_matrix_backends.torchscript import TorchScriptBackend  # noqa: E402

BACKENDS: dict[str, Backend] = {"pytorch": PyTorchBackend(), "torchscript": TorchScriptBackend(),
                                "torch_tensorrt": trt_backend.TorchTensorRTBackend()}
T4 = hardware.Gpu("Tesla T4", "535.104.05", 15360, (7, 5))
P100 = hardware.Gpu("Tesla P100-PCIE-16GB", "535.104.05", 16384, (6, 0))
A100 = hardware.Gpu("NVIDIA A100-SXM4-80GB", "535.104.05", 81920, (8, 0))
# Relative to the largest output: 8 mantissa bits (bf16) or 11 (fp16) through a few layers; int8 like test_backends.
TOLERANCE = {"fp32": 1e-5, "fp16": 1e-2, "bf16": 3e-2}


def _atol(precision: str, reference: np.ndarray) -> float:
    if precision == "int8":
        return 0.1 * float(reference.std(axis=0).min())
    return TOLERANCE[precision] * float(np.abs(reference).max())


def _too_old(reason: str | None) -> list[str]:
    """The probe's 'GPU too old for the precision' reasons (hardware.precision_reason's wording)."""
    return re.findall(r"[^;]+ has compute capability [^;]+; [^;]+ needs [\d.]+ or newer", reason or "")


# ---- what each backend declares -------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["pytorch", "torchscript"])
def test_bf16_is_declared_on_cuda_only(name: str) -> None:
    backend = BACKENDS[name]
    for precision in ("fp32", "fp16", "bf16"):
        assert backend.invalid_reason("pytorch", "none", precision, "cuda") is None
    assert backend.invalid_reason("pytorch", "none", "bf16", "cpu") == f"{name} does not implement none at bf16 on cpu"
    assert backend.invalid_reason("pytorch", "none", "bf16", "tensorrt") is not None


def test_torch_tensorrt_declares_tensorrt_fp32_fp16_and_calibrated_int8() -> None:
    backend = BACKENDS["torch_tensorrt"]
    for kind, precision in (("none", "fp32"), ("none", "fp16"), ("ptq_static", "int8")):
        assert backend.invalid_reason("pytorch", kind, precision, "tensorrt") is None
    assert backend.invalid_reason("pytorch", "none", "bf16", "tensorrt") == (
        "torch_tensorrt does not implement none at bf16 on tensorrt")
    assert backend.invalid_reason("pytorch", "none", "fp16", "cuda") is not None
    assert backend.invalid_reason("pytorch", "ptq_dynamic", "int8", "tensorrt") is not None
    assert backend.invalid_reason("tensorflow", "none", "fp32", "tensorrt") == (
        "torch_tensorrt takes pytorch models, not tensorflow")


@pytest.mark.parametrize(("fmt", "kind", "options", "words"), [
    ("state_dict", "none", {}, None),
    ("torch_export", "none", {}, None),
    ("state_dict", "ptq_static", {}, None),
    ("state_dict", "ptq_static", {"per_channel": True, "method": "minmax", "calibration_samples": 10}, None),
    ("torchscript", "none", {}, "but this model is a TorchScript file; give it as factory + weights"),
    ("torch_export", "ptq_static", {}, "but this model is a torch.export program; give it as factory + weights"),
    ("state_dict", "ptq_static", {"per_channel": False}, "per_channel: false) are not available"),
    ("state_dict", "ptq_static", {"method": "entropy"}, "calibrates with minmax, not 'entropy'"),
    ("state_dict", "ptq_static", {"io": "int8"}, "io: int8 is not available"),
])
def test_torch_tensorrt_option_reasons(fmt: str, kind: str, options: dict[str, Any], words: str | None) -> None:
    reason = BACKENDS["torch_tensorrt"].option_reason(StrategySpec(kind, kind, options), fmt)
    assert reason == words if words is None else (reason and words in reason), reason


def test_torch_tensorrt_is_registered() -> None:
    assert "torch_tensorrt" in registry.available()
    assert isinstance(registry.load_backend("torch_tensorrt"), trt_backend.TorchTensorRTBackend)


# ---- probes -------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("gpu", "precision", "too_old"), [
    (T4, "bf16", "Tesla T4 has compute capability 7.5; bf16 needs 8.0 or newer"),
    (T4, "fp16", None),
    (P100, "bf16", "Tesla P100-PCIE-16GB has compute capability 6.0; bf16 needs 8.0 or newer"),
    (P100, "fp16", None),
    (A100, "bf16", None),
])
@pytest.mark.parametrize("name", ["pytorch", "torchscript"])
def test_cuda_precision_probe_names_the_gpu_too_old(name: str, gpu: hardware.Gpu, precision: str,
                                                    too_old: str | None, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hardware, "gpus", lambda: (gpu,))
    reason = BACKENDS[name].probe("cuda", precision) or ""
    assert [part.strip() for part in _too_old(reason)] == ([too_old] if too_old else [])
    assert "no NVIDIA GPU" not in reason  # the listed GPU counts as present
    if torch.version.cuda is None:
        assert f"torch {torch.__version__} is a CPU-only build (install a CUDA build of torch)" in reason


@pytest.mark.parametrize(("gpu", "precision", "too_old"), [
    (P100, "int8", "Tesla P100-PCIE-16GB has compute capability 6.0; TensorRT int8 needs 6.1 or newer"),
    (P100, "fp16", None),
    (T4, "int8", None),
])
def test_tensorrt_precision_probe_names_the_gpu_too_old(gpu: hardware.Gpu, precision: str, too_old: str | None,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hardware, "gpus", lambda: (gpu,))
    reason = BACKENDS["torch_tensorrt"].probe("tensorrt", precision)
    assert [part.strip() for part in _too_old(reason)] == ([too_old] if too_old else [])


def test_driver_too_old_for_torch_is_its_own_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    if torch.cuda.is_available():
        pytest.skip("torch uses a GPU here; this checks the reasons for one it cannot use")
    monkeypatch.setattr(hardware, "gpus", lambda: (A100,))
    monkeypatch.setattr(torch.version, "cuda", "12.4")  # what a CUDA build reports; torch itself stays CPU-only
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: (11, 8))
    assert BACKENDS["pytorch"].probe("cuda", "fp32") == (
        "torch is built for CUDA 12.4, but the NVIDIA driver supports CUDA up to 11.8: update the driver or install "
        "a torch build for CUDA 11")
    monkeypatch.setattr(hardware, "driver_cuda_version", lambda: (12, 8))  # new enough: another cause
    assert BACKENDS["torchscript"].probe("cuda", "fp32") == (
        f"torch {torch.__version__} (CUDA 12.4) cannot use the GPU that nvidia-smi lists: torch.cuda.is_available() "
        f"is False (check CUDA_VISIBLE_DEVICES and the GPU's compute mode)")


def test_gpu_probes_without_a_gpu_name_every_missing_piece() -> None:
    if not (no_gpu := hardware.no_gpu_reason()):
        pytest.skip("this machine has an NVIDIA GPU")
    for name, target in (("pytorch", "cuda"), ("torchscript", "cuda"), ("torch_tensorrt", "tensorrt")):
        reason = BACKENDS[name].probe(target, "bf16" if target == "cuda" else "fp16") or ""
        assert reason.startswith(no_gpu)
        assert (f"torch {torch.__version__} is a CPU-only build (install a CUDA build of torch)" in reason) == (
            torch.version.cuda is None)
    assert BACKENDS["pytorch"].probe("cpu", "fp32") is None


def test_torch_tensorrt_probe_names_the_package_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    backend = BACKENDS["torch_tensorrt"]
    major, minor = trt_backend.release(torch.__version__)
    install = f"pip install 'torch-tensorrt=={major}.{minor}.*'"
    monkeypatch.setattr(trt_backend, "torch_tensorrt_version", lambda: None)
    reason = backend.probe("tensorrt", "fp16") or ""
    assert f"Torch-TensorRT is not installed: {install} (its release for torch {torch.__version__})" in reason
    modelopt = ("int8 in Torch-TensorRT is calibrated by NVIDIA ModelOpt (modelopt.torch.quantization), which is not "
                "installed: pip install nvidia-modelopt")
    assert modelopt not in reason
    assert (modelopt in (backend.probe("tensorrt", "int8") or "")) == (importlib.util.find_spec("modelopt") is None)

    monkeypatch.setattr(trt_backend, "torch_tensorrt_version", lambda: "2.4.1")
    reason = backend.probe("tensorrt", "int8") or ""
    assert (f"torch-tensorrt 2.4.1 is built for torch 2.4, not the installed torch {torch.__version__}: {install}"
            in reason) == ((major, minor) != (2, 4))
    assert ("torch-tensorrt 2.4.1 has no int8 in its dynamo frontend (ModelOpt int8 came with 2.5): install torch "
            "and torch-tensorrt 2.5 or newer") in reason
    monkeypatch.setattr(trt_backend, "torch_tensorrt_version", lambda: f"{major}.{minor}.0")  # the matching release
    assert "torch-tensorrt" not in (backend.probe("tensorrt", "fp16") or "").lower()


def test_torch_tensorrt_probe_on_this_machine() -> None:
    if trt_backend.torch_tensorrt_version() is not None:
        pytest.skip("torch-tensorrt is installed here")
    reason = BACKENDS["torch_tensorrt"].probe("tensorrt", "fp32")
    assert reason and "Torch-TensorRT is not installed: pip install 'torch-tensorrt==" in reason


# ---- dtype plumbing (CPU, real torch) -----------------------------------------------------------------------------

@pytest.mark.parametrize(("precision", "dtype"), [("fp32", torch.float32), ("fp16", torch.float16),
                                                  ("bf16", torch.bfloat16), ("int8", torch.float32)])
def test_place_converts_to_the_precision_dtype(precision: str, dtype: torch.dtype) -> None:
    module = place(tiny_models.tiny().eval(), "cpu", precision)
    assert {p.dtype for p in module.parameters()} == {dtype}
    assert {b.dtype for b in module.buffers() if b.is_floating_point()} == {dtype}


def test_bf16_session_casts_inputs_and_returns_float32(source: SourceModel, reference: np.ndarray) -> None:
    session = TorchSession(place(source.load(), "cpu", "bf16"), "cpu", "bf16")
    (prepared,) = session.prepare({"input": X.astype(np.float64)})
    assert prepared.dtype == torch.bfloat16 and prepared.device.type == "cpu"
    out = session.execute((prepared,))
    assert out.dtype == torch.bfloat16
    (got,) = session.fetch(out)
    assert got.dtype == np.float32 and got.shape == reference.shape
    np.testing.assert_allclose(got, reference, rtol=0, atol=_atol("bf16", reference))
    assert np.abs(got - reference).max() > 1e-4  # it did compute in bf16, not in fp32


@pytest.mark.parametrize("name", ["pytorch", "torchscript"])
def test_backends_carry_bf16_through_convert_and_load(name: str, source: SourceModel, reference: np.ndarray,
                                                      tmp_path: Path) -> None:
    meta = convert_with(CALIBRATION, BACKENDS[name], source, tmp_path, "none", "bf16", "cpu")
    session = BACKENDS[name].load(tmp_path, meta, "cpu", "bf16", 1)
    if name == "torchscript":
        assert {p.dtype for p in torch.jit.load(str(tmp_path / meta["file"])).parameters()} == {torch.bfloat16}
    (got,) = session.predict({"input": X})
    np.testing.assert_allclose(got, reference, rtol=0, atol=_atol("bf16", reference))
    assert np.abs(got - reference).max() > 1e-4


@pytest.fixture
def tf32_flags():
    """The process's TensorFloat-32 flags, put back after the test."""
    before = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = before


def test_gpu_session_switches_tf32_off_and_says_so(tf32_flags) -> None:
    session = TorchSession(tiny_models.tiny(), "cuda", "fp16")  # nothing runs: only the settings are checked
    assert torch.backends.cudnn.allow_tf32 is False and torch.backends.cuda.matmul.allow_tf32 is False
    info = session.info()
    assert info["device"] == "cuda" and info["dtype"] == "float16" and info["tensor_float_32"] is False
    # torch.export reads the flags: the session left them in a state it can read (conv and RNN together)
    torch.export.export(tiny_models.tiny().eval(), (torch.zeros(1, 3, 16, 16),), strict=False)


# ---- Torch-TensorRT helpers that need no GPU ----------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["state_dict", "torch_export"])
def test_export_covers_batches_one_to_max_batch(fmt: str, source: SourceModel, reference: np.ndarray,
                                                tmp_path: Path) -> None:
    module = source.load()
    if fmt == "torch_export":
        path = tmp_path / "tiny.pt2"
        torch.export.save(torch.export.export(module, (torch.from_numpy(X[:4]),),
                                              dynamic_shapes=({0: torch.export.Dim("batch")},)), str(path))
        module = SourceModel(**{**source.__dict__, "format": fmt, "path": path, "factory": None}).load()
    program, (example,) = trt_backend.export(module, source.inputs, 8, "cpu", torch.float32, 0)
    assert example.shape == (2, *tiny_models.INPUT_SHAPE)
    with torch.inference_mode():
        for batch in (1, 8):
            got = program.module()(torch.from_numpy(X[:batch])).numpy()
            np.testing.assert_allclose(got, reference[:batch], rtol=0, atol=1e-5)
        with pytest.raises((AssertionError, RuntimeError)):  # and no further: the engine's profile ends there
            program.module()(torch.from_numpy(X[:9]))


def test_export_for_a_single_batch_is_static(source: SourceModel, reference: np.ndarray) -> None:
    program, (example,) = trt_backend.export(source.load(), source.inputs, 1, "cpu", torch.float32, 0)
    assert example.shape[0] == 1
    with torch.inference_mode():
        np.testing.assert_allclose(program.module()(torch.from_numpy(X[:1])).numpy(), reference[:1], atol=1e-5)
        with pytest.raises((AssertionError, RuntimeError)):  # the program's guards hold it to batch 1
            program.module()(torch.from_numpy(X[:2]))


# The three shapes torch_tensorrt.dynamo.compile's signature has had: weakly typed (enabled_precisions only, as in
# 2.4), with use_explicit_typing as well (later 2.x), and strongly typed only (the main branch, for TensorRT 11).
def _weakly_typed(exported_program: Any, inputs: Any, *, enabled_precisions: Any = None,
                  disable_tf32: bool = False, min_block_size: int = 5) -> None: ...


def _explicit_typing(exported_program: Any, inputs: Any = None, *, enabled_precisions: Any = None,
                     use_explicit_typing: bool = False, disable_tf32: bool = False,
                     min_block_size: int = 5) -> None: ...


def _strongly_typed(exported_program: Any, inputs: Any = None, *, disable_tf32: bool = False,
                    min_block_size: int = 5, **kwargs: Any) -> None: ...


BASE = {"disable_tf32": True, "min_block_size": 1}


@pytest.mark.parametrize(("compile_fn", "precision", "extra"), [
    (_weakly_typed, "fp32", {}), (_explicit_typing, "fp32", {}), (_strongly_typed, "fp32", {}),
    (_weakly_typed, "fp16", {"enabled_precisions": {torch.float16}}),
    (_explicit_typing, "fp16", {"use_explicit_typing": True}),
    (_strongly_typed, "fp16", {}),
    (_weakly_typed, "int8", {"enabled_precisions": {torch.int8}}),
    (_explicit_typing, "int8", {"enabled_precisions": {torch.int8}, "use_explicit_typing": False}),
    (_strongly_typed, "int8", {}),
])
def test_compile_options_follow_the_release(compile_fn: Any, precision: str, extra: dict[str, Any]) -> None:
    options = trt_backend.compile_options(compile_fn, precision)
    assert options == {**BASE, **extra}
    inspect.signature(compile_fn).bind(None, None, **options)  # every option is one this release takes


# ---- on an NVIDIA GPU ---------------------------------------------------------------------------------------------

def _gpu(name: str, target: str, precision: str) -> Any:
    """A GPU test case, skipped with the backend's own probe reason where it cannot run."""
    reason = BACKENDS[name].probe(target, precision)
    return pytest.param(name, precision, marks=[pytest.mark.gpu, pytest.mark.skipif(reason is not None,
                                                                                    reason=reason or "")],
                        id=f"{name}-{precision}")


@pytest.mark.parametrize(("name", "precision"), [_gpu(n, "cuda", p) for n in ("pytorch", "torchscript")
                                                 for p in ("fp32", "fp16", "bf16")])
def test_cuda_precision_matches_fp32(name: str, precision: str, source: SourceModel, reference: np.ndarray,
                                     tmp_path: Path) -> None:
    backend = BACKENDS[name]
    meta = convert_with(CALIBRATION, backend, source, tmp_path, "none", precision, "cuda")
    session = backend.load(tmp_path, meta, "cuda", precision, 1)
    prepared = session.prepare({"input": X})
    assert prepared[0].device.type == "cuda" and prepared[0].dtype == getattr(
        torch, {"fp32": "float32", "fp16": "float16", "bf16": "bfloat16"}[precision])
    (got,) = session.fetch(session.execute(prepared))
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, reference, rtol=0, atol=_atol(precision, reference))
    assert session.info()["device"] == "cuda"


@pytest.mark.parametrize(("name", "precision"), [_gpu("torch_tensorrt", "tensorrt", p)
                                                 for p in ("fp32", "fp16", "int8")])
def test_torch_tensorrt_matches_fp32(name: str, precision: str, source: SourceModel, reference: np.ndarray,
                                     tmp_path: Path) -> None:
    backend, kind = BACKENDS[name], "ptq_static" if precision == "int8" else "none"
    meta = backend.convert(request_for(CALIBRATION, source, tmp_path, kind, precision, "tensorrt", max_batch=8))
    assert [p.name for p in tmp_path.iterdir()] == [trt_backend.FILE]  # the engines are inside model.ep
    assert meta["engines"] >= 1 and meta["profile"] == {"min": 1, "opt": 1, "max": 8}
    session = trt_backend.TorchTensorRTBackend().load(tmp_path, meta, "tensorrt", precision, 1)
    atol = _atol(precision, reference) if precision != "fp32" else 1e-3 * float(np.abs(reference).max())
    for batch in (1, 8):  # both ends of the engine's profile
        np.testing.assert_allclose(session.predict({"input": X[:batch]})[0], reference[:batch], rtol=0, atol=atol)
    assert session.info()["engines"] == meta["engines"]


def test_export_gives_every_input_the_same_dynamic_batch(tmp_path: Path) -> None:
    """Torch-TensorRT's export of a two-input model (float features, int64 ids): one batch dimension for both,
    the ids kept int64 while the features take the precision's dtype."""
    from bench_matrix.tensors import TensorSpec

    inputs = (TensorSpec("features", (tiny_models.FEATURES,)), TensorSpec("ids", (tiny_models.TOKENS,), "int64"))
    program, example = trt_backend.export(tiny_models.two_inputs(), inputs, 8, "cpu", torch.float32, 0)
    assert [t.dtype for t in example] == [torch.float32, torch.int64] and [len(t) for t in example] == [2, 2]
    data = tiny_models.token_data(8, 0)
    with torch.inference_mode():
        got = program.module()(*(torch.from_numpy(a) for a in data.values()))
        expected = tiny_models.two_inputs()(*(torch.from_numpy(a) for a in data.values()))
    np.testing.assert_allclose(got.numpy(), expected.numpy(), rtol=0, atol=1e-6)
    free = SourceModel(name="m", framework="pytorch", format="state_dict", path=tmp_path / "m.pt", sha256="",
                       inputs=(TensorSpec("ids", (None,), "int64"),))
    assert "builds engines for fixed sample shapes, but input ids (?) int64 has a free axis" in (
        trt_backend.free_axes_reason(free) or "")
