"""The committed any-model matrix: it loads, its classifiers were fitted on the data it evaluates them on,
and it plans every model through the backends that support it."""

from __future__ import annotations

import importlib.util
import re
from dataclasses import replace
from pathlib import Path

import pytest

from conftest import cli

pytestmark = pytest.mark.slow
MATRIX = Path(__file__).resolve().parents[1] / "matrices" / "any-model.yaml"


def build_script():
    path = MATRIX.parent / "any-model" / "build_models.py"
    spec = importlib.util.spec_from_file_location("build_models", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_classifiers_are_fitted_on_the_matrix_dataset():
    from bench_matrix.matrix.load import load_matrix

    matrix = load_matrix(MATRIX)
    bends = build_script().BENDS
    assert replace(matrix.dataset, labels=bends.labels) == bends  # `labels` does not apply to driving_bends
    tasks = {model.name: matrix.task_of(model) for model in matrix.models}
    assert tasks == {"mobilenet-v2": "classification", "resnet": "classification",
                     "cnn-onnx": "classification", "encoder": "none", "tabular-mlp": "regression"}


def test_it_plans_every_model_with_post_training_int8(tmp_path):
    out = cli(tmp_path, "plan", str(MATRIX))
    assert out.returncode == 0, out.stdout + out.stderr
    counts = re.search(r"(\d+) will run, 0 already stored, (\d+) will be skipped", out.stdout)
    assert counts and int(counts.group(1)) >= 40, out.stdout  # 40 without the optional openvino extra
    skipped = [line for line in out.stdout.splitlines() if "│ skipped" in line]
    # only OpenVINO's fp16 may be skipped: whether this CPU has it in OpenVINO is the CPU's (probed) business
    assert all(" openvino " in line and " fp16 " in line for line in skipped), skipped
    assert len(skipped) == int(counts.group(2))
    for model in ("mobilenet-v2", "resnet", "cnn-onnx", "encoder", "tabular-mlp"):
        rows = [line for line in out.stdout.splitlines() if f" {model} " in line and "will run" in line]
        assert any("ptq_static" in row and "int8" in row for row in rows), model
