"""What the built-in backends share: the ptq_static option check and calibration data in batches."""

from __future__ import annotations

import numpy as np

from bench_matrix.backends.base import ConvertRequest
from bench_matrix.matrix.spec import StrategySpec

CALIBRATION_BATCH = 32
DEFAULT_CALIBRATION_SAMPLES = 100


def static_options_reason(step: StrategySpec, runtime: str, methods: tuple[str, ...]) -> str | None:
    """Why the runtime cannot honour these ptq_static options, or None."""
    if step.options.get("io", "float") != "float":
        return (f"{runtime} int8 models take and return float tensors: io: int8 is not available "
                f"with this backend; remove the option or use io: float")
    method = step.options.get("method", "minmax")
    if method not in methods:
        return f"{runtime} static quantisation calibrates with {' or '.join(methods)}, not {method!r}"
    return None


def calibration_data(request: ConvertRequest, step: StrategySpec) -> np.ndarray:
    """The first `calibration_samples` calibration samples as one float32 array."""
    samples = int(step.options.get("calibration_samples", DEFAULT_CALIBRATION_SAMPLES))
    data = np.ascontiguousarray(request.calibration(samples), dtype=np.float32)
    if len(data) == 0:
        raise ValueError("ptq_static needs calibration samples but the calibration split is empty; "
                         "give the dataset a non-zero calibration fraction")
    return data


def batches(data: np.ndarray, size: int = CALIBRATION_BATCH) -> list[np.ndarray]:
    return [data[i:i + size] for i in range(0, len(data), size)]
