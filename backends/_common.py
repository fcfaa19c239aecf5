"""What the built-in backends share: the ptq_static option check and calibration data in batches."""

from __future__ import annotations

import numpy as np

from bench_matrix.plugin import ConvertRequest, Inputs, StrategySpec, count, take

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


def calibration_data(request: ConvertRequest, step: StrategySpec) -> Inputs:
    """The first `calibration_samples` calibration samples of every input (floating inputs as float32)."""
    samples = int(step.options.get("calibration_samples", DEFAULT_CALIBRATION_SAMPLES))
    data = {name: np.ascontiguousarray(a, dtype=np.float32 if np.issubdtype(a.dtype, np.floating) else a.dtype)
            for name, a in request.calibration(samples).items()}
    if count(data) == 0:
        raise ValueError("ptq_static needs calibration samples but the calibration split is empty; "
                         "give the dataset a non-zero calibration fraction")
    return data


def batches(data: Inputs, size: int = CALIBRATION_BATCH) -> list[Inputs]:
    """The samples of every input in consecutive batches of `size` (the last one may be smaller)."""
    return [take(data, slice(i, i + size)) for i in range(0, count(data), size)]
