"""Test helper: a tiny PilotNet-shaped model factory (also used as a user factory by the CLI tests)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torch import nn

INPUT_SHAPE = (3, 16, 16)


def tiny() -> "nn.Module":
    """Input normalisation, two strided convolutions and a dense head: 3x16x16 -> 2 (about 1.9 k parameters)."""
    from torch import nn

    return nn.Sequential(nn.BatchNorm2d(3),
                         nn.Conv2d(3, 8, 3, stride=2), nn.ReLU(),
                         nn.Conv2d(8, 8, 3, stride=2), nn.ReLU(), nn.Flatten(),
                         nn.Linear(8 * 3 * 3, 16), nn.ReLU(), nn.Linear(16, 2))

