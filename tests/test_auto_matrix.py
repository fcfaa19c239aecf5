"""One command on a model file: `run MODEL_FILE` and `init MODEL_FILE` (the automatic matrix), with tiny real
models of every format."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

import fuzz_cases
from conftest import cli

from bench_matrix.cli import main
from bench_matrix.registry import load_backend


def plan_runs(project: Path, matrix: Path) -> int:
    """`plan` accepts the matrix unchanged (exit 0) and skips exactly the cells whose backend's probe says
    this machine cannot run (OpenVINO fp16 on a CPU without fp16); the number of cells that will run."""
    done = cli(project, "plan", str(matrix))
    assert done.returncode == 0, done.stderr
    counts = re.search(r"(\d+) will run, \d+ already stored, (\d+) will be skipped", done.stdout)
    assert counts and int(counts.group(1)) > 0, done.stdout
    rows = [cells for cells in _table_rows(done.stdout) if cells[5] in ("will run", "skipped")]
    assert len(rows) == int(counts.group(1)) + int(counts.group(2)), done.stdout
    for _, backend, _, precision, target, state, _ in rows:
        reason = load_backend(backend).probe(target, precision)
        assert (state == "skipped") == (reason is not None), (backend, precision, target, state, reason)
    return int(counts.group(1))


def _table_rows(printed: str) -> list[list[str]]:
    """The first line of each row of `plan`'s cell table: its seven columns, stripped."""
    lines = (line.strip().strip("│").split("│") for line in printed.splitlines() if line.count("│") == 8)
    return [[cell.strip() for cell in cells] for cells in lines if cells[0].strip()]


def init(project: Path, model: str, *options: str) -> Path:
    """`init` writes the matrix to a file in another folder: its paths must hold there too."""
    out = project / "elsewhere" / f"{Path(model).name}.yaml"
    out.parent.mkdir(exist_ok=True)
    done = cli(project, "init", model, "-o", str(out), *options)
    assert done.returncode == 0, done.stderr
    return out


def test_init_of_an_onnx_file_is_a_matrix_plan_accepts(tmp_path):
    fuzz_cases.write_project(tmp_path)
    printed = cli(tmp_path, "init", "tiny.onnx")
    assert printed.returncode == 0, printed.stderr
    text = printed.stdout
    assert text.startswith("# The automatic matrix of ") and "X (3, 16, 16) float32" in text
    assert f'file: "{tmp_path / "tiny.onnx"}"' in text and "synthetic: {samples: 256}" in text
    assert 'backend: ["onnxruntime"' in text and 'strategy: ["none", "ptq_dynamic", "ptq_static"]' in text
    saved = init(tmp_path, "tiny.onnx")
    assert saved.read_text() == text
    assert plan_runs(tmp_path, saved) >= 4  # onnxruntime: none fp32, fp16; ptq_dynamic, ptq_static int8


def test_init_with_data_and_a_task(tmp_path):
    fuzz_cases.write_project(tmp_path)
    saved = init(tmp_path, "tiny.onnx", "--data", "data.npz", "--task", "regression")
    assert f'npz: "{tmp_path / "data.npz"}"\n  task: regression' in saved.read_text()
    plan_runs(tmp_path, saved)


def test_init_of_torchscript_and_torch_export_files(tmp_path):
    import torch

    import tiny_models

    model, x = tiny_models.tiny().eval(), torch.zeros(2, *tiny_models.INPUT_SHAPE)
    torch.jit.save(torch.jit.trace(model, x), tmp_path / "tiny.pt")
    batch = torch.export.Dim("batch")
    torch.export.save(torch.export.export(model, (x,), dynamic_shapes=({0: batch},)), tmp_path / "tiny.pt2")
    unsaid = cli(tmp_path, "init", "tiny.pt")
    assert unsaid.returncode == 2 and "TorchScript files do not say them" in unsaid.stderr
    assert "--input NAME:SHAPE:DTYPE" in unsaid.stderr and "Traceback" not in unsaid.stderr
    scripted = init(tmp_path, "tiny.pt", "--input", "input:3,16,16:float32")
    assert '- {name: "input", shape: [3, 16, 16], dtype: float32}' in scripted.read_text()
    for saved in (scripted, init(tmp_path, "tiny.pt2")):
        text = saved.read_text()
        assert '"pytorch"' in text and "torch_compile: compiles the model with Inductor when" in text
        plan_runs(tmp_path, saved)


def test_init_of_a_keras_file(tmp_path):
    import tiny_keras

    tiny_keras.tiny().save(tmp_path / "tiny.keras")
    saved = init(tmp_path, "tiny.keras")
    assert "framework: tensorflow" in saved.read_text() and '"tensorflow"' in saved.read_text()
    plan_runs(tmp_path, saved)


