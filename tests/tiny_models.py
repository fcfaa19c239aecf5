"""Test helper: a tiny PilotNet-shaped model factory (also used as a user factory by the CLI tests)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    from torch import nn

INPUT_SHAPE = (3, 16, 16)


def tiny() -> "nn.Module":
    """Input normalisation, two strided convolutions and a dense head: 3x16x16 -> 2 (about 1.9 k parameters)."""
    from torch import nn

    return nn.Sequential(nn.BatchNorm2d(3),
                         nn.Conv2d(3, 8, 3, stride=2), nn.ReLU(),
                         nn.Conv2d(8, 8, 3, stride=2), nn.ReLU(), nn.Flatten(),
                         nn.Linear(8 * 3 * 3, 16), nn.ReLU(), nn.Linear(16, 2))



def images(n: int, seed: int) -> "np.ndarray":
    """Noise images in [0, 1] (NCHW) whose colour balance varies from image to image."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return (rng.random((n, 3, 1, 1)) * rng.random((n, *INPUT_SHAPE))).astype(np.float32)


def colour_balance(x: "np.ndarray") -> "np.ndarray":
    """A learnable two-column target of NCHW images: red minus blue, and green."""
    import numpy as np

    means = x.mean(axis=(2, 3))
    return (np.stack([means[:, 0] - means[:, 2], means[:, 1]], axis=1) * 4 - 1).astype(np.float32)


def fitted() -> "nn.Module":
    """`tiny` fitted to colour_balance (100 Adam steps, seeded), in eval mode: its outputs follow its input as
    PilotNet's do (a random net outputs little but its biases, against which any precision check is vacuous)."""
    import torch

    torch.manual_seed(0)
    model = tiny()
    x = torch.from_numpy(images(512, 3))
    y = torch.from_numpy(colour_balance(x.numpy()))
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(100):
        batch = torch.randint(0, len(x), (64,))
        optimiser.zero_grad()
        torch.nn.functional.mse_loss(model(x[batch]), y[batch]).backward()
        optimiser.step()
    return model.eval()
