"""PilotNet reference models in PyTorch (NCHW 3x66x200 in, normalised [v, w] out), as in the study."""

from __future__ import annotations

import torch
from torch import nn


def _features() -> nn.Sequential:
    return nn.Sequential(
        nn.BatchNorm2d(3),
        nn.Conv2d(3, 24, 5, stride=2), nn.ReLU(),
        nn.Conv2d(24, 36, 5, stride=2), nn.ReLU(),
        nn.Conv2d(36, 48, 5, stride=2), nn.ReLU(),
        nn.Conv2d(48, 64, 3), nn.ReLU(),
        nn.Conv2d(64, 64, 3), nn.ReLU(),
        nn.Flatten(),
    )


def _head(widths: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(widths[:-2], widths[1:-1]):
        layers += [nn.Linear(a, b), nn.ReLU()]
    layers.append(nn.Linear(widths[-2], widths[-1]))
    return nn.Sequential(*layers)


class PilotNet(nn.Module):
    """Convolutions without padding (flatten 64x1x18 = 1152) followed by a dense head."""

    def __init__(self, head: list[int]):
        super().__init__()
        self.features = _features()
        self.head = _head([1152, *head, 2])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


def pilotnet() -> PilotNet:
    """NVIDIA's PilotNet: 1152 -> 100 -> 50 -> 10 -> 2 (about 252 k parameters)."""
    return PilotNet([100, 50, 10])


def pilotnet_jderobot() -> PilotNet:
    """The JdeRobot PyTorch variant: 1152 -> 1164 -> 100 -> 50 -> 10 -> 2 (1,595,528 parameters)."""
    return PilotNet([1164, 100, 50, 10])


FACTORIES = {"pilotnet": "bench_matrix.workload.pilotnet_torch:pilotnet",
             "pilotnet_jderobot": "bench_matrix.workload.pilotnet_torch:pilotnet_jderobot"}
