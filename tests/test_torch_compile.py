"""torch_compile and aot_inductor against the real torch.compile and AOTInductor on the fitted tiny model.

Inductor compiles take tens of seconds on 2 cores: the compiled session and the package are module
fixtures."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

from conftest import cli, matrix_text  # noqa: E402
from convert_helper import convert_with, request_for  # noqa: E402
from test_backends import CALIBRATION, X, _atol  # noqa: E402
from test_profile import by_kind, profiled_shares  # noqa: E402

import torch  # noqa: E402

from bench_matrix.errors import MatrixError  # noqa: E402
from bench_matrix.matrix.load import load_matrix  # noqa: E402
from bench_matrix.strategy import StrategySpec  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402
from bench_matrix_backends._inductor import compiled_graphs  # noqa: E402
from bench_matrix_backends.torch_compile import AOT_KERNELS, AotInductorBackend, \
    TorchCompileBackend  # noqa: E402

JIT, AOT = TorchCompileBackend(), AotInductorBackend()
BATCH = 8  # the throughput batch (max_batch) the artifacts are made for
NONE = StrategySpec("none", "none", {})
# Run in a fresh process, as the runner does: convert (argv: source JSON, out dir, backend class), or load and
# predict (argv: meta JSON, out dir, inputs .npy), printing JSON.
CONVERT = f"""
import json, sys
from pathlib import Path
sys.path.insert(0, {str(TESTS)!r})
from convert_helper import convert_with
from bench_matrix.sources import SourceModel
from bench_matrix_backends import torch_compile

source = SourceModel.from_dict(json.loads(sys.argv[1]))
backend = getattr(torch_compile, sys.argv[3])()
print(json.dumps(convert_with([], backend, source, Path(sys.argv[2]), max_batch={BATCH})))
"""
PREDICT = f"""
import json, sys
from pathlib import Path
import numpy as np, torch
from bench_matrix_backends.torch_compile import AotInductorBackend

