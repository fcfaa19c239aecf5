"""Test helper: run one backend's convert as the runner would, on calibration data the test chooses."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from bench_matrix.backends.base import Backend, ConvertRequest
from bench_matrix.matrix.spec import StrategySpec
from bench_matrix.sources import SourceModel


def convert_with(calibration: np.ndarray, backend: Backend, source: SourceModel, out: Path, kind: str = "none",
                 precision: str = "fp32", target: str = "cpu", shared_dir: Path | None = None,
                 **options: Any) -> dict[str, Any]:
    """Convert into `out` with strategy `kind` and `options`; the returned meta must be JSON, as the runner stores it."""
    out.mkdir(parents=True, exist_ok=True)
    request = ConvertRequest(source=source, strategy=StrategySpec(kind, kind, options), precision=precision,
                             target=target, out_dir=out, calibration=lambda n: calibration[:n], threads=1, seed=0,
                             shared_dir=shared_dir)
    meta = backend.convert(request)
    json.dumps(meta)
    return meta
