"""Targets, precisions and options that an installed backend declares (tests/plugin_npu.py, installed as a
distribution): accepted by the matrix, listed by `bench-matrix schema`, typos refused with did-you-mean."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from bench_matrix import registry
from bench_matrix.errors import MatrixError
from bench_matrix.matrix.load import load_matrix
from bench_matrix.registry import vocabulary
from conftest import TESTS, cli
from fuzz_cases import onnx_model

MATRIX = """\
models: [{name: tiny, framework: onnx, file: tiny.onnx}]
dataset: {synthetic: {samples: 32}}
axes: {backend: [npu_rt], strategy: [none], precision: [fp32, int4], target: [cpu, npu]}
backend_options: {npu_rt: {hint: latency, streams: 2}}
"""
ENTRY_POINTS = ("npu_rt = plugin_npu:NpuBackend\nbad_opts = plugin_npu:BadOptionsBackend\n"
                "fake_gpu = plugin_npu:FakeGpuBackend\ngone = no_such_module_of_bench_matrix:Backend\n")
FAST = ("settings: {window_s: 0.01, min_rounds: 2, timing_budget_s: 0.05, warmup_s: 0.0, batch_size: 4, "
        "processes: 1}\n")


def install(root: Path) -> Path:
    """Install the test backends as distribution 'npu-rt' as pip would: a .dist-info with entry points."""
    dist = root / "site" / "npu_rt-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: npu-rt\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bench_matrix.backends]\n" + ENTRY_POINTS)
    return root / "site"


@pytest.fixture
def project(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder with tiny.onnx, the plugin installed on sys.path (and in PYTHONPATH for the CLI)."""
    (tmp_path / "tiny.onnx").write_bytes(onnx_model())
    site = install(tmp_path)
    monkeypatch.syspath_prepend(str(site))
    paths = [str(site), str(TESTS), os.environ.get("PYTHONPATH", "")]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))
    return tmp_path


def load(project: Path, text: str):
    path = project / "m.yaml"
    path.write_text(text)
    return load_matrix(path, backends=["npu_rt", "onnxruntime"])


def problems(project: Path, text: str) -> list[str]:
    with pytest.raises(MatrixError) as info:
        load(project, text)
    return info.value.problems


def test_vocabulary_lists_what_each_installed_backend_declares(project):
    found = vocabulary()
    assert found.targets["npu"] == ["npu_rt"] and found.precisions["int4"] == ["npu_rt"]
    assert "npu_rt" in found.targets["cpu"] and "onnxruntime" in found.targets["cpu"]
    assert found.options["npu_rt"]["hint"]["enum"] == ["latency", "throughput"]
    assert "ModuleNotFoundError" in found.broken["gone"] and "gone" not in found.options
    assert "not a valid JSON Schema" in found.broken["bad_opts"] and "bad_opts" not in found.options


def test_declared_target_precision_and_options_are_accepted(project):
    matrix = load(project, MATRIX + "exclude: [{target: npu, precision: fp32}]\n")
    assert matrix.axes["precision"] == ("fp32", "int4") and matrix.axes["target"] == ("cpu", "npu")
    assert matrix.backend_options == {"npu_rt": {"hint": "latency", "streams": 2}}
    assert dict(matrix.exclude[0].values) == {"precision": "fp32", "target": "npu"}


@pytest.mark.parametrize("change, message", [
    (("target: [cpu, npu]", "target: [cpu, nppu]"),
     # the built-in targets, then those of installed backends (openvino's where it is installed), then npu
     (":3: axes.target[1]: 'nppu' is not allowed; allowed: cpu, cuda, tensorrt, ",
      ", npu; did you mean 'npu'?")),
    (("precision: [fp32, int4]", "precision: [fp32, int44]"),
     ":3: axes.precision[1]: 'int44' is not allowed; allowed: fp32, fp16, bf16, int8, int4; "
     "did you mean 'int4'?"),
    (("hint: latency", "hnt: latency"),
     ":4: backend_options.npu_rt.hnt: unknown key 'hnt'; allowed: hint, streams; did you mean 'hint'?"),
    (("hint: latency", "hint: fast"),
     ":4: backend_options.npu_rt.hint: 'fast' is not allowed; allowed: latency, throughput"),
    (("streams: 2", "streams: '2'"), ":4: backend_options.npu_rt.streams: expected integer, got str '2'"),
    (("streams: 2", "streams: 64"), ":4: backend_options.npu_rt.streams: must be <= 16, got 64"),
    (("{npu_rt: {", "{npu_tr: {"), ":4: backend_options.npu_tr: unknown key 'npu_tr'; allowed: "),
    (("npu_rt: {hint: latency, streams: 2}", "onnxruntime: {hint: latency}"),
     ":4: backend_options.onnxruntime.hint: unknown key 'hint'; "
                                        "backend onnxruntime declares no options"),
])
def test_mistakes_in_declared_vocabulary_are_located(project, change, message):
    (problem,) = problems(project, MATRIX.replace(*change))
    parts = message if isinstance(message, tuple) else (message,)
    assert problem.startswith(str(project / "m.yaml")) and all(part in problem for part in parts), problem
    if "npu_tr" in parts[0]:
        assert "did you mean 'npu_rt'?" in problem


def test_selector_values_include_declared_ones_with_did_you_mean(project):
    (problem,) = problems(project, MATRIX + "include: [{target: npux}]\n")
    assert "include[0].target: 'npux' is not a known target; known: cpu, cuda, tensorrt, " in problem
    assert ", npu; did you mean" in problem
    assert "did you mean 'npu'?" in problem


