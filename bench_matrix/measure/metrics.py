"""Task metrics of a cell's test outputs: against the labels (regression, classification) and against the fp32
baseline's outputs (every task). Pure numpy; docs/metrics.md defines every figure."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from bench_matrix.measurement import TASKS

# snr_db is clipped to ±this; +300 means identical (float32 rounding alone stays far below it)
SNR_LIMIT_DB = 300.0
TOP_K = 5
# Whether a larger value of each accuracy metric is better ("higher") or worse ("lower").
DIRECTIONS = {"mse": "lower", "mae": "lower", "mse_per_output": "lower", "max_abs_diff_vs_baseline": "lower",
              "cosine_similarity": "higher", "snr_db": "higher", "top1": "higher", "top5": "higher",
              "top1_agreement": "higher"}
# The one metric that sums up each task's accuracy (the report's Δ column and overview).
HEADLINE = {"regression": "mse", "classification": "top1", "none": "cosine_similarity"}

__all__ = ["DIRECTIONS", "HEADLINE", "SNR_LIMIT_DB", "TASKS", "evaluate", "non_finite_reason"]


def evaluate(task: str, outputs: Sequence[np.ndarray], labels: np.ndarray | None,
             reference: Sequence[np.ndarray] | None, plugins: Sequence[str] = ()) -> dict[str, Any]:
    """The task's metrics of `outputs` (every output of the model, batch axis first) against `labels` and,
    when given, fidelity against the fp32 baseline's `reference` outputs; plus each named metric plugin's."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of: {', '.join(TASKS)}")
    outs = _checked(outputs, "output")
    refs = None if reference is None else _checked(reference, "fp32 baseline output")
    if refs is not None:
        _same_shapes(outs, refs)
    result: dict[str, Any] = {}
    if task == "regression":
        result.update(regression(outs, _labels(labels, task, len(outs[0]))))
    elif task == "classification":
        result.update(classification(outs, _labels(labels, task, len(outs[0])), refs))
    if refs is not None:
        _merge(result, fidelity(outs, refs))
    if plugins:
        from bench_matrix.measure.metric_plugins import plugin_metrics
        result.update(plugin_metrics(plugins, task, outs, labels, refs))
    return result


def non_finite_reason(outputs: Sequence[np.ndarray], what: str = "output") -> str | None:
    """Why the outputs are not a result ("output 0 holds 3 NaN and 1 Inf values of 640"); None if finite."""
    problems = []
    for index, array in enumerate(outputs):
        values = np.asarray(array)
        if not np.issubdtype(values.dtype, np.inexact):
            continue
        nan, inf = int(np.isnan(values).sum()), int(np.isinf(values).sum())
        if nan or inf:
            problems.append(f"{what} {index} holds {nan} NaN and {inf} Inf values of {values.size}")
    return "; ".join(problems) or None


def regression(outputs: list[np.ndarray], labels: np.ndarray) -> dict[str, Any]:
    """mse, mae and mse_per_output against (N, K) labels matched to the outputs flattened and concatenated;
    with several outputs, each output's mse and mae (over its own label columns) under `per_output`."""
    pred = _flat(outputs)
    labels = np.asarray(labels, np.float64).reshape(len(labels), -1)
    if pred.shape != labels.shape:
        raise ValueError(f"model outputs have shape {pred.shape[1:]} per sample but labels have "
                         f"{labels.shape[1:]}" + _shapes_note(outputs))
    err = pred - labels
    out: dict[str, Any] = {"mse": float(np.mean(err ** 2)), "mae": float(np.mean(np.abs(err))),
                           "mse_per_output": [float(v) for v in np.mean(err ** 2, axis=0)]}
    if len(outputs) > 1:
        out["per_output"] = [{"mse": float(np.mean(part ** 2)), "mae": float(np.mean(np.abs(part)))}
                             for part in _split(err, outputs)]
    return out


def classification(outputs: list[np.ndarray], labels: np.ndarray, reference: list[np.ndarray] | None
                   ) -> dict[str, Any]:
    """top1 and top5 (k = min(5, classes)) of the first output's logits against integer class ids, and
    top1_agreement (the argmax equals the fp32 baseline's) when `reference` is given."""
    logits = np.asarray(outputs[0], np.float64).reshape(len(outputs[0]), -1)
    ids = _class_ids(labels, logits.shape[1])
    own = logits[np.arange(len(ids)), ids]
    beaten_by = np.sum(logits > own[:, None], axis=1)  # classes scored strictly higher than the true one
    out: dict[str, Any] = {"top1": float(np.mean(np.argmax(logits, axis=1) == ids)),
                           "top5": float(np.mean(beaten_by < min(TOP_K, logits.shape[1])))}
    if reference is not None:
        base = np.asarray(reference[0], np.float64).reshape(logits.shape)
        out["top1_agreement"] = float(np.mean(np.argmax(logits, axis=1) == np.argmax(base, axis=1)))
    return out


def fidelity(outputs: list[np.ndarray], reference: list[np.ndarray]) -> dict[str, Any]:
    """max_abs_diff_vs_baseline, cosine_similarity and snr_db over all outputs together; with several outputs,
    the same three for each output under `per_output`."""
    out: dict[str, Any] = _fidelity(_flat(outputs), _flat(reference))
    if len(outputs) > 1:
        pairs = zip(outputs, reference, strict=True)
        out["per_output"] = [_fidelity(_flat([o]), _flat([r])) for o, r in pairs]
    return out


