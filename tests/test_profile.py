"""Per-operator profiles (the profile scenario, Session.profile): ONNX Runtime's dynamic int8 keeps its
convolution at fp32 and runs its Gemm at int8, OpenVINO's fp32 layers are profiled, a backend without a hook
records why, and through the CLI the record, the report's section and a bad section's location."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import tiny_models
from bench_matrix.op_profile import KINDS, PRECISIONS, OperatorTime, Profile, kind_of
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import TensorSpec
from conftest import cli, install_slow_plugin, onnx_matrix_text
from convert_helper import convert_with

X = np.random.default_rng(0).random((1, 3, 16, 16), np.float32)
# A torch profile's operators (self CPU times) add up to at most TORCH_SHARE[1] of the profiled calls' own
# wall time (AOTInductor's call's time outside ops holds the profiler's record_function: 104-116 %; total
# instead of self times would give several times it), and in the best of TRIES profiles to at least
# TORCH_SHARE[0]: the rest is Python and the profiler's bookkeeping between ops, which a busy machine
# stretches (measured on 2 busy cores: at batch 32 eager 75-78 %, TorchScript 89-91 %; at batch 8 28-92 %
# eager)
TORCH_SHARE, TRIES, CALLS = (0.5, 1.3), 3, 20


def conv_gemm(folder: Path) -> Path:
    """tiny_models.conv_gemm saved as fp32.onnx in `folder`."""
    import onnx

    path = folder / "fp32.onnx"
    onnx.save(tiny_models.conv_gemm(), str(path))
    return path


def by_kind(profile: Profile) -> dict[str, set[str]]:
    """Each kind's precisions in the profile."""
    found: dict[str, set[str]] = {}
    for op in profile.operators:
        found.setdefault(op.kind, set()).add(op.precision)
    return found


def test_onnxruntime_dynamic_int8_runs_its_conv_at_fp32_and_its_gemm_at_int8(tmp_path: Path) -> None:
    from onnxruntime.quantization import QuantType, quantize_dynamic

    from bench_matrix_backends.onnxruntime import OnnxRuntimeBackend

    quantize_dynamic(conv_gemm(tmp_path), tmp_path / "model.onnx", op_types_to_quantize=["MatMul", "Gemm"],
                     reduce_range=True, weight_type=QuantType.QInt8)
    meta = {"file": "model.onnx", "inputs": {"input": "X"}}
    session = OnnxRuntimeBackend().load(tmp_path, meta, "cpu", "int8", 1)
    profile = session.profile(session.prepare({"input": X}), 5)
    assert profile.problem() is None and profile.calls == 5
    kinds = by_kind(profile)
    assert kinds["conv"] == {"fp32"} and kinds["matmul"] == {"int8"}
    assert math.isclose(sum(op.ms for op in profile.operators), profile.total_ms)
    fields = profile.fields()
    total = sum(op["ms"] for op in fields["profile_operators"])
    assert math.isclose(total, fields["profile_ms"], rel_tol=1e-4)
    assert not list(tmp_path.glob("*.json"))  # the trace went with its temporary folder


def test_openvino_fp32_profile_has_its_convolution(tmp_path: Path) -> None:
    from bench_matrix_backends.openvino import OpenVinoBackend

    path = conv_gemm(tmp_path)
    session = OpenVinoBackend().load(tmp_path, {"file": path.name, "inputs": {"input": "X"}, "options": {}},
                                     "cpu", "fp32", 1)
    profile = session.profile(session.prepare({"input": X}), 3)
    assert profile.problem() is None
    kinds = by_kind(profile)
    assert kinds["conv"] == {"fp32"} and kinds["matmul"] == {"fp32"}
    assert {op.kind for op in profile.operators} <= set(KINDS)
    assert {op.precision for op in profile.operators} <= set(PRECISIONS)


