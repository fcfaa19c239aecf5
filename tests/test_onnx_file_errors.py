"""ONNX model files that cannot run as they are say so naming the user's file and what to do: a fixed batch
axis (refused by `plan`), an operator ONNX does not define (the model's cells fail with that reason)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from conftest import FAST_SETTINGS, cli


def _onnx(path: Path, batch: int | str, first: str = "ReduceMean", domain: str = "") -> Path:
    """(batch,3,8,8) -> (batch,2): `first` of X (ReduceMean over H and W; an operator of `domain`), then a
    MatMul."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    reduce = {"axes": [2, 3], "keepdims": 0} if first == "ReduceMean" else {}
    nodes = [helper.make_node(first, ["X"], ["M"], domain=domain, **reduce),
             helper.make_node("MatMul", ["M", "W"], ["Y"])]
    x = helper.make_tensor_value_info("X", TensorProto.FLOAT, [batch, 3, 8, 8])
    y = helper.make_tensor_value_info("Y", TensorProto.FLOAT, [batch, 2])
    weights = numpy_helper.from_array(np.full((3, 2), 0.5, np.float32), "W")
    graph = helper.make_graph(nodes, "g", [x], [y], [weights])
    imports = [helper.make_opsetid("", 17), *([helper.make_opsetid(domain, 1)] if domain else [])]
    onnx.save(helper.make_model(graph, opset_imports=imports, ir_version=8), str(path))
    return path


def _project(folder: Path, model: Path, batch_size: int = 8) -> Path:
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (32, 8, 8, 3), dtype=np.uint8)  # laid out 3×8×8 for the model
    np.savez(folder / "data.npz", x=images, y=rng.random((32, 2), np.float32))
    (folder / "m.yaml").write_text(
        f"models:\n  - {{name: m, framework: onnx, file: {model.name}}}\n"
        "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "axes: {backend: [onnxruntime], strategy: [none, ptq_static], precision: [fp32, int8], "
        "target: [cpu]}\n"
        + FAST_SETTINGS.replace("batch_size: 8", f"batch_size: {batch_size}"))
    return folder


def _records(folder: Path) -> list[dict]:
    return json.loads(cli(folder, "report", "--format", "json").stdout)["records"]


def test_a_fixed_batch_axis_is_refused_by_plan_saying_what_to_do(tmp_path: Path) -> None:
    project = _project(tmp_path, _onnx(tmp_path / "fixed.onnx", 1))
    plan = cli(project, "plan", "m.yaml")
    assert plan.returncode == 2 and "Traceback" not in plan.stderr
    assert ("m.yaml:2: models[0]: model m: fixed.onnx: the model's input 'X' has a fixed batch size of 1, "
            "but the throughput batch (settings.batch_size, also the batch of the accuracy pass) is 8; "
            "export the model with a dynamic batch axis (torch.onnx.export(..., dynamic_axes={'X': {0: "
            "'batch'}}), or tf2onnx with a None batch), or set settings.batch_size: 1") in plan.stderr, \
        plan.stderr
    _onnx(tmp_path / "fixed.onnx", 4)
    plan = cli(project, "plan", "m.yaml")
    every = "'X' has a fixed batch size of 4, but bench-matrix runs every model at batch 1 (latency) and at "
    assert plan.returncode == 2 and f"{every}settings.batch_size (8)" in plan.stderr, plan.stderr


def test_a_fixed_batch_of_1_runs_at_a_throughput_batch_of_1(tmp_path: Path) -> None:
    project = _project(tmp_path, _onnx(tmp_path / "fixed.onnx", 1), batch_size=1)
    assert cli(project, "run", "m.yaml").returncode == 0
    assert [(r["cell"]["strategy"], r["status"]) for r in _records(project)] == [("none", "ok"),
                                                                                 ("ptq_static", "ok")]


def test_an_unknown_operator_names_the_users_file_not_the_cache(tmp_path: Path) -> None:
    model = _onnx(tmp_path / "custom.onnx", "N", first="NoSuchOp")
    project = _project(tmp_path, model)
    assert cli(project, "run", "m.yaml").returncode == 0
    for record in _records(project):
        assert record["status"] == "failed" and "\n" not in record["reason"]
        assert f"{model}: a node uses operator NoSuchOp, which is not an ONNX operator" in record["reason"]
        assert "export the model again with standard ONNX operators" in record["reason"]
        assert "cache" not in record["reason"], record["reason"]


def test_an_operator_no_runtime_has_names_the_users_file_not_the_cache(tmp_path: Path) -> None:
    """An operator of a custom domain may be a runtime's own (com.microsoft's): only loading can tell. When
    the runtime does not have it, the reason names the user's file, never the workspace's converted copy."""
    model = _onnx(tmp_path / "custom.onnx", "N", first="NoSuchOp", domain="custom.ops")
    project = _project(tmp_path, model)
    assert cli(project, "run", "m.yaml").returncode == 0
    for record in _records(project):
        assert record["status"] == "failed" and "\n" not in record["reason"]
        assert f"{model}: onnxruntime cannot load it" in record["reason"], record["reason"]
        assert "custom.ops:NoSuchOp" in record["reason"] and "cache" not in record["reason"], record["reason"]