def _fidelity(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {"max_abs_diff_vs_baseline": float(np.max(np.abs(pred - ref))) if pred.size else 0.0,
            "cosine_similarity": cosine_similarity(pred, ref), "snr_db": snr_db(pred, ref)}


def cosine_similarity(pred: np.ndarray, ref: np.ndarray) -> float:
    """Mean over samples of the cosine between each sample's flattened outputs and the reference's; a sample
    whose two vectors are both zero counts 1, one zero vector against a non-zero one counts 0."""
    dot = np.sum(pred * ref, axis=1)
    norms = np.linalg.norm(pred, axis=1) * np.linalg.norm(ref, axis=1)
    both_zero = ~pred.any(axis=1) & ~ref.any(axis=1)
    cos = np.where(norms > 0, dot / np.where(norms > 0, norms, 1.0), np.where(both_zero, 1.0, 0.0))
    return float(np.mean(np.clip(cos, -1.0, 1.0))) if len(cos) else 1.0


def snr_db(pred: np.ndarray, ref: np.ndarray) -> float:
    """10·log10(Σref² / Σ(pred − ref)²) in dB, clipped to ±SNR_LIMIT_DB (identical outputs: +SNR_LIMIT_DB)."""
    noise = float(np.sum((pred - ref) ** 2))
    signal = float(np.sum(ref ** 2))
    if noise == 0.0:
        return SNR_LIMIT_DB
    if signal == 0.0:
        return -SNR_LIMIT_DB
    return float(np.clip(10.0 * np.log10(signal / noise), -SNR_LIMIT_DB, SNR_LIMIT_DB))


def _merge(result: dict[str, Any], more: dict[str, Any]) -> None:
    """Add `more` to `result`, joining their `per_output` lists output by output."""
    mine, theirs = result.get("per_output"), more.get("per_output")
    result.update(more)
    if mine and theirs:
        result["per_output"] = [{**a, **b} for a, b in zip(mine, theirs, strict=True)]


def _checked(arrays: Sequence[np.ndarray], what: str) -> list[np.ndarray]:
    """The arrays as float64, each with the same batch size and finite; ValueError naming the problem."""
    if not arrays:
        raise ValueError(f"no {what}s to evaluate")
    out = [np.asarray(a, np.float64) for a in arrays]
    if any(a.ndim == 0 for a in out) or len({len(a) for a in out}) > 1:
        raise ValueError(f"every {what} needs the same batch axis first; shapes: {_shapes(out)}")
    reason = non_finite_reason(out, what)
    if reason:
        raise ValueError(reason)
    return out


def _same_shapes(outputs: list[np.ndarray], reference: list[np.ndarray]) -> None:
    if [a.shape for a in outputs] != [r.shape for r in reference]:
        raise ValueError(f"outputs have shapes {_shapes(outputs)} but the fp32 baseline's outputs have "
                         f"{_shapes(reference)}")


def _labels(labels: np.ndarray | None, task: str, samples: int) -> np.ndarray:
    if labels is None:
        raise ValueError(f"task {task!r} needs labels; use task 'none' for data without labels")
    labels = np.asarray(labels)
    if labels.ndim == 0 or len(labels) != samples:
        raise ValueError(f"labels have shape {labels.shape} but the outputs hold {samples} samples")
    return labels


def _class_ids(labels: np.ndarray, classes: int) -> np.ndarray:
    """(N,) or (N, 1) integer class ids in [0, classes) as int64; ValueError naming what is wrong."""
    ids = labels.reshape(len(labels), -1)
    if ids.shape[1] != 1:
        raise ValueError(f"classification needs one integer class id per sample, labels shape (N,); got "
                         f"labels of shape {labels.shape} (one-hot labels: take their argmax)")
    ids = ids[:, 0]
    if not (np.issubdtype(ids.dtype, np.integer) or np.all(np.mod(ids, 1) == 0)):
        raise ValueError(f"classification labels must be integer class ids; got {ids.dtype} values such as "
                         f"{ids[np.mod(ids, 1) != 0][0]}")
    ids = ids.astype(np.int64)
    if len(ids) and (ids.min() < 0 or ids.max() >= classes):
        raise ValueError(f"class ids range over [{ids.min()}, {ids.max()}] but the first output has logits "
                         f"for {classes} classes (ids 0..{classes - 1})")
    return ids


def _flat(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """(N, total) float64: each array flattened per sample, concatenated in output order."""
    return np.concatenate([np.asarray(a, np.float64).reshape(len(a), -1) for a in arrays], axis=1)


def _split(flat: np.ndarray, outputs: list[np.ndarray]) -> list[np.ndarray]:
    widths = np.cumsum([int(np.prod(a.shape[1:])) for a in outputs])[:-1]
    return np.split(flat, widths, axis=1)


def _shapes(arrays: Sequence[np.ndarray]) -> str:
    return ", ".join(str(tuple(a.shape)) for a in arrays)


def _shapes_note(outputs: list[np.ndarray]) -> str:
    if len(outputs) == 1:
        return ""
    return f" (the {len(outputs)} outputs {_shapes(outputs)} flattened and concatenated)"
