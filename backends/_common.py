"""What every built-in backend shares: the conversion step of a strategy, calibration batches, versions."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

import numpy as np

from bench_matrix.backends.base import ConvertRequest
from bench_matrix.matrix.schema import STRATEGY_KINDS
from bench_matrix.matrix.spec import StrategySpec

CALIBRATION_BATCH = 32
DEFAULT_CALIBRATION_SAMPLES = 100


def installed_versions(*distributions: str) -> dict[str, str]:
    """Versions of the installed distributions among `distributions`, read without importing them."""
    found = {}
    for name in distributions:
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            continue
    return found


def conversion_step(strategy: StrategySpec) -> StrategySpec:
    """The strategy's single conversion-stage step (kind 'none' when it has none, e.g. after training steps)."""
    steps = [s for s in _leaves(strategy)
             if s.kind != "none" and STRATEGY_KINDS.get(s.kind or "", {}).get("stage") == "conversion"]
    if len(steps) > 1:
        raise ValueError(f"strategy {strategy.name!r} combines several conversion steps "
                         f"({', '.join(str(s.kind) for s in steps)}); a backend applies at most one")
    return steps[0] if steps else StrategySpec(name="none", kind="none")


def _leaves(spec: StrategySpec) -> list[StrategySpec]:
    return [leaf for step in spec.steps for leaf in _leaves(step)] if spec.steps else [spec]


def check_static_options(step: StrategySpec, runtime: str, methods: tuple[str, ...]) -> None:
    """Reject ptq_static options the runtime cannot honour, before any work is done."""
    if step.options.get("io", "float") != "float":
        raise ValueError(f"{runtime} int8 models take and return float tensors: io: int8 is not available "
                         f"with this backend; remove the option or use io: float")
    method = step.options.get("method", "minmax")
    if method not in methods:
        raise ValueError(f"{runtime} static quantisation calibrates with {' or '.join(methods)}, "
                         f"not {method!r}; set method to one of those")


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
