"""PyTorch eager mode: the native baseline for PyTorch models."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from bench_matrix.plugin import ConvertRequest, Session, SourceModel, Support

from ._torch import TorchBackend, TorchSession, pin_threads, place


class PyTorchBackend(TorchBackend):
    """The source model as it is, run eagerly under torch.inference_mode()."""

    name = "pytorch"
    description = "PyTorch eager mode under torch.inference_mode() (the PyTorch fp32 baseline)"
    supports = (Support(("pytorch",), ("none",), ("fp32",), ("cpu",)),
                Support(("pytorch",), ("none",), ("fp32", "fp16", "bf16"), ("cuda",)))
    baseline_for = ("pytorch",)

    def convert(self, request: ConvertRequest) -> dict[str, Any]:
        step = request.step
        if step.kind != "none":
            raise ValueError(f"the pytorch backend runs the model as it is; strategy kind {step.kind!r} "
                             f"needs another backend (torchscript, onnxruntime or torch_tensorrt)")
        source = request.source
        shutil.copy2(source.path, request.out_dir / source.path.name)
        return {"source": {**source.to_dict(), "path": source.path.name}}

    def load(self, artifact_dir: Path, meta: dict[str, Any], target: str, precision: str,
             threads: int) -> Session:
        pin_threads(threads)
        source = SourceModel.from_dict({**meta["source"], "path": str(artifact_dir / meta["source"]["path"])})
        return TorchSession(place(source.load(), target, precision), target, precision)