@pytest.mark.parametrize("given, expected", [
    ("notes.txt", "notes.txt: is not a model bench-matrix reads; expected a model file (.h5, .keras, .onnx"),
    ("missing.onnx", "missing.onnx: no such file; expected a model file"),
    ("folder", "folder: is a folder without saved_model.pb; expected a model file"),
])
def test_a_path_that_is_not_a_model_exits_2_naming_it(tmp_path, capsys, monkeypatch, given, expected):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("hello\n")
    (tmp_path / "folder").mkdir()
    for command, also in (("run", ", or a matrix .yaml"), ("init", "")):
        assert main(["--workspace", str(tmp_path / "ws"), command, given]) == 2
        err = capsys.readouterr().err
        assert expected in err and "saved_model.pb)" + also in err and "Traceback" not in err, err


@pytest.mark.parametrize("options, expected", [
    (["--input", "x:3,a"], "--input 'x:3,a': give NAME:SHAPE:DTYPE"),
    (["--input", "x:3:float99"], "dtype 'float99' is not allowed; allowed: float32"),
    (["--data", "none.npz"], "--data none.npz: no such file or folder; expected an .npz"),
    (["--task", "regression"], "--task regression: synthetic data has no labels"),
])
def test_bad_model_options_exit_2(tmp_path, capsys, monkeypatch, options, expected):
    monkeypatch.chdir(fuzz_cases.write_project(tmp_path))
    assert main(["--workspace", str(tmp_path / "ws"), "init", "tiny.onnx", *options]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err, err


def test_model_options_are_refused_with_a_matrix(tmp_path, capsys):
    (tmp_path / "m.yaml").write_text("models: []\n")
    assert main(["--workspace", str(tmp_path / "ws"), "run", str(tmp_path / "m.yaml"), "--input", "x:3"]) == 2
    assert "--input: only for a model file" in capsys.readouterr().err


@pytest.mark.slow
def test_run_an_onnx_file_in_one_command(tmp_path):
    """The automatic matrix runs like any other: ok cells, stored; filters apply (default settings: each
    cell's rounds may take 3 s, so two cells, the baseline and one int8 cell)."""
    fuzz_cases.write_project(tmp_path)
    chosen = ("--backend", "onnxruntime", "--strategy", "none,ptq_static", "--precision", "fp32,int8")
    done = cli(tmp_path, "run", "tiny.onnx", *chosen)
    assert done.returncode == 0, done.stderr
    assert "automatic matrix of " in done.stdout and "written to " in done.stdout
    assert re.search(r"done: 2 ok, 0 skipped, 0 failed", done.stdout), done.stdout
    written = list((tmp_path / "ws" / "auto").glob("tiny-*.yaml"))
    assert len(written) == 1 and written[0].read_text() == cli(tmp_path, "init", "tiny.onnx").stdout
    again = cli(tmp_path, "run", "tiny.onnx", *chosen)
    assert "0 ok" in again.stdout and "2 already stored" in again.stdout, again.stdout
    planned = cli(tmp_path, "plan", "tiny.onnx", *chosen)  # the same automatic matrix, its cells stored
    assert planned.returncode == 0 and "automatic matrix of " in planned.stdout, planned.stderr
    assert re.search(r"0 will run, 2 already stored, 0 will be skipped", planned.stdout), planned.stdout


@pytest.mark.slow
def test_run_a_torchscript_file_with_two_outputs(tmp_path):
    """A TorchScript file returning two heads converts for ONNX Runtime and OpenVINO: ok cells, each output
    matched against the baseline's."""
    import torch

    import tiny_models

    two_heads = torch.jit.trace(tiny_models.fitted_two_outputs(), torch.rand(2, *tiny_models.INPUT_SHAPE),
                                strict=False)
    torch.jit.save(two_heads, tmp_path / "two_out.pt")
    shape = ",".join(map(str, tiny_models.INPUT_SHAPE))
    done = cli(tmp_path, "run", "two_out.pt", "--input", f"image:{shape}:float32", "--backend",
               "onnxruntime,openvino", "--strategy", "none", "--precision", "fp32")
    assert done.returncode == 0, done.stderr
    assert re.search(r"done: 2 ok, 0 skipped, 0 failed", done.stdout), done.stdout
    records = json.loads(cli(tmp_path, "report", "--format", "json").stdout)["records"]
    assert sorted(r["cell"]["backend"] for r in records) == ["onnxruntime", "openvino"]
    for record in records:
        outputs = record["metrics"]["per_output"]
        assert len(outputs) == 2 and all(o["cosine_similarity"] > 0.9999 for o in outputs), record
