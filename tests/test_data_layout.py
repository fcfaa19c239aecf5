"""Data already in the model's per-sample shape (an .npz stored the PyTorch way, N×C×H×W) is passed to the
model as it is; data read as H×W×C images that does not fit says which layout was assumed and how to declare
another."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import fuzz_cases
from conftest import cli, onnx_matrix_text

from bench_matrix import data
from bench_matrix.matrix.spec import DatasetSpec
from bench_matrix.tensors import TensorSpec

WEIGHTS = np.full((3, 2), 0.5, np.float32)  # fuzz_cases.onnx_model: Y = mean of X over H and W, times W


def _project(folder: Path, x: np.ndarray) -> Path:
    """tiny.onnx (N,3,16,16) -> (N,2), data.npz holding `x` and labels, and a matrix running it."""
    (folder / "tiny.onnx").write_bytes(fuzz_cases.onnx_model())
    np.savez(folder / "data.npz", x=x, y=np.random.default_rng(1).random((len(x), 2), np.float32))
    (folder / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]))
    return folder


def test_nchw_float_data_of_the_model_shape_is_passed_as_it_is(tmp_path: Path) -> None:
    x = np.random.default_rng(0).standard_normal((48, 3, 16, 16)).astype(np.float32)  # not pixels: no scale
    project = _project(tmp_path, x)
    plan = cli(project, "plan", "m.yaml")
    assert plan.returncode == 0, plan.stderr
    run = cli(project, "run", "m.yaml")
    assert run.returncode == 0, run.stderr
    (record,) = json.loads(cli(project, "report", "--format", "json").stdout)["records"]
    assert record["status"] == "ok", record["reason"]
    test = slice(36, 48)  # split by block: train 0.5, calibration 0.25, test 0.25
    expected = x[test].mean(axis=(2, 3)) @ WEIGHTS
    labels = np.load(project / "data.npz")["y"][test]
    np.testing.assert_allclose(record["metrics"]["mse"], np.mean((expected - labels) ** 2), rtol=1e-5)


def test_only_arrays_that_image_reading_would_change_are_passed_as_they_are(tmp_path: Path) -> None:
    np.savez(tmp_path / "d.npz", x=np.zeros((4, 3, 16, 16), np.float32), y=np.zeros(4))
    np.savez(tmp_path / "hwc.npz", x=np.zeros((4, 16, 16, 3), np.uint8), y=np.zeros(4))
    nchw, hwc = (DatasetSpec(kind="npz", paths=(tmp_path / name,)) for name in ("d.npz", "hwc.npz"))
    assert data.model_shaped(nchw, (TensorSpec("input", (3, 16, 16)),), "nchw") == ("x",)
    assert data.describe(nchw, "nchw", ("x",))["x"] == TensorSpec("x", (3, 16, 16), "float32")
    assert data.model_shaped(hwc, (TensorSpec("input", (16, 16, 3)),), "nhwc") == ()  # images, scaled as ever
    # uint8 pixels stay images even where the model's shape is theirs (layout left at nchw): never unscaled
    assert data.model_shaped(hwc, (TensorSpec("input", (16, 16, 3)),), "nchw") == ()
    assert data.model_shaped(nchw, None, "nchw") == ()  # the model's inputs unknown: read as images


def test_images_that_do_not_fit_say_which_layout_was_assumed(tmp_path: Path) -> None:
    x = np.random.default_rng(0).integers(0, 256, (48, 8, 8, 3), dtype=np.uint8)
    plan = cli(_project(tmp_path, x), "plan", "m.yaml")
    assert plan.returncode == 2 and "Traceback" not in plan.stderr
    assert ("m.yaml:2: models[0]: model tiny (tiny.onnx) with data.npz: the model's input X (3, 16, 16) "
            "float32 gets the data's 'x' of shape (3, 8, 8) per sample; the data's 'x' (8, 8, 3) per sample "
            "was read as H×W×C images and laid out C×H×W for the model (its layout: nchw); if the model "
            "takes H×W×C, set layout: nhwc on the model, and data stored in the model's own per-sample shape "
            "is passed as it is"
            ) in plan.stderr, plan.stderr
