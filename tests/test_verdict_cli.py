"""Requirements end to end with real runtimes: a run of a small matrix with requirements prints its verdict,
every report format shows the same verdicts, `report --check` gates on them, changing the requirements needs
no re-run, and bad requirement keys and values exit 2 naming the file, line and key."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from conftest import cli, onnx_matrix_text

pytestmark = pytest.mark.slow
FP32, FP16 = "tiny/onnxruntime/none/fp32/cpu", "tiny/onnxruntime/none/fp16/cpu"
REQUIRED = "requirements: {max_drop: 5%, p50_ms: 1000, objective: size}\n"


def _json(project: Path, *args: str) -> dict:
    out = cli(project, "report", "--format", "json", *args)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _verdicts(data: dict) -> dict[str, str]:
    keys = ("model", "backend", "strategy", "precision", "target")
    return {"/".join(r["cell"][k] for k in keys): r["verdict"]["status"]
            for r in data["records"] if "verdict" in r}


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tiny.onnx through ONNX Runtime at fp32 (the baseline) and fp16 (larger: its casts outweigh the tiny
    model's weights), measured once."""
    import fuzz_cases

    project = fuzz_cases.write_project(tmp_path_factory.mktemp("verdict"))
    (project / "m.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32", "fp16"], REQUIRED))
    run = cli(project, "run", "m.yaml")
    assert run.returncode == 0 and "2 ok, 0 skipped, 0 failed" in run.stdout, run.stdout + run.stderr
    assert "Verdict" in run.stdout and "onnxruntime none fp32" in run.stdout.split("Verdict")[1]  # printed
    return project


def _between(project: Path) -> float:
    """A size in MiB between the fp32 and the (larger) fp16 artifact's."""
    sizes = {r["cell"]["precision"]: r["metrics"]["size_bytes"] for r in _json(project)["records"]}
    assert sizes["fp32"] < sizes["fp16"] * 0.75
    return (sizes["fp16"] + sizes["fp32"]) / 2 / 2**20


def test_the_matrix_requirements_give_verdicts_and_a_recommendation(measured: Path) -> None:
    data = _json(measured)
    assert _verdicts(data) == {FP32: "pass", FP16: "pass"}
    required = {"max_drop": "5%", "p50_ms": 1000, "objective": "size"}
    assert data["requirements"]["tiny"] == {"from": "m.yaml", "requirements": required}
    (found,) = data["recommendations"]
    assert (found["model"], found["target"], found["objective"]) == ("tiny", "cpu", "size")
    assert (found["cell"], found["runner_up"], found["distinguishable"]) == (FP32, FP16, True)
    assert found["ratio"] > 1.3 and found["ratio_ci"] == [found["ratio"]] * 2 and found["passing"] == 2
    assert cli(measured, "report", "--check", "--format", "json").returncode == 0


def test_every_format_shows_the_same_verdicts(measured: Path, tmp_path: Path) -> None:
    limit = f"size_mib={_between(measured)}"
    data = _json(measured, "--require", limit)
    assert _verdicts(data) == {FP32: "pass", FP16: "fail"}
    (missed,) = next(r for r in data["records"] if r["cell"]["precision"] == "fp16")["verdict"]["failed"]
    assert missed["requirement"] == "size_mib" and missed["value"] > missed["limit"]
    said = re.escape(missed["text"])
    assert re.fullmatch(r"size_mib \S+ > \S+ \(\d+ % over\)", missed["text"])
    assert data["recommendations"][0]["cell"] == FP32 and data["recommendations"][0]["runner_up"] is None

    table = cli(measured, "report", "--require", limit, "--out", str(tmp_path / "pages"))
    assert table.returncode == 0, table.stderr
    verdict = table.stdout.split("Verdict")[1].split("tiny: results")[0]
    assert "and --require" in verdict and "onnxruntime none fp32" in verdict and "1 of 2" in verdict
    assert re.search(r"onnxruntime none fp16\s+│ fail: " + said, table.stdout)
    assert re.search(r"onnxruntime none fp32 \(baseline\)\s+│ pass ", table.stdout)

    page = (tmp_path / "pages" / "tiny.md").read_text()
    assert page.index("## Verdict") < page.index("## Results")
    assert f"| onnxruntime none fp16 | fail: {missed['text'].replace('>', '&gt;')} |" in page
    assert "| onnxruntime none fp32 (baseline) | pass |" in page
    index = (tmp_path / "pages" / "index.md").read_text()
    assert index.index("## Verdict") < index.index("## Models")
    assert "| tiny | cpu | onnxruntime none fp32 |" in index
    html = (tmp_path / "pages" / "report.html").read_text()
    assert html.index("<h2>Verdict</h2>") < html.index("<h2>Models</h2>")
    assert f"fail: {missed['text'].replace('>', '&gt;')}" in html and "<td>pass</td>" in html

    done = cli(measured, "report", "--require", limit, "--format", "csv", "--out", str(tmp_path / "csv"))
    assert done.returncode == 0, done.stderr
    with (tmp_path / "csv" / "results.csv").open(newline="") as handle:
        rows = {r["precision"]: r for r in csv.DictReader(handle)}
    assert (rows["fp32"]["verdict"], rows["fp16"]["verdict"]) == ("pass", "fail")
    assert rows["fp16"]["verdict_missed"] == missed["text"] and rows["fp32"]["verdict_missed"] == ""


