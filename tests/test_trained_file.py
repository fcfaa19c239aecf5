"""A trained built-in model's file is the same bytes wherever and by whichever process it was written."""

from __future__ import annotations

import zipfile

import numpy as np

from bench_matrix.matrix.spec import TrainingSpec
from bench_matrix.workload.pilotnet_torch import FACTORIES
from bench_matrix.workload.train import train_torch


def test_a_trained_torch_model_names_no_temporary_file_inside(tmp_path):
    """torch names a saved archive's entries after the path's stem: the partial file's pid and serial were
    in every entry, so the same model's size and bytes changed from run to run."""
    rng = np.random.default_rng(0)
    inputs, y = {"x": rng.random((4, 3, 66, 200), dtype=np.float32)}, rng.random((4, 2), dtype=np.float32)
    files = [tmp_path / "partial-123-0-model.pt", tmp_path / "partial-98765-7-model.pt"]
    for out in files:
        train_torch(FACTORIES["pilotnet"], inputs, y, TrainingSpec(epochs=1, batch_size=4), 0, out, 1)
    names = zipfile.ZipFile(files[0]).namelist()
    assert not any("partial" in name for name in names) and files[0].read_bytes() == files[1].read_bytes()
