"""Metric plugins: users' own task metrics, found through the `bench_matrix.metrics` entry-point group."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from bench_matrix.measurement import TASKS
from bench_matrix.registry import Group, PluginError

__all__ = ["METRICS", "Metric", "MetricPluginError", "load_metric", "metric_names", "plugin_metrics"]


class MetricPluginError(PluginError):
    """A metric plugin could not be loaded, does not fit the task, or failed computing its figures."""


class Metric:
    """A metric plugin: `compute` returns figures named in `directions`; they are stored as "NAME.FIGURE"."""

    name: str = ""
    tasks: tuple[str, ...] = TASKS  # the tasks it can score
    directions: dict[str, str] = {}  # figure -> "higher" or "lower" (which is better)

    def compute(self, outputs: list[np.ndarray], labels: np.ndarray | None,
                reference: list[np.ndarray] | None) -> dict[str, float]:
        """Figures of the test outputs (float64, batch axis first) against the labels and the baseline's."""
        raise NotImplementedError


METRICS = Group("bench_matrix.metrics", "metric plugin", Metric, MetricPluginError)


def metric_names() -> list[str]:
    """Names of the installed metric plugins, sorted."""
    return METRICS.names()


def load_metric(name: str) -> Metric:
    """Import, instantiate and check one registered metric plugin."""
    metric = METRICS.load(name)
    problem = _declaration_problem(metric, name)
    if problem:
        raise MetricPluginError(f"metric plugin {name!r} ({METRICS.entry(name).value}) {problem}")
    return metric


def _declaration_problem(metric: Metric, name: str) -> str | None:
    if metric.name != name:
        return f"calls itself {metric.name!r}; its `name` must be the entry-point name"
    unknown = [t for t in metric.tasks if t not in TASKS]
    if not metric.tasks or unknown:
        return f"declares tasks {list(metric.tasks)}; each must be one of: {', '.join(TASKS)}"
    wrong = {k: v for k, v in metric.directions.items() if v not in ("higher", "lower")}
    if not metric.directions or wrong:
        return f"declares directions {metric.directions}; give each figure \"higher\" or \"lower\""
    return None


def plugin_metrics(names: Sequence[str], task: str, outputs: list[np.ndarray], labels: np.ndarray | None,
                   reference: list[np.ndarray] | None) -> dict[str, float]:
    """Every named plugin's figures as {"NAME.FIGURE": value}; MetricPluginError naming a failing plugin."""
    figures: dict[str, float] = {}
    for name in names:
        metric = load_metric(name)
        if task not in metric.tasks:
            raise MetricPluginError(f"metric plugin {name!r} scores tasks {', '.join(metric.tasks)}, "
                                    f"not {task!r}")
        try:
            computed = metric.compute(outputs, labels, reference)
        except Exception as exc:
            raise MetricPluginError(f"metric plugin {name!r} failed: {type(exc).__name__}: {exc}") from exc
        figures.update(_checked_figures(name, metric, computed))
    return figures


def _checked_figures(name: str, metric: Metric, computed: object) -> dict[str, float]:
    if not isinstance(computed, dict):
        raise MetricPluginError(f"metric plugin {name!r} returned {type(computed).__name__}, "
                                "not a dict of figures")
    out = {}
    for figure, value in computed.items():
        if figure not in metric.directions:
            raise MetricPluginError(f"metric plugin {name!r} returned {figure!r}, which its `directions` "
                                    f"does not declare (declared: {', '.join(metric.directions)})")
        if not _finite_number(value):
            raise MetricPluginError(f"metric plugin {name!r} returned {figure}={value!r}: "
                                    "not a finite number")
        out[f"{name}.{figure}"] = float(value)
    return out


def _finite_number(value: object) -> bool:
    real = isinstance(value, int | float | np.number) and not isinstance(value, bool)
    return real and math.isfinite(value)  # type: ignore[arg-type]
