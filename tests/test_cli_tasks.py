"""Any model through the CLI with real runtimes: a classifier, two named inputs of different dtypes (synthetic
and from an .npz), two outputs, NaN outputs, and mistakes refused at plan time."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import task_models
from conftest import FAST_SETTINGS, TESTS, cli

from bench_matrix.report.render.columns import sig

pytestmark = pytest.mark.slow
SPLIT = "split: {train: 0.5, calibration: 0.25, test: 0.25}"
# cells no assertion reads (each costs two processes): the two-input models' eager cells, int8 heads, ORT nan
UNASKED = ("exclude: [{model: synthetic, backend: pytorch}, {model: npz, backend: pytorch},"
           " {model: heads, strategy: ptq_dynamic}, {model: nan, backend: onnxruntime}]\n")


def records(project: Path) -> dict[str, dict]:
    out = cli(project, "report", "--format", "json")
    assert out.returncode == 0, out.stderr
    return {"/".join(r["cell"][k] for k in ("model", "backend", "strategy", "precision")): r
            for r in json.loads(out.stdout)["records"]}


def factory_model(name: str, factory: str, weights: str, extra: str = "") -> str:
    return (f"  - {{name: {name}, framework: pytorch, factory: 'task_models:{factory}', weights: {weights}, "
            f"python_path: ['{TESTS}']{extra}}}\n")


def test_a_classifier_is_scored_by_top1_top5_and_agreement(tmp_path):
    task_models.save(task_models.classifier, tmp_path, "cls.pt")
    task_models.class_images(tmp_path)
    (tmp_path / "m.yaml").write_text(
        "models:\n" + factory_model("cls", "classifier", "cls.pt")
        + f"dataset: {{npz: images.npz, task: classification, {SPLIT}}}\n"
        "axes: {backend: [pytorch, onnxruntime], strategy: [none, ptq_static], precision: [fp32, int8], "
        "target: [cpu]}\n" + FAST_SETTINGS)
    run = cli(tmp_path, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "3 ok, 0 skipped, 0 failed" in run.stdout
    found = records(tmp_path)
    for key in ("cls/pytorch/none/fp32", "cls/onnxruntime/none/fp32", "cls/onnxruntime/ptq_static/int8"):
        m = found[key]["metrics"]
        assert 0 <= m["top1"] <= 1 and m["top5"] == 1.0  # three classes: the top 5 always hold the label
        assert "mse" not in m
    assert found["cls/onnxruntime/none/fp32"]["metrics"]["top1_agreement"] == 1.0
    assert found["cls/onnxruntime/ptq_static/int8"]["metrics"]["top1_agreement"] >= 0.8
    report = cli(tmp_path, "report")
    assert report.returncode == 0, report.stderr
    assert "Top-1" in report.stdout and "MSE" not in report.stdout


def test_named_inputs_of_two_dtypes_several_outputs_and_nan_outputs(tmp_path):
    for factory in ("two_input", "two_output", "not_a_number"):
        task_models.save(getattr(task_models, factory), tmp_path, f"{factory}.pt")
    task_models.features(tmp_path)
    (tmp_path / "reg").mkdir()
    reg = task_models.features(tmp_path / "reg", labels=3)
    inputs = (", inputs: [{name: features, shape: [6]}, "
              "{name: ids, shape: [5], dtype: int64, range: [0, 11]}]")
    (tmp_path / "m.yaml").write_text(
        "models:\n"
        + factory_model("synthetic", "two_input", "two_input.pt", inputs + ", dataset: {synthetic: {samples: 48}}")
        + factory_model("npz", "two_input", "two_input.pt", inputs + ", task: none")
        + factory_model("heads", "two_output", "two_output.pt",
                        f", inputs: [{{name: features, shape: [6]}}], dataset: {{npz: {reg}, {SPLIT}}}")
        + factory_model("nan", "not_a_number", "not_a_number.pt",
                        f", inputs: [{{name: features, shape: [6]}}], dataset: {{npz: {reg}, {SPLIT}}}")
        + f"dataset: {{npz: features.npz, {SPLIT}}}\n"
        "axes: {backend: [pytorch, onnxruntime], strategy: [none, ptq_dynamic], precision: [fp32, int8], "
        "target: [cpu]}\n" + FAST_SETTINGS + UNASKED)
    run = cli(tmp_path, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    found = records(tmp_path)
    for model in ("synthetic", "npz"):
        fp32 = found[f"{model}/onnxruntime/none/fp32"]
        assert fp32["status"] == "ok", fp32["reason"]
        assert fp32["metrics"]["cosine_similarity"] > 0.9999 and fp32["metrics"]["max_abs_diff_vs_baseline"] < 1e-4
        assert "mse" not in fp32["metrics"] and "top1" not in fp32["metrics"]
        assert found[f"{model}/onnxruntime/ptq_dynamic/int8"]["status"] == "ok"
    heads = found["heads/onnxruntime/none/fp32"]["metrics"]
    assert heads["mse"] == pytest.approx(found["heads/pytorch/none/fp32"]["metrics"]["mse"], rel=1e-4)
    assert len(heads["mse_per_output"]) == 3  # two heads, three label columns
    _each_head_is_reported(tmp_path, heads["per_output"])
    nan = found["nan/pytorch/none/fp32"]
    assert nan["status"] == "failed" and "not finite" in nan["reason"] and "NaN" in nan["reason"]


def _each_head_is_reported(project, heads: list[dict]) -> None:
    """The report's terminal and Markdown tables show each head's own MSE and difference from the baseline."""
    shown = cli(project, "report", "--model", "heads", "--out", str(project / "pages"))
    assert shown.returncode == 0, shown.stderr
    page = (project / "pages" / "heads.md").read_text().replace("\\|", "|")
    row = next(line for line in page.splitlines() if line.startswith("| onnxruntime none fp32 |"))
    for number, (head, dims) in enumerate(zip(heads, ("2", "1"), strict=True), 1):
        for header in ("MSE", "max |Δ|"):
            assert f"{header} ↓ out {number} ({dims})" in page, page
        assert f"out {number} ({dims})" in shown.stdout.replace("\n", " "), shown.stdout
        cells = [cell.strip() for cell in row.split("|")]
        assert sig(head["mse"], 4) in cells and sig(head["max_abs_diff_vs_baseline"], 3) in cells, (head, row)


def test_mistakes_known_before_running_are_refused_with_exit_2(tmp_path):
    task_models.save(task_models.two_input, tmp_path, "two.pt")
    task_models.features(tmp_path)
    base = f"dataset: {{npz: features.npz, task: none, {SPLIT}}}\n" \
           "axes: {backend: [pytorch], strategy: [none], precision: [fp32], target: [cpu]}\n"
    cases = {
        "[{name: features, shape: [6]}, {name: tokens, shape: [5], dtype: int64}]": "tokens",
        "[{name: features, shape: [7]}, {name: ids, shape: [5], dtype: int64}]": "(6)",
        "[{name: features, shape: [6]}, {name: ids, shape: [5], dtype: bool}]": "int64",
    }
    for inputs, named in cases.items():
        (tmp_path / "m.yaml").write_text("models:\n" + factory_model("two", "two_input", "two.pt",
                                                                     f", inputs: {inputs}") + base)
        plan = cli(tmp_path, "plan", "m.yaml")
        assert plan.returncode == 2, plan.stdout + plan.stderr
        assert "m.yaml:" in plan.stderr and "model two" in plan.stderr and named in plan.stderr
        assert "Traceback" not in plan.stderr
    (tmp_path / "m.yaml").write_text("models:\n" + factory_model("two", "two_input", "two.pt")
                                     + "dataset: {synthetic: {samples: 10}}\n" + base.split("\n", 1)[1])
    plan = cli(tmp_path, "plan", "m.yaml")
    assert plan.returncode == 2 and "models[0]" in plan.stderr and "must declare 'inputs'" in plan.stderr
