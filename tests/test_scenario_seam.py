"""The scenario seam: generic modules never name a scenario or the driving workload; they reach scenarios
through bench_matrix.scenarios only."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "bench_matrix"
MATRIX_CORE = ["matrix/schema.py", "matrix/extended.py", "matrix/spec.py", "matrix/load.py",  # hold the built-in
               "matrix/requirements.py", "matrix/require.py"]  # dataset's keys
GENERIC = ["runner.py", "run.py", "remeasure.py", "plan.py", "cell.py", "jobs/__init__.py", "jobs/measure.py",
           "plan_view.py", "scenarios/base.py", "scenarios/latency.py", "verdict.py", "ranking.py", "registry.py",
           *(str(p.relative_to(ROOT)) for p in sorted(ROOT.glob("executors/*.py"))),
           *(str(p.relative_to(ROOT)) for p in sorted(ROOT.glob("store*.py"))),
           "report/__init__.py",
           *(f"report/render/{name}.py" for name in ("html", "markdown", "terminal", "plots", "sections",
                                                     "verdict_view", "pareto_marks", "pareto_layout")),
           *(f"report/analysis/{name}.py" for name in ("recommend", "judging", "pareto"))]
SCENARIO = ("closed_loop", "closed loop", "closedloop", " laps", "simulator")
WORKLOAD = ("driving", "circuit")


@pytest.mark.parametrize("module", GENERIC + MATRIX_CORE)
def test_generic_module_names_no_scenario(module: str) -> None:
    text = (ROOT / module).read_text().lower()
    names = SCENARIO + (() if module in MATRIX_CORE else WORKLOAD)
    found = [name for name in names if name in text]
    assert not found, f"{module} names {found}: scenario-specific code belongs in bench_matrix/scenarios"


def test_scenarios_keep_their_matrix_sections_and_fields() -> None:
    from bench_matrix.matrix.extended import matrix_schema
    from bench_matrix.matrix.schema import SCHEMA
    from bench_matrix.registry import scenarios

    for scenario in scenarios():
        assert scenario.name not in SCHEMA["properties"]
        assert matrix_schema()["properties"][scenario.name] == scenario.schema
