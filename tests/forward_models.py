"""Test helper: a factory whose forward takes three named inputs and tells them apart, and data whose arrays
are stored in another order than forward's parameters; a factory taking keyword inputs as Hugging Face models
do, and modules no FX tracer can trace."""

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


VOCABULARY, TOKENS = 16, 6  # the keyword model's token ids per sample, and how many ids there are


def keywords() -> "nn.Module":
    """forward(input_ids=None, attention_mask=None, inputs_embeds=None) -> (2,), as a Hugging Face model's:
    the masked mean of the ids' embeddings through a dense layer; ValueError when input_ids and inputs_embeds
    are both given, as Hugging Face's models raise."""
    import torch
    from torch import nn

    class Keywords(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embedding = nn.Embedding(VOCABULARY, WIDTH)
            self.dense = nn.Linear(WIDTH, 2)

        def forward(self, input_ids: torch.Tensor | None = None, attention_mask: torch.Tensor | None = None,
                    inputs_embeds: torch.Tensor | None = None) -> torch.Tensor:
            if input_ids is not None and inputs_embeds is not None:
                raise ValueError("You cannot specify both input_ids and inputs_embeds at the same time")
            embeds = self.embedding(input_ids) if inputs_embeds is None else inputs_embeds
            mask = attention_mask.unsqueeze(-1).float()
            return self.dense((embeds * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1.0))

    torch.manual_seed(0)
    return Keywords()


def token_arrays(n: int = 48, seed: int = 0) -> dict[str, np.ndarray]:
    """Inputs of `keywords`: int64 token ids and an int64 attention mask whose first id is always attended."""
    rng = np.random.default_rng(seed)
    mask = (rng.random((n, TOKENS)) < 0.7).astype(np.int64)
    mask[:, 0] = 1
    return {"input_ids": rng.integers(0, VOCABULARY, (n, TOKENS)).astype(np.int64), "attention_mask": mask}


def branchy(transformers: bool = False) -> "nn.Module":
    """forward(input_ids, attention_mask) branching on the ids' values, which no FX tracer can trace; with
    `transformers`, its class says it comes from the transformers package (as a Hugging Face model's does)."""
    import torch
    from torch import nn

    class Branchy(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.dense = nn.Linear(TOKENS, 2)

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            x = (input_ids * attention_mask).float()
            return self.dense(x if x.sum() > 0 else -x)

    if transformers:
        Branchy.__module__ = "transformers.models.branchy.modeling_branchy"
    return Branchy()


def transformers_branchy() -> "nn.Module":
    """`branchy`, its class from the transformers package as far as its __module__ says."""
    return branchy(transformers=True)
