"""Test helper: a tiny PilotNet-shaped model factory (also used as a user factory by the CLI tests)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np
    import onnx
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


FEATURES, TOKENS, VOCABULARY = 6, 5, 10  # the two-input models' float features and int64 token ids per sample


def two_inputs() -> "nn.Module":
    """forward(features float (6,), ids int64 (5,)): the ids' mean embedding beside the features, a dense head -> 2."""
    import torch
    from torch import nn

    class TwoInputs(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.embedding = nn.Embedding(VOCABULARY, 4)
            self.head = nn.Sequential(nn.Linear(FEATURES + 4, 16), nn.ReLU(), nn.Linear(16, 2))

        def forward(self, features: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
            return self.head(torch.cat([features, self.embedding(ids).mean(dim=1)], dim=1))

    torch.manual_seed(0)
    return TwoInputs().eval()


def two_outputs() -> "nn.Module":
    """`tiny`'s trunk with two heads, returned as a dict whose keys are not in sorted order: {"speed": (N, 1),
    "angle": (N, 2)}."""
    import torch
    from torch import nn

    class TwoOutputs(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.trunk = tiny()[:-1]
            self.speed = nn.Linear(16, 1)
            self.angle = nn.Linear(16, 2)

        def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
            hidden = self.trunk(image)
            return {"speed": self.speed(hidden), "angle": self.angle(hidden)}

    torch.manual_seed(0)
    return TwoOutputs().eval()


def fitted_two_outputs() -> "nn.Module":
    """`two_outputs` with `fitted`'s trunk and head (as angle), and speed the sum of the two angles, so that both
    outputs follow the input."""
    import torch

    module, trained = two_outputs(), fitted()
    module.trunk.load_state_dict(trained[:-1].state_dict())
    module.angle.load_state_dict(trained[-1].state_dict())
    with torch.no_grad():
        module.speed.weight.copy_(trained[-1].weight.sum(dim=0, keepdim=True))
        module.speed.bias.copy_(trained[-1].bias.sum(dim=0, keepdim=True))
    return module


def token_data(n: int, seed: int) -> dict[str, "np.ndarray"]:
    """Inputs of `two_inputs`: standard-normal features and token ids in [0, VOCABULARY)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return {"features": rng.standard_normal((n, FEATURES)).astype(np.float32),
            "ids": rng.integers(0, VOCABULARY, (n, TOKENS)).astype(np.int64)}


def positions() -> "nn.Module":
    """forward(ids int64 (5,)) -> 2, with BERT's embeddings: a position_ids buffer sliced by the length read
    from the ids' shape, each position's embedding added to its token's."""
    import torch
    from torch import nn

    class Positions(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("position_ids", torch.arange(32).expand(1, -1), persistent=False)
            self.words, self.places = nn.Embedding(VOCABULARY, 16), nn.Embedding(32, 16)
            self.dense, self.head = nn.Linear(16, 16), nn.Linear(16, 2)

        def forward(self, ids: torch.Tensor) -> torch.Tensor:
            places = self.position_ids[:, :ids.size(1)]
            return self.head(torch.relu(self.dense(self.words(ids) + self.places(places))).mean(1))

    torch.manual_seed(0)
    return Positions().eval()


def conv_gemm() -> "onnx.ModelProto":
    """An ONNX model (N,3,16,16) -> Conv 3x3 (8 channels, padded) -> Relu -> Reshape -> Gemm -> (N,4)."""
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    weights = [numpy_helper.from_array(rng.standard_normal(shape).astype(np.float32), name)
               for name, shape in (("CW", (8, 3, 3, 3)), ("CB", (8,)), ("GW", (2048, 4)), ("GB", (4,)))]
    weights.append(numpy_helper.from_array(np.array([-1, 2048], np.int64), "S"))
    nodes = [helper.make_node("Conv", ["X", "CW", "CB"], ["C"], pads=[1, 1, 1, 1]),
             helper.make_node("Relu", ["C"], ["R"]), helper.make_node("Reshape", ["R", "S"], ["F"]),
             helper.make_node("Gemm", ["F", "GW", "GB"], ["Y"])]
    graph = helper.make_graph(nodes, "conv_gemm",
                              [helper.make_tensor_value_info("X", TensorProto.FLOAT, ["N", 3, 16, 16])],
                              [helper.make_tensor_value_info("Y", TensorProto.FLOAT, ["N", 4])], weights)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
