"""Test helper: user models beyond PilotNet — a classifier, a two-input model (float features and int64 token
ids), a two-output regressor and a model whose outputs are NaN — with data files that fit them."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torch import nn

CLASSES = 3
FEATURES, TOKENS, VOCAB = 6, 5, 11


def classifier() -> "nn.Module":
    """3x16x16 images -> logits over 3 classes."""
    from torch import nn

    return nn.Sequential(nn.Conv2d(3, 8, 3, stride=2), nn.ReLU(), nn.Conv2d(8, 8, 3, stride=2), nn.ReLU(),
                         nn.Flatten(), nn.Linear(8 * 3 * 3, 16), nn.ReLU(), nn.Linear(16, CLASSES))


def two_input() -> "nn.Module":
    """(features float32 (6,), ids int64 (5,)) -> one (4,) output: a dense layer over the features plus the
    mean embedding of the ids."""
    import torch
    from torch import nn

    class TwoInput(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.dense = nn.Linear(FEATURES, 4)
            self.embed = nn.Embedding(VOCAB, 4)

        def forward(self, features: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
            return torch.relu(self.dense(features)) + self.embed(ids).mean(dim=1)

    return TwoInput()


def two_output() -> "nn.Module":
    """(6,) features -> ((2,), (1,)): a regressor with two heads."""
    import torch
    from torch import nn

    class TwoOutput(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.body = nn.Linear(FEATURES, 8)
            self.first, self.second = nn.Linear(8, 2), nn.Linear(8, 1)

        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            hidden = torch.relu(self.body(x))
            return self.first(hidden), self.second(hidden)

    return TwoOutput()


def not_a_number() -> "nn.Module":
    """(6,) features -> (2,) outputs that are all NaN (log of a negative number)."""
    import torch
    from torch import nn

    class NotANumber(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.dense = nn.Linear(FEATURES, 2)

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.log(-torch.abs(self.dense(x)) - 1.0)

    return NotANumber()


def save(factory, folder: Path, name: str) -> Path:
    """The factory's seeded initial state_dict saved as folder/name."""
    import torch

    torch.manual_seed(0)
    path = folder / name
    torch.save(factory().state_dict(), path)
    return path


def class_images(folder: Path, n: int = 90) -> Path:
    """images.npz: 16x16 RGB uint8 images labelled by their brightest channel (int64 class ids 0..2)."""
    rng = np.random.default_rng(1)
    x = rng.integers(0, 120, size=(n, 16, 16, 3), dtype=np.uint8)
    y = np.arange(n) % CLASSES
    for i, label in enumerate(y):
        x[i, ..., label] += 100
    path = folder / "images.npz"
    np.savez(path, x=x, y=y.astype(np.int64))
    return path


def features(folder: Path, n: int = 80, labels: int = 0) -> Path:
    """features.npz: `features` float32 (n, 6), `ids` int64 (n, 5) and, with labels > 0, y float32 (n, labels)."""
    rng = np.random.default_rng(2)
    arrays = {"features": rng.standard_normal((n, FEATURES)).astype(np.float32),
              "ids": rng.integers(0, VOCAB, size=(n, TOKENS)).astype(np.int64)}
    if labels:
        arrays["y"] = rng.standard_normal((n, labels)).astype(np.float32)
    path = folder / "features.npz"
    np.savez(path, **arrays)
    return path
