"""`compare --remeasure` end to end: both sides' artifacts timed again in the same rounds; a real slowdown of
the new artifact is worse, the same artifacts are unchanged with a CPU-bound process beside them, and what
cannot be remeasured is judged on the stored samples and says why."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import cli, onnx_matrix_text

pytestmark = pytest.mark.slow
ROUNDS = "settings: {window_s: 0.05, min_rounds: 4, timing_budget_s: 0.6, warmup_iterations: 5, " \
         "warmup_s: 0.05, batch_size: 8, timeout_s: 120}\n"


def _model(hidden: int, layers: int) -> bytes:
    """(N,3,16,16) -> (N,2) through `layers` dense layers of width `hidden`: wider is slower."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    sizes = [768] + [hidden] * layers + [2]
    weights = [numpy_helper.from_array((rng.standard_normal(shape) / np.sqrt(shape[0])).astype(np.float32),
                                       f"W{i}") for i, shape in enumerate(zip(sizes, sizes[1:]))]
    nodes = [helper.make_node("Flatten", ["X"], ["H0"])]
    for i in range(len(weights)):
        nodes.append(helper.make_node("MatMul", [f"H{i}", f"W{i}"], [f"M{i}"]))
        last = i == len(weights) - 1
        output = "Y" if last else f"H{i + 1}"
        nodes.append(helper.make_node("Identity" if last else "Relu", [f"M{i}"], [output]))
    graph = helper.make_graph(nodes, "dense",
                              [helper.make_tensor_value_info("X", TensorProto.FLOAT, ["N", 3, 16, 16])],
                              [helper.make_tensor_value_info("Y", TensorProto.FLOAT, ["N", 2])], weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    return model.SerializeToString()


def _json(out: subprocess.CompletedProcess, code: int) -> dict:
    assert out.returncode == code, out.stdout + out.stderr
    return json.loads(out.stdout)


def _p50(result: dict) -> dict:
    (cell,) = result["cells"]
    return cell["metrics"]["p50"]


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Run "small" on a narrow network, then "large" with the same cell on a wider (slower) one; the tests
    that take something away run last."""
    import fuzz_cases

    onnx_project = fuzz_cases.write_project(tmp_path_factory.mktemp("remeasure"))
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["dense"], ["fp32"]).replace(
        "tiny.onnx", "dense.onnx").split("settings:")[0] + ROUNDS)
    for label, hidden in (("small", 96), ("large", 384)):
        (onnx_project / "dense.onnx").write_bytes(_model(hidden, 3))
        out = cli(onnx_project, "run", "m.yaml", "--force", "--label", label)
        assert out.returncode == 0, out.stdout + out.stderr
    return onnx_project


def test_a_slower_new_artifact_is_worse_on_the_paired_ratio(two_runs: Path) -> None:
    result = _json(cli(two_runs, "compare", "small", "large", "--remeasure", "--format", "json"), 1)
    p50 = _p50(result)
    assert result["remeasured"] and p50["name"] == "latency_ms.p50 (paired)", p50
    assert p50["verdict"] == "worse" and p50["change"] > 0.2, p50
    assert "(remeasured)" in result["base"] and "(remeasured)" in result["new"]
    markdown = cli(two_runs, "compare", "small", "large", "--remeasure", "--format", "md")
    assert markdown.returncode == 1 and "paired by round" in markdown.stdout, markdown.stdout
    assert "remeasured 1 cells here" in markdown.stderr, markdown.stderr


def test_the_same_artifacts_with_a_cpu_bound_process_beside_them_are_unchanged(two_runs: Path) -> None:
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        result = _json(cli(two_runs, "compare", "large", "large", "--remeasure", "--threshold", "p50=10%",
                           "--format", "json"), 0)
    finally:
        hog.kill()
        hog.wait()
    p50 = _p50(result)
    assert p50["name"] == "latency_ms.p50 (paired)" and p50["verdict"] == "unchanged", p50
    # near 1 however busy: seen at -11 % and +30 % (their intervals as wide: the verdict unchanged) with the
    # hog and another test worker on 2 cores (CI); twins paired wrongly would come out further apart
    assert abs(p50["change"]) < 0.4, p50


def test_remeasure_without_the_matrix_says_how_to_name_it(two_runs: Path) -> None:
    (two_runs / "m.yaml").rename(two_runs / "moved.yaml")
    try:
        out = cli(two_runs, "compare", "small", "large", "--remeasure")
        assert out.returncode == 2 and "--matrix FILE" in out.stderr and "Traceback" not in out.stderr, \
            out.stderr
        out = cli(two_runs, "compare", "small", "large", "--matrix", "moved.yaml")
        assert out.returncode == 2 and "use it with --remeasure" in out.stderr, out.stderr
    finally:
        (two_runs / "moved.yaml").rename(two_runs / "m.yaml")


def test_a_side_whose_artifact_is_gone_is_judged_on_its_stored_samples(two_runs: Path) -> None:
    stored = _json(cli(two_runs, "report", "--run", "small", "--format", "json"), 0)
    artifact = Path(stored["records"][0]["artifact_path"])
    for path in sorted(artifact.parent.rglob("*"), reverse=True):
        path.unlink() if path.is_file() else path.rmdir()
    artifact.parent.rmdir()
    out = cli(two_runs, "compare", "small", "large", "--remeasure", "--format", "json")
    assert "artifact not on this machine: base's" in out.stderr, out.stderr
    assert os.fspath(artifact) in out.stderr, out.stderr
    result = json.loads(out.stdout)
    assert not result["remeasured"] and _p50(result)["name"] == "latency_ms.p50", result


def test_each_side_is_scored_against_its_own_baseline(onnx_project: Path) -> None:
    """Two networks of one cell (the baseline itself), without labels: remeasured, each side's outputs agree
    with its own baseline's, as the stored comparison says, not with the other network's."""
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["dense"], ["fp32"]).replace(
        "file: tiny.onnx}", "file: dense.onnx, task: none}").split("settings:")[0] + ROUNDS)
    for label, hidden in (("small", 96), ("large", 384)):
        (onnx_project / "dense.onnx").write_bytes(_model(hidden, 3))
        out = cli(onnx_project, "run", "m.yaml", "--label", label)
        assert out.returncode == 0, out.stdout + out.stderr
    for remeasure in ([], ["--remeasure"]):
        result = _json(cli(onnx_project, "compare", "small", "large", *remeasure, "--format", "json"), 1)
        (cell,) = result["cells"]
        accuracy = cell["metrics"]["accuracy"]
        assert accuracy["name"] == "cosine_similarity", accuracy
        assert accuracy["base"] == pytest.approx(1, abs=1e-6), accuracy
        assert accuracy["new"] == pytest.approx(1, abs=1e-6), accuracy
