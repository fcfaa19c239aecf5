"""Load PyTorch source models safely: TorchScript, torch.export programs, or a factory plus weights."""

from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

    from bench_matrix.sources import SourceModel


def load_module(source: "SourceModel") -> "torch.nn.Module":
    """A fresh module in eval mode on the CPU."""
    import torch

    if source.format == "torchscript":
        module = torch.jit.load(str(source.path), map_location="cpu")
    elif source.format == "torch_export":  # exported in inference mode already; its module refuses .eval()
        return torch.export.load(str(source.path)).module()
    elif source.format == "state_dict":
        module = build_from_factory(source.factory or "", source.python_path)
        state = torch.load(str(source.path), map_location="cpu", weights_only=True)
        module.load_state_dict(state)
    else:
        raise ValueError(f"{source.path}: format {source.format!r} is not a PyTorch format")
    return module.eval()


def build_from_factory(factory: str, python_path: tuple[str, ...] = ()) -> "torch.nn.Module":
    """Call 'package.module:function' (with the matrix's python_path on sys.path) to build a module."""
    for entry in reversed(python_path):
        if entry not in sys.path:
            sys.path.insert(0, entry)
    module_name, _, attr = factory.partition(":")
    try:
        builder = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"cannot import factory {factory!r}: {exc}") from exc
    return builder()


def count_params(module: "torch.nn.Module") -> int:
    """Number of parameter elements (ScriptModules included)."""
    return int(sum(p.numel() for p in module.parameters()))
