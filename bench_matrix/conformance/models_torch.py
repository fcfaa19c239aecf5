"""The kit's PyTorch models: factories importable by name (a state_dict source is rebuilt from one), their
seeded weights, and eager fp32 outputs (a dict's values by sorted key, the order sessions fetch in)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bench_matrix.conformance.models import CHANNELS, CLASSES, FEATURES, HEAD, HIDDEN, VOCABULARY, WIDE, \
    batch_norm_statistics
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs

if TYPE_CHECKING:
    from torch import nn

TRUNK_OUT = 8 * 3 * 3  # two 3x3 convolutions of stride 2 take 16x16 to 3x3, with 8 channels


def image_net(outputs: int) -> "nn.Module":
    """Two strided convolutions, the first with a BatchNorm, and a dense head: (3, 16, 16) -> `outputs`."""
    from torch import nn

    return nn.Sequential(nn.Conv2d(CHANNELS, 8, 3, stride=2), nn.BatchNorm2d(8), nn.ReLU(),
                         nn.Conv2d(8, 8, 3, stride=2),
                         nn.ReLU(), nn.Flatten(), nn.Linear(TRUNK_OUT, HIDDEN), nn.ReLU(),
                         nn.Linear(HIDDEN, outputs))


def regression() -> "nn.Module":
    return image_net(2)


def classification() -> "nn.Module":
    return image_net(CLASSES)


def multi_io() -> "nn.Module":
    """forward(features, ids) -> {"speed": (N, 2), "angle": (N, 2)}: a dict with keys not in sorted order."""
    import torch
    from torch import nn

    class MultiIO(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embedding = nn.Embedding(VOCABULARY, 4)
            self.body = nn.Sequential(nn.Linear(FEATURES + 4, WIDE), nn.ReLU())
            self.speed, self.angle = nn.Linear(WIDE, HEAD), nn.Linear(WIDE, HEAD)

        def forward(self, features: torch.Tensor, ids: torch.Tensor) -> dict[str, torch.Tensor]:
            hidden = self.body(torch.cat([features, self.embedding(ids).mean(dim=1)], dim=1))
            return {"speed": self.speed(hidden), "angle": self.angle(hidden)}

    return MultiIO()


FACTORIES = {"regression": regression, "classification": classification, "multi_io": multi_io}


def factory(name: str) -> str:
    return f"{__name__}:{name}"


def save(name: str, folder: Path) -> Path:
    """The model with seeded He-initialised weights, zero biases and the kit's BatchNorm statistics, saved as
    a state_dict."""
    import torch
    from torch import nn

    torch.manual_seed(0)
    module = FACTORIES[name]().eval()
    for layer in module.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
            nn.init.zeros_(layer.bias)
        if isinstance(layer, nn.BatchNorm2d):
            for key, values in batch_norm_statistics(layer.num_features).items():
                getattr(layer, key).data.copy_(torch.from_numpy(values))
    path = folder / f"{name}.pt"
    torch.save(module.state_dict(), path)
    return path


def reference(source: SourceModel, inputs: Inputs) -> list[np.ndarray]:
    """The module's eager fp32 outputs on the CPU."""
    import torch

    with torch.inference_mode():
        out: Any = source.load()(*(torch.from_numpy(array) for array in inputs.values()))
    values = [out[key] for key in sorted(out)] if isinstance(out, dict) else [out]
    return [value.numpy() for value in values]