def test_check_exits_1_when_a_model_and_target_has_no_passing_cell(measured: Path) -> None:
    between = _between(measured)
    passed = cli(measured, "report", "--check", "--format", "json", "--require", f"size_mib={between}")
    assert passed.returncode == 0 and "check passed" in passed.stderr, passed.stderr
    json.loads(passed.stdout)  # the gate's line goes to stderr: stdout stays JSON
    failed = cli(measured, "report", "--check", "--format", "json", "--require", f"size_mib={between / 4}")
    assert failed.returncode == 1, failed.stderr
    assert "check failed: no cell passes the requirements for tiny on cpu" in failed.stderr
    closest = json.loads(failed.stdout)["recommendations"][0]
    assert closest["cell"] is None
    assert [c["cell"] for c in closest["closest"]] == [FP32, FP16]  # the smaller miss first
    table = cli(measured, "report", "--require", f"size_mib={between / 4}", "--format", "md", "--out",
                str(measured / "md"))
    assert table.returncode == 0, table.stderr
    index = (measured / "md" / "index.md").read_text()
    assert "no cell passes; closest: onnxruntime none fp32 (fail: size_mib" in index


def test_changing_the_requirements_needs_no_rerun(measured: Path, tmp_path: Path) -> None:
    text = (measured / "m.yaml").read_text()
    try:
        # an untimed bound: a timed one this far off can still straddle on 2 rounds of a loaded machine
        (measured / "m.yaml").write_text(text.replace("p50_ms: 1000", "size_mib: 0.000001"))
        assert _verdicts(_json(measured)) == {FP32: "fail", FP16: "fail"}
        assert cli(measured, "report", "--check", "--format", "json").returncode == 1
        (measured / "m.yaml").rename(measured / "moved.yaml")  # gone: the run's copy of its requirements
        data = _json(measured)
        assert _verdicts(data) == {FP32: "pass", FP16: "pass"}
        assert "the run's copy" in data["requirements"]["tiny"]["from"]
        assert _verdicts(_json(measured, "--matrix", "moved.yaml")) == {FP32: "fail", FP16: "fail"}
    finally:
        (measured / "moved.yaml").unlink(missing_ok=True)
        (measured / "m.yaml").write_text(text)


def test_without_requirements_there_is_no_verdict_and_check_is_a_mistake(measured: Path) -> None:
    (measured / "plain.yaml").write_text(onnx_matrix_text(["tiny"], ["fp32"]))
    run = cli(measured, "run", "plain.yaml", "--results", "plain.sqlite")
    assert run.returncode == 0, run.stdout + run.stderr
    data = _json(measured, "--results", "plain.sqlite")
    assert data["recommendations"] == [] and not _verdicts(data)
    out = cli(measured, "report", "--results", "plain.sqlite", "--check", "--format", "json")
    assert out.returncode == 2 and "no model has requirements to check" in out.stderr, out.stderr
    tried = _json(measured, "--results", "plain.sqlite", "--require", "p50_ms=1000")
    assert _verdicts(tried) == {FP32: "pass"}


@pytest.mark.parametrize(("requirements", "line", "expected"), [
    ("requirements:\n  p50: 5\n", 2, "requirements.p50: unknown key 'p50'; allowed: "),
    ("requirements:\n  max_drop: lots\n", 2, "requirements.max_drop: give the largest loss"),
    ("requirements:\n  top1: {min: 2, max: 1}\n", 2, "requirements.top1: min 2 is above max 1"),
    ("requirements:\n  objective: fast\n", 2,
     "requirements.objective: 'fast' is not allowed; allowed: p50, p99, size, throughput"),
    ("requirements:\n  closed_loop: {completed_pct: 100}\n", 2,
     "requirements.closed_loop: this matrix has no 'closed_loop' section"),
])
def test_bad_requirements_exit_2_naming_file_line_and_key(measured: Path, requirements: str, line: int,
                                                         expected: str) -> None:
    text = onnx_matrix_text(["tiny"], ["fp32"])
    (measured / "bad.yaml").write_text(text + requirements)
    first = text.count("\n") + line
    for args in (("plan", "bad.yaml"), ("report", "--matrix", "bad.yaml")):
        out = cli(measured, *args)
        assert out.returncode == 2, out.stdout + out.stderr
        assert f"bad.yaml:{first}: {expected}" in out.stderr, out.stderr
    if "unknown key" in expected:
        assert "did you mean 'p50_ms'?" in out.stderr


def test_bad_require_options_exit_2_before_anything_runs(measured: Path) -> None:
    out = cli(measured, "run", "m.yaml", "--force", "--require", "p50=5")
    assert out.returncode == 2 and "--require p50: unknown key 'p50'" in out.stderr, out.stderr
    assert "did you mean 'p50_ms'?" in out.stderr and "ok," not in out.stdout
    out = cli(measured, "report", "--require", "max_drop=5 percent")
    assert out.returncode == 2 and "--require max_drop: give the largest loss" in out.stderr, out.stderr
