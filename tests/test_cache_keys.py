"""Every cache key of the workspace changes with everything that changes what its entry holds (docs/metrics.md
§12), and two models that share a factory and weights but not their inputs share no cached export."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

from conftest import FAST_SETTINGS, cli, onnx_matrix_text  # noqa: E402

from bench_matrix import data  # noqa: E402
from bench_matrix.jobs import keys  # noqa: E402
from bench_matrix.matrix.spec import DatasetSpec, ModelSpec, Preprocess, Settings, SplitSpec  # noqa: E402
from bench_matrix.strategy import StrategySpec
from bench_matrix.registry import load_backend  # noqa: E402
from bench_matrix.sources import SourceModel  # noqa: E402
from bench_matrix.sources.code import model_code, module_file  # noqa: E402
from bench_matrix.strategies.registry import load_trainer  # noqa: E402
from bench_matrix.tensors import TensorSpec  # noqa: E402

INPUTS = (TensorSpec("p", (4,)), TensorSpec("q", (4,)))
SOURCE = SourceModel("m", "pytorch", "state_dict", Path("w.pt"), "a" * 64, INPUTS, factory="mod:build",
                     code_sha256="c" * 64)
STEP = StrategySpec("ptq_static", "ptq_static", {"calibration_samples": 10})
ORT = load_backend("onnxruntime")

# (what changes, the source as changed): each changes what a conversion, an export or a fine-tune makes
SOURCE_CHANGES = {
    "weights": replace(SOURCE, sha256="b" * 64),
    "input order": replace(SOURCE, inputs=INPUTS[::-1]),
    "input shape": replace(SOURCE, inputs=(TensorSpec("p", (5,)), INPUTS[1])),
    "input dtype": replace(SOURCE, inputs=(TensorSpec("p", (4,), "int64"), INPUTS[1])),
    "factory": replace(SOURCE, factory="mod:other"),
    "factory code": replace(SOURCE, code_sha256="d" * 64),
    "format": replace(SOURCE, format="torchscript"),
}


def _artifact(source=SOURCE, step=STEP, precision="int8", target="cpu", dataset=("fp", "nchw"),
              settings=Settings(), options=None) -> str:
    return keys.artifact_key(ORT, source, step, precision, target, list(dataset), settings, options or {})


@pytest.mark.parametrize("change", list(SOURCE_CHANGES))
def test_a_changed_source_changes_every_key_built_on_it(change):
    changed, trainer = SOURCE_CHANGES[change], load_trainer("torch")
    assert _artifact(changed) != _artifact()
    assert keys.intermediates_key(ORT, changed, 0) != keys.intermediates_key(ORT, SOURCE, 0)
    assert keys.params_key(changed) != keys.params_key(SOURCE)
    steps = (StrategySpec("prune", "prune", {}),)
    assert (keys.finetune_key(trainer, changed, steps, "regression", ["fp", "nchw"], 0)
            != keys.finetune_key(trainer, SOURCE, steps, "regression", ["fp", "nchw"], 0))


@pytest.mark.parametrize("change", [
    {"step": StrategySpec("ptq_static", "ptq_static", {"calibration_samples": 20})},
    {"precision": "fp16"}, {"target": "cuda"}, {"dataset": ("other", "nchw")}, {"dataset": ("fp", "nhwc")},
    {"settings": Settings(seed=1)}, {"settings": Settings(batch_size=64)}, {"options": {"opt_level": 1}}],
    ids=["step options", "precision", "target", "calibration data", "layout", "seed", "max batch", "options"])
def test_each_input_of_an_artifact_changes_its_key(change):
    assert _artifact(**change) != _artifact()


def test_data_that_is_never_read_does_not_change_an_artifact():
    none = StrategySpec("none", "none", {})
    assert _artifact(step=none, dataset=("other", "nhwc")) == _artifact(step=none)
    assert _artifact(settings=Settings(threads=2, timeout_s=5)) == _artifact()


def test_a_backend_or_trainer_revision_changes_its_keys(monkeypatch):
    before, trainer = _artifact(), load_trainer("torch")
    tuned = keys.finetune_key(trainer, SOURCE, (), "regression", ["fp", "nchw"], 0)
    monkeypatch.setattr(type(ORT), "revision", ORT.revision + 1)
    monkeypatch.setattr(type(trainer), "revision", trainer.revision + 1)
    assert _artifact() != before
    assert keys.finetune_key(trainer, SOURCE, (), "regression", ["fp", "nchw"], 0) != tuned


@pytest.mark.parametrize("change", [
    {"steps": (StrategySpec("prune", "prune", {"sparsity": 0.7}),)}, {"task": "classification"},
    {"dataset": ["other", "nchw"]}, {"dataset": ["fp", "nhwc"]}, {"seed": 1}],
    ids=["steps", "task", "training data", "layout", "seed"])
def test_each_input_of_a_fine_tune_changes_its_key(change):
    given = {"steps": (StrategySpec("prune", "prune", {"sparsity": 0.5}),), "task": "regression",
             "dataset": ["fp", "nchw"], "seed": 0}
    trainer = load_trainer("torch")
    assert keys.finetune_key(trainer, SOURCE, **{**given, **change}) != keys.finetune_key(trainer, SOURCE, **given)


MODEL = ModelSpec("m", "pytorch", factory="mod:build")


@pytest.mark.parametrize("change", [
    {"inputs": INPUTS[::-1]}, {"code": "other"}, {"task": "classification"}, {"dataset": "other"},
    {"settings": Settings(seed=1)}, {"settings": Settings(eval_samples=10)}, {"settings": Settings(batch_size=4)},
    {"baseline": ["pytorch", {"torch": "9"}]}, {"spec": replace(MODEL, factory="mod:other")},
    {"spec": replace(MODEL, layout="nhwc")}],
    ids=["inputs", "code", "task", "dataset", "seed", "eval samples", "batch", "baseline", "factory", "layout"])
def test_each_input_of_a_prepared_model_changes_its_key(change):
    given = {"spec": MODEL, "inputs": INPUTS, "code": "c", "task": "regression", "dataset": "fp",
             "settings": Settings(), "baseline": ["pytorch", {"torch": "1"}]}
    assert keys.model_key(**{**given, **change}) != keys.model_key(**given)


@pytest.mark.parametrize("change", [
    {"spec": ModelSpec("m", "pytorch", builtin="pilotnet_jderobot")}, {"code": "other"}, {"dataset": "other"},
    {"seed": 1}, {"libraries": {"torch": "9"}}, {"spec": ModelSpec("m", "pytorch", builtin="pilotnet", layout="nhwc")}],
    ids=["builtin", "code", "dataset", "seed", "libraries", "layout"])
def test_each_input_of_a_trained_builtin_changes_its_key(change):
    given = {"spec": ModelSpec("m", "pytorch", builtin="pilotnet"), "code": "c", "dataset": "fp", "seed": 0,
             "libraries": {"torch": "1"}}
    assert keys.builtin_key(**{**given, **change}) != keys.builtin_key(**given)


def test_a_factory_module_is_found_without_importing_it_and_its_edits_change_the_hash(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("raise ImportError('never imported')\n")
    module = tmp_path / "pkg" / "nets.py"
    module.write_text("def build():\n    return 1\n")
    spec = ModelSpec("m", "pytorch", factory="pkg.nets:build", python_path=(tmp_path,))
    assert module_file("pkg.nets", [str(tmp_path)]) == module
    before = model_code(spec)
    module.write_text("def build():\n    return 2\n")
    assert before is not None and model_code(spec) != before
    assert "pkg" not in sys.modules


@pytest.mark.parametrize("change", [
    {"preprocess": Preprocess(scale=1.0)}, {"split": SplitSpec(0.5, 0.25, 0.25)}, {"seed": 1}, {"samples": 100},
    {"task": "none"}], ids=["preprocess", "split", "seed", "samples", "task"])
def test_each_input_of_a_dataset_changes_its_fingerprint(change):
    spec = DatasetSpec("builtin")
    assert data.fingerprint(replace(spec, **change)) != data.fingerprint(spec)


def test_a_dataset_file_and_synthetic_inputs_change_the_fingerprint(tmp_path):
    np.savez(tmp_path / "d.npz", x=np.zeros((4, 2), np.float32))
    spec = DatasetSpec("npz", (tmp_path / "d.npz",))
    before = data.fingerprint(spec)
    np.savez(tmp_path / "d.npz", x=np.ones((4, 2), np.float32))
    assert data.fingerprint(spec) != before
    synthetic = DatasetSpec("synthetic")
    assert data.fingerprint(synthetic, INPUTS) != data.fingerprint(synthetic, INPUTS[::-1])


FACTORY = """import torch


