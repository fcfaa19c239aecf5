"""The scenario seam: generic modules never name a scenario or the driving workload; they reach scenarios
through bench_matrix.scenarios only (the core ones, latency among them, through base.CORE)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "bench_matrix"
MATRIX_CORE = ["matrix/schema.py", "matrix/extended.py", "matrix/spec.py", "matrix/load.py",  # hold the built-in
               "matrix/requirements.py", "matrix/require.py"]  # dataset's keys
GENERIC = ["runner.py", "run.py", "remeasure.py", "plan.py", "cell.py", "jobs/__init__.py", "jobs/measure.py",
           "plan_view.py", "scenarios/base.py", "scenarios/latency.py", "verdict.py", "ranking.py",
           "registry.py",
           *(str(p.relative_to(ROOT)) for p in sorted(ROOT.glob("executors/*.py"))),
           *(str(p.relative_to(ROOT)) for p in sorted(ROOT.glob("store*.py"))),
           "report/__init__.py",
           *(f"report/render/{name}.py" for name in ("html", "markdown", "terminal", "plots", "sections",
                                                     "verdict_view", "pareto_marks", "pareto_layout")),
           *(f"report/analysis/{name}.py" for name in ("recommend", "judging", "pareto"))]
SCENARIO = ("closed_loop", "closed loop", "closedloop", " laps", "simulator")
CORE = ("scenarios.latency", "scenarios import latency")  # named by scenarios/base.py's CORE only
WORKLOAD = ("driving", "circuit")


@pytest.mark.parametrize("module", GENERIC + MATRIX_CORE)
def test_generic_module_names_no_scenario(module: str) -> None:
    text = (ROOT / module).read_text().lower()
    names = SCENARIO + (() if module in MATRIX_CORE else WORKLOAD)
    found = [name for name in names if name in text]
    assert not found, f"{module} names {found}: scenario-specific code belongs in bench_matrix/scenarios"


@pytest.mark.parametrize("module", [m for m in GENERIC if not m.startswith("scenarios/")])
def test_generic_module_reaches_core_scenarios_through_the_seam(module: str) -> None:
    text = (ROOT / module).read_text()
    assert not [name for name in CORE if name in text], f"{module} names the latency scenario's module"


def test_core_scenarios_are_scenarios() -> None:
    from bench_matrix.named import resolve
    from bench_matrix.scenarios.base import CORE, Scenario

    assert all(issubclass(resolve(name), Scenario) for name in CORE)


def test_scenarios_keep_their_matrix_sections_and_fields() -> None:
    from bench_matrix.matrix.extended import matrix_schema
    from bench_matrix.matrix.schema import SCHEMA
    from bench_matrix.registry import scenarios

    for scenario in scenarios():
        assert scenario.name not in SCHEMA["properties"]
        assert matrix_schema()["properties"][scenario.name] == scenario.schema