session = AotInductorBackend().load(Path(sys.argv[2]), json.loads(sys.argv[1]), "cpu", "fp32", 2)
x = np.load(sys.argv[3])
outputs = {{n: session.predict({{"input": x[:n]}})[0].tolist() for n in (1, 5, {BATCH})}}
print(json.dumps({{"outputs": outputs, "info": session.info(), "threads": torch.get_num_threads()}}))
"""


def fresh_process(code: str, *args: str, home: Path) -> str:
    """Run `code` in a new Python whose temporary directory and home are `home`/tmp and `home`/home."""
    for name in ("tmp", "home"):
        (home / name).mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "TMPDIR": str(home / "tmp"), "HOME": str(home / "home")}
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


def written(home: Path) -> list[str]:
    """Every file a fresh_process left in its temporary directory or home."""
    return sorted(str(p.relative_to(home)) for p in home.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def jit_loaded(source: SourceModel,
               tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, Any, float]:
    """The tiny model converted by torch_compile in a fresh process (the compilation its artifact keeps is
    then a fresh process's, as in a run) and loaded here for batches 1 and 8, one thread, and the seconds the
    load took."""
    out = tmp_path_factory.mktemp("jit")
    meta = json.loads(fresh_process(CONVERT, json.dumps(source.to_dict()), str(out), "TorchCompileBackend",
                                    home=tmp_path_factory.mktemp("jit-home")))
    begin = time.perf_counter()
    session = JIT.load(out, meta, "cpu", "fp32", 1)
    return out, meta, session, time.perf_counter() - begin


@pytest.fixture(scope="module")
def jit(jit_loaded) -> tuple[Path, dict[str, Any], Any]:
    return jit_loaded[:3]


@pytest.fixture(scope="module")
def aot(source: SourceModel, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, Any]]:
    """The AOTInductor package of the tiny model for batches 1..8, converted in a fresh process whose
    temporary directory and home are watched: (that process's home, the artifact folder, the metadata)."""
    home, out = tmp_path_factory.mktemp("aot-home"), tmp_path_factory.mktemp("aot")
    meta = fresh_process(CONVERT, json.dumps(source.to_dict()), str(out), "AotInductorBackend", home=home)
    return home, out, json.loads(meta)


def _predict(session: Any, x: np.ndarray) -> np.ndarray:
    (out,) = session.predict({"input": x})
    return out


# ---- torch.compile -----------------------------------------------------------------------------------------

def test_compiled_outputs_match_eager_at_both_batch_sizes(jit, reference: np.ndarray) -> None:
    _, _, session = jit
    for rows in (slice(0, 1), slice(3, 4), slice(0, BATCH), slice(BATCH, 2 * BATCH)):
        np.testing.assert_allclose(_predict(session, X[rows]), reference[rows], rtol=0,
                                   atol=_atol("fp32", reference))


def test_compile_time_is_reported_apart_from_the_timed_calls(jit_loaded) -> None:
    out, meta, session, load_s = jit_loaded
    # the source itself, and the Inductor cache of its compilation for the cell's batch sizes
    assert sorted(p.name for p in out.iterdir()) == ["inductor-cache", "tiny.pt"]
    assert meta["options"] == {"mode": "default", "dynamic": False, "fullgraph": False}
    info = session.info()
    assert 0 < info["compile_s"] <= load_s and info["compiled_batches"] == [BATCH, 1]  # part of the load
    assert info["graphs"] == 2 and info["graph_breaks"] == 0  # one graph per batch size, nothing left eager
    assert {k: info[k] for k in ("device", "threads", "mode", "dynamic", "cuda_graphs")} == {
        "device": "cpu", "threads": 1, "mode": "default", "dynamic": False, "cuda_graphs": False}
    json.dumps(info)


WARM = """
import json, sys
from pathlib import Path
from bench_matrix_backends.torch_compile import TorchCompileBackend

session = TorchCompileBackend().load(Path(sys.argv[2]), json.loads(sys.argv[1]), "cpu", "fp32", 1)
print(json.dumps(session.info()))
"""


def test_a_load_compiles_from_the_cache_the_artifact_carries(jit, tmp_path: Path) -> None:
    """Compiled once, when converted: a load in a fresh process takes both graphs from the artifact's cache,
    and leaves nothing behind (the artifact is read, not written)."""
    out, meta, _ = jit
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    info = json.loads(fresh_process(WARM, json.dumps(meta), str(out), home=tmp_path))
    assert (info["cache_hits"], info["cache_misses"], info["graphs"]) == (2, 0, 2), info
    assert info["compile_s"] < meta["convert_compile_s"], (info, meta)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    assert written(tmp_path) == []


def test_timed_calls_never_recompile(jit) -> None:
    _, _, session = jit
    before = compiled_graphs()
    with torch._dynamo.config.patch(error_on_recompile=True):
        for rows in (slice(0, 1), slice(5, 6), slice(0, BATCH), slice(BATCH, 2 * BATCH), slice(2, 3)):
            session.execute(session.prepare({"input": X[rows]}))
        assert compiled_graphs() == before
        with pytest.raises(torch._dynamo.exc.RecompileError):  # what a batch size not compiled at load does
            session.execute(session.prepare({"input": X[:5]}))


def test_dynamic_batch_axis_serves_every_batch_with_the_threads_asked(jit, reference: np.ndarray) -> None:
    out, meta, _ = jit
    meta = {**meta, "options": {**meta["options"], "dynamic": True}}
    session = JIT.load(out, meta, "cpu", "fp32", 2)
    info = session.info()
    assert info["threads"] == 2 == torch.get_num_threads() and info["dynamic"] is True
    assert info["graphs"] == 2  # the batch axis symbolic for batches of 2 and more; batch 1 its own graph
    with torch._dynamo.config.patch(error_on_recompile=True):
        for rows in (slice(0, 1), slice(0, 5), slice(3, 6), slice(0, BATCH)):
            np.testing.assert_allclose(_predict(session, X[rows]), reference[rows], rtol=0,
                                       atol=_atol("fp32", reference))


def test_compiled_profiles_add_up_to_their_calls_fused_kernels_as_other(jit, aot) -> None:
    """torch.compile's fused kernels run in its compiled graph's call (CompiledFxGraph), AOTInductor's in the
    time its package's call spends outside aten ops; convolutions stay aten ops (extern kernels) at fp32."""
    profile, _ = profiled_shares(jit[2], {"input": X[:BATCH]})
    assert {"CompiledFxGraph", "TorchDynamo Cache Lookup"} <= {op.op_type for op in profile.operators}
    assert by_kind(profile)["conv"] == {"fp32"}
    profile, _ = profiled_shares(AOT.load(aot[1], aot[2], "cpu", "fp32", 1), {"input": X[:BATCH]})
    kernels = [op for op in profile.operators if op.op_type == AOT_KERNELS]
    assert len(kernels) == 1 and kernels[0].kind == "other" and kernels[0].ms > 0
    assert by_kind(profile)["conv"] == {"fp32"}


# ---- AOTInductor -------------------------------------------------------------------------------------------

def test_package_conversion_writes_only_into_its_output_directory(aot, source: SourceModel) -> None:
    home, out, meta = aot
    assert [p.name for p in out.iterdir()] == ["model.pt2"]  # Inductor's cache was in out_dir, then removed
    assert (out / "model.pt2").stat().st_size > source.path.stat().st_size  # compiled code and the weights
    assert written(home) == []  # nothing in the temporary directory or home
    assert meta["file"] == "model.pt2" and meta["max_batch"] == BATCH and meta["mode"] == "default"
    assert meta["inductor_configs"]["cpp.dynamic_threads"] is True


@pytest.mark.slow
def test_package_loads_in_a_fresh_process_for_every_batch_size(aot, reference: np.ndarray,
                                                               tmp_path: Path) -> None:
    _, out, meta = aot
    np.save(tmp_path / "x.npy", X)
    result = json.loads(fresh_process(PREDICT, json.dumps(meta), str(out),
                                      str(tmp_path / "x.npy"), home=tmp_path / "load"))
    for n, got in result["outputs"].items():
        np.testing.assert_allclose(np.array(got), reference[:int(n)], rtol=0, atol=_atol("fp32", reference))
    assert result["threads"] == 2 == result["info"]["threads"]
    assert result["info"]["batch_range"] == [1, BATCH]
    assert "compile_s" not in result["info"]  # compiled before, at conversion
    assert written(tmp_path / "load") == []  # the private Inductor cache went with the process


# ---- declarations, options and probes ----------------------------------------------------------------------

@pytest.mark.parametrize("backend", [JIT, AOT], ids=lambda b: b.name)
def test_sources_they_take_and_refuse(backend, source: SourceModel, tmp_path: Path) -> None:
    assert backend.option_reason(NONE, "state_dict") is None
    assert backend.option_reason(NONE, "torch_export") is None
    reason = backend.option_reason(NONE, "torchscript")
    assert reason == (f"{backend.name} compiles an nn.Module or a torch.export program (TorchDynamo and "
                      f"torch.export trace Python code, not TorchScript), but this model is a TorchScript "
                      f"file; give it as factory + weights (a state_dict) or as a torch.export .pt2 file")
    free = SourceModel(**{**source.__dict__, "inputs": (TensorSpec("input", (3, None, 16)),)})
    with pytest.raises(ValueError, match=r"compiles for fixed sample shapes .* declare its length"):
        convert_with(CALIBRATION, backend, free, tmp_path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("backend", [JIT, AOT], ids=lambda b: b.name)
def test_declarations_and_probes(backend, monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    assert backend.invalid_reason("pytorch", "none", "fp32", "cpu") is None
    assert backend.invalid_reason("pytorch", "none", "bf16", "cuda") is None
    assert backend.invalid_reason("pytorch", "ptq_static", "int8", "cpu") is not None
    assert backend.versions()["torch"] == torch.__version__
    assert backend.probe("cpu", "fp32") is None  # g++ and Python's headers are here
    if torch.version.cuda is None:
        assert "CPU-only build" in (backend.probe("cuda", "fp16") or "")
    monkeypatch.setenv("CXX", "no-such-c++")
    assert backend.probe("cpu", "fp32") == (
        "no C++ compiler found (Inductor compiles C++ kernels and wrappers): 'no-such-c++' is not on PATH; "
        "install g++ (apt-get install g++) or set CXX to a C++ compiler")
    monkeypatch.delenv("CXX")
    monkeypatch.setattr("sysconfig.get_path", lambda name: str(tmp_path))
    headers = backend.probe("cpu", "fp32")
    if backend is JIT:  # its CPU kernels are Python extension modules; a package's are not
        assert headers and headers.startswith(f"Python's C headers are missing ({tmp_path}/Python.h;")
    else:
        assert headers is None


@pytest.mark.parametrize(("options", "problem"), [
    ("{torch_compile: {mode: fast}}", "backend_options.torch_compile.mode: 'fast' is not allowed; allowed: "
                                      "default, reduce-overhead, max-autotune, max-autotune-no-cudagraphs"),
    ("{torch_compile: {dynamic: 'yes'}}", "backend_options.torch_compile.dynamic: expected boolean, got str"),
    ("{aot_inductor: {mode: reduce-overhead}}", "backend_options.aot_inductor.mode: 'reduce-overhead' is not "
                                                "allowed; allowed: default, max-autotune-no-cudagraphs"),
    ("{aot_inductor: {dynamic: true}}", "backend_options.aot_inductor.dynamic: unknown key 'dynamic'; "
                                        "allowed: mode"),
])
def test_option_mistakes_are_refused_with_the_matrix(tiny_project: Path, options: str, problem: str) -> None:
    path = tiny_project / "m.yaml"
    text = matrix_text(["torch_compile", "aot_inductor"], ["none"], ["fp32"], ["cpu"])
    path.write_text(text + "backend_options: {torch_compile: {mode: max-autotune, fullgraph: true}}\n")
    matrix = load_matrix(path, backends=["torch_compile", "aot_inductor"])
    assert matrix.backend_options == {"torch_compile": {"mode": "max-autotune", "fullgraph": True}}
    path.write_text(text + f"backend_options: {options}\n")
    with pytest.raises(MatrixError) as info:
        load_matrix(path, backends=["torch_compile", "aot_inductor"])
    assert any(problem in found for found in info.value.problems), info.value.problems


# ---- on an NVIDIA GPU --------------------------------------------------------------------------------------

TOLERANCE = {"fp32": 1e-5, "fp16": 1e-2, "bf16": 3e-2}  # of the largest output, as in test_torch_gpu


def _gpu(backend: Any, precision: str, mode: str = "default") -> Any:
    """A cuda case, skipped with the backend's own probe reason where it cannot run."""
    reason = backend.probe("cuda", precision)
    return pytest.param(backend, precision, mode, id=f"{backend.name}-{precision}-{mode}",
                        marks=[pytest.mark.gpu, pytest.mark.skipif(reason is not None, reason=reason or "")])


@pytest.mark.parametrize(("backend", "precision", "mode"), [
    *(_gpu(JIT, precision) for precision in ("fp32", "fp16", "bf16")),
    _gpu(JIT, "fp32", "reduce-overhead"), _gpu(AOT, "fp32"), _gpu(AOT, "bf16")])
def test_cuda_matches_fp32(backend: Any, precision: str, mode: str, source: SourceModel,
                           reference: np.ndarray, tmp_path: Path) -> None:
    request = replace(request_for(CALIBRATION, source, tmp_path, "none", precision, "cuda", max_batch=BATCH),
                      options={"mode": mode})
    session = backend.load(tmp_path, backend.convert(request), "cuda", precision, 1)
    for rows in (slice(0, 1), slice(0, BATCH), slice(BATCH, 2 * BATCH)):
        np.testing.assert_allclose(_predict(session, X[rows]), reference[rows], rtol=0,
                                   atol=TOLERANCE[precision] * float(np.abs(reference).max()))
    info = session.info()
    assert info["device"] == "cuda" and info["tensor_float_32"] is False and info["mode"] == mode
    if backend is JIT:
        assert info["cuda_graphs"] == (mode == "reduce-overhead") and info["compile_s"] > 0


def test_plan_says_which_cells_compile_and_why_they_take_long(tiny_project: Path) -> None:
    (tiny_project / "m.yaml").write_text(matrix_text(["torch_compile", "onnxruntime"], ["none"], ["fp32"],
                                                     ["cpu"]))
    plan = cli(tiny_project, "plan", "m.yaml")
    assert plan.returncode == 0, plan.stdout + plan.stderr
    assert "1 torch_compile cell(s): compiles the model with Inductor when converting" in plan.stdout
    assert "onnxruntime cell(s)" not in plan.stdout
