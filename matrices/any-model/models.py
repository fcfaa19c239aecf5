"""PyTorch factories of the any-model matrix: a small ResNet and a plain CNN (bend classifiers on 3x66x200
images), and a two-input transformer encoder (token ids and attention mask)."""

from __future__ import annotations

import torch
from torch import nn

CLASSES = 5  # the bends of the built-in driving_bends workload
VOCAB, SEQUENCE, WIDTH, HEADS, LAYERS = 1000, 32, 64, 4, 2


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 convolutions with BatchNorm, and a (1x1 if needed) shortcut."""

    def __init__(self, channels_in: int, channels_out: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels_in, channels_out, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels_out)
        self.conv2 = nn.Conv2d(channels_out, channels_out, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels_out)
        self.relu1, self.relu2 = nn.ReLU(), nn.ReLU()
        self.shortcut = nn.Identity()
        if stride != 1 or channels_in != channels_out:
            self.shortcut = nn.Sequential(nn.Conv2d(channels_in, channels_out, 1, stride, bias=False),
                                          nn.BatchNorm2d(channels_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.relu1(self.bn1(self.conv1(x)))
        return self.relu2(self.bn2(self.conv2(out)) + self.shortcut(x))


class SmallResNet(nn.Module):
    """A ResNet-10-style classifier: a strided stem, four basic blocks (16, 32, 64, 64 channels), global
    average pooling and a linear layer to the class logits."""

    def __init__(self, classes: int = CLASSES) -> None:
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(3, 16, 5, 2, 2, bias=False), nn.BatchNorm2d(16), nn.ReLU())
        self.blocks = nn.Sequential(BasicBlock(16, 16, 1), BasicBlock(16, 32, 2), BasicBlock(32, 64, 2),
                                    BasicBlock(64, 64, 2))
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.head = nn.Linear(64, classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(torch.flatten(self.pool(self.blocks(self.stem(x))), 1))


def resnet() -> nn.Module:
    """The factory the matrix names: an untrained SmallResNet (its weights come from resnet.pt)."""
    return SmallResNet()


def plain_cnn() -> nn.Module:
    """A VGG-style CNN (conv-BN-ReLU, max pooling) exported to cnn.onnx by build_models.py."""
    layers: list[nn.Module] = []
    channels = 3
    for width in (16, 32, 48, 64):
        layers += [nn.Conv2d(channels, width, 3, 1, 1), nn.BatchNorm2d(width), nn.ReLU(), nn.MaxPool2d(2)]
        channels = width
    return nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Dropout(0.2),
                         nn.Linear(channels, CLASSES))


class EncoderLayer(nn.Module):
    """Pre-norm transformer layer: masked multi-head self-attention and a GELU feed-forward block, written out
    with Linear layers so that TorchScript, FX quantisation and ONNX export all see plain operations."""

    def __init__(self) -> None:
        super().__init__()
        self.norm1, self.norm2 = nn.LayerNorm(WIDTH), nn.LayerNorm(WIDTH)
        self.qkv = nn.Linear(WIDTH, 3 * WIDTH)
        self.proj = nn.Linear(WIDTH, WIDTH)
        self.ff = nn.Sequential(nn.Linear(WIDTH, 4 * WIDTH), nn.GELU(), nn.Linear(4 * WIDTH, WIDTH))

    def forward(self, x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        batch, length = x.shape[0], x.shape[1]
        qkv = self.qkv(self.norm1(x)).reshape(batch, length, 3, HEADS, WIDTH // HEADS).permute(2, 0, 3, 1, 4)
        scores = torch.matmul(qkv[0], qkv[1].transpose(-2, -1)) * (WIDTH // HEADS) ** -0.5 + bias
        attended = torch.matmul(torch.softmax(scores, dim=-1), qkv[2]).transpose(1, 2)
        x = x + self.proj(attended.reshape(batch, length, WIDTH))
        return x + self.ff(self.norm2(x))


class Encoder(nn.Module):
    """(input_ids, attention_mask), both int64 (SEQUENCE,) -> (token states (SEQUENCE, WIDTH), the masked mean
    of the token states (WIDTH,)): a BERT-style sentence encoder."""

    def __init__(self) -> None:
        super().__init__()
        self.embed = nn.Embedding(VOCAB, WIDTH)
        self.position = nn.Parameter(torch.randn(SEQUENCE, WIDTH) * 0.02)
        self.layers = nn.ModuleList(EncoderLayer() for _ in range(LAYERS))
        self.norm = nn.LayerNorm(WIDTH)

    def forward(self, input_ids: torch.Tensor,
                attention_mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mask = attention_mask.to(torch.float32)
        bias = ((1.0 - mask) * -1e4)[:, None, None, :]  # finite, so fp16 stays finite; masked keys get ~0
        x = self.embed(input_ids) + self.position
        for layer in self.layers:
            x = layer(x, bias)
        states = self.norm(x)
        weights = mask[:, :, None]
        pooled = (states * weights).sum(dim=1) / weights.sum(dim=1).clamp(min=1.0)
        return states, pooled


def encoder() -> nn.Module:
    """The factory the matrix names: the two-layer encoder (its weights come from encoder.pt)."""
    return Encoder()