@pytest.mark.parametrize("backend, reason", [("gone", "failed to import: ModuleNotFoundError"),
                                             ("bad_opts", "its options are not a valid JSON Schema")])
def test_options_of_a_backend_that_cannot_be_used_are_refused(project, backend, reason):
    text = MATRIX.replace("backend_options: {", f"backend_options: {{{backend}: {{}}, ")
    (problem,) = problems(project, text)
    expected = f":4: backend_options.{backend}: backend {backend} cannot be used, so its options cannot be "
    assert expected in problem and reason in problem, problem


def test_without_the_plugin_its_vocabulary_is_refused(tmp_path):
    (tmp_path / "tiny.onnx").write_bytes(onnx_model())
    with pytest.raises(MatrixError) as info:
        load(tmp_path, MATRIX)
    found = "\n".join(info.value.problems)
    assert "axes.precision[1]: 'int4' is not allowed; allowed: fp32, fp16, bf16, int8; did you mean 'int8'?" \
        in found
    assert "axes.target[1]: 'npu' is not allowed; allowed: cpu, cuda, tensorrt" in found
    assert "backend_options.npu_rt: unknown key 'npu_rt'; allowed: aot_inductor, keras_predict, onnxruntime" \
        in found


def test_targets_are_only_those_installed_backends_declare(project, monkeypatch):
    """bench-matrix knows no target of its own: with npu_rt the only backend installed, cuda is refused."""
    only = {name: entry for name, entry in registry.available().items() if name == "npu_rt"}
    monkeypatch.setattr(registry, "available", lambda: only)
    (problem,) = problems(project, MATRIX.replace("target: [cpu, npu]", "target: [cpu, cuda]"))
    assert ":3: axes.target[1]: 'cuda' is not allowed; allowed: cpu, npu" in problem, problem


def test_schema_command_lists_the_installed_vocabulary(project):
    done = cli(project, "schema", env={"PYTHONPATH": os.environ["PYTHONPATH"]})
    assert done.returncode == 0, done.stderr
    schema = json.loads(done.stdout)
    axes = schema["properties"]["axes"]["properties"]
    assert "npu" in axes["target"]["items"]["enum"] and "int4" in axes["precision"]["items"]["enum"]
    options = schema["properties"]["backend_options"]
    assert options["properties"]["npu_rt"]["properties"]["hint"]["enum"] == ["latency", "throughput"]
    assert options["additionalProperties"] is False
    assert "failed to import" in options["properties"]["gone"]["x-message"]
    builtin = cli(project, "schema", "--builtin")
    assert builtin.stdout == (TESTS.parent / "docs" / "matrix.schema.json").read_text()


def test_plan_exits_2_on_a_typo_in_declared_vocabulary(project):
    (project / "m.yaml").write_text(MATRIX.replace("hint: latency", "hint: latncy"))
    done = cli(project, "plan", "m.yaml", env={"PYTHONPATH": os.environ["PYTHONPATH"]})
    assert done.returncode == 2, done.stdout + done.stderr
    assert ("backend_options.npu_rt.hint: 'latncy' is not allowed; allowed: latency, throughput; did you "
            "mean 'latency'?") in done.stderr


@pytest.mark.slow
def test_a_plugin_target_and_its_options_run_end_to_end(project):
    """The npu target (emulated on ONNX Runtime's CPU provider) runs, the options reach the conversion, the
    plugin's versions are in the record, its int4 is skipped with the plugin's reason."""
    (project / "m.yaml").write_text(MATRIX + FAST)
    run = cli(project, "run", "m.yaml", env={"NPU_RT_EMULATE": "1"})
    assert run.returncode == 0, run.stdout + run.stderr
    assert "2 ok, 2 skipped, 0 failed" in run.stdout
    out = cli(project, "report", "--format", "json")
    found = {(r["cell"]["precision"], r["cell"]["target"]): r for r in json.loads(out.stdout)["records"]}
    npu = found[("fp32", "npu")]
    assert npu["status"] == "ok" and npu["metrics"]["session"] == {"hint": "latency", "streams": 2}
    assert npu["env"]["backend_versions"] == {"npu-rt": "0.1"} and npu["metrics"]["cosine_similarity"] > 0.999
    assert "int4 needs an NPU compiler" in found[("int4", "npu")]["reason"]


@pytest.mark.slow
def test_a_target_its_backend_runs_on_cuda_is_also_timed_end_to_end(project):
    """The measure job asks the loaded backend where the target runs: on cuda (here emulated on the CPU) the
    latency is also timed end to end and the GPU's name and memory are recorded; on the CPU they are not."""
    text = MATRIX.split("axes:")[0] + "axes: {backend: [fake_gpu], strategy: [none], precision: [fp32], " \
                                      "target: [cpu, fake_gpu]}\n"
    (project / "m.yaml").write_text(text + FAST)
    run = cli(project, "run", "m.yaml")
    assert run.returncode == 0 and "2 ok, 0 skipped, 0 failed" in run.stdout, run.stdout + run.stderr
    found = {r["cell"]["target"]: r["metrics"] for r in json.loads(cli(project, "report", "--format",
                                                                         "json").stdout)["records"]}
    gpu_only = {"latency_ms_e2e", "gpu_name", "peak_gpu_mem_mb", "gpu_mem_method"}
    assert gpu_only <= set(found["fake_gpu"]) and not gpu_only & set(found["cpu"])