def test_kinds_and_what_is_no_result() -> None:
    assert [kind_of(t) for t in ("QLinearConv", "Convert", "DynamicQuantizeMatMul", "FullyConnected",
                                 "MaxPool", "Relu", "Reorder", "DequantizeLinear", "Add", "QLinearAdd",
                                 "TensorSliceDataset", "Maximum")] == \
        ["conv", "quant", "matmul", "matmul", "pool", "activation", "reshape", "quant"] + ["other"] * 3 + \
        ["activation"]
    torch_ops = ("aten::addmm", "aten::mm", "quantized::linear_dynamic", "aten::linear",
                 "mkldnn::_convolution_pointwise", "quantized::conv2d_relu", "aten::clamp_min",
                 "aten::max_pool2d", "aten::quantize_per_tensor", "aten::_unsafe_view", "CompiledFxGraph",
                 "aot_inductor::generated_kernels")
    assert [kind_of(t) for t in torch_ops] == ["matmul"] * 4 + ["conv", "conv", "activation", "pool", "quant",
                                                                 "reshape", "other", "other"]
    zero = OperatorTime("c", "Conv", "conv", "fp32", 0.0)
    assert Profile((zero,), 5).problem() == "the profiler reported zero time for every operator"
    infinite = OperatorTime("c", "Conv", "conv", "fp32", math.inf)
    assert "finite" in Profile((zero, infinite), 5).problem()
    assert Profile(reason="none here").fields() == {"profile_reason": "none here"}


@pytest.fixture(scope="module")
def profiled(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, str]]:
    """tiny.onnx through ONNX Runtime and through the slow_ort plugin (no profiler hook), profiled."""
    import fuzz_cases

    project = fuzz_cases.write_project(tmp_path_factory.mktemp("profile"))
    env = {**install_slow_plugin(project), "SLOW_ORT_DELAY_MS": "0"}
    text = onnx_matrix_text(["tiny"], ["fp32"], "profile: {calls: 5}\n")
    (project / "m.yaml").write_text(text.replace("[onnxruntime]", "[onnxruntime, slow_ort]"))
    out = cli(project, "run", "m.yaml", env=env)
    assert out.returncode == 0, out.stdout + out.stderr
    return project, env


def test_a_run_stores_the_profile_and_the_report_shows_it(profiled: tuple[Path, dict[str, str]]) -> None:
    project, env = profiled
    out = cli(project, "report", "--format", "json", env=env)
    records = {r["cell"]["backend"]: r["metrics"] for r in json.loads(out.stdout)["records"]}
    ort = records["onnxruntime"]
    assert ort["profile_calls"] == 5 and {op["op_type"] for op in ort["profile_operators"]} >= {"MatMul"}
    assert math.isclose(sum(op["ms"] for op in ort["profile_operators"]), ort["profile_ms"], rel_tol=1e-4)
    assert records["slow_ort"]["profile_reason"].startswith("slow_ort: no profiler hook")
    assert "profile_operators" not in records["slow_ort"] and "machine_flops" not in records["slow_ort"]
    assert ort["work_flops"] > 0 and ort["work_bytes"] > ort["work_weight_bytes"] > 0  # tiny.onnx's MatMuls
    assert ort["machine_threads"] == 1 and ort["machine_flops"]["fp32"] > 0 and ort["machine_bandwidth"] > 0
    out = cli(project, "report", "--format", "md", "--out", str(project / "pages"), env=env)
    page = (project / "pages" / "tiny.md").read_text()
    assert "## Where the time goes" in page and "Roofline %" in page
    assert "| onnxruntime none fp32 (baseline) |" in page
    assert "Not profiled: slow_ort none fp32: slow_ort: no profiler hook" in page
    assert {p.name for p in (project / "pages" / "plots").glob("*-tiny.png")} >= {"profile-tiny.png",
                                                                                 "roofline-tiny.png"}
    out = cli(project, "report", "--format", "md", "--backend", "slow_ort", "--out", str(project / "slow"),
              env=env)
    assert out.returncode == 0 and "Where the time goes" not in (project / "slow" / "tiny.md").read_text()
    assert not [*(project / "slow").rglob("profile-*")] and not [*(project / "slow").rglob("roofline-*")]


