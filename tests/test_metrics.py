"""Task metrics on hand-made arrays with values computed by hand, the NaN/Inf reason, and metric plugins."""

from __future__ import annotations

import math
from importlib.metadata import EntryPoint

import numpy as np
import pytest

from bench_matrix import registry
from bench_matrix.measure import metric_plugins
from bench_matrix.measure.metric_plugins import Metric, MetricPluginError, load_metric, metric_names
from bench_matrix.measure.metrics import DIRECTIONS, HEADLINE, SNR_LIMIT_DB, evaluate, non_finite_reason

LABELS = np.array([[0.0, 1.0], [1.0, 0.0]])
PRED = np.array([[0.5, 1.0], [1.0, -1.0]], dtype=np.float32)
REF = np.array([[0.5, 1.0], [1.0, -0.5]])
# 3 samples, 6 classes; the true class of each: 2, 1, 5
LOGITS = np.array([[3.0, 1.0, 2.0, 0.0, 0.0, 0.0],   # true class 2 ranked 2nd: top-5 only
                   [0.0, 5.0, 1.0, 0.0, 0.0, 0.0],   # true class 1 first: top-1
                   [6.0, 5.0, 4.0, 3.0, 2.0, 1.0]],  # true class 5 ranked 6th: neither
                  dtype=np.float32)
CLASSES = np.array([2, 1, 5])


def test_regression_keeps_todays_figures_and_adds_fidelity():
    out = evaluate("regression", [PRED], LABELS, [REF])
    assert out["mse"] == pytest.approx((0.25 + 0 + 0 + 1) / 4)
    assert out["mae"] == pytest.approx((0.5 + 0 + 0 + 1) / 4)
    assert out["mse_per_output"] == pytest.approx([0.125, 0.5])
    assert out["max_abs_diff_vs_baseline"] == pytest.approx(0.5)
    # sample 0 identical (cos 1); sample 1: (1 + 0.5) / (sqrt(2) * sqrt(1.25))
    assert out["cosine_similarity"] == pytest.approx((1 + 1.5 / math.sqrt(2 * 1.25)) / 2)
    assert out["snr_db"] == pytest.approx(10 * math.log10((0.25 + 1 + 1 + 0.25) / 0.25))
    assert "per_output" not in out  # one output: the record keeps its fields
    assert set(evaluate("regression", [PRED], LABELS, None)) == {"mse", "mae", "mse_per_output"}


def test_regression_with_several_outputs_matches_labels_to_the_concatenated_outputs():
    first, second = PRED[:, :1], PRED[:, 1:]
    out = evaluate("regression", [first, second], LABELS, [REF[:, :1], REF[:, 1:]])
    assert out["mse"] == pytest.approx(0.3125) and out["mse_per_output"] == pytest.approx([0.125, 0.5])
    (a, b) = out["per_output"]
    assert (a["mse"], a["mae"], b["mse"], b["mae"]) == pytest.approx((0.125, 0.25, 0.5, 0.5))
    assert a["max_abs_diff_vs_baseline"] == 0.0 and a["snr_db"] == SNR_LIMIT_DB
    assert b["max_abs_diff_vs_baseline"] == pytest.approx(0.5)
    assert b["snr_db"] == pytest.approx(10 * math.log10((1 + 0.25) / 0.25))
    with pytest.raises(ValueError, match=r"outputs have shape \(3,\) per sample but labels have \(2,\).*"
                                         r"flattened and concatenated"):
        evaluate("regression", [PRED, first], LABELS, None)


def test_classification_top1_top5_and_agreement():
    baseline = LOGITS.copy()
    baseline[0] = [0.0, 0.0, 9.0, 0.0, 0.0, 0.0]  # the baseline picks class 2 for sample 0, the cell class 0
    out = evaluate("classification", [LOGITS], CLASSES, [baseline])
    assert out["top1"] == pytest.approx(1 / 3)
    assert out["top5"] == pytest.approx(2 / 3)
    assert out["top1_agreement"] == pytest.approx(2 / 3)
    assert "top1_agreement" not in evaluate("classification", [LOGITS], CLASSES, None)


