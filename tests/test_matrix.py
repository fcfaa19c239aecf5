"""Matrix files: validation messages (file, line, key, allowed, did-you-mean) and expansion into cells."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench_matrix.errors import MatrixError
from bench_matrix.matrix.load import load_matrix
from bench_matrix.matrix.expand import training_key, combinations, rule, ruling_key
from bench_matrix.cell import Ruling
from bench_matrix.matrix.extended import schema_json
from bench_matrix.matrix.schema import PRECISIONS
from bench_matrix.matrix.spec import DatasetSpec

BASE = """\
models:
  - name: a
    framework: pytorch
    builtin: pilotnet
dataset:
  builtin: driving
axes:
  strategy: [none, ptq_dynamic]
  precision: [fp32, int8]
  target: [cpu]
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "matrix.yaml"
    path.write_text(text)
    return path


def problems(tmp_path: Path, text: str, backends: list[str] | None = None) -> list[str]:
    with pytest.raises(MatrixError) as info:
        load_matrix(write(tmp_path, text), backends=backends)
    return info.value.problems


def test_valid_matrix_loads_with_defaults(tmp_path):
    matrix = load_matrix(write(tmp_path, BASE))
    assert [m.name for m in matrix.models] == ["a"]
    assert matrix.dataset.labels.offset == (6.5, -7.1)  # the study's label normalisation for the driving set
    settings = matrix.settings
    assert settings.threads == 1 and settings.window_s == 0.1 and settings.min_rounds == 5
    assert settings.processes == 2


def test_typo_in_key_names_file_line_allowed_and_suggestion(tmp_path):
    text = BASE.replace("  target: [cpu]", "  target: [cpu]\n  stratgy: [none]")
    (message,) = problems(tmp_path, text)
    assert message.startswith(f"{tmp_path / 'matrix.yaml'}:11: axes.stratgy: unknown key 'stratgy'")
    assert "allowed: backend, framework, precision, strategy, target" in message
    assert "did you mean 'strategy'?" in message


def test_wrong_enum_value_lists_allowed_values(tmp_path):
    (message,) = problems(tmp_path, BASE.replace("precision: [fp32, int8]", "precision: [fp32, int4]"))
    assert ":9: axes.precision[1]: 'int4' is not allowed; allowed: fp32, fp16, bf16, int8" in message


def test_unknown_strategy_suggests_the_close_one(tmp_path):
    (message,) = problems(tmp_path, BASE.replace("ptq_dynamic]", "ptq_dinamic]"))
    assert "axes.strategy[1]: unknown strategy 'ptq_dinamic'" in message
    assert "did you mean 'ptq_dynamic'?" in message


def test_unknown_backend_checked_against_installed(tmp_path):
    text = BASE + "  backend: [onnxruntme]\n"
    (message,) = problems(tmp_path, text, backends=["onnxruntime", "pytorch"])
    assert "no backend 'onnxruntme' is installed; installed: onnxruntime, pytorch; did you mean 'onnxruntime'?" in message


def test_several_problems_reported_together(tmp_path):
    text = BASE.replace("framework: pytorch", "framework: jax").replace("target: [cpu]", "target: [gpu]")
    found = problems(tmp_path, text)
    assert len(found) == 2
    assert any("models[0].framework: 'jax' is not allowed" in p for p in found)
    assert any("axes.target[0]: 'gpu' is not allowed; allowed: cpu, cuda, tensorrt" in p for p in found)


def test_model_needs_exactly_one_source(tmp_path):
    text = BASE.replace("    builtin: pilotnet\n", "    builtin: pilotnet\n    file: m.onnx\n")
    assert any("give exactly one of 'builtin', 'file' or 'factory'" in p for p in problems(tmp_path, text))


def test_missing_model_file_and_wrong_suffix(tmp_path):
    text = BASE.replace("    builtin: pilotnet\n", "    file: model.tflite\n")
    found = problems(tmp_path, text)
    assert any("model file not found" in p and "model.tflite" in p for p in found)
    assert any("unsupported model file 'model.tflite'; allowed: files ending .pt, .pth, .pt2, .onnx, .keras, .h5"
               in p for p in found)


def test_split_fractions_must_sum_to_one(tmp_path):
    text = BASE.replace("  builtin: driving\n", "  builtin: driving\n  split: {train: 0.8, calibration: 0.1, test: 0.2}\n")
    (message,) = problems(tmp_path, text)
    assert "dataset.split: train + calibration + test must add up to 1" in message


def test_duplicate_key_and_invalid_yaml(tmp_path):
    assert any("duplicate key 'name'" in p for p in problems(tmp_path, BASE.replace("    framework: pytorch\n",
                                                                                    "    name: b\n    framework: pytorch\n")))
    (message,) = problems(tmp_path, "models: [a\n")
    assert "not valid YAML" in message


def test_yaml_is_loaded_safely(tmp_path):
    found = problems(tmp_path, "models: !!python/object/apply:os.system ['echo pwned']\n")
    assert any("models: the tag tag:yaml.org,2002:python/object/apply:os.system is not allowed" in p for p in found)


def test_strategy_options_validated_per_kind(tmp_path):
    text = BASE + "strategies:\n  mine:\n    kind: ptq_dynamic\n    calibration_samples: 10\n"
    (message,) = problems(tmp_path, text)
    assert "strategies.mine.calibration_samples: unknown key 'calibration_samples'" in message