def test_a_bad_profile_value_exits_2_naming_file_line_and_key(onnx_project: Path) -> None:
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"], "profile: {calls: 0}\n"))
    out = cli(onnx_project, "plan", "m.yaml")
    assert out.returncode == 2 and "m.yaml:6: profile.calls" in out.stderr, out.stderr


def profiled_shares(session: Any, inputs: dict[str, np.ndarray],
                    bounds: tuple[float, float] = TORCH_SHARE) -> tuple[Profile, list[float]]:
    """The session's profile of CALLS calls of `inputs`, checked for kinds and precisions, and in each of
    TRIES profiles its operators' time ÷ the profiled calls' own wall time (each execute timed; the
    unprofiled call and the warm-up left out): all at most bounds[1], the best at least bounds[0]."""
    spent: list[float] = []
    execute = session.execute

    def timed(prepared: Any) -> Any:
        begin = time.perf_counter()
        outputs = execute(prepared)
        spent.append(time.perf_counter() - begin)
        return outputs

    session.execute = timed
    prepared, shares = session.prepare(inputs), []
    try:
        for _ in range(TRIES):
            spent.clear()
            profile = session.profile(prepared, CALLS)
            assert profile.problem() is None and profile.calls == CALLS
            assert len(spent) >= CALLS + 1
            shares.append(profile.total_ms / (math.fsum(spent[-CALLS:]) * 1e3))
    finally:
        del session.execute  # the class's again: the session may be a module fixture's
    assert {op.kind for op in profile.operators} <= set(KINDS)
    assert {op.precision for op in profile.operators} <= set(PRECISIONS)
    assert bounds[0] <= max(shares) and max(shares) <= bounds[1], shares
    return profile, shares


@pytest.mark.parametrize(("name", "strategy", "precision", "conv", "matmul"), [
    ("pytorch", "none", "fp32", "fp32", "fp32"), ("torchscript", "ptq_dynamic", "int8", "fp32", "int8"),
    ("torchscript", "ptq_static", "int8", "int8", "int8")])
def test_torch_profile_adds_up_to_its_calls_at_the_precisions_that_ran(
        name: str, strategy: str, precision: str, conv: str, matmul: str, tiny_project: Path) -> None:
    from bench_matrix_backends.pytorch import PyTorchBackend
    from bench_matrix_backends.torchscript import TorchScriptBackend

    backend = PyTorchBackend() if name == "pytorch" else TorchScriptBackend()
    path = tiny_project / "tiny.pt"
    source = SourceModel(name="tiny", framework="pytorch", format="state_dict", path=path, sha256="0",
                         inputs=(TensorSpec("input", tiny_models.INPUT_SHAPE),), factory="tiny_models:tiny",
                         python_path=(str(Path(__file__).parent),))
    out = tiny_project / "artifact"
    meta = convert_with(tiny_models.images(8, 1), backend, source, out, strategy, precision)
    session = backend.load(out, meta, "cpu", precision, 1)
    profile, _ = profiled_shares(session, {"input": tiny_models.images(32, 0)})
    kinds = by_kind(profile)
    assert kinds["conv"] == {conv} and kinds["matmul"] == {matmul}, kinds


def test_a_torch_gpu_cell_says_why_it_has_no_profile() -> None:
    import torch

    from bench_matrix_backends._torch import TorchSession

    before = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    try:  # a GPU session switches TF32 off for the process: put it back for the tests after this one
        profile = TorchSession(torch.nn.Linear(2, 2), "cuda", "fp16").profile((), 5)
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = before
    assert profile.operators == () and "kernel launches" in profile.fields()["profile_reason"]
