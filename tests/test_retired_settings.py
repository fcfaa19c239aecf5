"""Matrices written for the single timed loop: its settings are read for a deprecation period, each with one
warning naming what replaced it; only a value they never allowed is refused."""

from __future__ import annotations

import json

import pytest

from bench_matrix.errors import MatrixError
from bench_matrix.matrix.load import load_matrix
from bench_matrix.matrix.retired import REPLACED
from bench_matrix.matrix.schema import RETIRED
from conftest import FAST_SETTINGS, cli, onnx_matrix_text
from test_matrix import BASE

OLD = """\
settings:
  min_iterations: 200
  min_time_s: 1.5
  max_time_s: 30
  ci_rel_width: 0.2
  throughput_time_s: 0.5
  passes: 2
"""


def test_each_retired_key_warns_once_and_maps_onto_what_replaced_it(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(BASE + OLD)
    matrix = load_matrix(path)
    assert (matrix.settings.timing_budget_s, matrix.settings.ci_target) == (30, 0.1)  # ci_target is ±
    assert len(matrix.warnings) == len(REPLACED) == len(RETIRED)
    for line, key in enumerate(OLD.splitlines()[1:], start=12):
        key = key.split(":")[0].strip()
        (warning,) = [w for w in matrix.warnings if f"settings.{key}:" in w]
        assert warning.startswith(f"{path}:{line}: settings.{key}: retired with the single timed loop, "
                                  f"replaced by {REPLACED[key].by}; "), warning
    reads = {key: w.split(f"{replaced.by}; ")[1] for key, replaced in REPLACED.items()
             for w in matrix.warnings if f".{key}:" in w}
    assert reads["max_time_s"].startswith("read as timing_budget_s: 30; write that instead")
    assert reads["ci_rel_width"].startswith("read as ci_target: 0.1; write that instead")
    assert reads["passes"].startswith("its value is ignored; remove it")


def test_a_setting_given_under_its_new_name_wins(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(BASE + "settings: {timing_budget_s: 5, max_time_s: 30}\n")
    matrix = load_matrix(path)
    assert matrix.settings.timing_budget_s == 5
    assert "ignored, as the matrix sets timing_budget_s; remove it" in matrix.warnings[0]


@pytest.mark.parametrize("setting, message", [
    ("min_time_s: -1", "settings.min_time_s: must be >= 0, got -1"),
    ("max_time_s: 0", "settings.max_time_s: must be > 0, got 0"),
    ("ci_rel_width: 2", "settings.ci_rel_width: must be <= 1, got 2"),
    ("passes: 0", "settings.passes: must be >= 1, got 0"),
    ("min_iterations: 2.5", "settings.min_iterations: expected integer, got float 2.5"),
    ("throughput_time_s: .inf", "settings.throughput_time_s: expected a finite number, got float inf "
                                "(.nan and .inf are not allowed)"),
])
def test_a_value_the_retired_key_never_allowed_is_refused(tmp_path, setting, message):
    path = tmp_path / "m.yaml"
    path.write_text(BASE + f"settings: {{{setting}}}\n")
    with pytest.raises(MatrixError) as info:
        load_matrix(path)
    assert info.value.problems == [f"{path}:11: {message}"]


def test_unknown_keys_are_not_told_to_use_a_retired_one(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(BASE + "settings: {max_time: 3}\n")
    with pytest.raises(MatrixError) as info:
        load_matrix(path)
    (problem,) = info.value.problems
    assert "unknown key 'max_time'" in problem and "time_s" not in problem.split("allowed:")[1]


@pytest.mark.slow
def test_plan_and_run_of_an_old_matrix_work_and_warn_once(onnx_project):
    settings = FAST_SETTINGS.replace("timing_budget_s: 0.05", "max_time_s: 0.05, min_time_s: 1.5, passes: 1, "
                                     "ci_rel_width: 0.5")
    matrix = onnx_matrix_text(["tiny"], ["fp32"]).replace(FAST_SETTINGS, settings)
    (onnx_project / "m.yaml").write_text(matrix)
    for command in ("plan", "run"):
        done = cli(onnx_project, command, "m.yaml")
        assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
        for key in ("max_time_s", "min_time_s", "passes", "ci_rel_width"):
            assert done.stderr.count(f"m.yaml:5: settings.{key}: retired") == 1, done.stderr
    report = json.loads(cli(onnx_project, "report", "--format", "json").stdout)
    (record,) = report["records"]
    assert record["status"] == "ok" and record["metrics"]["rounds"]["target"] == 0.25
