"""Training-aware strategies end to end through the CLI: fine-tuned once, shared by backends, measured
honestly; a classifier fine-tuned on its class labels."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

import task_models
from conftest import FAST_SETTINGS, TESTS, cli, matrix_text
from test_cli_tensorflow import _keras_project, _records

pytestmark = pytest.mark.slow

TORCH_STRATEGIES = (
    "strategies:\n"
    "  prune_local: {kind: prune, scope: local, conv_sparsity: 0.3, linear_sparsity: 0.5, epochs: 1,"
    " fraction: 0.5, min_weights: 0}\n"
    "  prune_global: {kind: prune, scope: global, final_sparsity: 0.4, epochs: 1, fraction: 0.5,"
    " min_weights: 0}\n"
    "  qat: {kind: qat, epochs: 1, fraction: 0.5}\n"
    "  prune_dynamic: {steps: [prune_local, ptq_dynamic]}\n")


def test_pytorch_pruning_and_qat(tiny_project: Path) -> None:
    text = matrix_text(["torchscript", "onnxruntime"],
                       ["prune_local", "prune_global", "qat", "prune_dynamic"], ["fp32", "int8"], ["cpu"],
                       TORCH_STRATEGIES + "exclude: [{backend: onnxruntime, strategy: prune_global}]\n")
    (tiny_project / "m.yaml").write_text(text)
    run = cli(tiny_project, "run", "m.yaml", timeout=900)
    assert run.returncode == 0 and "0 failed" in run.stdout, run.stdout + run.stderr
    # not a terminal: a line per step and phase, each fine-tuning's epochs with their loss and time left
    epoch = r"\] tiny · torchscript qat int8 · fine-tune · epoch 1/1 · loss [0-9.e+-]+ · about 0 s left"
    assert re.search(epoch, run.stdout), run.stdout
    assert re.search(r"\] tiny · measuring \d+ cells in rounds · round 1\n", run.stdout), run.stdout
    found = {key: r for key, r in _records(tiny_project).items() if r["status"] == "ok"}
    assert set(found) == {"torchscript/prune_local/fp32/cpu", "onnxruntime/prune_local/fp32/cpu",
                          "torchscript/prune_global/fp32/cpu", "torchscript/qat/int8/cpu",
                          "torchscript/prune_dynamic/int8/cpu", "onnxruntime/prune_dynamic/int8/cpu"}
    local = found["torchscript/prune_local/fp32/cpu"]["metrics"]
    # conv 0.3 and linear 0.5 of their weights: overall between the two, never below the smaller target
    assert 0.3 <= local["sparsity"] <= 0.5
    assert found["torchscript/prune_global/fp32/cpu"]["metrics"]["sparsity"] >= 0.4
    # one fine-tuning per strategy, shared by every backend: the same facts, the time counted in convert_s
    assert local["finetune"] == found["onnxruntime/prune_local/fp32/cpu"]["metrics"]["finetune"]
    assert local["convert_s"] >= local["finetune_s"] > 0
    # the combination starts from the pristine model too: pruned like prune_local, then quantised
    combined = found["torchscript/prune_dynamic/int8/cpu"]["metrics"]
    assert combined["sparsity"] == pytest.approx(local["sparsity"])
    plan = cli(tiny_project, "plan", "m.yaml")
    assert ("onnxruntime does not implement qat" in plan.stdout
            or "combinations it does not implement" in plan.stdout)


TF_STRATEGIES = (
    "strategies:\n"
    "  prune: {kind: prune, final_sparsity: 0.6, epochs: 2, fraction: 1.0, min_weights: 0}\n"
    "  qat: {kind: qat, epochs: 1, fraction: 1.0}\n"
    "  prune_dynamic: {steps: [prune, ptq_dynamic]}\n")


def test_tensorflow_pruning_and_qat_in_tflite(tmp_path: Path) -> None:
    project = _keras_project(tmp_path, "tiny.keras")
    (project / "m.yaml").write_text(
        "models:\n  - {name: tiny, framework: tensorflow, file: tiny.keras}\n"
        "dataset: {npz: data.npz, split: {train: 0.5, calibration: 0.25, test: 0.25}}\n" + TF_STRATEGIES +
        "axes: {backend: [tflite], strategy: [prune, qat, prune_dynamic], precision: [fp32, int8], "
        "target: [cpu]}\n"
        "include:\n  - {backend: onnxruntime, strategy: qat, precision: int8, target: cpu}\n"
        "settings: {window_s: 0.01, min_rounds: 2, timing_budget_s: 0.05, warmup_iterations: 2, "
        "warmup_s: 0.0, batch_size: 8, timeout_s: 300, processes: 1}\n")
    run = cli(project, "run", "m.yaml", timeout=900)
    assert run.returncode == 0 and "0 failed" in run.stdout, run.stdout + run.stderr
    epoch = r"\] tiny · tflite prune fp32 · fine-tune · epoch 2/2 · loss [0-9.e+-]+ · about 0 s left"
    assert re.search(epoch, run.stdout), run.stdout  # Keras' epochs, from its callback
    found = {key: r for key, r in _records(project).items() if r["status"] == "ok"}
    assert set(found) == {"tflite/prune/fp32/cpu", "tflite/qat/int8/cpu",
                          "tflite/prune_dynamic/int8/cpu", "onnxruntime/qat/int8/cpu"}
    # ONNX Runtime runs the same QAT model as QDQ pairs (tf2onnx): the same learned ranges, the same accuracy
    ort_qat, tflite_qat = (found[f"{b}/qat/int8/cpu"]["metrics"] for b in ("onnxruntime", "tflite"))
    assert ort_qat["finetune"] == tflite_qat["finetune"]
    assert ort_qat["mse"] == pytest.approx(tflite_qat["mse"], rel=0.1)
    pruned = found["tflite/prune/fp32/cpu"]["metrics"]
    assert pruned["sparsity"] >= 0.6 - 0.02 and pruned.get("clusters") is None  # tfmot rounds per layer
    qat = found["tflite/qat/int8/cpu"]["metrics"]
    assert qat["session"]["interpreter"].startswith("ai_edge_litert")
    assert json.dumps(qat["finetune"])  # facts are recorded


def test_a_classifier_is_fine_tuned_on_its_class_labels_and_none_is_refused(tmp_path: Path) -> None:
    task_models.save(task_models.classifier, tmp_path, "cls.pt")
    task_models.class_images(tmp_path)
    task_models.save(task_models.two_input, tmp_path, "two.pt")
    task_models.features(tmp_path)
    factory = "framework: pytorch, python_path: ['" + str(TESTS) + "']"
    (tmp_path / "m.yaml").write_text(
        "models:\n"
        f"  - {{name: cls, {factory}, factory: 'task_models:classifier', weights: cls.pt}}\n"
        f"  - {{name: two, {factory}, factory: 'task_models:two_input', weights: two.pt, task: none,"
        " dataset: {npz: features.npz}, inputs: [{name: features, shape: [6]},"
        " {name: ids, shape: [5], dtype: int64, range: [0, 11]}]}\n"
        "dataset: {npz: images.npz, task: classification,"
        " split: {train: 0.5, calibration: 0.25, test: 0.25}}\n"
        "strategies:\n  prune: {kind: prune, epochs: 3, lr: 0.01, fraction: 1.0, min_weights: 0}\n"
        "axes: {backend: [pytorch], strategy: [prune], precision: [fp32], target: [cpu]}\n"
        + FAST_SETTINGS)
    run = cli(tmp_path, "run", "m.yaml", timeout=900)
    assert run.returncode == 0 and "0 failed" in run.stdout, run.stdout + run.stderr
    plan = cli(tmp_path, "plan", "m.yaml")
    assert "fine-tuning needs labels; the task is none" in plan.stdout, plan.stdout
    report = cli(tmp_path, "report", "--format", "json")
    found = {(r["cell"]["model"], r["cell"]["strategy"]): r for r in json.loads(report.stdout)["records"]}
    assert found[("cls", "prune")]["status"] == "ok" and ("two", "prune") not in found, found.keys()
    metrics = found[("cls", "prune")]["metrics"]
    assert metrics["finetune"]["loss"] == "cross_entropy" and metrics["sparsity"] >= 0.3
    assert metrics["top1"] >= 0.5 and "mse" not in metrics  # brightest channel: well above chance (1/3) in 3 epochs
