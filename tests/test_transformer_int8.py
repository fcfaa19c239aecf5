"""ONNX Runtime int8 on transformer graphs exported from PyTorch, end to end: a ViT-style patch classifier and
a two-input text encoder (input_ids, attention_mask) give ok dynamic and static int8 cells with fidelity
figures, whatever ONNX Runtime's optional pre-quantisation pass manages on them (the record says which)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from conftest import cli

pytestmark = pytest.mark.slow
WIDTH, TOKENS, VOCAB = 32, 8, 50


class PatchClassifier(nn.Module):
    """ViT-style: 4×4 patches of a 3×16×16 image, a class token, one encoder layer, a linear head."""

    def __init__(self) -> None:
        super().__init__()
        self.patches = nn.Conv2d(3, WIDTH, kernel_size=4, stride=4)
        self.token = nn.Parameter(torch.randn(1, 1, WIDTH) * 0.02)
        self.position = nn.Parameter(torch.randn(1, 17, WIDTH) * 0.02)
        layer = nn.TransformerEncoderLayer(WIDTH, 4, 64, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, 1, enable_nested_tensor=False)
        self.head = nn.Linear(WIDTH, 3)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        tokens = self.patches(image).flatten(2).transpose(1, 2)
        tokens = torch.cat([self.token.expand(image.shape[0], -1, -1), tokens], 1) + self.position
        return self.head(self.encoder(tokens)[:, 0])


class TextEncoder(nn.Module):
    """Token ids and an attention mask (1: a token, 0: padding) in; the mean-pooled encoding, projected."""

    def __init__(self) -> None:
        super().__init__()
        self.embedding = nn.Embedding(VOCAB, WIDTH)
        layer = nn.TransformerEncoderLayer(WIDTH, 4, 64, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, 1, enable_nested_tensor=False)
        self.head = nn.Linear(WIDTH, 4)

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        hidden = self.encoder(self.embedding(input_ids), src_key_padding_mask=attention_mask == 0)
        weights = attention_mask.unsqueeze(-1).to(hidden.dtype)
        return self.head((hidden * weights).sum(1) / weights.sum(1).clamp(min=1.0))


def _export(model: nn.Module, example: tuple[torch.Tensor, ...], names: list[str], path: Path) -> None:
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model.eval(), example, str(path), dynamo=False, input_names=names,
                          output_names=["y"], dynamic_axes={name: {0: "batch"} for name in names},
                          opset_version=17)


def _project(root: Path) -> Path:
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    images = rng.random((64, 3, 16, 16), dtype=np.float32)  # already the model's per-sample shape
    _export(PatchClassifier(), (torch.from_numpy(images[:2]),), ["image"], root / "vit.onnx")
    np.savez(root / "images.npz", image=images, y=rng.integers(0, 3, 64))
    ids = rng.integers(1, VOCAB, (64, TOKENS)).astype(np.int64)
    mask = (np.arange(TOKENS)[None, :] < rng.integers(3, TOKENS + 1, (64, 1))).astype(np.int64)
    example = (torch.from_numpy(ids[:2]), torch.from_numpy(mask[:2]))
    _export(TextEncoder(), example, ["input_ids", "attention_mask"], root / "encoder.onnx")
    np.savez(root / "text.npz", input_ids=ids, attention_mask=mask)
    split = "split: {train: 0.25, calibration: 0.25, test: 0.5}"
    (root / "m.yaml").write_text(
        "models:\n"
        f"  - {{name: vit, framework: onnx, file: vit.onnx, task: classification,\n"
        f"     dataset: {{npz: images.npz, {split}}}}}\n"
        f"  - {{name: encoder, framework: onnx, file: encoder.onnx, task: none,\n"
        f"     dataset: {{npz: text.npz, {split}}}}}\n"
        f"dataset: {{npz: images.npz, {split}}}\n"
        "strategies:\n  ptq_static: {kind: ptq_static, calibration_samples: 16}\n"
        "axes: {backend: [onnxruntime], strategy: [none, ptq_dynamic, ptq_static], precision: [fp32, int8],"
        " target: [cpu]}\n"
        "settings: {window_s: 0.01, min_rounds: 2, timing_budget_s: 0.05, warmup_iterations: 2,"
        " warmup_s: 0.0, batch_size: 8, timeout_s: 300, processes: 1}\n")
    return root


def test_int8_cells_of_transformer_graphs_are_ok_with_fidelity_figures(tmp_path: Path) -> None:
    project = _project(tmp_path)
    run = cli(project, "run", "m.yaml", timeout=600)
    assert run.returncode == 0 and "0 failed" in run.stdout, run.stdout + run.stderr
    report = cli(project, "report", "--format", "json")
    found = json.loads(report.stdout)["records"]
    records = {f"{r['cell']['model']}/{r['cell']['strategy']}": r for r in found}
    for model in ("vit", "encoder"):
        for strategy in ("ptq_dynamic", "ptq_static"):
            record = records[f"{model}/{strategy}"]
            assert record["status"] == "ok", record
            metrics = record["metrics"]
            assert 0.5 < metrics["cosine_similarity"] <= 1.0, (model, strategy, metrics["cosine_similarity"])
            how = metrics["session"]["quantization"]["pre_process"]  # what ONNX Runtime's optional pass managed
            assert how["applied"] in ("full", "without symbolic shape inference", "none"), how
