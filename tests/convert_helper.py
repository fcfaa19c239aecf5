"""Test helper: run one backend's convert as the runner would, on calibration data the test chooses."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.backend import Backend, ConvertRequest
from bench_matrix.strategy import StrategySpec
from bench_matrix.sources import SourceModel
from bench_matrix.tensors import Inputs, take


def convert_with(calibration: np.ndarray | Inputs, backend: Backend, source: SourceModel, out: Path,
                 kind: str = "none", precision: str = "fp32", target: str = "cpu", shared_dir: Path | None = None,
                 max_batch: int = 1, **options: Any) -> dict[str, Any]:
    """Convert into `out` with strategy `kind` and `options` (an array: the calibration data of a single-input
    model); the returned meta must be JSON, as the runner stores it."""
    out.mkdir(parents=True, exist_ok=True)
    meta = backend.convert(request_for(calibration, source, out, kind, precision, target, shared_dir, max_batch,
                                       **options))
    json.dumps(meta)
    return meta


def request_for(calibration: np.ndarray | Inputs, source: SourceModel, out: Path, kind: str = "none",
                precision: str = "fp32", target: str = "cpu", shared_dir: Path | None = None, max_batch: int = 1,
                **options: Any) -> ConvertRequest:
    """The ConvertRequest the runner would make: the step resolved, calibration of every input."""
    data = feed(source, calibration)
    return ConvertRequest(source=source, step=StrategySpec(kind, kind, options), precision=precision,
                          target=target, out_dir=out, calibration=lambda n: take(data, slice(0, n)), threads=1,
                          seed=0, shared_dir=shared_dir, max_batch=max_batch)


def feed(source: SourceModel, data: np.ndarray | Inputs) -> Inputs:
    """`data` as the source's inputs: an array is the one input of a single-input model."""
    return dict(data) if isinstance(data, dict) else {source.inputs[0].name: data}
