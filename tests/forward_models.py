"""Test helper: a factory whose forward takes three named inputs and tells them apart, and data whose arrays
are stored in another order than forward's parameters."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torch import nn

WIDTH = 4  # every input's sample shape is (WIDTH,): swapped inputs would run, and compute something else


def abc() -> "nn.Module":
    """forward(a, b=None, c=None) -> (WIDTH,): dense(a) + 2 b - 3 c; b and c optional, each weighted
    differently, so that an input fed to another parameter changes the outputs."""
    import torch
    from torch import nn

    class ABC(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.dense = nn.Linear(WIDTH, WIDTH)

        def forward(self, a: torch.Tensor, b: torch.Tensor | None = None,
                    c: torch.Tensor | None = None) -> torch.Tensor:
            out = self.dense(a)
            if b is not None:
                out = out + 2 * b
            return out if c is None else out - 3 * c

    torch.manual_seed(0)
    return ABC()


def arrays(names: str, n: int = 32, seed: int = 0) -> dict[str, np.ndarray]:
    """One float32 (n, WIDTH) array per letter of `names`, in that order (as np.savez stores them)."""
    rng = np.random.default_rng(seed)
    return {name: rng.standard_normal((n, WIDTH)).astype(np.float32) for name in names}
