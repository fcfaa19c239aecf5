"""Shared fixtures: a tiny user project (model factory + weights, .npz dataset, matrix) and a CLI runner."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
FAST_SETTINGS = ("settings: {min_iterations: 5, min_time_s: 0.02, warmup_iterations: 2, warmup_s: 0.0, "
                 "throughput_time_s: 0.02, batch_size: 8, timeout_s: 120}\n")


@pytest.fixture
def tiny_project(tmp_path: Path) -> Path:
    """A directory holding tiny.pt (state_dict of tests/tiny_models.py:tiny), data.npz and nothing else."""
    import torch

    sys.path.insert(0, str(TESTS))
    from tiny_models import tiny

    torch.manual_seed(0)
    torch.save(tiny().state_dict(), tmp_path / "tiny.pt")
    rng = np.random.default_rng(0)
    x = rng.integers(0, 256, size=(96, 16, 16, 3), dtype=np.uint8)
    y = np.stack([x[..., 0].mean(axis=(1, 2)), x[..., 1].mean(axis=(1, 2))], axis=1) / 255.0
    np.savez(tmp_path / "data.npz", x=x, y=y.astype(np.float32))
    return tmp_path


def matrix_text(backends: list[str], strategies: list[str], precisions: list[str], targets: list[str],
                extra: str = "") -> str:
    return (f"models:\n  - {{name: tiny, framework: pytorch, factory: 'tiny_models:tiny', weights: tiny.pt, "
            f"python_path: ['{TESTS}']}}\n"
            f"dataset: {{npz: data.npz, split: {{train: 0.5, calibration: 0.25, test: 0.25}}}}\n"
            f"axes: {{backend: {backends}, strategy: {strategies}, precision: {precisions}, target: {targets}}}\n"
            + FAST_SETTINGS + extra)


def cli(project: Path, *args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run `bench-matrix` as a user would, in the project directory, with its own workspace."""
    return subprocess.run([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), *args],
                          cwd=project, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "COLUMNS": "200", **(env or {})})


def popen_cli(project: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "bench_matrix.cli", "--workspace", str(project / "ws"), *args],
                            cwd=project, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, **(env or {})})
