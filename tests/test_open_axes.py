"""Inputs with open axes (a dynamic image size): the shapes timed are said by init, plan, run and the report,
and a warning names each input whose open axes synthetic data gives the default length."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

import fuzz_cases
from conftest import cli
from test_auto_matrix import init

DYNAMIC = ("N", 3, "height", None)  # a named (symbolic) and an unnamed open axis
SAID = "model dyn: timed with X 3×8×8 float32 per sample (synthetic data; open axes given 8)"  # plan, run
DOCS = "(docs/models.md#inputs-with-open-axes)"
WARNED = ("input 'X' (3×?×?) float32 has open axes 2 and 3 (the batch axis is 0), which synthetic data gives "
          "the default length 8: it is timed at 3×8×8 per sample; give the lengths to time with ")


def project(tmp_path: Path) -> Path:
    """tiny.onnx (3×16×16), data.npz (16×16 RGB images) and dyn.onnx, whose height and width are open."""
    fuzz_cases.write_project(tmp_path)
    (tmp_path / "dyn.onnx").write_bytes(fuzz_cases.onnx_model(dims=DYNAMIC))
    return tmp_path


def warnings(stderr: str) -> list[str]:
    return re.findall(r"^warning: .*$", stderr, re.MULTILINE)


@pytest.mark.slow
def test_open_axes_are_said_by_init_plan_run_and_report(tmp_path):
    dyn = project(tmp_path) / "dyn.onnx"
    text = init(tmp_path, "dyn.onnx").read_text()
    assert "# Synthetic inputs are timed at X 3×8×8 float32 per sample.\n" in text
    assert "# X: axes 2 and 3 open in the file (the batch axis is 0), given 8 by synthetic data" in text
    assert '    #   - {name: "X", shape: [3, null, null], dtype: float32}\n' in text
    line = text.splitlines().index('  - name: "dyn"') + 1
    planned = cli(tmp_path, "plan", "elsewhere/dyn.onnx.yaml")
    assert planned.returncode == 0 and SAID in planned.stdout, planned.stderr
    assert warnings(planned.stderr) == [
        f"warning: elsewhere/dyn.onnx.yaml:{line}: model dyn ({dyn}): {WARNED}models[0].inputs: "
        f"[{{name: X, shape: [3, <length>, <length>], dtype: float32}}] {DOCS}"]
    chosen = ("--backend", "onnxruntime", "--strategy", "none", "--precision", "fp32")
    ran = cli(tmp_path, "run", "dyn.onnx", *chosen)
    assert ran.returncode == 0 and SAID in ran.stdout and "done: 1 ok" in ran.stdout, ran.stdout + ran.stderr
    assert warnings(ran.stderr) == [
        f"warning: model dyn ({dyn}): {WARNED}--input X:3,<length>,<length>:float32 {DOCS}"]
    assert cli(tmp_path, "report", "--format", "md", "--out", "reports").returncode == 0
    assert ("· inputs timed at X 3×8×8 float32 per sample (X: axes 2 and 3 open in the model, given "
            "synthetic data's default length)") in (tmp_path / "reports" / "dyn.md").read_text()


@pytest.mark.parametrize("model, options, said", [
    ("tiny.onnx", (), "model tiny: timed with X 3×16×16 float32 per sample (synthetic data)"),
    ("dyn.onnx", ("--input", "X:3,32,32:float32"),
     "model dyn: timed with X 3×32×32 float32 per sample (synthetic data)"),
    ("dyn.onnx", ("--data", "data.npz"),
     "model dyn: timed with X 3×16×16 float32 per sample (the data's shapes)"),
], ids=["fixed", "given", "data"])
def test_no_warning_where_every_axis_has_a_length(tmp_path, model, options, said):
    """A file whose axes are all fixed, lengths given with --input, or data: the shapes said, no warning."""
    saved = init(project(tmp_path), model, *options)
    assert "# X:" not in saved.read_text() and "# inputs:" not in saved.read_text()
    planned = cli(tmp_path, "plan", str(saved))
    assert planned.returncode == 0 and said in planned.stdout, planned.stdout + planned.stderr
    assert warnings(planned.stderr) == [], planned.stderr


def test_open_axes_of_declared_inputs_and_of_a_torch_export_file(tmp_path):
    """Several inputs, each warned on its own: declared `null` axes of a factory's inputs and torch.export's
    dynamic height and width (Dim)."""
    import torch
    from torch import nn

    model = nn.Sequential(nn.Conv2d(3, 4, 3), nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(4, 2)).eval()
    batch, height, width = (torch.export.Dim(n, min=low, max=64) for n, low in (("b", 2), ("h", 4), ("w", 4)))
    program = torch.export.export(model, (torch.rand(2, 3, 16, 16),),
                                  dynamic_shapes=({0: batch, 2: height, 3: width},))
    torch.export.save(program, tmp_path / "pooled.pt2")
    torch.save(__import__("tiny_models").two_inputs().state_dict(), tmp_path / "two.pt")
    inputs = [{"name": "features", "shape": [6]}, {"name": "ids", "shape": [None], "dtype": "int64"}]
    matrix = {"models": [{"name": "pooled", "framework": "pytorch", "file": "pooled.pt2"},
                         {"name": "two", "framework": "pytorch", "factory": "tiny_models:two_inputs",
                          "weights": "two.pt", "python_path": [str(Path(__file__).parent)],
                          "inputs": inputs}],
              "dataset": {"synthetic": {"samples": 64}},
              "axes": {"backend": ["pytorch"], "strategy": ["none"], "precision": ["fp32"],
                       "target": ["cpu"]}}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(matrix, sort_keys=False))
    planned = cli(tmp_path, "plan", "m.yaml")
    assert planned.returncode == 0, planned.stderr
    assert "model pooled: timed with input 3×8×8 float32 per sample (synthetic data; open axes given 8)" in \
        planned.stdout
    assert ("model two: timed with features 6 float32, ids 8 int64 per sample (synthetic data; open axes "
            "given 8)") in planned.stdout
    found = warnings(planned.stderr)
    assert len(found) == 2, planned.stderr
    assert found[0].startswith("warning: m.yaml:2: model pooled (pooled.pt2): input 'input' (3×?×?) float32 "
                               "has open axes 2 and 3 (the batch axis is 0)"), found
    assert found[1].startswith("warning: m.yaml:15: model two (tiny_models:two_inputs + two.pt): input 'ids' "
                               "(?) int64 has open axis 1 (the batch axis is 0), which synthetic data gives "
                               "the default length 8: it is timed at 8 per sample"), found
    assert found[1].endswith(f"give the lengths to time with models[1].inputs[1].shape: [<length>] {DOCS}"), \
        found