def test_every_strategy_of_the_study_is_expressible(tmp_path):
    text = BASE + """\
strategies:
  int8_io: {kind: ptq_static, io: int8}
  float_fallback: {kind: ptq_static, io: float}
  prune_poly: {kind: prune, schedule: polynomial, initial_sparsity: 0.5, final_sparsity: 0.8, epochs: 2}
  prune_local: {kind: prune, scope: local, conv_sparsity: 0.3, linear_sparsity: 0.5, epochs: 2}
  prune_global: {kind: prune, scope: global, final_sparsity: 0.3, epochs: 2}
  prune_quant: {steps: [prune_poly, ptq_dynamic]}
  qat_1pct: {kind: qat, epochs: 2, fraction: 0.01}
  cqat8: {kind: cqat, clusters: 8, init: kmeans++, cluster_epochs: 3, qat_epochs: 1}
  pqat: {kind: pqat, final_sparsity: 0.5, schedule: constant, prune_epochs: 3, qat_epochs: 1}
  pcqat: {kind: pcqat, clusters: 8, prune_epochs: 3, cluster_epochs: 3, qat_epochs: 1}
"""
    matrix = load_matrix(write(tmp_path, text))
    assert matrix.strategies["prune_quant"].kinds() == ("prune", "ptq_dynamic")
    assert matrix.strategies["int8_io"].options == {"io": "int8"}


def test_include_and_exclude_values_are_checked(tmp_path):
    text = BASE + "exclude:\n  - {target: cpuu}\ninclude:\n  - {model: b, precision: fp8}\n"
    found = problems(tmp_path, text)
    assert any("exclude[0].target: 'cpuu' is not a known target" in p and "did you mean 'cpu'?" in p for p in found)
    assert any("include[0].model: 'b' is not a known model; known: a" in p for p in found)
    assert any("include[0].precision: 'fp8' is not a known precision" in p for p in found)


def test_conversion_step_must_come_last(tmp_path):
    text = BASE + "strategies:\n  wrong: {steps: [ptq_dynamic, prune]}\n"
    assert any("only the last step may be a post-training" in p for p in problems(tmp_path, text))


def test_expansion_exclude_include_and_verdicts(tmp_path):
    text = BASE + """\
  backend: [x, y]
exclude:
  - {backend: y, strategy: ptq_dynamic}
include:
  - {backend: y, strategy: none, precision: fp16, target: cuda}
"""
    matrix = load_matrix(write(tmp_path, text))
    cells, excluded = combinations(matrix, ["x", "y", "z"])
    assert excluded == 2  # y x ptq_dynamic x {fp32, int8}
    assert len(cells) == 2 * 2 * 2 - 2 + 1
    rulings = {}
    for cell in cells:
        key = ruling_key(matrix, cell)
        if key[2] == "none" and key[3] == "int8":
            rulings[key] = Ruling(invalid="none at int8 is not a thing")
        elif key[4] == "cuda":
            rulings[key] = Ruling(skip="no GPU")
        else:
            rulings[key] = Ruling()
    expansion = rule(matrix, cells, excluded, rulings)
    states = {p.cell.key: (p.state, p.reason) for p in expansion.cells}
    assert states["a/y/none/fp16/cuda"] == ("skip", "no GPU")
    assert states["a/x/none/int8/cpu"][0] == "invalid"
    assert states["a/x/ptq_dynamic/int8/cpu"] == ("run", None)


def test_training_strategies_need_a_trainer_and_backends_are_asked_for_the_qat_kind(tmp_path):
    text = BASE.replace("strategy: [none, ptq_dynamic]", "strategy: [qat]") + "  backend: [x]\n"
    matrix = load_matrix(write(tmp_path, text))
    cells, excluded = combinations(matrix, ["x"])
    rulings = {ruling_key(matrix, c): Ruling() for c in cells}
    assert {key[2] for key in rulings} == {"qat"}  # a QAT model, no conversion step: the backend converts it
    unruled = rule(matrix, cells, excluded, rulings)
    assert {p.state for p in unruled.cells} == {"invalid"}
    assert "no installed trainer" in unruled.cells[0].reason
    keys = {training_key(matrix, c) for c in cells}
    refused = rule(matrix, cells, excluded, rulings, {k: Ruling(invalid="qat: torch: no such thing")
                                                       for k in keys})
    assert refused.cells[0].reason == "qat: torch: no such thing"
    able = rule(matrix, cells, excluded, rulings, {k: Ruling(by="torch") for k in keys})
    assert {p.state for p in able.cells} == {"run"}


def test_published_schema_is_current():
    published = Path(__file__).parents[1] / "docs" / "matrix.schema.json"
    assert published.read_text() == schema_json(), "run `bench-matrix schema > docs/matrix.schema.json`"
    assert json.loads(schema_json())["required"] == ["models", "dataset", "axes"]


def test_docs_show_the_current_default_matrix_and_defaults():
    root = Path(__file__).parents[1]
    docs = (root / "docs" / "matrix.md").read_text()
    assert (root / "matrix.yaml").read_text() in docs, "docs/matrix.md §1 must show matrix.yaml as it is"
    assert f"circuits: {DatasetSpec.circuits}      # default {DatasetSpec.circuits};" in docs
    for precision in PRECISIONS:
        assert f"`{precision}`" in docs and f"`{precision}`" in (root / "docs" / "plugins.md").read_text()