class Difference(torch.nn.Module):
    \"\"\"first.sum() - 3 * second.sum(), whatever the inputs are named: the order decides.\"\"\"

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.tensor([1.0, -3.0]))

    def forward(self, *xs):
        return (xs[0].sum(1) * self.w[0] + xs[1].sum(1) * self.w[1]).unsqueeze(1)


def build():
    return Difference()
"""


@pytest.mark.slow
def test_two_models_sharing_weights_with_other_inputs_share_no_export(tmp_path):
    import torch

    (tmp_path / "nets.py").write_text(FACTORY)
    sys.path.insert(0, str(tmp_path))
    torch.save(__import__("nets").build().state_dict(), tmp_path / "w.pt")
    rng = np.random.default_rng(0)
    p, q = rng.normal(size=(2, 40, 4)).astype(np.float32)
    np.savez(tmp_path / "d.npz", p=p, q=q, y=(p.sum(1) - 3 * q.sum(1))[:, None])
    models = "".join(f"  - {{name: {name}, framework: pytorch, factory: 'nets:build', weights: w.pt, python_path: "
                     f"['.'], inputs: [{order}]}}\n" for name, order in
                     (("pq", "{name: p, shape: [4]}, {name: q, shape: [4]}"),
                      ("qp", "{name: q, shape: [4]}, {name: p, shape: [4]}")))
    (tmp_path / "m.yaml").write_text(
        f"models:\n{models}dataset: {{npz: d.npz, split: {{train: 0.5, calibration: 0.25, test: 0.25}}}}\n"
        "axes: {backend: [pytorch, onnxruntime], strategy: [none], precision: [fp32], target: [cpu]}\n"
        + FAST_SETTINGS)
    run = cli(tmp_path, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    found = {r["cell"]["model"] + "/" + r["cell"]["backend"]: r["metrics"]
             for r in json.loads(cli(tmp_path, "report", "--format", "json").stdout)["records"]}
    assert found["pq/pytorch"]["mse"] < 1e-9 and found["qp/pytorch"]["mse"] > 1  # qp computes q - 3p
    for model in ("pq", "qp"):
        assert found[f"{model}/onnxruntime"]["max_abs_diff_vs_baseline"] < 1e-4
        assert found[f"{model}/onnxruntime"]["mse"] == pytest.approx(found[f"{model}/pytorch"]["mse"], rel=1e-5)


@pytest.mark.slow
def test_a_run_says_when_the_calibration_split_had_fewer_samples_than_asked(onnx_project):
    (onnx_project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["int8"]).replace(
        "strategy: [none]", "strategy: [ptq_static]"))
    run = cli(onnx_project, "run", "m.yaml")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "calibrated on 12 of the 100 samples asked for" in " ".join(run.stdout.split())
    found = json.loads(cli(onnx_project, "report", "--format", "json").stdout)["records"]
    assert found[0]["metrics"]["calibration"] == {"asked": 100, "used": 12}