def test_classification_top_k_is_capped_by_the_number_of_classes():
    logits = np.array([[1.0, 2.0, 3.0], [3.0, 2.0, 1.0]])
    out = evaluate("classification", [logits], np.array([0, 0]), None)
    assert out["top1"] == 0.5 and out["top5"] == 1.0  # 3 classes: top-3, which every label is in


def test_classification_label_mistakes_name_the_shapes():
    with pytest.raises(ValueError, match=r"one integer class id per sample.*\(3, 6\).*one-hot"):
        evaluate("classification", [LOGITS], np.eye(6)[CLASSES], None)
    with pytest.raises(ValueError, match=r"class ids range over \[1, 6\].*6 classes \(ids 0..5\)"):
        evaluate("classification", [LOGITS], np.array([2, 1, 6]), None)
    with pytest.raises(ValueError, match="integer class ids; got float64 values such as 0.5"):
        evaluate("classification", [LOGITS], np.array([2.0, 0.5, 1.0]), None)
    with pytest.raises(ValueError, match=r"labels have shape \(2,\) but the outputs hold 3 samples"):
        evaluate("classification", [LOGITS], np.array([2, 1]), None)
    with pytest.raises(ValueError, match="needs labels; use task 'none'"):
        evaluate("classification", [LOGITS], None, None)


def test_none_task_is_fidelity_only_per_output_and_overall():
    outputs = [np.array([[3.0, 4.0], [1.0, 0.0]]), np.array([[0.0], [2.0]])]
    reference = [np.array([[3.0, 4.0], [0.0, 1.0]]), np.array([[0.0], [2.0]])]
    out = evaluate("none", outputs, None, reference)
    # overall: sample 0 identical; sample 1 (1, 0, 2)·(0, 1, 2) = 4 over 5
    assert out["cosine_similarity"] == pytest.approx((1 + 4 / 5) / 2)
    assert out["snr_db"] == pytest.approx(10 * math.log10(30 / 2))
    assert out["max_abs_diff_vs_baseline"] == 1.0
    first, second = out["per_output"]
    assert first["cosine_similarity"] == pytest.approx(0.5) and second["cosine_similarity"] == 1.0
    assert second["snr_db"] == SNR_LIMIT_DB and set(out) == {"max_abs_diff_vs_baseline", "cosine_similarity",
                                                             "snr_db", "per_output"}
    assert evaluate("none", outputs, None, None) == {}


def test_zero_vectors_and_a_zero_reference_never_give_nan():
    zeros, ones = np.zeros((2, 3)), np.ones((2, 3))
    same = evaluate("none", [zeros], None, [zeros])
    assert same["cosine_similarity"] == 1.0 and same["snr_db"] == SNR_LIMIT_DB
    off = evaluate("none", [ones], None, [zeros])
    assert off["cosine_similarity"] == 0.0 and off["snr_db"] == -SNR_LIMIT_DB


def test_shape_mismatches_name_the_shapes():
    with pytest.raises(ValueError, match=r"outputs have shapes \(2, 2\) but the fp32 baseline's outputs have "
                                         r"\(2, 3\)"):
        evaluate("none", [PRED], None, [np.zeros((2, 3))])
    with pytest.raises(ValueError, match=r"same batch axis first; shapes: \(2, 2\), \(3, 1\)"):
        evaluate("none", [PRED, np.zeros((3, 1))], None, None)
    with pytest.raises(ValueError, match="unknown task 'detection'; choose one of: regression, classif"):
        evaluate("detection", [PRED], None, None)


def test_non_finite_outputs_are_named_and_refused():
    bad = np.zeros((4, 160), np.float32)
    bad[0, :3], bad[1, 0] = np.nan, -np.inf
    assert non_finite_reason([np.ones(3), bad]) == "output 1 holds 3 NaN and 1 Inf values of 640"
    assert non_finite_reason([PRED, np.arange(4)]) is None
    with pytest.raises(ValueError, match="output 1 holds 3 NaN and 1 Inf values of 640"):
        evaluate("none", [bad[:, :2], bad], None, None)
    with pytest.raises(ValueError, match="fp32 baseline output 0 holds 1 NaN"):
        evaluate("none", [PRED], None, [np.array([[np.nan, 0.0], [0.0, 0.0]])])


