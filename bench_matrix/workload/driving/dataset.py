"""Deterministic synthetic driving data set: camera images labelled with the expert's [v, w]."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .circuit import Circuit
from .expert import ExpertController
from .render import Camera, Lighting, render

MAX_OFFSET = 2.0  # metres either side of the centreline
MAX_HEADING_ERROR = np.radians(15.0)


@dataclass(frozen=True, eq=False)
class DrivingData:
    """Images [N, 66, 200, 3] uint8, raw labels [N, 2] float32 as (v, w), circuit index [N] int32."""

    images: np.ndarray
    labels: np.ndarray
    groups: np.ndarray

    def __len__(self) -> int:
        """Number of samples."""
        return len(self.labels)


def generate(n_samples: int, seed: int = 0, n_circuits: int = 8) -> DrivingData:
    """Render `n_samples` frames spread evenly over `n_circuits` circuits; bit-identical for a seed."""
    camera, expert = Camera(), ExpertController()
    circuit_seeds = np.random.default_rng(seed).integers(0, 2**31, n_circuits)
    counts = np.full(n_circuits, n_samples // n_circuits) + (np.arange(n_circuits) < n_samples % n_circuits)
    images = np.empty((n_samples, camera.rows, camera.cols, 3), dtype=np.uint8)
    labels = np.empty((n_samples, 2), dtype=np.float32)
    groups = np.repeat(np.arange(n_circuits, dtype=np.int32), counts)
    k = 0
    for index, (circuit_seed, count) in enumerate(zip(circuit_seeds, counts)):
        circuit = Circuit.from_seed(int(circuit_seed))
        rng = np.random.default_rng([seed, index])
        s = rng.uniform(0.0, circuit.length, count)
        x, y, heading = circuit.pose_at(s, rng.uniform(-MAX_OFFSET, MAX_OFFSET, count))
        reverse = np.pi * (rng.random(count) < 0.5)
        yaw = heading + reverse + rng.uniform(-MAX_HEADING_ERROR, MAX_HEADING_ERROR, count)
        for pose in zip(x.tolist(), y.tolist(), yaw.tolist()):
            images[k] = render(circuit, pose, Lighting.sample(rng), camera)
            labels[k] = expert.command(circuit, pose)
            k += 1
    return DrivingData(images, labels, groups)
