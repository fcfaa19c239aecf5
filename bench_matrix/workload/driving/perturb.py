"""Camera perturbations of a given strength (0: none, 1: the strongest searched by default), deterministic
from a seed and the brain step: every cell of a model sees the same perturbation at the same step."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .simulator import Brain, Observation

KINDS = ("light", "noise", "blur", "mix")
DARKEST = 0.75  # light at strength 1: the image keeps 25 % of its brightness and 25 % of its contrast
NOISE_SIGMA = 60.0  # noise at strength 1: Gaussian, this standard deviation in 8-bit levels
BLUR_SIGMA = 3.0  # blur at strength 1: Gaussian, this standard deviation in pixels


def dim(frame: np.ndarray, strength: float) -> np.ndarray:
    """Less light and less contrast: pixel values scaled about the image's mean, then the whole image."""
    keep = 1.0 - DARKEST * strength
    mean = frame.mean(axis=(0, 1), keepdims=True)
    return (mean + (frame - mean) * np.float32(keep)) * np.float32(keep)


def noise(frame: np.ndarray, strength: float, rng: np.random.Generator) -> np.ndarray:
    """Sensor noise: independent Gaussian noise on every pixel and channel."""
    return frame + rng.standard_normal(frame.shape, dtype=np.float32) * np.float32(NOISE_SIGMA * strength)


def blur(frame: np.ndarray, strength: float) -> np.ndarray:
    """Defocus: a separable Gaussian blur, edges extended."""
    sigma = BLUR_SIGMA * strength
    if sigma < 0.1:
        return frame
    radius = int(np.ceil(3 * sigma))
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    taps /= taps.sum()
    rows, cols = frame.shape[:2]
    down = np.pad(frame, [(radius, radius), (0, 0), (0, 0)], mode="edge")
    frame = sum(np.float32(t) * down[k:k + rows] for k, t in enumerate(taps))
    across = np.pad(frame, [(0, 0), (radius, radius), (0, 0)], mode="edge")
    return sum(np.float32(t) * across[:, k:k + cols] for k, t in enumerate(taps))


def perturb(frame: np.ndarray, kind: str, strength: float, seed: int, step: int) -> np.ndarray:
    """The frame (uint8) under perturbation `kind` at `strength`; the noise drawn from (seed, step)."""
    if strength <= 0:
        return frame
    image = frame.astype(np.float32)
    if kind in ("light", "mix"):
        image = dim(image, strength)
    if kind in ("blur", "mix"):
        image = blur(image, strength)
    if kind in ("noise", "mix"):
        image = noise(image, strength, np.random.default_rng([seed, step]))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@dataclass
class PerturbedCamera:
    """A brain that sees every frame perturbed; its own step count keys the noise."""

    brain: Brain
    kind: str
    strength: float
    seed: int
    steps: int = 0

    def __call__(self, observation: Observation) -> tuple[float, float]:
        frame = perturb(observation.frame, self.kind, self.strength, self.seed, self.steps)
        self.steps += 1
        return self.brain(Observation(frame, observation.pose))


def perturbed(brain: Brain, kind: str, seed: int) -> Callable[[float], Brain]:
    """A fresh perturbed brain for each strength (each lap counts its steps from 0)."""
    return lambda strength: PerturbedCamera(brain, kind, strength, seed)