def test_every_metric_has_a_direction():
    assert set(HEADLINE.values()) <= set(DIRECTIONS)
    assert (DIRECTIONS["mse"], DIRECTIONS["top1"], DIRECTIONS["snr_db"]) == ("lower", "higher", "higher")


class MeanAbsLogit(Metric):
    """A real plugin: the mean absolute first output, and its change against the baseline."""

    name = "logit_size"
    tasks = ("classification", "none")
    directions = {"mean_abs": "lower", "change": "lower"}

    def compute(self, outputs, labels, reference):
        figures = {"mean_abs": float(np.mean(np.abs(outputs[0])))}
        if reference is not None:
            figures["change"] = float(np.mean(np.abs(outputs[0] - reference[0])))
        return figures


class Broken(MeanAbsLogit):
    name = "broken"

    def compute(self, outputs, labels, reference):
        return {"mean_abs": float("nan")}


class Undeclared(MeanAbsLogit):
    name = "undeclared"

    def compute(self, outputs, labels, reference):
        return {"surprise": 1.0}


class Misnamed(MeanAbsLogit):
    name = "other"


class NotAMetric:
    name = "not_metric"


class NoDirections(MeanAbsLogit):
    name = "no_directions"
    directions = {"mean_abs": "up"}


@pytest.fixture
def installed(monkeypatch: pytest.MonkeyPatch) -> None:
    """Register this module's classes in the `bench_matrix.metrics` group, as an installed package would."""
    plugins = {"logit_size": "MeanAbsLogit", "broken": "Broken", "undeclared": "Undeclared",
               "misnamed": "Misnamed", "no_directions": "NoDirections", "missing": "NotThere",
               "plain": "DIRECTIONS", "not_metric": "NotAMetric"}
    group = metric_plugins.METRICS.name
    eps = [EntryPoint(name, f"{__name__}:{attr}", group) for name, attr in plugins.items()]
    monkeypatch.setattr(registry, "entry_points", lambda group: [ep for ep in eps if ep.group == group])


def test_plugin_figures_are_stored_under_the_plugin_name(installed: None) -> None:
    assert "logit_size" in metric_names() and "broken" in metric_names()
    out = evaluate("none", [LOGITS], None, [LOGITS - 1], plugins=["logit_size"])
    assert out["logit_size.mean_abs"] == pytest.approx(np.mean(np.abs(LOGITS)))
    assert out["logit_size.change"] == pytest.approx(1.0)
    assert out["cosine_similarity"] < 1.0  # the built-in figures stay
    assert isinstance(load_metric("logit_size"), MeanAbsLogit)


@pytest.mark.parametrize(("name", "message"), [
    ("broken", r"metric plugin 'broken' returned mean_abs=nan: not a finite number"),
    ("undeclared", r"'undeclared' returned 'surprise', which its `directions` does not declare"),
    ("misnamed", r"'misnamed' \(.*:Misnamed\) calls itself 'other'"),
    ("no_directions", r"'no_directions' .* declares directions \{'mean_abs': 'up'\}"),
    ("missing", r"'missing' \(.*:NotThere\) failed to import: AttributeError"),
    ("plain", r"'plain' .* is not a bench_matrix.measure.metric_plugins.Metric subclass"),
    ("not_metric", r"'not_metric' .* is not a bench_matrix.measure.metric_plugins.Metric subclass"),
    ("absent", r"no metric plugin named 'absent' is installed \(installed: broken, logit_size"),
])
def test_a_broken_plugin_is_named(installed: None, name: str, message: str) -> None:
    with pytest.raises(MetricPluginError, match=message):
        evaluate("none", [LOGITS], None, [LOGITS], plugins=[name])


def test_a_plugin_refuses_a_task_it_does_not_declare(installed: None) -> None:
    with pytest.raises(MetricPluginError, match="'logit_size' scores tasks classification, none, not 'regr"):
        evaluate("regression", [PRED], LABELS, None, plugins=["logit_size"])
